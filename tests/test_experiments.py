"""Experiment entry points: run(cfg) directly and a tiny Hydra multirun merged by collect."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from lfd_torch.store import KEY_COLUMNS, collect

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))


def test_lasa_metrics_run_writes_table_and_figure(tmp_path):
    import lasa_metrics

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("lasa_metrics", overrides=["shapes=[Line,Multi_Models_3]", f"+out_dir={tmp_path}"])
    result = lasa_metrics.run(cfg)
    table = pd.read_parquet(tmp_path / "results.parquet")
    assert len(table) == 14 and set(table["shape"]) == {"Line", "Multi_Models_3"}
    assert set(KEY_COLUMNS) <= set(table.columns) and table["git_sha"].notna().all()
    assert (tmp_path / "smoothing_area.png").stat().st_size > 0
    # smoothing with a window of 15 changes the path a little, never moves the goal
    assert (table["smoothing_area"] > 0).all() and (table["end_distance"] < 1e-9).all()
    assert len(result["table"]) == len(table)


@pytest.mark.slow
def test_lasa_metrics_multirun_and_collect(tmp_path):
    cmd = [
        sys.executable, str(ROOT / "experiments" / "lasa_metrics.py"), "-m", "preprocess.window=5,15",
        "shapes=[Line]", f"hydra.sweep.dir={tmp_path}",
    ]  # fmt: skip
    subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True, env={"OMP_NUM_THREADS": "1", "PATH": ""})
    merged = collect(tmp_path)
    assert len(merged) == 14 and set(merged["method"]) == {"savgol-w5", "savgol-w15"}
    # a wider window removes more: the smoothed path moves further from the raw one
    means = merged.groupby("method")["smoothing_area"].mean()
    assert means["savgol-w15"] > means["savgol-w5"]


def test_lasa_tasks_run_writes_rows_summary_and_figures(tmp_path):
    import lasa_tasks

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("lasa_tasks", overrides=["shapes=[Multi_Models_1]", "training=[one]", "n_random=12",
                                               "budget_s=40", "n_resample=60", f"+out_dir={tmp_path}"])  # fmt: skip
    result = lasa_tasks.run(cfg)
    table = pd.read_parquet(tmp_path / "results.parquet")
    assert set(KEY_COLUMNS) <= set(table.columns) and not table.duplicated(list(KEY_COLUMNS)).any()
    assert set(table["mode"]) == {"none", "full"} and {"demo", "random"} <= set(table["starts"])
    assert table["finished"].all() and (table["final_error"] < 1.0).all()
    rnd = table[table.starts == "random"]
    assert (rnd["pushes"] > 0).any()
    out = table[table.starts == "outside"]
    assert len(out) == 0 or out["recovery_samples"].notna().all()
    summary = (tmp_path / "summary.md").read_text()
    assert "Multi_Models_1" in summary and len(result["summary"]) == 1
    figs = {p.name for p in (tmp_path / "figures").iterdir()}
    for suffix in ("entropy.png", "steps.png", "modulation.png", "pushes.png", "tree.txt"):
        assert f"lasa_tasks_Multi_Models_1_{suffix}" in figs
    lib_dir = tmp_path / "libraries" / "Multi_Models_1_one"
    assert (lib_dir / "manifest.json").is_file()


def test_lasa_benchmark_one_training_demo_rows_and_shared_libraries(tmp_path, monkeypatch):
    import lasa_benchmark

    calls = []
    learn = lasa_benchmark.SkillLibrary.learn

    def counting(*args, **kwargs):
        calls.append(1)
        return learn(*args, **kwargs)

    monkeypatch.setattr(lasa_benchmark.SkillLibrary, "learn", counting)
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("lasa_benchmark", overrides=["shapes=[Angle]", "fold=2", "segmentations=[none]",
                                                   "primitives=[lpvds]", f"+out_dir={tmp_path}"])  # fmt: skip
    result = lasa_benchmark.run(cfg)
    table = pd.read_parquet(tmp_path / "results.parquet")
    assert len(calls) == 1  # one library, shared by the two modulation variants
    assert len(table) == 2 * 7 and not table.duplicated(list(KEY_COLUMNS)).any()
    assert set(table.method) == {"none+lpvds+none", "none+lpvds+full"}
    train = table[table.split == "train"]
    assert set(train.trajectory) == {2} and set(table[table.split == "test"].trajectory) == {0, 1, 3, 4, 5, 6}
    assert table[["E1", "E2", "E3", "DTWD", "final_error"]].notna().all().all() and table.reached.all()
    assert len(result["table"]) == len(table)
