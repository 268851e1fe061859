"""Trajectory regularization (paper Sec. I-A): every function maps ``Demos -> Demos``.

Notation: B demonstrations, T padded samples, d dimensions; see :mod:`lfd_torch.data.demos`.
"""

from lfd_torch.preprocess.pipeline import Preprocess
from lfd_torch.preprocess.regularize import (
    dimension_shares,
    estimate_velocities,
    moving_average,
    resample,
    savitzky_golay,
    screen_dimensions,
    smooth,
    subsample,
    trim_still_tail,
)

__all__ = [
    "Preprocess",
    "dimension_shares",
    "estimate_velocities",
    "moving_average",
    "resample",
    "savitzky_golay",
    "screen_dimensions",
    "smooth",
    "subsample",
    "trim_still_tail",
]
