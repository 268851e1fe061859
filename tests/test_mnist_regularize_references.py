"""Smoothing (moving average, Savitzky-Golay, odd extension) and MNIST reading / stroke extraction / timing against
independent references: per-sample numpy loops, scipy.signal.savgol_filter, a hand-written point reflection,
IDX bytes written here with struct, hand-drawn skeletons and images whose graph is known in closed form, and the
properties the docstrings state. Everything the tests read is written to tmp_path."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import scipy.signal
import torch

from lfd_torch.data import Demos
from lfd_torch.data.mnist import (
    MNIST_ENV,
    _adjacency,
    _degrees,
    _graph,
    _merge_junctions,
    _prune,
    extract_stroke,
    load_mnist,
    mnist_demos,
    mnist_dir,
    read_idx,
    stroke_trajectory,
)
from lfd_torch.errors import InvalidArgumentError, StoreError, TooFewSamplesError, UnknownNameError
from lfd_torch.preprocess.regularize import MAX_WINDOW, moving_average, savitzky_golay, smooth


# ============================================================================================== smoothing
def _ragged(seed: int, lengths=(23, 9, 16), d: int = 3) -> Demos:
    rng = np.random.default_rng(seed)
    seqs = [rng.normal(size=(n, d)).cumsum(0) for n in lengths]
    times = [np.cumsum(0.05 + 0.1 * rng.random(n)) for n in lengths]
    vels = [rng.normal(size=(n, d)) for n in lengths]  # deliberately unrelated to the positions
    return Demos.from_sequences(seqs, times=times, velocities=vels)


def _reflect(x: np.ndarray, h: int) -> np.ndarray:
    """Hand-written point reflection, one sample at a time: x[-k] = 2 x[0] - x[k], x[L-1+k] = 2 x[L-1] - x[L-1-k]."""
    L = len(x)
    rows = [2 * x[0] - x[k] for k in range(h, 0, -1)] + [x[t] for t in range(L)]
    rows += [2 * x[L - 1] - x[L - 1 - k] for k in range(1, h + 1)]
    return np.array(rows).reshape(L + 2 * h, x.shape[1])


def _loop_filter(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Per-sample weighted sum over the reflected signal (no convolution routine)."""
    h = len(kernel) // 2
    ext = _reflect(x, h)
    out = np.zeros_like(x)
    for t in range(len(x)):
        for k in range(len(kernel)):
            out[t] += kernel[k] * ext[t + k]
    return out


@pytest.mark.parametrize("window, order", [(5, 0), (5, 1), (7, 2), (9, 3), (9, 4), (9, 6)])
def test_savitzky_golay_equals_scipy_inside_and_the_reflected_sum_everywhere(window: int, order: int) -> None:
    """savitzky_golay equals scipy.signal.savgol_filter away from the ends (h = window // 2 samples) and, everywhere,
    the savgol_coeffs-weighted sum over the point-reflected row; the end points are kept (docstring)."""
    demos = _ragged(2)
    h = window // 2
    out = savitzky_golay(demos, window, order)
    coeffs = scipy.signal.savgol_coeffs(window, order)
    for i, seq in enumerate(demos.sequences()):
        x = seq.numpy()
        got = out.sequences()[i].numpy()
        np.testing.assert_allclose(got[h:-h], scipy.signal.savgol_filter(x, window, order, axis=0)[h:-h], atol=1e-10)
        np.testing.assert_allclose(got, _loop_filter(x, coeffs), rtol=0, atol=1e-10)
        np.testing.assert_allclose(got[[0, -1]], x[[0, -1]], rtol=0, atol=1e-10)


