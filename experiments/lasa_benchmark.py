"""LASA benchmark in the paper's protocol (Sec. V-A, Fig. 9): train on ONE demonstration, test on the other six.

The training demonstration is the fold (0..6, a sweep axis). Methods are the product segmentation {none,
bp_gm_hmm} x primitive {seds, lpvds} x modulation {none, full}; the library of a (segmentation, primitive) pair is
learned once and shared by its modulation variants (a modulation setting never refits), and is saved in the job
folder. All demonstrations are sub-sampled by 2 (``subsample``) as in the LPV-DS literature.

Metrics of every (shape, fold, method, demonstration), train and test:

* E1 (mean velocity error, mm/s) and E2 (mean |1 - cos|) of the step velocity M(x) f_m(x) at the demonstration's
  states, as the paper defines them (the modulated primitive; the engine's arrival shaping, rate floor and speed
  cap, is not part of it). The step m of each sample comes from :meth:`SkillEngine.assign_steps`: monotone in time,
  the left-to-right Viterbi path over the route's steps with emission log p(x | A_m);
* E3 (mean swept area, mm^2) between the demonstration and the engine's rollout from its start, the rollout sampled
  at the demonstration's time stamps (linear interpolation; after the rollout stops it stays at its end point);
* DTWD (mm) between the rollout and the demonstration, final-point error (mm) and whether the task finished.

One row per (shape, fold, method, seed, demo) goes to ``results.parquet`` in the job folder, with ``summary.md`` /
``summary.csv`` (mean and std of every metric per method, train and test) and ``violins.png`` (E1, E2, E3 by
method, train and test halves: paper Fig. 9); ``publish=true`` (not in a multirun) also writes them into
``paths.tables`` / ``paths.figures``. A sweep is merged with ``python -m lfd_torch.store.collect``.

    python experiments/lasa_benchmark.py                                   # quick: a few shapes, fold 0
    python experiments/lasa_benchmark.py -m fold=0,1,2,3,4,5,6             # folds (joblib launcher)
    python experiments/lasa_benchmark.py +experiment=lasa_benchmark_paper  # 30 shapes, fold 0, multirun

Resume: a job whose folder already holds its ``results.parquet`` from the same configuration (config hash and seed)
is skipped (``resume=true``, the default), so re-running a killed sweep with the same ``hydra.sweep.dir`` only runs
the jobs that had not finished; the parquet is written atomically as a job's last act, so a killed job leaves none.
``publish`` is not part of the config hash: ``publish=true`` in a finished job's folder publishes its stored rows.

Every setting is checked before anything is fitted (:func:`check_config`); a configuration error raised inside a fit
(an out-of-range fitter or segmenter setting) is raised, while a genuine fit failure (solver, certificate, a
demonstration a step cannot be fitted on) is recorded as rows with NaN metrics and the error in ``status``.
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
from lfd_torch.errors import InvalidArgumentError, LfdError
from lfd_torch.metrics import cosine_dissimilarity, dtw_distance, swept_area, velocity_error
from lfd_torch.modulation import MODULATION_MODES, Modulation
from lfd_torch.preprocess import subsample
from lfd_torch.skills import SkillEngine, SkillLibrary
from lfd_torch.store import atomic_write, finished_part, prepare_job, read_manifest, staged_results, write_table
from lfd_torch.store.job import RESULTS_NAME
from lfd_torch.utils import check_int, derive_seed
from lfd_torch.viz import violin_grid
from lfd_torch.store.config_checks import (
    check_entropy_quantile,
    get,
    is_config_error,
    name_list,
    positive_int,
    rollout_steps,
)

log = logging.getLogger(__name__)

METRICS = ("E1", "E2", "E3", "DTWD", "final_error")


def step_velocities(engine: SkillEngine, demos: Demos) -> torch.Tensor:
    """M(x) f_m(x) at every demonstration sample, m from :meth:`SkillEngine.assign_steps` (module docstring)."""
    _, steps = engine.assign_steps(demos.positions, demos.mask)
    B, T, d = demos.positions.shape
    v, _ = engine.velocity(demos.positions.reshape(-1, d), steps.reshape(-1),
                           torch.zeros(B * T, dtype=torch.bool), shaping=False)  # fmt: skip
    return v.view(B, T, d)


def evaluate(engine: SkillEngine, demos: Demos, dt: float, budget_s: float) -> dict[str, torch.Tensor]:
    """Per-demonstration metrics (module docstring): (B,) tensors."""
    mask = demos.mask
    v = step_velocities(engine, demos)
    out = engine.rollout(demos.start_points, dt=dt, n_steps=int(round(budget_s / dt)))
    res = out.result
    x_on_demo = res.positions_at(demos.times - demos.times[:, :1])  # the rollout at the demo's time stamps
    final = res.positions[torch.arange(res.n_starts), res.lengths - 1]
    return {
        "E1": velocity_error(v, demos.velocities, mask),
        "E2": cosine_dissimilarity(v, demos.velocities, mask),
        "E3": swept_area(x_on_demo, demos.positions, mask),
        "DTWD": dtw_distance(res.positions, demos.positions, res.lengths, demos.lengths),
        "final_error": torch.linalg.vector_norm(final - demos.attractor.to(final), dim=-1),
        "reached": out.done,
        "time_s": (res.lengths - 1).to(demos.dtype) * dt,
    }


def fitter(primitive_cfg: DictConfig) -> Any:
    return instantiate(primitive_cfg)


def check_config(cfg: DictConfig) -> dict[str, Any]:
    """Check every setting before anything is fitted (InvalidArgumentError / UnknownNameError naming the key);
    returns the checked values the run uses: ``shapes``, ``segmentations``, ``primitives``, ``modulations`` (mode
    -> :class:`Modulation`), ``settings`` (:class:`~lfd_torch.skills.SkillSettings`)."""
    check_int(cfg.fold, "fold", low=0)
    shapes = name_list(cfg, "shapes", LASA_NAMES, allow_all=True)
    segmenters, fitters = get(cfg, "segmenters"), get(cfg, "fitters")
    segmentations = name_list(cfg, "segmentations", list(segmenters.keys()))
    primitives = name_list(cfg, "primitives", list(fitters.keys()))
    modes = name_list(cfg, "modulations", MODULATION_MODES)
    positive_int(cfg, "subsample")
    rollout_steps(cfg, "dt", "budget_s")
    check_entropy_quantile(cfg)
    mod_kw = {k: v for k, v in OmegaConf.to_container(cfg.modulation, resolve=True).items() if k not in ("_target_", "mode")}
    modulations = {mode: Modulation(mode=mode, **mod_kw) for mode in modes}
    return {"shapes": shapes, "segmentations": segmentations, "primitives": primitives, "modulations": modulations,
            "settings": instantiate(cfg.skills)}  # fmt: skip


def run(cfg: DictConfig) -> dict[str, Any]:
    checked = check_config(cfg)
    job = prepare_job(cfg)
    out_dir, manifest = job.out_dir, job.manifest
    shapes = checked["shapes"]
    done = finished_part(out_dir / RESULTS_NAME, manifest) if cfg.resume else None
    if done is not None:  # a re-run sweep (same hydra.sweep.dir) skips its finished jobs
        log.info("%s already holds this job's rows (config %s); skipped", out_dir, manifest["config_hash"])
        summ = summary(done)
        written: list[Path] = []
        if cfg.get("publish"):  # publish is not in the config hash: publish the finished rows as they are
            stored = read_manifest(out_dir / RESULTS_NAME) or manifest
            written = publish(done, summ, cfg, stored)
            log.info("published the stored rows of %s", out_dir)
        return {"table": done, "summary": summ, "written": written, "skipped": True}
    settings = checked["settings"]
    arrival = settings.arrival
    lib_kw = settings.learn_kwargs
    rows: list[dict[str, Any]] = []
    for shape in tqdm(shapes, desc="lasa_benchmark", unit="shape", disable=not cfg.progress):
        demos = subsample(load_lasa(shape), int(cfg.subsample), keep_last=False)
        fold = int(cfg.fold)
        if fold >= demos.n_demos:
            raise InvalidArgumentError(f"fold (the training demonstration) must be in 0..{demos.n_demos - 1} for "
                                       f"{shape}, got {fold}")  # fmt: skip
        test_idx = [i for i in range(demos.n_demos) if i != fold]
        splits = {"train": ([fold], demos[[fold]]), "test": (test_idx, demos[test_idx])}
        for seg_name in checked["segmentations"]:
            for prim_name in checked["primitives"]:
                key = f"{seg_name}+{prim_name}"
                seed = derive_seed(cfg.experiment, shape, fold, key, cfg.seed)
                g = torch.Generator().manual_seed(seed)
                t0 = time.perf_counter()
                try:
                    segmenter = instantiate(cfg.segmenters[seg_name])
                    seg = segmenter(splits["train"][1], generator=g)
                    lib = SkillLibrary.learn(splits["train"][1], seg, primitive=fitter(cfg.fitters[prim_name]),
                                             generator=g, **lib_kw)  # fmt: skip
                except LfdError as exc:
                    if is_config_error(exc):  # a bad setting, not a failed fit: no row hides it
                        raise
                    log.error("%s fold %d %s failed: %s", shape, fold, key, exc)
                    for mod_name in checked["modulations"]:
                        for split, (idx, _) in splits.items():
                            for i in idx:
                                rows.append({"experiment": cfg.experiment, "shape": shape,
                                             "method": f"{key}+{mod_name}" + (f"@{cfg.tag}" if cfg.get("tag") else ""),
                                             "fold": fold, "seed": int(cfg.seed), "trajectory": int(i), "split": split,
                                             "status": f"{type(exc).__name__}: {exc}", **{m: math.nan for m in METRICS}})  # fmt: skip
                    continue
                fit_s = time.perf_counter() - t0
                if cfg.save_libraries:
                    lib.save(out_dir / "libraries" / f"{shape}_fold{fold}_{key}")
                for mod_name, modulation in checked["modulations"].items():
                    engine = SkillEngine(lib, modulation, arrival)
                    method = f"{key}+{mod_name}" + (f"@{cfg.tag}" if cfg.get("tag") else "")
                    for split, (idx, part) in splits.items():
                        values = evaluate(engine, part, float(cfg.dt), float(cfg.budget_s))
                        for b, i in enumerate(idx):
                            rows.append({
                                "experiment": cfg.experiment, "shape": shape, "method": method, "fold": fold,
                                "seed": int(cfg.seed), "trajectory": int(i), "split": split, "status": "ok",
                                "segmentation": seg_name, "primitive": prim_name, "modulation": str(mod_name),
                                **{m: float(values[m][b]) for m in METRICS}, "reached": bool(values["reached"][b]),
                                "time_s": float(values["time_s"][b]), "n_steps": lib.n_steps, "fit_s": fit_s,
                                "stability_passed": bool(lib.stability["passed"]) if lib.stability else None,
                            })  # fmt: skip
                log.info("%s fold %d %s: %d steps, %.1f s", shape, fold, key, lib.n_steps, fit_s)
    table = pd.DataFrame(rows)
    summ = summary(table)
    written = write_summary(summ, out_dir, "summary") + write_violins(table, out_dir / "violins.png")
    # the rows last: their presence marks the job as finished (resume)
    written.append(write_table(table, out_dir / RESULTS_NAME, manifest=manifest))
    if cfg.get("publish"):
        written += publish(table, summ, cfg, manifest)
    log.info("summary:\n%s", summ.to_string(index=False))
    return {"table": table, "summary": summ, "written": written, "skipped": False}


def publish(table: pd.DataFrame, summ: pd.DataFrame, cfg: DictConfig, manifest: dict[str, Any]) -> list[Path]:
    """The rows, summary and violins into ``paths.tables`` / ``paths.figures`` (``publish=true``)."""
    written = [write_table(table, Path(cfg.paths.tables) / f"{cfg.experiment}.parquet", manifest=manifest)]
    written += write_summary(summ, Path(cfg.paths.tables), f"{cfg.experiment}_summary")
    written += write_violins(table, Path(cfg.paths.figures) / f"{cfg.experiment}_violins.png")
    return written


def summary(table: pd.DataFrame) -> pd.DataFrame:
    """Mean and std of every metric per (method, split), plus the share of finished rollouts and of failed fits."""
    ok = table[table.status == "ok"]
    if not len(ok):
        return pd.DataFrame()
    agg = ok.groupby(["method", "split"], sort=False)[list(METRICS)].agg(["mean", "std"])
    agg.columns = [f"{m}_{stat}" for m, stat in agg.columns]
    agg["reached"] = ok.groupby(["method", "split"], sort=False)["reached"].mean()
    agg["rows"] = ok.groupby(["method", "split"], sort=False).size()
    agg["failed_rows"] = table[table.status != "ok"].groupby(["method", "split"]).size().reindex(agg.index).fillna(0)
    return agg.reset_index()


def write_summary(summ: pd.DataFrame, where: Path, name: str) -> list[Path]:
    """``{name}.md`` and ``{name}.csv`` of the summary under ``where``."""
    if not len(summ):
        return []
    md = summ.to_markdown(index=False, floatfmt=".3g")
    return [atomic_write(where / f"{name}.md", lambda p: p.write_text(md + "\n")),
            atomic_write(where / f"{name}.csv", lambda p: summ.to_csv(p, index=False))]  # fmt: skip


def write_violins(table: pd.DataFrame, path: Path) -> list[Path]:
    """E1, E2, E3 by method, train and test halves (paper Fig. 9), log scale."""
    ok = table[table.status == "ok"]
    if not len(ok):
        return []
    violin_grid(ok, ["E1", "E2", "E3"], by="method", hue="split", path=path,
                titles=["E1 (mm/s)", "E2 (1 - cos)", "E3 (mm^2)"], panel_size=(5.5, 3.8), log_scale=True)  # fmt: skip
    return [path]


@hydra.main(config_path="../conf", config_name="lasa_benchmark", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with staged_results(cfg):  # published outputs replace the old ones together, only when the run succeeds
        result = run(cfg)
    print(result["summary"].to_string(index=False, float_format=lambda v: f"{v:.3g}"))


if __name__ == "__main__":
    main()
