"""Dwell: the time a demonstration spends between two grid points, as evidence of where a step begins.

Notation:
    N  sequences, T padded grid length, B labellings (or chains) scored at once
    c  (N, T) dwell covariate on the sampler's grid: c_t = log(Delta_t / median Delta), Delta_t the pace between
       grid points t - 1 and t: the time between the instants at which the path length reaches their levels over
       the path length between them (:func:`~lfd_torch.segmentation.segmentation.grid_crossings`; c_0 = 0,
       unused); (B, N, T) where every chain has its own data (the Geweke test)
    b  (B, N, T) 1 where a run of a state starts at t (phase 0 of the explicit-duration states), else 0
    mask  (N, T) bool, the grid points where a run can start: D <= t <= T_i - D (the first and the last run last at
       least D points, :func:`~lfd_torch.segmentation.transitions.expand_min_duration`)

Why. The sampler's grid is equally spaced in path length (:mod:`.segmentation`, item 3c): a leg gets grid points
in proportion to its length whatever its timing, so the direction fields do not see how long the demonstrator
dwells somewhere. But a human demonstrator who ends one subtask and begins the next usually slows down or pauses
there (each subtask a reaching movement with its own bell-shaped speed profile, Flash & Hogan 1985), and that is
the cue that separates a step boundary from a turn made at speed inside one step (the scoop's dip-drag-lift hook,
a curved leg). The grid keeps it: the time between the grid points on either side of a pause is long. So the
model also explains the dwell, with one regression shared by all states,

    c_t = mu + delta b_t + e_t,   e_t ~ N(0, sigma^2),   t in mask,

whose parameters are learned from the data with the state sequence: (mu, delta, sigma^2) ~ NIG, i.e. the
Matrix-Normal-Inverse-Wishart prior of :mod:`.field` with d = 1 and regressors [1, b_t] (the same conjugate
kernels: :func:`~lfd_torch.segmentation.field.field_posterior`, ``field_log_marginal_likelihood``,
``sample_field``, ``field_log_density``). Nothing says in advance that switches come with a dwell: delta has a
symmetric prior around 0, so where c does not depend on where runs start, delta is ~0 and the term changes nothing
but an Occam factor of about 1/2 log(1 + n_starts v_delta), paid once; where the data have a dwell at switches, a
switch at a long dwell gains and a switch at speed pays about delta^2 / (2 sigma^2) nats. The model, not a
threshold, decides what a long dwell is.

Known limit (measured, not fixed): at constant speed c is not independent of the corners. The path length comes from
least-squares velocities (:func:`~lfd_torch.segmentation.segmentation.scale_velocities`), and a window that
straddles a corner measures the chord, about cos(theta / 2) of the speed, so the grid interval at a sharp corner
takes longer: c = 0.3-0.4 at 135-degree corners, 0.1-0.2 at 80 degrees, about 0 at 40 degrees
(``straight_const_3d``, data cases 3 and 8, 4 demonstrations). delta is then learned from the sharp corners
(0.12-0.21) and a true switch at a mild corner pays for its c ~ 0: 2.2-12.1 nats against the true labelling in 8 of
the 22 missed synthetic cases scored by ``experiments/diagnose_segmentation.py --parts``
(results/tables/diagnose_segmentation_missed.json). The grid's instants are interpolated between samples
(:func:`~lfd_torch.segmentation.segmentation.grid_crossings`, the pace between them): at 100 Hz the sample times
round a gap by at most 1 / k of it at each end and the interpolation changes no case's every-switch verdict, but at
10 Hz (k = 1) a grid gap is one or two whole samples, a fast noisy speed estimate made the grid drop a level and
the term read the two-sample gap as a pause (``bench_segmentation.py --rate 10``: every switch 60 % of the 280
cases with the sample times, 73 % with the pace). Nine corrections were tried and not kept
(``experiments/segmentation_studies.md``, "Dwell: corrections tried").

It is an emission of the phase-expanded HMM (phase 0: the first point of a run, any other phase: inside a run), so
every move stays exact: the forward filter and FFBS add log N(c_t; mu + delta, sigma^2) to the phase-0 states and
log N(c_t; mu, sigma^2) to the others; the Gibbs step draws (mu, delta, sigma^2) from the NIG posterior given the
phases; the collapsed score adds the NIG evidence of c given b. Points outside the mask are not observed (no
labelling can put a switch there; the start and end rests of every demonstration would otherwise pose as the spread
inside a step). It needs D >= 2 (with D = 1 the expanded states carry no phase).

Pace of a run (``dwell_pace``, an option, not the default). A demonstrator may also carry out each step at a pace
of its own (each subtask its own reaching movement), so that the pace changes where the step changes even without a
pause; the synthetic constant-speed families draw every leg's speed on its own. The option gives every run r a level
of its own, c_t = mu + u_r + delta b_t + e_t with u_r ~ N(0, g sigma^2), so that c of one sequence is Gaussian with
covariance sigma^2 Omega, Omega = blockdiag_r(I + g 1 1^T) over its runs (the points of a run in the mask). With the
level scaled by sigma the model stays conjugate: the NIG evidence is that of the generalised least-squares
statistics X^T Omega^-1 X, X^T Omega^-1 c, c^T Omega^-1 c (Sherman-Morrison per run: Omega_r^-1 = I - g / (1 + g n_r)
1 1^T), minus 1/2 log |Omega| = 1/2 sum_r log(1 + g n_r); g has a uniform prior over :data:`PACE_RATIOS` and is
summed out. g = 0 is the run-free term. Only the collapsed score (the map search's objective) carries the levels:
they are not an emission of single points, so the chains' moves, which need one, keep the run-free term; the
switch times at full rate keep its shift too (:func:`~lfd_torch.segmentation.segmentation._dwell_switch_prior`).
Measured (``--segment-option dwell_pace=True``): on the 280 synthetic cases (``experiments/bench_segmentation.py
--parts synthetic --jobs 2 --method segment --segment-option dwell_pace=True --json
results/tables/bench_segmentation_segment_dwell_pace.json``) every switch on 87.9 % against 86.4 % (4 cases gained,
none lost: straight 3-D at constant speed 7 / 7 of 10 with 1 / 4 demonstrations against 6 / 6, curved 3-D 9 / 9,
straight 2-D 10 / 10); but on the held-out families, whose speed varies regardless of the corners
(``--families rounded_const_2d rounded_const_3d rounded_vary_2d rounded_vary_3d``,
``bench_segmentation_held_out_dwell_pace.json``), 75.0 % against 76.3 % (2 gained, 3 lost, all with a varying
speed), and on LASA (``experiments/bench_segmentation_seeds.py --segment-option dwell_pace=True``,
``bench_segmentation_seeds_dwell_pace.json``) Multi_Models_1's one-step route {5, 6} is cut in two steps on 9 and 7
of 10 seeds (two route groupings), Multi_Models_3 gains a step on each route (7 and 5, 9-10 of 10)
and takes 10.5 s per seed (median; 12.7 s at most; the stored default table, another run: 6.3 s).
A constant pace per step is what the constant-speed families draw, not what a hand does; so it stays an option.
A drift of the pace within a run as well (a level and a slope per run, u_r + v_r (t - t_r) / n_r, v_r ~ N(0,
g sigma^2); Omega_r stays a sum of two orthogonal rank-one updates), which would let a hand's smooth change of pace
stay inside one step: it kept 1 of the 4 synthetic cases gained (the single straight 2-D case 0), and of the 5
varying-speed held-out cases that the levels changed it misses 2 that the default finds and finds none that the
default misses (a one-off patch on those 9 cases, not stored).

Prior (c is a log ratio to the sequence's median, so unit free): sigma^2 ~ IG with nu0 = 3, S0 = 0.1 (E[sigma^2]
= 0.1, i.e. a dwell typically within a factor e^0.3 of the median inside a step); (mu, delta) | sigma^2 ~ N(0,
sigma^2 10^2 I), so delta / sigma has a prior standard deviation of 10 (vague over any plausible dwell ratio).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, NonFiniteError
from lfd_torch.gmm import gaussian_log_density
from lfd_torch.segmentation.field import (
    FieldPrior,
    field_log_density,
    field_log_marginal_likelihood,
    field_posterior,
)

__all__ = [
    "dwell_covariate",
    "dwell_mask",
    "dwell_prior",
    "dwell_regressors",
    "dwell_posterior",
    "dwell_evidence",
    "dwell_log_likelihood",
    "dwell_log_prob",
    "dwell_start",
    "posterior_summary",
    "PACE_RATIOS",
]

_SLOPE_VARIANCE = 100.0  # (mu, delta) | sigma^2 ~ N(0, sigma^2 * this * I)
_NOISE_DOF = 3.0  # nu0 of sigma^2 ~ IW(nu0, S0) (d = 1: an inverse gamma)
_NOISE_MEAN = 0.1  # E[sigma^2] = S0 / (nu0 - 2)
#: g = (spread of the runs' pace levels / sigma)^2, uniform prior over these values ("Pace of a run")
PACE_RATIOS = (0.0, 1.0, 4.0, 16.0, 64.0)


def dwell_covariate(times: Tensor, grid: Tensor, levels: Tensor | None = None) -> Tensor:
    """(n,) c of one sequence: c_0 = 0, c_t = log(Delta_t / median Delta) for t >= 1.

    Args:
        times: (T,) sample times of the full-rate sequence, increasing (s).
        grid: (n,) increasing sample indices of the grid points (:func:`~lfd_torch.segmentation.path_grid`).
        levels: (n,) path length of every grid point, or None. Given, Delta_t is the pace, the time between the
            grid points over the path length between them (equal spacing unless the grid dropped a level).
    """
    t = times[grid]
    gaps = t[1:] - t[:-1]
    if gaps.numel() == 0:
        return torch.zeros_like(t)
    if levels is not None:
        gaps = gaps / (levels[1:] - levels[:-1]).to(gaps)
    if not bool((gaps > 0).all()) or not bool(torch.isfinite(gaps).all()):
        raise NonFiniteError("times (and levels) must increase strictly and be finite along the grid")
    return torch.cat([torch.zeros_like(t[:1]), torch.log(gaps / gaps.median())])


def dwell_mask(lengths: Tensor, T: int, min_duration: int) -> Tensor:
    """(N, T) bool: the grid points where a run can start (module docstring), given the (N,) valid lengths."""
    D = int(min_duration)
    if D < 2:
        raise InvalidArgumentError(f"the dwell term needs a minimum duration of at least 2 grid points, got {D}")
    t = torch.arange(T, device=lengths.device).unsqueeze(0)
    return (t >= D) & (t <= (lengths - D).unsqueeze(1))


def dwell_prior(dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> FieldPrior:
    """The NIG prior of (mu, delta, sigma^2) of the module docstring, as a d = 1, p = 2 MNIW."""
    return FieldPrior(
        mean=torch.zeros(1, 2, dtype=dtype, device=device),
        row_covariance=_SLOPE_VARIANCE * torch.eye(2, dtype=dtype, device=device),
        dof=torch.tensor(_NOISE_DOF, dtype=dtype, device=device),
        scale=torch.full((1, 1), _NOISE_MEAN * (_NOISE_DOF - 2.0), dtype=dtype, device=device),
    )


def dwell_regressors(phase: Tensor, mask: Tensor, dtype: torch.dtype = torch.float64) -> Tensor:
    """(..., N, T, 2) regressors [1, b_t] from the phases (..., N, T) of the explicit-duration states."""
    b = ((phase == 0) & mask).to(dtype)
    return torch.stack([torch.ones_like(b), b], -1)


def _sums(c: Tensor, mask: Tensor, phase: Tensor, per_run: bool = False) -> dict[str, Tensor]:
    """The data sums behind :func:`_statistics` for the labellings' phases (B, N, T), each (B,): n, sum b_t,
    sum c_t, sum b_t c_t, sum c_t^2 over the mask (b_t is 0 or 1, so b_t^2 = b_t and only sum b_t and sum b_t c_t
    depend on the labelling; the map search scores hundreds of labellings at once); with ``per_run`` also the sums
    of 1, b_t and c_t over every run (B, N T + 1) (:func:`_per_run`)."""
    B = phase.shape[0]
    m = mask.to(c.dtype)
    cm = (c * m).reshape(-1, mask.numel())  # (1 or B, N T)
    b = ((phase == 0) & mask).to(c.dtype).reshape(B, -1)
    out = {"n": m.sum().expand(B), "b": b.sum(-1), "c": cm.sum(-1).expand(B), "cb": (cm * b).sum(-1),
           "cc": (cm * c.reshape(-1, mask.numel())).sum(-1).expand(B)}
    if per_run:
        out.update(n_r=_per_run(m.reshape(1, -1), phase), b_r=_per_run(b, phase), c_r=_per_run(cm, phase))
    return out


def _gls_statistics(sums: dict[str, Tensor], ratio: float = 0.0) -> tuple[tuple[Tensor, ...], Tensor | None]:
    """MNIW statistics (counts, Szz, Suz, Suu) of shape (B, 1, ...) for the regressors [1, b_t] (those of
    :func:`~lfd_torch.segmentation.field.field_statistics`) from :func:`_sums`, and log |Omega| (B,) (None for
    g = 0). With a pace ratio g > 0 (module docstring, "Pace of a run") they are the generalised least-squares
    statistics X^T Omega^-1 X, Omega = blockdiag_r(I + g 1 1^T) over the runs r: per run,
    sum_t x_t y_t - g / (1 + g n_r) (sum_t x_t)(sum_t y_t), and log |Omega| = sum_r log(1 + g n_r)."""
    n = sums["n"]
    s_11, s_1b, s_bb, s_c, s_cb, s_cc = n, sums["b"], sums["b"], sums["c"], sums["cb"], sums["cc"]
    log_det = None
    if ratio > 0.0:
        n_r, b_r, c_r = sums["n_r"], sums["b_r"], sums["c_r"]
        f = ratio / (1.0 + ratio * n_r)
        s_11 = s_11 - (f * n_r * n_r).sum(-1)
        s_1b = s_1b - (f * n_r * b_r).sum(-1)
        s_bb = s_bb - (f * b_r * b_r).sum(-1)
        s_c = s_c - (f * c_r * n_r).sum(-1)
        s_cb = s_cb - (f * c_r * b_r).sum(-1)
        s_cc = s_cc - (f * c_r * c_r).sum(-1)
        log_det = torch.log1p(ratio * n_r).sum(-1)
    B = n.shape[0]
    szz = torch.stack([torch.stack([s_11, s_1b], -1), torch.stack([s_1b, s_bb], -1)], -2)  # (B, 2, 2)
    suz = torch.stack([s_c, s_cb], -1).unsqueeze(-2)  # (B, 1, 2)
    return (n.unsqueeze(-1), szz.unsqueeze(1), suz.unsqueeze(1), s_cc.view(B, 1, 1, 1)), log_det


def _statistics(c: Tensor, mask: Tensor, phase: Tensor) -> tuple[Tensor, ...]:
    """MNIW statistics (counts, Szz, Suz, Suu) of shape (B, 1, ...) of the labellings' phases (B, N, T), no
    pace levels (:func:`_gls_statistics` with g = 0)."""
    return _gls_statistics(_sums(c, mask, phase))[0]


def _per_run(x: Tensor, phase: Tensor) -> Tensor:
    """(B, N T + 1) sums of x (1 or B, N T) over the runs of the phases (B, N, T): run r of sequence i holds the
    points from one run start (phase 0, in the mask or not) to the next; slots that hold no run are 0."""
    B, N, T = phase.shape
    run = (phase == 0).long().cumsum(-1) + T * torch.arange(N, device=phase.device).unsqueeze(-1)  # 1 + i T ..
    return x.new_zeros(B, N * T + 1).scatter_add_(-1, run.reshape(B, -1), x.expand(B, -1))


def dwell_posterior(prior: FieldPrior, c: Tensor, mask: Tensor, phase: Tensor) -> FieldPrior:
    """NIG posterior of (mu, delta, sigma^2) for B labellings: batch shape (B, 1); phase (B, N, T)."""
    return field_posterior(prior, *_statistics(c, mask, phase))


def dwell_evidence(prior: FieldPrior, c: Tensor, mask: Tensor, phase: Tensor,
                   pace_ratios: tuple[float, ...] = (0.0,)) -> Tensor:
    """(B,) log p(c | b) with (mu, delta, sigma^2) integrated out, for the phases (B, N, T) of B labellings.

    ``pace_ratios``: the values of g = (spread of the runs' pace levels / sigma)^2 under a uniform prior, integrated
    out too (module docstring, "Pace of a run"); (0,): no level per run (:data:`PACE_RATIOS` for the default grid).
    """
    sums = _sums(c, mask, phase, per_run=any(g > 0.0 for g in pace_ratios))
    out = []
    for g in pace_ratios:
        stats, log_det = _gls_statistics(sums, float(g))
        ev = field_log_marginal_likelihood(prior, *stats)[..., 0]
        out.append(ev if log_det is None else ev - 0.5 * log_det)
    if len(out) == 1:
        return out[0]
    return torch.logsumexp(torch.stack(out), 0) - math.log(len(out))


def dwell_start(seen: Tensor) -> tuple[Tensor, Tensor]:
    """The chains' neutral start from the dwell values ``seen`` (n,) under the mask: (mu, delta) = (mean of c, 0) (2,)
    (no dwell effect until the states say otherwise) and sigma^2 = their variance, floored at 1e-6 ().

    With fewer than 2 values (short sequences, or a ``min_length`` near half a sequence, leave at most one grid point
    between the first and the last run's minimum duration) the sample variance, and with none the mean, are undefined:
    then mu = 0 (c is a log ratio to the median) and sigma^2 = the prior's E[sigma^2] (:data:`_NOISE_MEAN`); the term
    hardly constrains the labelling either way, and the Gibbs step draws the parameters from their (proper) NIG
    posterior from the first sweep on."""
    mu = seen.mean() if seen.numel() else seen.new_zeros(())
    noise = seen.var().clamp_min(1e-6) if seen.numel() >= 2 else seen.new_full((), _NOISE_MEAN)
    return torch.stack([mu, torch.zeros_like(mu)]), noise


def dwell_log_likelihood(c: Tensor, mask: Tensor, beta: Tensor, noise: Tensor) -> Tensor:
    """(B, N, T, 2) log N(c_t; mu + delta b, sigma^2) for b = 0 (inside a run) and b = 1 (first point of a run),
    0 outside the mask; c (N, T) or (B, N, T), beta (B, 2) = (mu, delta), noise (B,) = sigma^2."""
    N, T = mask.shape
    means = torch.stack([beta[:, 0], beta[:, 0] + beta[:, 1]], -1).unsqueeze(-1)  # (B, 2, 1)
    cov = noise.view(-1, 1, 1, 1).expand(-1, 2, 1, 1)
    ll = gaussian_log_density(c.reshape(-1, N * T, 1), means, cov)  # (B, N T, 2)
    return (ll * mask.reshape(1, N * T, 1).to(ll.dtype)).reshape(-1, N, T, 2)


def dwell_log_prob(prior: FieldPrior, c: Tensor, mask: Tensor, phase: Tensor, beta: Tensor, noise: Tensor) -> Tensor:
    """(B,) log p(c | b, mu, delta, sigma^2) + log NIG(mu, delta, sigma^2): the dwell part of the joint log
    probability of B chains with phases (B, N, T)."""
    ll = dwell_log_likelihood(c, mask, beta, noise)
    start = ((phase == 0) & mask).long().unsqueeze(-1)
    lp = ll.gather(-1, start).squeeze(-1).sum((-1, -2))
    return lp + field_log_density(beta.unsqueeze(-2), noise.view(-1, 1, 1), prior)


def posterior_summary(post: FieldPrior) -> dict[str, float]:
    """Posterior means of mu, delta and sigma of a single labelling's posterior (batch shape (1, 1))."""
    mean = post.mean.reshape(-1)
    var = float(post.scale.reshape(-1)[0]) / max(float(post.dof.reshape(-1)[0]) - 2.0, 1e-12)
    return {"dwell_mean": float(mean[0]), "dwell_shift": float(mean[1]), "dwell_noise": math.sqrt(var)}
