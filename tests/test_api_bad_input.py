"""Bad input at the public API: a typed lfd_torch error naming the argument, never a deep crash or a silent wrong
result; and the same results as before on valid input.

One block per reviewed entry point: segmentation state dicts and save, dimension screening, finite differences,
the modulation factors / entropy / matrix / policy, the area and aggregate metrics, MNIST strokes, Demos
construction and concatenation, and SkillTree.render.
"""

from __future__ import annotations

import gzip
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from lfd_torch.data import Demos, finite_difference, mnist_demos, stroke_trajectory
from lfd_torch.errors import (
    InvalidArgumentError,
    NonFiniteError,
    NonIncreasingTimeError,
    ShapeMismatchError,
    StoreError,
    TooFewSamplesError,
    UnknownNameError,
)

F = torch.float64
NAN = math.nan


@pytest.fixture
def demos(generator: torch.Generator) -> Demos:
    """Two random-walk demonstrations of 20 samples in 2-D, dt = 1."""
    seqs = [torch.cumsum(torch.rand(20, 2, generator=generator, dtype=F), 0) for _ in range(2)]
    return Demos.from_sequences(seqs)


# ------------------------------------------------------------------------------------ 1. segmentation state / save
@pytest.fixture
def segmentation(demos: Demos):
    from lfd_torch.segmentation import FixedSegmenter

    return FixedSegmenter([0.5])(demos)


@pytest.mark.parametrize("key", ["space_mean", "space_covariance", "attractors", "space_weights", "endpoints"])
def test_segmentation_state_with_nan_names_the_key(segmentation, key: str) -> None:
    from lfd_torch.segmentation import Segmentation

    state = segmentation.state_dict()
    with pytest.raises(NonFiniteError, match=key):
        Segmentation.from_state_dict({**state, key: state[key] * NAN})


def test_segmentation_file_with_nan_is_a_store_error(segmentation, tmp_path: Path) -> None:
    from lfd_torch.segmentation import Segmentation
    from lfd_torch.store.checksum import DIGEST_KEY, payload_digest

    state = segmentation.state_dict()
    state["space_mean"] = state["space_mean"] * NAN
    state[DIGEST_KEY] = payload_digest(state)  # a consistent file that holds NaN
    torch.save(state, tmp_path / "nan.pt")
    with pytest.raises(StoreError, match="nan.pt.*space_mean"):
        Segmentation.load(tmp_path / "nan.pt")


def test_segmentation_state_round_trip_unchanged(segmentation, demos: Demos) -> None:
    from lfd_torch.segmentation import Segmentation

    back = Segmentation.from_state_dict(segmentation.state_dict())
    x = demos.samples()[0]
    assert torch.equal(back.membership(x), segmentation.membership(x))
    assert torch.equal(back.log_density(x), segmentation.log_density(x))


def test_segmentation_save_none_names_path(segmentation, tmp_path: Path) -> None:
    from lfd_torch.segmentation import Segmentation

    with pytest.raises(StoreError, match="path"):
        segmentation.save(None)
    out = segmentation.save(tmp_path / "seg.pt")  # valid: written and read back
    assert out == tmp_path / "seg.pt"
    assert torch.equal(Segmentation.load(out).attractors, segmentation.attractors)


# ------------------------------------------------------------------------------------ 2. dimension shares
@pytest.mark.parametrize("scale", [1e200, 1e-200])
def test_dimension_shares_of_huge_or_tiny_demos_are_right(demos: Demos, scale: float) -> None:
    from lfd_torch.preprocess import dimension_shares, screen_dimensions

    want = dimension_shares(demos)
    scaled = Demos.from_sequences([s * scale for s in demos.sequences()])
    got = dimension_shares(scaled)
    assert torch.isfinite(got).all()
    torch.testing.assert_close(got, want, rtol=1e-12, atol=0.0)
    assert screen_dimensions(scaled, 0.01, return_kept=True)[1].tolist() == \
        screen_dimensions(demos, 0.01, return_kept=True)[1].tolist()  # fmt: skip


