"""Content checksums of saved state dicts: a flipped bit in a stored tensor is caught on load.

:func:`payload_digest` is the SHA-256 of a canonical byte stream of a nested structure (mappings with sorted
string keys, sequences, strings, numbers, None and tensors; a tensor contributes its dtype, shape and raw bytes
in C order), so the digest of a state dict does not depend on how ``torch.save`` lays the file out.
"""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from lfd_torch.errors import StoreError

__all__ = ["payload_digest", "verify_digest", "DIGEST_KEY"]

#: Key under which a state dict stores its own digest (excluded from the digest).
DIGEST_KEY = "sha256"


def _feed(h: Any, obj: Any) -> None:
    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        h.update(b"T" + str(t.dtype).encode() + repr(tuple(t.shape)).encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    elif isinstance(obj, Mapping):
        keys = sorted((k for k in obj if k != DIGEST_KEY), key=str)
        h.update(b"M%d" % len(keys))
        for key in keys:
            h.update(b"K" + str(key).encode() + b"\0")
            _feed(h, obj[key])
    elif isinstance(obj, (str, bytes)):
        raw = obj.encode() if isinstance(obj, str) else obj
        h.update(b"S%d:" % len(raw) + raw)
    elif isinstance(obj, bool) or obj is None:
        h.update(b"B" + repr(obj).encode())
    elif isinstance(obj, int):
        h.update(b"I" + str(obj).encode() + b"\0")
    elif isinstance(obj, float):
        h.update(b"F" + struct.pack("<d", obj))
    elif isinstance(obj, Sequence):
        h.update(b"L%d" % len(obj))
        for item in obj:
            _feed(h, item)
    else:
        raise StoreError(f"cannot checksum a {type(obj).__name__}")


def payload_digest(state: Mapping[str, Any]) -> str:
    """Hex SHA-256 of ``state`` (its own :data:`DIGEST_KEY` entry excluded)."""
    h = hashlib.sha256()
    _feed(h, state)
    return h.hexdigest()


def verify_digest(state: Mapping[str, Any], where: str) -> None:
    """Raise :class:`StoreError` naming ``where`` if ``state`` carries a digest that does not match its content."""
    stored = state.get(DIGEST_KEY)
    if stored is None:
        return
    if stored != payload_digest(state):
        raise StoreError(f"{where}: content does not match its checksum (the file is damaged or was altered)")
