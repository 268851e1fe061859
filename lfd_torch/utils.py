"""Small conversions shared by config-driven constructors, and the argument checks of the public boundary."""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from lfd_torch.errors import (
    InvalidArgumentError,
    LfdError,
    NonFiniteError,
    ShapeMismatchError,
    SolverError,
    TooFewSamplesError,
    UnknownNameError,
)

__all__ = [
    "resolve_dtype",
    "resolve_device",
    "float_dtype",
    "derive_seed",
    "FLOAT_DTYPES",
    "check_int",
    "check_float",
    "check_choice",
    "check_generator",
    "check_tensor",
    "real_array",
    "check_cost",
    "safe_magnitude",
    "solver_errors",
    "check_path",
]

_DTYPES = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32, "float64": torch.float64}


def resolve_dtype(dtype: torch.dtype | str | None) -> torch.dtype | None:
    """``torch.float64``, ``"float64"`` or ``"torch.float64"`` -> ``torch.float64`` (None passes through)."""
    if dtype is None or isinstance(dtype, torch.dtype):
        return dtype
    name = str(dtype).removeprefix("torch.")
    if name not in _DTYPES:
        raise UnknownNameError("dtype", str(dtype), tuple(_DTYPES))
    return _DTYPES[name]


def resolve_device(device: torch.device | str | None, name: str = "device") -> torch.device | None:
    """A device or its name; ``"auto"`` picks CUDA when present, else the CPU (None passes through).

    Raises:
        InvalidArgumentError: not a device name, or a CUDA device where CUDA is not available (naming ``name``).
    """
    if device is None:
        return None
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if not isinstance(device, torch.device):
        try:
            device = torch.device(device)
        except (RuntimeError, TypeError) as exc:
            raise InvalidArgumentError(f"{name} must be a torch.device or a device name such as 'cpu', 'cuda' or "
                                       f"'auto', got {_show(device)}") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InvalidArgumentError(f"{name} is {str(device)!r}, but CUDA is not available here; use 'cpu' or 'auto'")
    return device


def float_dtype(dtype: torch.dtype | str | None, name: str = "dtype", *, allow_none: bool = True,
                error: type[Exception] | None = None) -> torch.dtype | None:
    """``dtype`` (a torch dtype or its name; None passes through with ``allow_none``) checked to be one of
    :data:`FLOAT_DTYPES`.

    Raises:
        UnknownNameError: an unknown dtype name. InvalidArgumentError (or ``error``): another dtype, naming ``name``.
    """
    err = error or InvalidArgumentError
    if (dtype is None and not allow_none) or (dtype is not None and not isinstance(dtype, (torch.dtype, str))):
        raise err(f"{name} must be float32 or float64 (a torch dtype or its name), got {_show(dtype)}")
    if isinstance(dtype, str) and dtype.removeprefix("torch.") not in _DTYPES:
        raise UnknownNameError(name, dtype, tuple(str(d).removeprefix("torch.") for d in FLOAT_DTYPES))
    out = resolve_dtype(dtype)
    if out is not None and out not in FLOAT_DTYPES:
        raise err(f"{name} must be float32 or float64, got {out}")
    return out


def to_arguments(dtype: object, device: object, *, error: type[Exception] | None = None
                 ) -> tuple[torch.dtype | None, torch.device | None]:
    """The (dtype, device) of a ``.to(dtype, device)`` call, checked (:func:`float_dtype`, :func:`resolve_device`).

    As with ``torch.Tensor.to``, a first argument that is a device or a device name (``"cuda"``, ``"cpu"``,
    ``"auto"``, ``torch.device(...)``) is the device: ``model.to("cuda")`` moves the model.

    Raises:
        InvalidArgumentError: a device given twice, or one of the checks' errors.
    """
    is_device = isinstance(dtype, torch.device)
    if isinstance(dtype, str) and dtype.removeprefix("torch.") not in _DTYPES:
        try:
            is_device = dtype == "auto" or isinstance(torch.device(dtype), torch.device)
        except (RuntimeError, TypeError):
            is_device = False
    if is_device:
        if device is not None:
            raise InvalidArgumentError(f"the device is given twice: {_show(dtype)} (first argument) and "
                                       f"device={_show(device)}")  # fmt: skip
        dtype, device = None, dtype
    return float_dtype(dtype, error=error), resolve_device(device)


