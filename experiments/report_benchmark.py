"""Publish a finished lasa_benchmark sweep: merged table, summary (mean +- std per method, train and test) and
Fig. 9 violins into the project's results/ (refused while a job of the sweep has no finished rows -- none written,
unreadable, or of another configuration than the job's -- unless --force). Skipped parts are reported on stderr.

    python experiments/lasa_benchmark.py +experiment=lasa_benchmark_paper hydra.sweep.dir=multirun/lasa_benchmark_paper
    python experiments/report_benchmark.py multirun/lasa_benchmark_paper --name lasa_benchmark_paper
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import torch  # noqa: E402

torch.set_num_threads(1)  # the busy-waiting default pool is ~10x slower on a loaded 2-core box
sys.path.insert(0, str(Path(__file__).resolve().parent))

from lasa_benchmark import summary, write_summary, write_violins  # noqa: E402

from lfd_torch.errors import StoreError  # noqa: E402
from lfd_torch.store import PartialSweepWarning, collect, staged_outputs, unfinished_jobs  # noqa: E402
from lfd_torch.store.paths import project_root  # noqa: E402


def _report(caught: list[warnings.WarningMessage]) -> None:
    """Print each warning once (both collects of the sweep warn about the same skipped parts)."""
    for message in dict.fromkeys(str(w.message) for w in caught):
        print(f"warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sweep", type=Path)
    ap.add_argument("--name", default="lasa_benchmark_paper", help="stem of the published files")
    ap.add_argument("--force", action="store_true", help="publish even if some jobs have no rows")
    args = ap.parse_args(argv)
    missing = unfinished_jobs(args.sweep)
    if missing and not args.force:
        names = ", ".join(str(m) for m in missing[:5]) + (" ..." if len(missing) > 5 else "")
        print(f"error: {len(missing)} job(s) of {args.sweep} have no finished results (none, unreadable, or of another "
              f"configuration: {names}); re-run the sweep or pass --force", file=sys.stderr)  # fmt: skip
        return 2
    results = Path(project_root()) / "results"
    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", PartialSweepWarning)
            table = collect(args.sweep)
            summ = summary(table) if len(table) else table.iloc[:0]  # computed before anything is written
            if not len(summ):
                raise StoreError(f"no finished rows under {args.sweep}: nothing published")
            with staged_outputs(results) as staging:  # table, summary and violins replace the published ones together
                written = [staging / "tables" / f"{args.name}.parquet"]
                collect(args.sweep, save_to=written[0])
                written += write_summary(summ, staging / "tables", f"{args.name}_summary")
                written += write_violins(table, staging / "figures" / f"{args.name}_violins.png")
    except StoreError as exc:
        _report(caught)
        print(f"error: {exc}", file=sys.stderr)
        return 2
    _report(caught)
    print(f"{len(table)} rows, {table['shape'].nunique()} shapes -> {results} (" + ", ".join(
        str(p.relative_to(staging)) for p in written) + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
