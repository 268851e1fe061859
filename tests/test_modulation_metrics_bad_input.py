"""Bad input to the modulation, the metrics, the MNIST stroke helpers and Preprocess: a typed lfd_torch error that
names the argument, never a silent wrong result or a raw torch / Python error; valid input keeps its numbers.

Every test is seeded (numpy default_rng / torch.Generator with a fixed seed) and touches no global RNG.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from conftest import certified_primitive

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError
from lfd_torch.metrics import cosine_dissimilarity, dtw_distance, swept_area, velocity_error
from lfd_torch.modulation import (
    Branch,
    goal_direction,
    large_scale_factor,
    large_scale_gain,
    mixture_renyi_entropy,
    modulate,
    modulated_velocity,
    modulated_velocity_single,
    modulated_velocity_unchecked,
    pair_factors,
    pairwise_log_overlap,
    renyi_entropy,
    small_scale_factor,
    velocity_mixture,
)

F32, F64 = torch.float32, torch.float64
NAN, INF = math.nan, math.inf


def _spd(gen: torch.Generator, *batch: int, d: int = 2, dtype: torch.dtype = F64) -> torch.Tensor:
    B = torch.randn(*batch, d, d, generator=gen, dtype=dtype)
    return B @ B.transpose(-2, -1) / d + 0.3 * torch.eye(d, dtype=dtype)


# ---------------------------------------------------------------------------------------------- 1. S_k override
def test_velocity_covariance_override_is_validated_like_the_primitive_constructor() -> None:
    """Property (velocity_mixture docstring, StablePrimitive constructor): an override S_k with Inf or NaN is a
    NonFiniteError, a non-symmetric or indefinite one or one of another dtype a ShapeMismatchError (the exact
    types), each naming velocity_covariances (an Inf entry used to drop its component silently, an
    asymmetric S_k to be replaced by its symmetric part); the primitive's own S_k as override gives H2 unchanged."""
    prim = certified_primitive(2, 3, seed=41)
    x = prim.gmm.means + 0.5
    S = prim.velocity_covariances
    torch.testing.assert_close(renyi_entropy(prim, x, velocity_covariances=S.clone()), renyi_entropy(prim, x),
                               rtol=0.0, atol=0.0)  # fmt: skip
    inf, nan, asym, indefinite = S.clone(), S.clone(), S.clone(), S.clone()
    inf[1, 0, 0] = INF
    nan[2, 1, 0] = NAN
    asym[1, 0, 1] += 0.5
    indefinite[0] = torch.diag(torch.tensor([1.0, -0.5], dtype=F64))
    for fn in (renyi_entropy, velocity_mixture):
        for bad, error in ((inf, NonFiniteError), (nan, NonFiniteError), (asym, ShapeMismatchError),
                           (indefinite, ShapeMismatchError), (S.float(), ShapeMismatchError)):  # fmt: skip
            with pytest.raises(error, match="velocity_covariances") as exc:
                fn(prim, x, velocity_covariances=bad)
            assert exc.type is error, (fn.__name__, exc.type)