def test_smoothed_velocities_are_central_differences_of_the_smoothed_positions() -> None:
    """After smoothing (recompute_velocities default, and smooth()) the velocities are numpy.gradient(x, t) of the
    smoothed positions (the documented central scheme); with recompute_velocities=False the input velocities stay."""
    demos = _ragged(3)
    runs = [moving_average(demos, 5), savitzky_golay(demos, 7, 2), smooth(demos, 7, "savgol", 2),
            smooth(demos, 5, "moving_average")]  # fmt: skip
    for out in runs:
        for i in range(demos.n_demos):
            L = int(out.lengths[i])
            x, t = out.positions[i, :L].numpy(), out.times[i, :L].numpy()
            np.testing.assert_allclose(out.velocities[i, :L].numpy(), np.gradient(x, t, axis=0), atol=1e-9)
    for fn in (moving_average, savitzky_golay):
        kept = fn(demos, 5, recompute_velocities=False)
        assert torch.equal(kept.velocities, demos.velocities)


def test_smooth_dispatches_on_method_and_passes_polyorder() -> None:
    """smooth(..., "savgol", p) is Savitzky-Golay of order p (order 1 = a straight-line fit, unlike the default 3),
    "moving_average" is the windowed mean, any other name is an UnknownNameError. Reference: scipy inside."""
    demos = _ragged(4)
    sg1 = smooth(demos, 7, "savgol", 1)
    for i, seq in enumerate(demos.sequences()):
        x = seq.numpy()
        np.testing.assert_allclose(sg1.sequences()[i].numpy()[3:-3],
                                   scipy.signal.savgol_filter(x, 7, 1, axis=0)[3:-3], atol=1e-10)  # fmt: skip
    torch.testing.assert_close(smooth(demos, 5, "moving_average").positions, moving_average(demos, 5).positions)
    with pytest.raises(UnknownNameError):
        smooth(demos, 5, "gaussian")


def test_bad_windows_orders_and_inputs_are_typed_errors() -> None:
    """A negative or zero window, a negative polyorder, polyorder >= window and a non-Demos input (even with the
    no-op window 1) raise InvalidArgumentError, not numpy/scipy errors or a silent pass-through."""
    demos = _ragged(5)
    for w in (-1, 0):
        with pytest.raises(InvalidArgumentError):
            moving_average(demos, w)
    with pytest.raises(InvalidArgumentError, match="polyorder"):
        savitzky_golay(demos, 5, -1)
    with pytest.raises(InvalidArgumentError, match="polyorder"):
        savitzky_golay(demos, 5, 5)
    for fn in (moving_average, savitzky_golay):
        with pytest.raises(InvalidArgumentError, match="Demos"):
            fn(demos.positions, 1) if fn is moving_average else fn(demos.positions, 1, 0)


def test_a_window_above_max_window_is_refused_even_for_a_long_enough_demonstration() -> None:
    """MAX_WINDOW bounds the cost: a window of MAX_WINDOW + 2 samples on a demonstration that long is an
    InvalidArgumentError about the bound, not a TooFewSamplesError (nor a very long convolution)."""
    n = MAX_WINDOW + 2
    demos = Demos.from_sequences([np.linspace(0.0, 1.0, n)[:, None]], dt=0.01)
    with pytest.raises(InvalidArgumentError) as info:
        moving_average(demos, n)
    assert not isinstance(info.value, TooFewSamplesError)


# ============================================================================================== IDX reading
def _idx(code: int, dims: tuple[int, ...], payload: bytes) -> bytes:
    head = bytes([0, 0, code, len(dims)])
    for n in dims:
        head += n.to_bytes(4, "big")
    return head + payload


