"""Publish a run's outputs together: staged while it runs, moved into place when it succeeds.

A publishing run writes tables, figures and libraries under ``results/``. Written straight there, a run that fails
or is killed halfway leaves new figures and libraries beside the old tables. :func:`staged_outputs` gives the run a
staging folder inside ``results/`` (same file system, so every move is an atomic rename). When the run succeeds,
every staged file replaces its published counterpart: tables last, and a library's ``manifest.json`` after its
other files. On an exception the staging folder is removed, and nothing published changes. A run killed with
SIGKILL leaves its hidden ``.staging-*`` folder behind, and still nothing published changes.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

__all__ = ["staged_outputs", "staged_results"]

_counter = itertools.count()


def _publish_order(path: Path) -> tuple[int, int, str]:
    """Tables last; within a folder, manifest.json after the files it lists."""
    return (path.parts[0] == "tables", path.name == "manifest.json", str(path))


@contextlib.contextmanager
def staged_outputs(results: str | os.PathLike[str]) -> Iterator[Path]:
    """A fresh staging folder under ``results`` for the block's outputs, laid out as ``results`` itself
    (``tables/``, ``figures/``, ``libraries/``...). On a clean exit its files replace their published counterparts.
    On an exception it is removed and the exception propagates."""
    root = Path(results)
    root.mkdir(parents=True, exist_ok=True)
    staging = root / f".staging-{os.getpid()}-{next(_counter)}"
    staging.mkdir()
    try:
        yield staging
        files = sorted((p.relative_to(staging) for p in staging.rglob("*") if p.is_file()), key=_publish_order)
        for rel in files:
            target = root / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(staging / rel, target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


@contextlib.contextmanager
def staged_results(cfg: Any) -> Iterator[Callable[[str | os.PathLike[str]], Path]]:
    """For a Hydra experiment with ``publish: true``: ``cfg.paths.results`` (the root of ``paths.tables``,
    ``paths.figures`` and ``paths.libraries``) points into a staging folder while the block runs, and the outputs
    are published as :func:`staged_outputs` does. Yields ``final(path)``: where a path the run wrote ends up. A
    no-op without ``publish`` (``final`` is then the identity)."""
    if not cfg.get("publish"):
        yield Path
        return
    from omegaconf import open_dict

    published = Path(str(cfg.paths.results))
    with staged_outputs(published) as staging:

        def final(path: str | os.PathLike[str]) -> Path:
            p = Path(path)
            return published / p.relative_to(staging) if p.is_relative_to(staging) else p

        with open_dict(cfg):
            cfg.paths.results = str(staging)
        try:
            yield final
        finally:
            with open_dict(cfg):
                cfg.paths.results = str(published)