def test_dimension_shares_valid_input_unchanged(demos: Demos) -> None:
    from lfd_torch.preprocess import dimension_shares

    x = demos.samples()[0]
    var = x.var(dim=0, unbiased=False)
    assert torch.equal(dimension_shares(demos), var / var.sum())  # the power-of-two scaling is exact


# ------------------------------------------------------------------------------------ 3. finite differences
def _fd_cases(d: Demos):
    P, T, L = d.positions, d.times, d.lengths
    return {
        "zero times": (NonIncreasingTimeError, "times", (P, torch.zeros_like(T), L)),
        "constant times": (NonIncreasingTimeError, "times", (P, torch.ones_like(T), L)),
        "nan positions": (NonFiniteError, "positions", (P * NAN, T, L)),
        "nan times": (NonFiniteError, "times", (P, T * NAN, L)),
        "length 0": (TooFewSamplesError, "lengths", (P, T, torch.tensor([0, 20]))),
        "length 1": (TooFewSamplesError, "lengths", (P, T, torch.tensor([1, 20]))),
        "length > T": (ShapeMismatchError, "lengths", (P, T, torch.tensor([21, 20]))),
        "float lengths": (InvalidArgumentError, "lengths", (P, T, torch.tensor([20.0, 20.0]))),
        "lengths shape": (ShapeMismatchError, "lengths", (P, T, torch.tensor([20]))),
        "times shape": (ShapeMismatchError, "times", (P, T[:, :5], L)),
        "2-D positions": (ShapeMismatchError, "positions", (P[0], T, L)),
        "int positions": (ShapeMismatchError, "positions", (P.long(), T, L)),
    }


@pytest.mark.parametrize("case", [
    "zero times", "constant times", "nan positions", "nan times", "length 0", "length 1", "length > T",
    "float lengths", "lengths shape", "times shape", "2-D positions", "int positions"])  # fmt: skip
def test_finite_difference_bad_input(demos: Demos, case: str) -> None:
    error, name, args = _fd_cases(demos)[case]
    with pytest.raises(error, match=name):
        finite_difference(*args)


@pytest.mark.parametrize("scheme", ["central", "forward", "backward"])
def test_finite_difference_valid_input_unchanged(demos: Demos, scheme: str) -> None:
    P, T = demos.positions, demos.times
    lengths = torch.tensor([20, 7])
    P = torch.where(torch.arange(20).view(1, 20, 1) < lengths.view(2, 1, 1), P, NAN)  # padding is never read
    got = finite_difference(P, T, lengths, scheme)
    for i, n in enumerate(lengths.tolist()):
        x, t = P[i, :n].numpy(), T[i, :n].numpy()
        if scheme == "central":
            want = np.gradient(x, t, axis=0, edge_order=1)
        else:
            slope = np.diff(x, axis=0) / np.diff(t)[:, None]
            want = np.concatenate([slope, 0 * x[:1]]) if scheme == "forward" else np.concatenate([0 * x[:1], slope])
        np.testing.assert_allclose(got[i, :n].numpy(), want, rtol=1e-12, atol=1e-12)
        assert (got[i, n:] == 0).all()


# ------------------------------------------------------------------------------------ 4. modulation
def test_large_scale_gain_bad_input() -> None:
    from lfd_torch.modulation import large_scale_factor, large_scale_gain

    own, other = torch.zeros(3, dtype=F), torch.full((3,), 1.0, dtype=F)
    with pytest.raises(NonFiniteError, match="log_p_own"):
        large_scale_gain(torch.tensor([NAN, 0.0, 0.0], dtype=F), other, 3.0)
    with pytest.raises(NonFiniteError, match="log_p_other"):
        large_scale_gain(own, torch.tensor([0.0, NAN, 0.0], dtype=F), 3.0)
    with pytest.raises(InvalidArgumentError, match="log_p_own"):
        large_scale_gain(0.0, 1.0, 3.0)
    with pytest.raises(ShapeMismatchError, match="log_p_other"):
        large_scale_gain(own, torch.zeros(2, dtype=F), 3.0)
    with pytest.raises(NonFiniteError, match="c"):
        large_scale_factor(own, other, torch.tensor([NAN, 1.0, 1.0], dtype=F), 3.0)