# ---------------------------------------------------------------------------------------------- 2. small scale
def test_small_scale_factor_rejects_nan_and_shapes_that_do_not_broadcast() -> None:
    """Property (small_scale_factor, as large_scale_gain): NaN in h2 or in a tensor h2_ref is a NonFiniteError and
    an h2_ref that does not broadcast a ShapeMismatchError, naming the argument (they used to give NaN factors or a
    raw RuntimeError); valid input is min(1, exp(h2_ref - h2)), +-inf included; the unchecked hot path of the
    modulation adds no check (NaN passes through there, as before)."""
    with pytest.raises(NonFiniteError, match="h2"):
        small_scale_factor(torch.tensor([NAN, 1.0]), 0.0)
    with pytest.raises(NonFiniteError, match="h2_ref"):
        small_scale_factor(torch.tensor([0.0, 1.0]), torch.tensor(NAN))
    with pytest.raises(ShapeMismatchError, match="h2_ref"):
        small_scale_factor(torch.zeros(2), torch.zeros(3))
    h2 = torch.tensor([-1.0, 0.5, 2.0, INF, -INF, 3.0], dtype=F64)
    ref = torch.tensor([0.0, 0.5, 1.0, INF, 0.0, -INF], dtype=F64)
    want = torch.tensor([1.0, 1.0, math.exp(-1.0), 1.0, 1.0, 0.0], dtype=F64)
    torch.testing.assert_close(small_scale_factor(h2, ref), want, rtol=1e-15, atol=0.0)
    torch.testing.assert_close(small_scale_factor(h2[:3], 1.0), torch.tensor([1.0, 1.0, math.exp(-1.0)], dtype=F64),
                               rtol=1e-15, atol=0.0)  # fmt: skip
    x = torch.tensor([[1.0, 0.0]], dtype=F64)
    out = modulated_velocity_unchecked(x, x, torch.zeros(2, dtype=F64), None, None, torch.tensor([NAN], dtype=F64),
                                       torch.zeros(1, dtype=F64), "small", 3.0, 0.1)  # fmt: skip
    assert out.branch.tolist() == [int(Branch.UNMODULATED)]


# ---------------------------------------------------------------------------------------------- 3. goal direction
def test_goal_direction_requires_an_attractor_of_shape_d() -> None:
    """Property (goal_direction docstring: attractor (d,) with dim=-1): a (2, 1) attractor, which broadcast into a
    different goal per row, and a (1, 2) one are ShapeMismatchErrors naming attractor; a (d,) attractor gives
    (x - g) / ||x - g||, and the feature-major layout (dim=0, a (d, 1) attractor) still broadcasts."""
    x = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    for bad in (torch.tensor([[0.0], [5.0]]), torch.zeros(1, 2)):
        with pytest.raises(ShapeMismatchError, match="attractor"):
            goal_direction(x, bad)
    g = torch.tensor([0.0, -2.0])
    got = goal_direction(x, g)
    torch.testing.assert_close(got.distance, torch.tensor([math.sqrt(5.0), 3.0]))
    torch.testing.assert_close(got.unit, (x - g) / got.distance.unsqueeze(-1))
    fm = goal_direction(x.T.contiguous(), g.unsqueeze(-1), dim=0)
    torch.testing.assert_close(fm.unit, got.unit.T)


# ---------------------------------------------------------------------------------------------- 4. mixed dtypes
def test_mixed_dtypes_keep_the_documented_dtype_or_raise_in_matrix_and_factors() -> None:
    """Property (modulate: 'dtype of f'; factors module: 'the dtype of the first tensor argument'): modulate with a
    float64 unit and float32 f is a ShapeMismatchError naming unit (it returned float64), as check_tensor's dtype
    option does elsewhere; large_scale_gain / large_scale_factor with float32 log_p_own return float32 equal to
    the float32 computation (they returned float64)."""
    gen = torch.Generator().manual_seed(43)
    f = torch.randn(4, 2, generator=gen)
    unit = torch.nn.functional.normalize(torch.randn(4, 2, generator=gen, dtype=F64), dim=-1)
    with pytest.raises(ShapeMismatchError, match="unit"):
        modulate(f, unit, 1.0, 1.0)
    assert modulate(f, unit.float(), torch.ones(4, dtype=F64), 0.5).dtype == F32  # eigenvalues are cast
    own = torch.randn(5, generator=gen)
    other = torch.randn(5, generator=gen, dtype=F64)
    c = torch.randn(5, generator=gen, dtype=F64)
    gain = large_scale_gain(own, other, 3.0)
    assert gain.dtype == F32
    torch.testing.assert_close(gain, large_scale_gain(own, other.float(), 3.0), rtol=0.0, atol=0.0)
    factor = large_scale_factor(own, other, c, 3.0)
    assert factor.dtype == F32
    torch.testing.assert_close(factor, large_scale_factor(own, other.float(), c.float(), 3.0), rtol=0.0, atol=0.0)


