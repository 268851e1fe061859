"""Seed stability of the BP-GM-HMM on LASA (issue 7: the same step count on >= 9 of 10 seeds).

    python experiments/bench_segmentation_seeds.py [--shapes Multi_Models_1 ...] [--seeds 10]
    python experiments/bench_segmentation_seeds.py --selection collapsed --segment-option extra_dof=2
    python experiments/bench_segmentation_seeds.py --selection modal --segment-option n_chains=8 --json out.json

Segments all 7 demonstrations of each shape with default settings for seeds 0..N-1 and prints, per demonstration,
the most common step count and on how many seeds it occurs, per route (of the most common grouping) the most common
number of steps of the route and on how many seeds it occurs, and per shape the number of distinct route groupings,
and the attractor check of issue 7 (an intermediate attractor lies within 2 % of the data span of its
demonstrations): the median over seeds of the worst distance from an intermediate g_m to the path of any
demonstration that has step m, of the best any sample of step m's own pieces could do by that measure, and of the
distance from g_m to the nearest of those demonstrations (:func:`attractor_offsets`), and the share of each route's
path from which all of its demonstrations are within 2 % (:func:`route_coverage`, where any attractor of that route
could satisfy the check). ``--json`` also writes every seed's step counts, routes, attractor offsets and
segmentation wall time.

``--parts synthetic set3d`` runs the same seed check on data the sampler seed does not touch (issue 7 asks it of
"the synthetic families and the 3-D set" as well): ``synthetic``: for every benchmark family of
:mod:`lfd_torch.segmentation.synthetic` and 1 and 4 demonstrations, ``--cases`` data cases (the data of case c is
case c of ``bench_segmentation.py``), each segmented with sampler seeds 0..N-1; ``set3d``: the 3-D multi-step set
of ``experiments/segment_lasa.py`` (``conf/segment_lasa.yaml``: 5 demonstrations, 4 straight min-jerk legs, data
seed 0). A case is seed-stable when every demonstration gets its most common step count on >= 90 % of the seeds
(:func:`seed_stable`); the table gives per family the stable cases and the cases whose most common count is the
true one.

    python experiments/bench_segmentation_seeds.py --parts synthetic set3d --cases 3 --jobs 2 \
        --json results/tables/bench_segmentation_seeds_synthetic.json
"""

from __future__ import annotations

import argparse
import collections
import json
import statistics
import time
from pathlib import Path

import torch

from lfd_torch.data import load_lasa
from lfd_torch.segmentation import segment
from lfd_torch.segmentation.sampler import SELECTIONS
from lfd_torch.segmentation.synthetic import FAMILIES, multi_step_demos
from bench_segmentation import case_data, map_cases, segment_options, segment_settings

#: The experiment config that defines the 3-D set (its ``synthetic_3d`` entry, arguments of ``multi_step_demos``).
SEGMENT_LASA_CONF = Path(__file__).resolve().parents[1] / "conf" / "segment_lasa.yaml"


def attractor_offsets(seg, sequences: list[torch.Tensor]) -> tuple[float, float, float]:
    """(worst, bound, nearest) in % of the data span (the diagonal of the data's bounding box), over the
    intermediate steps.

    worst: max over steps m and demonstrations i with a piece of step m of the distance from g_m to path i (all of
    demonstration i's samples): g_m on every one of its demonstrations. bound: max over steps m of min over the
    samples p of step m's pieces of max_i dist(p, path i), what the best sample of the step's own pieces would give
    as g_m. nearest: max over steps m of min over those i of the distance from g_m to path i, the looser reading
    (g_m on the data of its demonstrations, not off all of them). All 0 when there is no intermediate step.
    """
    x = torch.cat(sequences)
    span = float((x.amax(0) - x.amin(0)).norm())
    worst, bound, nearest = 0.0, 0.0, 0.0
    for m in range(seg.n_steps):
        owners = [(i, a, b) for i, p in enumerate(seg.pieces) for step, a, b in p.tolist() if step == m]
        if not owners or any(b == sequences[i].shape[0] for i, _, b in owners):
            continue  # a route's last step ends at the task attractor
        paths = [sequences[i] for i in sorted({i for i, _, _ in owners})]
        g = seg.attractors[m].to(x)
        dists = [float((q - g).norm(dim=-1).min()) for q in paths]
        worst, nearest = max(worst, max(dists)), max(nearest, min(dists))
        cand = torch.cat([sequences[i][a:b] for i, a, b in owners])
        reach = torch.stack([torch.cdist(cand, q).amin(1) for q in paths]).amax(0)  # (n_cand,)
        bound = max(bound, float(reach.min()))
    return 100.0 * worst / span, 100.0 * bound / span, 100.0 * nearest / span


