"""Baxter sugar scooping (paper Sec. V-B, Figs 12-15; issue 10): one demonstration -> skills -> MuJoCo trials.

The spoon-tip demonstration (the seeded generator of :mod:`lfd_torch.robot.demonstration`, standing in for the
paper's kinesthetic recording, or a recorded CSV/NPZ via ``demo_path``) is smoothed, segmented by the BP-GM-HMM
with no number of steps given, and one P-QLF LPV-DS is learned per step. The decision engine then drives the
MuJoCo Baxter (100 Hz engine on the tip position, DLS velocity map, impedance at 1 kHz) in every mode of ``modes``:

* ``start``: the 7 start configurations of Fig. 14, undisturbed;
* ``disturbed``: ``n_disturbed`` trials from those starts, one disturbance each (a force pulse on the arm or a
  position jump, in the approach, scoop or transport stage, requested large or small; labels measured by the
  engine's own subtask-space test), the same trials and pushes in every mode.

One row per (mode, trial) with the success checks and the failure reason (``scooping.parquet``); a summary of success
rates with Wilson 95 % intervals per stage, disturbance kind and label (``scooping.md``). Success is the issue's strict
criterion: any contact with the can or cup walls or the table fails a run, also one a force pulse caused; the
``lenient_rate`` column (contacts begun during a pulse excused) is a diagnostic. Figures: 3-D segmentation
(Fig. 13), trajectories from the 7 starts (Fig. 14), disturbed trajectories (Fig. 15), one rendered frame. The
publish preset also stores what they draw (the smoothed demonstration, its segmentation, the drawn tip paths, the
frame's joint state, the configuration with the run's wall times) under ``libraries/scooping/``, from which
``experiments/figures.py`` redraws them and ``scooping.md`` with :func:`draw_figures` and :func:`markdown`.

    python experiments/scooping.py
    python experiments/scooping.py n_disturbed=60 figures=false
    python experiments/scooping.py +experiment=scooping_publish      # results/tables, results/figures
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

torch.set_num_threads(1)  # before any torch work; run() sets cfg.threads
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from lfd_torch.errors import StoreError
from lfd_torch.modulation import MODULATION_MODES, Modulation
from lfd_torch.robot import load_demonstration, scooping_demonstration
from lfd_torch.robot.demonstration import STAGE_NAMES
from lfd_torch.robot.task import ScoopingTask, controller_for, learn_scooping
from lfd_torch.robot.trials import (
    SuccessCriteria,
    TrialBatch,
    plan_disturbances,
    run_trials,
    start_configurations,
    wilson_interval,
)
from lfd_torch.segmentation import Segmentation
from lfd_torch.skills import Arrival, SkillSettings
from lfd_torch.store import atomic_write, prepare_job, staged_results, write_table
from lfd_torch.store.job import RESULTS_NAME
from lfd_torch.utils import derive_seed
from lfd_torch.viz.stored import load_demos, load_state, save_config, save_demos, save_state
from lfd_torch.store.config_checks import (
    check_entropy_quantile,
    name_list,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    positive_int,
)

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- learning
def learn(cfg: DictConfig, robot: Any, settings: SkillSettings | None = None) -> ScoopingTask:
    """The scooping task learned from the demonstration; ``settings``: the checked ``cfg.skills`` (None: built
    here)."""
    if cfg.demo_path:
        demo = load_demonstration(cfg.demo_path, tool_offset=float(cfg.robot.tool_offset))
    else:
        demo = scooping_demonstration(int(cfg.demo_seed), scene=robot.plant.scene,
                                      tool_offset=float(cfg.robot.tool_offset))  # fmt: skip
    g = torch.Generator().manual_seed(derive_seed(cfg.experiment, "learn", cfg.seed))
    settings = instantiate(cfg.skills) if settings is None else settings
    task = learn_scooping(demo, generator=g, preprocess=instantiate(cfg.preprocess),
                          segmenter=instantiate(cfg.segmentation), primitive=instantiate(cfg.ds), settings=settings)  # fmt: skip
    log.info("demonstration: %d samples, %.1f s; %d steps (stages %s); segmented in %.1f s, learned in %.1f s",
             demo.n_samples, float(demo.t[-1]), task.n_steps, task.step_stage.tolist(), task.info["segment_s"],
             task.info["learn_s"])  # fmt: skip
    return task


def modulations_of(cfg: DictConfig, modes: Any) -> dict[str, Modulation]:
    """One :class:`Modulation` per mode of ``modes``, with the run's ``cfg.modulation`` settings."""
    mod_kw = OmegaConf.to_container(cfg.modulation, resolve=True)
    return {mode: Modulation(mode=mode, **mod_kw) for mode in modes}


