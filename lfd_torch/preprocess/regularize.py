"""Trajectory regularization (paper Sec. I-A): smoothing, resampling, sub-sampling, dimension screening,
velocity estimation and trimming of the still tail.

Every function is pure, ``Demos -> Demos``; the input is never modified. Shapes follow :mod:`lfd_torch.data.demos`:
positions (B, T, d), times (B, T), lengths (B,).
"""

from __future__ import annotations

import logging

import scipy.signal
import torch
from torch import Tensor

from lfd_torch.data.demos import MIN_SAMPLES, Demos
from lfd_torch.data.finite_difference import finite_difference_unchecked
from lfd_torch.errors import InvalidArgumentError, TooFewSamplesError, UnknownNameError
from lfd_torch.utils import check_choice, check_cost, check_float, check_int

__all__ = [
    "moving_average",
    "savitzky_golay",
    "smooth",
    "resample",
    "subsample",
    "dimension_shares",
    "screen_dimensions",
    "estimate_velocities",
    "trim_still_tail",
]

log = logging.getLogger(__name__)


#: Bounds that keep the cost finite: smoothing window and resampled length (samples).
MAX_WINDOW = 100_001
MAX_SAMPLES = 1_000_000


def _check_demos(demos: object) -> Demos:
    if not isinstance(demos, Demos):
        raise InvalidArgumentError(f"demos must be a lfd_torch.data.Demos, got {type(demos).__name__}")
    return demos


def _check_window(window: int, demos: Demos) -> None:
    _check_demos(demos)
    check_int(window, "window", low=1, high=MAX_WINDOW)
    if window % 2 == 0:
        raise InvalidArgumentError(f"window must be a positive odd number of samples, got {window}")
    if window > int(demos.lengths.min()):
        i = int(torch.argmin(demos.lengths))
        raise TooFewSamplesError(f"has {int(demos.lengths[i])} samples, fewer than the window {window}", i)


def _odd_extension(demos: Demos, h: int) -> Tensor:
    """(B, T + 2h, d) positions extended past both ends of each row by point reflection.

    Beyond the end, x(L-1+k) = 2 x(L-1) - x(L-1-k) (and likewise before the start). Any symmetric linear smoother
    applied to this extension keeps the first and last samples, so a smoothed demonstration still starts at its
    start and ends at its goal, and straight lines pass unchanged.
    """
    B, T, d = demos.positions.shape
    L = demos.lengths.unsqueeze(1)  # (B, 1)
    j = torch.arange(-h, T + h, device=demos.device).unsqueeze(0).expand(B, -1)  # (B, T+2h)
    before, after = j < 0, j > L - 1
    src = torch.where(before, -j, torch.where(after, 2 * (L - 1) - j, j)).clamp(0, T - 1)
    x = demos.positions.gather(1, src.unsqueeze(-1).expand(-1, -1, d))
    anchor = torch.where(before, torch.zeros_like(j), torch.where(after, L - 1, j))
    a = demos.positions.gather(1, anchor.unsqueeze(-1).expand(-1, -1, d))
    reflect = (before | after).unsqueeze(-1)
    return torch.where(reflect, 2 * a - x, x)


def _filter(demos: Demos, kernel: Tensor, recompute_velocities: bool) -> Demos:
    """Convolve every dimension of every row with a symmetric (window,) kernel over the odd extension."""
    h = kernel.shape[0] // 2
    ext = _odd_extension(demos, h)  # (B, T+2h, d)
    B, _, d = ext.shape
    w = kernel.to(dtype=demos.dtype, device=demos.device).flip(0).reshape(1, 1, -1)
    out = torch.nn.functional.conv1d(ext.transpose(1, 2).reshape(B * d, 1, -1), w)  # (B*d, 1, T)
    smoothed = out.reshape(B, d, -1).transpose(1, 2)
    smoothed = demos.replace(positions=_edge_pad(smoothed, demos.lengths))
    return estimate_velocities(smoothed) if recompute_velocities else smoothed


