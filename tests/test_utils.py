"""Small shared conversions."""

from __future__ import annotations

import hashlib

import pytest
import torch

from lfd_torch.errors import InvalidArgumentError, UnknownNameError
from lfd_torch.utils import derive_seed, float_dtype, resolve_device, resolve_dtype, to_arguments


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


def test_to_arguments_take_a_device_as_the_first_argument_like_torch():
    """``model.to("cpu")`` moves the model, as ``Tensor.to("cpu")`` does (it read "cpu" as a dtype name)."""
    cpu = torch.device("cpu")
    assert to_arguments("cpu", None) == (None, cpu) and to_arguments(cpu, None) == (None, cpu)
    assert to_arguments("auto", None)[1] is not None
    assert to_arguments("float32", "cpu") == (torch.float32, cpu) and to_arguments(None, None) == (None, None)
    with pytest.raises(UnknownNameError, match="float32, float64"):  # only the names float_dtype accepts
        to_arguments("double precision", None)
    with pytest.raises(InvalidArgumentError, match="twice"):
        to_arguments("cpu", "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(InvalidArgumentError, match="CUDA is not available"):
            to_arguments("cuda", None)


def test_derive_seed_is_stable_and_distinct():
    reference = int.from_bytes(hashlib.sha256(b"lasa/Sshape/0").digest()[:8], "little") >> 1
    assert derive_seed("lasa", "Sshape", 0) == reference
    seeds = {derive_seed("lasa", shape, k) for shape in ("Sshape", "Angle") for k in range(5)}
    assert len(seeds) == 10 and all(0 <= s < 2**63 for s in seeds)


def test_real_array_and_min_rows_boundaries():
    """real_array takes signed and unsigned integers as real numbers (not complex or text); check_tensor's min_rows
    counts the samples of a 1-D tensor by its length."""
    import numpy as np

    from lfd_torch.errors import ShapeMismatchError, TooFewSamplesError
    from lfd_torch.utils import check_tensor, real_array

    for arr in (np.array([1, 2], dtype=np.uint8), np.array([-1, 2], dtype=np.int16), [0.5, 1.5]):
        out = real_array(arr, "q")
        assert out.dtype == np.float64 and out.tolist() == [float(v) for v in arr]
    for bad in (np.array([1 + 2j]), np.array(["a"]), torch.tensor([1 + 1j])):
        with pytest.raises(ShapeMismatchError, match="q"):
            real_array(bad, "q")
    check_tensor(torch.zeros(5, dtype=torch.float64), "x", min_rows=3)  # five samples
    with pytest.raises(TooFewSamplesError, match="x has 2 samples"):
        check_tensor(torch.zeros(2, dtype=torch.float64), "x", min_rows=3)
