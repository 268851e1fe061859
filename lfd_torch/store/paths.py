"""Where published results go: the project's ``results/``, never a folder relative to the working directory.

:func:`project_root` is ``$LFD_ROOT`` when set, else the source checkout that holds this package (the folder with
``pyproject.toml`` above ``lfd_torch/``). Configs refer to it as ``${lfd_root:}`` (an OmegaConf resolver registered
when ``lfd_torch`` is imported), so ``python experiments/x.py`` publishes to the same place from any directory.
"""

from __future__ import annotations

import os
from pathlib import Path

from lfd_torch.errors import StoreError

__all__ = ["project_root", "register_resolvers"]


def project_root() -> str:
    """Absolute path of the project root (module docstring).

    Raises:
        StoreError: ``LFD_ROOT`` is unset and the package is not inside a source checkout (an installed wheel):
            there is no project ``results/`` to publish to.
    """
    env = os.environ.get("LFD_ROOT")
    if env:
        return str(Path(env).expanduser().resolve())
    here = Path(__file__).resolve().parents[2]
    if (here / "pyproject.toml").is_file() and (here / "lfd_torch").is_dir():
        return str(here)
    raise StoreError("set LFD_ROOT to the folder whose results/ should receive published tables and figures")


def register_resolvers() -> None:
    """Register ``${lfd_root:}`` with OmegaConf (idempotent)."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("lfd_root"):
        OmegaConf.register_new_resolver("lfd_root", project_root)
