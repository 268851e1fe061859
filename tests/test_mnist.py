"""MNIST IDX reading (gz, raw, torchvision layout, env var, corrupt files) and digit stroke extraction."""

from __future__ import annotations

import gzip
import math
import struct
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from lfd_torch.data import Demos, extract_stroke, load_mnist, mnist_demos, mnist_files, read_idx, stroke_trajectory
from lfd_torch.data.mnist import MNIST_ENV
from lfd_torch.errors import InvalidArgumentError, StoreError, TooFewSamplesError, UnknownNameError

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "mnist"
HAS_SHARED = (SHARED / "t10k-images-idx3-ubyte.gz").is_file() and (SHARED / "t10k-labels-idx1-ubyte.gz").is_file()


# ---------------------------------------------------------------------------------------------- helpers
def idx_bytes(arr: np.ndarray) -> bytes:
    """The IDX encoding of a uint8 array."""
    arr = np.ascontiguousarray(arr, dtype=np.uint8)
    return bytes([0, 0, 0x08, arr.ndim]) + struct.pack(f">{arr.ndim}I", *arr.shape) + arr.tobytes()


def write_idx(path: Path, arr: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    data = idx_bytes(arr)
    if path.name.endswith(".gz"):
        with gzip.open(path, "wb") as f:
            f.write(data)
    else:
        path.write_bytes(data)
    return path


def write_set(folder: Path, images: np.ndarray, labels: np.ndarray, *, gz: bool, prefix: str = "t10k") -> None:
    ext = ".gz" if gz else ""
    write_idx(folder / f"{prefix}-images-idx3-ubyte{ext}", images)
    write_idx(folder / f"{prefix}-labels-idx1-ubyte{ext}", labels)


def draw(polylines: list[list[tuple[float, float]]], size: int = 28, width: float = 1.3) -> np.ndarray:
    """A uint8 image of thick anti-aliased polylines given as (row, col) points."""
    rr, cc = np.mgrid[0:size, 0:size].astype(np.float64)
    img = np.zeros((size, size))
    for line in polylines:
        for (r0, c0), (r1, c1) in zip(line[:-1], line[1:]):
            d = np.array([r1 - r0, c1 - c0])
            t = np.clip(((rr - r0) * d[0] + (cc - c0) * d[1]) / max(float(d @ d), 1e-12), 0, 1)
            dist = np.hypot(rr - (r0 + t * d[0]), cc - (c0 + t * d[1]))
            img = np.maximum(img, np.clip(width + 0.5 - dist, 0, 1))
    return (255 * img).astype(np.uint8)


def ring(r0: float, c0: float, a: float, b: float, n: int = 80) -> list[tuple[float, float]]:
    """Closed ellipse (row radius a, column radius b) as a polyline."""
    t = np.linspace(0, 2 * np.pi, n + 1)
    return [(r0 + a * math.cos(u), c0 + b * math.sin(u)) for u in t]


def one(shift: float = 0.0) -> np.ndarray:
    return draw([[(5, 14 + shift), (22, 13 + shift)]])


def seven(shift: float = 0.0) -> np.ndarray:
    return draw([[(6, 6 + shift), (6, 21 + shift), (23, 12 + shift)]])


def zero() -> np.ndarray:
    return draw([ring(14, 14, 8, 6)])


def eight() -> np.ndarray:
    return draw([ring(9, 14, 5, 4.5), ring(19.5, 14, 5.5, 5)])


def six() -> np.ndarray:
    return draw([[(4, 17), (8, 12), (14, 9), (19, 10)], ring(18.5, 14, 4.5, 4.5)])


@pytest.fixture
def tiny(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray]:
    images = np.stack([seven(), one(), seven(1.0), one(-1.0), seven(-1.0), one(1.0), zero()])
    labels = np.array([7, 1, 7, 1, 7, 1, 0], dtype=np.uint8)
    return tmp_path, images, labels


# ---------------------------------------------------------------------------------------------- reading
@pytest.mark.parametrize("gz", [True, False])
def test_load_gz_and_raw_round_trip(tiny, gz):
    folder, images, labels = tiny
    write_set(folder, images, labels, gz=gz)
    x, y = load_mnist("test", folder)
    assert x.dtype == torch.uint8 and x.shape == (7, 28, 28) and y.dtype == torch.int64
    assert np.array_equal(x.numpy(), images) and np.array_equal(y.numpy(), labels)
    assert mnist_files("test", folder)[0].name.endswith(".gz") == gz


def test_raw_file_preferred_and_train_split(tiny):
    folder, images, labels = tiny
    write_set(folder, images, labels, gz=True, prefix="train")
    write_set(folder, images[:3], labels[:3], gz=False, prefix="train")
    x, _ = load_mnist("train", folder)
    assert x.shape[0] == 3  # the uncompressed copy wins over its .gz
    with pytest.raises(StoreError, match="t10k-images-idx3-ubyte"):
        load_mnist("test", folder)


def test_torchvision_layout_and_env_var(tiny, monkeypatch):
    folder, images, labels = tiny
    write_set(folder / "MNIST" / "raw", images, labels, gz=True)
    x, y = load_mnist(directory=folder)
    assert x.shape[0] == 7
    monkeypatch.setenv(MNIST_ENV, str(folder))
    x2, y2 = load_mnist()
    assert torch.equal(x, x2) and torch.equal(y, y2)
    demos = mnist_demos(7, 2)
    assert demos.n_demos == 2 and demos.names == ("mnist/test/0", "mnist/test/2")


def test_missing_directory_and_files_name_what_was_looked_for(tmp_path, monkeypatch):
    monkeypatch.delenv(MNIST_ENV, raising=False)
    with pytest.raises(StoreError, match=MNIST_ENV):
        load_mnist()
    with pytest.raises(StoreError, match="does not exist"):
        load_mnist(directory=tmp_path / "nowhere")
    monkeypatch.setenv(MNIST_ENV, str(tmp_path / "nowhere"))
    with pytest.raises(StoreError, match=r"\$LFD_MNIST_DIR"):
        load_mnist()
    with pytest.raises(StoreError) as info:
        load_mnist(directory=tmp_path)
    msg = str(info.value)
    for part in ("t10k-images-idx3-ubyte.gz", "t10k-labels-idx1-ubyte", str(Path("MNIST") / "raw"), str(tmp_path)):
        assert part in msg
    with pytest.raises(UnknownNameError, match="test, train"):
        load_mnist("validation", tmp_path)


def test_images_without_labels_is_an_error(tiny):
    folder, images, _ = tiny
    write_idx(folder / "t10k-images-idx3-ubyte.gz", images)
    with pytest.raises(StoreError, match="labels"):
        load_mnist("test", folder)


def _corrupt(folder: Path, images: np.ndarray, labels: np.ndarray, kind: str) -> None:
    write_set(folder, images, labels, gz=False)
    img = folder / "t10k-images-idx3-ubyte"
    lab = folder / "t10k-labels-idx1-ubyte"
    data = img.read_bytes()
    if kind == "truncated":
        img.write_bytes(data[:-100])
    elif kind == "trailing":
        img.write_bytes(data + b"\x00" * 7)
    elif kind == "short_header":
        img.write_bytes(data[:10])
    elif kind == "foreign":
        img.write_bytes(b"%PDF-1.4 not an idx file at all" * 10)
    elif kind == "swapped":  # a labels file where the images belong
        img.write_bytes(lab.read_bytes())
    elif kind == "count":
        write_idx(lab, labels[:-1])
    elif kind == "label_range":
        bad = labels.copy()
        bad[0] = 12
        write_idx(lab, bad)
    elif kind == "bad_gzip":
        img.unlink()
        (folder / "t10k-images-idx3-ubyte.gz").write_bytes(gzip.compress(data)[:-40])
    elif kind == "not_gzip":
        img.unlink()
        (folder / "t10k-images-idx3-ubyte.gz").write_bytes(data)
    elif kind == "tiny_images":
        write_idx(img, images[:, :4, :4])
    else:  # pragma: no cover
        raise AssertionError(kind)


@pytest.mark.parametrize(
    "kind, match",
    [
        ("truncated", "truncated"),
        ("trailing", "longer than its header"),
        ("short_header", "truncated"),
        ("foreign", "not an IDX file|magic number"),
        ("swapped", "magic number 0x00000801, expected 0x00000803"),
        ("count", "7 images but .* 6 labels"),
        ("label_range", "label 12"),
        ("bad_gzip", "cannot read IDX file"),
        ("not_gzip", "cannot read IDX file"),
        ("tiny_images", "4 x 4 pixels"),
    ],
)
def test_corrupt_files_raise_store_error_naming_the_file(tiny, kind, match):
    folder, images, labels = tiny
    _corrupt(folder, images, labels, kind)
    with pytest.raises(StoreError, match=match) as info:
        load_mnist("test", folder)
    assert "t10k-" in str(info.value)


def test_read_idx_types_and_dimensions(tmp_path):
    arr = np.arange(24, dtype=">i4").reshape(2, 3, 4)
    path = tmp_path / "x.idx"
    path.write_bytes(bytes([0, 0, 0x0C, 3]) + struct.pack(">3I", 2, 3, 4) + arr.tobytes())
    out = read_idx(path)
    assert out.shape == (2, 3, 4) and np.array_equal(out, arr) and not out.flags.writeable
    path.write_bytes(bytes([0, 0, 0x07, 1, 0, 0, 0, 1, 5]))
    with pytest.raises(StoreError, match="not an IDX file"):
        read_idx(path)
    with pytest.raises(StoreError, match="cannot read"):
        read_idx(tmp_path / "missing.idx")


# ---------------------------------------------------------------------------------------------- strokes
def test_stroke_of_a_one_runs_top_to_bottom():
    st = extract_stroke(one())
    p = st.path
    assert not st.closed and st.n_endpoints == 2 and st.coverage > 0.99
    assert p[0, 1] > p[-1, 1] + 12  # y up: starts at the top
    assert 14 < st.length < 19  # the drawn segment is 17 px; skeleton ends shrink it by about the half width
    assert np.all(np.diff(p[:, 1]) < 0.1)  # monotone downwards


def test_stroke_of_a_seven_starts_top_left_and_follows_the_corner():
    st = extract_stroke(seven())
    p = st.path
    assert not st.closed and st.coverage > 0.99
    assert p[0, 0] < 9 and p[0, 1] > 19  # start near (col 6, row 6) -> y = 21
    assert p[-1, 1] < 7 and abs(p[-1, 0] - 12) < 2.5  # end near the bottom (row 23)
    corner = np.argmax(p[:, 0])
    assert p[corner, 0] > 18 and 0.3 < corner / len(p) < 0.7  # through the top-right corner
    assert 24 < st.length < 35  # 15 + 19 px drawn


def test_stroke_of_a_zero_ring_covers_the_loop_counter_clockwise_and_stays_open():
    st = extract_stroke(zero(), loop_gap=0.1)
    p = st.path
    assert st.closed and st.n_endpoints == 0 and st.coverage > 0.99
    top = p[:, 1].max()
    assert p[0, 1] > top - 0.75  # the start is the top-most point
    assert p[20, 0] < p[0, 0]  # the first move goes to the left (counter-clockwise at the top)
    perimeter = 2 * math.pi * math.sqrt((8**2 + 6**2) / 2)
    assert 0.8 * perimeter < st.length < 1.0 * perimeter
    gap = np.linalg.norm(p[0] - p[-1])
    assert 0.05 * perimeter < gap < 0.2 * perimeter  # cut open: the attractor is not the start
    # the path goes round once: the winding angle about the centre is close to 2 pi (1 - gap)
    c = p - p.mean(0)
    ang = np.unwrap(np.arctan2(c[:, 1], c[:, 0]))
    assert 0.8 * 2 * math.pi < abs(ang[-1] - ang[0]) < 2 * math.pi
    assert ang[-1] > ang[0]  # counter-clockwise with y up


def test_stroke_of_an_eight_passes_its_crossing_twice():
    st = extract_stroke(eight())
    assert st.closed and st.n_junctions >= 1 and st.coverage > 0.9
    both = 2 * math.pi * (math.sqrt((5**2 + 4.5**2) / 2) + math.sqrt((5.5**2 + 5**2) / 2))
    assert 0.7 * both < st.length < both
    p = st.path
    assert p[:, 1].max() - p[:, 1].min() > 15  # both loops are drawn


def test_stroke_of_a_six_starts_at_the_stem_and_ends_on_the_loop():
    st = extract_stroke(six())
    p = st.path
    assert not st.closed and st.n_endpoints == 1 and st.coverage > 0.95
    assert p[0, 1] > 21  # the top of the stem (row 4 -> y 23)
    assert p[-1, 1] < p[0, 1] - 8  # the loop's closing point is lower
    c = p[len(p) // 2 :] - np.array([14, 27 - 18.5])
    assert np.ptp(np.unwrap(np.arctan2(c[:, 1], c[:, 0]))) > math.pi  # the second half goes round the loop


def test_stroke_errors_are_typed():
    with pytest.raises(TooFewSamplesError, match="no ink"):
        extract_stroke(np.zeros((28, 28), dtype=np.uint8))
    with pytest.raises(InvalidArgumentError, match="image"):
        extract_stroke(np.zeros((28,), dtype=np.uint8))
    for kw, name in [({"threshold": 1.5}, "threshold"), ({"loop_gap": 1.0}, "loop_gap"), ({"prune": -1.0}, "prune"),
                     ({"upsample": 0}, "upsample"), ({"excursions": -1}, "excursions")]:  # fmt: skip
        with pytest.raises(InvalidArgumentError, match=name):
            extract_stroke(one(), **kw)
    with pytest.raises(UnknownNameError, match="time law"):
        stroke_trajectory(np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), time_law="bang")


def test_stroke_trajectory_units_and_time_law():
    path = np.stack([np.linspace(0, 20, 50), np.zeros(50)], 1)  # 20 px to the right
    pos, t, vel = stroke_trajectory(path, n_points=101, mm_per_pixel=2.0, mean_speed=20.0)
    assert np.allclose(pos[-1], 0) and np.allclose(pos[0], [-40.0, 0.0])
    assert math.isclose(t[-1], 2.0)  # 40 mm at 20 mm/s
    assert np.allclose(vel[[0, -1]], 0)  # minimum jerk: at rest at both ends
    assert math.isclose(np.abs(vel[:, 0]).max(), 1.875 * 20.0, rel_tol=1e-3)
    # the velocities are the derivative of the positions
    fd = np.gradient(pos[:, 0], t)
    assert np.abs(fd - vel[:, 0])[5:-5].max() < 0.5


def test_stroke_trajectory_rests_at_a_cusp():
    """The pen stops where its path reverses (a sharp return), and only there: the velocity labels are continuous
    through the return (one movement over it reverses them at full speed) and still the positions' derivative."""
    out = np.stack([np.linspace(0, 10, 41), np.zeros(41)], 1)
    back = np.stack([np.linspace(10, 4, 25)[1:], np.zeros(24)], 1)
    up = np.stack([np.full(24, 4.0), np.linspace(0, 6, 25)[1:]], 1)  # then a right-angle corner: no rest
    path = np.concatenate([out, back, up])
    kw = dict(n_points=801, mm_per_pixel=1.0, mean_speed=10.0)
    pos, t, vel = stroke_trajectory(path, **kw)
    assert math.isclose(t[-1], 2.2)  # 22 mm at 10 mm/s, as without the rest
    speed = np.linalg.norm(vel, axis=1)
    at_cusp = np.linalg.norm(pos - (pos[0] + [10.0, 0.0]), axis=1).argmin()  # the sample nearest the return point
    assert speed[at_cusp] < 0.01 * speed.max() and math.isclose(t[at_cusp], 1.0, abs_tol=2 * t[1])
    at_corner = np.linalg.norm(pos - (pos[0] + [4.0, 0.0]), axis=1).argmin()
    assert speed[at_corner] > 0.3 * speed.max()  # 90 degrees: not a cusp
    near = slice(at_cusp - 100, at_cusp + 100)  # +-0.27 s; the unrounded corner turns the velocity at once
    jump = np.linalg.norm(np.diff(vel[near], axis=0), axis=1).max()
    assert jump < 0.05 * speed.max()  # continuous velocity through the return
    fd = np.gradient(pos, t, axis=0)
    idx = np.arange(len(t))
    away = (np.abs(idx - at_cusp) > 3) & (np.abs(idx - at_corner) > 10)  # a sharp corner blends its tangents
    assert (np.linalg.norm(fd - vel, axis=1)[away][2:-2] < 0.02 * speed.max()).all()
    # one movement over the reversal: the labels turn round between two samples at full speed
    _, _, vel1 = stroke_trajectory(path, cusp_angle=None, **kw)
    assert np.linalg.norm(np.diff(vel1[near], axis=0), axis=1).max() > 1.5 * np.linalg.norm(vel1, axis=1).max()
    # the constant law keeps its uniform speed; bad thresholds are typed
    _, _, vc = stroke_trajectory(path, time_law="constant", **kw)
    assert np.allclose(np.linalg.norm(vc, axis=1), 10.0)
    for kw_bad, name in [({"cusp_angle": 0.0}, "cusp_angle"), ({"cusp_angle": 180.0}, "cusp_angle"),
                         ({"cusp_window": 0.0}, "cusp_window"), ({"cusp_angle": float("nan")}, "cusp_angle")]:  # fmt: skip
        with pytest.raises(InvalidArgumentError, match=name):
            stroke_trajectory(path, **kw_bad)


# ---------------------------------------------------------------------------------------------- demonstrations
def test_mnist_demos_from_tiny_files(tiny):
    folder, images, labels = tiny
    write_set(folder, images, labels, gz=True)
    demos = mnist_demos(7, 3, directory=folder, n_points=120, mean_speed=30.0)
    assert isinstance(demos, Demos) and demos.n_demos == 3 and demos.max_length == 120
    assert torch.allclose(demos.end_points, torch.zeros(3, 2, dtype=demos.dtype), atol=1e-9)
    assert torch.equal(demos.attractor, torch.zeros(2, dtype=demos.dtype))
    starts = demos.start_points  # top-left of the 7, in mm from its bottom end
    assert (starts[:, 1] > 30).all() and (starts[:, 0] < -5).all()
    x = demos.samples()[0]
    span = float((x.amax(0) - x.amin(0)).max())
    assert 30 < span < 50
    assert ((demos.durations > 1.5) & (demos.durations < 4)).all()
    assert torch.allclose(demos.velocities[:, [0, -1]], torch.zeros(3, 2, 2, dtype=demos.dtype), atol=1e-9)
    # the same orientation rule for every image: the demonstrations nearly coincide
    assert (demos.positions[1:] - demos.positions[:1]).norm(dim=-1).max() < 5.0
    assert mnist_demos(1, 2, directory=folder, offset=1).names == ("mnist/test/3", "mnist/test/5")
    assert mnist_demos(7, 1, directory=folder, indices=[4]).names == ("mnist/test/4",)


def test_mnist_demos_pool_keeps_the_most_alike(tiny):
    folder, images, labels = tiny
    odd = draw([[(6, 6), (6, 21), (14, 21), (14, 8), (23, 8)]])  # a 7 written another way
    write_set(folder, np.concatenate([odd[None], images]), np.concatenate([[7], labels]).astype(np.uint8), gz=True)
    first = mnist_demos(7, 3, directory=folder)
    assert first.names == ("mnist/test/0", "mnist/test/1", "mnist/test/3")
    alike = mnist_demos(7, 3, directory=folder, pool=4)
    assert alike.names == ("mnist/test/1", "mnist/test/3", "mnist/test/5")
    with pytest.raises(InvalidArgumentError, match="pool"):
        mnist_demos(7, 3, directory=folder, pool=0)


def test_mnist_demos_argument_errors(tiny):
    folder, images, labels = tiny
    write_set(folder, images, labels, gz=False)
    with pytest.raises(InvalidArgumentError, match="digit"):
        mnist_demos(10, 1, directory=folder)
    with pytest.raises(InvalidArgumentError, match="n_demos"):
        mnist_demos(7, 0, directory=folder)
    with pytest.raises(InvalidArgumentError, match="n_demos: 4 demonstrations of digit 7 .* only 3"):
        mnist_demos(7, 4, directory=folder)
    with pytest.raises(InvalidArgumentError, match="indices: image 1 is a 1"):
        mnist_demos(7, 1, directory=folder, indices=[1])
    with pytest.raises(InvalidArgumentError, match="min_coverage"):
        mnist_demos(7, 1, directory=folder, min_coverage=2.0)


@pytest.mark.skipif(not HAS_SHARED, reason="shared MNIST copy not present")
def test_shared_test_set_gives_strokes_of_every_digit():
    x, y = load_mnist("test", SHARED)
    assert x.shape == (10000, 28, 28) and y[:10].tolist() == [7, 2, 1, 0, 4, 1, 4, 9, 5, 9]
    for d in range(10):
        demos = mnist_demos(d, 3, directory=SHARED)
        pts = demos.samples()[0]
        span = float((pts.amax(0) - pts.amin(0)).max())
        assert demos.n_demos == 3 and torch.allclose(demos.end_points, torch.zeros(3, 2, dtype=demos.dtype))
        assert 25 < span < 90, (d, span)
        assert ((demos.durations > 0.8) & (demos.durations < 6)).all(), (d, demos.durations)


# ---------------------------------------------------------------------------------------------- experiment
def _run_experiment(tmp_path: Path, overrides: list[str]) -> tuple[dict, pd.DataFrame]:
    from hydra import compose, initialize_config_dir

    sys.path.insert(0, str(ROOT / "experiments"))
    import mnist as experiment

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("mnist", overrides=[*overrides, f"+out_dir={tmp_path / 'out'}"])
    result = experiment.run(cfg)
    return result, pd.read_parquet(tmp_path / "out" / "results.parquet")


def _check_table(table: pd.DataFrame, digits: list[int], n_starts: int) -> None:
    from lfd_torch.store import KEY_COLUMNS

    assert set(KEY_COLUMNS) <= set(table.columns) and not table.duplicated(list(KEY_COLUMNS)).any()
    assert len(table) == len(digits) * 2 * n_starts
    assert set(table["shape"]) == {f"digit_{d}" for d in digits} and set(table["method"]) == {"framework", "seds"}
    assert (table["status"] == "ok").all()
    assert table[["DTWD", "E3", "final_error"]].notna().all().all()


def test_experiment_on_synthetic_idx_files(tiny):
    folder, images, labels = tiny
    write_set(folder, images, labels, gz=True)
    result, table = _run_experiment(folder, [f"data.directory={folder}", "digits=[1,7]", "n_perturbed=2",
                                             "budget_s=15", "n_resample=60", "data.n_points=120"])  # fmt: skip
    _check_table(table, [1, 7], 5)
    fw = table[table.method == "framework"]
    assert fw["reached"].mean() >= 0.8  # straight and one-corner strokes: the framework reaches the goal
    figs = {p.name for p in (folder / "out" / "figures").iterdir()}
    assert {"mnist_strokes.png", "mnist_rollouts.png"} <= figs
    assert (folder / "out" / "summary.md").read_text().count("|") > 10 and len(result["summary"]) == 2
    # seeded: a second run gives the same metrics
    _, again = _run_experiment(folder, [f"data.directory={folder}", "digits=[7]", "n_perturbed=2", "budget_s=15",
                                        "n_resample=60", "data.n_points=120", "figures=false"])  # fmt: skip
    cols = ["DTWD", "E3", "final_error", "reached"]
    first = table[table.digit == 7].sort_values(["method", "trajectory"])[cols].reset_index(drop=True)
    pd.testing.assert_frame_equal(first, again.sort_values(["method", "trajectory"])[cols].reset_index(drop=True))


@pytest.mark.skipif(not HAS_SHARED, reason="shared MNIST copy not present")
def test_experiment_on_two_shared_digits(tmp_path):
    result, table = _run_experiment(tmp_path, [f"data.directory={SHARED}", "digits=[0,4]", "n_perturbed=1",
                                               "n_resample=80", "figures=false"])  # fmt: skip
    _check_table(table, [0, 4], 4)
    assert table.groupby("method")["reached"].mean()["framework"] >= 0.75


def test_medoid_orientation_flips_the_strokes_against_the_medoid():
    """Four level strokes, the first drawn the other way: it is the one flipped (against the set's medoid, not
    against stroke 0), and a stroke that may not be flipped keeps its direction."""
    from lfd_torch.data.mnist import _medoid_orientation

    t = np.linspace(0.0, 1.0, 50)
    base = np.stack([10 * t, 3 * np.sin(np.pi * t) + 2 * t], 1)  # an arch, higher at its end
    paths = [base[::-1].copy()] + [base + [0.2 * k, -0.1 * k] for k in (1, 2, 3)]
    assert _medoid_orientation(paths, [True] * 4) == [True, False, False, False]
    assert _medoid_orientation(paths, [False, True, True, True]) == [False] * 4