def derive_seed(*parts: object) -> int:
    """A 63-bit seed derived from ``parts`` (e.g. experiment, shape, seed index): stable across runs and machines.

    Gives every (experiment, shape, seed) its own stream without a global RNG, as ``torch.Generator().manual_seed``.
    """
    digest = hashlib.sha256("/".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


# ---------------------------------------------------------------------------------------------- validation
# One validation layer for the public boundary: every check names the argument, the value and what is accepted,
# and raises a typed lfd_torch error (also a ValueError, so existing ``except ValueError`` callers keep working).

#: Dtypes accepted for real-valued tensors (float16/bfloat16 lack the linear algebra the package needs on CPU).
FLOAT_DTYPES = (torch.float32, torch.float64)


def _show(value: object, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def check_int(
    value: object,
    name: str,
    *,
    low: int | None = None,
    high: int | None = None,
    allow_none: bool = False,
    error: type[Exception] | None = None,
) -> int | None:
    """``value`` as an int in [low, high] (bools and floats, even 2.0, are rejected; numpy integers accepted).

    ``high`` is the bound that keeps the cost of a call finite; the message says so.

    Raises:
        InvalidArgumentError (or ``error``, a subclass): naming ``name``, the value and the accepted range.
    """
    err = error or InvalidArgumentError
    if value is None and allow_none:
        return None
    rng = f"[{'-inf' if low is None else low}, {'inf' if high is None else high}]"
    accepted = f"an integer in {rng}" + (" or None" if allow_none else "")
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise err(f"{name} must be {accepted}, got {_show(value)} ({type(value).__name__})")
    out = int(value)
    if (low is not None and out < low) or (high is not None and out > high):
        raise err(f"{name} must be {accepted}, got {out}")
    return out


def check_float(
    value: object,
    name: str,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    allow_none: bool = False,
    allow_inf: bool = False,
    error: type[Exception] | None = None,
) -> float | None:
    """``value`` as a finite float within the given bounds (ints accepted, bools and strings rejected).

    Raises:
        InvalidArgumentError (or ``error``, a subclass): naming ``name``, the value and the accepted interval.
    """
    err = error or InvalidArgumentError
    if value is None and allow_none:
        return None
    left = "(" if low_open else "["
    right = ")" if high_open else "]"
    accepted = f"a {'' if allow_inf else 'finite '}number in {left}{'-inf' if low is None else low}, " \
               f"{'inf' if high is None else high}{right}" + (" or None" if allow_none else "")  # fmt: skip
    if isinstance(value, Tensor) and value.numel() == 1 and not value.is_complex():
        value = float(value)
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise err(f"{name} must be {accepted}, got {_show(value)} ({type(value).__name__})")
    out = float(value)
    bad = math.isnan(out) or (math.isinf(out) and not allow_inf)
    if low is not None:
        bad = bad or out < low or (low_open and out == low)
    if high is not None:
        bad = bad or out > high or (high_open and out == high)
    if bad:
        raise err(f"{name} must be {accepted}, got {out!r}")
    return out


def check_choice(value: object, name: str, valid: Sequence[str]) -> str:
    """``value`` if it is one of the strings ``valid``.

    Raises:
        UnknownNameError: naming ``name``, the value and the valid names.
    """
    if not isinstance(value, str) or value not in valid:
        raise UnknownNameError(name, _show(value) if not isinstance(value, str) else value, tuple(valid))
    return value


def check_generator(generator: object, name: str = "generator", *, where: str = "") -> torch.Generator:
    """``generator`` if it is a ``torch.Generator`` (every stochastic step of the package is seeded through one).

    Raises:
        InvalidArgumentError: naming ``name`` and the type received.
    """
    if not isinstance(generator, torch.Generator):
        who = f"{where} needs " if where else ""
        raise InvalidArgumentError(
            f"{who}{name}=torch.Generator() (every stochastic step is seeded), got {_show(generator)} "
            f"({type(generator).__name__})"
        )
    return generator


def safe_magnitude(dtype: torch.dtype) -> float:
    """Largest |value| accepted in a position or velocity of ``dtype``: max**0.25 (float64 ~1e77, float32 ~4e9).

    Quadratic forms (Mahalanobis distances, Lyapunov values, squared errors) of larger values overflow; inputs
    beyond it are rejected rather than silently returning Inf or NaN.
    """
    return float(torch.finfo(dtype).max) ** 0.25


def real_array(value: object, name: str, *, error: type[Exception] = ShapeMismatchError) -> np.ndarray:
    """``value`` (array-like or tensor) as a float64 numpy array; complex, string and object values raise ``error``
    naming ``name``."""
    if isinstance(value, Tensor):
        if value.is_complex():
            raise error(f"{name} must hold real numbers, got {value.dtype}")
        value = value.detach().cpu().numpy()
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise error(f"{name} is not a real array: {exc}") from exc
    if arr.dtype.kind not in "fiu":
        raise error(f"{name} must hold real numbers, got {value!r}")
    return arr.astype(float)


def check_tensor(
    value: object,
    name: str,
    *,
    ndim: int | None = None,
    min_ndim: int | None = None,
    last_dim: int | None = None,
    min_rows: int | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | None = None,
    finite: bool = True,
    bounded: bool = True,
    shape_hint: str = "",
) -> Tensor:
    """Validate a real-valued tensor argument and return it unchanged.

    Args:
        value: the argument.
        name: its name in messages.
        ndim / min_ndim: exact / smallest number of dimensions.
        last_dim: required size of the last dimension (the state dimension d).
        min_rows: smallest size of dimension -2 (samples), or of dimension 0 for 1-D tensors.
        dtype / device: required dtype and device (e.g. a model's); None: any of :data:`FLOAT_DTYPES`.
        finite: reject NaN and Inf; with ``bounded`` also magnitudes above :func:`safe_magnitude`.
        shape_hint: the expected shape for messages, e.g. ``"(N, d)"``.

    Raises:
        ShapeMismatchError: not a tensor, wrong rank, size, dtype or device.
        TooFewSamplesError: fewer than ``min_rows`` samples.
        NonFiniteError: NaN, Inf or (``bounded``) an overflowing magnitude.
    """
    hint = f" of shape {shape_hint}" if shape_hint else ""
    if not isinstance(value, Tensor):
        raise ShapeMismatchError(f"{name} must be a torch.Tensor{hint}, got {type(value).__name__}")
    if value.dtype not in FLOAT_DTYPES:
        raise ShapeMismatchError(f"{name} has dtype {value.dtype}; float32 or float64 is required (convert it with "
                                 f".to(torch.float64))")  # fmt: skip
    if dtype is not None and (value.dtype != dtype or (device is not None and value.device != device)):
        raise ShapeMismatchError(f"{name} is {value.dtype} on {value.device}, {dtype} on {device} is required; "
                                 "convert it with .to(dtype=..., device=...)")  # fmt: skip
    if (ndim is not None and value.ndim != ndim) or (min_ndim is not None and value.ndim < min_ndim):
        want = f"{ndim}" if ndim is not None else f">= {min_ndim}"
        raise ShapeMismatchError(f"{name} must have {want} dimensions{hint}, got shape {tuple(value.shape)}")
    if last_dim is not None and (value.ndim == 0 or value.shape[-1] != last_dim):
        raise ShapeMismatchError(f"{name} must have last dimension d = {last_dim}{hint}, got shape "
                                 f"{tuple(value.shape)}")  # fmt: skip
    if min_rows is not None:
        rows = value.shape[-2] if value.ndim >= 2 else (value.shape[0] if value.ndim == 1 else 1)
        if rows < min_rows:
            raise TooFewSamplesError(f"{name} has {rows} samples (shape {tuple(value.shape)}), at least {min_rows} "
                                     "are needed")  # fmt: skip
    if finite and value.numel():
        limit = safe_magnitude(value.dtype) if bounded else math.inf
        ok = (value.abs() <= limit) if bounded else torch.isfinite(value)  # |inf| <= inf: Inf needs isfinite
        if not bool(ok.all()):
            what = "NaN or Inf" if not bounded else f"NaN, Inf or magnitudes above {limit:.3g} (they overflow)"
            raise NonFiniteError(f"{name} contains {what}")
    return value


def check_cost(name: str, size: float, limit: float, what: str) -> None:
    """Raise when a hyperparameter makes a call allocate or iterate more than ``limit`` (``size`` units of ``what``).

    Raises:
        InvalidArgumentError: naming ``name``, the size it implies and the bound.
    """
    if size > limit:
        raise InvalidArgumentError(f"{name} implies {size:.3g} {what}, above the bound {limit:.3g} that keeps the "
                                   "cost of the call finite")  # fmt: skip


@contextlib.contextmanager
def solver_errors(what: str) -> Iterator[None]:
    """Re-raise a failure of linear algebra or a numerical solver inside the block as a typed SolverError.

    The cause stays chained (``raise ... from exc``); lfd_torch errors pass through unchanged.

    Raises:
        SolverError: naming ``what`` and the original error.
    """
    try:
        yield
    except LfdError:
        raise
    except (torch.linalg.LinAlgError, np.linalg.LinAlgError, ArithmeticError, RuntimeError) as exc:
        raise SolverError(f"{what} failed: {type(exc).__name__}: {exc}") from exc


def check_path(value: object, name: str = "path", *, error: type[Exception] | None = None) -> Path:
    """``value`` (a str or os.PathLike, not empty) as a Path.

    Raises:
        InvalidArgumentError (or ``error``): naming ``name`` and the value received.
    """
    if isinstance(value, bytes) or not isinstance(value, (str, os.PathLike)) or str(value) == "":
        raise (error or InvalidArgumentError)(f"{name} must be a file path (str or os.PathLike), got {_show(value)} "
                                              f"({type(value).__name__})")  # fmt: skip
    return Path(value)