@pytest.mark.parametrize(
    "code, pack, values",
    [
        (0x08, lambda v: bytes([v]), [0, 1, 200, 255, 7, 9]),
        (0x09, lambda v: v.to_bytes(1, "big", signed=True), [-128, -1, 0, 1, 127, -5]),
        (0x0B, lambda v: v.to_bytes(2, "big", signed=True), [-32768, -2, 0, 258, 32767, 1]),
        (0x0C, lambda v: v.to_bytes(4, "big", signed=True), [-(2**31), -3, 0, 65537, 2**31 - 1, 4]),
        (0x0D, lambda v: struct.pack(">f", v), [-1.5, 0.25, 3.0, 1e10, -2.0, 0.0]),
        (0x0E, lambda v: struct.pack(">d", v), [-1.5, 0.1, 3.0, 1e300, -2.0, 1 / 3]),
    ],
)
@pytest.mark.parametrize("gz", [False, True])
def test_read_idx_decodes_every_type_code_big_endian(tmp_path, code, pack, values, gz) -> None:
    """IDX type codes 0x08 uint8, 0x09 int8, 0x0B int16, 0x0C int32, 0x0D float32, 0x0E float64, all big-endian,
    dimensions (2, 3) in row-major order, raw or gzip. Reference: bytes packed value by value here."""
    import gzip

    data = _idx(code, (2, 3), b"".join(pack(v) for v in values))
    path = tmp_path / ("a.idx.gz" if gz else "a.idx")
    path.write_bytes(gzip.compress(data) if gz else data)
    arr = read_idx(path)
    assert arr.shape == (2, 3) and not arr.flags.writeable
    expect = np.array(values, dtype=np.float64).reshape(2, 3)
    if code == 0x0D:
        expect = expect.astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(arr.astype(np.float64), expect)


@pytest.mark.parametrize(
    "data",
    [
        b"", b"\x00\x00\x08",  # shorter than the 4-byte magic number
        bytes([0, 1, 8, 1]) + (1).to_bytes(4, "big") + b"\x05",  # second magic byte not zero
        bytes([0, 0, 8, 0]) + b"\x05",  # no dimension
        bytes([0, 0, 8, 2]) + (1).to_bytes(4, "big"),  # header cut inside the dimensions
    ],
)
def test_read_idx_refuses_headers_that_are_not_idx(tmp_path, data) -> None:
    """Docstring: a header that is not IDX (two zero bytes, a known type code, at least one dimension) or shorter
    than it declares is a StoreError (not an IndexError / struct.error, nor a 0-d array)."""
    path = tmp_path / "bad.idx"
    path.write_bytes(data)
    with pytest.raises(StoreError):
        read_idx(path)


def _write_pair(folder, images: np.ndarray, labels: np.ndarray) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "t10k-images-idx3-ubyte").write_bytes(_idx(0x08, images.shape, images.astype(np.uint8).tobytes()))
    (folder / "t10k-labels-idx1-ubyte").write_bytes(_idx(0x08, labels.shape, labels.astype(np.uint8).tobytes()))


def test_load_mnist_checks_both_image_sides_and_the_label_count(tmp_path) -> None:
    """Images must be 8..1024 px on both sides (28 x 4 is refused as well as 4 x 28) and there must be exactly one
    label per image (more labels than images is refused too): StoreError."""
    for k, (shape, n_labels) in enumerate((((2, 28, 4), 2), ((2, 4, 28), 2), ((2, 28, 28), 3), ((2, 28, 28), 1))):
        folder = tmp_path / str(k)
        _write_pair(folder, np.zeros(shape, np.uint8), np.arange(n_labels))
        with pytest.raises(StoreError):
            load_mnist("test", folder)
    _write_pair(tmp_path / "ok", np.zeros((2, 8, 1024), np.uint8), np.array([0, 9]))
    assert load_mnist("test", tmp_path / "ok")[0].shape == (2, 8, 1024)


def test_loaded_images_are_a_private_copy_and_a_rewritten_file_is_read_again(tmp_path) -> None:
    """load_mnist returns tensors the caller may change without changing what the next call returns (the files are
    cached), and a file rewritten with other content is read again. Reference: the arrays written here."""
    rng = np.random.default_rng(7)
    a = rng.integers(0, 256, (2, 28, 28), dtype=np.uint8)
    _write_pair(tmp_path, a, np.array([3, 4]))
    x, y = load_mnist("test", tmp_path)
    assert x.dtype == torch.uint8 and y.dtype == torch.int64
    x[0] = 7
    y[0] = 9
    x2, y2 = load_mnist("test", tmp_path)
    np.testing.assert_array_equal(x2.numpy(), a)
    assert y2.tolist() == [3, 4]
    b = rng.integers(0, 256, (3, 28, 28), dtype=np.uint8)
    _write_pair(tmp_path, b, np.array([1, 2, 5]))
    x3, y3 = load_mnist("test", tmp_path)
    np.testing.assert_array_equal(x3.numpy(), b)
    assert y3.tolist() == [1, 2, 5]


