"""MNIST digit strokes: the framework vs SEDS from several starts per digit (paper Sec. V-A, Figs 10-11).

Per digit in ``digits`` (0-9 by default), ``data.n_demos`` test-set images become demonstrations
(:func:`lfd_torch.data.mnist_demos`: skeleton -> longest pen trail -> mm, ending at the origin). Two methods learn
from the same demonstrations:

* ``framework``: BP-GM-HMM segmentation (no number of steps given) -> one P-QLF LPV-DS per step
  (``SkillLibrary.learn``) -> ``SkillEngine`` with modulation ``modulation.mode`` (full);
* ``seds``: one SEDS (``ds@seds``, K by BIC) on the whole demonstration set, integrated as it is
  (:func:`lfd_torch.rollout.rollout`).

Both are integrated with the same Euler step ``dt`` and budget ``budget_s`` from the demonstrations' starts
(``starts = demo``) and ``n_perturbed`` perturbed starts (a demonstration's start moved uniformly in a disc of
radius ``perturb`` x span; ``starts = perturbed``), and stop within ``reach_radius`` x span of the attractor.
One row per (digit, method, start): DTWD and E3 to the nearest demonstration (both paths resampled to
``n_resample`` points by arc length; DTWD in mm summed along the warping path, E3 the mean swept area in mm^2),
final error (mm), reached (the rollout stopped at the goal), time (s), path length (mm), fit time. Figures in the
job folder (``publish=true``: ``paths.figures``): ``mnist_strokes.png`` (Fig. 10: one image per digit with its
pen path, and the demonstrations in mm) and ``mnist_rollouts.png`` (Fig. 11: framework and SEDS rollouts per
digit). ``summary.md``: per digit and method, the means over starts. Publishing also stores what the figures draw
(per digit: the demonstrations, the first image and its pen path, the rollout paths of both methods) in
``paths.libraries``/mnist/digit_<d>.pt, from which ``experiments/figures.py`` redraws them.

    LFD_MNIST_DIR=/path/to/mnist python experiments/mnist.py
    python experiments/mnist.py data.directory=/path/to/mnist digits=[4,9] data.n_demos=5
    python experiments/mnist.py publish=true  # the published run (segmentation: the present defaults)
"""

from __future__ import annotations

import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
torch.set_num_threads(1)  # the busy-waiting default pool is ~10x slower on a loaded 2-core box
from hydra.utils import instantiate  # noqa: E402
from omegaconf import DictConfig, ListConfig, OmegaConf  # noqa: E402

from lfd_torch.data import Demos, extract_stroke, load_mnist  # noqa: E402
from lfd_torch.errors import InvalidArgumentError, LfdError  # noqa: E402
from lfd_torch.metrics import dtw_distance, swept_area  # noqa: E402
from lfd_torch.rollout import rollout  # noqa: E402
from lfd_torch.skills import SkillEngine, SkillLibrary  # noqa: E402
from lfd_torch.store import atomic_write, prepare_job, staged_results, write_table  # noqa: E402
from lfd_torch.store.job import RESULTS_NAME  # noqa: E402
from lfd_torch.utils import check_int, derive_seed  # noqa: E402
from lfd_torch.viz.stored import load_demos, save_demos  # noqa: E402
from lfd_torch.store.config_checks import (  # noqa: E402
    check_entropy_quantile,
    get,
    is_config_error,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    rollout_steps,
)

log = logging.getLogger(__name__)

METHODS: tuple[str, ...] = ("framework", "seds")


# ---------------------------------------------------------------------------------------------- metrics
def arc_resample(x: torch.Tensor, lengths: torch.Tensor, n: int) -> torch.Tensor:
    """(B, n, d) points equally spaced in path length along the valid prefix of each (B, T, d) path.

    A path of zero length (a start at the goal) repeats its point.
    """
    B, T, d = x.shape
    valid = torch.arange(T).unsqueeze(0) < lengths.unsqueeze(1)
    step = torch.linalg.vector_norm(x[:, 1:] - x[:, :-1], dim=-1) * valid[:, 1:]
    s = torch.cat([step.new_zeros(B, 1), step.cumsum(1)], 1)  # (B, T), flat after the valid part
    total = s[:, -1:]
    q = torch.linspace(0, 1, n, dtype=x.dtype).unsqueeze(0) * total  # (B, n)
    hi = torch.searchsorted(s.contiguous(), q.contiguous(), right=False).clamp(1, T - 1)
    lo = hi - 1
    s_lo, s_hi = s.gather(1, lo), s.gather(1, hi)
    w = ((q - s_lo) / (s_hi - s_lo).clamp_min(1e-12)).clamp(0, 1).unsqueeze(-1)
    take = lambda idx: x.gather(1, idx.unsqueeze(-1).expand(-1, -1, d))  # noqa: E731
    out = take(lo) + w * (take(hi) - take(lo))
    still = (total.squeeze(1) <= 0).view(B, 1, 1)
    return torch.where(still, x[:, :1].expand(-1, n, -1), out)


