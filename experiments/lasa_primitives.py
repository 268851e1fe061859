"""Stable primitives on LASA: SEDS vs LPV-DS (QLF) vs LPV-DS (P-QLF) (paper Sec. V-A, Fig. 9 without modulation).

Per shape (``data.shape``): train on demonstrations ``train_demos`` (default 0-3), test on ``test_demos`` (4-6),
every ``subsample``-th sample. For each method in ``cfg.methods`` (a ``ds`` config each), fit once with a generator
seeded from (experiment, shape, seed) -- the same for every method, so methods that share a GMM fitter share its
clustering -- then for every train and test demonstration record

    E1    mean_t ||x_dot_ref - f(x_ref)||                 (mm/s; the paper's "RMSE")
    RMSE  sqrt(mean_t ||x_dot_ref - f(x_ref)||^2)          (mm/s)
    E2    mean_t |1 - cos(x_dot_ref, f(x_ref))|            (dimensionless)
    DTWD  DTW distance between the reference path and the Euler rollout (dt = rollout.dt) from its start (mm,
          summed along the warping path; the rollout stops within rollout.position_tol of the attractor)

plus K, the fit time, the certificate margin and whether the rollout converged. One row per (method, demo) goes to
``results.parquet`` in the job folder (lfd_torch.store format; ``split`` says train/test, ``fold`` is 0). A method
that raises a typed error (solver, certificate, a demonstration a step cannot be fitted on) is recorded with NaN
metrics and the error in ``status``; a bad setting (InvalidArgumentError, UnknownNameError) is raised instead.

    python experiments/lasa_primitives.py data.shape=Sshape
    python experiments/lasa_primitives.py -m data.shape=Angle,Sshape,Snake
    python experiments/lasa_primitives.py +experiment=lasa_primitives_paper
"""

from __future__ import annotations

import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import hydra
import pandas as pd
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig

from lfd_torch.data import Demos
from lfd_torch.ds import StablePrimitive
from lfd_torch.errors import InvalidArgumentError, LfdError
from lfd_torch.metrics import cosine_dissimilarity, dtw_distance, velocity_error
from lfd_torch.preprocess import subsample
from lfd_torch.rollout import IntegrationMethod, rollout
from lfd_torch.store import prepare_job, run_manifest, staged_results, write_table
from lfd_torch.store.job import RESULTS_NAME
from lfd_torch.utils import check_choice, check_float, check_int, derive_seed
from lfd_torch.store.config_checks import get, is_config_error, positive_float, positive_int

log = logging.getLogger(__name__)

METRICS: tuple[str, ...] = ("E1", "RMSE", "E2", "DTWD")


def evaluate(model: StablePrimitive, demos: Demos, rollout_cfg: DictConfig) -> dict[str, torch.Tensor]:
    """Per-demonstration metrics of a primitive on ``demos``: (B,) tensors keyed by :data:`METRICS` + converged."""
    mask = demos.mask
    pred = model(demos.positions)
    dt = float(rollout_cfg.dt)
    n_steps = max(1, math.ceil(float(rollout_cfg.horizon_factor) * float(demos.durations.max()) / dt))
    result = rollout(
        model,
        demos.start_points,
        dt,
        n_steps,
        method=rollout_cfg.method,
        attractor=model.attractor,
        position_tol=float(rollout_cfg.position_tol),
        velocity_tol=float(rollout_cfg.velocity_tol),
    )
    return {
        "E1": velocity_error(pred, demos.velocities, mask),
        "RMSE": velocity_error(pred, demos.velocities, mask, kind="rms"),
        "E2": cosine_dissimilarity(pred, demos.velocities, mask),
        "DTWD": dtw_distance(result.positions, demos.positions, result.lengths, demos.lengths),
        "converged": result.converged,
        "rollout_steps": result.lengths - 1,
    }


def check_config(cfg: DictConfig) -> None:
    """Check the settings before anything is loaded or fitted (InvalidArgumentError / UnknownNameError naming the
    key; the demonstration indices are checked against the data set in :func:`run`)."""
    positive_int(cfg, "subsample")
    methods = get(cfg, "methods")
    if not isinstance(methods, DictConfig) or not len(methods):
        raise InvalidArgumentError(f"methods must map at least one method name to its ds config, got {methods!r}")
    for key in ("train_demos", "test_demos"):
        value = get(cfg, key)
        if not isinstance(value, (ListConfig, list, tuple)) or not len(value):
            raise InvalidArgumentError(f"{key} must be a non-empty list of demonstration indices, got {value!r}")
        for i in value:
            check_int(i, f"{key} entry")
    positive_float(cfg, "rollout.dt")
    positive_float(cfg, "rollout.horizon_factor")
    check_choice(get(cfg, "rollout.method"), "rollout.method", [m.value for m in IntegrationMethod])
    for key in ("rollout.position_tol", "rollout.velocity_tol"):  # as rollout() takes them (None: its default)
        check_float(get(cfg, key), key, low=0.0, allow_inf=True, allow_none=True)