def controllers(cfg: DictConfig, task: ScoopingTask, robot: Any, modulations: dict[str, Modulation] | None = None,
                arrival: Arrival | None = None) -> dict[str, Any]:
    """One controller per mode; ``modulations`` (mode -> :class:`Modulation`) and ``arrival`` are
    :func:`check_config`'s (None: built from ``cfg.modes``, ``cfg.modulation`` and ``cfg.skills``)."""
    modulations = modulations_of(cfg, cfg.modes) if modulations is None else modulations
    arrival = instantiate(cfg.skills).arrival if arrival is None else arrival
    return {mode: controller_for(task, robot, modulation, arrival=arrival,
                                 options=OmegaConf.to_container(cfg.controller, resolve=True))
            for mode, modulation in modulations.items()}  # fmt: skip


def run_batches(cfg: DictConfig, task: ScoopingTask, ctl: Any, robot: Any, q0: torch.Tensor, plan: list | None,
                bar: Any, crit: SuccessCriteria) -> tuple[list[dict], list[TrialBatch]]:
    """Trials in batches of ``batch_size`` (rows carry the global trial index), judged by ``crit``."""
    rows, batches = [], []
    n = q0.shape[0]
    step = int(cfg.batch_size)
    for a in range(0, n, step):
        part = None if plan is None else plan[a : a + step]
        res = run_trials(task, ctl, robot.plant, q0[a : a + step], disturbances=part, budget_s=float(cfg.budget_s),
                         jump_seed=derive_seed(cfg.experiment, "jumps", cfg.seed, a), criteria=crit,
                         away=float(cfg.away), progress=bar, workers=int(cfg.get("workers", 1)))  # fmt: skip
        for r in res.rows:
            r["trial"] = r["trial"] + a
        rows.extend(res.rows)
        batches.append(res)
    return rows, batches


# ---------------------------------------------------------------------------------------------- summary
def summary(table: pd.DataFrame) -> pd.DataFrame:
    """Success rate and Wilson 95 % interval per (kind of run, mode, stage, disturbance, label), with totals;
    ``disturbance = any`` counts the trials that were disturbed (a jump without a valid landing point is skipped and
    its trial, ``disturbance = none``, stays undisturbed).

    ``rate`` is the success rate of the issue's criterion: any contact with the can or cup walls or the table fails
    a run, also one that a force pulse shoved the arm into. ``lenient_rate`` (with ``lenient_lo``/``lenient_hi``) is
    a diagnostic only: the rate that would excuse contacts begun during a pulse or ``criteria.push_grace`` s after it
    (``lenient_success``); the gap between the two is the share of runs that a push itself drove into an object.

    A table stored before the strict rule (no ``lenient_success`` column: its ``success`` excused those contacts)
    is read as such: its ``success`` becomes ``lenient_success`` and a run with ``push_contacts`` fails."""
    if "lenient_success" not in table.columns:
        table = table.assign(lenient_success=table.success, success=table.success & (table.push_contacts == ""))
    out = []

    def add(frame: pd.DataFrame, **keys: Any) -> None:
        n, k = len(frame), int(frame.success.sum())
        lo, hi = wilson_interval(k, n)
        kl = int(frame.lenient_success.sum())
        llo, lhi = wilson_interval(kl, n)
        reasons = frame.loc[~frame.success, "reason"].str.replace(r" at [0-9.]+ s", "", regex=True).value_counts()
        out.append({**keys, "n": n, "successes": k, "rate": k / n if n else math.nan, "wilson_lo": lo,
                    "wilson_hi": hi, "lenient_rate": kl / n if n else math.nan, "lenient_lo": llo, "lenient_hi": lhi,
                    "failures": "; ".join(f"{r} x{c}" for r, c in reasons.items())})  # fmt: skip

    for (kind, mode), f in table.groupby(["kind", "method"], sort=False):
        add(f, kind=kind, method=mode, stage="all", disturbance="all", label="all")
        if kind != "disturbed":
            continue
        fired = f[f.disturbance != "none"]  # without the trials whose jump found no valid landing point
        add(fired, kind=kind, method=mode, stage="all", disturbance="any", label="all")
        for stage, g in fired.groupby("stage", sort=True):
            add(g, kind=kind, method=mode, stage=stage, disturbance="any", label="all")
        for (stage, dist, label), g in f.groupby(["stage", "disturbance", "label"], sort=True):
            add(g, kind=kind, method=mode, stage=stage, disturbance=dist, label=label)
        for stage, g in f.groupby("stage", sort=True):
            add(g, kind=kind, method=mode, stage=stage, disturbance="all", label="all")
        for (dist, label), g in f.groupby(["disturbance", "label"], sort=True):
            add(g, kind=kind, method=mode, stage="all", disturbance=dist, label=label)
    return pd.DataFrame(out)


