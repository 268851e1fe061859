"""Benchmark and accuracy study of the BP-GM-HMM segmentation (default settings of conf/segmentation/bp_gm_hmm.yaml).

Three parts (single-threaded torch; OMP_NUM_THREADS=1 recommended):

  lasa       wall-clock of ``segment`` on all 7 LASA demonstrations x 1000 samples (2-D) of several shapes: total
             seconds, sampler seconds, milliseconds per sweep (all chains batched), steps found.
  scaling    milliseconds per sweep against the subsampled length T (``max_samples``) and the number of
             sequences N, on one shape.
  synthetic  success rates on synthetic multi-step data with known switch points (``--seeds`` seeds per profile;
             3-5 legs, min-jerk or constant speed, 5 demonstrations, timing and corner jitter, white noise): a seed
             succeeds when the median boundary error is <= 3 % of the sequence length; also counted: exact number
             of steps, fewer steps than the truth.

    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py
    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts synthetic --seeds 20
    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts lasa scaling --json out.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from typing import Any

import torch

from lfd_torch.data import load_lasa
from lfd_torch.segmentation import segment
from lfd_torch.segmentation.synthetic import multi_step_demos

LASA_SHAPES = ("Multi_Models_1", "Multi_Models_2", "Multi_Models_3", "Multi_Models_4", "Angle", "Sshape")


def _timed(demos, seed: int, **kw: Any) -> tuple[float, Any]:
    g = torch.Generator().manual_seed(seed)
    t0 = time.perf_counter()
    seg = segment(demos, generator=g, **kw)
    return time.perf_counter() - t0, seg


def bench_lasa(shapes: tuple[str, ...] = LASA_SHAPES, seed: int = 0) -> list[dict[str, Any]]:
    """One row per shape: seconds for all 7 demonstrations with the default settings."""
    rows = []
    for shape in shapes:
        demos = load_lasa(shape)
        seconds, seg = _timed(demos, seed)
        n_iter = seg.sampler.trace.shape[1]
        rows.append({
            "part": "lasa", "shape": shape, "n_demos": demos.n_demos, "T_full": demos.max_length,
            "seconds": seconds, "sampler_seconds": seg.info["sampler_seconds"],
            "ms_per_sweep": 1e3 * seg.info["sampler_seconds"] / n_iter, "n_steps": seg.n_steps,
            "n_features": seg.sampler.n_features,
        })  # fmt: skip
    return rows


def bench_scaling(shape: str = "Angle", seed: int = 0, n_iterations: int = 10) -> list[dict[str, Any]]:
    """ms per sweep against T (max_samples) with N = 7, and against N with T = 60 (the default)."""
    demos = load_lasa(shape)
    rows = []
    for T in (50, 100, 200, 400):
        _, seg = _timed(demos, seed, max_samples=T, n_iterations=n_iterations)
        rows.append({"part": "scaling_T", "shape": shape, "T": T, "N": demos.n_demos,
                     "ms_per_sweep": 1e3 * seg.info["sampler_seconds"] / n_iterations})  # fmt: skip
    for N in (1, 2, 4, 7):
        _, seg = _timed(demos[list(range(N))], seed, max_samples=60, n_iterations=n_iterations)
        rows.append({"part": "scaling_N", "shape": shape, "T": 60, "N": N,
                     "ms_per_sweep": 1e3 * seg.info["sampler_seconds"] / n_iterations})  # fmt: skip
    return rows


def synthetic_study(seeds: int = 20, profiles: tuple[str, ...] = ("min_jerk", "constant")) -> list[dict[str, Any]]:
    """One row per (profile, seed): true and found step counts, median / max boundary error (fraction of T)."""
    rows = []
    for profile in profiles:
        for seed in range(seeds):
            data_gen = torch.Generator().manual_seed(10_000 + seed)
            syn = multi_step_demos(data_gen, n_demos=5, n_steps=3 + seed % 3, profile=profile)
            seconds, seg = _timed(syn.demos, seed)
            errs = []
            for i in range(syn.demos.n_demos):
                found = seg.boundaries[i, 1:-1]
                T = float(syn.demos.lengths[i])
                for t in syn.switch_times[i].tolist():
                    errs.append(float((found - t).abs().min()) / T if found.numel() else 1.0)
            med = statistics.median(errs)
            rows.append({
                "part": "synthetic", "profile": profile, "seed": seed, "true_steps": syn.n_steps,
                "found_steps": seg.n_steps, "median_error": med, "max_error": max(errs), "seconds": seconds,
                "success": med <= 0.03,
            })  # fmt: skip
    return rows


def summarize_synthetic(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for profile in sorted({r["profile"] for r in rows}):
        rs = [r for r in rows if r["profile"] == profile]
        n = len(rs)
        out.append({
            "profile": profile, "seeds": n,
            "all_switches_found (median err <= 3%)": sum(r["success"] for r in rs) / n,
            "exact_steps": sum(r["found_steps"] == r["true_steps"] for r in rs) / n,
            "fewer_steps": sum(r["found_steps"] < r["true_steps"] for r in rs) / n,
            "median_of_median_error": statistics.median(r["median_error"] for r in rs),
            "median_seconds": statistics.median(r["seconds"] for r in rs),
        })  # fmt: skip
    return out


def _print(rows: list[dict[str, Any]]) -> None:
    if not rows:
        return
    keys = list(rows[0])
    print(" | ".join(keys))
    for r in rows:
        print(" | ".join(f"{r[k]:.4g}" if isinstance(r[k], float) else str(r[k]) for k in keys))
    print()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", nargs="+", default=["lasa", "scaling", "synthetic"],
                        choices=["lasa", "scaling", "synthetic"])  # fmt: skip
    parser.add_argument("--shapes", nargs="+", default=list(LASA_SHAPES))
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--json", type=str, default=None, help="write all rows to this JSON file")
    args = parser.parse_args()
    torch.set_num_threads(1)
    result: dict[str, Any] = {}
    if "lasa" in args.parts:
        result["lasa"] = bench_lasa(tuple(args.shapes))
        _print(result["lasa"])
    if "scaling" in args.parts:
        result["scaling"] = bench_scaling()
        _print(result["scaling"])
    if "synthetic" in args.parts:
        rows = synthetic_study(args.seeds)
        result["synthetic"] = rows
        result["synthetic_summary"] = summarize_synthetic(rows)
        _print(rows)
        _print(result["synthetic_summary"])
    if args.json:
        from lfd_torch.store import atomic_write

        atomic_write(args.json, lambda p: p.write_text(json.dumps(result, indent=2)))


if __name__ == "__main__":
    main()
