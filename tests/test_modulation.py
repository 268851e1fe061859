"""Disturbance modulation: Renyi entropy (closed form vs Monte Carlo and vs the corrected eq. 16), growth away
from the data, the closed-form W D W^T against an explicit Gram-Schmidt frame, the branches and the c = 0 rule,
dV/dt < 0 of the modulated field on P-QLF primitives, batching, dtypes, CUDA, typed errors and configs."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from conftest import requires_cuda
from lfd_torch.ds import StablePrimitive, fit_lpvds
from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, UnknownNameError
from lfd_torch.gmm import GMM, fit_em
from lfd_torch.modulation import (
    MODULATION_MODES,
    Branch,
    Modulation,
    goal_direction,
    large_scale_gain,
    mixture_renyi_entropy,
    modulate,
    modulated_velocity,
    modulated_velocity_single,
    modulation_matrix,
    reference_entropy,
    renyi_entropy,
    small_scale_factor,
    velocity_mixture,
)
from test_primitive_contract import small_lasa

CONF = Path(__file__).resolve().parents[1] / "conf"


# ---------------------------------------------------------------------------------------------------- helpers
def random_spd(n: int, d: int, generator: torch.Generator, scale: float = 1.0, floor: float = 0.3) -> torch.Tensor:
    B = torch.randn(n, d, d, dtype=torch.float64, generator=generator)
    return scale * (B @ B.transpose(-2, -1) / d + floor * torch.eye(d, dtype=torch.float64))


def pqlf_primitive(d: int, K: int, generator: torch.Generator, anisotropy: float = 25.0) -> StablePrimitive:
    """A certified primitive whose Lyapunov matrix is far from I: A_k = P^-1 (-Q_k / 2 + S_k), S_k skew, so
    A_k^T P + P A_k = -Q_k < 0 while A_k + A_k^T is in general indefinite."""
    Qr, _ = torch.linalg.qr(torch.randn(d, d, dtype=torch.float64, generator=generator))
    eig = torch.logspace(0, -math.log10(anisotropy), d, dtype=torch.float64)
    P = Qr @ torch.diag(eig) @ Qr.T
    P = 0.5 * (P + P.T)
    Q = random_spd(K, d, generator, scale=1.0, floor=0.5)
    S = 3.0 * torch.randn(K, d, d, dtype=torch.float64, generator=generator)
    S = S - S.transpose(-2, -1)
    A = torch.linalg.solve(P, -0.5 * Q + S)
    g = torch.randn(d, dtype=torch.float64, generator=generator)
    means = g + 3.0 * torch.randn(K, d, dtype=torch.float64, generator=generator)
    w = torch.rand(K, dtype=torch.float64, generator=generator) + 0.5
    gmm = GMM(w / w.sum(), means, random_spd(K, d, generator, scale=1.0, floor=0.5))
    Sv = random_spd(K, d, generator, scale=4.0, floor=0.5)
    return StablePrimitive(gmm=gmm, A=A, attractor=g, P=P, velocity_covariances=Sv)


def gram_schmidt_frame(unit: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """(N, d, d) W with first column ``unit`` and a random orthonormal completion (classical Gram-Schmidt, float64)."""
    N, d = unit.shape
    u = unit.to(torch.float64)
    W = torch.zeros(N, d, d, dtype=torch.float64)
    for n in range(N):
        cols = [u[n] / u[n].norm()]
        while len(cols) < d:
            v = torch.randn(d, dtype=torch.float64, generator=generator)
            for q in cols:
                v = v - (q @ v) * q
            if v.norm() > 1e-6:
                cols.append(v / v.norm())
        W[n] = torch.stack(cols, dim=1)
    return W


def lyapunov_rate(primitive: StablePrimitive, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    e = x - primitive.attractor
    return 2.0 * torch.einsum("...i,ij,...j->...", e, primitive.P, v)


@functools.lru_cache(maxsize=None)
def angle_lpvds() -> StablePrimitive:
    demos = small_lasa("Angle", demos=(0, 1, 2), stride=8)
    model = fit_lpvds(
        demos, gmm=functools.partial(fit_em, n_components=4), lyapunov="pqlf", generator=torch.Generator().manual_seed(0)
    )
    return model


def angle_training_states() -> torch.Tensor:
    x, _, _ = small_lasa("Angle", demos=(0, 1, 2), stride=8).samples()
    return x


# ---------------------------------------------------------------------------------------------------- entropy
@pytest.mark.parametrize("d", [2, 3])
def test_renyi_entropy_matches_monte_carlo(d: int, generator: torch.Generator) -> None:
    """H2 = -log(Z^2 E_{u~q}[q(u)]) with q the normalised velocity mixture and Z = sum_k w_k (unnormalised)."""
    K = 2 if d == 2 else 3
    prim = pqlf_primitive(d, K, generator)
    x = prim.gmm.means + 0.5 * torch.randn(K, d, dtype=torch.float64, generator=generator)
    h2 = renyi_entropy(prim, x)
    # the mixture, built independently of lfd_torch.modulation: w_k = pi_k N(x; mu_k^x, Sigma_k^x), means A_k (x - g)
    pos = torch.distributions.MultivariateNormal(prim.gmm.means, covariance_matrix=prim.gmm.covariances)
    log_weights = prim.gmm.weights.log() + pos.log_prob(x.unsqueeze(-2))  # (B, K), not normalised
    vel_means = torch.stack([(prim.A[k] @ (x - prim.attractor).T).T for k in range(K)], dim=1)  # (B, K, d)
    mix = velocity_mixture(prim, x)
    torch.testing.assert_close(mix.log_weights, log_weights)
    assert float(torch.logsumexp(log_weights, -1).sub(0).abs().min()) > 1e-3  # really unnormalised
    n = 200_000
    chol = torch.linalg.cholesky(prim.velocity_covariances)
    for b in range(x.shape[0]):
        log_w = log_weights[b]
        q = torch.softmax(log_w, -1)
        labels = torch.multinomial(q, n, replacement=True, generator=generator)
        eps = torch.randn(n, d, dtype=torch.float64, generator=generator)
        u = vel_means[b][labels] + torch.einsum("nij,nj->ni", chol[labels], eps)
        comp = torch.distributions.MultivariateNormal(vel_means[b], scale_tril=chol)
        log_q_u = torch.logsumexp(q.log() + comp.log_prob(u.unsqueeze(-2)), -1)
        q_u = log_q_u.exp()
        mean = q_u.mean()
        se_log = float(q_u.std() / mean / math.sqrt(n))
        mc = -2.0 * torch.logsumexp(log_w, -1) - mean.log()
        assert abs(float(mc - h2[b])) < 5 * se_log + 1e-9, (float(mc), float(h2[b]), se_log)
        assert se_log < 0.02  # the test has resolving power


def test_renyi_entropy_equals_corrected_eq16(generator: torch.Generator) -> None:
    """The closed form equals the paper's eq. 16 in information form with the product determinant term (NOTES 4a)."""
    K, d, B = 3, 3, 5
    log_w = torch.randn(B, K, dtype=torch.float64, generator=generator) - 4.0  # unnormalised
    mu = torch.randn(B, K, d, dtype=torch.float64, generator=generator)
    S = random_spd(K, d, generator)
    got = mixture_renyi_entropy(log_w, mu, S)
    Si = torch.linalg.inv(S)
    expo = torch.empty(B, K, K, dtype=torch.float64)
    for b in range(B):
        for i in range(K):
            for j in range(K):
                Sij = torch.linalg.inv(Si[i] + Si[j])
                mij = Sij @ (Si[i] @ mu[b, i] + Si[j] @ mu[b, j])
                quad = mij @ (Si[i] + Si[j]) @ mij - (mu[b, i] @ Si[i] @ mu[b, i] + mu[b, j] @ Si[j] @ mu[b, j])
                logdet = torch.logdet(Si[i] + Si[j]) - torch.logdet(Si[i]) - torch.logdet(Si[j])  # product, 4a
                delta = 0.5 * (quad - logdet - d * math.log(2 * math.pi))
                expo[b, i, j] = log_w[b, i] + log_w[b, j] + delta
    ref = -torch.logsumexp(expo.flatten(-2), -1)
    torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-10)


