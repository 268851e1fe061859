"""LASA multi-step tasks through the whole framework: segmentation -> skill library -> decision engine.

For every shape (Multi_Models_1..4 by default) and training set (``one``: demonstration ``train_demo``, the paper's
protocol; ``all``: the seven), the demonstrations are segmented (BP-GM-HMM, no number of steps given), one P-QLF
LPV-DS is learned per step, and the engine runs B robots in each mode (``none``, ``full``) from four kinds of
starts:

* ``demo``: the starts of the seven demonstrations (no pushes);
* ``random``: uniform in a box twice the data span, with random large and small pushes during the run;
* ``outside``: random box starts outside the first subtask space of their route (large-scale recovery);
* ``inside``: random starts inside it but at least ``inside_min_distance`` x span from every demonstration
  (small-scale modulation).

One row per (shape, training, start kind, mode, start): finished, time to finish (s), path length, final error,
DTWD and E3 to the nearest demonstration (both paths resampled to ``n_resample`` points by arc length, so that E3
pairs points at equal path fractions), and for ``outside`` starts the samples and path length until the robot is
back inside its active subtask space. Figures (paper Figs 5-8) and the behaviour tree (Fig. 3) go to the job
folder, and with ``publish=true`` (preset ``+experiment=lasa_tasks_publish``) to ``paths.figures``; a summary table
of the comparisons goes beside the results. Publishing also stores what the figures are drawn from under
``paths.libraries``/lasa_tasks/: the libraries (per shape and training, and the 1-, 2-, 3-step libraries of Fig. 6),
the demonstrations and the run's configuration; ``experiments/figures.py`` redraws the figures from them with
:func:`replay` (the same starts, pushes and rollouts, recomputed from the stored libraries without fitting).

    python experiments/lasa_tasks.py
    python experiments/lasa_tasks.py shapes=[Multi_Models_3] n_random=200
    python experiments/lasa_tasks.py +experiment=lasa_tasks_publish         # README figures and tables
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import hydra
import pandas as pd
import torch
from tqdm import tqdm

torch.set_num_threads(1)  # the busy-waiting default pool is ~10x slower on a loaded 2-core box
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from lfd_torch.data import LASA_NAMES, Demos, load_lasa
from lfd_torch.errors import InvalidArgumentError
from lfd_torch.metrics import dtw_distance, swept_area
from lfd_torch.modulation import MODULATION_MODES, Branch, Modulation
from lfd_torch.preprocess.regularize import resample
from lfd_torch.segmentation import FixedSegmenter, NoSegmenter
from lfd_torch.skills import Arrival, SkillEngine, SkillLibrary, SkillSettings, random_pushes
from lfd_torch.skills.plot import plot_entropy, plot_rollout_panels
from lfd_torch.store import atomic_write, prepare_job, staged_results, write_table
from lfd_torch.store.job import RESULTS_NAME
from lfd_torch.utils import check_int, derive_seed
from lfd_torch.viz.stored import load_demos, save_config, save_demos
from lfd_torch.store.config_checks import (
    check_entropy_quantile,
    get,
    name_list,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    positive_int,
    rollout_steps,
)

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- starts
def _box(demos: Demos, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    x = demos.samples()[0]
    lo, hi = x.amin(0), x.amax(0)
    return 0.5 * (lo + hi), 0.5 * scale * (hi - lo)


def _uniform(centre: torch.Tensor, half: torch.Tensor, n: int, gen: torch.Generator) -> torch.Tensor:
    u = torch.rand((n, centre.numel()), generator=gen, dtype=centre.dtype)
    return centre + half * (2 * u - 1)


def starts(engine: SkillEngine, demos: Demos, cfg: DictConfig, gen: torch.Generator) -> dict[str, torch.Tensor]:
    """The four kinds of start states (module docstring)."""
    centre, half = _box(demos, 2.0)
    x_demo = demos.samples()[0]
    span = engine.library.span
    pool = _uniform(centre, half, 20 * int(cfg.n_random), gen)
    dec = engine.decide(pool)
    near = torch.cdist(pool, x_demo).amin(-1)
    outside = pool[~dec.inside & ~dec.done]
    inside = pool[dec.inside & (near >= cfg.inside_min_distance * span)]
    n = int(cfg.n_random)
    return {
        "demo": demos.start_points.clone(),
        "random": pool[:n],
        "outside": outside[:n],
        "inside": inside[:n],
    }


# ---------------------------------------------------------------------------------------------- metrics
def path_length(x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """(B,) length of each valid prefix of (B, T, d) paths."""
    seg = torch.linalg.vector_norm(x[:, 1:] - x[:, :-1], dim=-1)
    valid = torch.arange(seg.shape[1]).unsqueeze(0) < (lengths - 1).unsqueeze(1)
    return (seg * valid).sum(-1)


def nearest_demo_metrics(out: Any, demos: Demos, n_resample: int) -> tuple[torch.Tensor, torch.Tensor]:
    """DTWD and E3 of every rollout to its nearest demonstration (by DTWD), on arc-length resampled paths."""
    rolls = resample(out.result.to_demos(), n_resample, "arc_length").positions  # (B, Q, d)
    refs = resample(demos, n_resample, "arc_length").positions  # (N, Q, d)
    B, N = rolls.shape[0], refs.shape[0]
    a = rolls.repeat_interleave(N, 0)
    b = refs.repeat(B, 1, 1)
    dtw = dtw_distance(a, b).view(B, N)
    best = dtw.argmin(-1)
    e3 = swept_area(rolls, refs[best])
    return dtw.gather(-1, best.unsqueeze(-1)).squeeze(-1), e3


def recovery(engine: SkillEngine, out: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Samples until the robot is first inside its active subtask space, and the path length until then (inf if
    never)."""
    res = out.result
    B, T, d = res.positions.shape
    x = res.positions.reshape(-1, d)
    step = out.steps.reshape(-1)
    own, other = engine.own_other(x, step)
    inside = ((own >= other).view(B, T) | (out.branches == int(Branch.AT_GOAL))) & res.mask
    first = torch.where(inside.any(-1), inside.to(torch.int8).argmax(-1), torch.full((B,), T))
    lengths = (first + 1).clamp(max=T)
    dist = path_length(res.positions, lengths)
    never = first >= T
    return first.double().masked_fill(never, math.inf), dist.masked_fill(never, math.inf)


