"""Benchmark of the skill decision engine (not a test; prints medians, optionally writes JSON).

    python experiments/bench_engine.py [--shape Multi_Models_3] [--training all] [--repeats 7] [--dtype float64]
                                       [--parts tick,batch,rollout] [--json results/tables/bench_engine.json]

Run it as ``make bench`` does, with ``MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=1073741824``: without
them glibc returns and re-requests the large temporaries of every batched tick (a page-fault storm that made the
10,000-state tick 2-4x slower in our runs).

Every timing is a wall-clock median (the goals are wall-clock); every part also reports the
median CPU time of the benchmark's thread (``*_cpu_*``), and the JSON records the 1-minute load average before and
after: on a shared machine the wall times grow with the load while the CPU times mostly do not.

On a library learned from LASA ``--shape`` (all seven demonstrations by default: 2 routes, ~16-18 steps):
1. single-state tick through the py_trees tree (route, step completion, subtask test, primitive, entropy,
   modulation, rate floor and speed cap), mode ``full``: median over 2,000 ticks of states along the demonstrations,
   with the default engine (``tick_us_median``, eager; goal: <= 200 us, a 5 kHz control loop) and, unless
   ``--no-compile``, with the velocity's tensor part compiled (``SkillEngine(compile_tick=True)``,
   ``tick_us_median_compiled``). On a CPU the eager tick is the faster one: its tensor part is ~10 small kernels,
   fewer microseconds than the entry of a compiled call;
2. batched tick of 10,000 states (vectorised decisions + velocities), mode ``full`` (goal: <= 10 ms): uniform states
   in a box twice the data span as new tasks (the tree picks the route: every row in a route's first step), and the
   same states with a random route and progress (rows spread over every step: one group per step in the
   step-grouped velocity path; ``batch_10k_spread_steps_present`` says how many), medians over 3 x ``--repeats`` ticks;
3. 1,000-start full-task rollout with random large and small pushes, dt = 10 ms, 60 s budget, mode ``full``
   (goal: <= 5 s), with the fraction of rows that finished and the median / max task time.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from lfd_torch.data import load_lasa
from lfd_torch.segmentation import segment
from lfd_torch.skills import SkillEngine, SkillLibrary, random_pushes
from lfd_torch.store import atomic_write
from lfd_torch.utils import derive_seed


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shape", default="Multi_Models_3")
    ap.add_argument("--training", choices=["one", "all"], default="all")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--no-compile", action="store_true", help="skip the compiled single-state tick")
    ap.add_argument("--parts", default="tick,batch,rollout",
                    help="comma-separated subset of tick, batch, rollout to run (the JSON holds only those)")
    args = ap.parse_args(argv)
    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    if not parts or not parts <= {"tick", "batch", "rollout"}:
        ap.error(f"--parts must be a comma-separated subset of tick,batch,rollout, got {args.parts!r}")
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)

    demos = load_lasa(args.shape)
    train = demos[[0]] if args.training == "one" else demos
    g = torch.Generator().manual_seed(derive_seed("bench_engine", args.shape, args.training))
    seg = segment(train, generator=g)
    lib = SkillLibrary.learn(train, seg, generator=g, check=False)
    if dtype != torch.float64:  # learn in float64, run the engine in the requested dtype
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            lib.save(tmp)
            lib = SkillLibrary.load(tmp, dtype=dtype)
    eng = SkillEngine(lib, "full")
    out: dict = {"shape": args.shape, "training": args.training, "dtype": args.dtype, "steps": lib.n_steps,
                 "routes": len(lib.routes), "threads": args.threads,
                 "load_average_before": os.getloadavg()[0]}  # fmt: skip
    if "tick" in parts:
        out.update(bench_tick(eng, lib, demos, dtype, compiled=not args.no_compile))
    if "batch" in parts:
        out.update(bench_batch(eng, lib, demos, dtype, args.repeats))
    if "rollout" in parts:
        out.update(bench_rollout(eng, lib, demos, dtype, args.repeats))
    out["load_average_after"] = os.getloadavg()[0]
    print(json.dumps(out, indent=2))
    if args.json is not None:
        atomic_write(args.json, lambda p: p.write_text(json.dumps(out, indent=2) + "\n"))
    return out


def _box(demos, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Centre and span of the demonstrations (uniform states in centre +- span: a box twice the data span)."""
    x_all = demos.samples()[0].to(dtype)
    lo, hi = x_all.amin(0), x_all.amax(0)
    return 0.5 * (lo + hi), hi - lo


