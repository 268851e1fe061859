"""experiments/figures.py redraws the published figures from stored tables and libraries, without fitting.

The fixture publishes tiny runs of the five experiments into a temporary project root (``paths.root``), which
writes their tables, libraries and figures; figures.py then runs there (``LFD_ROOT``) with every fitter and the
scooping simulation replaced by ones that raise, and must rewrite every figure byte for byte.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from lfd_torch.data import Demos
from lfd_torch.errors import StoreError
from lfd_torch.viz.stored import load_config, load_demos, load_state, save_config, save_demos, save_state

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))
sys.path.insert(0, str(ROOT / "tests"))

import figures  # noqa: E402

#: Names of the fitting and simulation entry points; figures.py must call none of them.
FITTERS = ("fit_lpvds", "fit_seds", "segment", "fit_gmm", "fit_pcgmm", "learn_scooping", "run_trials", "solve_ik",
           "start_configurations")  # fmt: skip
EXPERIMENTS = ("lasa_tasks", "lasa_benchmark", "mnist", "segment_lasa", "scooping", "figures")


def _compose(name: str, overrides: list[str]):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(name, overrides=overrides)


@pytest.fixture(scope="module")
def published(tmp_path_factory) -> Path:
    """A project root whose results/ holds tiny published runs of every experiment figures.py redraws."""
    import lasa_benchmark
    import lasa_tasks
    import mnist
    import scooping
    import segment_lasa
    from test_mnist import one, seven, write_set

    root = tmp_path_factory.mktemp("project")
    common = [f"paths.root={root}", "publish=true", "progress=false"]
    segment_lasa.run(_compose("segment_lasa", common + [
        "shapes=[]", "synthetic_3d.n_demos=2", "synthetic_3d.n_steps=2", "synthetic_3d.samples_per_step=40",
        "segmentation.n_iterations=15", f"+out_dir={root / 'job_seg'}"]))  # fmt: skip
    lasa_tasks.run(_compose("lasa_tasks", common + [
        "shapes=[Multi_Models_1]", "training=[one]", "n_random=4", "budget_s=20", "n_resample=40",
        f"+out_dir={root / 'job_tasks'}"]))  # fmt: skip
    lasa_benchmark.run(_compose("lasa_benchmark", common + [
        "shapes=[Line]", "segmentations=[none]", "primitives=[lpvds]", f"+out_dir={root / 'job_bench'}"]))  # fmt: skip
    images = np.stack([seven(), one(), seven(1.0), one(-1.0)])
    write_set(root / "mnist", images, np.array([7, 1, 7, 1], dtype=np.uint8), gz=False)
    mnist.run(_compose("mnist", common + [
        "digits=[7]", "data.n_demos=2", "data.pool=null", "data.n_points=120", f"data.directory={root / 'mnist'}",
        "n_perturbed=1", "budget_s=15", "n_resample=40", f"+out_dir={root / 'job_mnist'}"]))  # fmt: skip
    # 1 s trials: each mode's runs stop early, some disturbed
    scooping.run(_compose("scooping", common + [
        "n_disturbed=6", "starts.n=2", "budget_s=1.0", "n_figure_trials=1", "workers=1",
        f"+out_dir={root / 'job_scoop'}"]))  # fmt: skip
    return root


def _raise(*args, **kwargs):
    raise AssertionError("figures.py fitted a model")


def _forbid_fitting(monkeypatch) -> None:
    from lfd_torch.gmm import PCGMMFitter
    from lfd_torch.segmentation import BPGMHMMSegmenter, FixedSegmenter, NoSegmenter
    from lfd_torch.skills import SkillLibrary

    for name, module in list(sys.modules.items()):
        if module is None or not (name.startswith("lfd_torch") or name in EXPERIMENTS):
            continue
        for attr in FITTERS:
            if callable(getattr(module, attr, None)):
                monkeypatch.setattr(module, attr, _raise)
    monkeypatch.setattr(SkillLibrary, "learn", classmethod(_raise))
    for cls in (BPGMHMMSegmenter, FixedSegmenter, NoSegmenter, PCGMMFitter):
        monkeypatch.setattr(cls, "__call__", _raise)
    if "lfd_torch.robot" in sys.modules:  # no MuJoCo physics step either (the frame is one mj_forward)
        from lfd_torch.robot import BaxterPlant

        monkeypatch.setattr(BaxterPlant, "step", _raise)


def _snapshot(results: Path) -> dict[str, bytes]:
    files = list((results / "figures").iterdir()) + list((results / "tables").glob("*.md"))
    files += list((results / "tables").glob("*_summary.csv"))
    return {str(p.relative_to(results)): p.read_bytes() for p in files}


def test_figures_redraws_every_published_file_identically_without_fitting(published, monkeypatch, capsys):
    results = published / "results"
    before = _snapshot(results)
    assert {"figures/segment_lasa_synthetic_3d.png", "figures/lasa_tasks_Multi_Models_1_pushes.png",
            "figures/lasa_benchmark_violins.png", "figures/mnist_rollouts.png",
            "tables/lasa_benchmark_summary.csv"} <= set(before)  # fmt: skip
    scooped = (results / "tables" / "scooping.parquet").is_file()
    if scooped:
        assert {f"figures/scooping_{n}.png" for n in ("segmentation", "starts", "disturbed")} <= set(before)
        assert "tables/scooping.md" in before
    shutil.rmtree(results / "figures")
    for name in ("lasa_benchmark_summary.md", "lasa_benchmark_summary.csv", "lasa_tasks.md", "mnist.md",
                 "scooping.md"):  # fmt: skip
        (results / "tables" / name).unlink(missing_ok=True)
    _forbid_fitting(monkeypatch)
    import lasa_tasks

    import lfd_torch.ds
    from lfd_torch.segmentation import NoSegmenter

    cfg = load_config(results / "libraries" / "lasa_tasks" / "config.json")
    train, _ = load_demos(results / "libraries" / "lasa_tasks" / "Multi_Models_1_demos.pt")
    for fit in (lambda: lasa_tasks.fig6_libraries(cfg, "Multi_Models_1", train[[0]]),
                lambda: lfd_torch.ds.fit_seds(train), lambda: NoSegmenter()(train)):  # fmt: skip
        with pytest.raises(AssertionError, match="fitted a model"):
            fit()
    if scooped:
        import scooping

        for call in (scooping.learn_scooping, scooping.run_trials, scooping.start_configurations):
            with pytest.raises(AssertionError, match="fitted a model"):
                call()
    monkeypatch.setenv("LFD_ROOT", str(published))
    assert figures.main([] if scooped else ["--only", "segment_lasa", "lasa_tasks", "lasa_benchmark", "mnist"]) == 0
    after = _snapshot(results)
    assert set(after) == set(before)
    changed = [name for name in before if after[name] != before[name]]
    assert not changed, f"redrawn differently: {changed}"
    out = capsys.readouterr().out
    assert "results/figures/mnist_strokes.png" in out and "files in" in out


def test_a_figure_without_stored_source_is_listed(tmp_path):
    folder = tmp_path / "results" / "figures"
    folder.mkdir(parents=True)
    for name in ("hand_made.png", "scooping_demo.png", "scooping_frame.png", "redrawn.png"):
        (folder / name).write_bytes(b"png")
    old = time.time() - 100
    for name in ("hand_made.png", "scooping_demo.png", "scooping_frame.png"):
        os.utime(folder / name, (old, old))
    # every figure is figures.py's to redraw; one this machine cannot draw (reported as such) is not stale
    stale = figures.stale_figures(tmp_path / "results", old + 50, (folder / "scooping_frame.png",))
    assert stale == [folder / "hand_made.png", folder / "scooping_demo.png"]
    assert figures.stale_figures(tmp_path / "results", old + 50)[-1] == folder / "scooping_frame.png"
    assert figures.stale_figures(tmp_path / "results", old - 50) == []


def _middle_of_largest_record(raw: bytearray) -> int:
    """Offset of the middle byte of the largest tensor record of a torch.save zip (the middle of the file if not a
    zip): the middle of the file itself may fall in a zip header's padding, which readers ignore."""
    import io
    import struct
    import zipfile

    if not zipfile.is_zipfile(io.BytesIO(bytes(raw))):
        return len(raw) // 2
    info = max(zipfile.ZipFile(io.BytesIO(bytes(raw))).infolist(), key=lambda i: i.compress_size)
    name_len, extra_len = struct.unpack("<HH", raw[info.header_offset + 26 : info.header_offset + 30])
    return info.header_offset + 30 + name_len + extra_len + info.compress_size // 2