def test_mixed_dtypes_in_the_mixture_entropy_are_typed_errors() -> None:
    """Property (mixture_renyi_entropy / pairwise_log_overlap: log_weights, covariances and factors share the
    means' dtype): float64 log_weights or covariances (or factors) with float32 means are ShapeMismatchErrors
    naming the argument (they returned float64, or raised a raw 'expected scalar type' RuntimeError); one dtype
    throughout matches the float64 result to float32 precision."""
    gen = torch.Generator().manual_seed(44)
    K, d = 3, 2
    means = torch.randn(4, K, d, generator=gen)
    logw = torch.randn(4, K, generator=gen)
    S = _spd(gen, K)
    with pytest.raises(ShapeMismatchError, match="log_weights"):
        mixture_renyi_entropy(logw.double(), means, S.float())
    with pytest.raises(ShapeMismatchError, match="covariances"):
        mixture_renyi_entropy(logw, means, S)
    with pytest.raises(ShapeMismatchError, match="covariances"):
        pairwise_log_overlap(means, S)
    with pytest.raises(ShapeMismatchError, match="factors"):
        pairwise_log_overlap(means, None, factors=pair_factors(S))
    got = mixture_renyi_entropy(logw, means, S.float())
    assert got.dtype == F32
    torch.testing.assert_close(got, mixture_renyi_entropy(logw.double(), means.double(), S).float(), rtol=1e-5,
                               atol=1e-5)  # fmt: skip


# ---------------------------------------------------------------------------------------------- 5. entropy shapes
def test_mixture_entropy_checks_factors_components_and_batch_shapes() -> None:
    """Property (pairwise_log_overlap / mixture_renyi_entropy Raises: ShapeMismatchError for inconsistent shapes):
    factors that are not two tensors, factors or covariances built for another K, and covariance or factor batch
    shapes that do not broadcast with the means' are ShapeMismatchErrors naming the argument (they were a raw
    TypeError / RuntimeError); per-row covariances and their per-row factors give the same overlaps."""
    gen = torch.Generator().manual_seed(45)
    K, d = 2, 2
    means = torch.randn(3, K, d, generator=gen, dtype=F64)
    logw = torch.randn(3, K, generator=gen, dtype=F64)
    S = _spd(gen, K)
    for bad in ((1, 2), [*pair_factors(S)], (pair_factors(S)[0],)):
        with pytest.raises(ShapeMismatchError, match="factors"):
            mixture_renyi_entropy(logw, means, S, factors=bad)
    with pytest.raises(ShapeMismatchError, match="covariances"):
        pairwise_log_overlap(torch.zeros(3, d, dtype=F64), torch.eye(d, dtype=F64).expand(2, d, d))
    other_K = pair_factors(_spd(gen, 3))
    with pytest.raises(ShapeMismatchError, match="factors"):
        pairwise_log_overlap(means, None, factors=other_K)
    with pytest.raises(ShapeMismatchError, match="factors"):
        mixture_renyi_entropy(logw, means, S, factors=other_K)
    rows4 = _spd(gen, 4, K)
    with pytest.raises(ShapeMismatchError, match="covariances"):
        mixture_renyi_entropy(logw, means, rows4)
    with pytest.raises(ShapeMismatchError, match="covariances"):
        pairwise_log_overlap(means, rows4)
    with pytest.raises(ShapeMismatchError, match="factors"):
        pairwise_log_overlap(means, None, factors=pair_factors(rows4))
    rows = _spd(gen, 3, K)
    torch.testing.assert_close(pairwise_log_overlap(means, rows), pairwise_log_overlap(means, None,
                               factors=pair_factors(rows)), rtol=1e-14, atol=1e-14)  # fmt: skip
    torch.testing.assert_close(mixture_renyi_entropy(logw, means, rows),
                               mixture_renyi_entropy(logw, means, rows, factors=pair_factors(rows)),
                               rtol=1e-14, atol=1e-14)  # fmt: skip


