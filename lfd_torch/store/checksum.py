"""Content checksums of saved state dicts: a flipped bit in a stored tensor is caught on load.

:func:`payload_digest` is the SHA-256 of a canonical byte stream of a nested structure (mappings with sorted
string keys, sequences, strings, numbers, None and tensors; a tensor contributes its dtype, shape and raw bytes
in C order), so the digest of a state dict does not depend on how ``torch.save`` lays the file out.
"""

from __future__ import annotations

import hashlib
import os
import struct
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from lfd_torch.errors import StoreError

__all__ = ["payload_digest", "verify_digest", "zip_member_spans", "compact_cpu", "DIGEST_KEY"]

#: Key under which a state dict stores its own digest (excluded from the digest).
DIGEST_KEY = "sha256"


def _feed(h: Any, obj: Any) -> None:
    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        h.update(b"T" + str(t.dtype).encode() + repr(tuple(t.shape)).encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")  # 0-d tensors too
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


def compact_cpu(t: torch.Tensor) -> torch.Tensor:
    """A detached, contiguous CPU copy of ``t`` whose storage holds exactly its elements (for saving).

    ``torch.save`` writes a view's whole storage; bytes outside the view are covered by no checksum.
    """
    t = t.detach().cpu()
    if t.is_contiguous() and t.untyped_storage().nbytes() == t.numel() * t.element_size() and t.storage_offset() == 0:
        return t
    return t.clone(memory_format=torch.contiguous_format)


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
    try:
        actual = payload_digest(state)
    except (StoreError, RuntimeError, TypeError, ValueError) as exc:  # a damaged file can hold objects it cannot hash
        raise StoreError(f"{where}: {exc} (the file is damaged or was altered)") from exc
    if stored != actual:
        raise StoreError(f"{where}: content does not match its checksum (the file is damaged or was altered)")


def zip_member_spans(path: str | os.PathLike[str]) -> dict[str, tuple[int, int]]:
    """Byte ranges [start, end) of the stored members of a ``torch.save`` zip file, by member name.

    ``torch.save`` stores its members uncompressed: ``<archive>/data.pkl`` is the metadata pickle and
    ``<archive>/data/<key>`` the raw bytes of each tensor storage (the payload). Used to aim byte flips at a part
    of a file in tests and audits.

    Raises:
        StoreError: the file is not a zip archive, or a member is compressed.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
    except (OSError, zipfile.BadZipFile) as exc:
        raise StoreError(f"{path} is not a torch zip file: {exc}") from exc
    spans = {}
    for info in infos:
        if info.compress_type != zipfile.ZIP_STORED:
            raise StoreError(f"{path}: member {info.filename} is compressed")
        off = info.header_offset  # local header: 30 fixed bytes, then the name and the extra field
        start = off + 30 + int.from_bytes(raw[off + 26 : off + 28], "little") + int.from_bytes(raw[off + 28 : off + 30], "little")
        spans[info.filename] = (start, start + info.compress_size)
    return spans
