"""Small shared conversions."""

from __future__ import annotations

import hashlib

import pytest
import torch

from lfd_torch.errors import InvalidArgumentError, UnknownNameError
from lfd_torch.utils import derive_seed, float_dtype, resolve_device, resolve_dtype


def test_resolve_dtype_and_device():
    assert resolve_dtype("float32") is torch.float32 and resolve_dtype("torch.float64") is torch.float64
    assert resolve_dtype(torch.float16) is torch.float16 and resolve_dtype(None) is None
    with pytest.raises(UnknownNameError, match="float64"):
        resolve_dtype("double precision")
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")


def test_bad_dtype_and_device_arguments_are_typed_errors_naming_them():
    assert float_dtype("float32") is torch.float32 and float_dtype(None) is None
    for bad in (torch.float16, torch.int64, "bfloat16"):
        with pytest.raises(InvalidArgumentError, match="dtype"):
            float_dtype(bad)
    with pytest.raises(InvalidArgumentError, match="dtype"):
        float_dtype(3)
    with pytest.raises(InvalidArgumentError, match="device"):
        resolve_device("bogus")
    with pytest.raises(InvalidArgumentError, match="device"):
        resolve_device(3)
    if not torch.cuda.is_available():
        for cuda in ("cuda", torch.device("cuda:0")):
            with pytest.raises(InvalidArgumentError, match="CUDA is not available"):
                resolve_device(cuda)


def test_derive_seed_is_stable_and_distinct():
    reference = int.from_bytes(hashlib.sha256(b"lasa/Sshape/0").digest()[:8], "little") >> 1
    assert derive_seed("lasa", "Sshape", 0) == reference
    seeds = {derive_seed("lasa", shape, k) for shape in ("Sshape", "Angle") for k in range(5)}
    assert len(seeds) == 10 and all(0 <= s < 2**63 for s in seeds)