# ---------------------------------------------------------------------------------------------- figures
# What the figures draw is gathered once (figure_data), stored under libraries/scooping/ by the publish preset
# (store_figure_data) and drawn by draw_figures, which experiments/figures.py calls on the stored copy.
_DRAWN_MODES = ("full", "none")  # Fig. 15 rows
_FRAME_TITLE = "MuJoCo frame: start configuration 0"


def _path(tip: torch.Tensor, length: Any) -> torch.Tensor:
    """(T, 3) float32 valid part of a logged tip path (m): what the figures draw, stored small."""
    return tip[: int(length)].detach().cpu().to(torch.float32).clone()


def figure_data(task: ScoopingTask, start_batches: dict[str, TrialBatch], dist_batches: dict[str, list[TrialBatch]],
                table: pd.DataFrame, n_per_stage: int, q_frame: torch.Tensor) -> dict[str, Any]:
    """Everything Figs 13-15 and the frame draw, as plain tensors, numbers and strings.

    Returns:
        ``demos`` the smoothed demonstration (1, T, 3) m; ``segmentation``; ``step_stage`` (M,) long;
        ``attractors`` (M, 3) m; ``starts``: the mode-``full`` start runs (``tip`` list of (T_i, 3), ``success``)
        or None; ``disturbed``: mode -> stage name -> up to ``n_per_stage`` drawn trials (``trial``, ``tip``,
        ``success``, ``disturbance`` kind, ``sample`` where it starts, -1 none) or None; ``q_frame`` (7,) rad.
    """
    starts = None
    if "full" in start_batches:
        res = start_batches["full"]
        starts = {"tip": [_path(res.tip[i], res.lengths[i]) for i in range(res.tip.shape[0])],
                  "success": [bool(r["success"]) for r in res.rows]}  # fmt: skip
    disturbed = None
    if any(dist_batches.get(m) for m in _DRAWN_MODES):
        disturbed = {}
        for mode in (m for m in _DRAWN_MODES if dist_batches.get(m)):
            flat = [(b, i) for b in dist_batches[mode] for i in range(b.tip.shape[0])]
            sub = table[(table.method == mode) & (table.kind == "disturbed")].reset_index(drop=True)
            disturbed[mode] = {}
            for stage in STAGE_NAMES:
                picks = sub.index[(sub.stage == stage) & (sub.disturbance != "none")][:n_per_stage]
                drawn = []
                for j in picks:
                    b, i = flat[j]
                    drawn.append({"trial": int(sub.trial[j]), "tip": _path(b.tip[i], b.lengths[i]),
                                  "success": bool(sub.success[j]), "disturbance": str(sub.disturbance[j]),
                                  "sample": int(b.disturbance_sample[i])})  # fmt: skip
                disturbed[mode][stage] = drawn
    return {"demos": task.demos, "segmentation": task.segmentation, "step_stage": task.step_stage.detach().cpu(),
            "attractors": task.library.attractors.detach().cpu(), "starts": starts, "disturbed": disturbed,
            "q_frame": q_frame.detach().cpu().double()}  # fmt: skip


