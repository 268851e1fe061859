"""LASA demonstration statistics before/after regularization (the foundation's main job).

For every shape: load, regularize with ``cfg.preprocess``, and compare with the same pipeline without smoothing
(E1 between velocity estimates, E3 swept area and DTWD between the paths), plus path statistics. One row per
(shape, demonstration) goes to ``results.parquet`` in the job folder; a violin plot of ``plot_metric`` by shape
goes beside it.

    python experiments/lasa_metrics.py
    python experiments/lasa_metrics.py -m preprocess.window=5,15
    python -m lfd_torch.store.collect multirun/lasa_metrics --out results/tables/lasa_metrics.parquet
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from pathlib import Path
from typing import Any

import hydra
import pandas as pd
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig

from lfd_torch.data import LASA_NAMES, Demos
from lfd_torch.errors import UnknownNameError
from lfd_torch.metrics import dtw_distance, swept_area, velocity_error
from lfd_torch.preprocess import Preprocess
from lfd_torch.store import prepare_job, staged_results, write_table
from lfd_torch.store.job import RESULTS_NAME
from lfd_torch.viz import violin
from lfd_torch.store.config_checks import get, name_list

log = logging.getLogger(__name__)


def _common(a: Demos, b: Demos) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Align two versions of one set on their shared valid samples: (xa, xb, va, vb, lengths)."""
    lengths = torch.minimum(a.lengths, b.lengths)
    T = int(lengths.max())
    return a.positions[:, :T], b.positions[:, :T], a.velocities[:, :T], b.velocities[:, :T], lengths


#: The columns of :func:`demo_statistics` (what ``plot_metric`` may name).
STATISTICS: tuple[str, ...] = ("n_samples", "duration", "path_length", "mean_speed", "peak_speed", "end_distance",
                               "smoothing_velocity_e1", "smoothing_area", "smoothing_dtwd")  # fmt: skip


def demo_statistics(raw: Demos, preprocess: Preprocess) -> pd.DataFrame:
    """One row per demonstration: path statistics of the regularized demos and their distance to the unsmoothed ones."""
    out = preprocess(raw)
    reference = dataclasses.replace(preprocess, smoothing="none", window=1)(raw)
    xa, xb, va, vb, lengths = _common(out, reference)
    mask = torch.arange(xa.shape[1], device=lengths.device).unsqueeze(0) < lengths.unsqueeze(1)
    step = (out.positions[:, 1:] - out.positions[:, :-1]).norm(dim=-1) * out.mask[:, 1:]
    speed = out.velocities.norm(dim=-1) * out.mask
    stats = {
        "n_samples": out.lengths,
        "duration": out.durations,
        "path_length": step.sum(1),
        "mean_speed": speed.sum(1) / out.lengths,
        "peak_speed": speed.max(1).values,
        "end_distance": (out.end_points - out.attractor).norm(dim=-1),
        "smoothing_velocity_e1": velocity_error(va, vb, mask),
        "smoothing_area": swept_area(xa, xb, mask),
        "smoothing_dtwd": dtw_distance(xa, xb, lengths, lengths),
    }
    return pd.DataFrame({k: v.detach().cpu().numpy() for k, v in stats.items()})


def method_name(preprocess: Preprocess) -> str:
    """A name that tells regularizations apart: smoothing and window, then every other non-default setting."""
    parts = [f"{preprocess.smoothing}-w{preprocess.window}"]
    for field in dataclasses.fields(preprocess):
        value = getattr(preprocess, field.name)
        if field.name not in ("smoothing", "window") and value != field.default:
            parts.append(f"{field.name}={value}")
    return ",".join(parts)


def run(cfg: DictConfig) -> dict[str, Any]:
    """Tabulate statistics for ``cfg.shapes``; returns the table and the paths written."""
    shapes = name_list(cfg, "shapes", LASA_NAMES, allow_all=True)
    plot_metric = get(cfg, "plot_metric")
    if not isinstance(plot_metric, str) or plot_metric not in STATISTICS:
        raise UnknownNameError("plot_metric", str(plot_metric), STATISTICS)
    # an integer seed; publish=true refused in a multirun (every job would overwrite the published table)
    job = prepare_job(cfg)
    torch.manual_seed(cfg.seed)  # nothing here is random; kept so every job seeds the same way
    preprocess: Preprocess = instantiate(cfg.preprocess)
    method = method_name(preprocess)
    frames = []
    t0 = time.perf_counter()
    for shape in shapes:
        raw = instantiate(cfg.data, shape=shape)
        table = demo_statistics(raw, preprocess)
        table.insert(0, "trajectory", range(len(table)))
        table.insert(0, "seed", cfg.seed)
        table.insert(0, "fold", 0)  # every demonstration, no train/test split
        table.insert(0, "method", method)
        table.insert(0, "shape", shape)
        table.insert(0, "experiment", cfg.experiment)
        frames.append(table)
    table = pd.concat(frames, ignore_index=True)
    log.info("%d shapes regularized and measured in %.2f s", len(shapes), time.perf_counter() - t0)

    out_dir, manifest = job.out_dir, job.manifest
    written = [write_table(table, out_dir / RESULTS_NAME, manifest=manifest)]
    written.append(out_dir / f"{cfg.plot_metric}.png")
    violin(table, cfg.plot_metric, by="shape", path=written[-1])
    if cfg.publish:
        written.append(write_table(table, Path(cfg.paths.tables) / f"{cfg.experiment}.parquet", manifest=manifest))
        written.append(Path(cfg.paths.figures) / f"{cfg.experiment}_{cfg.plot_metric}.png")
        violin(table, cfg.plot_metric, by="shape", path=written[-1])
    summary = table.groupby("shape")[["path_length", "smoothing_velocity_e1", "smoothing_area"]].mean()
    log.info("per-shape means:\n%s", summary.to_string(float_format=lambda v: f"{v:.4g}"))
    return {"table": table, "written": written}


@hydra.main(config_path="../conf", config_name="lasa_metrics", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with staged_results(cfg) as final:  # published outputs replace the old ones together, only on success
        result = run(cfg)
    for path in result["written"]:
        print(f"wrote {final(path)}")


if __name__ == "__main__":
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    torch.set_num_threads(1)
    main()