def route_coverage(seg, sequences: list[torch.Tensor], tol: float = 0.02) -> float:
    """Min over the routes with an intermediate step of the % of their demonstrations' samples p with
    max_i dist(p, path i) <= ``tol`` x span over the route's demonstrations i: where on the route an intermediate
    attractor could lie on all of them, whatever the step boundaries (100 when no route has one)."""
    x = torch.cat(sequences)
    span = float((x.amax(0) - x.amin(0)).norm())
    out = 100.0
    for r, steps in enumerate(seg.routes):
        members = [i for i in range(len(sequences)) if int(seg.route_of[i]) == r]
        if len(steps) < 2 or len(members) < 2:
            continue
        cand = torch.cat([sequences[i] for i in members])
        reach = torch.stack([torch.cdist(cand, sequences[i]).amin(1) for i in members]).amax(0)
        out = min(out, 100.0 * float((reach <= tol * span).double().mean()))
    return out


def seed_stable(steps_per_seed: list[list[int]], share: float = 0.9) -> tuple[list[int], bool]:
    """Most common step count of every demonstration over the seeds, and whether each occurs on at least ``share``
    of the seeds. steps_per_seed: S seeds x N demonstrations."""
    per_demo = [collections.Counter(col).most_common(1)[0] for col in zip(*steps_per_seed)]
    return [c for c, _ in per_demo], all(n >= share * len(steps_per_seed) for _, n in per_demo)


def stability_case(demos, true_steps: int, seeds: int, selection: str, options: dict) -> dict:
    """Every demonstration's step count under sampler seeds 0..seeds-1, the verdict of :func:`seed_stable` and
    whether every most common count is ``true_steps``."""
    steps, seconds = [], []
    for seed in range(seeds):
        t0 = time.perf_counter()
        seg = segment(demos, generator=torch.Generator().manual_seed(seed), selection=selection, **options)
        seconds.append(round(time.perf_counter() - t0, 3))
        steps.append([len(seg.step_sequence(i)) for i in range(demos.n_demos)])
    modal, stable = seed_stable(steps)
    return {"true_steps": true_steps, "steps_per_seed": steps, "modal_steps": modal, "stable": stable,
            "modal_is_true": all(m == true_steps for m in modal), "seconds": seconds}


def _synthetic_case(task: tuple) -> dict:
    family, n, case, seeds, selection, options = task
    torch.set_num_threads(1)
    syn = case_data(family, case, n)
    return {"family": family, "n_demos": n, "case": case,
            **stability_case(syn.demos, syn.n_steps, seeds, selection, options)}


def synthetic_stability(families: list[str], n_demos: list[int], cases: int, seeds: int, selection: str,
                        options: dict, jobs: int = 1) -> list[dict]:
    """One row per (family, n_demos, case): :func:`stability_case` plus the true step count (``jobs`` worker
    processes, one thread each; the rows do not depend on it)."""
    tasks = [(f, n, c, seeds, selection, options) for f in families for n in n_demos for c in range(cases)]
    rows = []
    for row in map_cases(_synthetic_case, tasks, jobs):
        print(f"    {row['family']} N={row['n_demos']} case={row['case']}: true {row['true_steps']}, "
              f"modal {row['modal_steps']}, stable={row['stable']}", flush=True)
        rows.append(row)
    return rows