def run(cfg: DictConfig) -> dict[str, Any]:
    """Fit and evaluate every method on ``cfg.data.shape``; returns the table, the fitted models and paths written."""
    check_config(cfg)
    job = prepare_job(cfg)  # an integer seed; publish=true refused in a multirun (the jobs would overwrite it)
    shape = str(cfg.data.shape)
    demos = subsample(instantiate(cfg.data), int(cfg.subsample), keep_last=False)  # plain x[::k], as the protocol
    train_idx, test_idx = list(cfg.train_demos), list(cfg.test_demos)
    for key, idx in (("train_demos", train_idx), ("test_demos", test_idx)):
        for i in idx:
            check_int(i, f"{key} entry", low=-demos.n_demos, high=demos.n_demos - 1)  # as Demos indexing takes them
    splits = {"train": (train_idx, demos[train_idx]), "test": (test_idx, demos[test_idx])}
    out_dir = job.out_dir
    rows: list[dict[str, Any]] = []
    models: dict[str, StablePrimitive] = {}
    written: list[Path] = []
    for method, method_cfg in cfg.methods.items():
        fit = instantiate(method_cfg)
        # The same seed for every method: LPV-DS (QLF) and (P-QLF) then share one clustering, so that they differ
        # only in the Lyapunov function.
        fit_seed = derive_seed(cfg.experiment, shape, cfg.seed)
        generator = torch.Generator(device=demos.device).manual_seed(fit_seed)
        common = {"experiment": cfg.experiment, "shape": shape, "method": str(method), "fold": 0, "seed": cfg.seed,
                  "fit_seed": fit_seed}  # fmt: skip
        t0 = time.perf_counter()
        try:
            model = fit(splits["train"][1], generator=generator)
        except LfdError as exc:
            if is_config_error(exc):  # a bad setting, not a failed fit: no row hides it
                raise
            log.error("%s on %s failed: %s", method, shape, exc)
            for split, (idx, _) in splits.items():
                for i in idx:
                    rows.append({**common, "trajectory": int(i), "split": split, "status": f"{type(exc).__name__}: {exc}",
                                 **{m: math.nan for m in METRICS}})  # fmt: skip
            continue
        fit_time = time.perf_counter() - t0
        models[str(method)] = model
        cert = model.stability_certificate()
        if cfg.save_models:
            written.append(model.save(out_dir / "models" / f"{shape}_{method}.pt"))
        for split, (idx, part) in splits.items():
            values = evaluate(model, part, cfg.rollout)
            for b, i in enumerate(idx):
                rows.append({
                    **common, "trajectory": int(i), "split": split, "status": "ok",
                    **{m: float(values[m][b]) for m in METRICS},
                    "converged": bool(values["converged"][b]), "rollout_steps": int(values["rollout_steps"][b]),
                    "n_components": model.n_components, "fit_time_s": fit_time, "max_margin": cert.max_margin,
                })  # fmt: skip
    table = pd.DataFrame(rows)
    manifest = run_manifest(cfg, cfg.seed)
    written.append(write_table(table, out_dir / RESULTS_NAME, manifest=manifest))
    if cfg.publish:
        written.append(write_table(table, Path(cfg.paths.tables) / f"{cfg.experiment}_{shape}.parquet", manifest=manifest))
    ok = table[table.status == "ok"]
    if len(ok):
        summary = ok.groupby(["method", "split"])[list(METRICS)].mean()
        log.info("%s:\n%s", shape, summary.to_string(float_format=lambda v: f"{v:.3f}"))
    return {"table": table, "models": models, "written": written}


@hydra.main(config_path="../conf", config_name="lasa_primitives", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with staged_results(cfg) as final:  # published outputs replace the old ones together, only on success
        result = run(cfg)
    for path in result["written"]:
        print(f"wrote {final(path)}")


if __name__ == "__main__":
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    torch.set_num_threads(1)
    main()