# ---------------------------------------------------------------------------------------------- one task
#: Training sets: ``one`` (demonstration ``train_demo``, the paper's protocol) and ``all`` (the seven).
TRAININGS: tuple[str, ...] = ("one", "all")


def learn(cfg: DictConfig, demos: Demos, segmenter: Any, seed_parts: tuple,
          settings: SkillSettings | None = None) -> tuple[SkillLibrary, float]:
    """The library of ``demos`` and its fit time (s); ``settings``: the checked ``cfg.skills`` (None: built here)."""
    settings = instantiate(cfg.skills) if settings is None else settings
    g = torch.Generator().manual_seed(derive_seed(*seed_parts))
    t0 = time.perf_counter()
    seg = segmenter(demos, generator=g)
    lib = SkillLibrary.learn(demos, seg, primitive=instantiate(cfg.ds), generator=g, **settings.learn_kwargs)
    return lib, time.perf_counter() - t0


def modulations_of(cfg: DictConfig, modes: Any) -> dict[str, Modulation]:
    """One :class:`Modulation` per mode of ``modes``, with the run's ``cfg.modulation`` settings."""
    mod_kw = {k: v for k, v in OmegaConf.to_container(cfg.modulation, resolve=True).items() if k not in ("_target_", "mode")}
    return {mode: Modulation(mode=mode, **mod_kw) for mode in modes}


def engines_of(lib: SkillLibrary, modulations: dict[str, Modulation], arrival: Arrival) -> dict[str, SkillEngine]:
    """One engine per mode over ``lib`` (:func:`modulations_of`), with the run's arrival settings."""
    return {mode: SkillEngine(lib, modulation, arrival) for mode, modulation in modulations.items()}


def task_starts(cfg: DictConfig, shape: str, training: str, engines: dict[str, SkillEngine],
                demos_all: Demos) -> dict[str, torch.Tensor]:
    """The seeded start states of one task (:func:`starts` from the task's own generator)."""
    gen = torch.Generator().manual_seed(derive_seed(cfg.experiment, shape, training, "starts", cfg.seed))
    return starts(engines["full"], demos_all, cfg, gen)