def test_large_scale_gain_valid_input_unchanged() -> None:
    from lfd_torch.modulation import large_scale_factor, large_scale_gain

    own = torch.tensor([0.0, 0.0, -math.inf, -math.inf, 5.0], dtype=F)
    other = torch.tensor([math.log(2.0), math.log(10.0), 0.0, -math.inf, 5.0], dtype=F)
    tol = dict(rtol=1e-14, atol=0.0)
    torch.testing.assert_close(large_scale_gain(own, other, 3.0), torch.tensor([2.0, 3.0, 3.0, 1.0, 1.0], dtype=F),
                               **tol)  # fmt: skip
    c = torch.tensor([1.0, -1.0, 0.0, 2.0, -3.0], dtype=F)
    torch.testing.assert_close(large_scale_factor(own, other, c, 3.0),
                               torch.tensor([-2.0, 3.0, 0.0, -1.0, 1.0], dtype=F), **tol)  # fmt: skip


def test_entropy_bad_input() -> None:
    from lfd_torch.modulation import mixture_renyi_entropy, pair_factors, pairwise_log_overlap, renyi_entropy

    S = torch.eye(2, dtype=F).repeat(2, 1, 1)
    with pytest.raises(ShapeMismatchError, match="covariances"):
        pair_factors(torch.eye(2, dtype=F))
    with pytest.raises(ShapeMismatchError, match="covariances"):
        pair_factors(torch.ones(2, 2, 3, dtype=F))
    with pytest.raises(NonFiniteError, match="covariances"):
        pair_factors(S * NAN)
    with pytest.raises(NonFiniteError, match="means"):
        mixture_renyi_entropy(torch.zeros(2, dtype=F), torch.full((2, 2), NAN, dtype=F), S)
    with pytest.raises(NonFiniteError, match="log_weights"):
        mixture_renyi_entropy(torch.tensor([NAN, 0.0], dtype=F), torch.zeros(2, 2, dtype=F), S)
    with pytest.raises(TooFewSamplesError, match="means"):
        mixture_renyi_entropy(torch.zeros(0, dtype=F), torch.zeros(0, 2, dtype=F), torch.zeros(0, 2, 2, dtype=F))
    with pytest.raises(NonFiniteError, match="means"):
        pairwise_log_overlap(torch.full((2, 2), NAN, dtype=F), S)
    with pytest.raises(ShapeMismatchError, match="means"):
        pairwise_log_overlap(torch.zeros(2, 3, dtype=F), S)
    with pytest.raises(InvalidArgumentError, match="primitive"):
        renyi_entropy(None, torch.zeros(2, dtype=F))