@pytest.mark.parametrize(
    "relative, damage",
    [
        ("libraries/segment_lasa/synthetic_3d/segmentation.pt", "flip"),
        ("libraries/segment_lasa/synthetic_3d/demos.pt", "delete"),
        ("libraries/lasa_tasks/config.json", "flip"),
        ("libraries/lasa_tasks/Multi_Models_1_demos.pt", "truncate"),
        ("libraries/lasa_tasks/Multi_Models_1_one/manifest.json", "delete"),
        ("libraries/lasa_tasks/Multi_Models_1_steps2/step_1.pt", "flip"),
        ("libraries/mnist/digit_7.pt", "flip"),
        ("tables/lasa_benchmark.parquet", "truncate"),
        ("libraries/scooping/trials.pt", "flip"),
        ("libraries/scooping/demos.pt", "flip"),
        ("libraries/scooping/segmentation.pt", "truncate"),
        ("libraries/scooping/segmentation.pt", "delete"),
        ("libraries/scooping/config.json", "flip"),
        ("tables/scooping.parquet", "delete"),
    ],
)
def test_missing_or_damaged_stored_file_raises_store_error_naming_it(published, monkeypatch, tmp_path, relative,
                                                                     damage):  # fmt: skip
    copy = tmp_path / "project"
    shutil.copytree(published / "results", copy / "results")
    path = copy / "results" / relative
    raw = bytearray(path.read_bytes())
    if damage == "delete":
        path.unlink()
    elif damage == "truncate":
        path.write_bytes(bytes(raw[: len(raw) // 2]))
    else:  # one flipped bit in the middle of the largest stored tensor (torch.save zip) or of the JSON text
        raw[_middle_of_largest_record(raw)] ^= 0x04
        path.write_bytes(bytes(raw))
    monkeypatch.setenv("LFD_ROOT", str(copy))
    group = relative.split("/")[1] if relative.startswith("libraries") else relative.split("/")[1].split(".")[0]
    with pytest.raises(StoreError, match=re.escape(path.name)):
        figures.main(["--only", group])


def test_scooping_frame_without_offscreen_rendering_is_reported_not_redrawn(published, monkeypatch, tmp_path,
                                                                            capsys):  # fmt: skip
    assert (published / "results" / "libraries" / "scooping").is_dir()
    copy = tmp_path / "project"
    shutil.copytree(published / "results", copy / "results")
    frame = copy / "results" / "figures" / "scooping_frame.png"
    kept = frame.read_bytes() if frame.is_file() else None
    start = time.time()
    monkeypatch.setenv("LFD_ROOT", str(copy))
    monkeypatch.setenv("LFD_MUJOCO_GL", "no_such_gl_backend")  # mujoco refuses to import: no GL context
    assert figures.main(["--only", "scooping"]) == 0
    err = capsys.readouterr().err
    assert "scooping_frame.png not drawn: MuJoCo offscreen rendering unavailable" in err
    assert (frame.read_bytes() if frame.is_file() else None) == kept
    for name in ("segmentation", "starts", "disturbed"):
        assert (copy / "results" / "figures" / f"scooping_{name}.png").stat().st_mtime >= start - 0.05


def test_stored_demos_round_trip(tmp_path, generator):
    T, d = 30, 2
    x = torch.randn(3, T, d, generator=generator, dtype=torch.float64).cumsum(1)
    demos = Demos.from_sequences([x[0], x[1, :20], x[2, :25]], dt=0.1, names=["a", "b", "c"])
    back, extra = load_demos(save_demos(demos, tmp_path / "d.pt", note="x", image=torch.arange(4)))
    for name in ("positions", "velocities", "times", "lengths", "attractor"):
        torch.testing.assert_close(getattr(back, name), getattr(demos, name), rtol=0, atol=0)
    assert back.names == demos.names and extra["note"] == "x" and extra["image"].tolist() == [0, 1, 2, 3]
    lean, _ = load_demos(save_demos(demos, tmp_path / "lean.pt", velocities=False))
    torch.testing.assert_close(lean.positions, demos.positions, rtol=0, atol=0)
    # without stored velocities they are re-estimated: central differences inside the valid part
    inner = (x[0, 2:] - x[0, :-2]) / 0.2
    torch.testing.assert_close(lean.velocities[0, 1:-1], inner)
    assert (tmp_path / "lean.pt").stat().st_size < (tmp_path / "d.pt").stat().st_size


def test_stored_state_checksum_catches_an_altered_value(tmp_path):
    path = save_state({"a": torch.ones(5, dtype=torch.float64), "n": 3}, tmp_path / "s.pt")
    assert load_state(path)["n"] == 3
    state = torch.load(path, weights_only=True)
    state["a"][2] = 1.0 + 2**-40  # a change torch.save writes without complaint
    torch.save(state, path)
    with pytest.raises(StoreError, match=r"s\.pt.*checksum"):
        load_state(path)
    with pytest.raises(StoreError, match="missing.pt is missing"):
        load_state(tmp_path / "missing.pt")


def test_stored_config_round_trip_and_tamper(tmp_path):
    cfg = {"dt": 0.01, "budget_s": math.inf, "shapes": ["A", "B"], "pushes": {"n": 2}, "hydra": {"x": 1},
           "paths": {"root": str(tmp_path)}}  # fmt: skip
    path = save_config(cfg, tmp_path / "config.json")
    back = load_config(path)
    assert back.dt == 0.01 and back.budget_s == math.inf and list(back.shapes) == ["A", "B"]
    assert "hydra" not in back and "paths" not in back and str(tmp_path) not in path.read_text()
    path.write_text(path.read_text().replace('"n": 2', '"n": 3'))
    with pytest.raises(StoreError, match="config.json"):
        load_config(path)
    import json

    from lfd_torch.store.checksum import DIGEST_KEY, payload_digest

    doc = {"config": {"dt": 0.01}, "schema_version": 999}  # a consistent file of another schema
    doc[DIGEST_KEY] = payload_digest(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(StoreError, match="schema 999"):
        load_config(path)


def test_make_figures_reads_stored_files_and_make_results_recomputes():
    text = (ROOT / "Makefile").read_text()

    def recipe(target: str) -> list[str]:
        block = re.search(rf"^{target}:.*\n((?:\t.*\n)+)", text, re.M)
        assert block, target
        return [line.strip() for line in block.group(1).splitlines()]

    assert recipe("figures") == ["$(BIN)/python experiments/figures.py"]
    steps = " ".join(recipe("results"))
    for preset in ("segment_lasa_publish", "lasa_tasks_publish", "lasa_benchmark_publish", "lasa_benchmark_paper",
                   "mnist.py publish=true", "report_benchmark.py", "scooping_publish"):  # fmt: skip
        assert preset in steps
    assert recipe("results")[-1] == "$(BIN)/python experiments/figures.py"
    assert recipe("run") == ["$(BIN)/python experiments/lasa_benchmark.py"]


def test_segmentation_figure_axes_carry_the_unit(generator):
    from lfd_torch.segmentation import FixedSegmenter
    from lfd_torch.segmentation.plot import plot_segmentation

    t = torch.linspace(0, 1, 60, dtype=torch.float64)
    demos = Demos.from_sequences([torch.stack([t, t**2], -1) * 10.0], dt=0.05)
    fig = plot_segmentation(FixedSegmenter([0.5])(demos), demos, unit="mm", title="two steps")
    ax = fig.axes[0]
    assert ax.get_xlabel() == "x_1 (mm)" and ax.get_ylabel() == "x_2 (mm)" and ax.get_title() == "two steps"
