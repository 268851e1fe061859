"""Benchmark of the foundation's batched kernels (not a test; prints medians).

    python experiments/bench_core.py [--repeats 5] [--threads 1] [--json results/tables/bench_core.json]

1. E1-E3 over all 210 LASA demonstrations (30 shapes x 7 demos x 1000 samples).
2. Squared-cost DTW of 210 pairs of 1000-sample trajectories: ours (batched torch) vs dtaidistance's C code.
3. Batched rollout: 10,000 starts x 2,000 Euler steps of an 8-component linear-mixture field in float32, vs a plain
   eager loop (one start at a time, one Python step at a time) timed on a few starts and extrapolated.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import json
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from lfd_torch.data import LASA_NAMES, Demos, load_lasa
from lfd_torch.ds import LPVDS
from lfd_torch.gmm import GMM
from lfd_torch.metrics import cosine_dissimilarity, dtw_distance, swept_area, velocity_error
from lfd_torch.rollout import rollout


def median_time(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def all_lasa() -> Demos:
    return Demos.concat([load_lasa(name) for name in LASA_NAMES])


def bench_metrics(demos: Demos, repeats: int) -> dict[str, float]:
    x, v, mask = demos.positions, demos.velocities, demos.mask
    # a stand-in model output: central-difference velocities and a shifted copy of the path as the "rollout"
    g = torch.Generator().manual_seed(0)
    pred_v = v + 5.0 * torch.randn(v.shape, generator=g, dtype=v.dtype)
    rolled = x + torch.randn(x.shape[0], 1, x.shape[2], generator=g, dtype=x.dtype)

    def run() -> tuple[torch.Tensor, ...]:
        return (velocity_error(pred_v, v, mask), cosine_dissimilarity(pred_v, v, mask), swept_area(rolled, x, mask))

    t, (e1, e2, e3) = median_time(run, repeats)
    print(f"[metrics] E1+E2+E3 over {x.shape[0]} demos x {x.shape[1]} samples (float64): median {t * 1e3:.1f} ms "
          f"(goal <= 200 ms); means E1={e1.mean():.3f} E2={e2.mean():.4f} E3={e3.mean():.3f}")  # fmt: skip
    return {"metrics_s": t, "n_demos": x.shape[0], "n_samples": x.shape[1]}


def bench_dtw(demos: Demos, repeats: int) -> dict[str, float]:
    from dtaidistance import dtw_ndim

    a = demos.positions
    b = torch.roll(demos.positions, shifts=1, dims=0)  # pair each demo with the previous one in the list
    a_np = [np.ascontiguousarray(r.numpy()) for r in a]
    b_np = [np.ascontiguousarray(r.numpy()) for r in b]
    t_ours, ours = median_time(lambda: dtw_distance(a, b, squared_cost=True), repeats)
    t_ref, ref = median_time(
        lambda: np.array([dtw_ndim.distance_fast(p, q, use_pruning=False) for p, q in zip(a_np, b_np)]), repeats
    )
    diff = np.abs(ours.numpy() - ref).max()
    print(f"[dtw] {a.shape[0]} pairs x {a.shape[1]} samples, squared cost: ours {t_ours:.3f} s, dtaidistance (C) "
          f"{t_ref:.3f} s, ratio {t_ours / t_ref:.2f}x (goal <= 3x); max |diff| {diff:.2e}")  # fmt: skip
    t_euc, _ = median_time(lambda: dtw_distance(a, b), repeats)
    print(f"[dtw] same pairs, Euclidean local cost (DTWD of the LPV-DS literature): ours {t_euc:.3f} s")
    return {"dtw_squared_s": t_ours, "dtw_dtaidistance_s": t_ref, "dtw_ratio": t_ours / t_ref,
            "dtw_max_abs_diff": float(diff), "dtw_euclidean_s": t_euc}  # fmt: skip


def linear_mixture(n_components: int, d: int, generator: torch.Generator, dtype: torch.dtype) -> tuple[LPVDS, Tensor]:
    """An LPV-DS with K random components, f(x) = sum_k gamma_k(x) A_k (x - g), A_k + A_k^T < 0 (certified, P = I).

    Built directly from parameters (no fitting), so the benchmark times the package's own field evaluation.
    """
    f64 = dict(dtype=torch.float64)
    means = 20 * torch.randn(n_components, d, generator=generator, **f64)
    R = torch.randn(n_components, d, d, generator=generator, **f64)
    covariances = 10 * (R @ R.transpose(1, 2)) + 20 * torch.eye(d, **f64)
    weights = torch.full((n_components,), 1.0 / n_components, **f64)
    M = torch.randn(n_components, d, d, generator=generator, **f64)
    S = torch.randn(n_components, d, d, generator=generator, **f64)
    A = -(M @ M.transpose(1, 2) + 0.5 * torch.eye(d, **f64)) + (S - S.transpose(1, 2))
    g = torch.zeros(d, **f64)
    eye = torch.eye(d, **f64)
    model = LPVDS(GMM(weights, means, covariances), A, g, eye, eye.expand(n_components, d, d).clone())
    model = model.to(dtype=dtype)
    return model, model.attractor


def bench_rollout(repeats: int, n_starts: int = 10_000, n_steps: int = 2_000) -> dict[str, float]:
    gen = torch.Generator().manual_seed(1)
    field, g = linear_mixture(8, 2, gen, torch.float32)
    x0 = 40 * torch.rand(n_starts, 2, generator=gen, dtype=torch.float32) - 20
    dt = 0.01
    # Full length for the comparison with the eager loop (same work: no row stops), then with per-row stopping.
    t_batched, res = median_time(lambda: rollout(field, x0, dt, n_steps, method="euler"), repeats)
    t_stop, res_stop = median_time(
        lambda: rollout(field, x0, dt, n_steps, method="euler", attractor=g, position_tol=1e-3, velocity_tol=1e-3),
        repeats,
    )
    n_eager = 5

    def eager() -> torch.Tensor:
        out = torch.empty(n_eager, n_steps + 1, 2)
        for b in range(n_eager):
            x = x0[b : b + 1].clone()
            out[b, 0] = x[0]
            for k in range(n_steps):
                x = x + dt * field(x)
                out[b, k + 1] = x[0]
        return out

    t_eager, eager_out = median_time(eager, max(1, repeats // 2))
    t_eager_full = t_eager / n_eager * n_starts
    # same numbers as the batched engine on the rows that did not stop early
    print(f"[rollout] {n_starts} starts x {n_steps} Euler steps, 8-component LPV-DS, float32, "
          f"{torch.get_num_threads()} thread(s): batched {t_batched:.3f} s (goal <= 2 s); plain eager loop "
          f"{t_eager / n_eager * 1e3:.0f} ms per start -> {t_eager_full:.0f} s extrapolated; ratio "
          f"{t_eager_full / t_batched:.0f}x; with stopping at 1e-3: {t_stop:.3f} s, converged "
          f"{int(res_stop.converged.sum())}/{n_starts}, mean length {res_stop.lengths.float().mean():.0f}; "
          f"first-start max |batched - eager| {float((res.positions[0, :int(res.lengths[0])] - eager_out[0, :int(res.lengths[0])]).abs().max()):.1e}")  # fmt: skip
    return {"rollout_s": t_batched, "eager_ms_per_start": t_eager / n_eager * 1e3, "eager_extrapolated_s": t_eager_full,
            "rollout_ratio": t_eager_full / t_batched, "rollout_stop_s": t_stop,
            "rollout_stop_mean_length": float(res_stop.lengths.float().mean())}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--only", choices=["metrics", "dtw", "rollout"], default=None)
    parser.add_argument("--json", default=None, help="also write the medians (s) to this JSON file")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    demos = all_lasa()
    out: dict[str, float] = {}
    if args.only in (None, "metrics"):
        out |= bench_metrics(demos, args.repeats)
    if args.only in (None, "dtw"):
        out |= bench_dtw(demos, args.repeats)
    if args.only in (None, "rollout"):
        out |= bench_rollout(args.repeats)
    if args.json:
        from lfd_torch.store import atomic_save
        from lfd_torch.store.manifest import git_sha

        record = {"bench_core": out, "provenance": {"git_sha": git_sha(), "repeats": args.repeats,
                                                   "threads": args.threads, "load_average": os.getloadavg()[0]}}
        atomic_save(args.json, lambda tmp: tmp.write_text(json.dumps(record, indent=2) + "\n"), what="benchmark table")


if __name__ == "__main__":
    main()
