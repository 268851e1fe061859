"""Violin plots of results tables (Fig. 9 style)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PathCollection, PolyCollection
from matplotlib.figure import Figure

from lfd_torch.errors import LfdError, UnknownNameError
from lfd_torch.store import run_manifest, write_table
from lfd_torch.viz import MEAN_MARKER_GID, PlotError, metric_columns, save_figure, violin, violin_grid

METHODS = ["SEDS", "LPV-DS", "LPV-DS+mod"]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def table(generator: torch.Generator) -> pd.DataFrame:
    """3 methods x 7 trajectories x 4 seeds; trajectory 0 is the training one (LASA protocol)."""
    rows = []
    for m, method in enumerate(METHODS):
        for seed in range(4):
            for trajectory in range(7):
                e = torch.rand(3, generator=generator, dtype=torch.float64) * (m + 1)
                rows.append(
                    {
                        "experiment": "lasa",
                        "shape": "Sshape",
                        "method": method,
                        "fold": 0,
                        "seed": seed,
                        "trajectory": trajectory,
                        "split": "train" if trajectory == 0 else "test",
                        "E1": float(e[0]),
                        "E2": float(e[1]),
                        "E3": float(e[2]) * 100.0,
                        "config_hash": "abc",
                        "package_version": "0.1.0",
                        "git_sha": "unknown",
                    }
                )
    return pd.DataFrame(rows)


def _violins(ax) -> list[PolyCollection]:
    return [c for c in ax.collections if isinstance(c, PolyCollection)]


def _mean_points(ax) -> np.ndarray:
    (points,) = [c for c in ax.collections if isinstance(c, PathCollection) and c.get_gid() == MEAN_MARKER_GID]
    return np.asarray(points.get_offsets())


def test_violin_one_per_method_with_means(table: pd.DataFrame) -> None:
    fig = violin(table, "E1")
    assert isinstance(fig, Figure) and isinstance(fig.canvas, FigureCanvasAgg)
    (ax,) = fig.axes
    assert len(_violins(ax)) == len(METHODS)
    assert [t.get_text() for t in ax.get_xticklabels()] == METHODS
    assert ax.get_ylabel() == "E1" and ax.get_xlabel() == "method"
    points = _mean_points(ax)
    expected = table.groupby("method")["E1"].mean()[METHODS].to_numpy()
    np.testing.assert_allclose(points[:, 0], np.arange(len(METHODS)))
    np.testing.assert_allclose(points[:, 1], expected, rtol=1e-12)


def test_violin_split_train_test(table: pd.DataFrame) -> None:
    fig = violin(table, "E2", hue="split", order=METHODS[::-1])
    (ax,) = fig.axes
    assert len(_violins(ax)) == 2 * len(METHODS)  # one half-violin per (method, split)
    assert [t.get_text() for t in ax.get_xticklabels()] == METHODS[::-1]
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend == ["train", "test", "mean"]
    points = _mean_points(ax)
    means = table.groupby(["method", "split"])["E2"].mean()
    expected = [means[(m, s)] for m in METHODS[::-1] for s in ("train", "test")]
    np.testing.assert_allclose(points[:, 1], expected, rtol=1e-12)
    # Each half's mean sits on its own side of the shared centre line.
    offsets = points[:, 0] - np.repeat(np.arange(len(METHODS)), 2)
    assert np.all(offsets[0::2] < 0) and np.all(offsets[1::2] > 0)
    # Each half-violin lies on one side of its centre line.
    for i, poly in enumerate(_violins(ax)):
        xs = poly.get_paths()[0].vertices[:, 0]
        centre = i // 2
        if i % 2 == 0:
            assert xs.max() <= centre + 1e-9
        else:
            assert xs.min() >= centre - 1e-9


def test_violin_dodged_hue_without_split(table: pd.DataFrame) -> None:
    labels = np.where(table["trajectory"] < 2, "train", np.where(table["trajectory"] < 5, "val", "test"))
    three = table.assign(split=labels)
    fig = violin(three, "E1", hue="split")
    (ax,) = fig.axes
    assert len(_violins(ax)) == 3 * len(METHODS)
    points = _mean_points(ax)
    # Each mean marker is at the horizontal centre of its (symmetric) violin.
    for poly, (x, _) in zip(_violins(ax), points):
        xs = poly.get_paths()[0].vertices[:, 0]
        assert abs((xs.min() + xs.max()) / 2 - x) < 1e-9
    with pytest.raises(PlotError, match="exactly two"):
        violin(three, "E1", hue="split", split=True)


def test_violin_writes_png_and_pdf(table: pd.DataFrame, tmp_path: Path) -> None:
    png = tmp_path / "figs" / "e1.png"
    pdf = tmp_path / "figs" / "e1.pdf"
    violin(table, "E1", hue="split", path=png, dpi=60)
    violin(table, "E1", hue="split", path=pdf)
    assert png.read_bytes()[:8] == PNG_MAGIC and png.stat().st_size > 2_000
    assert pdf.read_bytes()[:5] == b"%PDF-" and pdf.stat().st_size > 5_000
    assert sorted(p.name for p in png.parent.iterdir()) == ["e1.pdf", "e1.png"]  # no temp files left


def test_violin_reads_table_files(table: pd.DataFrame, tmp_path: Path) -> None:
    manifest = run_manifest(None, 0)
    path = write_table(table.drop(columns=["config_hash", "package_version", "git_sha"]).query("seed == 0"),
                       tmp_path / "results.parquet", manifest=manifest)
    assert len(_violins(violin(path, "E3").axes[0])) == len(METHODS)
    table.to_csv(tmp_path / "results.csv", index=False)
    assert len(_violins(violin(tmp_path / "results.csv", "E3").axes[0])) == len(METHODS)


def test_violin_bad_names_give_clear_errors(table: pd.DataFrame) -> None:
    with pytest.raises(UnknownNameError) as info:
        violin(table, "E4")
    message = str(info.value)
    assert "unknown metric 'E4'" in message and "E1, E2, E3" in message
    assert "seed" not in message.split("valid names:")[1]  # keys and provenance are not metrics
    with pytest.raises(UnknownNameError, match="metric 'method'"):
        violin(table, "method")
    with pytest.raises(UnknownNameError, match="'algo'"):
        violin(table, "E1", by="algo")
    with pytest.raises(UnknownNameError, match="'phase'"):
        violin(table, "E1", hue="phase")
    with pytest.raises(PlotError, match="format"):
        violin(table, "E1", path="fig.xyz")
    assert issubclass(PlotError, LfdError) and issubclass(PlotError, ValueError)
    assert metric_columns(table) == ["E1", "E2", "E3"]


def test_violin_non_finite_values_are_left_out_with_a_warning(table: pd.DataFrame) -> None:
    broken = table.copy()
    broken.loc[[0, 1], "E1"] = [np.nan, np.inf]
    with pytest.warns(RuntimeWarning, match="2 of 84 rows"):
        fig = violin(broken, "E1")
    expected = broken[np.isfinite(broken["E1"])].groupby("method")["E1"].mean()[METHODS].to_numpy()
    np.testing.assert_allclose(_mean_points(fig.axes[0])[:, 1], expected, rtol=1e-12)
    with pytest.raises(PlotError, match="no finite"):
        violin(broken.assign(E1=np.nan), "E1")


def test_violin_into_given_axes_and_failed_save_keeps_old_file(
    table: pd.DataFrame, tmp_path: Path, monkeypatch
) -> None:
    fig = Figure()
    ax = fig.add_subplot()
    assert violin(table, "E2", ax=ax) is fig
    target = tmp_path / "fig.png"
    target.write_bytes(b"old figure")

    def failing_savefig(self, fname, **kwargs):
        Path(fname).write_bytes(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(Figure, "savefig", failing_savefig)
    with pytest.raises(OSError, match="disk full"):
        save_figure(fig, target)
    assert target.read_bytes() == b"old figure"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png"]


def test_violin_grid_panels(table: pd.DataFrame, tmp_path: Path) -> None:
    out = tmp_path / "fig9.png"
    fig = violin_grid(table, ["E1", "E2", "E3"], hue="split", path=out, order=METHODS, dpi=60)
    assert len(fig.axes) == 3
    for ax, metric in zip(fig.axes, ["E1", "E2", "E3"]):
        assert len(_violins(ax)) == 2 * len(METHODS)
        assert ax.get_title() == metric
        assert [t.get_text() for t in ax.get_xticklabels()] == METHODS
    assert [ax.get_legend() is not None for ax in fig.axes] == [False, False, True]
    assert out.read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(UnknownNameError, match="E9"):
        violin_grid(table, ["E1", "E9"])
    with pytest.raises(PlotError, match="empty"):
        violin_grid(table, [])