def _ray_start(prim: StablePrimitive, dirs: torch.Tensor) -> torch.Tensor:
    """Per direction v, the largest vertex t* = v^T Sigma_k^-1 (mu_k - g) / v^T Sigma_k^-1 v of the concave
    quadratics log N(g + t v; mu_k, Sigma_k); beyond it (and t > 0, the vertex of the velocity terms) every exponent
    of H2 decreases strictly."""
    Pk = prim.gmm.precisions
    dm = prim.gmm.means - prim.attractor
    num = torch.einsum("ri,kij,kj->rk", dirs, Pk, dm)
    den = torch.einsum("ri,kij,rj->rk", dirs, Pk, dirs)
    return (num / den).amax(-1).clamp_min(0.0)


@pytest.mark.parametrize("which", ["synthetic3d", "angle"])
def test_renyi_entropy_rises_along_rays_and_stays_finite(which: str, generator: torch.Generator) -> None:
    prim = pqlf_primitive(3, 3, generator) if which == "synthetic3d" else angle_lpvds()
    d = prim.dim
    dirs = torch.randn(16, d, dtype=torch.float64, generator=generator)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    t0 = _ray_start(prim, dirs)
    data_scale = float((prim.gmm.means - prim.attractor).norm(dim=-1).max())
    steps = torch.logspace(math.log10(1e-3 * data_scale), 6, 80, dtype=torch.float64)  # up to 1e6 units
    t = t0[:, None] * 1.001 + steps[None, :]  # (R, T), strictly increasing from just beyond the last vertex
    x = prim.attractor + t[..., None] * dirs[:, None, :]
    h2 = renyi_entropy(prim, x)
    assert torch.isfinite(h2).all()
    assert (h2.diff(dim=-1) > 0).all(), "H2 must rise strictly along every ray beyond the data"
    # low on the data, much higher away from it
    x_data = prim.gmm.means
    assert float(renyi_entropy(prim, x_data).max()) < float(h2[:, -1].min())
    # 1e6 units from the data: finite (large) in both dtypes, and the modulated field stays finite
    far = prim.gmm.means[0] + 1e6 * dirs
    for dtype in (torch.float32, torch.float64):
        p = prim.to(dtype=dtype)
        xf = far.to(dtype)
        hf = renyi_entropy(p, xf)
        assert torch.isfinite(hf).all() and (hf > 1e6).all(), hf
        ref = reference_entropy(p, p.gmm.means, 1.0)
        own = p.gmm.log_prob(xf)
        for other in (own - 1.0, own + 1.0):  # inside (small-scale) and outside (large-scale)
            res = Modulation("full")(p, xf, None, own, other, ref)
            assert torch.isfinite(res.velocity).all()
            assert (res.velocity.norm(dim=-1) > 0).all()