def path_length(x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """(B,) length of the valid prefix of each (B, T, d) path."""
    seg = torch.linalg.vector_norm(x[:, 1:] - x[:, :-1], dim=-1)
    valid = torch.arange(seg.shape[1]).unsqueeze(0) < (lengths - 1).unsqueeze(1)
    return (seg * valid).sum(-1)


def nearest_demo_metrics(x: torch.Tensor, lengths: torch.Tensor, demos: Demos, n: int) -> dict[str, torch.Tensor]:
    """DTWD (mm) and E3 (mm^2) of each rollout to its nearest demonstration (by DTWD), arc-length resampled."""
    rolls = arc_resample(x, lengths, n)  # (B, n, d)
    refs = arc_resample(demos.positions, demos.lengths, n)  # (N, n, d)
    B, N = rolls.shape[0], refs.shape[0]
    dtw = dtw_distance(rolls.repeat_interleave(N, 0), refs.repeat(B, 1, 1)).view(B, N)
    best = dtw.argmin(-1)
    return {
        "DTWD": dtw.gather(-1, best.unsqueeze(-1)).squeeze(-1),
        "E3": swept_area(rolls, refs[best]),
        "nearest_demo": best,
    }


# ---------------------------------------------------------------------------------------------- starts
def make_starts(demos: Demos, cfg: DictConfig, gen: torch.Generator) -> tuple[torch.Tensor, list[str]]:
    """(B, 2) start states -- the demonstrations' starts, then ``n_perturbed`` moved ones -- and their kinds."""
    x0 = demos.start_points.clone()
    x = demos.samples()[0]
    span = float((x.amax(0) - x.amin(0)).max())
    k = int(cfg.n_perturbed)
    if k > 0:
        base = x0[torch.arange(k) % demos.n_demos]
        r = float(cfg.perturb) * span * torch.rand(k, generator=gen, dtype=x0.dtype).sqrt()
        phi = 2 * math.pi * torch.rand(k, generator=gen, dtype=x0.dtype)
        moved = base + torch.stack([r * torch.cos(phi), r * torch.sin(phi)], -1)
        x0 = torch.cat([x0, moved])
    return x0, ["demo"] * demos.n_demos + ["perturbed"] * k


# ---------------------------------------------------------------------------------------------- one digit
def fit_framework(cfg: DictConfig, demos: Demos, digit: int) -> tuple[SkillEngine, float]:
    g = torch.Generator().manual_seed(derive_seed(cfg.experiment, digit, "framework", cfg.seed))
    t0 = time.perf_counter()
    seg = instantiate(cfg.segmentation)(demos, generator=g)
    settings = instantiate(cfg.skills)
    lib = SkillLibrary.learn(demos, seg, primitive=instantiate(cfg.ds), generator=g, **settings.learn_kwargs)
    engine = SkillEngine(lib, instantiate(cfg.modulation), settings.arrival)
    return engine, time.perf_counter() - t0


def run_digit(cfg: DictConfig, digit: int) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Both methods on one digit: rows and what the figures need."""
    demos = instantiate(cfg.data, digit=digit)
    x = demos.samples()[0]
    span = float((x.amax(0) - x.amin(0)).max())
    radius = float(cfg.reach_radius) * span
    gen = torch.Generator().manual_seed(derive_seed(cfg.experiment, digit, "starts", cfg.seed))
    x0, kinds = make_starts(demos, cfg, gen)
    n_steps = int(round(float(cfg.budget_s) / float(cfg.dt)))
    common = {"experiment": cfg.experiment, "shape": f"digit_{digit}", "fold": 0, "seed": int(cfg.seed),
              "digit": digit, "n_demos": demos.n_demos, "demos": " ".join(demos.names)}  # fmt: skip
    rows: list[dict[str, Any]] = []
    paths: dict[str, Any] = {}
    for method in METHODS:
        extra: dict[str, Any] = {}
        try:
            if method == "framework":
                engine, fit_s = fit_framework(cfg, demos, digit)
                t0 = time.perf_counter()
                out = engine.rollout(x0, dt=float(cfg.dt), n_steps=n_steps)
                res, reached = out.result, out.done
                lib = engine.library
                extra = {"n_steps_task": lib.n_steps, "n_components": sum(s.primitive.n_components for s in lib.skills),
                         "stability_passed": bool(lib.stability["passed"]) if lib.stability else None}  # fmt: skip
            else:
                g = torch.Generator().manual_seed(derive_seed(cfg.experiment, digit, "seds", cfg.seed))
                t0 = time.perf_counter()
                model = instantiate(cfg.seds)(demos, generator=g)
                fit_s = time.perf_counter() - t0
                t0 = time.perf_counter()
                res = rollout(model, x0, float(cfg.dt), n_steps, attractor=model.attractor, position_tol=radius,
                              velocity_tol=math.inf)  # fmt: skip
                reached = res.converged
                extra = {"n_steps_task": 1, "n_components": model.n_components, "stability_passed": True}
            roll_s = time.perf_counter() - t0
        except LfdError as exc:
            if is_config_error(exc):  # a bad setting, not a failed fit: no row hides it
                raise
            log.error("digit %d, %s failed: %s", digit, method, exc)
            for b, kind in enumerate(kinds):
                rows.append({**common, "method": method, "trajectory": b, "starts": kind,
                             "status": f"{type(exc).__name__}: {exc}", "DTWD": math.nan, "E3": math.nan,
                             "final_error": math.nan, "reached": False})  # fmt: skip
            continue
        m = nearest_demo_metrics(res.positions, res.lengths, demos, int(cfg.n_resample))
        final = res.positions[torch.arange(res.n_starts), res.lengths - 1]
        err = torch.linalg.vector_norm(final - demos.attractor.to(final), dim=-1)
        plen = path_length(res.positions, res.lengths)
        paths[method] = [res.positions[b, : int(res.lengths[b])].clone() for b in range(res.n_starts)]
        for b, kind in enumerate(kinds):
            rows.append({
                **common, "method": method, "trajectory": b, "starts": kind, "status": "ok",
                "DTWD": float(m["DTWD"][b]), "E3": float(m["E3"][b]), "nearest_demo": int(m["nearest_demo"][b]),
                "final_error": float(err[b]), "reached": bool(reached[b]),
                "time_s": float(res.lengths[b] - 1) * float(cfg.dt), "path_length": float(plen[b]),
                "fit_s": fit_s, "rollout_s": roll_s, **extra,
            })  # fmt: skip
        log.info("digit %d %-9s: %d steps, DTWD %.0f mm, reached %d/%d, fit %.1f s", digit, method,
                 extra["n_steps_task"], float(m["DTWD"].mean()), int(reached.sum()), len(kinds), fit_s)  # fmt: skip
    return rows, {"demos": demos, "starts": x0, "kinds": kinds, "paths": paths}


# ---------------------------------------------------------------------------------------------- figures
def _figure(n_rows: int, n_cols: int, scale: float = 1.9) -> tuple[Any, np.ndarray]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(scale * n_cols, scale * n_rows + 0.4), layout="constrained")
    FigureCanvasAgg(fig)
    axes = np.asarray(fig.subplots(n_rows, n_cols, squeeze=False))
    return fig, axes


def _demo_panel(ax: Any, demos: Demos, colour: str | None = None) -> None:
    for k, p in enumerate(demos.sequences()):
        p = p.numpy()
        ax.plot(p[:, 0], p[:, 1], color=colour or f"C{k}", lw=2.5 if colour else 1.5, alpha=0.35 if colour else 1.0)
        if not colour:
            ax.plot(p[0, 0], p[0, 1], "o", color=f"C{k}", ms=4)
    ax.plot(0, 0, "k*", ms=9)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)


def figure_data(tasks: dict[int, dict], images: torch.Tensor, stroke_kw: dict) -> dict[int, dict]:
    """What the two figures draw, per digit: ``demos``, ``index`` and ``image`` (H, W) uint8 of the first
    demonstration's image, its pen path ``stroke`` (P, 2) in pixels, the start ``kinds`` and the rollout
    ``paths`` per method (float32 (T_b, 2) each, mm)."""
    data = {}
    for d, task in tasks.items():
        demos = task["demos"]
        index = int(demos.names[0].rsplit("/", 1)[-1])
        st = extract_stroke(images[index], **stroke_kw)
        data[d] = {"demos": demos, "index": index, "image": images[index].clone(),
                   "stroke": torch.tensor(np.array(st.path), dtype=torch.float64), "kinds": list(task["kinds"]),
                   "paths": {m: [p.to(torch.float32) for p in ps] for m, ps in task["paths"].items()}}  # fmt: skip
    return data


def store(data: dict[int, dict], libraries: Path) -> list[Path]:
    """``libraries/mnist/digit_<d>.pt`` per digit of :func:`figure_data`."""
    return [save_demos(item["demos"], libraries / "mnist" / f"digit_{d}.pt",
                       **{k: v for k, v in item.items() if k != "demos"}) for d, item in data.items()]  # fmt: skip


def load_figure_data(libraries: Path, digits: list[int]) -> dict[int, dict]:
    """:func:`figure_data` from the files of :func:`store` (StoreError naming a missing or damaged one)."""
    data = {}
    for d in digits:
        demos, item = load_demos(libraries / "mnist" / f"digit_{d}.pt")
        data[d] = {"demos": demos, **item}
    return data


def figure_strokes(data: dict[int, dict], path: Path) -> Path:
    """Paper Fig. 10: per digit, the first image with its pen path (start o, attractor *) and the demos in mm."""
    from lfd_torch.viz import save_figure

    digits = sorted(data)
    fig, axes = _figure(2, len(digits))
    for j, d in enumerate(digits):
        item = data[d]
        demos, index = item["demos"], item["index"]
        img = item["image"].numpy()
        H, W = img.shape
        st = item["stroke"].numpy()
        ax = axes[0, j]
        ax.imshow(img, cmap="gray_r", extent=(-0.5, W - 0.5, -0.5, H - 0.5), alpha=0.6)
        ax.scatter(st[:, 0], st[:, 1], c=np.linspace(0, 1, len(st)), cmap="viridis", s=1.5)
        ax.plot(*st[0], "o", color="tab:green", ms=5)
        ax.plot(*st[-1], "*", color="tab:red", ms=8)
        ax.set_title(f"digit {d} (image {index}), px", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
        _demo_panel(axes[1, j], demos)
        axes[1, j].set_title(f"{demos.n_demos} demos, mm", fontsize=8)
    fig.suptitle("MNIST strokes: skeleton -> longest pen trail (dark = start) -> demonstrations ending at the origin",
                 fontsize=9)  # fmt: skip
    return save_figure(fig, path, dpi=150)


def figure_rollouts(data: dict[int, dict], table: pd.DataFrame, path: Path) -> Path:
    """Paper Fig. 11: per digit, the rollouts of the framework (top) and of SEDS (bottom) over the demos."""
    from lfd_torch.viz import save_figure

    digits = sorted(data)
    fig, axes = _figure(len(METHODS), len(digits))
    for j, d in enumerate(digits):
        task = data[d]
        for i, method in enumerate(METHODS):
            ax = axes[i, j]
            _demo_panel(ax, task["demos"], colour="0.5")
            for b, p in enumerate(task["paths"].get(method, [])):
                p = p.numpy()
                style = "-" if task["kinds"][b] == "demo" else "--"
                ax.plot(p[:, 0], p[:, 1], style, color="tab:blue" if method == "framework" else "tab:red", lw=1)
                ax.plot(p[0, 0], p[0, 1], "o", color="k", ms=2.5)
            part = table[(table.digit == d) & (table.method == method)]
            ok = part[part.status == "ok"]
            label = (f"DTWD {ok.DTWD.mean():.0f}, {int(ok.reached.sum())}/{len(part)}" if len(ok)
                     else "failed")  # fmt: skip
            ax.set_title(f"{d}: {method} ({label})", fontsize=7)
    fig.suptitle("MNIST: framework (blue, top) vs SEDS (red, bottom); grey: demonstrations, dashed: perturbed starts, "
                 "mm; titles: mean DTWD (mm), goal reached", fontsize=8)  # fmt: skip
    return save_figure(fig, path, dpi=150)


# ---------------------------------------------------------------------------------------------- run
def summary(table: pd.DataFrame) -> pd.DataFrame:
    """Per digit and method: mean DTWD, E3, final error, reached share, rollout time; and the DTWD ratio."""
    ok = table[table.status == "ok"]
    agg = ok.groupby(["digit", "method"]).agg(
        DTWD=("DTWD", "mean"), E3=("E3", "mean"), final_error=("final_error", "mean"),
        reached=("reached", "mean"), time_s=("time_s", "mean"), steps=("n_steps_task", "first"),
    ).reset_index()  # fmt: skip
    wide = agg.pivot(index="digit", columns="method")
    wide.columns = [f"{metric}_{method}" for metric, method in wide.columns]
    wide = wide.reset_index()
    if {"DTWD_framework", "DTWD_seds"} <= set(wide.columns):
        wide["DTWD_ratio"] = wide["DTWD_framework"] / wide["DTWD_seds"]
    return wide


def check_config(cfg: DictConfig) -> None:
    """Check every setting before anything is loaded or fitted (InvalidArgumentError naming the key)."""
    digits = get(cfg, "digits")
    if not isinstance(digits, (ListConfig, list, tuple)) or not len(digits):
        raise InvalidArgumentError(f"digits must be a non-empty list of digits 0..9, got {digits!r}")
    for d in digits:
        check_int(d, "digits entry", low=0, high=9)
    if len(set(digits)) != len(digits):
        raise InvalidArgumentError(f"digits must not repeat a digit, got {list(digits)}")
    nonnegative_int(cfg, "n_perturbed")
    nonnegative_float(cfg, "perturb")
    rollout_steps(cfg, "dt", "budget_s")
    positive_float(cfg, "reach_radius")
    check_int(get(cfg, "n_resample"), "n_resample", low=2)
    check_entropy_quantile(cfg)
    instantiate(cfg.modulation)
    instantiate(cfg.skills)


def run(cfg: DictConfig) -> dict[str, Any]:
    """All digits of ``cfg.digits``; returns the table, the summary and the paths written."""
    check_config(cfg)
    job = prepare_job(cfg)
    out_dir, manifest = job.out_dir, job.manifest
    t_start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    tasks: dict[int, dict] = {}
    for d in tqdm(list(cfg.digits), desc="mnist", unit="digit", disable=not cfg.get("progress", True)):
        part, task = run_digit(cfg, int(d))
        rows.extend(part)
        tasks[int(d)] = task
    table = pd.DataFrame(rows)
    written: list[Path] = [write_table(table, out_dir / RESULTS_NAME, manifest=manifest)]
    summ = summary(table)
    md = summ.to_markdown(index=False, floatfmt=".3g")
    written.append(atomic_write(out_dir / "summary.md", lambda p: p.write_text(md + "\n")))
    if cfg.figures or cfg.publish:
        images, _ = load_mnist(str(cfg.data.split), cfg.data.directory)
        stroke_kw = OmegaConf.to_container(cfg.data.stroke, resolve=True) if cfg.data.get("stroke") else {}
        data = figure_data(tasks, images, dict(stroke_kw))
        if cfg.figures:
            fig_dir = Path(cfg.paths.figures) if cfg.publish else out_dir / "figures"
            written.append(figure_strokes(data, fig_dir / "mnist_strokes.png"))
            written.append(figure_rollouts(data, table, fig_dir / "mnist_rollouts.png"))
        if cfg.publish:
            written.extend(store(data, Path(cfg.paths.libraries)))
    if cfg.publish:
        tables = Path(cfg.paths.tables)
        written.append(write_table(table, tables / f"{cfg.experiment}.parquet", manifest=manifest))
        written.append(atomic_write(tables / f"{cfg.experiment}.md", lambda p: p.write_text(md + "\n")))
    log.info("summary (%.0f s):\n%s", time.perf_counter() - t_start, md)
    return {"table": table, "summary": summ, "written": written, "tasks": tasks}


@hydra.main(config_path="../conf", config_name="mnist", version_base="1.3")
def main(cfg: DictConfig) -> None:
    t0 = time.perf_counter()
    with staged_results(cfg) as final:  # published outputs replace the old ones together, only on success
        result = run(cfg)
    print(result["summary"].to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    for path in result["written"]:
        print(f"wrote {final(path)}")
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