def store_figure_data(data: dict[str, Any], where: Path) -> list[Path]:
    """``where``/{demos,segmentation,trials}.pt of :func:`figure_data` (checksummed)."""
    where.mkdir(parents=True, exist_ok=True)
    return [save_demos(data["demos"], where / "demos.pt", velocities=False, step_stage=data["step_stage"],
                       attractors=data["attractors"]),
            data["segmentation"].save(where / "segmentation.pt"),
            save_state({k: data[k] for k in ("starts", "disturbed", "q_frame")}, where / "trials.pt")]  # fmt: skip


def load_figure_data(where: Path) -> dict[str, Any]:
    """:func:`figure_data` from the files of :func:`store_figure_data` (StoreError naming a missing or damaged one)."""
    demos, extra = load_demos(where / "demos.pt")
    seg_path = where / "segmentation.pt"
    if not seg_path.is_file():
        raise StoreError(f"stored file {seg_path} is missing (run the publish preset that writes it: make results)")
    return {"demos": demos, "segmentation": Segmentation.load(seg_path), "step_stage": extra["step_stage"],
            "attractors": extra["attractors"], **load_state(where / "trials.pt")}  # fmt: skip


def _vessels(ax: Any, scene: Any) -> None:
    th = np.linspace(0, 2 * np.pi, 60)
    for v, colour in ((scene.can, "0.4"), (scene.cup, "tab:brown")):
        base = scene.table_top + v.wall
        for z in (base, base + v.height):
            ax.plot(v.center[0] + v.radius * np.cos(th), v.center[1] + v.radius * np.sin(th), z, color=colour, lw=0.8)
        for a in th[::10]:
            x, y = v.center[0] + v.radius * np.cos(a), v.center[1] + v.radius * np.sin(a)
            ax.plot([x, x], [y, y], [base, base + v.height], color=colour, lw=0.5)
    can = scene.can
    surf = scene.table_top + can.wall + can.fill
    ax.plot(can.center[0] + can.radius * np.cos(th), can.center[1] + can.radius * np.sin(th), surf, color="goldenrod",
            lw=1.2)  # fmt: skip


def _axes3d(title: str) -> tuple[Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(6.4, 5.2))
    ax = fig.add_subplot(projection="3d")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(title, fontsize=10)
    ax.view_init(elev=28, azim=-150)
    return fig, ax


def _demo_path(data: dict[str, Any]) -> np.ndarray:
    demos = data["demos"]
    return demos.positions[0, : int(demos.lengths[0])].numpy()


def fig13_segmentation(data: dict[str, Any], scene: Any, path: Path) -> Path:
    """Fig. 13: the smoothed demonstration coloured by BP-GM-HMM step, with the attractors."""
    n_steps = int(data["step_stage"].shape[0])
    fig, ax = _axes3d(f"Fig. 13: demonstration segmented into {n_steps} steps (BP-GM-HMM, no prior)")
    x = _demo_path(data)
    lab = data["segmentation"].labels[0][: x.shape[0]].numpy()
    cmap = __import__("matplotlib").colormaps["tab10"]
    for m in range(n_steps):
        sel = lab == m
        ax.scatter(x[sel, 0], x[sel, 1], x[sel, 2], s=2, color=cmap(m),
                   label=f"step {m} ({STAGE_NAMES[int(data['step_stage'][m])]})")  # fmt: skip
    g = data["attractors"].numpy()
    ax.scatter(g[:, 0], g[:, 1], g[:, 2], marker="*", s=80, color="k", label="attractors $g_m$")
    _vessels(ax, scene)
    ax.legend(fontsize=7, loc="upper left")
    return _save(fig, path)


