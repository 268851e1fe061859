"""Figures drawn from results tables (and nothing else).

Notation:
    table    results table of :mod:`lfd_torch.store` (one row per experiment, shape, method, fold, seed,
             trajectory; metric columns E1, E2, E3, DTWD, ... in the data's units)
    by       column whose levels are the violins (default ``method``)
    hue      optional second grouping (e.g. ``split``: train/test), drawn as split halves when it has two levels

Figures use the Agg canvas without pyplot and are saved atomically, the format following the extension.
The checksummed files the published figures are redrawn from are read and written by :mod:`lfd_torch.viz.stored`.
"""

from lfd_torch.viz.violin import MEAN_MARKER_GID, PlotError, metric_columns, save_figure, violin, violin_grid

__all__ = ["violin", "violin_grid", "save_figure", "metric_columns", "PlotError", "MEAN_MARKER_GID"]
