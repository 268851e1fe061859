"""Demos container and LASA loader."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lfd_torch.data import LASA_MULTI_NAMES, LASA_NAMES, Demos, finite_difference, load_lasa
from lfd_torch.errors import (
    InvalidDemoError,
    NonFiniteError,
    NonIncreasingTimeError,
    ShapeMismatchError,
    TooFewSamplesError,
    UnknownNameError,
)


def ragged(generator: torch.Generator, lengths=(12, 7, 9), d=3) -> list[np.ndarray]:
    return [torch.randn(n, d, generator=generator, dtype=torch.float64).cumsum(0).numpy() for n in lengths]


def test_lasa_all_30_shapes_offline():
    assert len(LASA_NAMES) == 30 and len(set(LASA_NAMES)) == 30
    assert set(LASA_MULTI_NAMES) == {f"Multi_Models_{i}" for i in range(1, 5)}
    for name in LASA_NAMES:
        demos = load_lasa(name)
        assert demos.positions.shape == (7, 1000, 2), name
        assert demos.velocities.shape == (7, 1000, 2)
        assert demos.times.shape == (7, 1000)
        assert torch.equal(demos.lengths, torch.full((7,), 1000))
        assert torch.equal(demos.attractor, torch.zeros(2, dtype=torch.float64))
        # every LASA demonstration ends at the origin
        assert demos.end_points.abs().max() < 1e-6


def test_lasa_unknown_name_lists_valid_names():
    with pytest.raises(UnknownNameError) as err:
        load_lasa("Circle")
    assert "Circle" in str(err.value) and "Sshape" in str(err.value) and "Multi_Models_3" in str(err.value)
    assert isinstance(err.value, LookupError)


def test_lasa_dtype_and_cache_immutable():
    a = load_lasa("Sine", dtype=torch.float32)
    assert a.dtype == torch.float32
    a.positions.add_(1.0)  # a caller mutating its copy must not corrupt the cache
    b = load_lasa("Sine")
    assert b.end_points.abs().max() < 1e-6


def test_from_sequences_pads_and_masks(generator):
    seqs = ragged(generator)
    demos = Demos.from_sequences(seqs, dt=0.1)
    assert demos.positions.shape == (3, 12, 3)
    assert demos.lengths.tolist() == [12, 7, 9]
    assert demos.mask.sum().item() == 28
    for i, s in enumerate(seqs):
        np.testing.assert_array_equal(demos.sequences()[i].numpy(), s)
        # edge padding repeats the last sample, velocities are zero on padding
        assert torch.equal(demos.positions[i, len(s):], torch.as_tensor(s[-1]).expand(12 - len(s), 3))
        assert torch.all(demos.velocities[i, len(s):] == 0)
        np.testing.assert_allclose(demos.velocities[i, : len(s)].numpy(), np.gradient(s, 0.1, axis=0), atol=1e-12)
    np.testing.assert_allclose(demos.attractor.numpy(), np.mean([s[-1] for s in seqs], axis=0))
    x, v, idx = demos.samples()
    assert x.shape == (28, 3) and idx.tolist() == [0] * 12 + [1] * 7 + [2] * 9


def test_finite_difference_matches_numpy_gradient_nonuniform(generator):
    lengths = torch.tensor([10, 6])
    t = torch.rand(2, 10, generator=generator, dtype=torch.float64).add(0.1).cumsum(1)
    x = torch.randn(2, 10, 2, generator=generator, dtype=torch.float64)
    v = finite_difference(x, t, lengths)
    for i, n in enumerate(lengths.tolist()):
        ref = np.gradient(x[i, :n].numpy(), t[i, :n].numpy(), axis=0, edge_order=1)
        np.testing.assert_allclose(v[i, :n].numpy(), ref, rtol=1e-12, atol=1e-12)
        assert torch.all(v[i, n:] == 0)
    fwd = finite_difference(x, t, lengths, scheme="forward")
    np.testing.assert_allclose(fwd[1, 2].numpy(), ((x[1, 3] - x[1, 2]) / (t[1, 3] - t[1, 2])).numpy())
    assert torch.all(fwd[1, 5] == 0)  # the last valid sample rests at the goal


def test_indexing_and_split(generator):
    demos = Demos.from_sequences(ragged(generator, (5, 9, 7, 4)), names=["a", "b", "c", "d"])
    train, test = demos.split([0])
    assert len(train) == 1 and len(test) == 3
    assert train.max_length == 5 and test.names == ("b", "c", "d")
    assert test.max_length == 9
    assert torch.equal(demos[2].positions[0], demos.positions[2, :7])
    assert demos[-1].names == ("d",)
    assert demos[1:3].names == ("b", "c")
    assert demos[torch.tensor([True, False, True, False])].names == ("a", "c")
    with pytest.raises(IndexError):
        demos[4]
    with pytest.raises(TooFewSamplesError):
        demos.split([0, 1, 2, 3])
    for empty in ([], ()):  # numpy reads [] as float64: the message said "integers or booleans"
        with pytest.raises(IndexError, match="selects no demonstration"):
            demos.split(empty)
    both = Demos.concat([train, test])
    assert both.names == demos.names and torch.equal(both.positions, demos.positions)


def test_to_dtype(generator):
    demos = Demos.from_sequences(ragged(generator))
    d32 = demos.to(dtype=torch.float32)
    assert d32.positions.dtype == d32.velocities.dtype == d32.times.dtype == d32.attractor.dtype == torch.float32
    assert d32.lengths.dtype == torch.long


def test_nan_names_demo_and_sample(generator):
    seqs = ragged(generator)
    seqs[1][4, 2] = np.nan
    with pytest.raises(NonFiniteError) as err:
        Demos.from_sequences(seqs)
    assert err.value.demo_index == 1 and "NaN" in str(err.value) and "sample 4" in str(err.value)
    seqs = ragged(generator)
    seqs[2][0, 0] = np.inf
    with pytest.raises(NonFiniteError, match="demonstration 2: .*Inf"):
        Demos.from_sequences(seqs)


def test_too_few_samples_and_shapes(generator):
    seqs = ragged(generator)
    with pytest.raises(TooFewSamplesError) as err:
        Demos.from_sequences(seqs + [np.zeros((2, 3))])
    assert err.value.demo_index == 3
    with pytest.raises(ShapeMismatchError, match="dimensions differ"):
        Demos.from_sequences([np.zeros((5, 2)), np.zeros((5, 3))])
    with pytest.raises(ShapeMismatchError):
        Demos.from_sequences([np.zeros(5)])
    with pytest.raises(ShapeMismatchError, match="velocities"):
        Demos.from_sequences(seqs, velocities=[s[:, :2] for s in seqs])
    with pytest.raises(ShapeMismatchError, match="attractor"):
        Demos.from_sequences(seqs, attractor=np.zeros(2))
    with pytest.raises(TooFewSamplesError):
        Demos.from_sequences([])
    assert issubclass(TooFewSamplesError, InvalidDemoError) and issubclass(InvalidDemoError, ValueError)


def test_non_increasing_time(generator):
    seqs = ragged(generator)
    times = [np.arange(len(s), dtype=float) for s in seqs]
    times[2][5] = times[2][4]
    with pytest.raises(NonIncreasingTimeError) as err:
        Demos.from_sequences(seqs, times=times)
    assert err.value.demo_index == 2 and "sample 5" in str(err.value)
    with pytest.raises(NonIncreasingTimeError):
        Demos.from_sequences(seqs, dt=0.0)


def test_padded_constructor_validates(generator):
    demos = Demos.from_sequences(ragged(generator))
    bad = demos.positions.clone()
    bad[1, 3, 0] = float("nan")
    with pytest.raises(NonFiniteError):
        demos.replace(positions=bad)
    bad = demos.positions.clone()
    bad[1, 10, 0] = float("nan")  # padding of row 1 (length 7) is not checked
    demos.replace(positions=bad)
    with pytest.raises(ShapeMismatchError):
        demos.replace(times=demos.times[:, :5])
    with pytest.raises(ShapeMismatchError):
        demos.replace(velocities=demos.velocities.float())


def test_padding_is_canonical_whatever_the_caller_passes(generator):
    demos = Demos.from_sequences(ragged(generator), dt=0.5)
    junk = demos.replace(
        positions=demos.positions.masked_fill(~demos.mask.unsqueeze(-1), 7.0),
        velocities=demos.velocities.masked_fill(~demos.mask.unsqueeze(-1), 3.0),
        times=demos.times.masked_fill(~demos.mask, 0.0),
    )
    for name in ("positions", "velocities", "times"):
        assert torch.equal(getattr(junk, name), getattr(demos, name)), name


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.int64])
def test_demos_refuse_dtypes_other_than_float32_and_float64(dtype) -> None:
    from lfd_torch.errors import ShapeMismatchError

    x = torch.zeros(1, 5, 2).to(dtype)
    with pytest.raises(ShapeMismatchError, match="float32 or float64"):
        Demos(x, torch.zeros_like(x), torch.arange(5).to(dtype).unsqueeze(0), torch.tensor([5]), torch.zeros(2).to(dtype))


def test_demos_refuse_zero_dimensional_states() -> None:
    from lfd_torch.errors import ShapeMismatchError

    with pytest.raises(ShapeMismatchError, match="d = 0"):
        Demos.from_sequences([torch.zeros(5, 0, dtype=torch.float64)])


def test_demos_boundaries_of_lengths_indices_and_timing() -> None:
    """Three samples are enough and two are not; demos[-n] is the first and -n - 1 is out of range (also in a list);
    durations run from the first to the last valid sample and dt is the median step (uneven steps)."""
    from lfd_torch.errors import InvalidIndexError, TooFewSamplesError

    seqs = [np.zeros((3, 2)) + np.arange(3)[:, None], np.zeros((5, 2)) + np.arange(5)[:, None]]
    times = [np.array([0.0, 0.1, 0.3]), np.array([0.0, 0.1, 0.2, 0.3, 1.0])]
    demos = Demos.from_sequences(seqs, times=times)
    with pytest.raises(TooFewSamplesError):
        Demos.from_sequences([np.zeros((2, 2)) + np.arange(2)[:, None]])
    assert demos.durations.tolist() == pytest.approx([0.3, 1.0])
    assert demos.dt.tolist() == pytest.approx([0.1, 0.1])  # (lower) medians of (0.1, 0.2) and (0.1, 0.1, 0.1, 0.7)
    assert torch.equal(demos[-2].positions, demos[0].positions)
    for bad in (-3, [-3], [0, -3]):
        with pytest.raises(InvalidIndexError):
            demos[bad]