def test_entropy_valid_input_unchanged(generator: torch.Generator) -> None:
    from lfd_torch.modulation import mixture_renyi_entropy, pair_factors, pairwise_log_overlap

    K, d = 3, 2
    A = torch.randn(K, d, d, generator=generator, dtype=F)
    S = A @ A.transpose(-2, -1) + 0.5 * torch.eye(d, dtype=F)
    mu = torch.randn(4, K, d, generator=generator, dtype=F)
    logw = torch.randn(4, K, generator=generator, dtype=F)
    logw[0, 1] = -math.inf  # a zero weight stays allowed
    S_pair = S.unsqueeze(0) + S.unsqueeze(1)  # reference: log N(mu_i; mu_j, S_i + S_j) by torch.distributions
    ref = torch.distributions.MultivariateNormal(mu.unsqueeze(-3), S_pair).log_prob(mu.unsqueeze(-2))
    torch.testing.assert_close(pairwise_log_overlap(mu, S), ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(pairwise_log_overlap(mu, None, factors=pair_factors(S)), ref, rtol=1e-12, atol=1e-12)
    want = -torch.logsumexp((logw.unsqueeze(-1) + logw.unsqueeze(-2) + ref).flatten(-2), -1)
    torch.testing.assert_close(mixture_renyi_entropy(logw, mu, S), want, rtol=1e-12, atol=1e-12)


def test_matrix_bad_input() -> None:
    from lfd_torch.modulation import modulate, modulation_matrix, radial_component

    f = torch.ones(3, 2, dtype=F)
    u = torch.tensor([[1.0, 0.0]] * 3, dtype=F)
    with pytest.raises(NonFiniteError, match="f"):
        modulate(f * NAN, u, 1.0, 1.0)
    with pytest.raises(NonFiniteError, match="unit"):
        modulate(f, u * NAN, 1.0, 1.0)
    with pytest.raises(ShapeMismatchError, match="unit"):
        modulate(torch.ones(3, 3, dtype=F), u, 1.0, 1.0)
    with pytest.raises(InvalidArgumentError, match="d1"):
        modulate(f, u, NAN, 1.0)
    with pytest.raises(NonFiniteError, match="d1"):
        modulate(f, u, torch.full((3,), NAN, dtype=F), 1.0)
    with pytest.raises(ShapeMismatchError, match="d"):
        modulate(f, u, 1.0, torch.ones(2, dtype=F))
    with pytest.raises(NonFiniteError, match="unit"):
        modulation_matrix(u * NAN, 1.0, 1.0)
    with pytest.raises(InvalidArgumentError, match="d1"):
        modulation_matrix(u, NAN, 1.0)
    with pytest.raises(NonFiniteError, match="f"):
        radial_component(f * NAN, u)
    with pytest.raises(ShapeMismatchError, match="unit"):
        radial_component(torch.ones(3, 3, dtype=F), u)


def test_matrix_valid_input_unchanged(generator: torch.Generator) -> None:
    from lfd_torch.modulation import goal_direction, modulate, modulation_matrix, radial_component

    x, f = torch.randn(5, 3, generator=generator, dtype=F), torch.randn(5, 3, generator=generator, dtype=F)
    d1, dd = torch.randn(5, generator=generator, dtype=F), torch.rand(5, generator=generator, dtype=F)
    u = goal_direction(x, torch.zeros(3, dtype=F)).unit
    c = (f * u).sum(-1)
    assert torch.equal(radial_component(f, u), c)
    assert torch.equal(radial_component(f.T, u.T, dim=0), (f.T * u.T).sum(0))
    assert torch.equal(modulate(f, u, d1, dd), dd.unsqueeze(-1) * f + ((d1 - dd) * c).unsqueeze(-1) * u)
    M = modulation_matrix(u, d1, dd)
    torch.testing.assert_close((M @ f.unsqueeze(-1)).squeeze(-1), modulate(f, u, d1, dd), rtol=1e-12, atol=1e-12)
    assert torch.equal(modulate(f, u, 2.0, 0.5), modulate(f, u, torch.tensor(2.0, dtype=F), 0.5))


def _single_args(**changes):
    args = dict(e=[1.0, 0.0], f=[0.0, 1.0], log_p_own=0.0, log_p_other=-1.0, h2=2.0, h2_ref=0.0, mode="full",
                lambda_limit=3.0, radial_floor=0.1)  # fmt: skip
    args.update(changes)
    return args


@pytest.mark.parametrize("changes, error, name", [
    (dict(mode="bogus"), UnknownNameError, "mode"),
    (dict(f=[0.0, 1.0, 5.0]), ShapeMismatchError, "f"),
    (dict(f=[NAN, 1.0]), NonFiniteError, "f"),
    (dict(e=[math.inf, 0.0]), NonFiniteError, "e"),
    (dict(f=[NAN, 1.0], mode="none"), NonFiniteError, "f"),
    (dict(log_p_own=NAN), NonFiniteError, "log_p_own"),
    (dict(h2=NAN), NonFiniteError, "h2"),
    (dict(h2_ref=NAN, mode="small"), NonFiniteError, "h2_ref"),
])  # fmt: skip
def test_modulated_velocity_single_bad_input(changes, error, name) -> None:
    from lfd_torch.modulation import modulated_velocity_single

    with pytest.raises(error, match=name):
        modulated_velocity_single(**_single_args(**changes))


def test_modulated_velocity_single_valid_input_unchanged(generator: torch.Generator) -> None:
    from lfd_torch.modulation import Branch, modulated_velocity_single, modulated_velocity_unchecked

    x, f = torch.randn(8, 2, generator=generator, dtype=F), torch.randn(8, 2, generator=generator, dtype=F)
    own, other = torch.randn(8, generator=generator, dtype=F), torch.randn(8, generator=generator, dtype=F)
    h2, ref = torch.randn(8, generator=generator, dtype=F), torch.zeros(8, dtype=F)
    x[0] = 0.0  # at the goal
    g = torch.zeros(2, dtype=F)
    for mode in ("none", "large", "small", "full"):
        want = modulated_velocity_unchecked(x, f, g, own, other, h2, ref, mode, 3.0, 0.1)
        for i in range(8):
            u, b = modulated_velocity_single(x[i].tolist(), f[i].tolist(), float(own[i]), float(other[i]),
                                             float(h2[i]), 0.0, mode, 3.0, 0.1)  # fmt: skip
            torch.testing.assert_close(torch.tensor(u, dtype=F), want.velocity[i], rtol=1e-12, atol=1e-12)
            assert b == Branch(int(want.branch[i]))
    assert modulated_velocity_single([1.0, 0.0], [0.0, 1.0], -math.inf, -math.inf, math.inf, math.inf, "full", 3.0,
                                     0.1) == ([0.0, 1.0], Branch.UNMODULATED)  # fmt: skip
    # what a mode does not use is not read: NaN / None there is fine, as before
    assert modulated_velocity_single(**_single_args(mode="large", h2=NAN, h2_ref=None)) == \
        modulated_velocity_single(**_single_args(mode="large"))  # fmt: skip
    assert modulated_velocity_single(**_single_args(mode="small", log_p_own=None, log_p_other=NAN)) == \
        modulated_velocity_single(**_single_args(mode="small"))  # fmt: skip


def test_modulation_field_needs_callable_densities() -> None:
    from lfd_torch.modulation import Modulation

    with pytest.raises(InvalidArgumentError, match="log_p_own"):
        Modulation().field(object(), log_p_own=3.0, h2_ref=1.0)
    with pytest.raises(InvalidArgumentError, match="log_p_other"):
        Modulation().field(object(), log_p_own=lambda x: x[:, 0], log_p_other=-1.0, h2_ref=1.0)
    assert callable(Modulation().field(object(), log_p_own=lambda x: x[:, 0], h2_ref=1.0))  # valid: built


# ------------------------------------------------------------------------------------ 5. metrics
def test_area_bad_input() -> None:
    from lfd_torch.metrics.area import quadrilateral_areas, triangle_areas

    one = torch.ones(3, 1, dtype=F)
    two = torch.ones(3, 2, dtype=F)
    with pytest.raises(ShapeMismatchError, match="u"):
        triangle_areas(one, one)
    with pytest.raises(NonFiniteError, match="u"):
        triangle_areas(two * NAN, two)
    with pytest.raises(NonFiniteError, match="v"):
        triangle_areas(two, two * math.inf)
    with pytest.raises(ShapeMismatchError, match="v"):
        triangle_areas(torch.ones(3, 3, dtype=F), torch.ones(2, 3, dtype=F))
    with pytest.raises(ShapeMismatchError, match="v"):
        triangle_areas(two, torch.ones(3, 3, dtype=F))
    with pytest.raises(ShapeMismatchError, match="u"):
        triangle_areas([[1.0, 0.0]], [[0.0, 1.0]])
    with pytest.raises(ShapeMismatchError, match="p0"):
        quadrilateral_areas(one, one, one, one)
    with pytest.raises(NonFiniteError, match="p2"):
        quadrilateral_areas(two, two, two * NAN, two)
    with pytest.raises(ShapeMismatchError, match="p3"):
        quadrilateral_areas(two, two, two, torch.ones(3, 3, dtype=F))


def test_area_valid_input_unchanged() -> None:
    from lfd_torch.metrics import swept_area
    from lfd_torch.metrics.area import quadrilateral_areas, triangle_areas

    u = torch.tensor([[2.0, 0.0, 0.0], [1.0, 1.0, 0.0]], dtype=F)
    v = torch.tensor([[0.0, 3.0, 0.0], [1.0, 1.0, 0.0]], dtype=F)
    assert torch.equal(triangle_areas(u, v), torch.tensor([3.0, 0.0], dtype=F))
    sq = [torch.tensor(p, dtype=F) for p in ([0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0])]
    assert float(quadrilateral_areas(*sq)) == 1.0
    bow = [sq[0], sq[1], sq[3], sq[2]]  # a bow-tie: lobes added
    assert float(quadrilateral_areas(*bow)) == 0.5
    ref = torch.zeros(1, 3, 2, dtype=F)
    ref[0, :, 0] = torch.arange(3.0)
    roll = ref + torch.tensor([0.0, 1.0], dtype=F)
    assert torch.equal(swept_area(roll, ref), torch.tensor([1.0], dtype=F))


def test_aggregate_bad_input() -> None:
    from lfd_torch.metrics import aggregate

    with pytest.raises(InvalidArgumentError, match="values"):
        aggregate(torch.tensor([-1.0, 1.0], dtype=F), kind="rms")
    with pytest.raises(NonFiniteError, match="counts"):
        aggregate(torch.tensor([1.0, 1.0], dtype=F), torch.tensor([NAN, 1.0]))
    with pytest.raises(NonFiniteError, match="counts"):
        aggregate(torch.tensor([1.0, 1.0], dtype=F), torch.tensor([math.inf, 1.0]))


def test_aggregate_valid_input_unchanged() -> None:
    from lfd_torch.metrics import aggregate

    v, n = torch.tensor([1.0, 3.0, -2.0], dtype=F), torch.tensor([1, 3, 0])
    assert float(aggregate(v, n)) == 2.5
    assert float(aggregate(v)) == 2.0 / 3.0
    assert float(aggregate(v, n, kind="rms")) == math.sqrt(7.0)  # a negative value with weight 0 is ignored
    assert float(aggregate(torch.tensor([3.0, 4.0], dtype=F), kind="rms")) == math.sqrt(12.5)
    with pytest.raises(TooFewSamplesError, match="counts"):
        aggregate(v, torch.zeros(3))


def test_cosine_dissimilarity_bad_eps() -> None:
    from lfd_torch.metrics import cosine_dissimilarity

    a = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]], dtype=F)
    b = torch.tensor([[[1.0, 0.0], [1.0, 0.0], [0.0, 0.0]]], dtype=F)
    for bad in ("a", torch.tensor([1e-9, 1.0]), -1.0, NAN, math.inf, None):
        with pytest.raises(InvalidArgumentError, match="eps"):
            cosine_dissimilarity(a, b, eps=bad)


