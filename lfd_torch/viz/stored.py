"""What the published figures are redrawn from: checksummed state files under ``results/libraries/``.

The publish presets of the experiments store, beside their tables (``results/tables/*.parquet``), the fitted skill
libraries (:meth:`~lfd_torch.skills.SkillLibrary.save`), segmentations
(:meth:`~lfd_torch.segmentation.Segmentation.save`) and the few other things a figure draws (demonstrations, MNIST
images and rollout paths, the run's configuration) under ``results/libraries/<experiment>/``;
``experiments/figures.py`` redraws every figure from them without fitting.

Notation:
    state    a plain dict of tensors, numbers, strings, lists and None, written with ``torch.save`` together with
             the SHA-256 of its content (:func:`lfd_torch.store.checksum.payload_digest`) and checked on load
    demos    :class:`~lfd_torch.data.Demos`: positions (N, T, d), velocities (N, T, d), times (N, T), lengths (N,),
             attractor (d,), in the data's units (LASA and MNIST: mm, s)
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import torch

from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError, StoreError
from lfd_torch.store import atomic_save
from lfd_torch.store.checksum import DIGEST_KEY, payload_digest, verify_digest
from lfd_torch.store.paths import project_root
from lfd_torch.utils import check_path

__all__ = [
    "STATE_SCHEMA",
    "results_dir",
    "save_state",
    "load_state",
    "save_demos",
    "load_demos",
    "save_config",
    "load_config",
]

STATE_SCHEMA = 1
_SCHEMA_KEY = "schema_version"


def results_dir() -> Path:
    """The project's ``results/`` (``${lfd_root:}/results``: ``$LFD_ROOT`` when set, else the checkout)."""
    return Path(project_root()) / "results"


def save_state(state: Mapping[str, Any], path: str | os.PathLike[str]) -> Path:
    """Write ``state`` atomically with its content checksum; returns the path.

    Raises:
        StoreError: ``path`` is not a file path, ``state`` is not a mapping or holds something that cannot be
            checksummed (not a tensor, number, str, list, dict), or the file cannot be written (a file where a
            folder should be, no permission, disk full: the message names the file; nothing is left half-written
            and an existing file keeps its content).
    """
    path = check_path(path, "path", error=StoreError)
    if not isinstance(state, Mapping):
        raise StoreError(f"state must be a mapping (a dict of tensors, numbers, strings, lists), got "
                         f"{type(state).__name__}")  # fmt: skip
    out = {k: v for k, v in state.items() if k != DIGEST_KEY}
    out[_SCHEMA_KEY] = STATE_SCHEMA
    out[DIGEST_KEY] = payload_digest(out)
    atomic_save(path, lambda tmp: torch.save(out, tmp))
    return path


