"""Trajectory-reproduction metrics of the paper (Sec. V-A), batched over trajectories.

Notation:
    B          number of trajectories (or trajectory pairs)
    T          padded number of samples; T_i valid samples of trajectory i
    d          state dimension
    x_ref      (B, T, d)  reference (demonstrated) positions, data units (LASA: mm)
    x_dot_ref  (B, T, d)  reference velocities, data units per second
    x_dot      (B, T, d)  predicted velocities M f(x_ref)
    x          (B, T, d)  rollout started at x_ref,0, sampled on the demonstration's time grid
    mask       (B, T)     True on valid samples; alternatively ``lengths`` (B,) for prefix-valid rows

Every metric is a pure function ``f(pred, target, mask=None) -> (B,)`` (one value per trajectory):
    E1  :func:`velocity_error`          mean_t ||x_dot_ref - x_dot||  (``kind="rms"``: true RMSE)
    E2  :func:`cosine_dissimilarity`    mean_t |1 - cos(x_dot_ref, x_dot)|
    E3  :func:`swept_area`              mean_t area(x_ref,t, x_ref,t+1, x_t+1, x_t)
    DTWD :func:`dtw_distance`           dynamic time warping distance between rollout and reference
:func:`aggregate` pools the per-trajectory values over a set.
"""

from lfd_torch.metrics.aggregate import AGGREGATE_KINDS, aggregate
from lfd_torch.metrics.area import SWEPT_AREA_REDUCTIONS, quadrilateral_areas, swept_area, triangle_areas
from lfd_torch.metrics.dtw import dtw_distance
from lfd_torch.metrics.velocity import VELOCITY_ERROR_KINDS, cosine_dissimilarity, velocity_error

__all__ = [
    "velocity_error",
    "cosine_dissimilarity",
    "swept_area",
    "quadrilateral_areas",
    "triangle_areas",
    "dtw_distance",
    "aggregate",
    "VELOCITY_ERROR_KINDS",
    "SWEPT_AREA_REDUCTIONS",
    "AGGREGATE_KINDS",
]
