"""What every experiment job does first: check its seed, refuse to publish from a multirun, find its folder."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lfd_torch.errors import InvalidArgumentError
from lfd_torch.store.manifest import run_manifest

__all__ = ["JobContext", "prepare_job"]


@dataclass(frozen=True)
class JobContext:
    """Attributes: out_dir (the job's folder), manifest (:func:`run_manifest`), multirun (a Hydra sweep job)."""

    out_dir: Path
    manifest: dict[str, Any]
    multirun: bool


def prepare_job(cfg: Any) -> JobContext:
    """The job folder (Hydra's output dir, else ``cfg.out_dir``, else ``.``) and run manifest of ``cfg``.

    Raises:
        InvalidArgumentError: ``cfg.seed`` is not an integer, or ``cfg.publish`` is true in a multirun (every job
            would overwrite the published results; merge the sweep with ``python -m lfd_torch.store.collect``).
    """
    seed = cfg.get("seed") if hasattr(cfg, "get") else None
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise InvalidArgumentError(f"seed must be an integer, got {seed!r}")
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
    return JobContext(out_dir, run_manifest(cfg, seed=seed), multirun)
