"""Markdown summary of a collected ``lasa_primitives`` table (one row per shape x method).

    python -m lfd_torch.store.collect multirun/lasa_primitives/<date>/<time> --out results/tables/lasa_primitives_corl.parquet
    python experiments/report_primitives.py results/tables/lasa_primitives_corl.parquet [--split test]
        [--method lpvds_pqlf] [--baseline seds]

For every (shape, method) the per-demonstration metrics of ``split`` are averaged over the demonstrations of a
seed, then over the seeds (mean; the spread over seeds is shown as +- one standard deviation for RMSE):

    RMSE  root-mean-square velocity error (mm/s)      e_dot  mean |1 - cos| (E2, dimensionless)
    DTWD  DTW distance of the rollout (mm)             K      number of components (mean over seeds)
    fit   learning time per fit (s; median over seeds) certified  every fit returned a certified model

A fit that failed (``status`` not ``ok``) counts as not certified and its metrics are missing. The last line
counts the shapes where ``--method`` is no worse than ``--baseline`` on both the mean RMSE and the mean e_dot.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # no torch here; keeps any BLAS user below single-threaded
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pandas as pd  # noqa: E402

__all__ = ["summarise", "count_no_worse", "markdown", "main"]


def summarise(table: pd.DataFrame, split: str = "test") -> pd.DataFrame:
    """Per (shape, method) summary of one split of a collected table.

    Args:
        table: collected ``lasa_primitives`` rows (one per experiment/shape/method/fold/seed/trajectory).
        split: ``"train"`` or ``"test"``.

    Returns:
        DataFrame indexed by (shape, method) with columns RMSE, RMSE_std, e_dot, DTWD, K, fit_s, certified,
        n_seeds, n_failed.
    """
    rows = table[table["split"] == split]
    if rows.empty:
        raise ValueError(f"no rows with split == {split!r}")
    ok = rows["status"] == "ok"
    cert = ok & (rows["max_margin"] < 0)
    rows = rows.assign(_cert=cert)
    per_seed = rows.groupby(["shape", "method", "seed"]).agg(
        RMSE=("RMSE", "mean"), e_dot=("E2", "mean"), DTWD=("DTWD", "mean"), K=("n_components", "first"),
        fit_s=("fit_time_s", "first"), certified=("_cert", "all"),
    )  # fmt: skip
    g = per_seed.groupby(["shape", "method"])
    out = pd.DataFrame({
        "RMSE": g["RMSE"].mean(), "RMSE_std": g["RMSE"].std(ddof=0), "e_dot": g["e_dot"].mean(),
        "DTWD": g["DTWD"].mean(), "K": g["K"].mean(), "fit_s": g["fit_s"].median(),
        "certified": g["certified"].all(), "n_seeds": g.size(),
        "n_failed": g["RMSE"].apply(lambda s: int(s.isna().sum())),
    })  # fmt: skip
    return out


def count_no_worse(summary: pd.DataFrame, method: str, baseline: str) -> tuple[int, int, list[str]]:
    """Shapes where ``method`` has mean RMSE <= and mean e_dot <= those of ``baseline``.

    Returns:
        (count, number of shapes with both methods, the shapes that count).
    """
    shapes = sorted(set(summary.xs(method, level="method").index) & set(summary.xs(baseline, level="method").index))
    good = []
    for s in shapes:
        a, b = summary.loc[(s, method)], summary.loc[(s, baseline)]
        if a["RMSE"] <= b["RMSE"] and a["e_dot"] <= b["e_dot"] and a["certified"]:
            good.append(s)
    return len(good), len(shapes), good


def _fmt(v: float, digits: int = 3) -> str:
    return "nan" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}g}"


def markdown(summary: pd.DataFrame) -> str:
    """The summary as a GitHub markdown table."""
    lines = [
        "| shape | method | RMSE (mm/s) | e_dot | DTWD (mm) | K | fit (s) | certified |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (shape, method), r in summary.iterrows():
        cert = "yes" if r["certified"] else f"NO ({int(r['n_failed'])} failed)"
        lines.append(
            f"| {shape} | {method} | {_fmt(r['RMSE'], 4)} ± {_fmt(r['RMSE_std'], 2)} | {_fmt(r['e_dot'])} | "
            f"{_fmt(r['DTWD'], 4)} | {r['K']:.1f} | {_fmt(r['fit_s'])} | {cert} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("table", type=Path, help="collected .parquet (or .csv) table")
    parser.add_argument("--split", default="test", choices=("train", "test"))
    parser.add_argument("--method", default="lpvds_pqlf")
    parser.add_argument("--baseline", default="seds")
    args = parser.parse_args(argv)
    table = pd.read_parquet(args.table) if args.table.suffix == ".parquet" else pd.read_csv(args.table)
    summary = summarise(table, args.split)
    n_seeds = sorted(set(summary["n_seeds"].tolist()))
    print(f"{args.table} ({args.split} split; seeds per cell: {n_seeds})\n")
    print(markdown(summary))
    if args.method in summary.index.get_level_values("method") and args.baseline in summary.index.get_level_values(
        "method"
    ):
        n, total, good = count_no_worse(summary, args.method, args.baseline)
        print(f"\n{args.method} RMSE and e_dot <= {args.baseline} on {n} of {total} shapes: {', '.join(good)}")
    print(f"all fits certified: {bool(summary['certified'].all())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