def roll(cfg: DictConfig, shape: str, training: str, kind: str, engine: SkillEngine, x0: torch.Tensor) -> Any:
    """The engine's rollout from ``x0``; ``random`` starts get the task's seeded random pushes (their directions
    are drawn during the run, so a push plan reproduces only for the same batch of starts)."""
    lib = engine.library
    pushes = None
    if kind == "random":
        pushes = random_pushes(x0.shape[0], generator=torch.Generator().manual_seed(
            derive_seed(cfg.experiment, shape, training, "pushes", cfg.seed)), n_pushes=int(cfg.pushes.n),
            window=(int(cfg.pushes.first_s / cfg.dt), int(cfg.pushes.last_s / cfg.dt)),
            magnitude=(cfg.pushes.low * lib.span, cfg.pushes.high * lib.span))  # fmt: skip
    return engine.rollout(x0, dt=cfg.dt, n_steps=int(round(cfg.budget_s / cfg.dt)), pushes=pushes)


def run_task(cfg: DictConfig, shape: str, training: str, out_dir: Path,
             checked: dict[str, Any]) -> tuple[list[dict[str, Any]], dict]:
    """The rows of one task and what its figures draw; ``checked``: :func:`check_config`'s values."""
    settings = checked["settings"]
    demos_all = load_lasa(shape)
    train = demos_all[[int(cfg.train_demo)]] if training == "one" else demos_all
    lib, fit_s = learn(cfg, train, instantiate(cfg.segmentation), (cfg.experiment, shape, training, cfg.seed),
                       settings)  # fmt: skip
    lib.save(out_dir / "libraries" / f"{shape}_{training}")
    log.info("%s/%s: %d steps, %d routes, learned in %.1f s, stability %s", shape, training, lib.n_steps,
             len(lib.routes), fit_s, lib.stability and lib.stability["passed"])  # fmt: skip
    engines = engines_of(lib, checked["modulations"], settings.arrival)
    kinds = task_starts(cfg, shape, training, engines, demos_all)
    rows: list[dict[str, Any]] = []
    outs: dict[tuple[str, str], Any] = {}
    for kind, x0 in kinds.items():
        if x0.shape[0] == 0:
            log.warning("%s/%s: no %s starts found", shape, training, kind)
            continue
        for mode, eng in engines.items():
            t0 = time.perf_counter()
            out = roll(cfg, shape, training, kind, eng, x0)
            seconds = time.perf_counter() - t0
            outs[(kind, mode)] = out
            res = out.result
            dtw, e3 = nearest_demo_metrics(out, demos_all, int(cfg.n_resample))
            rec_samples, rec_path = recovery(eng, out) if kind == "outside" else (None, None)
            final = res.positions[torch.arange(res.n_starts), res.lengths - 1]
            err = torch.linalg.vector_norm(final - demos_all.attractor.to(final), dim=-1)
            plen = path_length(res.positions, res.lengths)
            n_push = torch.zeros(res.n_starts, dtype=torch.long)
            for p in out.pushes:
                n_push[p["row"]] += int(p["applied"])
            for b in range(res.n_starts):
                rows.append({
                    "experiment": cfg.experiment, "shape": shape, "method": f"{training}/{kind}/{mode}", "fold": 0,
                    "seed": int(cfg.seed), "trajectory": b, "training": training, "starts": kind, "mode": mode,
                    "n_steps_task": lib.n_steps, "n_routes": len(lib.routes), "route": int(out.routes[b]),
                    "finished": bool(out.done[b]), "time_s": float(res.lengths[b] - 1) * cfg.dt,
                    "path_length": float(plen[b]), "final_error": float(err[b]), "DTWD": float(dtw[b]),
                    "E3": float(e3[b]), "pushes": int(n_push[b]),
                    "large_share": float((out.branches[b, : res.lengths[b]] == int(Branch.LARGE_SCALE)).double().mean()),
                    "recovery_samples": math.nan if rec_samples is None else float(rec_samples[b]),
                    "recovery_path": math.nan if rec_path is None else float(rec_path[b]),
                    "rollout_s": seconds, "learn_s": fit_s,
                    "stability_passed": bool(lib.stability["passed"]) if lib.stability else None,
                    "worst_margin": float(lib.stability["worst_margin"]) if lib.stability else math.nan,
                })  # fmt: skip
    return rows, {"library": lib, "outs": outs, "demos": demos_all, "train": train, "engines": engines}


# ---------------------------------------------------------------------------------------------- figures
#: Rollouts drawn per panel: Fig. 7 (modulation, outside / inside starts) and Fig. 8 (pushes).
MODULATION_ROWS = 5
PUSH_ROWS = 12
FIG6_STEPS = (1, 2, 3)


