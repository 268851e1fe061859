"""Emission kernels of the BP-GM-HMM segmentation (``segmentation.field``, ``segmentation.dwell``) against independent
references: closed forms written out naively (the matrix-variate t marginal of a Matrix-Normal-Inverse-Wishart
regression, the multivariate t of a normal-inverse-gamma one), explicit dense Gaussian conditioning, the chain rule
of one-step predictive densities, scipy.stats densities and quadrature over the Student t's scale mixture.

Each test writes its reference from the model stated in the module docstrings, not from the kernels' algebra."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats
from scipy.special import multigammaln

from lfd_torch.segmentation.dwell import (
    dwell_evidence,
    dwell_log_prob,
    dwell_mask,
    dwell_prior,
    dwell_regressors,
)
from lfd_torch.segmentation.field import (
    FieldPrior,
    field_log_density,
    field_log_likelihood,
    field_log_marginal_likelihood,
    field_mixture_evidence,
    field_mixture_posterior_mean,
    field_observations,
    field_posterior,
    field_prior,
    field_statistics,
    rotation_field_evidence,
    sample_field,
)

F64 = torch.float64


def _logdet(a: np.ndarray) -> float:
    sign, value = np.linalg.slogdet(a)
    assert sign > 0
    return float(value)


def _matrix_t_logpdf(U: np.ndarray, loc: np.ndarray, omega: np.ndarray, nu: float, s0: np.ndarray) -> float:
    """log density of the matrix-variate t (Gupta & Nagar 2000, ch. 4): U (n, d) | Psi ~ MN(loc, Omega, Psi) (rows
    covary by Omega, columns by Psi), Psi ~ IW(nu, S0) integrated out:

        p(U) = Gamma_d((nu + n) / 2) / Gamma_d(nu / 2) pi^(-n d / 2) |Omega|^(-d / 2) |S0|^(nu / 2)
               |S0 + (U - loc)^T Omega^-1 (U - loc)|^(-(nu + n) / 2)."""
    n, d = U.shape
    r = U - loc
    q = r.T @ np.linalg.solve(omega, r)
    return (multigammaln(0.5 * (nu + n), d) - multigammaln(0.5 * nu, d) - 0.5 * n * d * math.log(math.pi)
            - 0.5 * d * _logdet(omega) + 0.5 * nu * _logdet(s0) - 0.5 * (nu + n) * _logdet(s0 + q))


def _spd(gen: torch.Generator, k: int, scale: float, ridge: float) -> torch.Tensor:
    a = torch.randn(k, k, generator=gen, dtype=F64)
    return scale * a @ a.T + ridge * torch.eye(k, dtype=F64)


def _regression_data(gen: torch.Generator, n: int, d: int, slope: float = 0.0):
    """Regressors z = [x, 1] (n, d + 1), directions u near a constant one plus ``slope`` times the reversed
    positions (n, d) and reliabilities w in [0.3, 1) (n,)."""
    x = torch.randn(n, d, generator=gen, dtype=F64)
    z = torch.cat([x, torch.ones(n, 1, dtype=F64)], -1)
    base = torch.linspace(0.8, -0.4, d, dtype=F64)
    u = base + slope * x.flip(-1) + 0.15 * torch.randn(n, d, generator=gen, dtype=F64)
    w = torch.rand(n, generator=gen, dtype=F64) * 0.7 + 0.3
    return z, u, w


def test_matrix_t_reference_is_the_multivariate_t_for_one_column() -> None:
    """Self-check of the reference used below: for d = 1 the matrix-variate t is scipy's multivariate t with nu dof
    and shape S0 / nu Omega."""
    gen = torch.Generator().manual_seed(1)
    n = 6
    omega = _spd(gen, n, 0.3, 0.5).numpy()
    U = torch.randn(n, 1, generator=gen, dtype=F64).numpy()
    loc = torch.randn(n, 1, generator=gen, dtype=F64).numpy()
    want = stats.multivariate_t(loc=loc[:, 0], shape=0.7 / 3.5 * omega, df=3.5).logpdf(U[:, 0])
    assert _matrix_t_logpdf(U, loc, omega, 3.5, np.array([[0.7]])) == pytest.approx(float(want), abs=1e-10)


@pytest.mark.parametrize("d", [2, 3])
def test_field_evidence_and_posterior_against_the_matrix_t_and_dense_conditioning(d: int) -> None:
    """MNIW regression u_t = B z_t + e_t, e_t ~ N(0, Psi / w_t), B | Psi ~ MN(M0, Psi, V0), Psi ~ IW(nu0, S0), with a
    nonzero M0, a non-diagonal V0 and S0, hard labels over K = 3 states (the last one empty), for d = 2 and 3:

    * the evidence plus the Jacobian d / 2 sum log w is the matrix-variate t of the state's directions with row
      covariance W^-1 + Z V0 Z^T and location Z M0^T (written out with numpy and scipy.special.multigammaln);
    * given any Psi, the posterior of vec(B) from explicit dense Gaussian conditioning of the stacked regression
      (prior covariance Psi kron V0, noise covariance diag(1 / w) kron Psi) has mean M_n and covariance Psi kron V_n;
    * S_n is the residual form S0 + R^T W R + (M_n - M0) V0^-1 (M_n - M0)^T, R = U - Z M_n^T, and nu_n = nu0 + n;
    * an empty state's evidence is exactly 0 (documented)."""
    gen = torch.Generator().manual_seed(20 + d)
    p, n, K = d + 1, 11, 3
    m0 = 0.4 * torch.randn(d, p, generator=gen, dtype=F64)
    v0 = _spd(gen, p, 0.5, 0.4)
    s0 = _spd(gen, d, 0.05, 0.1)
    nu0 = d + 2.5
    prior = FieldPrior(mean=m0, row_covariance=v0, dof=torch.tensor(nu0, dtype=F64), scale=s0)
    z, u, w = _regression_data(gen, n, d, slope=0.3)
    labels = torch.tensor([0, 1, 0, 0, 1, 0, 1, 0, 0, 1, 0])
    weights = torch.nn.functional.one_hot(labels, K).to(F64)
    st = field_statistics(z, u, w, weights)
    ev = field_log_marginal_likelihood(prior, *st)
    post = field_posterior(prior, *st)
    assert ev.shape == (K,)
    psi = _spd(gen, d, 0.1, 0.05).numpy()  # any fixed noise covariance for the conditional posterior of B
    M0, V0, S0 = m0.numpy(), v0.numpy(), s0.numpy()
    for k in range(2):
        rows = (labels == k).numpy()
        Z, U, W = z.numpy()[rows], u.numpy()[rows], w.numpy()[rows]
        m = len(W)
        # evidence: the matrix-variate t
        omega = np.diag(1.0 / W) + Z @ V0 @ Z.T
        want = _matrix_t_logpdf(U, Z @ M0.T, omega, nu0, S0)
        assert float(ev[k]) + 0.5 * d * float(np.log(W).sum()) == pytest.approx(want, abs=1e-9), k
        # B | Psi: dense conditioning, vec row-major (B[i, j] -> i p + j, U[t, i] -> t d + i)
        A = np.zeros((m * d, d * p))
        for t in range(m):
            for i in range(d):
                A[t * d + i, i * p:(i + 1) * p] = Z[t]
        prior_cov = np.kron(psi, V0)
        noise_cov = np.kron(np.diag(1.0 / W), psi)
        precision = np.linalg.inv(prior_cov) + A.T @ np.linalg.solve(noise_cov, A)
        cov = np.linalg.inv(precision)
        mean = cov @ (np.linalg.solve(prior_cov, M0.reshape(-1)) + A.T @ np.linalg.solve(noise_cov, U.reshape(-1)))
        np.testing.assert_allclose(post.mean[k].numpy().reshape(-1), mean, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(np.kron(psi, post.row_covariance[k].numpy()), cov, rtol=1e-9, atol=1e-12)
        # Psi | U: IW(nu0 + n, S_n), S_n in residual form
        Mn = post.mean[k].numpy()
        R = U - Z @ Mn.T
        s_n = S0 + R.T @ np.diag(W) @ R + (Mn - M0) @ np.linalg.solve(V0, (Mn - M0).T)
        np.testing.assert_allclose(post.scale[k].numpy(), s_n, rtol=1e-9, atol=1e-12)
        assert float(post.dof[k]) == nu0 + m
    assert float(ev[2]) == 0.0


def test_field_evidence_is_the_product_of_one_step_predictive_t_densities() -> None:
    """Chain rule: log p(u_1..n | z) = sum_t log p(u_t | u_<t, z), each one-step predictive the multivariate t with
    nu_(t-1) - d + 1 dof, location M_(t-1) z_t and shape S_(t-1) (1 / w_t + z_t^T V_(t-1) z_t) / (nu_(t-1) - d + 1)
    (scipy.stats.multivariate_t), the posterior after t - 1 samples recomputed from scratch at every step in the
    information form (Lambda = V0^-1 + sum w z z^T, M = (M0 V0^-1 + sum w u z^T) Lambda^-1, S in residual form). A
    field prior with slope_scale != 1, d = 2."""
    gen = torch.Generator().manual_seed(7)
    d, n = 2, 12
    prior = field_prior(d, direction_noise=0.3, extra_dof=3.0, slope_scale=1.7)
    z, u, w = _regression_data(gen, n, d, slope=0.4)
    ev = field_log_marginal_likelihood(prior, *field_statistics(z, u, w, torch.ones(n, 1, dtype=F64)))[0]
    M0, V0, S0, nu0 = (prior.mean.numpy(), prior.row_covariance.numpy(), prior.scale.numpy(), float(prior.dof))
    Z, U, W = z.numpy(), u.numpy(), w.numpy()
    lam0 = np.linalg.inv(V0)
    total = 0.0
    for t in range(n):
        Zp, Up, Wp = Z[:t], U[:t], W[:t]
        lam = lam0 + (Zp.T * Wp) @ Zp
        M = (M0 @ lam0 + (Up.T * Wp) @ Zp) @ np.linalg.inv(lam)
        R = Up - Zp @ M.T
        S = S0 + (R.T * Wp) @ R + (M - M0) @ lam0 @ (M - M0).T
        nu = nu0 + t
        df = nu - d + 1
        shape = S * (1.0 / W[t] + Z[t] @ np.linalg.solve(lam, Z[t])) / df
        total += stats.multivariate_t(loc=M @ Z[t], shape=shape, df=df).logpdf(U[t])
    assert float(ev) + 0.5 * d * float(np.log(W).sum()) == pytest.approx(total, abs=1e-9)


def test_straight_component_under_a_slope_scale_against_the_matrix_t() -> None:
    """Spike-and-slab with ``slope_scale`` = 2.5 (the slope entries' prior variance differs from the offset's): the
    straight component is u_t = b + e_t with b | Psi ~ N(0, v Psi), v the OFFSET variance 1 / direction_noise^2, so its
    evidence is the matrix-variate t with row covariance W^-1 + v 1 1^T; the affine one has W^-1 + Z V0 Z^T. The
    mixture evidence log(rho p_s + (1 - rho) p_a), log P(straight | u) and the posterior means (straight: slope 0,
    offset sum w u / (1 / v + sum w), E[Psi] = S_n / (nu_n - d - 1) with S_n in residual form; affine: M_n and its
    S_n / (nu_n - d - 1), M_n by weighted least squares against the prior) written out with numpy."""
    gen = torch.Generator().manual_seed(3)
    d, n, rho, su = 2, 10, 0.5, 0.3
    prior = field_prior(d, direction_noise=su, extra_dof=3.0, slope_scale=2.5)
    z, u, w = _regression_data(gen, n, d, slope=0.33)
    st = field_statistics(z, u, w, torch.ones(n, 1, dtype=F64))
    ev, log_ps = field_mixture_evidence(prior, *st, rho)
    mean, psi = field_mixture_posterior_mean(prior, *st, rho)
    Z, U, W = z.numpy(), u.numpy(), w.numpy()
    V0, S0, nu0 = prior.row_covariance.numpy(), prior.scale.numpy(), float(prior.dof)
    v = 1.0 / su**2
    jac = 0.5 * d * float(np.log(W).sum())
    ev_s = _matrix_t_logpdf(U, np.zeros_like(U), np.diag(1.0 / W) + v * np.ones((n, n)), nu0, S0)
    ev_a = _matrix_t_logpdf(U, np.zeros_like(U), np.diag(1.0 / W) + Z @ V0 @ Z.T, nu0, S0)
    mix = np.logaddexp(math.log(rho) + ev_s, math.log(1 - rho) + ev_a)
    ps = math.exp(math.log(rho) + ev_s - mix)
    assert 0.05 < ps < 0.95  # both components matter
    assert float(ev[0]) + jac == pytest.approx(mix, abs=1e-9)
    assert float(torch.exp(log_ps[0])) == pytest.approx(ps, abs=1e-10)
    # straight posterior
    lam = 1.0 / v + W.sum()
    b_s = (W[:, None] * U).sum(0) / lam
    R = U - b_s
    s_s = S0 + (R.T * W) @ R + np.outer(b_s, b_s) / v
    mean_s = np.concatenate([np.zeros((d, d)), b_s[:, None]], -1)
    psi_s = s_s / (nu0 + n - d - 1)
    # affine posterior
    lam0 = np.linalg.inv(V0)
    M = np.linalg.solve(lam0 + (Z.T * W) @ Z, (Z.T * W) @ U).T
    R = U - Z @ M.T
    s_a = S0 + (R.T * W) @ R + M @ lam0 @ M.T
    psi_a = s_a / (nu0 + n - d - 1)
    np.testing.assert_allclose(mean[0].numpy(), ps * mean_s + (1 - ps) * M, rtol=0, atol=1e-10)
    np.testing.assert_allclose(psi[0].numpy(), ps * psi_s + (1 - ps) * psi_a, rtol=0, atol=1e-10)


def _skew_design(Z: np.ndarray, d: int) -> np.ndarray:
    """(n d, q) design of u_t = W x_t + b, stacked sample-major, with W skew (W[i, j] = w_ij = -W[j, i], i < j, pairs
    in row-major order) and theta = (w_ij..., b): written out from the definition."""
    n = Z.shape[0]
    pairs = [(i, j) for i in range(d) for j in range(i + 1, d)]
    D = np.zeros((n * d, len(pairs) + d))
    for t in range(n):
        x = Z[t, :d]
        for k, (i, j) in enumerate(pairs):
            D[t * d + i, k] += x[j]  # u_i gets w_ij x_j
            D[t * d + j, k] -= x[i]  # u_j gets -w_ij x_i
        for i in range(d):
            D[t * d + i, len(pairs) + i] = 1.0
    return D


@pytest.mark.parametrize("d", [2, 3])
def test_rotation_evidence_under_a_slope_scale_is_the_multivariate_t_of_the_skew_design(d: int) -> None:
    """Rigid-rotation field with ``slope_scale`` = 2 (rate prior variance V0[0, 0] = 4 / sigma_u^2, offset variance
    1 / sigma_u^2): theta | sigma^2 ~ N(0, sigma^2 L0^-1), sigma^2 ~ IG(a0, b0), a0 = (nu0 - d - 1) d / 2 + 1, b0 =
    sigma_u^2 (a0 - 1) (mean E[Psi]_11), u_t ~ N(W x_t + b, sigma^2 / w_t I). Integrating theta and sigma^2 out, the
    stacked directions are multivariate t with 2 a0 dof and shape b0 / a0 (diag(1 / w) + D L0^-1 D^T) (scipy), D
    the design written out from the skew definition; E[B | u] from dense Gaussian conditioning of theta (the same
    given any sigma^2) and E[sigma^2 | u] = b_n / (a_n - 1), b_n = b0 + y^T (diag(1 / w) + D L0^-1 D^T)^-1 y / 2."""
    gen = torch.Generator().manual_seed(30 + d)
    n, su = 8, 0.25
    prior = field_prior(d, direction_noise=su, extra_dof=3.0, slope_scale=2.0)
    x = 0.5 * torch.randn(n, d, generator=gen, dtype=F64)
    z = torch.cat([x, torch.ones(n, 1, dtype=F64)], -1)
    u = 0.3 * torch.randn(n, d, generator=gen, dtype=F64) + torch.linspace(0.5, -0.5, d, dtype=F64)
    u[:, 0] += 0.8 * x[:, 1]  # a rotation in the (0, 1) plane
    u[:, 1] -= 0.8 * x[:, 0]
    w = torch.rand(n, generator=gen, dtype=F64) * 0.7 + 0.3
    ev, mean, psi = rotation_field_evidence(prior, *field_statistics(z, u, w, torch.ones(n, 1, dtype=F64)))
    Z, y, W = z.numpy(), u.numpy().reshape(-1), np.repeat(w.numpy(), d)
    D = _skew_design(Z, d)
    n_rates = d * (d - 1) // 2
    l0inv = np.diag([(2.0 / su) ** 2] * n_rates + [1.0 / su**2] * d)
    extra = float(prior.dof) - d - 1
    a0 = extra * d / 2 + 1
    b0 = su**2 * (a0 - 1)
    A = np.diag(1.0 / W) + D @ l0inv @ D.T
    want = stats.multivariate_t(loc=np.zeros(n * d), shape=b0 / a0 * A, df=2 * a0).logpdf(y)
    assert float(ev[0]) + 0.5 * d * float(np.log(w.numpy()).sum()) == pytest.approx(float(want), abs=1e-9)
    theta = np.linalg.solve(np.linalg.inv(l0inv) + (D.T * W) @ D, (D.T * W) @ y)
    B = np.zeros((d, d + 1))
    for k, (i, j) in enumerate((i, j) for i in range(d) for j in range(i + 1, d)):
        B[i, j], B[j, i] = theta[k], -theta[k]
    B[:, d] = theta[n_rates:]
    np.testing.assert_allclose(mean[0].numpy(), B, rtol=0, atol=1e-10)
    b_n = b0 + 0.5 * y @ np.linalg.solve(A, y)
    np.testing.assert_allclose(psi[0].numpy(), b_n / (a0 + n * d / 2 - 1) * np.eye(d), rtol=1e-10, atol=0)


def test_field_log_likelihood_against_scipy_and_the_scale_mixture(generator) -> None:
    """log N(u; B z, Psi / w) and log t_nu(u; B z, Psi / w) with non-isotropic Psi against
    scipy.stats.multivariate_normal / multivariate_t; the distances returned with ``maha_out`` are
    w r^T Psi^-1 r (numpy solve; the sampler's draw of lambda needs the reliability-weighted one); and the t is the
    Gaussian scale mixture of the module docstring, int N(u; B z, Psi / (w lambda)) Gamma(lambda; nu / 2, nu / 2)
    d lambda by quadrature."""
    d, n, K, nu = 3, 5, 2, 4.5
    z = torch.cat([torch.randn(n, d, generator=generator, dtype=F64), torch.ones(n, 1, dtype=F64)], -1)
    u = torch.randn(n, d, generator=generator, dtype=F64)
    w = torch.rand(n, generator=generator, dtype=F64) * 0.9 + 0.05
    b = 0.4 * torch.randn(K, d, d + 1, generator=generator, dtype=F64)
    psi = torch.stack([_spd(generator, d, 0.1, 0.03) for _ in range(K)])
    gauss = field_log_likelihood(z, u, w, b, psi)
    robust, q = field_log_likelihood(z, u, w, b, psi, nu, maha_out=True)
    assert gauss.shape == robust.shape == q.shape == (n, K)
    for t in range(n):
        for k in range(K):
            mean = (b[k] @ z[t]).numpy()
            cov = (psi[k] / w[t]).numpy()
            r = u[t].numpy() - mean
            assert float(q[t, k]) == pytest.approx(float(w[t]) * r @ np.linalg.solve(psi[k].numpy(), r), rel=1e-10)
            assert float(gauss[t, k]) == pytest.approx(
                stats.multivariate_normal(mean, cov).logpdf(u[t].numpy()), rel=1e-10, abs=1e-10)
            assert float(robust[t, k]) == pytest.approx(
                stats.multivariate_t(mean, cov, df=nu).logpdf(u[t].numpy()), rel=1e-10, abs=1e-10)
    t, k = 2, 1
    mean, cov = (b[k] @ z[t]).numpy(), (psi[k] / w[t]).numpy()

    def integrand(lam: float) -> float:
        return (stats.multivariate_normal(mean, cov / lam).pdf(u[t].numpy())
                * stats.gamma(a=nu / 2, scale=2 / nu).pdf(lam))

    mixture, _ = integrate.quad(integrand, 0.0, np.inf, epsabs=0.0, epsrel=1e-11, limit=200)
    assert float(robust[t, k]) == pytest.approx(math.log(mixture), abs=1e-8)


def test_field_observations_reliability_written_out_per_sample() -> None:
    """w = s^2 / (s^2 + s0^2) with s^2 = max(||v||^2 - d sigma_v^2, 0) and s0 = max(sigma_v / sigma_u, speed_floor),
    a plain-Python loop over the samples, with the velocity noise one per sequence (N,) and one per sample (N, T),
    a speed floor that binds for one sequence and not the other, a valid sample at rest and padding; a valid sample
    keeps a reliability in (0, 1] (module docstring: w in (0, 1]; 0 marks padding), and padding has u = 0; a given
    centre and radius standardise the positions as they are."""
    gen = torch.Generator().manual_seed(5)
    N, T, d, su, floor = 2, 7, 2, 0.25, 0.4
    x = torch.randn(N, T, d, generator=gen, dtype=F64)
    v = torch.randn(N, T, d, generator=gen, dtype=F64) * torch.tensor([0.3, 1.5], dtype=F64)[:, None, None]
    v[0, 3] = 0.0  # valid, at rest
    valid = torch.ones(N, T, dtype=torch.bool)
    valid[1, 5:] = False
    centre, radius = torch.tensor([0.3, -0.2], dtype=F64), torch.tensor(1.7, dtype=F64)
    per_seq = torch.tensor([0.05, 0.2], dtype=F64)  # s0 = max(0.2, 0.4) = 0.4 (floor binds), max(0.8, 0.4) = 0.8
    per_sample = per_seq[:, None] * (1.0 + torch.rand(N, T, generator=gen, dtype=F64))
    for noise in (per_seq, per_sample):
        obs = field_observations(x, v, valid, velocity_noise=noise, direction_noise=su, speed_floor=floor,
                                 centre=centre, radius=radius)
        for i in range(N):
            for t in range(T):
                sv = float(noise[i] if noise.ndim == 1 else noise[i, t])
                vv = v[i, t].tolist()
                speed2 = sum(c * c for c in vv)
                if not bool(valid[i, t]):
                    assert float(obs.w[i, t]) == 0.0 and obs.u[i, t].abs().max().item() == 0.0
                    continue
                s0 = max(sv / su, floor)
                signal = max(speed2 - d * sv**2, 0.0)
                want = signal / (signal + s0**2)
                got = float(obs.w[i, t])
                assert 0.0 < got <= 1.0, (i, t)
                assert got == pytest.approx(max(want, 1e-8), rel=1e-12, abs=1e-15), (i, t)
                if speed2 > 0:
                    assert obs.u[i, t].tolist() == pytest.approx([c / math.sqrt(speed2) for c in vv], rel=1e-12)
                xs = [(float(x[i, t, j]) - float(centre[j])) / 1.7 for j in range(d)]
                assert obs.z[i, t].tolist() == pytest.approx(xs + [1.0], rel=1e-12, abs=1e-15)


@pytest.mark.parametrize("d,extra,slope", [(2, 1.5, 1.0), (3, 4.0, 2.5)])
def test_field_prior_density_is_the_documented_mniw(d: int, extra: float, slope: float) -> None:
    """field_prior(d, direction_noise=s, extra_dof=e, slope_scale=c) is Psi ~ IW(nu0 = d + 1 + e, S0 = s^2 e I)
    (so E[Psi] = s^2 I) and B | Psi ~ MN(0, Psi, diag(c^2, ..., c^2, 1) / s^2): its log density at random points
    equals scipy.stats.invwishart plus scipy.stats.matrix_normal with those parameters written from the
    docstring."""
    gen = torch.Generator().manual_seed(40 + d)
    s = 0.3
    prior = field_prior(d, direction_noise=s, extra_dof=extra, slope_scale=slope)
    colcov = np.diag([slope**2] * d + [1.0]) / s**2
    for _ in range(3):
        psi = _spd(gen, d, 0.05, 0.02)
        b = torch.randn(d, d + 1, generator=gen, dtype=F64)
        want = (stats.invwishart(df=d + 1 + extra, scale=s**2 * extra * np.eye(d)).logpdf(psi.numpy())
                + stats.matrix_normal(mean=np.zeros((d, d + 1)), rowcov=psi.numpy(), colcov=colcov).logpdf(b.numpy()))
        assert float(field_log_density(b, psi, prior)) == pytest.approx(float(want), abs=1e-9)


def test_sample_field_noise_marginal_is_the_inverse_gamma_of_the_inverse_wishart() -> None:
    """Under Psi ~ IW(nu, S), each diagonal entry Psi_ii ~ IG((nu - d + 1) / 2, S_ii / 2): Kolmogorov-Smirnov test of
    sample_field's noise draws (20,000, fixed seed) against scipy.stats.invgamma, at a small nu where a dof off by
    one changes the law; and the draws' mean against the IW mean S / (nu - d - 1)."""
    gen = torch.Generator().manual_seed(11)
    d, n, nu = 3, 20000, 8.0
    S = torch.tensor([[0.5, 0.1, 0.0], [0.1, 0.3, 0.05], [0.0, 0.05, 0.4]], dtype=F64)
    params = FieldPrior(mean=torch.zeros(n, d, d + 1, dtype=F64), row_covariance=torch.eye(d + 1, dtype=F64).expand(
        n, -1, -1), dof=torch.tensor(nu, dtype=F64).expand(n), scale=S.expand(n, d, d))
    _, psi = sample_field(params, gen)
    for i in range(d):
        law = stats.invgamma(a=(nu - d + 1) / 2, scale=float(S[i, i]) / 2)
        assert stats.kstest(psi[:, i, i].numpy(), law.cdf).pvalue > 1e-3, i
    torch.testing.assert_close(psi.mean(0), S / (nu - d - 1), atol=0.04, rtol=0.1)


def _phases(starts: list[list[int]], T: int, D: int) -> torch.Tensor:
    """(1, N, T) phases of runs that start at the given points (phase = points since the start, capped at D - 1)."""
    phase = torch.zeros(1, len(starts), T, dtype=torch.long)
    for i, ss in enumerate(starts):
        for t in range(T):
            begun = max(s for s in ss if s <= t)
            phase[0, i, t] = min(t - begun, D - 1)
    return phase


def test_dwell_regressors_and_log_prob_written_out() -> None:
    """dwell_regressors is [1, b_t] with b_t = 1 exactly where a run starts (phase 0) inside the mask (a loop), and
    dwell_log_prob is sum over the mask of log N(c_t; mu + delta b_t, sigma^2) plus the NIG prior density
    log IG(sigma^2; nu0 / 2, S0 / 2) + log N((mu, delta); 0, sigma^2 V0) (scipy.stats), nu0 = 3, S0 = 0.1, V0 = 100 I
    from the module docstring."""
    gen = torch.Generator().manual_seed(9)
    N, T, D = 2, 18, 3
    mask = dwell_mask(torch.tensor([18, 15]), T, D)
    starts = [[0, 4, 9, 13], [0, 3, 8]]
    phase = _phases(starts, T, D)
    X = dwell_regressors(phase[0], mask)
    for i in range(N):
        for t in range(T):
            want_b = 1.0 if (t in starts[i] and bool(mask[i, t])) else 0.0
            assert X[i, t].tolist() == [1.0, want_b], (i, t)
    c = 0.3 * torch.randn(N, T, generator=gen, dtype=F64)
    beta = torch.tensor([[0.1, 0.7], [-0.2, 0.3]], dtype=F64)
    noise = torch.tensor([0.15, 0.4], dtype=F64)
    got = dwell_log_prob(dwell_prior(), c, mask, phase.expand(2, -1, -1), beta, noise)
    for j in range(2):
        mu, delta, s2 = float(beta[j, 0]), float(beta[j, 1]), float(noise[j])
        want = stats.invgamma(a=1.5, scale=0.05).logpdf(s2)
        want += stats.multivariate_normal(np.zeros(2), 100.0 * s2 * np.eye(2)).logpdf([mu, delta])
        for i in range(N):
            for t in range(T):
                if bool(mask[i, t]):
                    b = 1.0 if t in starts[i] else 0.0
                    want += stats.norm(mu + delta * b, math.sqrt(s2)).logpdf(float(c[i, t]))
        assert float(got[j]) == pytest.approx(want, abs=1e-9), j


def test_dwell_evidence_is_the_product_of_one_step_predictive_t_densities() -> None:
    """Chain rule for the NIG regression c_t = mu + delta b_t + e_t over the mask: log p(c | b) = sum_t
    log p(c_t | c_<t), each the Student t with nu_(t-1) dof, location x_t^T m_(t-1) and scale^2
    S_(t-1) / nu_(t-1) (1 + x_t^T Lambda_(t-1)^-1 x_t) (scipy.stats.t), the posterior after the earlier points
    recomputed from scratch (Lambda = I / 100 + sum x x^T, m = Lambda^-1 sum x c, S = S0 + sum (c - x^T m)^2 +
    m^T m / 100, nu = nu0 + count), for two labellings of the same data."""
    gen = torch.Generator().manual_seed(13)
    N, T, D = 2, 16, 2
    mask = dwell_mask(torch.tensor([16, 13]), T, D)
    c = 0.4 * torch.randn(N, T, generator=gen, dtype=F64)
    c[0, 6] += 1.2
    labellings = ([[0, 6, 10], [0, 4, 9]], [[0, 3, 6, 12], [0, 7]])
    phase = torch.cat([_phases(s, T, D) for s in labellings])
    got = dwell_evidence(dwell_prior(), c, mask, phase)
    for j, starts in enumerate(labellings):
        xs, ys = [], []
        for i in range(N):
            for t in range(T):
                if bool(mask[i, t]):
                    xs.append([1.0, 1.0 if t in starts[i] else 0.0])
                    ys.append(float(c[i, t]))
        Xa, ya = np.array(xs), np.array(ys)
        total = 0.0
        for t in range(len(ya)):
            X, y = Xa[:t], ya[:t]
            lam = np.eye(2) / 100.0 + X.T @ X
            m = np.linalg.solve(lam, X.T @ y)
            S = 0.1 + ((y - X @ m) ** 2).sum() + m @ m / 100.0
            nu = 3.0 + t
            scale = math.sqrt(S / nu * (1.0 + Xa[t] @ np.linalg.solve(lam, Xa[t])))
            total += stats.t(df=nu, loc=Xa[t] @ m, scale=scale).logpdf(ya[t])
        assert float(got[j]) == pytest.approx(total, abs=1e-9), j
