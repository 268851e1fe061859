"""Typed errors of lfd_torch.

Every error the package raises on bad input derives from :class:`LfdError`, and also from the
builtin exception a caller would naturally catch (``ValueError``, ``LookupError``, ``RuntimeError``).
"""

from __future__ import annotations

__all__ = [
    "LfdError",
    "InvalidArgumentError",
    "InvalidDemoError",
    "NonFiniteError",
    "TooFewSamplesError",
    "ShapeMismatchError",
    "NonIncreasingTimeError",
    "UnknownNameError",
    "SolverError",
    "CertificationError",
    "StoreError",
    "PlotError",
    "InvalidGMMError",
    "InvalidIndexError",
]


class LfdError(Exception):
    """Base class of every error raised by lfd_torch."""


class InvalidArgumentError(LfdError, ValueError):
    """An argument outside its valid range or of the wrong kind (a tolerance < 0, a non-callable field, ...)."""


class InvalidIndexError(InvalidArgumentError, IndexError):
    """An index (of a demonstration, a step, a route) outside its valid range or of the wrong type."""


class InvalidDemoError(InvalidArgumentError):
    """A demonstration fails validation.

    Attributes:
        demo_index: index of the offending demonstration in its set (None when not specific to one).
        problem: short description of what is wrong.
    """

    def __init__(self, problem: str, demo_index: int | None = None):
        self.demo_index = demo_index
        self.problem = problem
        where = f"demonstration {demo_index}: " if demo_index is not None else ""
        super().__init__(f"{where}{problem}")


class NonFiniteError(InvalidDemoError):
    """NaN or Inf inside the valid part of a demonstration or input tensor."""


class TooFewSamplesError(InvalidDemoError):
    """A demonstration (or input) has fewer samples than an operation needs."""


class ShapeMismatchError(InvalidDemoError):
    """Tensors whose shapes (batch, time or state dimension) do not agree."""


class NonIncreasingTimeError(InvalidDemoError):
    """Time stamps that are not strictly increasing."""


class UnknownNameError(LfdError, LookupError):
    """A name (data set, shape, method) that is not known; the message lists the valid ones."""

    def __init__(self, kind: str, name: str, valid: list[str] | tuple[str, ...]):
        self.kind = kind
        self.name = name
        self.valid = tuple(valid)
        super().__init__(f"unknown {kind} {name!r}; valid names: {', '.join(self.valid)}")

    def __str__(self) -> str:  # LookupError/KeyError would quote the message
        return self.args[0]


class SolverError(LfdError, RuntimeError):
    """A numerical solver failed, or returned a status other than optimal."""


class CertificationError(LfdError, RuntimeError):
    """A fitted model does not pass its stability certificate; it is never returned."""


class StoreError(LfdError, RuntimeError):
    """Reading or writing a results table or model file failed."""


class PlotError(LfdError, ValueError):
    """Arguments or data that cannot make the requested plot (empty metric, bad ``split``, unknown format)."""


class InvalidGMMError(InvalidArgumentError):
    """Mixture parameters that do not define a valid density (negative weights, weights not summing to 1,
    covariances that are not symmetric positive definite)."""