def fig6_libraries(cfg: DictConfig, shape: str, train: Demos) -> dict[int, SkillLibrary]:
    """Fig. 6: the training data with 1, 2, 3 equal-time steps, one library each (fitted, not checked)."""
    libs = {}
    for k in FIG6_STEPS:
        seg = NoSegmenter() if k == 1 else FixedSegmenter([j / k for j in range(1, k)])
        g = torch.Generator().manual_seed(derive_seed(cfg.experiment, shape, "fig6", k, cfg.seed))
        libs[k] = SkillLibrary.learn(train, seg(train), primitive=instantiate(cfg.ds), generator=g, check=False)
    return libs


def fig6_panels(cfg: DictConfig, libs: dict[int, SkillLibrary], demos: Demos,
                arrival: Arrival) -> list[tuple[str, SkillLibrary, Any]]:
    """Fig. 6 panels: each library's engine (mode none, the run's ``arrival``) from the demonstrations' starts."""
    panels = []
    for k, lib_k in sorted(libs.items()):
        out = SkillEngine(lib_k, "none", arrival).rollout(demos.start_points, dt=cfg.dt,
                                                          n_steps=int(round(cfg.budget_s / cfg.dt)))  # fmt: skip
        panels.append((f"{k} step{'s' if k > 1 else ''} (equal time)", lib_k, out))
    return panels


def figures(cfg: DictConfig, shape: str, tasks: dict[str, dict], fig6: list, fig_dir: Path) -> list[Path]:
    """Paper Figs 3, 5-8 for one shape (module docstring), from the tasks' libraries and rollouts.

    Args:
        tasks: per training, ``library``, ``demos`` (all seven), ``engines`` (per mode) and ``outs`` (per (start
            kind, mode) the :class:`~lfd_torch.skills.engine.EngineRollout`; the figures draw the ``demo`` /
            ``none`` rollouts, the first :data:`MODULATION_ROWS` of ``outside`` / ``inside`` and the first
            :data:`PUSH_ROWS` of ``random``).
        fig6: :func:`fig6_panels` of the first training's Fig. 6 libraries.
    """
    written = []
    one, everything = tasks.get("one"), tasks.get("all")
    base = one or everything
    assert base is not None
    lib, demos = base["library"], base["demos"]
    written.append(plot_entropy(lib, demos, fig_dir / f"lasa_tasks_{shape}_entropy.png",
                                title=f"{shape}: H2 of each step's primitive (white: H2 = H2(x_r))"))  # fmt: skip
    # Fig. 6: the same training data with 1, 2, 3 equal steps and with the BP-GM-HMM steps, engine mode none
    panels = list(fig6) + [(f"BP-GM-HMM: {lib.n_steps} steps", lib, base["outs"][("demo", "none")])]
    written.append(plot_rollout_panels(panels, demos, fig_dir / f"lasa_tasks_{shape}_steps.png",
                                       title=f"{shape}: LPV-DS with 1, 2, 3 and the model's steps"))  # fmt: skip
    # Fig. 7: before/after modulation from starts outside and inside a subtask space
    outs = base["outs"]
    panels = []
    for kind in ("outside", "inside"):
        for mode in ("none", "full"):
            if (kind, mode) in outs:
                panels.append((f"{kind} A_m, {mode}", lib, outs[(kind, mode)]))
    if panels:
        written.append(plot_rollout_panels(panels, demos, fig_dir / f"lasa_tasks_{shape}_modulation.png",
                                           max_rows=MODULATION_ROWS,
                                           title=f"{shape}: before / after modulation (red: large, green: small)"))  # fmt: skip
    # Fig. 8: complete tasks under random pushes (crosses)
    panels = [(f"{t}: pushes, {mode}", tk["library"], tk["outs"][("random", mode)])
              for t, tk in tasks.items() for mode in ("none", "full") if ("random", mode) in tk["outs"]]  # fmt: skip
    written.append(plot_rollout_panels(panels, demos, fig_dir / f"lasa_tasks_{shape}_pushes.png", max_rows=PUSH_ROWS,
                                       title=f"{shape}: whole task under random pushes"))  # fmt: skip
    # Fig. 3: the behaviour tree built from the segmentation of all demonstrations
    tree_lib = (everything or base)["engines"]["full"]
    written.extend(tree_lib.tree.render(fig_dir / f"lasa_tasks_{shape}_tree"))
    return written