def load_state(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a file written by :func:`save_state` (tensors on the CPU).

    Raises:
        StoreError: the file is missing, unreadable, of another schema, or does not match its checksum (the message
            names the file), or ``path`` is not a file path.
    """
    path = check_path(path, "path", error=StoreError)
    if not path.is_file():
        raise StoreError(f"stored file {path} is missing (run the publish preset that writes it: make results)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # truncated or foreign file
        raise StoreError(f"cannot read stored file {path}: {exc}") from exc
    if not isinstance(state, dict) or DIGEST_KEY not in state:
        raise StoreError(f"stored file {path} is not a checksummed state")
    verify_digest(state, f"stored file {path}")
    if state.get(_SCHEMA_KEY) != STATE_SCHEMA:
        raise StoreError(f"stored file {path}: schema {state.get(_SCHEMA_KEY)!r}, expected {STATE_SCHEMA}")
    return {k: v for k, v in state.items() if k not in (DIGEST_KEY, _SCHEMA_KEY)}


def _demos_state(demos: Demos, velocities: bool) -> dict[str, Any]:
    state = {"positions": demos.positions.detach().cpu(), "times": demos.times.detach().cpu(),
             "lengths": demos.lengths.detach().cpu(), "attractor": demos.attractor.detach().cpu(),
             "names": list(demos.names)}  # fmt: skip
    if velocities:
        state["velocities"] = demos.velocities.detach().cpu()
    return state


def _demos_from_state(state: Mapping[str, Any], where: Path) -> Demos:
    try:
        if "velocities" in state:
            return Demos(state["positions"], state["velocities"], state["times"], state["lengths"],
                         state["attractor"], tuple(state["names"]))  # fmt: skip
        n = [int(v) for v in state["lengths"]]
        return Demos.from_sequences([p[:k] for p, k in zip(state["positions"], n)],
                                    times=[t[:k] for t, k in zip(state["times"], n)], attractor=state["attractor"],
                                    names=tuple(state["names"]), dtype=state["positions"].dtype)  # fmt: skip
    except KeyError as exc:
        raise StoreError(f"stored demonstrations {where} lack {exc}") from exc


def save_demos(demos: Demos, path: str | os.PathLike[str], *, velocities: bool = True, **extra: Any) -> Path:
    """Store demonstrations (and ``extra`` entries beside them) with :func:`save_state`.

    Args:
        velocities: store the velocities too; False halves the file, and :func:`load_demos` re-estimates them by
            central differences (for figures, which draw positions only).

    Raises:
        StoreError: ``demos`` is not a :class:`~lfd_torch.data.Demos`, or as :func:`save_state`.
    """
    if not isinstance(demos, Demos):
        raise StoreError(f"demos must be a lfd_torch.data.Demos, got {type(demos).__name__}")
    return save_state({"demos": _demos_state(demos, velocities), **extra}, path)


def load_demos(path: str | os.PathLike[str]) -> tuple[Demos, dict[str, Any]]:
    """The demonstrations of a :func:`save_demos` file and its other entries.

    Raises:
        StoreError: as :func:`load_state`, or the file holds no demonstrations.
    """
    path = check_path(path, "path", error=StoreError)
    state = load_state(path)
    if "demos" not in state:
        raise StoreError(f"stored file {path} holds no demonstrations")
    demos = _demos_from_state(state.pop("demos"), Path(path))
    return demos, state


def save_config(cfg: Any, path: str | os.PathLike[str], *, drop: tuple[str, ...] = ("hydra", "paths")) -> Path:
    """Store a run's resolved configuration as JSON with its checksum.

    Args:
        cfg: an OmegaConf ``DictConfig`` or a mapping.
        drop: top-level keys left out: by default Hydra's run-time node and ``paths`` (where this machine wrote,
            not part of the experiment; readers find ``results/`` through :func:`results_dir`). A single string is
            one key.

    Raises:
        StoreError: ``cfg`` is not a mapping or holds values JSON cannot store, ``path`` is not a file path, or the
            file cannot be written (the message names it; an existing file keeps its content).
        InvalidArgumentError: ``drop`` is not a string or an iterable of strings.
    """
    from omegaconf import DictConfig, OmegaConf

    path = check_path(path, "path", error=StoreError)
    if isinstance(drop, str):
        drop = (drop,)
    keys = tuple(drop) if isinstance(drop, Iterable) else None
    if keys is None or not all(isinstance(k, str) for k in keys):
        raise InvalidArgumentError(f"drop must be a key or a sequence of top-level keys (strings), got {drop!r}")
    if isinstance(cfg, DictConfig):
        data = OmegaConf.to_container(cfg, resolve=True)
    elif isinstance(cfg, Mapping):
        data = dict(cfg)
    else:
        raise StoreError(f"cfg must be a DictConfig or a mapping, got {type(cfg).__name__}")
    assert isinstance(data, dict)
    for key in keys:
        data.pop(key, None)
    doc = {"config": data, _SCHEMA_KEY: STATE_SCHEMA}
    doc[DIGEST_KEY] = payload_digest(doc)
    try:
        text = json.dumps(doc, indent=1, sort_keys=True, allow_nan=True)
    except (TypeError, ValueError) as exc:
        raise StoreError(f"cannot store the configuration in {path} as JSON: {exc}") from exc
    atomic_save(path, lambda tmp: tmp.write_text(text + "\n"))
    return path


def load_config(path: str | os.PathLike[str]) -> Any:
    """The configuration of a :func:`save_config` file, as an OmegaConf ``DictConfig``.

    Raises:
        StoreError: the file is missing, not JSON, or does not match its checksum (the message names it), or
            ``path`` is not a file path.
    """
    from omegaconf import OmegaConf

    path = check_path(path, "path", error=StoreError)
    if not path.is_file():
        raise StoreError(f"stored configuration {path} is missing (run the publish preset that writes it)")
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StoreError(f"cannot read stored configuration {path}: {exc}") from exc
    if not isinstance(doc, dict) or DIGEST_KEY not in doc or "config" not in doc:
        raise StoreError(f"{path} is not a stored configuration")
    verify_digest(doc, f"stored configuration {path}")
    if doc.get(_SCHEMA_KEY) != STATE_SCHEMA:  # as load_state: a file of another schema is not read as this one
        raise StoreError(f"stored configuration {path}: schema {doc.get(_SCHEMA_KEY)!r}, expected {STATE_SCHEMA}")
    return OmegaConf.create(doc["config"])
