"""Independent references for the velocity-mixture Renyi entropy, the modulation policy and the batched DTW
distance, each aimed at a mutant that the other tests let through: scipy closed forms of the pairwise overlaps and of
H2 (precomputed per-row factors, covariance overrides forwarded by the reference entropy, a duck-typed primitive),
numpy quantiles of H2 for the Modulation's threshold, the inclusive magnitude limit of the policy (with the radial
component of the modulated velocity negative there), and a naive O(n m) DTW loop with NaN padding on both sides,
plus the documented input errors of dtw_distance."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from conftest import certified_primitive

from lfd_torch.ds import StablePrimitive
from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError
from lfd_torch.metrics import dtw_distance
from lfd_torch.modulation import (
    Branch,
    Modulation,
    mixture_renyi_entropy,
    modulated_velocity,
    pair_factors,
    pairwise_log_overlap,
    reference_entropy,
    renyi_entropy,
    velocity_mixture,
)
from lfd_torch.utils import safe_magnitude

F64 = torch.float64


def T(a) -> torch.Tensor:
    return torch.tensor(np.asarray(a), dtype=F64)


def _spd(rng: np.random.Generator, d: int, scale: float = 1.0, floor: float = 0.3) -> np.ndarray:
    B = rng.standard_normal((d, d))
    return scale * (B @ B.T / d + floor * np.eye(d))


def _h2_scipy(pi, mx, Sx, A, g, S, x) -> float:
    """H2(x) = -log sum_ij w_i w_j N(mu_i; mu_j, S_i + S_j), w_k = pi_k N(x; mu_k^x, Sigma_k^x) unnormalised,
    mu_k = A_k (x - g): double loop with scipy densities."""
    K = len(pi)
    logw = [math.log(pi[k]) + multivariate_normal(mx[k], Sx[k]).logpdf(x) for k in range(K)]
    mu = [A[k] @ (x - g) for k in range(K)]
    terms = [logw[i] + logw[j] + multivariate_normal(mu[j], S[i] + S[j]).logpdf(mu[i])
             for i in range(K) for j in range(K)]  # fmt: skip
    m = max(terms)
    return -(m + math.log(sum(math.exp(t - m) for t in terms)))


def _h2_of(prim: StablePrimitive, x: np.ndarray, S: np.ndarray | None = None) -> float:
    S = prim.velocity_covariances.numpy() if S is None else S
    return _h2_scipy(prim.gmm.weights.numpy(), prim.gmm.means.numpy(), prim.gmm.covariances.numpy(), prim.A.numpy(),
                     prim.attractor.numpy(), S, x)  # fmt: skip


def _naive_dtw(a: np.ndarray, b: np.ndarray) -> float:
    """O(n m) DTW with Euclidean local cost, steps (i-1, j), (i, j-1), (i-1, j-1), both ends matched."""
    n, m = len(a), len(b)
    D = np.full((n + 1, m + 1), math.inf)
    D[0, 0] = 0.0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            c = math.sqrt(sum((p - q) ** 2 for p, q in zip(a[i - 1], b[j - 1])))
            D[i, j] = c + min(D[i - 1, j], D[i, j - 1], D[i - 1, j - 1])
    return float(D[n, m])


# ---------------------------------------------------------------------------------------------------- entropy
def test_pairwise_log_overlap_uses_precomputed_factors_without_covariances() -> None:
    """Property (pairwise_log_overlap docstring: 'factors: precomputed pair_factors of the covariances (then
    covariances is not used)'): with covariances=None and factors from pair_factors, shared (K, d, d) or gathered per
    row from a bank of covariance sets, entry (i, j) is scipy's log N(mu_i; mu_j, S_i + S_j); mixture_renyi_entropy
    with the gathered factors is the scipy closed form of the unnormalised mixture."""
    rng = np.random.default_rng(31)
    M, B, K, d = 3, 5, 3, 2
    bank = np.stack([np.stack([_spd(rng, d) for _ in range(K)]) for _ in range(M)])  # (M, K, d, d)
    means = rng.standard_normal((B, K, d)) * 1.5
    logw = rng.standard_normal((B, K)) - 2.0
    step = np.array([2, 0, 1, 2, 0])
    L_inv, half = pair_factors(T(bank))  # (M, K, K, d, d), (M, K, K)
    shared = pairwise_log_overlap(T(means), None, factors=(L_inv[1], half[1])).numpy()
    rows = pairwise_log_overlap(T(means), None, factors=(L_inv[step], half[step])).numpy()
    h2 = mixture_renyi_entropy(T(logw), T(means), T(bank[step]), factors=(L_inv[step], half[step])).numpy()
    for b in range(B):
        S = bank[step[b]]
        total = 0.0
        for i in range(K):
            for j in range(K):
                want = multivariate_normal(means[b, j], bank[1, i] + bank[1, j]).logpdf(means[b, i])
                assert math.isclose(shared[b, i, j], want, rel_tol=1e-10, abs_tol=1e-10), (b, i, j)
                want = multivariate_normal(means[b, j], S[i] + S[j]).logpdf(means[b, i])
                assert math.isclose(rows[b, i, j], want, rel_tol=1e-10, abs_tol=1e-10), (b, i, j)
                total += math.exp(logw[b, i] + logw[b, j] + want)
        assert math.isclose(h2[b], -math.log(total), rel_tol=1e-10), b


def test_mixture_renyi_entropy_rejects_covariances_of_the_wrong_shape() -> None:
    """Property (mixture_renyi_entropy's Raises: 'ShapeMismatchError: inconsistent shapes'): covariances whose
    trailing shape is not (K, d, d) raise ShapeMismatchError, also a (1, d, d) stack that would broadcast silently
    over the K components; the well-shaped call equals the scipy closed form."""
    rng = np.random.default_rng(32)
    K, d = 3, 2
    means = rng.standard_normal((4, K, d))
    logw = rng.standard_normal((4, K))
    S = np.stack([_spd(rng, d) for _ in range(K)])
    got = mixture_renyi_entropy(T(logw), T(means), T(S)).numpy()
    for b in range(4):
        total = sum(math.exp(logw[b, i] + logw[b, j]) * multivariate_normal(means[b, j], S[i] + S[j]).pdf(means[b, i])
                    for i in range(K) for j in range(K))  # fmt: skip
        assert math.isclose(got[b], -math.log(total), rel_tol=1e-10)
    for bad in (S[:1], S[:2], np.stack([np.eye(d + 1)] * K), S[0]):
        with pytest.raises(ShapeMismatchError):
            mixture_renyi_entropy(T(logw), T(means), T(bad))


def test_reference_entropy_forwards_the_velocity_covariance_override() -> None:
    """Property (reference_entropy docstring: 'velocity_covariances: optional override of S_k'): with an isotropic
    override, quantile None is the scipy H2(g) of the overridden mixture and quantile q the numpy linear q-quantile of
    the overridden H2 over the training states (not those of the primitive's own S_k); a bool quantile is refused
    like any value that is not a number in [0, 1]."""
    prim = certified_primitive(2, 3, seed=33)
    rng = np.random.default_rng(34)
    x = prim.gmm.means.numpy()[[0, 1, 2, 0, 2, 1]] + rng.standard_normal((6, 2))
    iso = np.stack([np.eye(2) * v for v in (0.3, 4.0, 12.0)])
    want = np.array([_h2_of(prim, xb, iso) for xb in x])
    own = np.array([_h2_of(prim, xb) for xb in x])
    assert np.abs(want - own).min() > 0.1  # the override matters at every state
    g = prim.attractor.numpy()
    got_g = float(reference_entropy(prim, None, None, velocity_covariances=T(iso)))
    assert math.isclose(got_g, _h2_of(prim, g, iso), rel_tol=1e-10)
    assert abs(_h2_of(prim, g, iso) - _h2_of(prim, g)) > 0.1
    for q in (0.0, 0.4, 1.0):
        got = float(reference_entropy(prim, T(x), q, velocity_covariances=T(iso)))
        assert math.isclose(got, float(np.quantile(want, q)), rel_tol=1e-10), q
    for bad in (True, False):
        with pytest.raises(InvalidArgumentError):
            reference_entropy(prim, T(x), bad)


def test_duck_typed_primitive_needs_the_override_and_rejects_non_finite_positions() -> None:
    """Property (velocity_mixture docstring: any object with gmm, A, attractor; Raises: InvalidArgumentError without
    velocity covariances, NonFiniteError for NaN or Inf in x): for a duck-typed primitive whose density does not check
    its input, renyi_entropy with the override equals the scipy closed form, is refused without it, and NaN or Inf
    in x is a NonFiniteError raised by the entropy module itself."""
    rng = np.random.default_rng(35)
    K, d = 2, 2
    pi = np.array([0.3, 0.7])
    mx = rng.standard_normal((K, d)) * 2.0
    Sx = np.stack([_spd(rng, d, floor=0.5) for _ in range(K)])
    A = np.stack([-np.eye(d) + 0.3 * rng.standard_normal((d, d)) for _ in range(K)])
    g = np.array([0.5, -1.0])
    S = np.stack([_spd(rng, d) for _ in range(K)])
    comps = torch.distributions.MultivariateNormal(T(mx), covariance_matrix=T(Sx), validate_args=False)

    class _Gmm:
        def log_prob_components(self, x: torch.Tensor) -> torch.Tensor:
            return T(np.log(pi)) + comps.log_prob(x.unsqueeze(-2))

    prim = types.SimpleNamespace(gmm=_Gmm(), A=T(A), attractor=T(g))
    x = rng.standard_normal((4, d)) * 2.0
    got = renyi_entropy(prim, T(x), velocity_covariances=T(S)).numpy()
    np.testing.assert_allclose(got, [_h2_scipy(pi, mx, Sx, A, g, S, xb) for xb in x], rtol=1e-10)
    with pytest.raises(InvalidArgumentError):
        velocity_mixture(prim, T(x))
    for bad in (math.nan, math.inf, -math.inf):
        xb = T(x)
        xb[2, 1] = bad
        with pytest.raises(NonFiniteError):
            renyi_entropy(prim, xb, velocity_covariances=T(S))


# ---------------------------------------------------------------------------------------------------- policy
def test_modulation_reference_entropy_uses_its_entropy_quantile() -> None:
    """Property (Modulation.entropy_quantile docstring): Modulation(entropy_quantile=q).reference_entropy(prim, x)
    is the numpy linear q-quantile of the scipy H2 over the training states, and with q = None the H2 of the goal."""
    prim = certified_primitive(2, 3, seed=36)
    rng = np.random.default_rng(37)
    x = prim.gmm.means.numpy()[[0, 1, 2, 1, 0, 2, 2]] + 1.5 * rng.standard_normal((7, 2))
    want = np.array([_h2_of(prim, xb) for xb in x])
    for q in (0.0, 0.25, 0.5, 0.9):
        got = float(Modulation("full", entropy_quantile=q).reference_entropy(prim, T(x)))
        assert math.isclose(got, float(np.quantile(want, q)), rel_tol=1e-10), q
    assert np.quantile(want, 0.25) < want.max() - 0.1  # q really changes the threshold
    got_g = float(Modulation("small", entropy_quantile=None).reference_entropy(prim, T(x)))
    assert math.isclose(got_g, _h2_of(prim, prim.attractor.numpy()), rel_tol=1e-10)


def test_policy_accepts_magnitudes_up_to_the_limit_and_still_points_at_the_goal() -> None:
    """Property (_check_vectors / modulated_velocity's Raises: only a magnitude *above* safe_magnitude is a
    NonFiniteError): x, f and g with coordinates exactly +-safe_magnitude are accepted in every mode and give a
    finite velocity whose radial component e_g^T M f is negative in the large- and small-scale branches (per-sample
    loop), while the next float above the limit in x, f or g is refused."""
    L = safe_magnitude(F64)
    x = T([[L, -L], [-L, L], [L, L], [-L, 0.0]])
    f = T([[L, 0.0], [0.0, -L], [-L, L], [0.0, L]])
    g = T([0.0, -L])
    own = T([0.0, 0.0, -1.0, -1.0])
    other = T([1.0, 1.0, -2.0, -2.0])  # two samples outside A_m, two inside
    h2 = T([5.0, 5.0, 5.0, 5.0])
    for mode in ("none", "large", "small", "full"):
        res = modulated_velocity(x, f, g, log_p_own=own, log_p_other=other, h2=h2, h2_ref=1.0, mode=mode)
        v = res.velocity.numpy()
        assert np.isfinite(v).all(), mode
        for i in range(4):
            e = x[i].numpy() - g.numpy()
            r = float(np.linalg.norm(e))
            if int(res.branch[i]) in (int(Branch.LARGE_SCALE), int(Branch.SMALL_SCALE)):
                assert r > 0 and float(v[i] @ e) / r < 0.0, (mode, i)
        if mode == "full":
            assert res.branch.tolist() == [int(Branch.LARGE_SCALE)] * 2 + [int(Branch.SMALL_SCALE)] * 2
    above = torch.nextafter(torch.tensor(L, dtype=F64), torch.tensor(math.inf, dtype=F64))
    for which in range(3):
        args = [x.clone(), f.clone(), g.clone()]
        args[which].view(-1)[0] = above
        with pytest.raises(NonFiniteError):
            modulated_velocity(*args, mode="none")


# ---------------------------------------------------------------------------------------------------- DTW
@pytest.mark.parametrize("Ta, Tb", [(9, 14), (14, 9)])
def test_dtw_ignores_nan_padding_of_either_trajectory(Ta: int, Tb: int) -> None:
    """Property (dtw_distance docstring: 'Padded samples (beyond lengths_a / lengths_b) may hold any value, even
    NaN'): NaN in the padding of a and of b, starting right after the last valid sample, leaves the distance equal
    to a naive O(n m) DTW loop over the valid samples, whichever trajectory is the longer padded one."""
    rng = np.random.default_rng(38 + Ta)
    B, d = 4, 2
    a = rng.standard_normal((B, Ta, d)).cumsum(1)
    b = rng.standard_normal((B, Tb, d)).cumsum(1)
    la = np.array([Ta - 1, 3, 1, Ta - 4])
    lb = np.array([Tb - 2, 1, 5, Tb - 1])
    for k in range(B):
        a[k, la[k]:] = math.nan
        b[k, lb[k]:] = math.nan
    got = dtw_distance(T(a), T(b), torch.tensor(la), torch.tensor(lb)).numpy()
    want = [_naive_dtw(a[k, : la[k]], b[k, : lb[k]]) for k in range(B)]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_dtw_rejects_non_finite_valid_samples_and_integer_inputs() -> None:
    """Property (dtw_distance's Raises and _check_pair): NaN or Inf at a valid sample of either trajectory is a
    NonFiniteError naming the pair, whichever is the longer one; an integer tensor on either side is an
    InvalidArgumentError (not silently promoted); finite inputs give the naive DTW."""
    rng = np.random.default_rng(40)
    for Ta, Tb in ((6, 8), (8, 6)):
        a = rng.standard_normal((3, Ta, 2)).cumsum(1)
        b = rng.standard_normal((3, Tb, 2)).cumsum(1)
        np.testing.assert_allclose(dtw_distance(T(a), T(b)).numpy(), [_naive_dtw(a[k], b[k]) for k in range(3)],
                                   rtol=1e-12)  # fmt: skip
        for bad in (math.nan, math.inf, -math.inf):
            for side in ("a", "b"):
                aa, bb = T(a), T(b)
                (aa if side == "a" else bb)[1, 2, 0] = bad
                with pytest.raises(NonFiniteError) as err:
                    dtw_distance(aa, bb)
                assert err.value.demo_index == 1, (side, bad)
    ints = torch.arange(12).reshape(1, 6, 2)
    for args in ((ints, ints.double()), (ints.double(), ints), (ints, ints)):
        with pytest.raises(InvalidArgumentError):
            dtw_distance(*args)
