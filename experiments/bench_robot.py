"""Benchmarks of the Baxter scooping stack (issue 10): batched FK + Jacobian, and disturbed MuJoCo trials.

* ``kinematics``: :meth:`~lfd_torch.robot.BaxterArm.pose_and_jacobian` of 10,000 random joint configurations in
  float32 (target <= 50 ms on 2 cores), median of ``--repeats`` timed calls after a warm-up; float64 alongside.
* ``trials``: ``--trials`` disturbed trials (default 500) of the learned task in one modulation mode, batched as in
  ``experiments/scooping.py`` (one ``MjData`` per trial, one engine ``step_batch`` per 10 ms tick, the trials split
  over ``--workers`` forked processes; target <= 5 min on 2 cores).

    python experiments/bench_robot.py                         # both, JSON into outputs/bench_robot/
    python experiments/bench_robot.py --only kinematics
    python experiments/bench_robot.py --publish               # results/tables/scooping_bench.json

The allocator is set as ``make bench`` sets it for the engine benchmark (``MALLOC_MMAP_THRESHOLD_=33554432
MALLOC_TRIM_THRESHOLD_=1073741824``, here through ``mallopt`` at start-up, recorded in the JSON): without it glibc
unmaps the 10,000-row temporaries of every call and faults them in again, which made the float32 FK + Jacobian
60-68 ms instead of 35-48 ms in our runs.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

torch.set_num_threads(int(os.environ.get("LFD_THREADS", "1")))


def keep_large_allocations() -> bool:
    """glibc mallopt: serve blocks below 32 MiB from the heap and trim it only above 1 GiB (False off glibc)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    return bool(libc.mallopt(m_mmap_threshold, 32 * 1024 * 1024)) and bool(
        libc.mallopt(m_trim_threshold, 1024 * 1024 * 1024))

from lfd_torch.robot import BaxterArm
from lfd_torch.robot.trials import SuccessCriteria, plan_disturbances, run_trials, start_configurations
from lfd_torch.store import atomic_write
from lfd_torch.store.paths import project_root
from lfd_torch.utils import derive_seed


def bench_kinematics(n: int, repeats: int) -> dict:
    arm = BaxterArm()
    g = torch.Generator().manual_seed(0)
    out = {}
    for dtype in (torch.float32, torch.float64):
        lo, hi = arm.lower(dtype), arm.upper(dtype)
        q = lo + (hi - lo) * torch.rand(n, 7, generator=g, dtype=dtype)
        arm.pose_and_jacobian(q)  # warm-up: chain build and caches
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            arm.pose_and_jacobian(q)
            times.append(time.perf_counter() - t0)
        out[str(dtype).replace("torch.", "")] = {"n": n, "median_ms": 1e3 * statistics.median(times),
                                                 "min_ms": 1e3 * min(times), "repeats": repeats}  # fmt: skip
    return out


def bench_trials(n: int, mode: str, seed: int, budget_s: float, workers: int) -> dict:
    """``n`` disturbed trials of the ``conf/scooping.yaml`` task in one mode (the experiment's settings)."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    here = Path(__file__).resolve().parent
    sys.path.insert(0, str(here))
    import scooping

    with initialize_config_dir(config_dir=str(here.parent / "conf"), version_base="1.3"):
        cfg = compose("scooping", overrides=[f"seed={seed}", f"budget_s={budget_s}", f"workers={workers}"])
    robot = instantiate(cfg.robot, _convert_="all")
    t0 = time.perf_counter()
    task = scooping.learn(cfg, robot)
    learn_s = time.perf_counter() - t0
    ctl = scooping.controllers(cfg, task, robot)[mode]
    q_starts = start_configurations(task, robot.arm, int(cfg.starts.n), radius=float(cfg.starts.radius),
                                    height=float(cfg.starts.height))  # fmt: skip
    g = torch.Generator().manual_seed(derive_seed(cfg.experiment, "disturbances", cfg.seed))
    plan = plan_disturbances(n, g, **OmegaConf.to_container(cfg.disturbances, resolve=True))
    q0 = q_starts[torch.arange(n) % q_starts.shape[0]]
    crit = SuccessCriteria(**OmegaConf.to_container(cfg.criteria, resolve=True))
    t0 = time.perf_counter()
    res = run_trials(task, ctl, robot.plant, q0, disturbances=plan, budget_s=budget_s, jump_seed=seed,
                     criteria=crit, away=float(cfg.away), workers=workers)  # fmt: skip
    wall = time.perf_counter() - t0
    ok = sum(r["success"] for r in res.rows)  # strict: every forbidden contact fails, pushed or not
    lenient = sum(r["lenient_success"] for r in res.rows)  # diagnostic: contacts begun by a force pulse excused
    fired = sum(r["disturbance"] != "none" for r in res.rows)
    return {"trials": n, "disturbed": fired, "mode": mode, "workers": workers, "successes": ok,
            "lenient_successes": lenient, "wall_s": wall,
            "learn_s": learn_s, "simulated_s": float(res.lengths.sum()) * res.dt, "budget_s": budget_s}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=("kinematics", "trials"), default=None)
    ap.add_argument("--configs", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--trials", type=int, default=500)
    ap.add_argument("--mode", default="full")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--budget", type=float, default=40.0)
    ap.add_argument("--workers", type=int, default=2, help="forked processes (2 cores: 2)")
    ap.add_argument("--publish", action="store_true")
    args = ap.parse_args(argv)
    report: dict = {"python": sys.version.split()[0], "torch": torch.__version__, "threads": torch.get_num_threads(),
                    "cpus": os.cpu_count(), "machine": platform.machine(),
                    "large_allocations_kept": keep_large_allocations()}  # fmt: skip
    if args.only in (None, "kinematics"):
        report["kinematics"] = bench_kinematics(args.configs, args.repeats)
        print("FK + Jacobian of %d configurations: float32 %.1f ms, float64 %.1f ms (median)" % (
            args.configs, report["kinematics"]["float32"]["median_ms"], report["kinematics"]["float64"]["median_ms"]))
    if args.only in (None, "trials"):
        report["trials"] = bench_trials(args.trials, args.mode, args.seed, args.budget, args.workers)
        t = report["trials"]
        print("%d trials (%d disturbed), mode %s: %.1f s wall, %d successes" % (
            t["trials"], t["disturbed"], t["mode"], t["wall_s"], t["successes"]))
    root = Path(project_root()) / "results" / "tables" if args.publish else Path("outputs") / "bench_robot"
    path = root / ("scooping_bench.json" if args.publish else "bench_robot.json")
    atomic_write(path, lambda p: p.write_text(json.dumps(report, indent=2) + "\n"))
    print("wrote", path)
    return report


if __name__ == "__main__":
    main()