# ---------------------------------------------------------------------------------------------- 6. metrics dtypes
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_metrics_reject_half_precision(dtype: torch.dtype) -> None:
    """Property (FLOAT_DTYPES: float32 / float64 only): float16 and bfloat16 trajectories are ShapeMismatchErrors
    about the dtype naming the argument, in dtw_distance, swept_area, velocity_error and cosine_dissimilarity
    (float16 100 was reported as an overflowing magnitude, bfloat16 computed silently); float32 with float64 still
    promotes to the float64 result."""
    a = torch.full((1, 3, 2), 100.0, dtype=dtype)
    b = torch.zeros(1, 3, 2, dtype=dtype)
    for fn, first, second in ((dtw_distance, "a", "b"), (swept_area, "rollout", "reference"),
                              (velocity_error, "pred_x_dot", "ref_x_dot"),
                              (cosine_dissimilarity, "pred_x_dot", "ref_x_dot")):  # fmt: skip
        with pytest.raises(ShapeMismatchError, match=f"{first} has dtype"):
            fn(a, b)
        with pytest.raises(ShapeMismatchError, match=f"{second} has dtype"):
            fn(b.float(), a)
    gen = torch.Generator().manual_seed(46)
    x, y = torch.randn(2, 5, 2, generator=gen, dtype=F64), torch.randn(2, 5, 2, generator=gen, dtype=F64)
    for fn in (dtw_distance, swept_area, velocity_error):
        mixed = fn(x.float(), y)
        assert mixed.dtype == F64
        torch.testing.assert_close(mixed, fn(x.float().double(), y), rtol=0.0, atol=0.0)


# ---------------------------------------------------------------------------------------------- 7. minor
def test_modulated_velocity_rejects_a_complex_entropy() -> None:
    """Property (modulated_velocity: h2 a real tensor or a number): a complex h2 or h2_ref is a ShapeMismatchError
    naming it, without the UserWarning of a dropped imaginary part; a real float32 h2 is cast as before."""
    gen = torch.Generator().manual_seed(47)
    x = torch.randn(3, 2, generator=gen, dtype=F64)
    g = torch.zeros(2, dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ShapeMismatchError, match="h2"):
            modulated_velocity(x, x, g, h2=torch.ones(3, dtype=torch.complex128), h2_ref=0.0, mode="small")
        with pytest.raises(ShapeMismatchError, match="h2_ref"):
            modulated_velocity(x, x, g, h2=1.0, h2_ref=torch.zeros((), dtype=torch.complex64), mode="small")
    out = modulated_velocity(x, x, g, h2=torch.ones(3), h2_ref=0.0, mode="small")
    ref = modulated_velocity(x, x, g, h2=torch.ones(3, dtype=F64), h2_ref=0.0, mode="small")
    assert torch.equal(out.velocity, ref.velocity) and torch.equal(out.branch, ref.branch)


def test_modulated_velocity_single_names_a_missing_value_the_branch_needs() -> None:
    """Property (modulated_velocity_single docstring: None only where the branch taken does not need the value):
    None densities in mode full, or a None h2 / h2_ref when the small-scale check runs, are InvalidArgumentErrors
    naming the argument (a raw TypeError before); h2 = None on the large-scale branch and at the goal stays fine."""
    e, f = [1.0, 0.0], [0.0, 1.0]
    with pytest.raises(InvalidArgumentError, match="log_p_own"):
        modulated_velocity_single(e, f, None, None, 0.0, 0.0, "full", 3.0, 0.1)
    with pytest.raises(InvalidArgumentError, match="log_p_other"):
        modulated_velocity_single(e, f, 0.0, None, 0.0, 0.0, "large", 3.0, 0.1)
    with pytest.raises(InvalidArgumentError, match="h2"):
        modulated_velocity_single(e, f, 0.0, -1.0, None, 0.0, "full", 3.0, 0.1)
    with pytest.raises(InvalidArgumentError, match="h2_ref"):
        modulated_velocity_single(e, f, None, None, 1.0, None, "small", 3.0, 0.1)
    u, b = modulated_velocity_single(e, f, -1.0, 0.0, None, None, "full", 3.0, 0.1)
    assert b == Branch.LARGE_SCALE and u == pytest.approx([-0.1 * math.e, 0.0], rel=1e-15)  # a = 0.1, s = e
    assert modulated_velocity_single([0.0, 0.0], f, None, None, None, None, "full", 3.0, 0.1)[1] == Branch.AT_GOAL


