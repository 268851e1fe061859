"""Independent references for the disturbance modulation (policy), the velocity-mixture Renyi entropy and the
behaviour tree, each aimed at a mutant that the other tests let through: a naive per-sample numpy loop of eqs
12-18 with an explicit W D W^T frame (QR completion), closed-form H2 of a Gaussian mixture with scipy's
multivariate normal for the pairwise overlaps, a Monte Carlo estimate of the overlap integral, dV/dt < 0 for random
SPD P, and the documented tree structure and decisions on stub densities."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest
import torch
from py_trees.common import Status
from scipy.stats import multivariate_normal

from conftest import certified_primitive

from lfd_torch.ds import StablePrimitive
from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError
from lfd_torch.modulation import (
    Branch,
    Modulation,
    mixture_renyi_entropy,
    modulated_velocity,
    modulated_velocity_single,
    modulated_velocity_unchecked,
    pairwise_log_overlap,
    reference_entropy,
    renyi_entropy,
    velocity_mixture,
)

F64 = torch.float64
MODES = ("none", "large", "small", "full")


# ---------------------------------------------------------------------------------------------------- references
def _frame(e: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """An orthonormal W with first column e/||e|| (QR of [e, random columns]), independent of the closed form."""
    d = e.shape[0]
    B = np.column_stack([e, rng.standard_normal((d, d - 1))])
    Q, R = np.linalg.qr(B)
    return Q * np.sign(R[0, 0]) if d == 1 else Q @ np.diag(np.sign(np.diag(R)))


def _reference_one(x, f, g, own, other, h2, ref, mode, limit, kappa, rng):
    """Eqs 12-18 as the policy docstring states them, for one sample in numpy, with the c = 0 rule: returns the
    velocity and the branch. Where |c| >= kappa ||f|| the velocity is W D W^T f with an explicit frame W."""
    e = x - g
    r = float(np.linalg.norm(e))
    if mode == "none":
        return f.copy(), Branch.UNMODULATED
    if r == 0.0:
        return np.zeros_like(f), Branch.AT_GOAL
    eg = e / r
    c = float(eg @ f)
    a = max(abs(c), kappa * float(np.linalg.norm(f)))
    d = f.shape[0]
    outside = mode in ("large", "full") and own < other
    if outside:
        ratio = 1.0 if own == other == -math.inf else math.exp(min(other - own, 700.0))
        s = max(min(limit, ratio), 1.0)
        if abs(c) >= kappa * np.linalg.norm(f) and c != 0.0:
            W = _frame(e, rng)
            D = np.diag([-np.sign(c) * s] + [0.0] * (d - 1))
            return W @ D @ W.T @ f, Branch.LARGE_SCALE
        return -a * s * eg, Branch.LARGE_SCALE
    if mode in ("small", "full") and h2 > ref:
        lam = min(1.0, math.exp(ref - h2))
        if abs(c) >= kappa * np.linalg.norm(f) and c != 0.0:
            W = _frame(e, rng)
            D = np.diag([lam - np.sign(c)] + [lam] * (d - 1))
            return W @ D @ W.T @ f, Branch.SMALL_SCALE
        return lam * f - a * eg, Branch.SMALL_SCALE
    return f.copy(), Branch.UNMODULATED


def _random_case(n: int, d: int, seed: int):
    """Seeded samples covering every branch and the exact ties: x = g, f orthogonal to e (c = 0), f along +-e,
    own == other, other = -inf, own = other = -inf, h2 == h2_ref, and h2 far above h2_ref (lambda_ss underflows)."""
    rng = np.random.default_rng(seed)
    g = rng.standard_normal(d) * 2.0
    x = g + rng.standard_normal((n, d))
    f = rng.standard_normal((n, d)) * 3.0
    x[:4] = g
    e = x - g
    for i in range(4, 14):  # c = 0 exactly (d >= 2): f = rotation of e by 90 degrees in the first plane
        f[i] = 0.0
        f[i, 0], f[i, 1] = -e[i, 1], e[i, 0]
    f[14:18] = 2.0 * e[14:18]  # c > 0: f points away from g
    f[18:22] = -0.5 * e[18:22]  # c < 0
    own = rng.standard_normal(n)
    other = own + 1.5 * rng.standard_normal(n)
    other[22:30] = own[22:30]  # ties: inside
    other[30:34] = -math.inf
    own[34:37] = -math.inf
    other[34:36] = -math.inf  # both -inf: inside (not <), s would be 1
    h2 = rng.standard_normal(n) * 2.0
    ref = rng.standard_normal(n)
    h2[37:45] = ref[37:45]  # ties: unmodulated
    h2[45:50] = ref[45:50] + 2000.0  # lambda_ss underflows to 0
    own[4:14:2] = other[4:14:2] - 1.0  # half of the c = 0 samples are outside A_m
    return rng, g, x, f, own, other, h2, ref


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("kappa", [0.0, 0.1, 0.6])
def test_modulated_velocity_matches_a_naive_per_sample_loop(d: int, kappa: float) -> None:
    """Property: in every mode, the checked, the feature-major unchecked and the single-sample forms all equal a
    naive numpy loop of eqs 12-18 (explicit W D W^T where |c| >= kappa ||f||, else the floored formulas
    -a s e_g and lambda_ss f - a e_g), with the branch rules on exact ties (own == other is inside, H2 == H2_ref
    is unmodulated, both densities -inf is inside) and zero velocity at x = g."""
    n, limit = 80, 2.5
    rng, g, x, f, own, other, h2, ref = _random_case(n, d, seed=100 + d)
    T = lambda a: torch.tensor(a, dtype=F64)  # noqa: E731
    for mode in MODES:
        want_v = np.zeros((n, d))
        want_b = []
        for i in range(n):
            v, b = _reference_one(x[i], f[i], g, own[i], other[i], h2[i], ref[i], mode, limit, kappa, rng)
            want_v[i] = v
            want_b.append(int(b))
        kwargs = {}
        if mode in ("large", "full"):
            kwargs.update(log_p_own=T(own), log_p_other=T(other))
        if mode in ("small", "full"):
            kwargs.update(h2=T(h2), h2_ref=T(ref))
        res = modulated_velocity(T(x), T(f), T(g), mode=mode, lambda_limit=limit, radial_floor=kappa, **kwargs)
        assert res.branch.tolist() == want_b, mode
        np.testing.assert_allclose(res.velocity.numpy(), want_v, rtol=1e-9, atol=1e-10, err_msg=mode)
        # feature-major (d, n) layout of the hot path
        fm = modulated_velocity_unchecked(
            T(x).T.contiguous(), T(f).T.contiguous(), T(g).unsqueeze(-1),
            kwargs.get("log_p_own"), kwargs.get("log_p_other"), kwargs.get("h2"), kwargs.get("h2_ref"),
            mode, limit, kappa, dim=0,
        )  # fmt: skip
        assert fm.branch.tolist() == want_b, mode
        np.testing.assert_allclose(fm.velocity.T.numpy(), want_v, rtol=1e-9, atol=1e-10, err_msg=mode)
        for i in range(n):
            u, b = modulated_velocity_single(list(x[i] - g), list(f[i]), own[i], other[i], h2[i], ref[i], mode,
                                             limit, kappa)  # fmt: skip
            assert int(b) == want_b[i], (mode, i)
            np.testing.assert_allclose(u, want_v[i], rtol=1e-9, atol=1e-10, err_msg=f"{mode} {i}")


def test_lyapunov_rate_is_negative_for_random_spd_p_and_meets_the_documented_bounds() -> None:
    """Property (eqs 19-21 as the policy docstring restates them): for a random SPD P far from I and velocities f
    with V_f = 2 e^T P f < 0 (many of them with c > 0, moving away from g in the Euclidean sense), the modulated
    velocity gives dV/dt = 2 e^T P M f < 0 for x != g in every mode, and dV/dt <= -2 kappa s lambda_min(P) r ||f||
    (large scale), dV/dt <= lambda_ss V_f - 2 kappa lambda_min(P) r ||f|| (small scale)."""
    rng = np.random.default_rng(7)
    for d in (2, 3):
        Q, _ = np.linalg.qr(rng.standard_normal((d, d)))
        P = Q @ np.diag(np.logspace(0, -2, d)) @ Q.T
        lmin = float(np.linalg.eigvalsh(P)[0])
        n, kappa, limit = 400, 0.1, 3.0
        g = rng.standard_normal(d)
        e = rng.standard_normal((n, d)) * rng.uniform(0.01, 10.0, (n, 1))
        f = rng.standard_normal((n, d)) * 2.0
        f[np.einsum("ni,ij,nj->n", e, P, f) > 0] *= -1.0
        f[:20] = (-(P @ e[:20].T).T)  # the P-gradient descent direction
        c = np.einsum("ni,ni->n", e, f)
        assert (c > 0).sum() > 20  # the case where -sgn(c) turns the radial component around
        own = rng.standard_normal(n)
        other = own + rng.standard_normal(n)
        ref = 0.0
        h2 = rng.standard_normal(n) * 3.0
        h2[:10] = 900.0  # lambda_ss underflows
        T = lambda a: torch.tensor(a, dtype=F64)  # noqa: E731
        x = g + e
        for mode in ("large", "small", "full"):
            res = modulated_velocity(T(x), T(f), T(g), log_p_own=T(own), log_p_other=T(other), h2=T(h2),
                                     h2_ref=ref, mode=mode, lambda_limit=limit, radial_floor=kappa)  # fmt: skip
            v = res.velocity.numpy()
            rate = 2.0 * np.einsum("ni,ij,nj->n", e, P, v)
            assert (rate < 0).all(), (mode, rate.max())
            r = np.linalg.norm(e, axis=1)
            nf = np.linalg.norm(f, axis=1)
            br = res.branch.numpy()
            large = br == int(Branch.LARGE_SCALE)
            s = np.clip(np.exp(other - own), 1.0, limit)
            assert np.all(rate[large] <= -2 * kappa * s[large] * lmin * r[large] * nf[large] * (1 - 1e-9))
            small = br == int(Branch.SMALL_SCALE)
            lam = np.minimum(1.0, np.exp(ref - h2))
            vf = 2.0 * np.einsum("ni,ij,nj->n", e, P, f)
            bound = lam * vf - 2 * kappa * lmin * r * nf
            assert np.all(rate[small] <= bound[small] + 1e-9 * np.abs(bound[small]))


# ---------------------------------------------------------------------------------------------------- policy checks
def test_modulated_velocity_rejects_non_finite_vectors_and_mixed_dtypes() -> None:
    """Property (modulated_velocity's Raises): NaN or Inf in x, f or the attractor is a NonFiniteError, and f or the
    attractor in another dtype than x is a ShapeMismatchError (no silent promotion)."""
    x = torch.tensor([[1.0, 2.0], [0.5, -1.0]], dtype=F64)
    f = torch.tensor([[-1.0, 0.0], [0.0, 1.0]], dtype=F64)
    g = torch.zeros(2, dtype=F64)
    for mode in MODES:
        for bad in (math.nan, math.inf):
            for which in range(3):
                args = [x.clone(), f.clone(), g.clone()]
                args[which].view(-1)[0] = bad
                with pytest.raises(NonFiniteError):
                    modulated_velocity(*args, log_p_own=0.0, log_p_other=-1.0, h2=0.0, h2_ref=1.0, mode=mode)
        with pytest.raises(ShapeMismatchError):
            modulated_velocity(x, f.float(), g, log_p_own=0.0, log_p_other=-1.0, h2=0.0, h2_ref=1.0, mode=mode)
        with pytest.raises(ShapeMismatchError):
            modulated_velocity(x, f, g.float(), log_p_own=0.0, log_p_other=-1.0, h2=0.0, h2_ref=1.0, mode=mode)


def _h2_reference(prim: StablePrimitive, x: np.ndarray, S: np.ndarray | None = None) -> float:
    """Eq. 15 with the NOTES 4a/4b corrections, double loop with scipy densities."""
    pi, mx, Sx = prim.gmm.weights.numpy(), prim.gmm.means.numpy(), prim.gmm.covariances.numpy()
    A, g = prim.A.numpy(), prim.attractor.numpy()
    S = prim.velocity_covariances.numpy() if S is None else S
    K = len(pi)
    logw = [math.log(pi[k]) + multivariate_normal(mx[k], Sx[k]).logpdf(x) for k in range(K)]
    mu = [A[k] @ (x - g) for k in range(K)]
    terms = [logw[i] + logw[j] + multivariate_normal(mu[j], S[i] + S[j]).logpdf(mu[i]) for i in range(K) for j in range(K)]
    m = max(terms)
    return -(m + math.log(sum(math.exp(t - m) for t in terms)))


def test_modulation_call_passes_its_configuration_and_the_documented_defaults() -> None:
    """Property (Modulation docstring): __call__ uses the instance's radial_floor and lambda_limit (equal to
    modulated_velocity with the same arguments and H2 from renyi_entropy), mode 'none' evaluates the primitive when
    f is None, entropy_quantile=None with h2_ref=None means H2(g), and field() takes log p(x|A_m-) = -inf when no
    other subtask density is given."""
    prim = certified_primitive(2, 3, seed=5)
    rng = np.random.default_rng(6)
    g = prim.attractor
    x = g + torch.tensor(rng.standard_normal((40, 2)) * 2.0, dtype=F64)
    e = x - g
    f = torch.stack([-e[:, 1], e[:, 0]], dim=-1)  # c = 0: the floor decides the speed
    own = torch.tensor(rng.standard_normal(40), dtype=F64)
    other = own + torch.tensor(rng.standard_normal(40) * 2.0, dtype=F64)
    h2 = renyi_entropy(prim, x)
    ref = float(h2.median())
    for kappa, limit in ((0.0, 1.0), (0.7, 5.0)):
        mod = Modulation("full", lambda_limit=limit, radial_floor=kappa)
        got = mod(prim, x, f, own, other, ref)
        want = modulated_velocity(x, f, g, log_p_own=own, log_p_other=other, h2=h2, h2_ref=ref, mode="full",
                                  lambda_limit=limit, radial_floor=kappa)  # fmt: skip
        assert torch.equal(got.branch, want.branch)
        torch.testing.assert_close(got.velocity, want.velocity, rtol=1e-12, atol=1e-12)
        assert {1, 2} <= set(got.branch.tolist())
    assert torch.equal(Modulation("none")(prim, x).velocity, prim(x))
    literal = Modulation("small", entropy_quantile=None)(prim, x, f)
    h2_g = _h2_reference(prim, g.numpy())
    want = modulated_velocity(x, f, g, h2=h2, h2_ref=h2_g, mode="small")
    assert torch.equal(literal.branch, want.branch)
    torch.testing.assert_close(literal.velocity, want.velocity, rtol=1e-9, atol=1e-12)
    field = Modulation("large").field(prim, lambda z: torch.full(z.shape[:-1], -5.0, dtype=F64))
    torch.testing.assert_close(field(x), prim(x))  # own = -5 > other = -inf: inside, unmodulated
    with pytest.raises(InvalidArgumentError, match="entropy_quantile"):
        Modulation(entropy_quantile=-0.1)
    with pytest.raises(InvalidArgumentError, match="entropy_quantile"):
        Modulation(entropy_quantile=1.5)
    assert Modulation("small").uses_entropy and Modulation("full").uses_entropy
    assert not Modulation("large").uses_entropy and not Modulation("none").uses_entropy
    assert Modulation("large").uses_subtask_densities and not Modulation("small").uses_subtask_densities


# ---------------------------------------------------------------------------------------------------- entropy
def test_pairwise_log_overlap_matches_scipy_and_monte_carlo() -> None:
    """Property (pairwise_log_overlap docstring): entry (i, j) is log N(mu_i; mu_j, S_i + S_j) (scipy), for shared
    (K, d, d) and per-row (B, K, d, d) covariances, and it equals the log of the overlap integral
    int N(u; mu_i, S_i) N(u; mu_j, S_j) du = E_{u ~ N(mu_i, S_i)}[N(u; mu_j, S_j)] (Monte Carlo, 5 standard errors)."""
    rng = np.random.default_rng(11)
    B, K, d = 3, 3, 3
    means = rng.standard_normal((B, K, d)) * 1.5
    S = np.stack([(lambda M: M @ M.T / d + 0.2 * np.eye(d))(rng.standard_normal((d, d))) for _ in range(K)])
    S_rows = np.stack([np.stack([(lambda M: M @ M.T / d + 0.2 * np.eye(d))(rng.standard_normal((d, d)))
                                 for _ in range(K)]) for _ in range(B)])  # fmt: skip
    T = lambda a: torch.tensor(a, dtype=F64)  # noqa: E731
    shared = pairwise_log_overlap(T(means), T(S)).numpy()
    rows = pairwise_log_overlap(T(means), T(S_rows)).numpy()
    for b in range(B):
        for i in range(K):
            for j in range(K):
                want = multivariate_normal(means[b, j], S[i] + S[j]).logpdf(means[b, i])
                assert math.isclose(shared[b, i, j], want, rel_tol=1e-10, abs_tol=1e-10), (b, i, j)
                want = multivariate_normal(means[b, j], S_rows[b, i] + S_rows[b, j]).logpdf(means[b, i])
                assert math.isclose(rows[b, i, j], want, rel_tol=1e-10, abs_tol=1e-10), (b, i, j)
    n, mu = 200_000, 0.4 * means[:1]  # close means: the estimator has a small variance
    near = pairwise_log_overlap(T(mu), T(S)).numpy()[0]
    for i, j in ((0, 1), (2, 0), (1, 1)):
        u = rng.multivariate_normal(mu[0, i], S[i], size=n)
        p = multivariate_normal(mu[0, j], S[j]).pdf(u)
        se = p.std() / p.mean() / math.sqrt(n)
        assert se < 0.02
        assert abs(math.log(p.mean()) - near[i, j]) < 5 * se, (i, j)


def test_mixture_renyi_entropy_is_the_closed_form_of_the_unnormalised_mixture() -> None:
    """Property (mixture_renyi_entropy docstring): H2 = -log sum_ij w_i w_j N(mu_i; mu_j, S_i + S_j) with
    unnormalised weights (scaling all w by z shifts H2 by -2 log z), a -inf log weight drops its component, and
    a log_weights shape that is not means.shape[:-1] is a ShapeMismatchError."""
    rng = np.random.default_rng(12)
    K, d = 4, 2
    means = rng.standard_normal((5, K, d)) * 2.0
    S = np.stack([(lambda M: M @ M.T / d + 0.3 * np.eye(d))(rng.standard_normal((d, d))) for _ in range(K)])
    logw = rng.standard_normal((5, K)) - 3.0
    logw[4, 1] = -math.inf
    T = lambda a: torch.tensor(a, dtype=F64)  # noqa: E731
    got = mixture_renyi_entropy(T(logw), T(means), T(S)).numpy()
    for b in range(5):
        total = sum(math.exp(logw[b, i] + logw[b, j]) * multivariate_normal(means[b, j], S[i] + S[j]).pdf(means[b, i])
                    for i in range(K) for j in range(K))  # fmt: skip
        assert math.isclose(got[b], -math.log(total), rel_tol=1e-10), b
    shifted = mixture_renyi_entropy(T(logw + 1.7), T(means), T(S)).numpy()
    np.testing.assert_allclose(shifted, got - 3.4, rtol=1e-12, atol=1e-12)
    keep = [0, 2, 3]
    dropped = mixture_renyi_entropy(T(logw[4, keep]), T(means[4, keep]), T(S[keep])).numpy()
    assert math.isclose(float(dropped), got[4], rel_tol=1e-12)
    with pytest.raises(ShapeMismatchError):
        mixture_renyi_entropy(T(logw[:, :3]), T(means), T(S))
    with pytest.raises(ShapeMismatchError):
        mixture_renyi_entropy(T(logw[:4]), T(means), T(S))


def test_renyi_entropy_and_reference_entropy_against_a_scipy_double_loop() -> None:
    """Property (entropy module docstring and reference_entropy): H2(x) of the primitive's mixture (w_k = pi_k
    N(x; mu_k^x, Sigma_k^x) unnormalised, mu_k = A_k (x - g) with g far from 0 and A_k non-symmetric, S_k the
    primitive's velocity covariances or the override); H2(x_r) with quantile None is H2(g) and with quantile q the
    numpy linear-interpolated q-quantile of H2 over the training states; bad inputs are typed errors."""
    prim = certified_primitive(2, 3, seed=21)
    rng = np.random.default_rng(22)
    x = prim.gmm.means.numpy()[[0, 1, 2, 0, 1]] + rng.standard_normal((5, 2))
    T = lambda a: torch.tensor(a, dtype=F64)  # noqa: E731
    h2 = renyi_entropy(prim, T(x)).numpy()
    want = np.array([_h2_reference(prim, xb) for xb in x])
    np.testing.assert_allclose(h2, want, rtol=1e-10)
    iso = np.stack([np.eye(2) * v for v in (0.5, 2.0, 7.0)])
    h2_iso = renyi_entropy(prim, T(x), velocity_covariances=T(iso)).numpy()
    np.testing.assert_allclose(h2_iso, [_h2_reference(prim, xb, iso) for xb in x], rtol=1e-10)
    mix = velocity_mixture(prim, T(x), velocity_covariances=T(iso))
    np.testing.assert_allclose(mix.covariances.numpy(), iso)
    # reference entropy
    g = prim.attractor.numpy()
    assert np.linalg.norm(g) > 1.0
    assert math.isclose(float(reference_entropy(prim, None, None)), _h2_reference(prim, g), rel_tol=1e-10)
    for q in (0.0, 0.3, 0.75, 1.0):
        assert math.isclose(float(reference_entropy(prim, T(x), q)), float(np.quantile(want, q)), rel_tol=1e-10), q
    with pytest.raises(InvalidArgumentError):
        reference_entropy(prim, T(x), 1.5)
    with pytest.raises(InvalidArgumentError):
        reference_entropy(prim, T(x), -0.1)
    with pytest.raises(InvalidArgumentError):
        reference_entropy(prim, None, 0.5)
    with pytest.raises(InvalidArgumentError):
        reference_entropy(prim, T(np.zeros((0, 2))), 0.5)
    with pytest.raises(ShapeMismatchError):
        renyi_entropy(prim, T(x), velocity_covariances=T(iso[:2]))
    with pytest.raises(ShapeMismatchError):
        renyi_entropy(prim, T(x).float())
    with pytest.raises(NonFiniteError):
        renyi_entropy(prim, T(np.array([[math.nan, 0.0]])))


# ---------------------------------------------------------------------------------------------------- tree
class _StubEngine:
    """What SkillTree needs of an engine: routes, a probe (log p(x|A_m) and arrival per step, set by the test) and
    a drive that returns the step as the velocity and records (step, inside, densities)."""

    def __init__(self, routes, n_steps):
        self.routes = tuple(tuple(r) for r in routes)
        self.dim = 2
        self._f = {"dtype": F64}
        self.ld = [0.0] * n_steps
        self.arrived = [False] * n_steps
        self.drives: list[tuple[int, bool, tuple[float, float] | None]] = []
        self.probes = 0

    def tick_probe(self, x):
        self.probes += 1
        return list(self.ld), list(self.arrived)

    def tick_velocity(self, x, step, inside, densities):
        self.drives.append((step, inside, densities))
        return torch.full((2,), float(step), dtype=F64), Branch.SMALL_SCALE if inside else Branch.LARGE_SCALE


def _shape(node):
    """(class name, node name, memory, children) of a py_trees subtree."""
    kids = tuple(_shape(c) for c in node.children)
    return (type(node).__name__, node.name, getattr(node, "memory", None), kids)


def _step_shape(m):
    return ("Selector", f"step {m}", False, (
        ("Reached", f"Reached {m}", None, ()),
        ("Sequence", f"track {m}", False, (("InSubtask", f"InSubtask {m}", None, ()), ("Track", f"Track {m}", None, ()))),
        ("Recover", f"Recover {m}", None, ()),
    ))  # fmt: skip


def _choose(*routes):
    return ("ChooseRoute", f"ChooseRoute {','.join(map(str, routes))}", None, ())


def test_tree_structure_is_the_documented_one() -> None:
    """Property (tree module docstring): for routes (0, 1, 3) and (0, 2, 3) the tree is exactly the documented one
    (Selector 'task' > Sequence 'routes 0,1' > ChooseRoute, Selector 'step 0' = [Reached, Sequence 'track'
    = [InSubtask, Track], Recover], Selector 'after step 0' with one Sequence per way on, in route order); every
    composite has memory=False; a single route is one Sequence; routes that start differently are two root
    branches; three routes whose second steps are 1, 2, 1 part after step 0 into two ways (routes 0,2 share step
    1, then part again)."""
    from lfd_torch.skills.tree import SkillTree

    tree = SkillTree(_StubEngine([(0, 1, 3), (0, 2, 3)], 4))
    want = ("Selector", "task", False, (
        ("Sequence", "routes 0,1", False, (
            _choose(0, 1), _step_shape(0),
            ("Selector", "after step 0", False, (
                ("Sequence", "route 0", False, (_choose(0), _step_shape(1), _step_shape(3))),
                ("Sequence", "route 1", False, (_choose(1), _step_shape(2), _step_shape(3))),
            )),
        )),
    ))  # fmt: skip
    assert _shape(tree.root) == want
    single = SkillTree(_StubEngine([(0, 1, 2)], 3))
    assert _shape(single.root) == ("Selector", "task", False, (
        ("Sequence", "route 0", False, (_choose(0), _step_shape(0), _step_shape(1), _step_shape(2))),))  # fmt: skip
    apart = SkillTree(_StubEngine([(0, 1), (2, 1)], 3))
    assert _shape(apart.root) == ("Selector", "task", False, (
        ("Sequence", "route 0", False, (_choose(0), _step_shape(0), _step_shape(1))),
        ("Sequence", "route 1", False, (_choose(1), _step_shape(2), _step_shape(1))),
    ))  # fmt: skip
    three = SkillTree(_StubEngine([(0, 1, 3), (0, 2, 3), (0, 1, 4)], 5))
    assert _shape(three.root) == ("Selector", "task", False, (
        ("Sequence", "routes 0,1,2", False, (
            _choose(0, 1, 2), _step_shape(0),
            ("Selector", "after step 0", False, (
                ("Sequence", "routes 0,2", False, (
                    _choose(0, 2), _step_shape(1),
                    ("Selector", "after step 1", False, (
                        ("Sequence", "route 0", False, (_choose(0), _step_shape(3))),
                        ("Sequence", "route 2", False, (_choose(2), _step_shape(4))),
                    )),
                )),
                ("Sequence", "route 1", False, (_choose(1), _step_shape(2), _step_shape(3))),
            )),
        )),
    ))  # fmt: skip


def test_tree_ticks_take_the_documented_decisions() -> None:
    """Property (tree module docstring, leaf docstrings): the first tick picks the route whose first subtask space
    is the most likely (the first on ties); InSubtask is SUCCESS iff log p(x|A_m) >= max_{k != m} log p(x|A_k)
    (a tie is inside) and hands those two densities to the drive; inside drives Track, outside Recover; the
    visitor logs Reached before InSubtask before Track; arrival completes the step and the next step drives in the
    same tick; a completed step stays complete whatever x; an uncompleted step is not skipped; ticks are
    memoryless (Recover on one tick, Track on the next); the end of the route is done with a zero velocity."""
    from lfd_torch.skills.tree import SkillTree

    eng = _StubEngine([(0, 1), (2, 1)], 3)
    tree = SkillTree(eng)
    x = torch.zeros(2, dtype=F64)
    eng.ld = [-1.0, -9.0, -1.0]  # tie between the first steps 0 and 2: the first route
    res = tree.tick(x)
    assert (res.route, res.index, res.step, res.done) == (0, 0, 0, False)
    assert eng.drives[-1] == (0, True, (-1.0, -1.0))  # own == other is inside
    assert res.decisions == (
        ("ChooseRoute 0", "SUCCESS"), ("Reached 0", "FAILURE"), ("InSubtask 0", "SUCCESS"), ("Track 0", "RUNNING"),
        ("track 0", "RUNNING"), ("step 0", "RUNNING"), ("route 0", "RUNNING"), ("task", "RUNNING"),
    )  # fmt: skip
    assert eng.probes == 1  # once per tick
    eng.ld = [-2.0, -9.0, -1.0]
    res = tree.tick(x)
    assert (res.route, res.step) == (1, 2) and eng.drives[-1] == (2, True, (-1.0, -2.0))
    # outside A_0: Recover with (own, largest other)
    eng.ld = [-3.0, -2.5, -2.0]
    res = tree.tick(x, step=0)
    assert res.step == 0 and eng.drives[-1] == (0, False, (-3.0, -2.0)) and res.branch == Branch.LARGE_SCALE
    eng.ld = [-1.0, -2.5, -2.0]
    res = tree.tick(x, step=0)  # the next tick re-evaluates from the root: inside now
    assert eng.drives[-1] == (0, True, (-1.0, -2.0))
    # own density the largest: the other density is the largest of the others, not own
    eng.ld = [5.0, -2.5, -2.0]
    tree.tick(x, step=0)
    assert eng.drives[-1] == (0, True, (5.0, -2.0))
    # arrival at g_0: the step completes, step 1 drives in the same tick
    eng.arrived = [True, False, False]
    eng.ld = [-5.0, -1.0, -4.0]
    res = tree.tick(x, step=0)
    assert (res.index, res.step, res.done) == (1, 1, False) and eng.drives[-1] == (1, True, (-1.0, -4.0))
    # step 0 completed earlier stays complete even where x is no longer in its ball; step 1 is not skipped
    eng.arrived = [False, False, False]
    res = tree.tick(x, step=1, route=0)
    assert (res.index, res.step) == (1, 1) and eng.drives[-1][0] == 1
    assert ("Reached 0", "SUCCESS") in res.decisions and ("Reached 1", "FAILURE") in res.decisions
    # the end of the route: done, zero velocity at the goal
    eng.arrived = [False, True, False]
    res = tree.tick(x, step=1, route=0)
    assert res.done and res.step is None and res.index == 2 and res.branch == Branch.AT_GOAL
    assert torch.equal(res.velocity, torch.zeros(2, dtype=F64))


def test_tree_way_on_and_progress_rules() -> None:
    """Property (_Context.way_on and SkillTree.tick docstrings): where the routes part, the robot goes on with the
    route whose next subtask space is the most likely, keeping its own route on ties, and only among routes with
    its steps so far; a step shared by routes with different steps before it needs route=; a step that the routes
    reach through the same steps is taken as the first route's."""
    from lfd_torch.skills.tree import SkillTree

    eng = _StubEngine([(0, 1, 3), (0, 2, 3), (4, 5)], 6)
    tree = SkillTree(eng)
    x = torch.zeros(2, dtype=F64)
    eng.arrived = [True, False, False, False, False, False]
    eng.ld = [-9.0, -1.0, -1.0, -9.0, -9.0, 0.0]  # tie between steps 1 and 2; step 5 (another route) likelier
    for own in (0, 1):
        res = tree.tick(x, step=0, route=own)
        assert (res.route, res.index) == (own, 1), own
    eng.ld = [-9.0, -3.0, -1.0, -9.0, -9.0, 0.0]
    res = tree.tick(x, step=0, route=0)
    assert (res.route, res.step) == (1, 2)
    res = tree.tick(x, step=0)  # routes 0 and 1 share step 0's head: route 0 stands for them
    assert (res.route, res.step) == (1, 2)
    with pytest.raises(InvalidArgumentError):
        tree.tick(x, step=3)  # heads (0, 1, 3) and (0, 2, 3) differ
    assert tree.tick(x, step=3, route=1).route == 1


def test_tree_progress_of_a_repeated_step_is_its_first_occurrence() -> None:
    """Property (SkillTree._progress: a step is placed by the steps before it, routes[r].index(step), the same rule
    as its heads check): in route (0, 1, 2, 1) step 1 given alone is the first visit (index 1, step 2 still to do),
    so reaching g_1 there moves on to step 2, not to the end of the task."""
    from lfd_torch.skills.tree import SkillTree

    eng = _StubEngine([(0, 1, 2, 1)], 3)
    tree = SkillTree(eng)
    x = torch.zeros(2, dtype=F64)
    res = tree.tick(x, step=1)
    assert (res.index, res.step, res.done) == (1, 1, False)
    eng.arrived = [False, True, False]
    res = tree.tick(x, step=1)
    assert (res.index, res.step, res.done) == (2, 2, False)
