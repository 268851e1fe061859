"""Trajectories coloured by step over the subtask-space regions (paper Fig. 2 / Fig. 13 style).

Uses matplotlib's Agg backend through the object-oriented API (no pyplot state); 2-D plots the plane, 3-D plots
the first two dimensions' regions under a 3-D view of the trajectories.
"""

from __future__ import annotations

from pathlib import Path

import torch

from lfd_torch.data import Demos
from lfd_torch.segmentation.segmentation import Segmentation

__all__ = ["plot_segmentation"]


def plot_segmentation(
    segmentation: Segmentation,
    demos: Demos,
    path: str | Path | None = None,
    *,
    grid_size: int = 200,
    margin: float = 0.1,
    title: str | None = None,
    unit: str | None = None,
):
    """Draw each demonstration coloured by step, the attractors g_m, and (2-D) the regions A_m.

    The region of step m is where p(x | A_m) is the largest step density and above a low level (so that space far
    from all steps is left blank).

    Args:
        segmentation: result of a segmenter on ``demos``.
        demos: the segmented demonstrations.
        path: where to save the figure (png/pdf); None only returns it.
        grid_size: region raster resolution per axis (2-D).
        margin: plot margin as a fraction of the data range.
        title: optional axes title.
        unit: unit of the state, shown on the axes (e.g. ``"mm"``); None leaves the labels bare.

    Returns:
        matplotlib Figure.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure

    from lfd_torch.data import Demos
    from lfd_torch.errors import ShapeMismatchError

    if not isinstance(demos, Demos) or demos.n_demos != segmentation.n_sequences or demos.dim != segmentation.dim:
        raise ShapeMismatchError(f"demos must be the {segmentation.n_sequences} segmented demonstrations "
                                 f"({segmentation.dim}-D), got {getattr(demos, 'n_demos', type(demos).__name__)}")
    if demos.dim < 2:
        raise ShapeMismatchError(f"plot_segmentation draws 2-D or 3-D paths (3-D shows the first three axes), "
                                 f"got {demos.dim}-D demonstrations")
    M = segmentation.n_steps
    d = demos.dim
    palette = [
        "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf",
    ]  # fmt: skip
    colors = [palette[m % len(palette)] for m in range(M)]
    fig = Figure(figsize=(5.5, 4.5))
    FigureCanvasAgg(fig)
    x_all = demos.samples()[0].to(torch.float64)
    lo, hi = x_all.min(0).values, x_all.max(0).values
    pad = (hi - lo).clamp_min(1e-9) * margin
    lo, hi = lo - pad, hi + pad
    if d == 2:
        ax = fig.add_subplot(1, 1, 1)
        gx = torch.linspace(float(lo[0]), float(hi[0]), grid_size, dtype=torch.float64, device="cpu")  # plotted
        gy = torch.linspace(float(lo[1]), float(hi[1]), grid_size, dtype=torch.float64, device="cpu")
        X, Y = torch.meshgrid(gx, gy, indexing="xy")
        pts = torch.stack([X, Y], -1)
        ld = segmentation.log_density(pts.to(segmentation.space_mean)).cpu()  # (G, G, M)
        best = ld.argmax(-1).to(torch.float64)
        level = torch.quantile(segmentation.log_density(x_all.to(segmentation.space_mean)).amax(-1).cpu(), 0.01) - 10.0
        best[ld.amax(-1) < level] = float("nan")
        ax.pcolormesh(X.numpy(), Y.numpy(), best.numpy(), cmap=ListedColormap(colors), vmin=-0.5, vmax=M - 0.5,
                      alpha=0.18, shading="auto")  # fmt: skip
    else:
        ax = fig.add_subplot(1, 1, 1, projection="3d")
    for i, seq in enumerate(demos.sequences()):
        for m, a, b in segmentation.pieces[i].tolist():
            piece = seq[a : min(b + 1, len(seq))].cpu().numpy()
            ax.plot(*piece[:, : min(d, 3)].T, color=colors[m], lw=1.4)
    g = segmentation.attractors.cpu().numpy()
    for m in range(M):
        ax.scatter(*g[m, : min(d, 3)], color=colors[m], edgecolor="k", s=60, marker="*", zorder=5, label=f"step {m + 1}")
    ax.legend(loc="best", fontsize=7)
    if title:
        ax.set_title(title)
    suffix = f" ({unit})" if unit else ""
    ax.set_xlabel("x_1" + suffix)
    ax.set_ylabel("x_2" + suffix)
    if d == 2:
        ax.set_aspect("equal", adjustable="box")
    else:
        ax.set_zlabel("x_3" + suffix)
    if path is not None:
        from lfd_torch.store import atomic_path  # results store convention: atomic writes

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=130, bbox_inches="tight", format=path.suffix.lstrip(".") or "png")
    return fig