def store(cfg: DictConfig, shape: str, tasks: dict[str, dict], fig6_libs: dict[int, SkillLibrary],
          libraries: Path) -> list[Path]:
    """Store what :func:`replay` needs under ``libraries/lasa_tasks/``: per training ``<shape>_<training>/``,
    the Fig. 6 libraries ``<shape>_steps<k>/``, ``<shape>_demos.pt`` and ``config.json``."""
    where = libraries / cfg.experiment
    written = [save_config(cfg, where / "config.json")]
    for training, task in tasks.items():
        written.append(task["library"].save(where / f"{shape}_{training}"))
    for k, lib_k in fig6_libs.items():
        written.append(lib_k.save(where / f"{shape}_steps{k}"))
    first = next(iter(tasks.values()))
    written.append(save_demos(first["demos"], where / f"{shape}_demos.pt", velocities=False))
    return written


def replay(cfg: DictConfig, shape: str, libraries: Path) -> tuple[dict[str, dict], list]:
    """The ``tasks`` and ``fig6`` arguments of :func:`figures` from the stored libraries of one shape (no fitting):
    the same seeded starts and pushes; only the rollouts the figures draw are recomputed (``random`` in full, its
    push plan depends on the batch).

    Raises:
        StoreError: a stored library, demonstration or configuration file is missing or damaged (named).
    """
    where = libraries / cfg.experiment
    demos_all, _ = load_demos(where / f"{shape}_demos.pt")
    tasks: dict[str, dict] = {}
    trainings = [str(t) for t in cfg.training]
    base = "one" if "one" in trainings else trainings[0]  # the training whose Figs 5-7 are drawn
    arrival, modulations = instantiate(cfg.skills).arrival, modulations_of(cfg, cfg.modes)
    for training in trainings:
        lib = SkillLibrary.load(where / f"{shape}_{training}")
        engines = engines_of(lib, modulations, arrival)
        kinds = task_starts(cfg, shape, training, engines, demos_all)
        outs = {}
        for kind, x0 in kinds.items():
            if x0.shape[0] == 0 or (training != base and kind != "random"):
                continue
            rows = {"demo": x0.shape[0], "random": x0.shape[0]}.get(kind, MODULATION_ROWS)
            for mode, eng in engines.items():
                if kind == "demo" and mode != "none":
                    continue
                outs[(kind, mode)] = roll(cfg, shape, training, kind, eng, x0[:rows])
        tasks[training] = {"library": lib, "demos": demos_all, "engines": engines, "outs": outs}
    fig6_libs = {k: SkillLibrary.load(where / f"{shape}_steps{k}") for k in FIG6_STEPS}
    return tasks, fig6_panels(cfg, fig6_libs, demos_all, arrival)


def summary(table: pd.DataFrame) -> pd.DataFrame:
    """The comparisons: per shape and training, none vs full."""
    rows = []
    for (shape, training), part in table.groupby(["shape", "training"], sort=False):
        row: dict[str, Any] = {"shape": shape, "training": training, "steps": int(part.n_steps_task.iloc[0]),
                               "routes": int(part.n_routes.iloc[0])}  # fmt: skip
        for mode in ("none", "full"):
            m = part[part["mode"] == mode]
            out, ins, rnd = m[m.starts == "outside"], m[m.starts == "inside"], m[m.starts == "random"]
            row[f"finished_{mode}"] = float(m.finished.mean())
            row[f"recovery_steps_{mode}"] = float(out.recovery_samples.median()) if len(out) else math.nan
            row[f"recovery_path_{mode}"] = float(out.recovery_path.median()) if len(out) else math.nan
            row[f"inside_E3_{mode}"] = float(ins.E3.median()) if len(ins) else math.nan
            row[f"inside_DTWD_{mode}"] = float(ins.DTWD.median()) if len(ins) else math.nan
            row[f"pushed_time_s_{mode}"] = float(rnd.time_s.median()) if len(rnd) else math.nan
            row[f"max_time_s_{mode}"] = float(m.time_s.max())
        rows.append(row)
    return pd.DataFrame(rows)