def test_an_empty_directory_argument_means_the_environment_variable(tmp_path, monkeypatch) -> None:
    """mnist_dir: an empty directory (an unset config key) is 'not given' and falls back to $LFD_MNIST_DIR."""
    monkeypatch.setenv(MNIST_ENV, str(tmp_path))
    assert mnist_dir("") == tmp_path
    assert mnist_dir(None) == tmp_path


# ============================================================================================== skeleton graph
def _tee(stem: int) -> np.ndarray:
    """A 15 px bar on row 2 and a stem of ``stem`` px below its middle pixel (2, 7): the stem edge is ``stem`` px."""
    s = np.zeros((20, 15), dtype=bool)
    s[2, :] = True
    s[3 : 3 + stem, 7] = True
    return s


def test_prune_removes_terminal_spurs_strictly_shorter_than_min_length_and_keeps_the_junction() -> None:
    """A 4 px spur survives prune(min_length=4) (strictly shorter is cut) and goes at 4.5, leaving exactly the bar,
    junction pixel included. Reference: the hand-drawn skeleton."""
    skel = _tee(4)
    np.testing.assert_array_equal(_prune(skel, 4.0), skel)
    np.testing.assert_array_equal(_prune(skel, 4.5), _tee(0))


def test_prune_keeps_a_short_stroke_that_is_not_a_spur() -> None:
    """Only terminal branches ending at a junction are spurs: a lone 3 px line (endpoint to endpoint) is kept."""
    s = np.zeros((6, 6), dtype=bool)
    s[2, 1:4] = True
    np.testing.assert_array_equal(_prune(s, 10.0), s)


def test_prune_repeats_until_no_spur_is_left() -> None:
    """A 2 px branch ending in a fork of two 2 px spurs: the spurs go first, then the branch has become a spur and
    goes too (module docstring: 'again until none is left'); the bar alone remains."""
    s = np.zeros((10, 21), dtype=bool)
    s[2, :] = True
    s[3:5, 10] = True
    s[4, 8:13] = True
    bar = np.zeros_like(s)
    bar[2, :] = True
    np.testing.assert_array_equal(_prune(s, 3.0), bar)


def test_junctions_merge_only_across_a_branch_shorter_than_merge() -> None:
    """An H: two vertical lines joined by a bar whose edge is 4 px: merge 4 keeps two 3-way junctions (6 nodes,
    5 edges), merge 4.5 makes one 4-way crossing (5 nodes, 4 edges). A 2 px spur on a T (endpoint-junction) is
    never merged. Reference: the node degrees counted by hand."""
    h = np.zeros((11, 9), dtype=bool)
    h[:, 2] = h[:, 6] = True
    h[5, 3:6] = True
    g = _graph(_adjacency(h))
    for m, n_nodes, degs in ((4.0, 6, [1, 1, 1, 1, 3, 3]), (4.5, 5, [1, 1, 1, 1, 4])):
        cluster, edges = _merge_junctions(*g, m)
        n = max(cluster.values()) + 1
        assert n == n_nodes and sorted(_degrees(n, edges).tolist()) == degs
    cluster, edges = _merge_junctions(*_graph(_adjacency(_tee(2))), 3.0)
    n = max(cluster.values()) + 1
    assert n == 4 and sorted(_degrees(n, edges).tolist()) == [1, 1, 1, 3]


# ============================================================================================== strokes
def _image(*boxes: tuple[slice, slice], value: int = 255) -> np.ndarray:
    img = np.zeros((28, 28), dtype=np.uint8)
    for r, c in boxes:
        img[r, c] = value
    return img