def test_reference_entropy_options(generator: torch.Generator) -> None:
    prim = angle_lpvds()
    x = angle_training_states()
    h2 = renyi_entropy(prim, x)
    torch.testing.assert_close(reference_entropy(prim, x, 1.0), h2.max())
    torch.testing.assert_close(reference_entropy(prim, x, 0.5), h2.median(), rtol=0, atol=float(h2.std()) * 0.05)
    torch.testing.assert_close(reference_entropy(prim, None, None), renyi_entropy(prim, prim.attractor))
    # the paper's literal x_r = g would modulate most demonstrated states (NOTES sec. 4)
    assert float((h2 > reference_entropy(prim, None, None)).double().mean()) > 0.5
    with pytest.raises(InvalidArgumentError, match="quantile"):
        reference_entropy(prim, x, 1.5)
    with pytest.raises(InvalidArgumentError, match="x"):
        reference_entropy(prim, None, 0.9)


# ---------------------------------------------------------------------------------------------------- matrix
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("d", [2, 3])
def test_closed_form_matches_gram_schmidt_wdwt(d: int, dtype: torch.dtype, generator: torch.Generator) -> None:
    N = 64
    x = torch.randn(N, d, dtype=torch.float64, generator=generator)
    g = torch.randn(d, dtype=torch.float64, generator=generator)
    f = torch.randn(N, d, dtype=torch.float64, generator=generator)
    d1 = 3.0 * torch.randn(N, dtype=torch.float64, generator=generator)
    dd = torch.rand(N, dtype=torch.float64, generator=generator)
    unit64 = goal_direction(x, g).unit
    W = gram_schmidt_frame(unit64, generator)
    D = torch.diag_embed(torch.cat([d1[:, None], dd[:, None].expand(N, d - 1)], dim=1))
    M_ref = W @ D @ W.transpose(-2, -1)
    v_ref = (M_ref @ f.unsqueeze(-1)).squeeze(-1)
    unit = goal_direction(x.to(dtype), g.to(dtype)).unit
    got_v = modulate(f.to(dtype), unit, d1.to(dtype), dd.to(dtype))
    got_M = modulation_matrix(unit, d1.to(dtype), dd.to(dtype))
    assert got_v.dtype == dtype and got_M.dtype == dtype
    tol = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got_v, v_ref.to(dtype), **tol)
    torch.testing.assert_close(got_M, M_ref.to(dtype), **tol)