def check_config(cfg: DictConfig) -> dict[str, Any]:
    """Check every setting before anything is fitted (InvalidArgumentError / UnknownNameError naming the key);
    returns the checked objects the run uses: ``modulations`` (mode -> :class:`Modulation`, :func:`modulations_of`)
    and ``settings`` (:class:`~lfd_torch.skills.SkillSettings`)."""
    shapes = name_list(cfg, "shapes", LASA_NAMES)
    name_list(cfg, "training", TRAININGS)
    modes = name_list(cfg, "modes", MODULATION_MODES)
    if "full" not in modes:  # the starts are classified by the full engine's subtask-space test
        raise InvalidArgumentError(f"modes must include full (the starts are drawn with its engine), got {modes}")
    if cfg.figures and "none" not in modes:  # Figs 5-7 draw the unmodulated rollouts
        raise InvalidArgumentError(f"modes must include none when figures=true (Figs 5-7 draw it), got {modes}")
    n_demos = load_lasa(shapes[0]).n_demos  # every LASA shape has seven
    check_int(get(cfg, "train_demo"), "train_demo", low=-n_demos, high=n_demos - 1)
    positive_int(cfg, "n_random")
    nonnegative_float(cfg, "inside_min_distance")
    rollout_steps(cfg, "dt", "budget_s")
    check_int(get(cfg, "n_resample"), "n_resample", low=2)
    n_pushes = nonnegative_int(cfg, "pushes.n")
    first_s, last_s = positive_float(cfg, "pushes.first_s"), positive_float(cfg, "pushes.last_s")
    first, last = int(first_s / cfg.dt), int(last_s / cfg.dt)  # the push window in samples, as roll() makes it
    if first < 1 or last - first + 1 < n_pushes:
        raise InvalidArgumentError(f"pushes.first_s..pushes.last_s ({first_s}..{last_s} s, samples {first}..{last} at "
                                   f"dt {cfg.dt}) must start at >= 1 sample and hold pushes.n = {n_pushes} samples")  # fmt: skip
    low, high = positive_float(cfg, "pushes.low"), positive_float(cfg, "pushes.high")
    if low > high:
        raise InvalidArgumentError(f"pushes.low must not exceed pushes.high, got {low} > {high}")
    check_entropy_quantile(cfg)
    return {"modulations": modulations_of(cfg, modes), "settings": instantiate(cfg.skills)}


def run(cfg: DictConfig) -> dict[str, Any]:
    checked = check_config(cfg)
    job = prepare_job(cfg)
    out_dir, manifest = job.out_dir, job.manifest
    rows: list[dict[str, Any]] = []
    written: list[Path] = []
    fig_dir = Path(cfg.paths.figures) if cfg.publish else out_dir / "figures"
    for shape in tqdm(list(cfg.shapes), desc="lasa_tasks", unit="shape", disable=not cfg.get("progress", True)):
        tasks = {}
        for training in cfg.training:
            part, task = run_task(cfg, str(shape), str(training), out_dir, checked)
            rows.extend(part)
            tasks[str(training)] = task
        if cfg.figures or cfg.publish:
            base = tasks.get("one") or tasks.get("all")
            assert base is not None
            fig6_libs = fig6_libraries(cfg, str(shape), base["train"])
            if cfg.figures:
                panels = fig6_panels(cfg, fig6_libs, base["demos"], checked["settings"].arrival)
                written.extend(figures(cfg, str(shape), tasks, panels, fig_dir))
            if cfg.publish:
                written.extend(store(cfg, str(shape), tasks, fig6_libs, Path(cfg.paths.libraries)))
    table = pd.DataFrame(rows)
    written.append(write_table(table, out_dir / RESULTS_NAME, manifest=manifest))
    summ = summary(table)
    md = summ.to_markdown(index=False, floatfmt=".3g")
    written.append(atomic_write(out_dir / "summary.md", lambda p: p.write_text(md + "\n")))
    if cfg.publish:
        tables = Path(cfg.paths.tables)
        written.append(write_table(table, tables / f"{cfg.experiment}.parquet", manifest=manifest))
        written.append(atomic_write(tables / f"{cfg.experiment}.md", lambda p: p.write_text(md + "\n")))
    log.info("summary:\n%s", md)
    return {"table": table, "summary": summ, "written": written}


@hydra.main(config_path="../conf", config_name="lasa_tasks", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with staged_results(cfg):  # published outputs replace the old ones together, only when the run succeeds
        result = run(cfg)
    print(result["summary"].to_string(index=False))


if __name__ == "__main__":
    main()