def test_excursions_zero_draws_no_dead_end_out_and_back() -> None:
    """A T (bar and a dead-end stem) with free turning: excursions=1 draws the stem out and back (coverage 1),
    excursions=0 allows none, so one of the three arms is left out (coverage about 0.7)."""
    img = _image((slice(6, 9), slice(4, 24)), (slice(9, 20), slice(13, 16)))
    assert extract_stroke(img, excursions=1, turn_weight=0.0).coverage == pytest.approx(1.0)
    assert extract_stroke(img, excursions=0, turn_weight=0.0).coverage < 0.8


def test_a_closed_loop_starts_at_its_top_left_pixel() -> None:
    """A rectangular ring (no endpoint) starts at its top-most skeleton pixel, left-most among the pixels of the flat
    top side: near the top-left corner, not the top-right one. Reference: the drawn ring (x 7..20)."""
    img = _image((slice(5, 8), slice(6, 22)), (slice(20, 23), slice(6, 22)), (slice(5, 23), slice(6, 9)),
                 (slice(5, 23), slice(19, 22)))  # fmt: skip
    st = extract_stroke(img)
    assert st.closed and st.n_endpoints == 0
    assert st.path[0, 0] < 10.0 and st.path[0, 1] > 19.0


def test_loop_gap_drops_that_fraction_of_the_closed_trail() -> None:
    """'the closed trail is then cut open by dropping its last loop_gap fraction': the path with loop_gap g is the
    first points of the uncut loop (loop_gap 0, which closes on itself), and its length is (1 - g) times the loop's,
    to within one 0.25 px step. Reference: the same ring extracted with loop_gap 0."""
    img = _image((slice(5, 8), slice(6, 22)), (slice(20, 23), slice(6, 22)), (slice(5, 23), slice(6, 9)),
                 (slice(5, 23), slice(19, 22)))  # fmt: skip
    full = extract_stroke(img, loop_gap=0.0)
    assert np.linalg.norm(full.path[0] - full.path[-1]) < 1e-9
    for g in (0.1, 0.3, 0.5):
        st = extract_stroke(img, loop_gap=g)
        np.testing.assert_allclose(st.path, full.path[: len(st.path)], rtol=0, atol=1e-12)
        assert (1 - g) * full.length - 0.25 - 1e-9 <= st.length <= (1 - g) * full.length + 1e-9


def _slanted_bar(drop: int) -> np.ndarray:
    img = np.zeros((28, 28), dtype=np.uint8)
    for c in range(4, 24):
        r = int(round(16 - (c - 4) * drop / 19))
        img[r - 1 : r + 2, c] = 255
    return img


def test_ends_further_apart_than_level_tol_start_at_the_higher_one() -> None:
    """A bar rising about 5 px to the right: with level_tol 3 its ends are not level and the higher (right) end
    starts; with level_tol 6 they count as level and the left-most end starts (module docstring step 4)."""
    img = _slanted_bar(5)
    p = extract_stroke(img).path
    assert p[0, 1] > p[-1, 1] + 3.0 and p[0, 0] > p[-1, 0]
    q = extract_stroke(img, level_tol=6.0).path
    assert q[0, 0] < q[-1, 0]


def test_the_ink_threshold_is_inclusive() -> None:
    """'threshold at threshold x 255': a bar of intensity exactly 100 is ink at threshold 100 / 255 (upsample 1, no
    interpolation), and nothing is ink just above it."""
    img = _image((slice(5, 23), slice(12, 15)), value=100)
    assert extract_stroke(img, threshold=100 / 255, upsample=1).length > 10
    with pytest.raises(TooFewSamplesError, match="no ink"):
        extract_stroke(img, threshold=100.5 / 255, upsample=1)


