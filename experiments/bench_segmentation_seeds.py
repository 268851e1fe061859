"""Seed stability of the BP-GM-HMM on LASA (issue 7: the same step count on >= 9 of 10 seeds).

    python experiments/bench_segmentation_seeds.py [--shapes Multi_Models_1 ...] [--seeds 10]
    python experiments/bench_segmentation_seeds.py --selection collapsed --segment-option extra_dof=2
    python experiments/bench_segmentation_seeds.py --selection modal --segment-option n_chains=8 --json out.json

Segments all 7 demonstrations of each shape with default settings for seeds 0..N-1 and prints, per demonstration,
the most common step count and on how many seeds it occurs, per route (of the most common grouping) the most common
number of steps of the route and on how many seeds it occurs, and per shape the number of distinct route groupings.
``--json`` also writes every seed's step counts, routes and segmentation wall time.
"""

from __future__ import annotations

import argparse
import collections
import json
import time

import torch

from lfd_torch.data import load_lasa
from lfd_torch.segmentation import segment
from lfd_torch.segmentation.sampler import SELECTIONS
from bench_segmentation import segment_options


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shapes", nargs="+", default=[f"Multi_Models_{i}" for i in range(1, 5)])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--selection", choices=list(SELECTIONS), default="joint",
                    help="segment(selection=...): how the returned sample is chosen")
    ap.add_argument("--segment-option", nargs="+", default=[], metavar="KEY=VALUE",
                    help="further segment() keyword arguments (numbers, or None), e.g. extra_dof=2")
    ap.add_argument("--json", default=None, help="write the settings and every seed's result to this JSON file")
    args = ap.parse_args(argv)
    options = segment_options(args.segment_option)
    torch.set_num_threads(1)
    print("| shape | modal steps per demo (seeds of", args.seeds, ") | modal steps per route | distinct route groupings |")
    print("|---|---|---|---|")
    out = {"settings": {"seeds": args.seeds, "selection": args.selection, "options": options}, "shapes": {}}
    for shape in args.shapes:
        demos = load_lasa(shape)
        counts = [collections.Counter() for _ in range(demos.n_demos)]
        groupings = collections.Counter()
        route_steps: dict[tuple[int, ...], collections.Counter] = collections.defaultdict(collections.Counter)
        runs = []
        for seed in range(args.seeds):
            t0 = time.perf_counter()
            seg = segment(demos, generator=torch.Generator().manual_seed(seed), selection=args.selection, **options)
            runs.append({"seed": seed, "seconds": round(time.perf_counter() - t0, 3),
                         "steps_per_demo": [len(seg.step_sequence(i)) for i in range(demos.n_demos)],
                         "routes": [list(r) for r in seg.routes], "route_of": seg.route_of.tolist()})
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
        print(f"| {shape} | {modal} | {per_route} | {len(groupings)} |", flush=True)
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
