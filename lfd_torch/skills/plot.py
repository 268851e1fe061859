"""Figures of the skill engine (2-D): entropy maps (paper Fig. 5) and task rollouts (Figs 6-8).

Every function draws into a new matplotlib figure and writes it atomically with
:func:`lfd_torch.viz.save_figure`; the data come from the library, the demonstrations and engine rollouts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from lfd_torch.errors import PlotError  # noqa: E402
from lfd_torch.modulation import Branch, renyi_entropy  # noqa: E402
from lfd_torch.viz import save_figure  # noqa: E402

__all__ = ["plot_entropy", "plot_rollout_panels"]

_BRANCH_COLOURS = {int(Branch.UNMODULATED): "tab:blue", int(Branch.SMALL_SCALE): "tab:green",
                   int(Branch.LARGE_SCALE): "tab:red", int(Branch.AT_GOAL): "black"}  # fmt: skip


def _check_2d(library: Any) -> None:
    if library.dim != 2:
        raise PlotError(f"these figures are 2-D; the library has dimension {library.dim}")


def _extent(library: Any, demos: Any, margin: float = 0.15) -> tuple[float, float, float, float]:
    x = demos.samples()[0]
    lo, hi = x.amin(0), x.amax(0)
    pad = margin * (hi - lo).max()
    return float(lo[0] - pad), float(hi[0] + pad), float(lo[1] - pad), float(hi[1] + pad)


def plot_entropy(library: Any, demos: Any, path: str | Path, *, grid_size: int = 150, title: str | None = None) -> Path:
    """One panel per step: H2 of its primitive over the plane (log colour scale of H2 - min H2 + 1), the step's
    training states and g_m, and the contour H2 = H2(x_r) (the small-scale threshold)."""
    _check_2d(library)
    x0, x1, y0, y1 = _extent(library, demos)
    f = {"dtype": library.dtype, "device": library.device}
    gx, gy = torch.meshgrid(torch.linspace(x0, x1, grid_size, **f), torch.linspace(y0, y1, grid_size, **f), indexing="xy")
    grid = torch.stack([gx, gy], -1)
    M = library.n_steps
    cols = min(M, 4)
    rows = math.ceil(M / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.0 * rows), squeeze=False, layout="constrained")
    for m, skill in enumerate(library.skills):
        ax = axes[m // cols][m % cols]
        h2 = renyi_entropy(skill.primitive, grid.reshape(-1, 2)).reshape(grid_size, grid_size)
        lifted = (h2 - h2.min() + 1.0).cpu()  # >= 1: H2 grows quadratically off the data, a log scale shows both
        ax.imshow(lifted, origin="lower", extent=(x0, x1, y0, y1), cmap="viridis", aspect="auto",
                  norm=matplotlib.colors.LogNorm(vmin=1.0, vmax=float(lifted.max())))  # fmt: skip
        ax.contour(gx.cpu(), gy.cpu(), h2.cpu(), levels=[float(skill.h2_ref)], colors="white", linewidths=0.8)
        xs = skill.train_positions.cpu()
        ax.plot(xs[:, 0], xs[:, 1], ".", color="tab:orange", ms=1.5)
        g = skill.attractor.cpu()
        ax.plot(g[0], g[1], "r*", ms=9)
        ax.set_title(f"step {m + 1}", fontsize=9)
        ax.set_xlabel("x (mm)", fontsize=8)
        if m % cols == 0:  # one y label per row: the panels share the extent
            ax.set_ylabel("y (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
    for k in range(M, rows * cols):
        axes[k // cols][k % cols].axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def plot_rollout_panels(
    panels: Sequence[tuple[str, Any, Any]],
    demos: Any,
    path: str | Path,
    *,
    max_rows: int = 60,
    title: str | None = None,
) -> Path:
    """Side-by-side panels of engine rollouts.

    Args:
        panels: ``(title, library, EngineRollout)`` per panel; each rollout's samples are coloured by the branch
            taken (blue unmodulated, green small-scale, red large-scale), pushes are marked by crosses, attractors
            by stars, the demonstrations drawn in grey.
        demos: the demonstrations.
        path: output file.
        max_rows: at most this many rollouts per panel (the first ones).
    """
    if not panels:
        raise PlotError("no panels to draw")
    for _, lib, _ in panels:
        _check_2d(lib)
    x0, x1, y0, y1 = _extent(panels[0][1], demos, margin=0.6)
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.4), squeeze=False)
    for ax, (name, lib, out) in zip(axes[0], panels):
        for seq in demos.sequences():
            s = seq.cpu()
            ax.plot(s[:, 0], s[:, 1], color="0.75", lw=1.5, zorder=1)
        res = out.result
        B = min(res.n_starts, max_rows)
        for b in range(B):
            n = int(res.lengths[b])
            xy = res.positions[b, :n].cpu()
            br = out.branches[b, :n].cpu()
            ax.plot(xy[:, 0], xy[:, 1], color="0.3", lw=0.4, zorder=2)
            for code, colour in _BRANCH_COLOURS.items():
                sel = br == code
                if bool(sel.any()) and code != int(Branch.AT_GOAL):
                    ax.plot(xy[sel, 0], xy[sel, 1], ".", color=colour, ms=1.2, zorder=3)
            ax.plot(xy[0, 0], xy[0, 1], "o", mfc="none", mec="k", ms=4, zorder=4)
        for p in out.pushes:
            if p["applied"] and p["row"] < B:
                xy = res.positions[p["row"], p["sample"]].cpu()
                ax.plot(xy[0], xy[1], "x", color="tab:purple", ms=5, zorder=5)
        g = lib.attractors.cpu()
        ax.plot(g[:, 0], g[:, 1], "r*", ms=8, zorder=6)
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_title(name, fontsize=9)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x (mm)", fontsize=8)
        ax.set_ylabel("y (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    out_path = save_figure(fig, path)
    plt.close(fig)
    return out_path