def test_ink_components_are_8_connected() -> None:
    """The largest 8-connected component is kept: a one-pixel diagonal line and two squares touching at a corner
    are one component each (ink_share 1), at upsample 1 where nothing blurs them together."""
    diag = np.zeros((28, 28), dtype=np.uint8)
    for r in range(4, 24):
        diag[r, r] = 255
    assert extract_stroke(diag, upsample=1).ink_share == 1.0
    corner = _image((slice(4, 14), slice(4, 14)), (slice(14, 24), slice(14, 24)))
    assert extract_stroke(corner, upsample=1).ink_share == 1.0


# ============================================================================================== timing
def test_every_trajectory_ends_exactly_at_the_origin() -> None:
    """'the path ends at the origin': the last position is exactly (0, 0) for paths with a cusp (several
    minimum-jerk pieces, where the piece arithmetic can round below the total length), any scale and speed."""
    rng = np.random.default_rng(0)
    for _ in range(200):
        out = np.cumsum(rng.uniform(0.1, 0.7, 30))
        back = out[-1] - np.cumsum(rng.uniform(0.1, 0.5, 10))
        up = np.cumsum(rng.uniform(0.1, 0.5, 10))
        path = np.concatenate([np.stack([out, np.zeros(30)], 1), np.stack([back, np.zeros(10)], 1),
                               np.stack([np.ones(10), up], 1)]) * rng.uniform(0.3, 3)  # fmt: skip
        pos, _, _ = stroke_trajectory(path, n_points=50, mm_per_pixel=rng.uniform(0.5, 3),
                                      mean_speed=rng.uniform(5, 40))  # fmt: skip
        assert pos[-1].tolist() == [0.0, 0.0]


def test_velocity_direction_is_the_arc_length_tangent_on_unevenly_sampled_paths() -> None:
    """Velocities point along the path's tangent: on an arc of a circle sampled at alternating 0.01 and 0.15 rad,
    the direction is within 2.5 degrees of the circle's tangent away from the ends (an index-based gradient is
    off by about 4 degrees there). Reference: the circle's analytic tangent."""
    th = np.concatenate([[0.0], np.cumsum(np.tile([0.01, 0.15], 12))])
    circ = 10 * np.stack([np.cos(th), np.sin(th)], 1)
    pos, _, vel = stroke_trajectory(circ, n_points=300, time_law="constant", mm_per_pixel=1.0)
    c = pos + circ[-1]
    tangent = np.stack([-c[:, 1], c[:, 0]], 1) / np.linalg.norm(c, axis=1, keepdims=True)
    unit = vel / np.linalg.norm(vel, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip((unit * tangent).sum(1), -1.0, 1.0)))
    assert angle[15:-15].max() < 2.5


def test_cusps_lie_at_the_apex_of_a_reversal_and_not_within_a_window_of_either_end() -> None:
    """_cusps: out 10 px along x and back 3 px has one cusp, at the apex s = 10 (closed form); a hook of 0.6 px at
    the end, or (the path reversed) at the start, lies within cusp_window = 1 of that end and gives none."""
    from lfd_torch.data.mnist import _arc, _cusps

    out = np.stack([np.linspace(0, 10, 41), np.zeros(41)], 1)
    for back, expect in ((3.0, [10.0]), (0.6, [])):
        hook = np.stack([10 - np.linspace(0, back, 13)[1:], np.zeros(12)], 1)
        p = np.concatenate([out, hook])
        assert _cusps(p, _arc(p), 120.0, 1.0) == pytest.approx(expect)
        q = p[::-1].copy()
        assert _cusps(q, _arc(q), 120.0, 1.0) == pytest.approx([back] if expect else [])


def test_a_zero_scale_is_refused_by_name() -> None:
    """mm_per_pixel must be > 0: 0 is an InvalidArgumentError naming mm_per_pixel (not 'zero length')."""
    path = np.stack([np.linspace(0, 10, 20), np.zeros(20)], 1)
    with pytest.raises(InvalidArgumentError, match="mm_per_pixel"):
        stroke_trajectory(path, mm_per_pixel=0.0)


