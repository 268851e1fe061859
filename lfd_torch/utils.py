"""Small conversions shared by config-driven constructors."""

from __future__ import annotations

import hashlib

import torch

from lfd_torch.errors import UnknownNameError

__all__ = ["resolve_dtype", "resolve_device", "derive_seed"]

_DTYPES = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32, "float64": torch.float64}


def resolve_dtype(dtype: torch.dtype | str | None) -> torch.dtype | None:
    """``torch.float64``, ``"float64"`` or ``"torch.float64"`` -> ``torch.float64`` (None passes through)."""
    if dtype is None or isinstance(dtype, torch.dtype):
        return dtype
    name = str(dtype).removeprefix("torch.")
    if name not in _DTYPES:
        raise UnknownNameError("dtype", str(dtype), tuple(_DTYPES))
    return _DTYPES[name]


def resolve_device(device: torch.device | str | None) -> torch.device | None:
    """A device or its name; ``"auto"`` picks CUDA when present, else the CPU (None passes through)."""
    if device is None or isinstance(device, torch.device):
        return device
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def derive_seed(*parts: object) -> int:
    """A 63-bit seed derived from ``parts`` (e.g. experiment, shape, seed index): stable across runs and machines.

    Gives every (experiment, shape, seed) its own stream without a global RNG, as ``torch.Generator().manual_seed``.
    """
    digest = hashlib.sha256("/".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1