def test_cosine_dissimilarity_valid_eps_unchanged() -> None:
    from lfd_torch.metrics import cosine_dissimilarity

    a = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]], dtype=F)
    b = torch.tensor([[[1.0, 0.0], [1.0, 0.0], [0.0, 0.0]]], dtype=F)
    want = torch.tensor([1.0 / 3.0], dtype=F)  # samples: agree (0), orthogonal (1), both at rest (0)
    for eps in (1e-9, 0.0, 0, torch.tensor(1e-9)):
        torch.testing.assert_close(cosine_dissimilarity(a, b, eps=eps), want, rtol=1e-15, atol=1e-15)


# ------------------------------------------------------------------------------------ 6. MNIST
def _seven(size: int = 28) -> np.ndarray:
    """A uint8 image of a thick 7 (as the tiny MNIST sets of test_mnist)."""
    rr, cc = np.mgrid[0:size, 0:size].astype(np.float64)
    img = np.zeros((size, size))
    line = [(6.0, 6.0), (6.0, 21.0), (23.0, 12.0)]
    for (r0, c0), (r1, c1) in zip(line[:-1], line[1:]):
        d = np.array([r1 - r0, c1 - c0])
        t = np.clip(((rr - r0) * d[0] + (cc - c0) * d[1]) / float(d @ d), 0, 1)
        img = np.maximum(img, np.clip(1.8 - np.hypot(rr - (r0 + t * d[0]), cc - (c0 + t * d[1])), 0, 1))
    return (255 * img).astype(np.uint8)


