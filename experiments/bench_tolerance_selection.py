"""Would a learned smooth tolerance decide the steps? A measurement of the next step of issue 7, not a method of
the package.

For every case, ``segment`` (default settings otherwise) runs at the tolerances :data:`CANDIDATES`
(``direction_noise``); the four labellings are then scored by the evidence of ``diagnose_tolerance.py`` (directions
whose deviation from the state's field is white or AR(1), exact Kalman evidence with the fields integrated, plus
the rest of the sampler's collapsed score) with the tolerance learned by type-II over its ``GRID``: the labelling
and setting with the highest score are chosen together. The white map search only proposes; the smooth-tolerance
evidence decides among its proposals. Reported as ``bench_segmentation.py`` reports a method (exact step count,
every switch within 3 %, median boundary error; per family and number of demonstrations) and, on LASA, as
``bench_segmentation_seeds.py`` reports seed stability (every demonstration's modal step count and on how many
seeds).

    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_tolerance_selection.py --parts synthetic lasa --jobs 2 \
        --json results/tables/bench_tolerance_selection.json
"""

from __future__ import annotations

import argparse
import collections
import statistics
import time

import torch

from lfd_torch.data import load_lasa
from lfd_torch.segmentation import segment
from lfd_torch.segmentation.synthetic import FAMILIES
from bench_segmentation import case_data, map_cases, score_case, switches_from_labels
from bench_segmentation_seeds import seed_stable
from diagnose_segmentation import captured_runs
from diagnose_tolerance import GRID, _grid_view, _labels, _rest_of_score, grid_settings, smooth_tolerance_evidence

#: the tolerances (rad) whose map-search labellings are proposed
CANDIDATES = (0.2, 0.1, 0.05, 0.02)
LASA_SHAPES = ("Multi_Models_1", "Multi_Models_2", "Multi_Models_3", "Multi_Models_4")


def select(demos, seed: int):
    """(segmentation, info): the proposal chosen by the learned smooth-tolerance evidence."""
    segs, captured_run = [], None
    for sigma in CANDIDATES:
        with captured_runs() as captured:
            segs.append(segment(demos, generator=torch.Generator().manual_seed(seed), direction_noise=sigma))
        captured_run = captured[-1] if captured_run is None else captured_run  # the grid is the same for all
    z, u, c = _grid_view(captured_run, CANDIDATES[0])
    g_rho, g_q, g_tau2 = grid_settings(u.dtype)
    hyper = segs[0].sampler.hyperparameters
    scores = torch.stack([smooth_tolerance_evidence(z, u, c, _labels(s), g_rho, g_q, g_tau2)
                          + _rest_of_score(captured_run, hyper, _labels(s), s.sampler.features) for s in segs])
    j, g = divmod(int(scores.argmax()), len(GRID))
    return segs[j], {"tolerance": CANDIDATES[j], "setting": list(GRID[g]),
                     "score_gaps": [round(float(scores[k].max() - scores[j, g]), 1) for k in range(len(segs))]}


def _synthetic_case(task: tuple[str, int, int]) -> dict:
    family, n, seed = task
    torch.set_num_threads(1)
    syn = case_data(family, seed, n)
    t0 = time.perf_counter()
    seg, info = select(syn.demos, seed)
    found = [switches_from_labels(lab) for lab in seg.labels]
    return {"family": family, "n_demos": n, "seed": seed, **score_case(syn.switch_times, syn.demos.lengths, found),
            "seconds": time.perf_counter() - t0, **info}


def _lasa_shape(task: tuple[str, int]) -> dict:
    shape, seeds = task
    torch.set_num_threads(1)
    demos = load_lasa(shape)
    steps, chosen = [], []
    for seed in range(seeds):
        seg, info = select(demos, seed)
        steps.append([len(seg.step_sequence(i)) for i in range(demos.n_demos)])
        chosen.append(info)
    modal, stable = seed_stable(steps)
    counts = [collections.Counter(col)[m] for col, m in zip(zip(*steps), modal)]
    return {"shape": shape, "modal_steps": modal, "seeds_with_modal": counts, "stable": stable,
            "steps_per_seed": steps, "chosen": chosen}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", nargs="+", choices=("synthetic", "lasa"), default=["synthetic", "lasa"])
    ap.add_argument("--cases", type=int, default=10, help="data cases per family and number of demonstrations")
    ap.add_argument("--seeds", type=int, default=10, help="sampler seeds per LASA shape")
    ap.add_argument("--families", nargs="+", choices=list(FAMILIES), default=list(FAMILIES))
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    out: dict = {}
    if "synthetic" in args.parts:
        tasks = [(f, n, c) for f in args.families for n in (1, 4) for c in range(args.cases)]
        rows = list(map_cases(_synthetic_case, tasks, args.jobs))
        out["synthetic"] = rows
        print("| family | demos | every switch | exact | chosen tolerance 0.2 / 0.1 / 0.05 / 0.02 |")
        print("|---|---|---|---|---|")
        for f in args.families:
            for n in (1, 4):
                rs = [r for r in rows if r["family"] == f and r["n_demos"] == n]
                tol = collections.Counter(r["tolerance"] for r in rs)
                print(f"| {f} | {n} | {sum(r['all_switches'] for r in rs)}/{len(rs)} | "
                      f"{sum(r['exact_steps'] for r in rs)}/{len(rs)} | "
                      + " / ".join(str(tol[t]) for t in CANDIDATES) + " |", flush=True)
        for n in (1, 4, None):
            rs = [r for r in rows if n is None or r["n_demos"] == n]
            print(f"all, {n or 'both'} demos: every switch {100 * statistics.mean(r['all_switches'] for r in rs):.1f} %,"
                  f" exact {100 * statistics.mean(r['exact_steps'] for r in rs):.1f} %, median error "
                  f"{statistics.median(r['median_error_pct'] for r in rs):.2f} %")
    if "lasa" in args.parts:
        shapes = list(map_cases(_lasa_shape, [(s, args.seeds) for s in LASA_SHAPES], args.jobs))
        out["lasa"] = shapes
        for r in shapes:
            print(f"{r['shape']}: modal steps {r['modal_steps']} on {r['seeds_with_modal']} of {args.seeds} seeds, "
                  f"stable {r['stable']}, chosen tolerances {[c['tolerance'] for c in r['chosen']]}", flush=True)
    if args.json:
        import json

        from lfd_torch.store import atomic_write, git_sha

        out.update({"candidates": list(CANDIDATES), "git_sha": git_sha(), "cases": args.cases, "seeds": args.seeds})
        atomic_write(args.json, lambda p: p.write_text(json.dumps(out, indent=1)))


if __name__ == "__main__":
    main()