def moving_average(demos: Demos, window: int, *, recompute_velocities: bool = True) -> Demos:
    """Centred moving average over ``window`` (odd) samples, batched as a convolution.

    The ends use point reflection (:func:`_odd_extension`), so each demonstration keeps its start and end point.

    Args:
        demos: input set.
        window: odd window length in samples (1 returns the input).
        recompute_velocities: re-estimate velocities from the smoothed positions (central differences).
    """
    _check_window(window, demos)
    if window == 1:
        return demos
    return _filter(demos, torch.full((window,), 1.0 / window, dtype=torch.float64), recompute_velocities)


def savitzky_golay(demos: Demos, window: int, polyorder: int = 3, *, recompute_velocities: bool = True) -> Demos:
    """Savitzky-Golay smoothing of positions, batched as a convolution with ``scipy.signal.savgol_coeffs``.

    Inside, the result equals ``scipy.signal.savgol_filter``; at the ends the signal is extended by point
    reflection, so each demonstration keeps its start and end point (scipy's modes move the end point, i.e. the goal).
    """
    _check_window(window, demos)
    check_int(polyorder, "polyorder", low=0)
    if polyorder >= window:
        raise InvalidArgumentError(f"polyorder ({polyorder}) must be smaller than window ({window})")
    if window == 1:
        return demos
    kernel = torch.as_tensor(scipy.signal.savgol_coeffs(window, polyorder), dtype=torch.float64)
    return _filter(demos, kernel, recompute_velocities)


def smooth(demos: Demos, window: int, method: str = "savgol", polyorder: int = 3) -> Demos:
    """Window smoothing by ``method`` in {"savgol", "moving_average"}; velocities are re-estimated."""
    _check_demos(demos)
    if method == "savgol":
        return savitzky_golay(demos, window, polyorder)
    if method == "moving_average":
        return moving_average(demos, window)
    raise UnknownNameError("smoothing method", method, ("savgol", "moving_average"))


def _edge_pad(values: Tensor, lengths: Tensor) -> Tensor:
    """Overwrite the padding of (B, T, ...) ``values`` with each row's last valid entry."""
    T = values.shape[1]
    rows = torch.arange(values.shape[0], device=values.device)
    last = values[rows, lengths - 1].unsqueeze(1)
    mask = torch.arange(T, device=values.device).unsqueeze(0) < lengths.unsqueeze(1)
    while mask.ndim < values.ndim:
        mask = mask.unsqueeze(-1)
    return torch.where(mask, values, last)


def _interp(grid: Tensor, values: Tensor, lengths: Tensor, query: Tensor) -> Tensor:
    """Batched piecewise-linear interpolation.

    Args:
        grid: (B, T) non-decreasing abscissae (edge-padded).
        values: (B, T, k) ordinates.
        lengths: (B,) valid samples.
        query: (B, Q) abscissae inside each row's range.
    Returns:
        (B, Q, k)
    """
    idx = torch.searchsorted(grid.contiguous(), query.contiguous(), right=True)  # first grid > q
    upper = torch.minimum(idx, (lengths - 1).unsqueeze(1)).clamp(min=1)
    lower = upper - 1
    g0 = grid.gather(1, lower)
    g1 = grid.gather(1, upper)
    span = g1 - g0
    w = torch.where(span > 0, (query - g0) / torch.where(span > 0, span, torch.ones_like(span)), torch.ones_like(span))
    w = w.clamp(0, 1).unsqueeze(-1)
    k = values.shape[-1]
    v0 = values.gather(1, lower.unsqueeze(-1).expand(-1, -1, k))
    v1 = values.gather(1, upper.unsqueeze(-1).expand(-1, -1, k))
    return v0 + w * (v1 - v0)