@pytest.fixture
def mnist_dir(tmp_path: Path) -> Path:
    images = np.stack([_seven(), _seven()])
    labels = np.array([7, 7], dtype=np.uint8)
    for name, arr in (("t10k-images-idx3-ubyte.gz", images), ("t10k-labels-idx1-ubyte.gz", labels)):
        head = bytes([0, 0, 0x08, arr.ndim]) + struct.pack(f">{arr.ndim}I", *arr.shape)
        with gzip.open(tmp_path / name, "wb") as fh:
            fh.write(head + arr.tobytes())
    return tmp_path


@pytest.mark.parametrize("indices", [[0.5], [1.0], [True], ["1"]])
def test_mnist_demos_rejects_non_integer_indices(mnist_dir: Path, indices) -> None:
    with pytest.raises(InvalidArgumentError, match="indices"):
        mnist_demos(7, 1, directory=mnist_dir, indices=indices, n_points=20)


def test_mnist_demos_rejects_unknown_stroke_keys(mnist_dir: Path) -> None:
    with pytest.raises(UnknownNameError, match="stroke.*bogus.*level_tol"):
        mnist_demos(7, 1, directory=mnist_dir, stroke={"bogus": 1}, n_points=20)


def test_mnist_demos_valid_indices_unchanged(mnist_dir: Path) -> None:
    base = mnist_demos(7, 1, directory=mnist_dir, indices=[1], n_points=20)
    assert base.names == ("mnist/test/1",)
    for idx in (np.array([1]), torch.tensor([1]), [np.int64(1)]):
        got = mnist_demos(7, 1, directory=mnist_dir, indices=idx, n_points=20, stroke={"level_tol": 3.0})
        assert got.names == base.names and torch.equal(got.positions, base.positions)


