"""SEDS in the one-demonstration regime vs LPV-DS (not a test; prints a table).

    OMP_NUM_THREADS=1 python experiments/bench_seds.py [--shapes all | Angle NShape ...]
        [--methods seds_old seds lpvds] [--seed 0] [--json results.json] [--custom NAME '{"fit_seds": "kwargs"}']

The default shapes are the twelve of ``SHAPES``; ``--shapes all`` runs the 30 LASA shapes (about 2 minutes on
one core for the three default methods).

Protocol (the paper's, Sec. V-A): every 2nd sample of each LASA shape (``subsample(..., 2, keep_last=False)``),
train on demonstration 0, test on demonstrations 1-6. Per shape and method:

* ``K``: number of components; ``fit_s``: wall-clock fit time (one thread);
* ``E1``: test velocity error (:func:`lfd_torch.metrics.velocity_error`, mean over samples of ||x_dot - f(x)||,
  averaged over the six test demonstrations), mm/s;
* ``vmax``: max ||f(x)|| over the test states (mm/s), next to ``vdemo``, the max demonstrated test speed;
* ``reach``: how many of the 6 Euler rollouts (dt = 0.01 s, 3,000 steps = 30 s) from the test starts come within
  0.5 mm of the attractor (a rollout that diverges to NaN/Inf counts as not reaching); ``dfinal``: the largest
  distance to the attractor at the end of the six rollouts (mm).

Methods (``--methods``):

* ``seds_old``: the former ``fit_seds`` defaults, written out: MSE objective, K by the plain BIC of an EM fit of the
  joint data over K = 2..10 (``k_selection="bic"``), covariance floor ``reg=1e-4``, no prior on A_k;
* ``seds``: ``fit_seds`` with its current defaults (see :mod:`lfd_torch.ds.seds`): likelihood objective, K of
  LPV-DS's PC-GMM on the same data (``k_selection="pcgmm"``), covariance floor ``reg=1e-2``, prior N(-I, 10^2) on
  the entries of A_k in scaled units (``gain_prior=10``), L-BFGS with restarts;
* ``seds_mse``: current defaults but the MSE objective (the objective's effect at the same K);
* ``lpvds``: ``fit_lpvds(train, gmm=PCGMMFitter(), generator=g)`` (P-QLF, PC-GMM defaults).

Every fit of a shape gets the same ``torch.Generator().manual_seed(derive_seed("bench_seds", shape, seed))``, so
SEDS with ``k_selection="pcgmm"`` runs the very PC-GMM fit LPV-DS runs and gets the same K.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import json
import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from lfd_torch.data import LASA_NAMES, Demos, load_lasa
from lfd_torch.ds import StablePrimitive, fit_lpvds, fit_seds
from lfd_torch.errors import LfdError
from lfd_torch.gmm import PCGMMFitter
from lfd_torch.metrics import velocity_error
from lfd_torch.preprocess import subsample
from lfd_torch.rollout import rollout
from lfd_torch.utils import derive_seed

#: Default shapes: the ones named in the issue (Angle, NShape, Sshape, Snake, CShape, Multi_Models_3) and six others.
SHAPES = ("Angle", "NShape", "Sshape", "Snake", "CShape", "Multi_Models_3",
          "GShape", "JShape", "Khamesh", "Leaf_2", "Trapezoid", "WShape")  # fmt: skip

METHODS: dict[str, Callable[..., StablePrimitive]] = {
    "seds_old": lambda d, g: fit_seds(d, objective="mse", k_selection="bic", reg=1e-4, gain_prior=None,
                                         generator=g),
    "seds": lambda d, g: fit_seds(d, generator=g),
    "seds_mse": lambda d, g: fit_seds(d, objective="mse", generator=g),
    "lpvds": lambda d, g: fit_lpvds(d, gmm=PCGMMFitter(), generator=g),
}

DT, N_STEPS, POSITION_TOL = 0.01, 3000, 0.5


def evaluate(model: StablePrimitive, test: Demos) -> dict[str, float]:
    """E1, vmax and goal reaching on the test demonstrations."""
    with torch.no_grad():
        pred = model(test.positions)
    m = test.mask
    e1 = float(velocity_error(pred, test.velocities, m).mean())
    vmax = float(pred.norm(dim=-1)[m].max())
    vdemo = float(test.velocities.norm(dim=-1)[m].max())
    x0 = test.positions[:, 0]
    try:
        res = rollout(model, x0, DT, N_STEPS, attractor=model.attractor, position_tol=POSITION_TOL,
                      velocity_tol=math.inf)  # fmt: skip
        reach = int(res.converged.sum())
        dfinal = float((res.final_positions - model.attractor).norm(dim=-1).max())
    except LfdError:  # the rollout diverged (NaN/Inf)
        reach, dfinal = 0, math.inf
    return {"E1": e1, "vmax": vmax, "vdemo": vdemo, "reach": reach, "dfinal": dfinal}


def run(shapes: list[str], methods: list[str], seed: int) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    for shape in shapes:
        demos = subsample(load_lasa(shape), 2, keep_last=False)
        train, test = demos[[0]], demos[list(range(1, demos.n_demos))]
        for name in methods:
            g = torch.Generator().manual_seed(derive_seed("bench_seds", shape, seed))
            t0 = time.perf_counter()
            try:
                model = METHODS[name](train, g)
            except LfdError as err:  # typed failure of a fit: reported, not hidden
                rows.append({"shape": shape, "method": name, "error": f"{type(err).__name__}: {err}"})
                print(f"{shape:15s} {name:9s} FAILED {type(err).__name__}: {err}", flush=True)
                continue
            fit_s = time.perf_counter() - t0
            row: dict[str, object] = {"shape": shape, "method": name, "K": model.n_components, "fit_s": fit_s,
                                      **evaluate(model, test)}  # fmt: skip
            for key in ("objective", "k_selection", "n_effective", "fallback"):
                if key in model.info:
                    row[key] = model.info[key]
            rows.append(row)
            print(f"{shape:15s} {name:9s} K={row['K']:2d} E1={row['E1']:8.1f} vmax={row['vmax']:8.0f} "
                  f"(demo {row['vdemo']:4.0f}) reach={row['reach']}/6 dfinal={row['dfinal']:6.1f} fit={fit_s:6.2f}s",
                  flush=True)  # fmt: skip
    return rows


def table(rows: list[dict[str, object]], methods: list[str]) -> str:
    """Markdown table, one line per shape, the methods side by side; then per-method medians and totals."""
    by = {(r["shape"], r["method"]): r for r in rows}
    shapes = list(dict.fromkeys(r["shape"] for r in rows))
    head = "| shape | " + " | ".join(f"{m} K / E1 / vmax / reach / fit s" for m in methods) + " |"
    lines = [head, "|" + "---|" * (len(methods) + 1)]

    def cell(r: dict[str, object] | None) -> str:
        if r is None:
            return "-"
        if "error" in r:
            return "FAILED"
        return f"{r['K']} / {r['E1']:.1f} / {r['vmax']:.0f} / {r['reach']}/6 / {r['fit_s']:.1f}"

    for s in shapes:
        lines.append(f"| {s} | " + " | ".join(cell(by.get((s, m))) for m in methods) + " |")
    summary = []
    for m in methods:
        ok = [r for r in rows if r["method"] == m and "error" not in r]
        if not ok:
            summary.append("-")
            continue
        summary.append(f"median E1 {statistics.median(r['E1'] for r in ok):.1f}, max vmax "
                       f"{max(r['vmax'] for r in ok):.0f}, reach {sum(r['reach'] for r in ok)}/{6 * len(ok)}, "
                       f"total {sum(r['fit_s'] for r in ok):.0f} s")  # fmt: skip
    lines.append("| **all** | " + " | ".join(summary) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=list(SHAPES), help=f"LASA shapes, or 'all' ({len(LASA_NAMES)})")
    parser.add_argument("--methods", nargs="*", default=["seds_old", "seds", "lpvds"], choices=list(METHODS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--custom", nargs=2, action="append", default=[], metavar=("NAME", "JSON"),
                        help="an extra method: fit_seds with these keyword arguments (JSON), e.g. "
                        "--custom lik3 '{\"objective\": \"likelihood\", \"n_components\": 3}'")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None, help="also write the rows as JSON")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    for name, kwargs in args.custom:
        METHODS[name] = lambda d, g, kw=json.loads(kwargs): fit_seds(d, generator=g, **kw)
    methods = args.methods + [name for name, _ in args.custom]
    shapes = list(LASA_NAMES) if args.shapes == ["all"] else args.shapes
    rows = run(shapes, methods, args.seed)
    print()
    print(table(rows, methods))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