def bench_tick(eng: SkillEngine, lib: SkillLibrary, demos, dtype: torch.dtype, *, compiled: bool) -> dict:
    """1. single-state tick through the py_trees tree, eager and (``compiled``) with a compiled velocity."""
    out: dict = {"tick_compiled": compiled}
    engines = [("tick_us_median", eng)]
    if compiled:
        engines.append(("tick_us_median_compiled", SkillEngine(lib, "full", compile_tick=True)))
    xs = demos.samples()[0].to(dtype)
    idx = torch.randperm(xs.shape[0], generator=torch.Generator().manual_seed(0))[:2000]
    states = xs[idx]
    step0 = lib.routes[0][0]
    for name, e in engines:
        for x in states[:50]:
            e.tick(x, step=step0)
        times, cpu = [], []
        for x in states:
            t0, c0 = time.perf_counter(), time.thread_time()
            e.tick(x, step=step0)
            times.append(time.perf_counter() - t0)
            cpu.append(time.thread_time() - c0)
        out[name] = 1e6 * statistics.median(times)
        out[name.replace("tick_us", "tick_cpu_us")] = 1e6 * statistics.median(cpu)
    return out


def bench_batch(eng: SkillEngine, lib: SkillLibrary, demos, dtype: torch.dtype, repeats: int) -> dict:
    """2. batched tick of 10,000 states: new tasks, and rows spread over every step of both routes."""
    c, h = _box(demos, dtype)
    n = 10_000
    X = c + h * (2 * torch.rand((n, lib.dim), generator=torch.Generator().manual_seed(1), dtype=dtype) - 1)
    g = torch.Generator().manual_seed(4)
    lengths = torch.tensor([len(r) for r in lib.routes])
    route = torch.randint(0, len(lib.routes), (n,), generator=g)
    index = (torch.rand(n, generator=g, dtype=torch.float64) * lengths[route]).long()
    out: dict = {}
    for key, args in (("batch_10k", (X,)), ("batch_10k_spread", (X, route, index))):
        eng.step_batch(*args)
        times, cpu = [], []
        for _ in range(3 * repeats):  # ~10 ms each: three times the repeats for a steadier median
            t0, c0 = time.perf_counter(), time.thread_time()
            eng.step_batch(*args)
            times.append(time.perf_counter() - t0)
            cpu.append(time.thread_time() - c0)
        out[f"{key}_ms_median"] = 1e3 * statistics.median(times)
        out[f"{key}_cpu_ms_median"] = 1e3 * statistics.median(cpu)
    out["batch_10k_spread_steps_present"] = int(torch.unique(eng.decide(X, route, index).step).numel())
    return out


def bench_rollout(eng: SkillEngine, lib: SkillLibrary, demos, dtype: torch.dtype, repeats: int) -> dict:
    """3. 1,000-start full-task rollout with random large and small pushes."""
    c, h = _box(demos, dtype)
    B = 1000
    x0 = c + h * (2 * torch.rand((B, lib.dim), generator=torch.Generator().manual_seed(2), dtype=dtype) - 1)
    out: dict = {}
    times, cpu, res = [], [], None
    for _ in range(max(1, repeats // 2)):
        plan = random_pushes(B, generator=torch.Generator().manual_seed(3), n_pushes=2, window=(50, 500),
                             magnitude=(0.1 * lib.span, 0.3 * lib.span))  # fmt: skip
        t0, c0 = time.perf_counter(), time.thread_time()
        res = eng.rollout(x0, dt=0.01, n_steps=6000, pushes=plan)
        times.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    assert res is not None
    task_t = (res.result.lengths - 1).double() * 0.01
    out["rollout_1000_s_median"] = statistics.median(times)
    out["rollout_1000_cpu_s_median"] = statistics.median(cpu)
    out["rollout_finished"] = float(res.done.double().mean())
    out["rollout_task_time_s_median"] = float(task_t.median())
    out["rollout_task_time_s_max"] = float(task_t.max())
    out["rollout_samples"] = int(res.result.lengths.max())
    out["pushes_applied"] = sum(p["applied"] for p in res.pushes)
    return out


if __name__ == "__main__":
    main()