@pytest.mark.parametrize("path, error", [
    (np.full((5, 2), np.nan), NonFiniteError),
    (np.zeros((0, 2)), TooFewSamplesError),
    (np.zeros((1, 2)), TooFewSamplesError),
    (np.arange(15.0).reshape(5, 3), ShapeMismatchError),
    (np.arange(10.0), ShapeMismatchError),
    ([["a", "b"], ["c", "d"]], ShapeMismatchError),
])  # fmt: skip
def test_stroke_trajectory_bad_path(path, error) -> None:
    with pytest.raises(error, match="path"):
        stroke_trajectory(path)


def test_stroke_trajectory_valid_path_unchanged() -> None:
    path = np.array([[0.0, 0.0], [0.0, 4.0], [3.0, 4.0]])
    pos, t, vel = stroke_trajectory(path, n_points=11, time_law="constant", mm_per_pixel=1.0, mean_speed=7.0)
    assert pos.shape == (11, 2) and t.shape == (11,) and vel.shape == (11, 2)
    np.testing.assert_allclose(pos[0], [-3.0, -4.0])
    np.testing.assert_allclose(pos[-1], [0.0, 0.0])
    np.testing.assert_allclose(t, np.linspace(0.0, 1.0, 11))
    np.testing.assert_allclose(np.linalg.norm(vel, axis=1), 7.0)
    two = stroke_trajectory(np.array([[0.0, 0.0], [1.0, 1.0]]), n_points=5)[0]  # two points are enough
    assert two.shape == (5, 2)