def _literal_reference(x, f, g, own, other, h2, ref, lam_limit):
    """Branch and W D W^T f of eqs 9, 12, 13, 17, 18 with an explicit Gram-Schmidt W (float64, per sample)."""
    gen = torch.Generator().manual_seed(7)
    N, d = x.shape
    unit = goal_direction(x, g).unit
    W = gram_schmidt_frame(unit, gen)
    out = torch.empty_like(f)
    branch = torch.empty(N, dtype=torch.int8)
    for n in range(N):
        c = float(W[n, :, 0] @ f[n])
        sgn = math.copysign(1.0, c) if c != 0 else 0.0
        if own[n] < other[n]:
            s = max(min(lam_limit, math.exp(float(other[n] - own[n]))), 1.0)
            D = torch.diag(torch.tensor([-sgn * s] + [0.0] * (d - 1), dtype=torch.float64))
            branch[n] = Branch.LARGE_SCALE
        elif h2[n] > ref:
            lam = min(1.0, math.exp(float(ref - h2[n])))
            D = torch.diag(torch.tensor([-sgn + lam] + [lam] * (d - 1), dtype=torch.float64))
            branch[n] = Branch.SMALL_SCALE
        else:
            D = torch.eye(d, dtype=torch.float64)
            branch[n] = Branch.UNMODULATED
        out[n] = W[n] @ D @ W[n].T @ f[n]
    return out, branch


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("d", [2, 3])
def test_branches_match_explicit_eigenvalue_matrices(d: int, dtype: torch.dtype, generator: torch.Generator) -> None:
    N = 200
    x = torch.randn(N, d, dtype=torch.float64, generator=generator)
    g = torch.randn(d, dtype=torch.float64, generator=generator)
    f = torch.randn(N, d, dtype=torch.float64, generator=generator)
    own = torch.randn(N, dtype=torch.float64, generator=generator)
    other = torch.randn(N, dtype=torch.float64, generator=generator)
    h2 = torch.randn(N, dtype=torch.float64, generator=generator)
    ref = 0.0
    v_ref, b_ref = _literal_reference(x, f, g, own, other, h2, ref, 2.5)
    assert {int(b) for b in b_ref.unique()} == {0, 1, 2}
    c = lambda t: t.to(dtype)  # noqa: E731
    res = modulated_velocity(
        c(x), c(f), c(g), log_p_own=c(own), log_p_other=c(other), h2=c(h2), h2_ref=ref, lambda_limit=2.5, radial_floor=0.0
    )
    tol = dict(rtol=1e-4, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    assert res.velocity.dtype == dtype
    torch.testing.assert_close(res.branch, b_ref)
    torch.testing.assert_close(res.velocity, v_ref.to(dtype), **tol)
    # the default floor changes only the samples with |c| < kappa ||f||
    floored = modulated_velocity(
        c(x), c(f), c(g), log_p_own=c(own), log_p_other=c(other), h2=c(h2), h2_ref=ref, lambda_limit=2.5, radial_floor=0.1
    )
    cc = (goal_direction(x, g).unit * f).sum(-1)
    keep = (cc.abs() >= 0.1 * f.norm(dim=-1) * (1 + 1e-6)) | (b_ref == Branch.UNMODULATED)
    assert (~keep).any() and keep.any()
    torch.testing.assert_close(floored.velocity[keep], v_ref[keep].to(dtype), **tol)
    # large scale always points at g with speed in [max(|c|, kappa||f||), lambda_limit ||f||]
    large = b_ref == Branch.LARGE_SCALE
    v = floored.velocity[large].double()
    e = (x - g)[large]
    cos = -(v * e).sum(-1) / (v.norm(dim=-1) * e.norm(dim=-1))
    assert (cos > 1 - 1e-5).all()
    speed = v.norm(dim=-1)
    lo = torch.maximum(cc[large].abs(), 0.1 * f[large].norm(dim=-1))
    assert (speed >= lo * (1 - 1e-5)).all() and (speed <= 2.5 * f[large].norm(dim=-1) * (1 + 1e-5)).all()


def test_factors() -> None:
    own = torch.tensor([0.0, 0.0, 0.0, -math.inf, -math.inf, 5.0], dtype=torch.float64)
    other = torch.tensor([math.log(2.0), math.log(10.0), -1.0, 0.0, -math.inf, 5.0], dtype=torch.float64)
    s = large_scale_gain(own, other, 3.0)
    torch.testing.assert_close(s, torch.tensor([2.0, 3.0, 1.0, 3.0, 1.0, 1.0], dtype=torch.float64))
    h2 = torch.tensor([0.0, 1.0, 3.0, math.inf, math.inf], dtype=torch.float64)
    ref = torch.tensor([1.0, 1.0, 1.0, 1.0, math.inf], dtype=torch.float64)
    lam = small_scale_factor(h2, ref)
    torch.testing.assert_close(lam, torch.tensor([1.0, 1.0, math.exp(-2.0), 0.0, 1.0], dtype=torch.float64))
    with pytest.raises(InvalidArgumentError, match="lambda_limit"):
        large_scale_gain(own, other, 0.5)


# ---------------------------------------------------------------------------------------------------- c = 0, goal
@pytest.mark.parametrize("d", [2, 3])
def test_c_zero_rule_does_not_stall(d: int, generator: torch.Generator) -> None:
    x = torch.randn(8, d, dtype=torch.float64, generator=generator)
    g = torch.zeros(d, dtype=torch.float64)
    e = x / x.norm(dim=-1, keepdim=True)
    f = torch.randn(8, d, dtype=torch.float64, generator=generator)
    f = f - (f * e).sum(-1, keepdim=True) * e  # f orthogonal to e_g: c = 0
    own = torch.zeros(8, dtype=torch.float64)
    cases = {  # (log_p_other, h2): large-scale, and small-scale with lambda_ss underflowing to 0
        "large": (own + 1.0, own),
        "small": (own - 1.0, own + 1e4),
    }
    for name, (other, h2) in cases.items():
        kw = dict(log_p_own=own, log_p_other=other, h2=h2, h2_ref=0.0, lambda_limit=2.0)
        literal = modulated_velocity(x, f, g, radial_floor=0.0, **kw)
        assert (literal.velocity.norm(dim=-1) < 1e-12 * f.norm(dim=-1)).all(), name  # the literal formula stalls
        res = modulated_velocity(x, f, g, radial_floor=0.1, **kw)
        s = 2.0 if name == "large" else 1.0
        expected = -0.1 * s * f.norm(dim=-1, keepdim=True) * e
        torch.testing.assert_close(res.velocity, expected)
        assert (2 * (x * res.velocity).sum(-1) < 0).all()


def test_goal_gives_zero_velocity(generator: torch.Generator) -> None:
    prim = pqlf_primitive(3, 2, generator)
    g = prim.attractor
    x = torch.stack([g, g + 1.0])
    f = torch.randn(2, 3, dtype=torch.float64, generator=generator)  # even a non-zero f at the goal
    for mode in ("large", "small", "full"):
        for other in (-10.0, 10.0):
            res = modulated_velocity(
                x, f, g, log_p_own=0.0, log_p_other=other, h2=torch.tensor([5.0, 5.0], dtype=torch.float64),
                h2_ref=0.0, mode=mode,
            )
            assert (res.velocity[0] == 0).all() and int(res.branch[0]) == Branch.AT_GOAL
            assert res.velocity[1].norm() > 0
    mod = Modulation("full", entropy_quantile=None)
    res = mod(prim, g.unsqueeze(0), None, torch.zeros(1, dtype=torch.float64), torch.ones(1, dtype=torch.float64))
    assert (res.velocity == 0).all()
    torch.testing.assert_close(Modulation("none")(prim, x, f).velocity, f)


# ---------------------------------------------------------------------------------------------------- stability
def _sample_states(prim: StablePrimitive, n: int, generator: torch.Generator) -> torch.Tensor:
    lo = prim.gmm.means.amin(0)
    hi = prim.gmm.means.amax(0)
    span = (hi - lo).clamp_min(1.0)
    box = lo - 2 * span + 5 * span * torch.rand(n, prim.dim, dtype=torch.float64, generator=generator)
    near_goal = prim.attractor + 1e-3 * span * torch.randn(n // 10, prim.dim, dtype=torch.float64, generator=generator)
    return torch.cat([box, near_goal])


@pytest.mark.parametrize("which", ["angle", "synthetic2d", "synthetic3d"])
def test_modulated_field_decreases_lyapunov(which: str, generator: torch.Generator) -> None:
    prim = {
        "angle": angle_lpvds,
        "synthetic2d": lambda: pqlf_primitive(2, 3, generator),
        "synthetic3d": lambda: pqlf_primitive(3, 3, generator),
    }[which]()
    P64 = prim.P
    assert float(torch.linalg.eigvalsh(P64)[0]) < 0.9  # a genuine P-QLF, P != I
    x = _sample_states(prim, 3000, generator)
    f = prim(x)
    e_unit = goal_direction(x, prim.attractor).unit
    c = (e_unit * f).sum(-1)
    assert (c > 0).any(), "the sample must contain states where f points away from g in the Euclidean sense"
    assert (lyapunov_rate(prim, x, f) < 0).all()
    train = prim.gmm.means if which != "angle" else angle_training_states()
    own = torch.randn(x.shape[0], dtype=torch.float64, generator=generator)
    other = torch.randn(x.shape[0], dtype=torch.float64, generator=generator)
    for radial_floor in (0.0, 0.1):
        mod = Modulation("full", lambda_limit=4.0, entropy_quantile=0.5, radial_floor=radial_floor)
        res = mod(prim, x, f, own, other, mod.reference_entropy(prim, train))
        assert {int(b) for b in res.branch.unique()} >= {1, 2}
        rate = lyapunov_rate(prim, x, res.velocity)
        assert (rate < 0).all(), float(rate.max())
        # the bound of the policy docstring for the floored large-scale branch
        if radial_floor > 0:
            large = res.branch == Branch.LARGE_SCALE
            r = (x - prim.attractor).norm(dim=-1)
            bound = -2 * radial_floor * float(torch.linalg.eigvalsh(P64)[0]) * r * f.norm(dim=-1)
            assert (rate[large] <= bound[large] * (1 - 1e-9)).all()


# ---------------------------------------------------------------------------------------------------- API
def test_batched_equals_loop_and_shapes(generator: torch.Generator) -> None:
    prim = pqlf_primitive(3, 3, generator)
    x = _sample_states(prim, 20, generator)[:20]
    own = torch.randn(20, dtype=torch.float64, generator=generator)
    other = torch.randn(20, dtype=torch.float64, generator=generator)
    mod = Modulation("full", entropy_quantile=0.5)
    ref = mod.reference_entropy(prim, prim.gmm.means)
    batched = mod(prim, x, None, own, other, ref)
    for n in range(20):
        one = mod(prim, x[n], None, own[n], other[n], ref)
        torch.testing.assert_close(one.velocity, batched.velocity[n], rtol=1e-12, atol=1e-12)
        assert one.branch.shape == () and int(one.branch) == int(batched.branch[n])
    grid = mod(prim, x.reshape(4, 5, 3), None, own.reshape(4, 5), other.reshape(4, 5), ref)
    torch.testing.assert_close(grid.velocity.reshape(20, 3), batched.velocity, rtol=1e-12, atol=1e-12)
    assert grid.branch.shape == (4, 5) and grid.branch.dtype == torch.int8
    torch.testing.assert_close(renyi_entropy(prim, x.reshape(4, 5, 3)).reshape(20), renyi_entropy(prim, x))


@pytest.mark.parametrize("d", [2, 3])
def test_feature_major_layout_equals_the_row_major_one(d: int, generator: torch.Generator) -> None:
    """``dim=0`` (the engine's (d, n) layout) gives the (n, d) results transposed, in every mode, with states at
    the goal, outside and inside A_m and on both sides of H2_ref."""
    from lfd_torch.modulation import modulated_velocity_unchecked, radial_component

    n = 400
    g = torch.randn(d, generator=generator, dtype=torch.float64)
    x = g + torch.randn(n, d, generator=generator, dtype=torch.float64)
    x[:5] = g  # at the goal
    f = torch.randn(n, d, generator=generator, dtype=torch.float64)
    own = torch.randn(n, generator=generator, dtype=torch.float64)
    other = torch.randn(n, generator=generator, dtype=torch.float64)
    h2 = torch.randn(n, generator=generator, dtype=torch.float64)
    ref = torch.randn(n, generator=generator, dtype=torch.float64)
    xt, ft = x.T.contiguous(), f.T.contiguous()
    unit, r = goal_direction(x, g)
    unit_t, r_t = goal_direction(xt, g.unsqueeze(-1), dim=0)
    torch.testing.assert_close(unit_t.T, unit, rtol=1e-15, atol=1e-15)
    torch.testing.assert_close(r_t, r, rtol=1e-15, atol=0.0)
    torch.testing.assert_close(radial_component(ft, unit_t, dim=0), radial_component(f, unit), rtol=1e-14, atol=1e-15)
    for mode in MODULATION_MODES:
        a = modulated_velocity_unchecked(x, f, g, own, other, h2, ref, mode, 2.5, 0.1)
        b = modulated_velocity_unchecked(xt, ft, g.unsqueeze(-1), own, other, h2, ref, mode, 2.5, 0.1, dim=0)
        torch.testing.assert_close(b.velocity.T, a.velocity, rtol=1e-14, atol=1e-15)
        assert torch.equal(b.branch, a.branch) and b.branch.shape == (n,)
        if mode == "full":
            assert {int(v) for v in a.branch.unique()} == {int(v) for v in Branch}


@pytest.mark.parametrize("d", [2, 3])
def test_single_sample_form_equals_the_tensor_one(d: int, generator: torch.Generator) -> None:
    """``modulated_velocity_single`` (the single-state tick's Python-float form) gives the velocity and branch of
    ``modulated_velocity_unchecked`` sample by sample, in every mode: at the goal, with f orthogonal to e (the
    c = 0 rule), on ties own == other, with no other subtask (-inf) and on both sides of H2_ref."""
    from lfd_torch.modulation import modulated_velocity_unchecked

    n = 300
    g = torch.randn(d, generator=generator, dtype=torch.float64)
    x = g + torch.randn(n, d, generator=generator, dtype=torch.float64)
    x[:5] = g
    f = torch.randn(n, d, generator=generator, dtype=torch.float64)
    e = x - g
    f[5:15] = 0
    f[5:15, 0], f[5:15, 1] = -e[5:15, 1], e[5:15, 0]  # f orthogonal to e: c = 0
    own = torch.randn(n, generator=generator, dtype=torch.float64)
    other = torch.randn(n, generator=generator, dtype=torch.float64)
    other[15:25] = own[15:25]
    other[25:35] = -math.inf
    h2 = torch.randn(n, generator=generator, dtype=torch.float64)
    ref = torch.randn(n, generator=generator, dtype=torch.float64)
    for mode in MODULATION_MODES:
        want = modulated_velocity_unchecked(x, f, g, own, other, h2, ref, mode, 2.5, 0.1)
        for i in range(n):
            u, branch = modulated_velocity_single(e[i].tolist(), f[i].tolist(), float(own[i]), float(other[i]),
                                                  float(h2[i]), float(ref[i]), mode, 2.5, 0.1)  # fmt: skip
            assert int(branch) == int(want.branch[i]), (mode, i)
            torch.testing.assert_close(torch.tensor(u, dtype=torch.float64), want.velocity[i], rtol=1e-14, atol=1e-15)
        if mode == "full":
            assert {int(v) for v in want.branch.unique()} == {int(v) for v in Branch}


def test_modes(generator: torch.Generator) -> None:
    prim = pqlf_primitive(2, 3, generator)
    x = _sample_states(prim, 200, generator)
    f = prim(x)
    own = torch.randn(x.shape[0], dtype=torch.float64, generator=generator)
    other = torch.randn(x.shape[0], dtype=torch.float64, generator=generator)
    ref = reference_entropy(prim, prim.gmm.means, 1.0)
    out = {m: Modulation(m)(prim, x, f, own, other, ref) for m in MODULATION_MODES}
    assert (out["none"].branch == 0).all() and torch.equal(out["none"].velocity, f)
    assert set(out["large"].branch.unique().tolist()) <= {0, 1, 3}
    assert set(out["small"].branch.unique().tolist()) <= {0, 2, 3}
    full = out["full"]
    torch.testing.assert_close(full.velocity[full.branch == 1], out["large"].velocity[full.branch == 1])
    torch.testing.assert_close(full.velocity[full.branch == 2], out["small"].velocity[full.branch == 2])
    assert torch.equal(full.velocity[full.branch == 0], f[full.branch == 0])
    # 'large' needs no entropy threshold, 'small' no densities
    Modulation("large")(prim, x, f, own, other)
    Modulation("small")(prim, x, f, h2_ref=ref)
    # a rollout field
    field = Modulation("full").field(prim, prim.gmm.log_prob, None, ref)
    torch.testing.assert_close(field(x), Modulation("full")(prim, x, f, prim.gmm.log_prob(x), -math.inf, ref).velocity)


def test_typed_errors(generator: torch.Generator) -> None:
    prim = pqlf_primitive(2, 2, generator)
    x = torch.randn(5, 2, dtype=torch.float64, generator=generator)
    f = prim(x)
    z = torch.zeros(5, dtype=torch.float64)
    with pytest.raises(UnknownNameError, match="bogus"):
        Modulation("bogus")
    with pytest.raises(InvalidArgumentError, match="lambda_limit"):
        Modulation(lambda_limit=0.5)
    with pytest.raises(InvalidArgumentError, match="radial_floor"):
        Modulation(radial_floor=1.5)
    with pytest.raises(InvalidArgumentError, match="entropy_quantile"):
        Modulation(entropy_quantile=2.0)
    with pytest.raises(InvalidArgumentError, match="log_p_own"):
        Modulation("full")(prim, x, f, None, z, 0.0)
    with pytest.raises(InvalidArgumentError, match="h2_ref"):
        Modulation("full")(prim, x, f, z, z)
    with pytest.raises(ShapeMismatchError, match="log_p_own"):
        Modulation("full")(prim, x, f, torch.zeros(3, dtype=torch.float64), z, 0.0)
    with pytest.raises(ShapeMismatchError, match="f must"):
        modulated_velocity(x, f[:3], prim.attractor, mode="none")
    with pytest.raises(ShapeMismatchError, match="attractor"):
        modulated_velocity(x, f, torch.zeros(3, dtype=torch.float64), mode="none")
    with pytest.raises(ShapeMismatchError, match="x is"):
        renyi_entropy(prim, x.float())
    with pytest.raises(NonFiniteError, match="x"):
        renyi_entropy(prim, torch.full((1, 2), math.nan, dtype=torch.float64))
    with pytest.raises(NonFiniteError, match="h2_ref"):
        modulated_velocity(x, f, prim.attractor, h2=z, h2_ref=math.nan, mode="small")
    with pytest.raises(ShapeMismatchError, match="velocity_covariances"):
        renyi_entropy(prim, x, velocity_covariances=torch.eye(2, dtype=torch.float64))


@pytest.mark.parametrize("name", ["none", "large", "small", "full"])
def test_configs_instantiate(name: str) -> None:
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name=f"modulation/{name}")
    node = cfg.modulation if "modulation" in cfg else cfg
    mod = instantiate(node)
    assert isinstance(mod, Modulation) and mod.mode == name
    assert mod.lambda_limit >= 1 and mod.entropy_quantile == 1.0 and 0 <= mod.radial_floor <= 1


@requires_cuda
@pytest.mark.cuda
def test_cuda_matches_cpu(generator: torch.Generator) -> None:
    prim = angle_lpvds()
    x = _sample_states(prim, 500, generator)
    own = torch.randn(x.shape[0], dtype=torch.float64, generator=generator)
    other = torch.randn(x.shape[0], dtype=torch.float64, generator=generator)
    mod = Modulation("full", entropy_quantile=0.5)
    for dtype in (torch.float64, torch.float32):
        pc = prim.to(dtype=dtype)
        pg = prim.to(dtype=dtype, device="cuda")
        ref = mod.reference_entropy(pc, angle_training_states().to(dtype))
        cpu = mod(pc, x.to(dtype), None, own.to(dtype), other.to(dtype), ref)
        gpu = mod(pg, x.to(dtype).cuda(), None, own.to(dtype).cuda(), other.to(dtype).cuda(), ref.cuda())
        assert gpu.velocity.device.type == "cuda" and gpu.velocity.dtype == dtype
        tol = dict(rtol=1e-4, atol=1e-3) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(renyi_entropy(pg, x.to(dtype).cuda()).cpu(), renyi_entropy(pc, x.to(dtype)), **tol)
        same = gpu.branch.cpu() == cpu.branch
        assert float(same.double().mean()) > 0.99
        torch.testing.assert_close(gpu.velocity.cpu()[same], cpu.velocity[same], **tol)