def set3d_stability(seeds: int, selection: str, options: dict) -> dict:
    """:func:`stability_case` on the 3-D set of ``experiments/segment_lasa.py``."""
    from omegaconf import OmegaConf

    kw = OmegaConf.to_container(OmegaConf.load(SEGMENT_LASA_CONF).synthetic_3d, resolve=True)
    syn = multi_step_demos(torch.Generator().manual_seed(kw.pop("data_seed")), dim=3, **kw)
    return stability_case(syn.demos, syn.n_steps, seeds, selection, options)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", nargs="+", choices=("lasa", "synthetic", "set3d"), default=["lasa"])
    ap.add_argument("--shapes", nargs="+", default=[f"Multi_Models_{i}" for i in range(1, 5)])
    ap.add_argument("--families", nargs="+", choices=list(FAMILIES), default=list(FAMILIES))
    ap.add_argument("--n-demos", nargs="+", type=int, default=[1, 4])
    ap.add_argument("--cases", type=int, default=3, help="data cases per family and number of demonstrations")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes for --parts synthetic (one thread each)")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--selection", choices=list(SELECTIONS), default="map",
                    help="segment(selection=...): how the returned sample is chosen")
    ap.add_argument("--segment-option", nargs="+", default=[], metavar="KEY=VALUE",
                    help="further segment() keyword arguments (numbers, or None), e.g. extra_dof=2")
    ap.add_argument("--json", default=None, help="write the settings and every seed's result to this JSON file")
    args = ap.parse_args(argv)
    options = segment_options(args.segment_option)
    torch.set_num_threads(1)
    settings = segment_settings({**options, "selection": args.selection})
    out = {"settings": {"seeds": args.seeds, "selection": args.selection, "options": options,
                        "segment_settings": settings}, "shapes": {}}
    if "synthetic" in args.parts:
        rows = synthetic_stability(args.families, args.n_demos, args.cases, args.seeds, args.selection, options,
                                   args.jobs)
        out["synthetic"] = rows
        out["settings"]["cases"] = args.cases
        print("| family | demonstrations | seed-stable cases | most common count = truth |")
        print("|---|---|---|---|")
        for family in args.families:
            for n in args.n_demos:
                sel = [r for r in rows if r["family"] == family and r["n_demos"] == n]
                print(f"| {family} | {n} | {sum(r['stable'] for r in sel)} / {len(sel)} | "
                      f"{sum(r['modal_is_true'] for r in sel)} / {len(sel)} |", flush=True)
        print(f"all: {sum(r['stable'] for r in rows)} / {len(rows)} seed-stable, "
              f"{sum(r['modal_is_true'] for r in rows)} / {len(rows)} with the true count", flush=True)
    if "set3d" in args.parts:
        out["set3d"] = set3d_stability(args.seeds, args.selection, options)
        r = out["set3d"]
        print(f"3-D set: true {r['true_steps']}, most common {r['modal_steps']}, stable={r['stable']}", flush=True)
    if "lasa" not in args.parts:
        args.shapes = []
    else:
        print("| shape | modal steps per demo (seeds of", args.seeds, ") | modal steps per route | distinct route "
              "groupings | attractor off its demos, % span (best possible), median | off the nearest of them, median "
              "| route path within 2 % of all its demos, % (min over routes), median |")
        print("|---|---|---|---|---|---|---|")
    for shape in args.shapes:
        demos = load_lasa(shape)
        counts = [collections.Counter() for _ in range(demos.n_demos)]
        groupings = collections.Counter()
        route_steps: dict[tuple[int, ...], collections.Counter] = collections.defaultdict(collections.Counter)
        runs = []
        for seed in range(args.seeds):
            t0 = time.perf_counter()
            seg = segment(demos, generator=torch.Generator().manual_seed(seed), selection=args.selection, **options)
            seconds = round(time.perf_counter() - t0, 3)
            worst, bound, nearest = attractor_offsets(seg, demos.sequences())
            coverage = route_coverage(seg, demos.sequences())
            runs.append({"seed": seed, "seconds": seconds, "attractor_off_pct": round(worst, 3),
                         "attractor_bound_pct": round(bound, 3), "attractor_nearest_pct": round(nearest, 3),
                         "route_coverage_pct": round(coverage, 1),
                         "steps_per_demo": [len(seg.step_sequence(i)) for i in range(demos.n_demos)],
                         "routes": [list(r) for r in seg.routes], "route_of": seg.route_of.tolist(),
                         "collapsed_log_prob": round(float(seg.info["collapsed_log_prob"]), 3)})
            for i in range(demos.n_demos):
                counts[i][len(seg.step_sequence(i))] += 1
            groups = sorted(tuple(i for i in range(demos.n_demos) if int(seg.route_of[i]) == r) for r in range(seg.n_routes))
            groupings[tuple(groups)] += 1
            for r, g in enumerate(sorted(range(seg.n_routes), key=lambda r: min(i for i in range(demos.n_demos)
                                                                             if int(seg.route_of[i]) == r))):
                route_steps[groups[r]][len(seg.routes[g])] += 1
        modal = " ".join(f"{c.most_common(1)[0][0]} ({c.most_common(1)[0][1]})" for c in counts)
        top = groupings.most_common(1)[0][0]
        per_route = " ".join(f"{{{','.join(map(str, g))}}}: {route_steps[g].most_common(1)[0][0]} "
                             f"({route_steps[g].most_common(1)[0][1]})" for g in top)
        off = statistics.median(r["attractor_off_pct"] for r in runs)
        bnd = statistics.median(r["attractor_bound_pct"] for r in runs)
        near = statistics.median(r["attractor_nearest_pct"] for r in runs)
        cov = statistics.median(r["route_coverage_pct"] for r in runs)
        print(f"| {shape} | {modal} | {per_route} | {len(groupings)} | {off:.1f} ({bnd:.1f}) | {near:.1f} | {cov:.0f} |",
              flush=True)
        out["shapes"][shape] = {
            "modal_steps_per_demo": [list(c.most_common(1)[0]) for c in counts],
            "modal_steps_per_route": {",".join(map(str, g)): list(route_steps[g].most_common(1)[0]) for g in top},
            "distinct_route_groupings": len(groupings), "runs": runs,
        }
    if args.json:
        from lfd_torch.store import atomic_write, git_sha

        out["settings"]["git_sha"] = git_sha()
        atomic_write(args.json, lambda p: p.write_text(json.dumps(out, indent=1)))


if __name__ == "__main__":
    main()
