"""Violin plots of a results table, in the style of the paper's Fig. 9 (E1-E3 of SEDS, LPV-DS, LPV-DS + modulation,
train and test).

One violin per method (``by``), optionally split or dodged by ``hue`` (e.g. ``split``: train/test), dashed
quartile lines inside and a white dot at each group's mean. The plots read the results table and nothing
else. Figures are built on the non-interactive Agg canvas without pyplot (no window, no global figure
registry, safe in a sweep job) and saved atomically, the format following the file's extension.

Kernel density estimates are cut at the data range by default (``cut=0``): the errors are non-negative and a
violin should not suggest values that were never observed.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import seaborn as sns
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from lfd_torch.errors import PlotError, UnknownNameError
from lfd_torch.store.atomic import atomic_write
from lfd_torch.store.table import KEY_COLUMNS, PROVENANCE_COLUMNS
from lfd_torch.utils import check_float, check_path

__all__ = ["violin", "violin_grid", "save_figure", "metric_columns", "PlotError", "MEAN_MARKER_GID", "MAX_DPI"]

#: Largest accepted ``dpi``: 2400 dots per inch (a 5 x 3.5 inch figure is then 12000 x 8400 pixels, 400 MB of
#: RGBA); larger values only exhaust memory.
MAX_DPI = 2400.0

#: ``gid`` of the scatter artist that marks the group means (one point per violin).
MEAN_MARKER_GID = "lfd_torch.mean"

_NON_METRIC_COLUMNS = frozenset(KEY_COLUMNS) | frozenset(PROVENANCE_COLUMNS)


def metric_columns(table: pd.DataFrame) -> list[str]:
    """Numeric columns of a results table that are neither keys nor provenance, in table order."""
    return [
        c
        for c in table.columns
        if c not in _NON_METRIC_COLUMNS
        and pd.api.types.is_numeric_dtype(table[c])
        and not pd.api.types.is_bool_dtype(table[c])
    ]


def _load(table: pd.DataFrame | str | os.PathLike[str]) -> pd.DataFrame:
    if isinstance(table, pd.DataFrame):
        return table
    if isinstance(table, (str, os.PathLike)):
        path = Path(table)
        if path.suffix.lower() == ".csv":
            try:
                return pd.read_csv(path)
            except (OSError, ValueError) as exc:
                raise PlotError(f"cannot read {path}: {exc}") from exc
        from lfd_torch.store.table import read_table

        return read_table(path, validate=False)
    raise PlotError(f"table must be a DataFrame or a path to a .parquet/.csv file, not {type(table).__name__}")


def _check_metric(table: pd.DataFrame, metric: str) -> None:
    valid = metric_columns(table)
    if metric in valid:
        return
    if isinstance(metric, str) and metric not in _NON_METRIC_COLUMNS and metric in table.columns:
        n = int((table.columns == metric).sum())
        if n > 1:
            raise PlotError(f"metric column {metric!r} appears {n} times in the table; drop or rename the duplicates")
        dtype = table[metric].dtype
        raise PlotError(f"metric column {metric!r} is not numeric (dtype {dtype}); convert it first, e.g. with "
                        f"pd.to_numeric (valid metrics: {', '.join(valid) or 'none'})")  # fmt: skip
    raise UnknownNameError("metric", metric, valid)


def _check_dpi(dpi: object) -> float:
    return check_float(dpi, "dpi", low=0.0, low_open=True, high=MAX_DPI, error=PlotError)


def _check_column(table: pd.DataFrame, column: str, role: str) -> None:
    if column not in table.columns:
        raise UnknownNameError(f"column for {role}", column, [str(c) for c in table.columns])


def _levels(values: pd.Series, given: Sequence[Any] | None, name: str = "order") -> list[Any]:
    if given is not None:
        if isinstance(given, (str, bytes)) or not isinstance(given, Iterable):
            raise PlotError(f"{name} must be a sequence of levels (e.g. a list of method names), got {given!r}")
        levels = list(given)
        present = list(pd.unique(values.dropna()))
        if not any(level in present for level in levels):
            shown = ", ".join(str(v) for v in levels[:3]) + (" ..." if len(levels) > 3 else "")
            raise UnknownNameError(f"{name} level(s)", shown, [str(v) for v in present])
        return levels
    if isinstance(values.dtype, pd.CategoricalDtype):
        present = set(values.dropna().unique())
        return [c for c in values.cat.categories if c in present]
    return list(pd.unique(values.dropna()))


def _check_format(path: Path) -> str:
    fmt = path.suffix.lower().lstrip(".")
    supported = FigureCanvasAgg.get_supported_filetypes()
    if fmt not in supported:
        raise PlotError(f"cannot save {path}: unknown figure format {fmt!r}; use one of {sorted(supported)}")
    return fmt


def save_figure(fig: Figure, path: str | os.PathLike[str], *, dpi: int = 200) -> Path:
    """Save a figure atomically (temporary file + rename), the format following the extension.

    Args:
        fig: the figure.
        path: destination, e.g. ``results/figures/fig9.pdf`` (``.png``, ``.pdf``, ``.svg``, ...).
        dpi: resolution of raster formats (dots per inch), in (0, :data:`MAX_DPI` = 2400].

    Returns:
        The destination path.

    Raises:
        PlotError: unknown extension, or ``dpi`` not a number in (0, 2400] (checked before anything is written).
        OSError: the file cannot be written (raised as is; the destination keeps its previous content).
    """
    path = check_path(path, "path", error=PlotError)
    fmt = _check_format(path)
    dpi = _check_dpi(dpi)
    # Reproducible PDFs: no creation date embedded.
    metadata = {"CreationDate": None} if fmt == "pdf" else None
    return atomic_write(
        path, lambda tmp: fig.savefig(tmp, format=fmt, dpi=dpi, bbox_inches="tight", metadata=metadata)
    )


def _new_figure(figsize: tuple[float, float], n_panels: int = 1) -> tuple[Figure, list[Axes]]:
    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, n_panels, squeeze=False)[0]
    return fig, list(axes)


def _prepare(
    table: pd.DataFrame, metric: str, by: str, hue: str | None
) -> tuple[pd.DataFrame, int]:
    _check_column(table, by, "by")
    if hue is not None:
        _check_column(table, hue, "hue")
    _check_metric(table, metric)
    columns = list(dict.fromkeys([by, *([hue] if hue is not None else []), metric]))
    data = table[columns]
    values = data[metric].to_numpy(dtype=float, na_value=np.nan)
    keep = np.isfinite(values) & data[by].notna().to_numpy()
    if hue is not None:
        keep &= data[hue].notna().to_numpy()
    return data.loc[keep], int((~keep).sum())


def violin(
    table: pd.DataFrame | str | os.PathLike[str],
    metric: str,
    by: str = "method",
    hue: str | None = None,
    *,
    split: bool | None = None,
    order: Sequence[Any] | None = None,
    hue_order: Sequence[Any] | None = None,
    ax: Axes | None = None,
    path: str | os.PathLike[str] | None = None,
    inner: str | None = "quart",
    show_mean: bool = True,
    log_scale: bool = False,
    cut: float = 0.0,
    width: float = 0.8,
    palette: str | Sequence[Any] | Mapping[Any, Any] | None = None,
    title: str | None = None,
    ylabel: str | None = None,
    figsize: tuple[float, float] = (5.0, 3.5),
    dpi: int = 200,
    legend: bool = True,
) -> Figure:
    """Violin plot of one metric of a results table, one violin per ``by`` level.

    Args:
        table: the results table (DataFrame), or a path to a ``.parquet`` or ``.csv`` copy of it.
        metric: numeric column to plot (e.g. ``"E1"``), in its own units.
        by: column whose levels are the violins (default ``"method"``).
        hue: optional second grouping column (e.g. ``"split"`` with train/test).
        split: draw the two hue levels as the halves of one violin. Default: True when ``hue`` has exactly two
            levels (and differs from ``by``). True with another number of hue levels is a PlotError.
        order: ``by`` levels, left to right (default: order of first appearance; levels without data leave
            an empty slot; at least one must be present, a string is not a sequence of levels).
        hue_order: ``hue`` levels (default: order of first appearance).
        ax: axes to draw into; default: a new figure on the Agg canvas.
        path: if given, save the figure there, atomically; the format follows the extension (.png, .pdf, ...).
        inner: seaborn's inner marks: ``"quart"`` (dashed quartiles, as Fig. 9), ``"box"``, ``"point"``,
            ``"stick"`` or None.
        show_mean: mark each group's mean with a white dot (artist gid :data:`MEAN_MARKER_GID`).
        log_scale: logarithmic value axis (the density is estimated on the log scale).
        cut: how far, in bandwidths, the density extends past the extreme data points.
        width: width of a full violin, in category units.
        palette: seaborn palette for the hue (or ``by``) levels.
        title: axes title (default none); ``ylabel``: value-axis label (default: ``metric``).
        figsize: size of a new figure, inches (ignored with ``ax``).
        dpi: resolution of raster files, dots per inch, in (0, :data:`MAX_DPI`].
        legend: draw the legend (hue levels and the mean marker).

    Returns:
        The figure holding the plot.

    Raises:
        UnknownNameError: ``metric`` is not a numeric non-key column of the table, ``by``/``hue`` is not a
            column, or none of the ``order`` (``hue_order``) levels is in the data (the message lists the valid
            names).
        PlotError: no finite value of ``metric`` to plot, ``metric`` a column that is not numeric or duplicated,
            ``order`` a string, an impossible ``split``, an unknown file format or a ``dpi`` out of range.
        StoreError: ``table`` is a path that cannot be read.

    Warns:
        RuntimeWarning: rows with a non-finite metric (NaN, inf: e.g. a diverged rollout) or a missing group
            are left out; the warning counts them.
    """
    frame = _load(table)
    if path is not None:
        _check_format(Path(path))
        _check_dpi(dpi)
    data, n_dropped = _prepare(frame, metric, by, hue)
    if data.empty:
        raise PlotError(f"no finite values of {metric!r} to plot ({n_dropped} rows, none finite)")
    if n_dropped:
        warnings.warn(
            f"{n_dropped} of {len(frame)} rows left out of the {metric!r} violins (non-finite value or missing group)",
            RuntimeWarning,
            stacklevel=2,
        )

    order = _levels(data[by], order)
    use_hue = hue is not None and hue != by
    hue_levels = _levels(data[hue], hue_order, "hue_order") if use_hue else []
    if split is None:
        split = use_hue and len(hue_levels) == 2
    if split and len(hue_levels) != 2:
        raise PlotError(f"split=True needs a hue with exactly two levels, got {hue_levels}")

    if ax is None:
        if len(order) > 8:  # keep ~0.35 inch per level so many shapes stay legible
            figsize = (max(figsize[0], 0.35 * len(order) + 1.5), figsize[1])
        fig, (ax,) = _new_figure(figsize)
    else:
        fig = ax.figure

    sns.violinplot(
        data=data,
        x=by,
        y=metric,
        # Without a hue of their own, violins are coloured by their ``by`` level (as in Fig. 9).
        hue=hue if use_hue else by,
        order=order,
        hue_order=hue_levels if use_hue else order,
        split=bool(split),
        dodge=use_hue,
        inner=inner,
        cut=cut,
        width=width,
        palette=palette,
        log_scale=log_scale if log_scale else None,
        legend=bool(legend) and use_hue,
        ax=ax,
    )

    if show_mean:
        means = data.groupby([by, hue] if use_hue else [by], sort=False, observed=True)[metric].mean()
        xs, ys = [], []
        n_hue = max(len(hue_levels), 1)
        for i, level in enumerate(order):
            for k, hue_level in enumerate(hue_levels if use_hue else [None]):
                key = (level, hue_level) if use_hue else level
                if key not in means.index:
                    continue
                if not use_hue:
                    x = float(i)
                elif split:
                    # Just inside the half-violin, next to the shared centre line.
                    x = i + (-1 if k % 2 == 0 else 1) * width / 10
                else:
                    # The dodged violin's centre (as seaborn places it).
                    x = i + width / n_hue * (k + 0.5) - width / 2
                xs.append(x)
                ys.append(float(means.loc[key]))
        ax.scatter(
            xs, ys, s=22, marker="o", facecolor="white", edgecolor="black", linewidth=0.8, zorder=4,
            gid=MEAN_MARKER_GID,
        )

    ax.set_xlabel(by)
    if len(order) > 6 or max((len(str(level)) for level in order), default=0) > 12:
        ax.tick_params(axis="x", labelrotation=60)
        for label in ax.get_xticklabels():
            label.set_horizontalalignment("right")
            label.set_rotation_mode("anchor")
    ax.set_ylabel(ylabel if ylabel is not None else metric)
    if title is not None:
        ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    ax.set_axisbelow(True)

    if legend:
        handles, labels, legend_title = [], [], None
        existing = ax.get_legend()
        if existing is not None:
            handles = list(existing.legend_handles)
            labels = [text.get_text() for text in existing.get_texts()]
            legend_title = existing.get_title().get_text() or None
        if show_mean:
            handles.append(
                Line2D([], [], linestyle="none", marker="o", markerfacecolor="white", markeredgecolor="black")
            )
            labels.append("mean")
        if handles:
            ax.legend(handles, labels, title=legend_title, fontsize="small", title_fontsize="small")

    if path is not None:
        save_figure(fig, path, dpi=dpi)
    return fig


def violin_grid(
    table: pd.DataFrame | str | os.PathLike[str],
    metrics: Sequence[str],
    by: str = "method",
    hue: str | None = None,
    *,
    path: str | os.PathLike[str] | None = None,
    order: Sequence[Any] | None = None,
    hue_order: Sequence[Any] | None = None,
    titles: Sequence[str] | None = None,
    panel_size: tuple[float, float] = (4.0, 3.5),
    dpi: int = 200,
    **violin_kwargs: Any,
) -> Figure:
    """Panels of :func:`violin`, one per metric, side by side (the layout of Fig. 9: E1, E2, E3).

    All panels share the ``by`` and ``hue`` level order (computed over the whole table unless given) and one
    legend, drawn in the last panel.

    Args:
        table: the results table, or a path to a ``.parquet``/``.csv`` copy.
        metrics: metric columns, one panel each, left to right.
        by, hue, order, hue_order: as in :func:`violin`.
        path: if given, save the figure there atomically (format from the extension).
        titles: one title per panel (default: the metric names).
        panel_size: (width, height) of one panel, inches.
        dpi: resolution of raster files.
        **violin_kwargs: passed to :func:`violin` (``split``, ``inner``, ``show_mean``, ``log_scale``, ...).

    Returns:
        The figure, with ``len(metrics)`` axes.

    Raises:
        UnknownNameError: any metric or column is unknown (checked before drawing).
        PlotError: empty ``metrics``, wrong number of ``titles``, unknown file format, or a panel's error.
    """
    frame = _load(table)
    if isinstance(metrics, str) or not isinstance(metrics, Sequence):
        raise PlotError(f"metrics must be a sequence of metric column names, got {metrics!r}")
    metrics = list(metrics)
    if not metrics:
        raise PlotError("metrics is empty: give at least one metric column")
    if titles is not None and len(titles) != len(metrics):
        raise PlotError(f"{len(titles)} titles for {len(metrics)} metrics")
    if path is not None:
        _check_format(Path(path))
        _check_dpi(dpi)
    _check_column(frame, by, "by")
    if hue is not None:
        _check_column(frame, hue, "hue")
    for metric in metrics:
        _check_metric(frame, metric)
    for key in ("ax", "path", "legend", "figsize", "title"):
        if key in violin_kwargs:
            raise PlotError(f"violin_grid sets {key!r} itself")

    order = _levels(frame[by], order)
    if hue is not None and hue != by:
        hue_order = _levels(frame[hue], hue_order, "hue_order")
    fig, axes = _new_figure((panel_size[0] * len(metrics), panel_size[1]), len(metrics))
    for i, (metric, ax) in enumerate(zip(metrics, axes)):
        violin(
            frame,
            metric,
            by=by,
            hue=hue,
            order=order,
            hue_order=hue_order,
            ax=ax,
            title=titles[i] if titles is not None else metric,
            legend=i == len(metrics) - 1,
            **violin_kwargs,
        )
    if path is not None:
        save_figure(fig, path, dpi=dpi)
    return fig
