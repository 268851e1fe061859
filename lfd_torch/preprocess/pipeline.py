"""The regularization pipeline as one configurable callable (Hydra group ``preprocess``)."""

from __future__ import annotations

from dataclasses import dataclass

from lfd_torch.data.demos import Demos
from lfd_torch.errors import InvalidArgumentError, UnknownNameError
from lfd_torch.utils import check_float, check_int
from lfd_torch.preprocess.regularize import (
    MAX_SAMPLES,
    MAX_WINDOW,
    estimate_velocities,
    resample,
    screen_dimensions,
    smooth,
    subsample,
    trim_still_tail,
)

__all__ = ["Preprocess"]


def _int_at_least(value: object, low: int, name: str, *, odd: bool = False, high: int | None = None) -> None:
    check_int(value, name, low=low, high=high)
    if odd and value % 2 == 0:  # type: ignore[operator]
        raise InvalidArgumentError(f"{name} must be an odd integer >= {low}, got {value!r}")


@dataclass(frozen=True)
class Preprocess:
    """Regularize demonstrations in a fixed order: resample -> smooth -> velocities -> trim -> screen -> subsample.

    Every field is a keyword of the constructor and a key of ``conf/preprocess/*.yaml``.

    Attributes:
        smoothing: "savgol", "moving_average" or "none".
        window: smoothing window in samples (odd); 1 disables smoothing.
        polyorder: Savitzky-Golay polynomial order.
        n_samples: resample every demonstration to this length (None keeps the samples).
        resample_mode: "time" or "arc_length".
        velocity_scheme: "central", "forward", "backward", or "given" to keep the velocities as loaded
            (only honoured when nothing upstream changed the positions).
        trim_position_tol, trim_velocity_tol: cut the still tail near the attractor (None disables); finite numbers
            >= 0, data units.
        screen_threshold: drop dimensions whose variance share is below it (None disables).
        subsample_step: keep every k-th sample (1 keeps all).
    """

    smoothing: str = "savgol"
    window: int = 15
    polyorder: int = 3
    n_samples: int | None = None
    resample_mode: str = "time"
    velocity_scheme: str = "central"
    trim_position_tol: float | None = None
    trim_velocity_tol: float | None = None
    screen_threshold: float | None = None
    subsample_step: int = 1

    def __post_init__(self) -> None:
        if self.smoothing not in ("savgol", "moving_average", "none"):
            raise UnknownNameError("smoothing", self.smoothing, ("savgol", "moving_average", "none"))
        if self.velocity_scheme not in ("central", "forward", "backward", "given"):
            raise UnknownNameError("velocity_scheme", self.velocity_scheme, ("central", "forward", "backward", "given"))
        if (self.trim_position_tol is None) != (self.trim_velocity_tol is None):
            raise InvalidArgumentError("set both trim_position_tol and trim_velocity_tol, or neither")
        # argument ranges are checked here, at construction, not only when a step happens to run
        _int_at_least(self.window, 1, "window", odd=True, high=MAX_WINDOW)
        _int_at_least(self.polyorder, 0, "polyorder")
        if self.smoothing == "savgol" and self.window > 1 and self.polyorder >= self.window:
            raise InvalidArgumentError(f"polyorder ({self.polyorder}) must be smaller than window ({self.window})")
        if self.n_samples is not None:
            _int_at_least(self.n_samples, 3, "n_samples", high=MAX_SAMPLES)
        if self.resample_mode not in ("time", "arc_length"):
            raise UnknownNameError("resample_mode", self.resample_mode, ("time", "arc_length"))
        _int_at_least(self.subsample_step, 1, "subsample_step")
        for name in ("trim_position_tol", "trim_velocity_tol"):  # the checks trim_still_tail makes when called
            check_float(getattr(self, name), name, low=0.0, allow_none=True)
        v = self.screen_threshold
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < 1):
            raise InvalidArgumentError(f"screen_threshold must be a number in [0, 1) or None, got {v!r}")

    def __call__(self, demos: Demos) -> Demos:
        """Apply the steps to ``demos`` (a :class:`~lfd_torch.data.Demos`); returns a new set."""
        if not isinstance(demos, Demos):
            raise InvalidArgumentError(f"demos must be a lfd_torch.data.Demos, got {type(demos).__name__}")
        changed = False
        if self.n_samples is not None:
            demos, changed = resample(demos, self.n_samples, self.resample_mode), True
        if self.smoothing != "none" and self.window > 1:
            demos, changed = smooth(demos, self.window, self.smoothing, self.polyorder), True
        if self.velocity_scheme != "given":
            demos = estimate_velocities(demos, self.velocity_scheme)
        elif changed:
            raise InvalidArgumentError("velocity_scheme='given' cannot be used after resampling or smoothing")
        if self.trim_position_tol is not None:
            demos = trim_still_tail(demos, self.trim_position_tol, self.trim_velocity_tol)
        if self.screen_threshold is not None:
            demos = screen_dimensions(demos, self.screen_threshold)
        if self.subsample_step > 1:
            demos = subsample(demos, self.subsample_step)
        return demos