# ------------------------------------------------------------------------------------ 7. Demos
def test_demos_from_sequences_bad_arguments(demos: Demos) -> None:
    seqs = demos.sequences()
    with pytest.raises(InvalidArgumentError, match="device"):
        Demos.from_sequences(seqs, device="bogus")
    with pytest.raises(ShapeMismatchError, match="times"):
        Demos.from_sequences(seqs, times=0.1)
    with pytest.raises(ShapeMismatchError, match="velocities"):
        Demos.from_sequences(seqs, velocities=3)
    with pytest.raises(InvalidArgumentError, match="dt"):
        Demos.from_sequences(seqs, times=[torch.arange(20.0)] * 2, dt=-1.0)
    with pytest.raises(InvalidArgumentError, match="dt"):
        Demos.from_sequences(seqs, times=[torch.arange(20.0)] * 2, dt=1.0)


def test_demos_names_must_be_a_sequence(demos: Demos) -> None:
    fields = (demos.positions, demos.velocities, demos.times, demos.lengths, demos.attractor)
    for bad in (None, 5):
        with pytest.raises(ShapeMismatchError, match="names"):
            Demos(*fields, bad)
    assert Demos(*fields, ["a", "b"]).names == ("a", "b")
    assert Demos(*fields).names == ()


@pytest.mark.parametrize("parts", ["tensor", "dict", "demos"])
def test_demos_concat_bad_parts(demos: Demos, parts: str) -> None:
    value = {"tensor": [torch.zeros(2)], "dict": {"a": demos}, "demos": demos}[parts]
    with pytest.raises(InvalidArgumentError, match="parts"):
        Demos.concat(value)


def test_demos_valid_input_unchanged(demos: Demos) -> None:
    seqs = demos.sequences()
    times = [torch.arange(20, dtype=F) * 0.5] * 2
    a = Demos.from_sequences(seqs, times=times)
    b = Demos.from_sequences(seqs, dt=0.5)
    assert torch.equal(a.velocities, b.velocities) and torch.equal(a.times, b.times)
    assert Demos.from_sequences(seqs, device="cpu").device == torch.device("cpu")
    both = Demos.concat([demos, demos])
    assert torch.equal(Demos.concat((demos, demos)).positions, both.positions)
    assert both.n_demos == 4 and torch.equal(both.positions[2:], demos.positions)


def test_demos_concat_takes_any_iterable(demos: Demos) -> None:
    got = Demos.concat(d for d in (demos, demos))  # a generator was a TypeError (subscripted)
    assert torch.equal(got.positions, Demos.concat([demos, demos]).positions)


# ------------------------------------------------------------------------------------ 8. SkillTree.render
class _StubEngine:
    """What SkillTree needs of an engine to build its tree (routes, dimension, dtype)."""

    def __init__(self) -> None:
        self.routes = ((0, 1),)
        self.dim = 2
        self._f = {"dtype": F}


def test_skill_tree_render_path(tmp_path: Path) -> None:
    from lfd_torch.skills import SkillTree

    tree = SkillTree(_StubEngine())
    with pytest.raises(StoreError, match="path"):
        tree.render(None)
    written = tree.render(tmp_path / "tree")
    assert tmp_path / "tree.txt" in written and (tmp_path / "tree.txt").read_text() == tree.ascii()