def resample(demos: Demos, n_samples: int, mode: str = "time") -> Demos:
    """Resample every demonstration to ``n_samples`` points by linear interpolation.

    Args:
        demos: input set.
        n_samples: common length of the output, in [3, 1000000] (memory: B n_samples (d + 1) floats).
        mode: ``"time"`` (uniform in time between each demonstration's first and last time stamp) or
            ``"arc_length"`` (uniform along the path length; time stamps are interpolated too, so the timing of the
            demonstration is kept).
    Returns:
        Demos with lengths all ``n_samples``; velocities re-estimated by central differences.
    """
    _check_demos(demos)
    check_int(n_samples, "n_samples", high=MAX_SAMPLES)
    if n_samples < MIN_SAMPLES:
        raise TooFewSamplesError(f"n_samples must be >= {MIN_SAMPLES}, got {n_samples}")
    check_choice(mode, "resample mode", ("time", "arc_length"))
    check_cost("n_samples", float(demos.n_demos) * n_samples * (demos.dim + 1), 2e8, "resampled values")
    B = demos.n_demos
    u = torch.linspace(0, 1, n_samples, dtype=demos.dtype, device=demos.device).unsqueeze(0)  # (1, Q)
    rows = torch.arange(B, device=demos.device)
    if mode == "time":
        grid = demos.times
    elif mode == "arc_length":
        step = (demos.positions[:, 1:] - demos.positions[:, :-1]).norm(dim=-1)
        step = step * demos.mask[:, 1:]
        grid = torch.cat([step.new_zeros(B, 1), step.cumsum(1)], 1)
        if (grid[rows, demos.lengths - 1] <= 0).any():
            i = int(torch.nonzero(grid[rows, demos.lengths - 1] <= 0)[0])
            raise TooFewSamplesError("has zero path length; cannot resample by arc length", i)
    else:
        raise UnknownNameError("resampling mode", mode, ("time", "arc_length"))
    start, end = grid[:, :1], grid[rows, demos.lengths - 1].unsqueeze(1)
    query = start + u * (end - start)
    stacked = torch.cat([demos.positions, demos.times.unsqueeze(-1)], -1)
    out = _interp(grid, stacked, demos.lengths, query)
    positions, times = out[..., :-1], out[..., -1]
    if mode == "arc_length":  # a still start is one point of the path: it keeps its first time stamp, as the end
        times[:, 0] = demos.times[:, 0]  # keeps its last (the interpolation takes the last sample of a flat run)
    lengths = torch.full((B,), n_samples, dtype=torch.long, device=demos.device)
    velocities = finite_difference_unchecked(positions, times, lengths)  # from checked demos
    return Demos(positions, velocities, times, lengths, demos.attractor, demos.names)


def subsample(demos: Demos, step: int, *, keep_last: bool = True) -> Demos:
    """Keep every ``step``-th sample (0, step, 2 step, ...).

    Args:
        demos: input set.
        step: stride in samples (>= 1).
        keep_last: also keep each demonstration's last sample (its end point, usually the goal) when the stride
            skips it. ``False`` is the plain ``x[::step]`` of the LPV-DS literature's LASA protocol.

    Velocities are taken from the input at the kept samples (not re-estimated).
    """
    _check_demos(demos)
    check_int(step, "step", low=1)
    if step == 1:
        return demos
    L = demos.lengths
    if keep_last:
        n_kept = (L - 1 + step - 1) // step + 1  # samples 0, step, ... below L-1, plus L-1
    else:
        n_kept = (L + step - 1) // step  # samples 0, step, ... up to L-1
    Tn = int(n_kept.max())
    j = torch.arange(Tn, device=demos.device).unsqueeze(0)
    src = torch.minimum(j * step, (L - 1).unsqueeze(1))  # with keep_last, the last kept index of a row is L-1
    last = src.gather(1, (n_kept - 1).unsqueeze(1))
    src = torch.where(j < n_kept.unsqueeze(1), src, last)
    if (n_kept < MIN_SAMPLES).any():
        i = int(torch.nonzero(n_kept < MIN_SAMPLES)[0])
        raise TooFewSamplesError(f"keeps {int(n_kept[i])} samples after sub-sampling by {step}", i)
    d = demos.dim
    gather3 = src.unsqueeze(-1).expand(-1, -1, d)
    mask = (j < n_kept.unsqueeze(1)).unsqueeze(-1)
    vel = demos.velocities.gather(1, gather3) * mask
    return Demos(demos.positions.gather(1, gather3), vel, demos.times.gather(1, src), n_kept, demos.attractor,
                 demos.names)  # fmt: skip