# ============================================================================================== mnist_demos
def test_mnist_demos_skips_pieces_and_partial_trails_and_checks_indices(tmp_path) -> None:
    """mnist_demos skips an image keeping less than min_ink_share of the ink (a bar and a separate dot: about 0.86)
    and one whose trail covers less than min_coverage (a T without excursions: about 0.7); an index below 0 and a
    min_coverage above 1 are InvalidArgumentErrors. Reference: images and IDX files written here."""
    bar = _image((slice(4, 24), slice(13, 16)))
    dotted = _image((slice(5, 23), slice(8, 11)), (slice(10, 13), slice(20, 23)))
    tee = _image((slice(6, 9), slice(4, 24)), (slice(9, 20), slice(13, 16)))
    _write_pair(tmp_path, np.stack([dotted, tee, bar, bar]), np.array([1, 1, 1, 1]))
    kw = dict(directory=tmp_path, n_points=30, stroke=dict(excursions=0, turn_weight=0.0))
    assert mnist_demos(1, 2, **kw).names == ("mnist/test/2", "mnist/test/3")
    assert mnist_demos(1, 3, min_ink_share=0.8, **kw).names[0] == "mnist/test/0"
    assert mnist_demos(1, 3, min_coverage=0.6, **kw).names[0] == "mnist/test/1"
    with pytest.raises(InvalidArgumentError, match="indices"):
        mnist_demos(1, 1, indices=[-1], **kw)
    with pytest.raises(InvalidArgumentError, match="min_coverage"):
        mnist_demos(1, 1, min_coverage=1.2, **kw)


def test_the_most_alike_are_the_tightest_n_not_the_centre_of_a_bigger_cluster() -> None:
    """_alike(paths, n): the path whose n - 1 nearest (DTW) are nearest, and those. Straight strokes of lengths
    10, 10.1, 13, 13.6, 14.2 px (distance grows with the length difference): for n = 2 the tight pair {10, 10.1}
    wins (its 1 nearest is 0.1 away), although 13.6 has the nearest two neighbours; for n = 3, 13.6 and its two."""
    from lfd_torch.data.mnist import _alike

    paths = [np.stack([np.linspace(0, a, 30), np.zeros(30)], 1) for a in (10, 10.1, 13, 13.6, 14.2)]
    assert _alike(paths, 2) == [0, 1]
    assert _alike(paths, 3) == [2, 3, 4]
    assert _alike(paths, 5) == [0, 1, 2, 3, 4]


def _theta() -> np.ndarray:
    """A rectangular ring with a bar across its middle (a theta): no endpoint, two junctions, and no closed trail
    through every branch (the trail from the top ends elsewhere)."""
    return _image((slice(5, 8), slice(6, 22)), (slice(20, 23), slice(6, 22)), (slice(5, 23), slice(6, 9)),
                  (slice(5, 23), slice(19, 22)), (slice(13, 16), slice(6, 22)))  # fmt: skip


def test_loop_gap_cuts_only_a_trail_that_closes_on_itself() -> None:
    """The loop_gap cut (and the wrap-around smoothing) apply to a closed trail that returns to its start; a theta's
    trail ends far from its start, so loop_gap changes nothing there."""
    a, b = extract_stroke(_theta(), loop_gap=0.0), extract_stroke(_theta(), loop_gap=0.3)
    assert a.closed and np.linalg.norm(a.path[0] - a.path[-1]) > 5.0
    np.testing.assert_array_equal(a.path, b.path)


def test_a_closed_skeleton_starts_at_its_top_most_pixel_even_when_its_trail_does_not_close() -> None:
    """Module docstring step 3: 'A skeleton without endpoints ... starts at its top-most pixel'. For a theta (ring
    y 4..22 and a bar at y ~ 13) the path must start on the top side (y ~ 21), not at a junction of the bar."""
    p = extract_stroke(_theta()).path
    assert p[0, 1] > p[:, 1].max() - 1.0