def _save(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    def write(p: Path) -> None:
        fig.savefig(p, dpi=130, bbox_inches="tight", format="png")

    out = atomic_write(path, write)
    plt.close(fig)
    return out


def fig14_starts(data: dict[str, Any], scene: Any, path: Path) -> Path:
    """Fig. 14: the mode-``full`` runs from the start configurations beside the demonstration."""
    fig, ax = _axes3d("Fig. 14: generalisation from 7 start configurations (MuJoCo, mode full)")
    x = _demo_path(data)
    ax.plot(x[:, 0], x[:, 1], x[:, 2], color="k", lw=1.5, ls="--", label="demonstration")
    starts = data["starts"]
    for i, (tip, ok) in enumerate(zip(starts["tip"], starts["success"])):
        p = tip.numpy()
        ax.plot(p[:, 0], p[:, 1], p[:, 2], lw=1.0, color="tab:blue" if ok else "tab:red",
                label=("success" if ok else "failure") if i == 0 else None)  # fmt: skip
        ax.scatter(*p[0], color="tab:green", s=15)
    _vessels(ax, scene)
    ax.legend(fontsize=7, loc="upper left")
    return _save(fig, path)


def fig15_disturbed(data: dict[str, Any], scene: Any, path: Path) -> Path:
    """Fig. 15: per drawn mode and stage, the stored disturbed trials with where each disturbance starts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drawn = data["disturbed"]
    modes = [m for m in _DRAWN_MODES if m in drawn]
    fig = plt.figure(figsize=(5.0 * len(STAGE_NAMES), 4.4 * len(modes)))
    x = _demo_path(data)
    for r, mode in enumerate(modes):
        for c, stage in enumerate(STAGE_NAMES):
            ax = fig.add_subplot(len(modes), len(STAGE_NAMES), r * len(STAGE_NAMES) + c + 1, projection="3d")
            ax.set_title(f"{mode}: disturbed in the {stage} stage", fontsize=9)
            ax.view_init(elev=28, azim=-150)
            ax.plot(x[:, 0], x[:, 1], x[:, 2], color="k", lw=1.2, ls="--")
            for trial in drawn[mode][stage]:
                p = trial["tip"].numpy()
                ax.plot(p[:, 0], p[:, 1], p[:, 2], lw=0.9, color="tab:blue" if trial["success"] else "tab:red")
                k = int(trial["sample"])
                if k >= 0:
                    ax.scatter(*p[k], marker="x", color="tab:orange" if trial["disturbance"] == "force" else "m", s=25)
            _vessels(ax, scene)
    fig.suptitle("Fig. 15: disturbed trials (orange x: a force pulse starts, magenta x: a position jump lands; "
                 "red: failed)", fontsize=10)  # fmt: skip
    return _save(fig, path)


_RENDER = """
import sys, numpy as np, mujoco
xml, qfile, out = sys.argv[1:4]
m = mujoco.MjModel.from_xml_path(xml)
d = mujoco.MjData(m)
z = np.load(qfile)
d.qpos[z["adr"]] = z["q"]
mujoco.mj_forward(m, d)
cam = mujoco.MjvCamera()
cam.lookat[:] = [0.55, 0.6, -0.15]
cam.distance, cam.azimuth, cam.elevation = 1.7, -140.0, -25.0
with mujoco.Renderer(m, 480, 640) as r:
    r.update_scene(d, camera=cam)
    np.save(out, r.render())
"""


def render_frame(robot: Any, q: torch.Tensor, path: Path) -> Path | None:
    """One offscreen MuJoCo frame of the arm at ``q`` (7,) rad, rendered in a subprocess with ``MUJOCO_GL=egl``
    (the GL backend is fixed when mujoco is imported); None, with a log message, when no GL context is available."""
    import os
    import subprocess
    import sys
    import tempfile

    plant = robot.plant
    with tempfile.TemporaryDirectory() as tmp:
        xml, qfile, out = Path(tmp, "model.xml"), Path(tmp, "q.npz"), Path(tmp, "frame.npy")
        xml.write_text(plant.xml)
        np.savez(qfile, q=q.double().numpy(), adr=plant.qpos_adr)
        env = {**os.environ, "MUJOCO_GL": os.environ.get("LFD_MUJOCO_GL", "egl")}
        proc = subprocess.run([sys.executable, "-c", _RENDER, str(xml), str(qfile), str(out)], env=env,
                              capture_output=True, text=True, timeout=120)  # fmt: skip
        if proc.returncode != 0 or not out.exists():
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
            log.warning("MuJoCo offscreen rendering unavailable here, frame skipped: %s", tail[0])
            return None
        img = np.load(out)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(6.4, 4.8))
    plt.imshow(img)
    plt.axis("off")
    plt.title(_FRAME_TITLE, fontsize=9)
    return _save(fig, path)


def draw_figures(data: dict[str, Any], robot: Any, fig_dir: Path, name: str, *, render: bool) -> list[Path]:
    """Figs 13-15 and (``render``) the MuJoCo frame of :func:`figure_data` as ``fig_dir``/``name``_*.png; the
    figures whose data is absent (no ``full`` mode, no disturbed trials) and a frame that cannot be rendered are
    skipped."""
    scene = robot.plant.scene
    written = [fig13_segmentation(data, scene, fig_dir / f"{name}_segmentation.png")]
    if data["starts"] is not None:
        written.append(fig14_starts(data, scene, fig_dir / f"{name}_starts.png"))
    if data["disturbed"] is not None:
        written.append(fig15_disturbed(data, scene, fig_dir / f"{name}_disturbed.png"))
    if render:
        frame = render_frame(robot, data["q_frame"], fig_dir / f"{name}_frame.png")
        if frame is not None:
            written.append(frame)
    return written


def markdown(table: pd.DataFrame, cfg: Any, n_steps: int, step_stage: list[int], timings: dict[str, float]) -> str:
    """``summary.md`` / ``scooping.md``: a header line (seeds, steps found, wall time per mode in s) and the
    :func:`summary` of ``table``."""
    head = (f"Baxter sugar scooping (experiments/scooping.py, seed {cfg.seed}, demo_seed {cfg.demo_seed}): "
            f"{n_steps} steps found; stages of the steps {list(step_stage)}; "
            f"wall time per mode: " + ", ".join(f"{k} {v:.0f}" for k, v in timings.items()) + "\n\n")  # fmt: skip
    return head + summary(table).to_markdown(index=False, floatfmt=".3g") + "\n"


def store_config(cfg: DictConfig, timings: dict[str, float], n_steps: int, step_stage: list[int],
                 where: Path) -> Path:
    """``where``/config.json: the run's configuration and, under ``run``, what the markdown header reports:
    ``wall_time_s`` as [name, s] pairs in the header's order (the JSON keys are sorted), ``n_steps``, ``step_stage``."""
    data = OmegaConf.to_container(cfg, resolve=True)
    data["run"] = {"wall_time_s": [[k, float(v)] for k, v in timings.items()], "n_steps": int(n_steps),
                   "step_stage": [int(s) for s in step_stage]}  # fmt: skip
    return save_config(data, where / "config.json", drop=("hydra", "paths", "out_dir"))


# ---------------------------------------------------------------------------------------------- run
def check_config(cfg: DictConfig) -> dict[str, Any]:
    """Check every setting before anything is built or fitted (InvalidArgumentError / UnknownNameError naming the
    key); returns the checked objects the run uses: ``modulations`` (mode -> :class:`Modulation`,
    :func:`modulations_of`), ``settings`` (:class:`~lfd_torch.skills.SkillSettings`) and ``criteria``
    (:class:`SuccessCriteria`)."""
    positive_int(cfg, "threads")
    modes = name_list(cfg, "modes", MODULATION_MODES)
    positive_int(cfg, "starts.n")
    nonnegative_float(cfg, "starts.radius")
    nonnegative_float(cfg, "starts.height")
    positive_float(cfg, "budget_s")
    nonnegative_int(cfg, "n_disturbed")
    positive_int(cfg, "batch_size")
    if "workers" in cfg:
        positive_int(cfg, "workers")
    nonnegative_float(cfg, "away")
    nonnegative_int(cfg, "n_figure_trials")
    check_entropy_quantile(cfg)
    modulations = modulations_of(cfg, modes)
    settings = instantiate(cfg.skills)
    criteria = SuccessCriteria(**OmegaConf.to_container(cfg.criteria, resolve=True))
    return {"modulations": modulations, "settings": settings, "criteria": criteria}


def run(cfg: DictConfig) -> dict[str, Any]:
    checked = check_config(cfg)
    torch.set_num_threads(int(cfg.threads))
    job = prepare_job(cfg)
    out_dir, manifest = job.out_dir, job.manifest
    # the plan is drawn before learning so that a bad `disturbances` setting fails first (its own generator: the
    # order changes nothing)
    g = torch.Generator().manual_seed(derive_seed(cfg.experiment, "disturbances", cfg.seed))
    plan = plan_disturbances(int(cfg.n_disturbed), g, **OmegaConf.to_container(cfg.disturbances, resolve=True))
    robot = instantiate(cfg.robot, _convert_="all")
    task = learn(cfg, robot, checked["settings"])
    ctls = controllers(cfg, task, robot, checked["modulations"], checked["settings"].arrival)
    crit = checked["criteria"]
    q_starts = start_configurations(task, robot.arm, int(cfg.starts.n), radius=float(cfg.starts.radius),
                                    height=float(cfg.starts.height))  # fmt: skip
    q_dist = q_starts[torch.arange(len(plan)) % q_starts.shape[0]]
    rows: list[dict[str, Any]] = []
    start_batches: dict[str, TrialBatch] = {}
    dist_batches: dict[str, list[TrialBatch]] = {}
    timings: dict[str, float] = {}
    ticks = int(round(float(cfg.budget_s) / robot.plant.control_period)) + 1
    n_batches = math.ceil(len(plan) / int(cfg.batch_size)) if plan else 0
    total = len(cfg.modes) * (1 + n_batches) * ticks
    with tqdm(total=total, desc="scooping", unit="tick", disable=not cfg.get("progress", True)) as bar:
        for mode, ctl in ctls.items():
            t0 = time.perf_counter()
            r_start, b_start = run_batches(cfg, task, ctl, robot, q_starts, None, bar, crit)
            t1 = time.perf_counter()
            r_dist, b_dist = run_batches(cfg, task, ctl, robot, q_dist, plan, bar, crit) if plan else ([], [])
            t2 = time.perf_counter()
            timings[f"start_{mode}_s"], timings[f"disturbed_{mode}_s"] = t1 - t0, t2 - t1
            start_batches[mode] = b_start[0]
            dist_batches[mode] = b_dist
            for kind, part in (("start", r_start), ("disturbed", r_dist)):
                for r in part:
                    rows.append({"experiment": cfg.experiment, "shape": "baxter_scooping", "method": mode, "fold": 0,
                                 "seed": int(cfg.seed), "trajectory": f"{kind}_{r['trial']:04d}", "kind": kind,
                                 "n_steps": task.n_steps, **r})  # fmt: skip
            log.info("%s: starts %d/%d, disturbed %d/%d (%.0f s, %.0f s)", mode, sum(r["success"] for r in r_start),
                     len(r_start), sum(r["success"] for r in r_dist), len(r_dist), t1 - t0, t2 - t1)  # fmt: skip
    table = pd.DataFrame(rows)
    summ = summary(table)
    written: list[Path] = [write_table(table, out_dir / RESULTS_NAME, manifest=manifest)]
    md = markdown(table, cfg, task.n_steps, task.step_stage.tolist(), timings)
    written.append(atomic_write(out_dir / "summary.md", lambda p: p.write_text(md)))
    if cfg.publish:
        tables = Path(cfg.paths.tables)
        written.append(write_table(table, tables / f"{cfg.experiment}.parquet", manifest=manifest))
        written.append(atomic_write(tables / f"{cfg.experiment}.md", lambda p: p.write_text(md)))
    if cfg.figures or cfg.publish:
        data = figure_data(task, start_batches, dist_batches, table, int(cfg.n_figure_trials), q_starts[0])
        if cfg.publish:
            where = Path(cfg.paths.libraries) / str(cfg.experiment)
            written.extend(store_figure_data(data, where))
            written.append(store_config(cfg, timings, task.n_steps, task.step_stage.tolist(), where))
        fig_dir = Path(cfg.paths.figures) if cfg.publish else out_dir / "figures"
        written.extend(draw_figures(data, robot, fig_dir, str(cfg.experiment), render=bool(cfg.render)))
    log.info("summary:\n%s", md)
    return {"table": table, "summary": summ, "task": task, "timings": timings, "written": written}


@hydra.main(config_path="../conf", config_name="scooping", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with staged_results(cfg):  # published outputs replace the old ones together, only when the run succeeds
        result = run(cfg)
    print(result["summary"].to_string(index=False))


if __name__ == "__main__":
    main()