def dimension_shares(demos: Demos) -> Tensor:
    """(d,) share of each dimension in the total variance of all valid positions (sums to 1).

    The positions are first scaled by a power of two (exact) that brings their largest magnitude to [0.5, 1): the
    shares do not change, and the variances neither overflow (|x| ~ 1e200) nor underflow (|x| ~ 1e-200).
    """
    x, _, _ = _check_demos(demos).samples()
    e = torch.frexp(x.abs().max()).exponent.to(torch.int64)  # 0 for all-zero positions
    h = torch.div(e, 2, rounding_mode="floor")
    x = torch.ldexp(torch.ldexp(x, -h), h - e)  # two halves: no 2^k factor under- or overflows itself
    var = x.var(dim=0, unbiased=False)
    total = var.sum()
    if total <= 0:
        return torch.full_like(var, 1.0 / var.numel())
    return var / total


def screen_dimensions(
    demos: Demos, threshold: float = 0.01, *, return_kept: bool = False
) -> Demos | tuple[Demos, Tensor]:
    """Drop dimensions whose share of the total position variance is below ``threshold``.

    The dropped and kept dimensions are logged (logger ``lfd_torch.preprocess``); ``return_kept=True`` also
    returns the (d_kept,) long tensor of kept dimension indices, to map results back to the full space.
    At least one dimension is always kept (the one with the largest variance).
    """
    _check_demos(demos)
    check_float(threshold, "threshold", low=0.0, high=1.0, high_open=True)
    shares = dimension_shares(demos)
    keep = shares >= threshold
    keep[torch.argmax(shares)] = True
    kept = torch.nonzero(keep).reshape(-1)
    dropped = torch.nonzero(~keep).reshape(-1)
    if dropped.numel():
        log.info(
            "dimension screening: dropped %s (variance shares %s), kept %s",
            dropped.tolist(),
            [round(float(s), 6) for s in shares[dropped]],
            kept.tolist(),
        )
    out = Demos(
        demos.positions[..., kept],
        demos.velocities[..., kept],
        demos.times,
        demos.lengths,
        demos.attractor[kept],
        demos.names,
    )
    return (out, kept) if return_kept else out


def estimate_velocities(demos: Demos, scheme: str = "central") -> Demos:
    """Replace the velocities by finite differences of the positions (see :func:`finite_difference`)."""
    _check_demos(demos)
    return demos.replace(velocities=finite_difference_unchecked(demos.positions, demos.times, demos.lengths, scheme))


def trim_still_tail(demos: Demos, position_tol: float, velocity_tol: float) -> Demos:
    """Cut the still tail near the attractor.

    A sample is *still* when it lies within ``position_tol`` of the attractor and moves no faster than
    ``velocity_tol`` (both bounds inclusive). The trailing run of still samples of each demonstration is cut,
    keeping its first sample (the demonstration then ends where it first came to rest at the goal). At least
    ``MIN_SAMPLES`` are kept.
    Units: those of the data (LASA: mm and mm/s).
    """
    _check_demos(demos)
    check_float(position_tol, "position_tol", low=0.0)
    check_float(velocity_tol, "velocity_tol", low=0.0)
    dist = (demos.positions - demos.attractor).norm(dim=-1)
    speed = demos.velocities.norm(dim=-1)
    moving = ~((dist <= position_tol) & (speed <= velocity_tol)) & demos.mask
    T = demos.max_length
    t = torch.arange(T, device=demos.device).expand_as(moving)
    last_moving = torch.where(moving, t, torch.full_like(t, -1)).max(dim=1).values  # -1 if all still
    new_len = torch.minimum(last_moving + 2, demos.lengths).clamp(min=MIN_SAMPLES)
    new_len = torch.minimum(new_len, demos.lengths)
    Tn = int(new_len.max())
    mask = (torch.arange(Tn, device=demos.device).unsqueeze(0) < new_len.unsqueeze(1)).unsqueeze(-1)
    positions = _edge_pad(demos.positions[:, :Tn], new_len)
    times = _edge_pad(demos.times[:, :Tn], new_len)
    velocities = demos.velocities[:, :Tn] * mask
    return Demos(positions, velocities, times, new_len, demos.attractor, demos.names)