def test_stroke_trajectory_checks_scale_and_speed_types() -> None:
    """Property (stroke_trajectory: mm_per_pixel and mean_speed finite numbers > 0): a string or None is an
    InvalidArgumentError naming the argument (a raw TypeError before); an int scale gives the float result."""
    from lfd_torch.data.mnist import stroke_trajectory

    path = np.stack([np.linspace(0, 10, 20), np.zeros(20)], 1)
    for kw, name in ((dict(mm_per_pixel="a"), "mm_per_pixel"), (dict(mean_speed=None), "mean_speed"),
                     (dict(mean_speed=True), "mean_speed"), (dict(mm_per_pixel=[2.0]), "mm_per_pixel")):  # fmt: skip
        with pytest.raises(InvalidArgumentError, match=name):
            stroke_trajectory(path, **kw)
    for got, want in zip(stroke_trajectory(path, mm_per_pixel=2, mean_speed=30),
                         stroke_trajectory(path, mm_per_pixel=2.0, mean_speed=30.0)):  # fmt: skip
        np.testing.assert_array_equal(got, want)


def test_extract_stroke_reads_a_bool_image_as_an_ink_mask() -> None:
    """Property (extract_stroke: a bool image is an ink mask, True = 255): a bool bar gives the stroke of the same
    bar drawn in uint8 255 (it was read on the 0..255 scale and failed with 'no ink'), as a numpy array and as a
    torch tensor."""
    from lfd_torch.data.mnist import extract_stroke

    ink = np.zeros((28, 28), dtype=bool)
    ink[5:23, 12:16] = True
    want = extract_stroke(ink.astype(np.uint8) * np.uint8(255))
    for image in (ink, torch.from_numpy(ink)):
        got = extract_stroke(image)
        np.testing.assert_array_equal(got.path, want.path)
        assert (got.closed, got.n_endpoints, got.coverage) == (want.closed, want.n_endpoints, want.coverage)


def test_preprocess_checks_trim_tolerances_are_finite_at_construction() -> None:
    """Property (Preprocess checks its arguments at construction): an infinite or NaN trim tolerance is an
    InvalidArgumentError naming it when the Preprocess is built (inf was accepted, then rejected by the call);
    finite tolerances >= 0 are kept as given."""
    from lfd_torch.preprocess import Preprocess

    for kw, name in ((dict(trim_position_tol=INF, trim_velocity_tol=1.0), "trim_position_tol"),
                     (dict(trim_position_tol=1.0, trim_velocity_tol=INF), "trim_velocity_tol"),
                     (dict(trim_position_tol=NAN, trim_velocity_tol=1.0), "trim_position_tol"),
                     (dict(trim_position_tol=1.0, trim_velocity_tol=True), "trim_velocity_tol")):  # fmt: skip
        with pytest.raises(InvalidArgumentError, match=name):
            Preprocess(**kw)
    p = Preprocess(trim_position_tol=0, trim_velocity_tol=np.float32(2.5))
    assert p.trim_position_tol == 0 and p.trim_velocity_tol == np.float32(2.5)
    assert type(p.trim_position_tol) is int and type(p.trim_velocity_tol) is np.float32
