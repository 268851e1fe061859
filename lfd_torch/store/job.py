"""What every experiment job does first: check its seed, refuse to publish from a multirun, find its folder, and set
aside rows that an earlier run of another configuration left in it."""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lfd_torch.errors import InvalidArgumentError, StoreError
from lfd_torch.store.manifest import run_manifest, same_run
from lfd_torch.store.table import read_manifest

__all__ = ["JobContext", "prepare_job", "RESULTS_NAME"]

log = logging.getLogger(__name__)

#: The file in a job's folder that holds its rows (what :func:`~lfd_torch.store.collect` merges).
RESULTS_NAME = "results.parquet"
_INT64 = (-(2**63), 2**63 - 1)  # the seed is stored in an int64 column of every row


@dataclass(frozen=True)
class JobContext:
    """Attributes: out_dir (the job's folder), manifest (:func:`run_manifest`), multirun (a Hydra sweep job),
    set_aside (where an earlier run's ``results.parquet`` of another configuration was moved, else None)."""

    out_dir: Path
    manifest: dict[str, Any]
    multirun: bool
    set_aside: Path | None = None


def _set_aside_foreign_results(out_dir: Path, manifest: dict[str, Any]) -> Path | None:
    """Move ``out_dir/results.parquet`` aside (renamed ``results.parquet.<ns>.stale``: kept, but no longer a part of
    the sweep) unless its run manifest has the job's ``config_hash`` and ``seed``. A job re-run into a folder of an
    earlier sweep (same ``hydra.sweep.dir``, another setting) that fails would otherwise leave the old rows there, to
    be counted as this job's. Rows of this configuration stay: resuming decides about them (:func:`finished_part`).

    Raises:
        StoreError: the file cannot be moved.
    """
    path = out_dir / RESULTS_NAME
    if not path.is_file():
        return None
    try:
        old = read_manifest(path)
    except StoreError:  # damaged: not this job's rows either
        old = None
    if same_run(old, manifest):
        return None
    stale = path.with_name(f"{path.name}.{time.time_ns()}.stale")
    try:
        os.replace(path, stale)
    except OSError as exc:
        raise StoreError(f"cannot move {path} (rows of another configuration) aside to {stale.name}: {exc}") from exc
    found = "no readable run manifest" if old is None else \
        f"config_hash {old.get('config_hash')!r}, seed {old.get('seed')!r}"
    log.warning("%s holds rows of another run (%s; this job: config_hash %r, seed %r): moved aside to %s", path,
                found, manifest["config_hash"], manifest["seed"], stale.name)  # fmt: skip
    return stale


def prepare_job(cfg: Any) -> JobContext:
    """The job folder (Hydra's output dir, else ``cfg.out_dir``, else ``.``) and run manifest of ``cfg``.

    A ``results.parquet`` already in the folder whose run manifest is not this job's configuration and seed (left by
    an earlier sweep into the same ``hydra.sweep.dir``) is moved aside first (``JobContext.set_aside``): if this job
    then fails, the folder holds no rows, and the sweep counts the job as unfinished instead of merging stale rows.

    Raises:
        InvalidArgumentError: ``cfg.seed`` is not an integer in the int64 range (it is stored in an int64 column), or
            ``cfg.publish`` is true in a multirun (every job would overwrite the published results; merge the sweep
            with ``python -m lfd_torch.store.collect``).
        StoreError: an earlier ``results.parquet`` of another configuration cannot be moved aside.
    """
    seed = cfg.get("seed") if hasattr(cfg, "get") else None
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise InvalidArgumentError(f"seed must be an integer, got {seed!r}")
    if not _INT64[0] <= seed <= _INT64[1]:
        raise InvalidArgumentError(f"seed must be in the int64 range [{_INT64[0]}, {_INT64[1]}] (it is stored in an "
                                   f"int64 column of every row), got {seed}")  # fmt: skip
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hydra_on = HydraConfig.initialized()
    except ImportError:  # pragma: no cover - hydra is a dependency
        hydra_on = False
    multirun = bool(hydra_on and HydraConfig.get().mode == RunMode.MULTIRUN)
    if cfg.get("publish") and multirun:
        raise InvalidArgumentError("publish=true in a multirun would let every job overwrite the published results; "
                                   "merge the sweep with `python -m lfd_torch.store.collect` instead")  # fmt: skip
    out_dir = Path(HydraConfig.get().runtime.output_dir) if hydra_on else Path(cfg.get("out_dir", "."))
    manifest = run_manifest(cfg, seed=seed)
    return JobContext(out_dir, manifest, multirun, _set_aside_foreign_results(out_dir, manifest))
