"""Redraw every published figure and summary table from the stored tables and libraries (``make figures``).

Reads only ``results/tables/*`` and ``results/libraries/*`` (the project's ``results/``: ``$LFD_ROOT/results`` when
``LFD_ROOT`` is set, else the checkout's) and never fits a model: the figures are drawn by the experiments' own
plotting functions, on the stored segmentations, skill libraries and rollout paths, and the engine rollouts that
the skill figures show are recomputed from the stored libraries with the same seeded starts and pushes.

* ``segment_lasa``: ``segment_lasa_<set>.png`` (paper Figs 2, 6) from ``libraries/segment_lasa/<set>/``, and
  ``segment_lasa_map_<set>.png`` (``selection="map", position_weight=None``) from
  ``libraries/segment_lasa_map/<set>/`` where stored;
* ``lasa_tasks``: per shape ``lasa_tasks_<shape>_{entropy,steps,modulation,pushes}.png`` and ``_tree.{txt,dot}``
  (Figs 3, 5-8) from ``libraries/lasa_tasks/`` and the summary ``tables/lasa_tasks.md``;
* ``lasa_benchmark``: for every ``tables/lasa_benchmark*.parquet`` the Fig. 9 violins
  ``figures/<name>_violins.png`` and the summary ``tables/<name>_summary.{md,csv}`` (mean and std per method,
  train and test);
* ``mnist``: ``mnist_strokes.png``, ``mnist_rollouts.png`` (Figs 10, 11) from ``libraries/mnist/digit_<d>.pt``
  and ``tables/mnist.md``;
* ``scooping``: ``scooping_{segmentation,starts,disturbed}.png`` (Figs 13-15) and the MuJoCo frame
  ``scooping_frame.png`` from ``libraries/scooping/`` (the frame is skipped, with a message, where MuJoCo cannot
  render offscreen), and ``tables/scooping.md`` from ``tables/scooping.parquet`` and the stored wall times.

A missing or damaged stored file raises :class:`~lfd_torch.errors.StoreError` naming it (``make results`` writes
them all). At the end, every file of ``results/figures`` that this run did not rewrite is listed (exit status 1),
except those this machine cannot draw (listed apart).

    python experiments/figures.py                      # everything (make figures)
    python experiments/figures.py --only lasa_benchmark mnist
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
import torch  # noqa: E402

torch.set_num_threads(1)  # the busy-waiting default pool is ~10x slower on a loaded 2-core box
sys.path.insert(0, str(Path(__file__).resolve().parent))

import pandas as pd  # noqa: E402

from lfd_torch.errors import StoreError  # noqa: E402
from lfd_torch.segmentation import Segmentation  # noqa: E402
from lfd_torch.store import PROVENANCE_COLUMNS, atomic_write, read_table  # noqa: E402
from lfd_torch.viz.stored import load_config, load_demos, results_dir  # noqa: E402

#: Prefixes of figures other commands write into results/figures (not redrawn here): none, every figure is redrawn.
OTHER_FIGURES: tuple[str, ...] = ()

#: ``report(path)``: a file was written; ``report(path, skipped=why)``: it cannot be drawn on this machine.
Report = Callable[..., None]


def _table(results: Path, name: str) -> pd.DataFrame:
    return read_table(results / "tables" / f"{name}.parquet")


def _markdown(frame: pd.DataFrame, path: Path, floatfmt: str) -> Path:
    md = frame.to_markdown(index=False, floatfmt=floatfmt)
    return atomic_write(path, lambda p: p.write_text(md + "\n"))


def segment_lasa_figures(results: Path, report: Callable[[Path], None]) -> None:
    """``segment_lasa_<set>.png`` for every data set of ``tables/segment_lasa.parquet``, and its markdown; the same
    for ``tables/segment_lasa_map.parquet`` (the ``selection="map"`` run) where it exists."""
    import segment_lasa

    for experiment in ("segment_lasa", "segment_lasa_map"):
        if experiment != "segment_lasa" and not (results / "tables" / f"{experiment}.parquet").exists():
            continue
        table = _table(results, experiment)
        for name in pd.unique(table["shape"]):
            where = results / "libraries" / experiment / str(name)
            seg = Segmentation.load(where / "segmentation.pt")
            demos, _ = load_demos(where / "demos.pt")
            report(segment_lasa.draw(str(name), seg, demos, results / "figures" / f"{experiment}_{name}.png"))
        shown = table.drop(columns=["experiment", "method", "fold", *(c for c in PROVENANCE_COLUMNS if c != "seed")],
                           errors="ignore")  # fmt: skip
        report(_markdown(shown, results / "tables" / f"{experiment}.md", ".4g"))


def lasa_tasks_figures(results: Path, report: Callable[[Path], None]) -> None:
    """Figs 3, 5-8 of every shape of ``tables/lasa_tasks.parquet``, and the summary markdown."""
    import lasa_tasks

    libraries = results / "libraries"
    cfg = load_config(libraries / "lasa_tasks" / "config.json")
    table = _table(results, "lasa_tasks")
    for shape in pd.unique(table["shape"]):
        tasks, fig6 = lasa_tasks.replay(cfg, str(shape), libraries)
        for path in lasa_tasks.figures(cfg, str(shape), tasks, fig6, results / "figures"):
            report(Path(path))
    report(_markdown(lasa_tasks.summary(table), results / "tables" / "lasa_tasks.md", ".3g"))


def lasa_benchmark_figures(results: Path, report: Callable[[Path], None]) -> None:
    """Violins and summary of every stored ``lasa_benchmark*`` table."""
    import lasa_benchmark

    names = sorted(p.name[: -len(".parquet")] for p in (results / "tables").glob("lasa_benchmark*.parquet"))
    if not names:
        raise StoreError(f"no lasa_benchmark*.parquet in {results / 'tables'} (run make results)")
    for name in names:
        table = _table(results, name)
        for path in lasa_benchmark.write_violins(table, results / "figures" / f"{name}_violins.png"):
            report(path)
        for path in lasa_benchmark.write_summary(lasa_benchmark.summary(table), results / "tables", f"{name}_summary"):
            report(path)


def mnist_figures(results: Path, report: Callable[[Path], None]) -> None:
    """Figs 10-11 from ``libraries/mnist/digit_<d>.pt`` for every digit of ``tables/mnist.parquet``."""
    import mnist

    table = _table(results, "mnist")
    data = mnist.load_figure_data(results / "libraries", sorted(int(d) for d in pd.unique(table["digit"])))
    report(mnist.figure_strokes(data, results / "figures" / "mnist_strokes.png"))
    report(mnist.figure_rollouts(data, table, results / "figures" / "mnist_rollouts.png"))
    report(_markdown(mnist.summary(table), results / "tables" / "mnist.md", ".3g"))


def scooping_figures(results: Path, report: Report) -> None:
    """Figs 13-15 and the MuJoCo frame from ``libraries/scooping/``, and ``tables/scooping.md``."""
    from hydra.utils import instantiate

    import scooping

    where = results / "libraries" / "scooping"
    cfg = load_config(where / "config.json")
    name = str(cfg.experiment)
    table = _table(results, name)
    data = scooping.load_figure_data(where)
    robot = instantiate(cfg.robot, _convert_="all")  # the MuJoCo scene of the run (drawn vessels, rendered frame)
    drawn = scooping.draw_figures(data, robot, results / "figures", name, render=bool(cfg.render))
    for path in drawn:
        report(path)
    frame = results / "figures" / f"{name}_frame.png"
    if cfg.render and frame not in drawn:
        report(frame, skipped="MuJoCo offscreen rendering unavailable here")
    run = cfg.run
    timings = {str(k): float(v) for k, v in run.wall_time_s}
    md = scooping.markdown(table, cfg, int(run.n_steps), [int(s) for s in run.step_stage], timings)
    report(atomic_write(results / "tables" / f"{name}.md", lambda p: p.write_text(md)))


GROUPS: dict[str, Callable[[Path, Report], None]] = {
    "segment_lasa": segment_lasa_figures,
    "lasa_tasks": lasa_tasks_figures,
    "lasa_benchmark": lasa_benchmark_figures,
    "mnist": mnist_figures,
    "scooping": scooping_figures,
}


def stale_figures(results: Path, since: float, skipped: tuple[Path, ...] = ()) -> list[Path]:
    """Files of ``results/figures`` last written before ``since`` (time.time()), other commands' figures and the
    ``skipped`` ones (which this machine cannot draw) aside."""
    folder = results / "figures"
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(OTHER_FIGURES)
                  and p.stat().st_mtime < since and p not in skipped)  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="+", choices=sorted(GROUPS), help="redraw these groups only")
    args = ap.parse_args(argv)
    results = results_dir()
    start = time.time()
    written: list[Path] = []
    not_drawn: list[Path] = []  # figures this machine cannot draw (reported with the reason)

    def report(path: Path, skipped: str | None = None) -> None:
        try:
            shown = Path(path).resolve().relative_to(results.parent.resolve())
        except ValueError:
            shown = Path(path)
        if skipped:
            not_drawn.append(Path(path))
            print(f"[{time.time() - start:6.1f} s] {shown} not drawn: {skipped}", file=sys.stderr, flush=True)
            return
        written.append(Path(path))
        print(f"[{time.time() - start:6.1f} s] {shown}", flush=True)

    for name in args.only or list(GROUPS):
        GROUPS[name](results, report)
    print(f"{len(written)} files in {time.time() - start:.0f} s from {results / 'tables'} and {results / 'libraries'}")
    stale = stale_figures(results, start, tuple(not_drawn)) if not args.only else []
    for path in stale:
        print(f"not redrawn (no stored source): {path}", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
