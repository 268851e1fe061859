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
