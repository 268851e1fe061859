"""Benchmark of the non-parametric GMM fitters on LASA (CoRL-style split): time and number of components.

For each shape, the training set is demonstrations 0-3 (0-based), whose samples are stacked and subsampled
with a fixed stride to about ``--points`` samples (default 2,000: every 2nd sample). PC-GMM is also run on
about 1,000 points (every 4th sample). Each (method, shape, size) is fitted with ``--seeds`` seeds; the table
reports the median wall-clock and CPU (process) time per fit and the K of every seed. Single-threaded torch.

    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_gmm.py
    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_gmm.py --shapes Angle Snake --seeds 3 --json out.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable, Sequence

import torch

from lfd_torch.data import load_lasa
from lfd_torch.gmm import GMM, fit_damm, fit_em_bic, fit_pcgmm

SHAPES = ("Sshape", "Snake", "CShape", "NShape", "heee", "Angle")
TRAIN_DEMOS = [0, 1, 2, 3]


def training_samples(shape: str, points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(x (M, 2), x_dot (M, 2)) of demonstrations 0-3, every ceil(N / points)-th stacked sample, float64."""
    x, x_dot, _ = load_lasa(shape)[TRAIN_DEMOS].samples()
    stride = max(1, -(-x.shape[0] // points))
    return x[::stride].contiguous(), x_dot[::stride].contiguous()


def _time_fit(fit: Callable[..., GMM], x: torch.Tensor, x_dot: torch.Tensor, seed: int) -> tuple[float, float, int]:
    g = torch.Generator().manual_seed(seed)
    t0, c0 = time.perf_counter(), time.process_time()
    gmm = fit(x, x_dot, generator=g)
    return time.perf_counter() - t0, time.process_time() - c0, gmm.n_components


def run(
    shapes: Sequence[str] = SHAPES, seeds: int = 5, points: int = 2000, small_points: int = 1000, em_bic: bool = False
) -> list[dict]:
    """Fit every configuration and return one row per (method, shape, size)."""
    methods: list[tuple[str, int, Callable[..., GMM]]] = [
        ("pcgmm", small_points, fit_pcgmm),
        ("pcgmm", points, fit_pcgmm),
        ("damm", points, fit_damm),
    ]
    if em_bic:
        methods.append(("em_bic", points, lambda x, x_dot, generator: fit_em_bic(x, generator=generator)))
    rows = []
    for shape in shapes:
        for name, n, fit in methods:
            x, x_dot = training_samples(shape, n)
            fit(x, x_dot, generator=torch.Generator().manual_seed(10_000))  # warm-up (imports, caches)
            runs = [_time_fit(fit, x, x_dot, seed) for seed in range(seeds)]
            rows.append(
                dict(
                    method=name, shape=shape, n_points=int(x.shape[0]),
                    wall_s=statistics.median(r[0] for r in runs), cpu_s=statistics.median(r[1] for r in runs),
                    k=[r[2] for r in runs],
                )
            )  # fmt: skip
            r = rows[-1]
            print(f"{r['method']:7s} {r['shape']:7s} N={r['n_points']:5d}  wall {r['wall_s']:.3f} s  "
                  f"cpu {r['cpu_s']:.3f} s  K={r['k']}", flush=True)  # fmt: skip
    return rows


def format_table(rows: list[dict]) -> str:
    """Markdown table of the rows."""
    lines = ["| method | shape | N | median wall (s) | median CPU (s) | K per seed |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['shape']} | {r['n_points']} | {r['wall_s']:.3f} | {r['cpu_s']:.3f} | "
            f"{', '.join(map(str, r['k']))} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--shapes", nargs="+", default=list(SHAPES))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--points", type=int, default=2000)
    parser.add_argument("--small-points", type=int, default=1000)
    parser.add_argument("--em-bic", action="store_true", help="also time EM + BIC (K = 1..10)")
    parser.add_argument("--json", default=None, help="write the rows to this JSON file")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = run(args.shapes, args.seeds, args.points, args.small_points, args.em_bic)
    print()
    print(format_table(rows))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
