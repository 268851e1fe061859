"""Direction-field emission of the BP-GM-HMM: each state is an affine field of motion directions over positions.

Notation:
    d  state dimension, p = d + 1 regressor dimension
    x  (..., d) positions, standardised: x~ = (x - centre) / radius (radius = RMS distance to the centre)
    z  (..., p) regressor [x~, 1]
    u  (..., d) unit direction of motion v / ||v||
    w  (...,) direction reliability in (0, 1]: s^2 / (s^2 + s0^2), s = ||v|| the speed, s0 the rest speed
    B  (..., K, d, p) field of state k: E[u | x, k] = B_k z
    Psi (..., K, d, d) direction noise covariance at full reliability: u | x, k ~ N(B_k z, Psi_k / w)
    MNIW(M0, V0, nu0, S0): Psi ~ IW(nu0, S0), B | Psi ~ MN(M0, Psi, V0)

Why this emission (the paper leaves "x_t" open, NOTES.md sec. 2). A Gaussian on the position alone cannot be
the step model: along a uniformly traversed straight leg, splitting one state into two halves multiplies the
density of every sample by about 2, so the likelihood gains n log 2 nats for n samples and the posterior always
prefers more states on longer legs; it also cannot tell an out-and-back leg, or two steps that pass through one
region, apart. What changes at a step boundary is the direction of motion as a function of where the robot is:
a step is a piece of path that one stable primitive ("a smooth vector field") reproduces. So the emission of state
k is the conditional density of the unit direction given the position under an affine field,

    p(u_t | x_t, s_t = k) = N(u_t; B_k [x~_t, 1], Psi_k / w_t).

A straight leg has a constant field (B_k = [0, u]); a circular arc has u = R (x - c) / r, exactly affine; a corner,
a reversal or a cusp needs two fields, because an affine field is continuous in x. A long leg is not split: a
second state gains nothing once the first explains the directions. The positions are the covariates (they carry
the spatial identification the paper asks of the Gaussian emission: a field is anchored in space through its
offset and slope); they are not themselves modelled, so the position density of a step is taken from the step's
samples afterwards (subtask spaces, :mod:`.segmentation`).

Robustness: the emission is the Student t with ``dof`` = nu (a Gaussian scale mixture, u ~ N(B z, Psi / (w
lambda)), lambda ~ Gamma(nu / 2, nu / 2)), because a few directions are not those of any field: the chord across
a corner, a direction measured at rest whose noise is not small. Under a Gaussian those would be paid for by a
state of their own; under the t they cost about log of their distance. The conditional draw of the parameters
samples lambda_t | state, residual ~ Gamma((nu + d) / 2, (nu + w r^T Psi^-1 r) / 2) and then uses the Gaussian
update with weights w_t lambda_t (data augmentation; the lambda are discarded after the update).

The reliability weight w_t accounts for the direction of a slow motion being noisy: for a velocity v = s u + e
with isotropic noise e of scale sigma_v per axis, the direction error scales like sigma_v / s, so the direction
noise covariance is Psi / w with w = s^2 / (s^2 + s0^2); the true squared speed s^2 is estimated without the bias
of the noise, ||v||^2 - d sigma_v^2 (clamped at 0). A sample at rest (w -> 0) carries no direction information, and its state is
then decided by its neighbours (the sticky transitions), which is what one expects of a pause at a corner.
With s0 = sigma_v / sigma_u (sigma_v the velocity noise per axis, sigma_u = ``direction_noise``) and
Psi = sigma_u^2 I, Psi / w = sigma_u^2 I + sigma_v^2 / s^2 I: the tolerance of the field plus the propagated
velocity noise (:func:`lfd_torch.segmentation.segment` estimates sigma_v from the data).

The noise model behind it is additive: a measured direction is the field's direction, with the field's tolerance
Psi_k, plus the propagated velocity noise, u_t ~ N(B_k z_t, Psi_k + c_t I) with c_t = sigma_v^2 / s_t^2 =
sigma_u^2 (1 / w_t - 1) (:func:`field_log_likelihood_additive`). The sampler uses Psi_k / w_t =
Psi_k + c_t Psi_k / sigma_u^2 instead, because it keeps the MNIW update conjugate (weighted statistics); the two
agree when Psi_k = sigma_u^2 I, and at full speed (c_t -> 0) for any Psi_k. They differ where a sample carries no
direction information (w_t -> 0): under Psi_k / w_t the ratio of the densities of two states tends to
(|Psi_b| / |Psi_a|)^(1/2), so at a rest the state with the tighter field is preferred for no reason in the data,
while under the additive model it tends to 1 (both densities become N(u; 0, c_t I)), as it should. The
change-point posterior that places every switch at full rate (:mod:`.segmentation`, item 3) uses the additive
model; it only moves a switch between the two states the sampler put on either side of it.

Conjugate prior (Matrix-Normal-Inverse-Wishart; Minka 2000, "Bayesian linear regression"): with weighted statistics
Szz = sum_t w_t z_t z_t^T, Suz = sum_t w_t u_t z_t^T, Suu = sum_t w_t u_t u_t^T and n = number of samples,

    V_n^-1 = V0^-1 + Szz,   M_n = (M0 V0^-1 + Suz) V_n,   nu_n = nu0 + n,
    S_n = S0 + Suu + M0 V0^-1 M0^T - M_n V_n^-1 M_n^T.

The prior is set on the standardised scale: M0 = 0; E[Psi] = ``direction_noise``^2 I; V0 = diag(1, ..., 1, 1) /
``direction_noise``^2 (the slope entries scaled by ``slope_scale``^2, default 1, :func:`field_prior`), so that a
priori the slope entries have a standard deviation of about 1 (a field may turn the
direction by about a radian per radius of the data, i.e. curvature radii down to the data's own size) and the
offset about 1 (a unit direction).

The deviations u_t - B_k z_t are independent here (a white tolerance). :func:`correlated_tolerance_observations`
gives the conjugate views of a correlated (AR(1)) tolerance, which the sampler's collapsed score uses with
``tolerance_correlation`` (:mod:`.sampler`, "Correlated tolerance").
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError
from lfd_torch.gmm import NIWPrior, inverse_wishart_log_density, log_multigamma, sample_niw
from lfd_torch.gmm.gaussian import LOG_2PI

__all__ = ["FieldPrior", "FieldObservations", "field_observations", "field_prior", "field_statistics",
           "field_posterior", "field_log_marginal_likelihood", "straight_field_prior", "field_mixture_evidence",
           "field_mixture_posterior_mean", "rotation_field_evidence", "sample_field", "field_log_density",
           "field_log_likelihood",
           "field_log_likelihood_additive", "correlated_tolerance_observations", "correlated_tolerance_prior",
           "demo_offset_statistics", "TOLERANCE_MEMORY"]



@dataclass(frozen=True, eq=False)
class FieldPrior:
    """MNIW parameters; fields may carry leading batch dimensions (...).

    Attributes:
        mean: (..., d, p) M.
        row_covariance: (..., p, p) V (the column covariance of B given Psi, in the regressor space).
        dof: (...,) nu.
        scale: (..., d, d) S.
    """

    mean: Tensor
    row_covariance: Tensor
    dof: Tensor
    scale: Tensor


@dataclass(frozen=True, eq=False)
class FieldObservations:
    """What the emission sees of a batch of padded sequences.

    Attributes:
        z: (N, T, p) regressors [x~, 1].
        u: (N, T, d) unit directions.
        w: (N, T) reliabilities (0 on padding).
        centre: (d,) and radius: () of the standardisation.
    """

    z: Tensor
    u: Tensor
    w: Tensor
    centre: Tensor
    radius: Tensor


def field_observations(
    x: Tensor, v: Tensor, valid: Tensor, *, velocity_noise: Tensor | float = 0.0, direction_noise: float = 0.2,
    speed_floor: float = 0.0, centre: Tensor | None = None, radius: Tensor | None = None,
) -> FieldObservations:
    """Regressors, unit directions and reliabilities of padded sequences.

    Args:
        x: (N, T, d) positions.
        v: (N, T, d) velocities.
        valid: (N, T) bool, False on padding.
        velocity_noise: sigma_v, standard deviation of the velocity noise per axis, a number, one per sequence
            (N,) or one per sample (N, T), >= 0 (unit of v).
        direction_noise: sigma_u of the fields (the prior's expected direction noise).
        speed_floor: s0 is at least this (unit of v): for noise-free data, a direction at rest is still unreliable.
        centre, radius: the standardisation (None: from the valid samples of x).

    Returns:
        FieldObservations.
    """
    if x.shape != v.shape or x.shape[:2] != valid.shape:
        raise ShapeMismatchError(f"x {tuple(x.shape)}, v {tuple(v.shape)}, valid {tuple(valid.shape)} differ")
    sv = torch.as_tensor(velocity_noise, dtype=x.dtype, device=x.device)
    shape_ok = sv.ndim == 0 or (sv.ndim == 1 and sv.shape[0] == x.shape[0]) or (sv.ndim == 2 and sv.shape == x.shape[:2])
    if not shape_ok or not bool((sv >= 0).all()):
        raise InvalidArgumentError("velocity_noise must be >= 0: a number, one per sequence (N,) or one per sample "
                                   f"(N, T), got {velocity_noise!r}")
    if not direction_noise > 0:
        raise InvalidArgumentError(f"direction_noise must be > 0, got {direction_noise!r}")
    sv = sv.reshape(-1, 1) if sv.ndim == 1 else sv
    s0 = (sv / direction_noise).clamp_min(speed_floor)
    pts = x[valid]
    if centre is None:
        centre = pts.mean(0)
    if radius is None:
        radius = ((pts - centre).square().sum(-1).mean()).sqrt().clamp_min(torch.finfo(x.dtype).tiny)
    xs = (x - centre) / radius
    z = torch.cat([xs, torch.ones_like(xs[..., :1])], -1)
    speed = v.norm(dim=-1)
    u = v / speed.clamp_min(torch.finfo(x.dtype).tiny).unsqueeze(-1)
    d = x.shape[-1]
    signal = (speed.square() - d * sv.square()).clamp_min(0.0)  # E[s^2] = s_true^2 + d sigma_v^2
    w = signal / (signal + s0.square()).clamp_min(torch.finfo(x.dtype).tiny)
    w = torch.where(valid, w.clamp_min(1e-8), torch.zeros_like(w))
    u = torch.where(valid.unsqueeze(-1), u, torch.zeros_like(u))
    return FieldObservations(z=z, u=u, w=w, centre=centre, radius=radius)


def field_prior(dim: int, *, direction_noise: float = 0.2, extra_dof: float = 2.0, slope_scale: float = 1.0,
                dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> FieldPrior:
    """The weakly informative MNIW prior of the module docstring, on the standardised scale.

    Args:
        dim: d.
        direction_noise: prior expected standard deviation of the direction noise (unit vectors; radians for small
            errors).
        extra_dof: nu0 - d - 1 (> 0): the weight of that expectation.
        slope_scale: prior standard deviation of the slope entries (> 0; per radius of the data): V0 =
            diag(slope_scale^2, ..., slope_scale^2, 1) / ``direction_noise``^2. 1 lets a field turn the direction
            by about a radian per radius; larger admits tighter curves and charges a gentle one a larger Occam
            factor.
    """
    if not (direction_noise > 0 and extra_dof > 0 and slope_scale > 0):
        raise InvalidArgumentError("direction_noise, extra_dof and slope_scale must be > 0")
    p = dim + 1
    dof = dim + 1.0 + extra_dof
    spread = torch.tensor([float(slope_scale) ** 2] * dim + [1.0], dtype=dtype, device=device)
    return FieldPrior(
        mean=torch.zeros(dim, p, dtype=dtype, device=device),
        row_covariance=torch.diag(spread) / direction_noise**2,
        dof=torch.tensor(dof, dtype=dtype, device=device),
        scale=torch.eye(dim, dtype=dtype, device=device) * direction_noise**2 * (dof - dim - 1.0),
    )


def field_statistics(obs_z: Tensor, obs_u: Tensor, obs_w: Tensor, weights: Tensor) -> tuple[Tensor, ...]:
    """Sufficient statistics per state.

    Args:
        obs_z: (..., n, p), obs_u: (..., n, d), obs_w: (..., n) reliabilities.
        weights: (..., n, K) state responsibilities (one-hot for hard labels, 0 on padding).

    Returns:
        counts (..., K), Szz (..., K, p, p), Suz (..., K, d, p), Suu (..., K, d, d).
    """
    counts = weights.sum(-2)
    wt = (weights * obs_w.unsqueeze(-1)).transpose(-1, -2)  # (..., K, n)

    def moment(a: Tensor, b: Tensor) -> Tensor:  # sum_t wt_kt a_t b_t^T as one matmul over the flattened outer products
        outer = (a.unsqueeze(-1) * b.unsqueeze(-2)).flatten(-2)  # (..., n, i j)
        return (wt @ outer).unflatten(-1, (a.shape[-1], b.shape[-1]))

    return counts, moment(obs_z, obs_z), moment(obs_u, obs_z), moment(obs_u, obs_u)


def demo_offset_statistics(counts: Tensor, szz: Tensor, suz: Tensor, suu: Tensor, ratio: float
                           ) -> tuple[tuple[Tensor, ...], Tensor]:
    """Statistics of a state whose every demonstration adds its own offset to the shared field.

    Sequence i of state k sees u_t ~ N((B_k + Delta_ik e_p^T) z_t, Psi_k / w_t), Delta_ik ~ N(0, ``ratio`` Psi_k)
    (e_p the offset regressor), independent across sequences. Integrating Delta_ik out leaves a matrix-normal
    regression on B_k with the same Psi_k whose row covariance is W_i^-1 + ratio z_p z_p^T over the samples of
    sequence i (z_p the offset column); by Woodbury its weighted statistics are those of the sequence less a
    rank-one term, with g_i = ratio / (1 + ratio a_i), a_i = Szz_i[p, p]:

        Szz* = Szz_i - g_i Szz_i[:, p] Szz_i[p, :],   Suz* = Suz_i - g_i Suz_i[:, p] Szz_i[p, :],
        Suu* = Suu_i - g_i Suz_i[:, p] Suz_i[:, p]^T,

    and the evidence gains -d / 2 log(1 + ratio a_i) per sequence (the determinant of the row covariance). The MNIW
    update and evidence of :func:`field_log_marginal_likelihood` on the sums over sequences are then exact. The
    same as an MNIW regression with one extra offset column per sequence of prior variance ``ratio``.

    Args:
        counts (..., N, K), szz (..., N, K, p, p), suz (..., N, K, d, p), suu (..., N, K, d, d): per-sequence
            statistics (:func:`field_statistics` with the sequence axis kept); ratio >= 0.

    Returns:
        The statistics summed over the N sequences ((..., K), (..., K, p, p), ...) and the log-determinant term
        (..., K) to add to the evidence.
    """
    d = suu.shape[-1]
    a = szz[..., -1, -1]  # (..., N, K)
    g = (ratio / (1.0 + ratio * a))[..., None, None]
    zc, uc = szz[..., :, -1:], suz[..., :, -1:]  # (..., N, K, p, 1), (..., N, K, d, 1)
    szz_s = szz - g * zc @ zc.transpose(-1, -2)
    suz_s = suz - g * uc @ zc.transpose(-1, -2)
    suu_s = suu - g * uc @ uc.transpose(-1, -2)
    extra = (-0.5 * d * torch.log1p(ratio * a)).sum(-2)
    return (counts.sum(-2), szz_s.sum(-4), suz_s.sum(-4), suu_s.sum(-4)), extra


def field_posterior(prior: FieldPrior, counts: Tensor, szz: Tensor, suz: Tensor, suu: Tensor) -> FieldPrior:
    """Conjugate MNIW update (module docstring); batch shape (..., K)."""
    v0_inv = torch.linalg.inv(prior.row_covariance)
    prec_n = v0_inv + szz
    prec_n = 0.5 * (prec_n + prec_n.transpose(-1, -2))
    chol = torch.linalg.cholesky(prec_n)
    v_n = torch.cholesky_inverse(chol)
    a = prior.mean @ v0_inv + suz  # (..., d, p)
    m_n = a @ v_n
    s_n = prior.scale + suu + prior.mean @ v0_inv @ prior.mean.transpose(-1, -2) - m_n @ a.transpose(-1, -2)
    s_n = 0.5 * (s_n + s_n.transpose(-1, -2))
    return FieldPrior(mean=m_n, row_covariance=0.5 * (v_n + v_n.transpose(-1, -2)), dof=prior.dof + counts,
                      scale=s_n)


def _chol_logdet(matrix: Tensor) -> Tensor:
    return 2.0 * torch.log(torch.diagonal(torch.linalg.cholesky(matrix), dim1=-2, dim2=-1)).sum(-1)


def field_log_marginal_likelihood(prior: FieldPrior, counts: Tensor, szz: Tensor, suz: Tensor, suu: Tensor) -> Tensor:
    """log p(u_1..n | z_1..n) with (B, Psi) integrated out under the MNIW prior, from weighted statistics.

    With weights omega_t (u_t ~ N(B z_t, Psi / omega_t)), the rescaled sqrt(omega_t) u_t are Gaussian regressions on
    sqrt(omega_t) z_t with covariance Psi, whose evidence is (Minka 2000)

        log p = -n d / 2 log pi + d / 2 log(|V_n| / |V0|) + log Gamma_d(nu_n / 2) - log Gamma_d(nu0 / 2)
                + nu0 / 2 log|S0| - nu_n / 2 log|S_n|,

    and the change of variables adds d / 2 sum_t log omega_t, which the caller adds (it does not depend on the
    state). Batch shape (..., K); exactly 0 for empty states.
    """
    return _log_evidence(prior, field_posterior(prior, counts, szz, suz, suu), counts)


def _log_evidence(prior: FieldPrior, post: FieldPrior, counts: Tensor) -> Tensor:
    """The evidence formula of :func:`field_log_marginal_likelihood` from the prior and its posterior."""
    d = prior.scale.shape[-1]
    out = (
        -0.5 * d * math.log(math.pi) * counts
        + 0.5 * d * (_chol_logdet(post.row_covariance) - _chol_logdet(prior.row_covariance))
        + log_multigamma(0.5 * post.dof, d)
        - log_multigamma(0.5 * prior.dof, d)
        + 0.5 * prior.dof * _chol_logdet(prior.scale)
        - 0.5 * post.dof * _chol_logdet(post.scale)
    )
    return torch.where(counts > 0, out, torch.zeros_like(out))


def straight_field_prior(prior: FieldPrior) -> FieldPrior:
    """The prior of a straight state: slope fixed at 0, so the field is its offset column alone (regressor [1])."""
    return FieldPrior(mean=prior.mean[..., -1:], row_covariance=prior.row_covariance[..., -1:, -1:], dof=prior.dof,
                      scale=prior.scale)


def _straight_posterior(prior: FieldPrior, counts: Tensor, szz: Tensor, suz: Tensor, suu: Tensor
                        ) -> tuple[FieldPrior, FieldPrior]:
    """The straight prior and its posterior: the MNIW on the statistics of the offset regressor alone."""
    straight = straight_field_prior(prior)
    return straight, field_posterior(straight, counts, szz[..., -1:, -1:], suz[..., -1:], suu)


def _affine(prior: FieldPrior, counts: Tensor, szz: Tensor, suz: Tensor, suu: Tensor, wide: FieldPrior | None
            ) -> tuple[Tensor, Tensor, Tensor]:
    """log p(u | z, affine) and the posterior means of B and Psi under the affine slab: ``prior`` alone, or an equal
    mixture of ``prior`` and ``wide`` (a second slope scale), each component's means weighted by its posterior
    probability."""
    d = suu.shape[-1]
    means, psis, evs = [], [], []
    for component in (prior,) if wide is None else (prior, wide):
        post = field_posterior(component, counts, szz, suz, suu)
        means.append(post.mean)
        psis.append(post.scale / (post.dof - d - 1.0).clamp_min(1.0)[..., None, None])
        evs.append(_log_evidence(component, post, counts))
    if wide is None:
        return evs[0], means[0], psis[0]
    ev = torch.logaddexp(evs[0], evs[1]) - math.log(2.0)
    r = torch.exp(evs[1] - math.log(2.0) - ev)[..., None, None]  # P(wide | u, z, affine)
    return ev, (1 - r) * means[0] + r * means[1], (1 - r) * psis[0] + r * psis[1]


@functools.lru_cache(maxsize=16)
def _rotation_map(d: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """(d p, q) G with vec(B) = G theta (vec stacks the columns of B), theta = (w_ij for i < j, b), B = [W, b],
    W = sum_ij w_ij (e_i e_j^T - e_j e_i^T) skew-symmetric: q = d (d - 1) / 2 + d."""
    pairs = [(i, j) for i in range(d) for j in range(i + 1, d)]
    with torch.inference_mode(False):  # cached: a normal tensor even when first built by the sampler (inference mode)
        G = torch.zeros(d * (d + 1), len(pairs) + d, dtype=dtype, device=device)
        for k, (i, j) in enumerate(pairs):
            G[j * d + i, k] = 1.0  # B[i, j] = w_ij
            G[i * d + j, k] = -1.0  # B[j, i] = -w_ij
        for i in range(d):
            G[d * d + i, len(pairs) + i] = 1.0  # B[i, d] = b_i
    return G


def rotation_field_evidence(prior: FieldPrior, counts: Tensor, szz: Tensor, suz: Tensor, suu: Tensor
                            ) -> tuple[Tensor, Tensor, Tensor]:
    """Evidence and posterior means of a rigid-rotation field: E[u | x] = W x~ + b with W skew-symmetric and an
    isotropic tolerance Psi = sigma^2 I.

    A circular arc in a plane is u = R (x - c) / r, R a quarter turn in the plane: a skew W = R / r (one rate per
    plane, d (d - 1) / 2 in all) and an offset b, q = d (d - 1) / 2 + d parameters theta against the affine field's
    d (d + 1). Two arcs meeting at a sharp corner are no single rotation, so this component raises the evidence of a
    true arc and not that of such a merge (a rounded corner with short stretches of its legs is close to one wide
    arc, and there it helps the merge too). Prior (the same scales as ``prior``): theta | sigma^2 ~ N(0, sigma^2 L0^-1)
    with L0^-1 diagonal (each rate the slope variance V0[0, 0], each offset the offset variance V0[p - 1, p - 1] of
    ``prior.row_covariance``), sigma^2 ~ IG(a0, b0) with a0 = (nu0 - d - 1) d / 2 + 1 and mean E[Psi]_11 of
    ``prior``. Normal-inverse-gamma regression on the weighted statistics (u_t ~ N(B z_t, sigma^2 / omega_t I)):
    with vec(B) = G theta, Gram = G^T (Szz kron I_d) G, c = G^T vec(Suz), y = tr Suu, n = d counts scalar
    observations,

        L_n = L0 + Gram,  m = L_n^-1 c,  a_n = a0 + n / 2,  b_n = b0 + (y - m^T c) / 2,
        log p = -n / 2 log 2 pi + 1/2 log |L0| / |L_n| + a0 log b0 - a_n log b_n + log Gamma(a_n) - log Gamma(a0),

    without the Jacobian d / 2 sum_t log omega_t (added by the caller, as for
    :func:`field_log_marginal_likelihood`). Batch shape (..., K); 0 for empty states.

    Returns:
        log p(u | z, rotation) (..., K), E[B | u, z] (..., K, d, p) and E[Psi | u, z] = E[sigma^2] I (..., K, d, d).
    """
    d = suu.shape[-1]
    p = d + 1
    G = _rotation_map(d, szz.dtype, szz.device)
    n_rates = G.shape[-1] - d
    v0 = torch.diagonal(prior.row_covariance, dim1=-2, dim2=-1)
    variances = torch.cat([v0[..., :1].expand(*v0.shape[:-1], n_rates), v0[..., -1:].expand(*v0.shape[:-1], d)], -1)
    eye = torch.eye(d, dtype=szz.dtype, device=szz.device)
    kron = (szz[..., :, None, :, None] * eye[:, None, :]).reshape(*szz.shape[:-2], p * d, p * d)  # Szz kron I_d
    gram = G.T @ kron @ G
    cross = (G.T @ suz.transpose(-1, -2).reshape(*suz.shape[:-2], d * p, 1)).squeeze(-1)
    precision = torch.diag_embed(1.0 / variances) + gram
    chol = torch.linalg.cholesky(0.5 * (precision + precision.transpose(-1, -2)))
    m = torch.cholesky_solve(cross.unsqueeze(-1), chol).squeeze(-1)
    extra = prior.dof - d - 1.0
    a0 = extra * d / 2.0 + 1.0
    b0 = prior.scale[..., 0, 0] / extra * (a0 - 1.0)
    a_n = a0 + 0.5 * d * counts
    b_n = b0 + 0.5 * (torch.diagonal(suu, dim1=-2, dim2=-1).sum(-1) - (m * cross).sum(-1)).clamp_min(0.0)
    log_det = -torch.log(variances).sum(-1) - 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    ev = (-0.5 * d * counts * math.log(2.0 * math.pi) + 0.5 * log_det + a0 * torch.log(b0) - a_n * torch.log(b_n)
          + torch.lgamma(a_n) - torch.lgamma(a0))
    mean = (G @ m.unsqueeze(-1)).squeeze(-1).unflatten(-1, (p, d)).transpose(-1, -2)
    psi = (b_n / (a_n - 1.0))[..., None, None] * eye
    return torch.where(counts > 0, ev, torch.zeros_like(ev)), mean, psi


def _mixture(prior: FieldPrior, counts: Tensor, szz: Tensor, suz: Tensor, suu: Tensor, straight_weight: float,
             wide: FieldPrior | None = None, rotation_weight: float = 0.0
             ) -> tuple[Tensor, Tensor, FieldPrior | None, Tensor, Tensor]:
    """The slab's posterior means (B, Psi), the straight posterior, log p(u | z) and log P(straight | u, z) under
    the spike-and-slab prior (the slab: affine, or with ``rotation_weight`` r > 0 the mixture (1 - r) affine + r
    rotation, :func:`rotation_field_evidence`)."""
    ev_a, mean_a, psi_a = _affine(prior, counts, szz, suz, suu, wide)
    if rotation_weight > 0:
        ev_r, mean_r, psi_r = rotation_field_evidence(prior, counts, szz, suz, suu)
        ev_slab = torch.logaddexp(math.log1p(-rotation_weight) + ev_a, math.log(rotation_weight) + ev_r)
        r = torch.exp(math.log(rotation_weight) + ev_r - ev_slab)[..., None, None]  # P(rotation | u, z, slab)
        mean_a, psi_a, ev_a = (1 - r) * mean_a + r * mean_r, (1 - r) * psi_a + r * psi_r, ev_slab
    if straight_weight <= 0:
        return mean_a, psi_a, None, ev_a, torch.full_like(ev_a, float("-inf"))
    straight, post_s = _straight_posterior(prior, counts, szz, suz, suu)
    log_s = math.log(straight_weight) + _log_evidence(straight, post_s, counts)
    ev = torch.logaddexp(math.log1p(-straight_weight) + ev_a, log_s)
    return mean_a, psi_a, post_s, ev, log_s - ev


def field_mixture_evidence(prior: FieldPrior, counts: Tensor, szz: Tensor, suz: Tensor, suu: Tensor,
                           straight_weight: float, wide: FieldPrior | None = None, rotation_weight: float = 0.0
                           ) -> tuple[Tensor, Tensor]:
    """Evidence of a state under the spike-and-slab field prior: straight (slope 0) with probability rho =
    ``straight_weight``, else affine (``prior``; with ``wide``, an equal mixture of the two slope scales),

        p(u | z) = rho p(u | z, straight) + (1 - rho) p(u | z, affine),
        p(u | z, affine) = p(u | z, prior)  or  (p(u | z, prior) + p(u | z, wide)) / 2,

    all MNIW evidences (:func:`field_log_marginal_likelihood`; the straight one on the statistics of the offset
    regressor alone, under ``prior``). With ``rotation_weight`` r > 0 the affine part is itself the mixture
    (1 - r) p(u | z, affine) + r p(u | z, rotation) (:func:`rotation_field_evidence`). Batch shape (..., K); 0 for
    empty states.

    Returns:
        log p(u | z) and log P(straight | u, z) (-inf when rho = 0).
    """
    return _mixture(prior, counts, szz, suz, suu, straight_weight, wide, rotation_weight)[3:]


def field_mixture_posterior_mean(prior: FieldPrior, counts: Tensor, szz: Tensor, suz: Tensor, suu: Tensor,
                                 straight_weight: float, wide: FieldPrior | None = None, rotation_weight: float = 0.0
                                 ) -> tuple[Tensor, Tensor]:
    """Posterior means E[B | u, z] (..., K, d, p) and E[Psi | u, z] (..., K, d, d) under the spike-and-slab prior of
    :func:`field_mixture_evidence`: the components' means weighted by their posterior probabilities (a straight
    field's slope columns are 0)."""
    mean_a, psi_a, post_s, _, log_ps = _mixture(prior, counts, szz, suz, suu, straight_weight, wide, rotation_weight)
    if post_s is None:
        return mean_a, psi_a
    d = suu.shape[-1]
    psi_s = post_s.scale / (post_s.dof - d - 1.0).clamp_min(1.0)[..., None, None]
    mean_s = torch.cat([torch.zeros_like(mean_a[..., :-1]), post_s.mean], -1)
    ps = torch.exp(log_ps)[..., None, None]
    return ps * mean_s + (1 - ps) * mean_a, ps * psi_s + (1 - ps) * psi_a


def sample_field(params: FieldPrior, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Draw (B, Psi) from MNIW distributions of batch shape (...).

    Psi ~ IW(nu, S) through :func:`lfd_torch.gmm.sample_niw` (its covariance draw), then
    B = M + chol(Psi) G chol(V)^T with G standard normal.

    Returns:
        B (..., d, p), Psi (..., d, d).
    """
    d, p = params.mean.shape[-2:]
    # numpy's rule, not torch.broadcast_shapes, whose first call imports sympy (about 0.3 s inside ``segment``)
    batch = np.broadcast_shapes(params.mean.shape[:-2], params.scale.shape[:-2], params.dof.shape,
                                params.row_covariance.shape[:-2])
    dt, dev = params.mean.dtype, params.mean.device
    niw = NIWPrior(mean=torch.zeros(*batch, d, dtype=dt, device=dev), kappa=torch.ones(batch, dtype=dt, device=dev),
                   dof=params.dof.expand(batch), scale=params.scale.expand(*batch, d, d))
    _, psi = sample_niw(niw, generator)
    g = torch.randn(*batch, d, p, generator=generator, dtype=dt, device=dev)
    l_psi = torch.linalg.cholesky(psi)
    l_v = torch.linalg.cholesky(params.row_covariance.expand(*batch, p, p))
    b = params.mean.expand(*batch, d, p) + l_psi @ g @ l_v.transpose(-1, -2)
    return b, psi


def field_log_density(b: Tensor, psi: Tensor, params: FieldPrior) -> Tensor:
    """log MNIW(B, Psi | params), batched over (...)."""
    d, p = b.shape[-2:]
    l_psi = torch.linalg.cholesky(psi)
    logdet_psi = 2.0 * torch.log(torch.diagonal(l_psi, dim1=-2, dim2=-1)).sum(-1)
    log_iw = inverse_wishart_log_density(psi, params.dof, params.scale)
    l_v = torch.linalg.cholesky(params.row_covariance)
    logdet_v = 2.0 * torch.log(torch.diagonal(l_v, dim1=-2, dim2=-1)).sum(-1)
    diff = b - params.mean  # (..., d, p)
    y = torch.linalg.solve_triangular(l_psi, diff, upper=False)  # Psi^-1/2 diff
    y = torch.linalg.solve_triangular(l_v.expand(*y.shape[:-2], p, p), y.transpose(-1, -2), upper=False)
    log_mn = -0.5 * d * p * LOG_2PI - 0.5 * p * logdet_psi - 0.5 * d * logdet_v - 0.5 * y.square().sum((-1, -2))
    return log_iw + log_mn


def field_log_likelihood(
    z: Tensor, u: Tensor, w: Tensor, b: Tensor, psi: Tensor, dof: float | None = None, *, maha_out: bool = False
) -> Tensor | tuple[Tensor, Tensor]:
    """log t_nu(u_t; B_k z_t, Psi_k / w_t) (Student t; Gaussian with ``dof=None``) of every sample and state.

    Args:
        z: (..., n, p), u: (..., n, d), w: (..., n) (> 0 where the value is used).
        b: (..., K, d, p), psi: (..., K, d, d).
        dof: nu of the Student t; None for the Gaussian N(u_t; B_k z_t, Psi_k / w_t).
        maha_out: also return the squared Mahalanobis distances w_t r^T Psi_k^-1 r, (..., n, K).

    Returns:
        (..., n, K) log densities (and the distances).
    """
    d = u.shape[-1]
    pred = torch.einsum("...kij,...nj->...nki", b, z)  # (..., n, K, d)
    r = u.unsqueeze(-2) - pred
    l_psi = torch.linalg.cholesky(psi)  # (..., K, d, d)
    prec = torch.cholesky_inverse(l_psi)
    maha = torch.einsum("...nki,...kij,...nkj->...nk", r, prec, r)
    half_logdet = torch.log(torch.diagonal(l_psi, dim1=-2, dim2=-1)).sum(-1)  # (..., K)
    wc = w.clamp_min(1e-8).unsqueeze(-1)
    q = wc * maha
    base = 0.5 * d * torch.log(wc) - half_logdet.unsqueeze(-2)
    if dof is None:
        out = base - 0.5 * d * LOG_2PI - 0.5 * q
    else:
        nu = float(dof)
        const = math.lgamma(0.5 * (nu + d)) - math.lgamma(0.5 * nu) - 0.5 * d * math.log(nu * math.pi)
        out = base + const - 0.5 * (nu + d) * torch.log1p(q / nu)
    return (out, q) if maha_out else out


def field_log_likelihood_additive(
    z: Tensor, u: Tensor, w: Tensor, b: Tensor, psi: Tensor, dof: float | None = None, *, direction_noise: float = 0.2
) -> Tensor:
    """log t_nu(u_t; B_k z_t, Psi_k + c_t I), c_t = sigma_u^2 (1 / w_t - 1): the additive noise model (docstring).

    Args:
        z: (..., n, p), u: (..., n, d), w: (..., n) reliabilities in (0, 1].
        b: (..., K, d, p), psi: (..., K, d, d).
        dof: nu of the Student t; None for the Gaussian.
        direction_noise: sigma_u, the one that defined w (:func:`field_observations`).

    Returns:
        (..., n, K) log densities. Equal to :func:`field_log_likelihood` when Psi_k = sigma_u^2 I.
    """
    d = u.shape[-1]
    pred = torch.einsum("...kij,...nj->...nki", b, z)  # (..., n, K, d)
    r = u.unsqueeze(-2) - pred
    c = direction_noise**2 * (1.0 / w.clamp(1e-8, 1.0) - 1.0)  # (..., n) propagated velocity noise
    eye = torch.eye(d, dtype=u.dtype, device=u.device)
    cov = psi.unsqueeze(-4) + c[..., None, None, None] * eye  # (..., n, K, d, d)
    chol = torch.linalg.cholesky(cov)
    y = torch.linalg.solve_triangular(chol, r.unsqueeze(-1), upper=False).squeeze(-1)
    q = y.square().sum(-1)
    half_logdet = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    if dof is None:
        return -half_logdet - 0.5 * d * LOG_2PI - 0.5 * q
    nu = float(dof)
    const = math.lgamma(0.5 * (nu + d)) - math.lgamma(0.5 * nu) - 0.5 * d * math.log(nu * math.pi)
    return -half_logdet + const - 0.5 * (nu + d) * torch.log1p(q / nu)



def correlated_tolerance_prior(prior: FieldPrior, rho: float, ratio: float = 1.0) -> FieldPrior:
    """The field prior of the tolerance of :func:`correlated_tolerance_observations`: Psi is now the covariance of the
    innovations xi_t, whose stationary deviation Psi / (1 - rho^2) is ``ratio``^2 times the expectation of ``prior``,
    so E[Psi] scales by f = ratio^2 (1 - rho^2) and V0 by 1 / f (the prior of B, Psi (x) V0, is unchanged). rho = 0
    and ratio = 1 return ``prior``."""
    f = ratio**2 * (1.0 - rho**2)
    if f == 1.0:
        return prior
    return FieldPrior(mean=prior.mean, row_covariance=prior.row_covariance / f, dof=prior.dof, scale=prior.scale * f)


#: Memory of the correlated tolerance's filter, grid points: a sample that has been in its run longer is predicted
#: from the last ``TOLERANCE_MEMORY`` samples of the run (:func:`correlated_tolerance_observations`).
TOLERANCE_MEMORY = 10


def correlated_tolerance_observations(obs: FieldObservations, rho: float, direction_noise: float,
                                      scale: float | None = None, floor: float = 0.0,
                                      memory: int = TOLERANCE_MEMORY) -> tuple[tuple[Tensor, Tensor, Tensor], ...]:
    """Regressors, directions and weights of a correlated (AR(1)) direction tolerance, one view per age of a sample
    in its run (0: the run's first sample, ..., ``memory``: that many samples or more after it).

    The white emission lets a direction leave its field by independent noise: u_t = B_k z_t + e_t. Along a human
    curve the deviation drifts and persists, at a corner it jumps; a tolerance that is a smooth process charges the
    jump and not the drift. Within a run of state k

        u_t = B_k z_t + eta_t + e_t,   eta_t = rho eta_(t-1) + xi_t,  xi_t ~ N(0, Psi_k),
        e_t ~ N(0, r_t Psi_k),  r_t = c'_t / s_i^2,  eta at a run's first sample ~ N(0, Psi_k / (1 - rho^2)),

    with c'_t = c_t + tau^2 the white noise (the propagated velocity noise c_t = sigma_u^2 (1 / w_t - 1) recovered
    from ``obs``, sigma_u = ``direction_noise``, and a floor tau = ``floor``), s_i^2 = (1 - rho^2) sigma^2 = E[Psi_k]
    per axis (:func:`correlated_tolerance_prior`, sigma = ``scale`` the stationary tolerance): the white noise is
    written in units of Psi_k, as the white emission's Psi_k / w_t (:mod:`.field` docstring), which keeps every
    factor conjugate. The run's directions are then N(vec(B_k Z), Omega (x) Psi_k), Omega = R + diag(r), R the unit
    AR(1) correlation, and the scalar Kalman filter of eta (gain K_j = P_j / (P_j + r_j)) factors that density into
    one-step predictions: u_t - m_t(u) given the filter's prediction m_t, a linear combination of the run's earlier
    directions, is N(B_k (z_t - m_t(z)), S_t Psi_k), S_t = P_t + r_t, the same combination applied to the regressors
    (B_k enters linearly). So each sample is a weighted MNIW regression of u_t - m_t(u) on z_t - m_t(z) with weight
    1 / S_t and log Jacobian d / 2 log(1 / S_t): the sampler's conjugate scores need only the view of each sample's
    age. Beyond ``memory`` samples into a run the filter starts ``memory`` samples back (from the stationary
    prior): a proper density still (each factor is a density of u_t given earlier directions), the exact one for
    runs up to ``memory`` + 1 samples; the filter forgets at about its gain, a few grid points unless the white noise
    dominates. Where a direction carries no information (w_t = 0, r_t infinite) the filter predicts through it, so a
    pause does not reset the deviation: a corner taken at rest is still a jump. rho = 0, sigma = sigma_u and tau = 0
    give the white emission of ``obs`` exactly (every view that of age 0).

    Args:
        obs: (N, T, .) observations of :func:`field_observations` made with ``direction_noise``.
        rho: the correlation of consecutive deviations, in [0, 1).
        direction_noise: sigma_u of ``obs``.
        scale: sigma, the stationary tolerance (> 0); None: ``direction_noise``.
        floor: tau >= 0, the white floor.
        memory: the oldest age with a view of its own (>= 1).

    Returns:
        ``memory`` + 1 views (z, u, w), each (N, T, p), (N, T, d), (N, T): view a of sample t predicts it from the a
        samples before it (fewer at the start of a sequence); w is 0 where ``obs.w`` is (padding).
    """
    if not 0.0 <= rho < 1.0:
        raise InvalidArgumentError(f"tolerance_correlation must be in [0, 1), got {rho!r}")
    scale = direction_noise if scale is None else float(scale)
    if not scale > 0:
        raise InvalidArgumentError(f"scale must be > 0, got {scale!r}")
    if not floor >= 0:
        raise InvalidArgumentError(f"floor must be >= 0, got {floor!r}")
    if int(memory) < 1:
        raise InvalidArgumentError(f"memory must be >= 1, got {memory!r}")
    r2 = 1.0 - rho**2
    seen = obs.w > 0
    if rho == 0.0 and scale == direction_noise and floor == 0.0:
        start = (obs.z, obs.u, obs.w)  # the white emission as it is
        return (start,) * (int(memory) + 1)
    s2 = r2 * scale**2
    c = direction_noise**2 * (1.0 / obs.w.clamp_min(1e-8) - 1.0) + floor**2  # (N, T) white noise c'_t
    r = torch.where(seen, c / s2, torch.full_like(c, float("inf")))

    t = torch.arange(c.shape[1], device=c.device)

    def back(a: Tensor, m: int) -> Tensor:  # a[t - m] at t (a[0] where t < m, where it is never used)
        return a[:, (t - m).clamp_min(0)]

    views = []
    for age in range(int(memory) + 1):
        m_u, m_z = torch.zeros_like(obs.u), torch.zeros_like(obs.z)  # the filter's prediction, applied to u and z
        p = torch.full_like(c, 1.0 / r2)  # its variance: the stationary prior at the run's first sample
        for k in range(age):  # the samples t - age .. t - 1, oldest first
            lag = age - k
            r_j = back(r, lag)
            t_ok = t >= lag  # sample t - lag exists
            gain = torch.where(t_ok & torch.isfinite(r_j), p / (p + r_j.nan_to_num(posinf=1.0)), torch.zeros_like(p))
            m_u = rho * (m_u + gain.unsqueeze(-1) * (back(obs.u, lag) - m_u))
            m_z = rho * (m_z + gain.unsqueeze(-1) * (back(obs.z, lag) - m_z))
            p = rho**2 * (1.0 - gain) * p + 1.0
        w = torch.where(seen, 1.0 / (p + r.nan_to_num(posinf=1.0)), torch.zeros_like(c))
        views.append((obs.z - m_z, obs.u - m_u, w))
    return tuple(views)
