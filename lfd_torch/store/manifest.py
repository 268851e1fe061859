"""Run manifest: what produced a result (configuration hash, seed, code version, environment, time).

The configuration hash is the SHA-256 of the canonical JSON of the resolved configuration (keys sorted at
every level, compact separators, tuples as lists, paths as POSIX strings, numpy/torch scalars and arrays as
plain numbers and lists), shortened to ``length`` hex digits. By default the top-level keys ``seed`` and
``hydra`` are left out: the seed is its own column of every result row, so all jobs of a seed sweep share one
``config_hash``; the ``hydra`` node holds run-time paths, not the experiment.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import json
import math
import numbers
import os
import platform
import subprocess
from collections.abc import Collection, Mapping, Set
from datetime import datetime, timezone
from pathlib import Path, PurePath
from typing import Any

import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from lfd_torch.errors import StoreError

__all__ = ["config_hash", "canonical_json", "git_sha", "run_manifest", "same_run", "MANIFEST_FIELDS",
           "DEFAULT_HASH_EXCLUDE"]

#: Top-level configuration keys that :func:`config_hash` leaves out unless told otherwise.
# Top-level keys that say where results go or which seed runs, not what is computed.
DEFAULT_HASH_EXCLUDE: tuple[str, ...] = ("seed", "hydra", "paths", "out_dir", "publish", "resume", "progress")

#: Keys of the dictionary returned by :func:`run_manifest`.
MANIFEST_FIELDS: tuple[str, ...] = (
    "config_hash",
    "seed",
    "package_version",
    "git_sha",
    "python_version",
    "torch_version",
    "timestamp",
)

_GIT_TIMEOUT_S = 10.0


def _canonical(value: Any, where: str) -> Any:
    """Convert ``value`` to plain JSON types with a single representation per value."""
    if isinstance(value, (DictConfig, ListConfig)):
        value = OmegaConf.to_container(value, resolve=True, throw_on_missing=True)
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, enum.Enum):
        return _canonical(value.value, where)
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        number = float(value)
        if not math.isfinite(number):  # JSON has no literal for them; keep them distinct and hashable
            return {"__float__": repr(number)}
        return number
    if isinstance(value, PurePath):
        return value.as_posix()
    if isinstance(value, np.generic):
        return _canonical(value.item(), where)
    if isinstance(value, np.ndarray):
        return _canonical(value.tolist(), where)
    if type(value).__module__.startswith("torch") and hasattr(value, "tolist"):
        return _canonical(value.detach().cpu().tolist(), where)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _canonical(
            {field.name: getattr(value, field.name) for field in dataclasses.fields(value)}, where
        )
    if isinstance(value, Mapping):
        out: dict[str, Any] = {}
        for key, item in value.items():
            if isinstance(key, str):
                name = key
            elif key is None or isinstance(key, (bool, numbers.Number, enum.Enum)):
                name = json.dumps(_canonical(key, where))
            else:
                raise StoreError(f"cannot hash config: key {key!r} at {where or '<root>'} is not a scalar")
            if name in out:
                raise StoreError(f"cannot hash config: keys {key!r} and {name!r} at {where or '<root>'} collide")
            out[name] = _canonical(item, f"{where}.{name}" if where else name)
        return out
    if isinstance(value, (list, tuple)):
        return [_canonical(item, f"{where}[{i}]") for i, item in enumerate(value)]
    if isinstance(value, Set):
        items = [_canonical(item, f"{where}{{}}") for item in value]
        return sorted(items, key=lambda item: json.dumps(item, sort_keys=True))
    raise StoreError(f"cannot hash config: value of type {type(value).__name__} at {where or '<root>'}")


def canonical_json(cfg: Mapping[str, Any] | DictConfig | None, *, exclude: Collection[str] = ()) -> str:
    """The canonical JSON text of a resolved configuration (see the module docstring).

    Args:
        cfg: a mapping or OmegaConf ``DictConfig`` (interpolations are resolved), or None.
        exclude: top-level keys to leave out.

    Returns:
        Compact JSON with sorted keys; equal configurations give equal text whatever their key order.

    Raises:
        StoreError: a value has no canonical form, a mandatory value is missing (``???``) or an
            interpolation cannot be resolved.
    """
    if cfg is not None and not isinstance(cfg, (Mapping, DictConfig)):
        raise StoreError(f"config must be a mapping, a DictConfig or None, not {type(cfg).__name__}")
    try:
        plain = _canonical(cfg, "")
    except OmegaConfBaseException as exc:
        raise StoreError(f"cannot resolve config: {exc}") from exc
    if isinstance(plain, dict):
        plain = {key: item for key, item in plain.items() if key not in set(exclude)}
    return json.dumps(plain, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def config_hash(
    cfg: Mapping[str, Any] | DictConfig | None,
    *,
    length: int = 12,
    exclude: Collection[str] = DEFAULT_HASH_EXCLUDE,
) -> str:
    """Stable short hash of a resolved configuration.

    Args:
        cfg: a mapping or OmegaConf ``DictConfig`` (interpolations are resolved), or None.
        length: number of hex digits kept, 1..64.
        exclude: top-level keys left out of the hash (default: ``seed`` and ``hydra``).

    Returns:
        The first ``length`` hex digits of the SHA-256 of :func:`canonical_json`.

    Raises:
        StoreError: see :func:`canonical_json`; or ``length`` out of range.
    """
    if isinstance(length, bool) or not isinstance(length, int) or not 1 <= length <= 64:
        raise StoreError(f"length must be an int in 1..64, got {length!r}")
    text = canonical_json(cfg, exclude=exclude)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:length]


def _run_git(args: list[str], cwd: str) -> str | None:
    try:
        done = subprocess.run(
            ["git", *args],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=_GIT_TIMEOUT_S,
            check=False,
            env={**os.environ, "GIT_OPTIONAL_LOCKS": "0"},  # `git status` must not write the index
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def _git_sha_uncached(repo_dir: str) -> str:
    sha = _run_git(["rev-parse", "HEAD"], repo_dir)
    if not sha:
        return "unknown"
    status = _run_git(["status", "--porcelain", "--untracked-files=no"], repo_dir)
    if status is None:  # cannot tell whether the tree is clean: do not claim it is
        return f"{sha}-dirty"
    return f"{sha}-dirty" if status else sha


@functools.cache
def _git_sha_cached(repo_dir: str) -> str:
    return _git_sha_uncached(repo_dir)


def _package_root() -> Path:
    # lfd_torch/store/manifest.py -> the directory holding the lfd_torch package (the repository root
    # for an editable install). Not the working directory: Hydra changes it to the job's output folder.
    return Path(__file__).resolve().parents[2]


def git_sha(repo_dir: str | os.PathLike[str] | None = None) -> str:
    """Commit of the source tree, with ``-dirty`` appended when tracked files have uncommitted changes.

    The lookup runs ``git`` once per directory and process and is cached (changes made later in the same
    process are not seen).

    Args:
        repo_dir: a directory inside the repository; default: the one holding the lfd_torch package.

    Returns:
        ``"<40 hex digits>"``, ``"<40 hex digits>-dirty"``, or ``"unknown"`` when git is missing or the
        directory is not inside a repository.
    """
    directory = Path(repo_dir) if repo_dir is not None else _package_root()
    return _git_sha_cached(str(directory.resolve()))


def run_manifest(cfg: Mapping[str, Any] | DictConfig | None, seed: int) -> dict[str, Any]:
    """Provenance of one run, to attach to every result row it produces.

    Args:
        cfg: the run's configuration (resolved before hashing), or None.
        seed: the run's seed. If ``cfg`` has a top-level ``seed`` it must be equal.

    Returns:
        A flat dict with the keys of :data:`MANIFEST_FIELDS`: ``config_hash`` (str, :func:`config_hash`),
        ``seed`` (int), ``package_version`` (``lfd_torch.__version__``), ``git_sha`` (:func:`git_sha`),
        ``python_version``, ``torch_version`` and ``timestamp`` (UTC, ISO 8601, seconds).

    Raises:
        StoreError: ``seed`` is not an integer, disagrees with ``cfg.seed``, or the config cannot be hashed.
    """
    import torch  # deferred: reading and merging tables must not pay for importing torch

    import lfd_torch

    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise StoreError(f"seed must be an integer, got {seed!r}")
    seed = int(seed)
    if cfg is not None and isinstance(cfg, (Mapping, DictConfig)) and "seed" in cfg:
        try:
            cfg_seed = cfg["seed"]
        except OmegaConfBaseException as exc:
            raise StoreError(f"cannot read cfg.seed: {exc}") from exc
        if cfg_seed != seed:
            raise StoreError(f"seed {seed} disagrees with the configuration's seed {cfg_seed!r}")
    return {
        "config_hash": config_hash(cfg),
        "seed": seed,
        "package_version": lfd_torch.__version__,
        "git_sha": git_sha(),
        "python_version": platform.python_version(),
        "torch_version": torch.__version__,
        "timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def same_run(found: Mapping[str, Any] | None, manifest: Mapping[str, Any],
             keys: Collection[str] = ("config_hash", "seed")) -> bool:
    """Whether rows whose run manifest is ``found`` (None: it could not be read) belong to the run that ``manifest``
    describes: the same value at every key of ``keys`` (by default its configuration and seed; add ``git_sha`` to
    require the same code too). A key absent from both counts as the same (None == None)."""
    return found is not None and all(found.get(k) == manifest.get(k) for k in keys)
