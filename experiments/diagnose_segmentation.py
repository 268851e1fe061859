"""Model or search? The collapsed score of the true steps against the labelling returned (synthetic families).

For every case (a benchmark family of :mod:`lfd_torch.segmentation.synthetic`, the data seed of
``bench_segmentation.py``), :func:`lfd_torch.segmentation.segment` runs with the given options; then the sampler's
own collapsed score log p(u, s, F | z) (:meth:`lfd_torch.segmentation.sampler._Run._collapsed_score`, the
objective of ``selection="map"``) is evaluated for the returned labelling and for the ground truth on the same grid
(grid point j of demonstration i labelled with the true step of its full-rate sample; true step m is state m,
owned by every demonstration). A positive gap (found - true) with fewer steps found means the model prefers
the merge: the search is not to blame. Prints one row per case, and with ``--parts`` a second table with the
gap split into the score's terms (:meth:`lfd_torch.segmentation.sampler._Run._collapsed_score_parts`): the
emission (field and position evidence of the states), the dwell term, the transitions, the initial state and the
feature prior, each found - true: which part of the model prefers the returned labelling.

    OMP_NUM_THREADS=1 .venv/bin/python experiments/diagnose_segmentation.py --family curved_dwell_2d --seeds 0 3 5 6 \
        --segment-option selection=map position_weight=None straight_weight=0.5
    OMP_NUM_THREADS=1 .venv/bin/python experiments/diagnose_segmentation.py --parts \
        --case straight_const_3d 4 1 --case scoop_dwell_3d 1 7 --json gaps.json
"""

from __future__ import annotations

import argparse
import contextlib

import torch

import lfd_torch.segmentation.sampler as sampler_module
from lfd_torch.segmentation import segment
from lfd_torch.segmentation.synthetic import FAMILIES
from bench_segmentation import case_data, segment_options


@contextlib.contextmanager
def captured_runs():
    """The sampler runs made inside the block (their observations and scoring are what the segmentation used), made
    outside inference mode so that their methods can be called after the block."""
    runs, original, mode = [], sampler_module._Run.sample, sampler_module._INFERENCE_MODE

    def sample(self):
        runs.append(self)
        return original(self)

    sampler_module._Run.sample = sample
    sampler_module._INFERENCE_MODE = False
    try:
        yield runs
    finally:
        sampler_module._Run.sample = original
        sampler_module._INFERENCE_MODE = mode


def case_labellings(family: str, seed: int, n_demos: int = 1, n_steps: int | None = None,
                    noise_scale: float | None = None, **options):
    """One benchmark case segmented with ``options``: the Segmentation, the sampler run it made and the true
    labelling (N, T) on the run's grid (grid point j of demonstration i labelled with the true step of its
    full-rate sample; true step m is state m; padding repeats the last label). ``n_steps``: the family drawn with
    that many legs, as ``bench_segmentation.py --n-steps``; ``noise_scale``: new white noise at that multiple of
    the case's level, as ``bench_segmentation.py --noise-scale`` (the same draw of the noise)."""
    syn = case_data(family, seed, n_demos, n_steps=n_steps, noise_scale=noise_scale)
    with captured_runs() as runs:
        seg = segment(syn.demos, generator=torch.Generator().manual_seed(seed), **options)
    run = runs[-1]
    M = int(syn.switch_times.shape[1]) + 1
    truth = torch.zeros(run.N, run.T, dtype=torch.long)
    for i in range(run.N):
        grid = torch.tensor(seg.info["grid"][i])
        steps = (grid.unsqueeze(-1) >= syn.switch_times[i].unsqueeze(0)).sum(-1)  # (n_i,) true step of each point
        truth[i] = M - 1
        truth[i, : grid.numel()] = steps
    return seg, run, truth


def score_gap(family: str, seed: int, n_demos: int = 1, n_steps: int | None = None,
              noise_scale: float | None = None, **options) -> dict:
    """Steps and collapsed scores of the returned and the true labelling of one case (:func:`case_labellings`)."""
    seg, run, truth = case_labellings(family, seed, n_demos, n_steps, noise_scale, **options)
    res = seg.sampler
    M = int(truth.max()) + 1
    features = torch.ones(run.N, M, dtype=torch.bool)
    hyper = [torch.tensor([res.hyperparameters[k]], dtype=run.dtype)
             for k in ("transition_concentration", "stickiness", "feature_mass")]

    def parts(s, f):
        phases = sampler_module.duration_phases(s[None], run.D)
        return {k: float(v[0]) for k, v in run._collapsed_score_parts(s[None], f[None], phases, *hyper).items()}

    found, true = parts(res.states, res.features), parts(truth, features)
    return {"family": family, "seed": seed, "true_steps": M,
            "found_steps": [len(seg.step_sequence(i)) for i in range(run.N)],
            "score_found": round(sum(found.values()), 1), "score_true": round(sum(true.values()), 1),
            "gap": round(sum(found.values()) - sum(true.values()), 1),
            "gap_parts": {k: round(found[k] - true[k], 1) for k in found}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--family", choices=list(FAMILIES))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--n-demos", type=int, default=1)
    ap.add_argument("--segment-option", nargs="+", default=[], metavar="KEY=VALUE",
                    help="segment() keyword arguments, e.g. selection=map position_weight=None")
    ap.add_argument("--parts", action="store_true", help="also split every gap into the score's terms")
    ap.add_argument("--case", nargs=3, action="append", default=[], metavar=("FAMILY", "N_DEMOS", "SEED"),
                    help="a case to score (repeatable; replaces --family, --n-demos and --seeds)")
    ap.add_argument("--n-steps", type=int, default=None, metavar="M",
                    help="straight and curved families drawn with M legs (the cases of bench_segmentation.py --n-steps)")
    ap.add_argument("--noise-scale", type=float, default=None, metavar="S",
                    help="new white position noise at S times each case's level (bench_segmentation.py --noise-scale)")
    ap.add_argument("--json", default=None, help="write every case's row (scores, gap, its terms) to this JSON file")
    args = ap.parse_args()
    if args.case:
        for family, _, _ in args.case:
            if family not in FAMILIES:
                ap.error(f"unknown family {family!r}")
        cases = [(f, int(n), int(seed)) for f, n, seed in args.case]
    elif args.family is None:
        ap.error("give --family (with --seeds, --n-demos) or --case")
    else:
        cases = [(args.family, args.n_demos, seed) for seed in args.seeds]
    options = segment_options([o for o in args.segment_option if not o.startswith("selection=")])
    options.update({"selection": o.split("=", 1)[1] for o in args.segment_option if o.startswith("selection=")})
    torch.set_num_threads(1)
    print("| family | demonstrations | seed | true steps | found steps | collapsed score found | true | gap (nats) |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for family, n_demos, seed in cases:
        r = {"n_demos": n_demos, **score_gap(family, seed, n_demos, args.n_steps, args.noise_scale, **options)}
        rows.append(r)
        print(f"| {r['family']} | {n_demos} | {r['seed']} | {r['true_steps']} | {r['found_steps']} | "
              f"{r['score_found']} | {r['score_true']} | {r['gap']} |", flush=True)
    if args.parts:
        names = list(rows[0]["gap_parts"])
        print("\ngap (found - true, nats) by term\n")
        print("| family | demonstrations | seed | " + " | ".join(names) + " |")
        print("|---|---|---|" + "---|" * len(names))
        for r in rows:
            print(f"| {r['family']} | {r['n_demos']} | {r['seed']} | "
                  + " | ".join(str(r["gap_parts"][k]) for k in names) + " |")
    if args.json:
        import json

        from lfd_torch.store import atomic_write, git_sha

        out = {"options": options, "n_steps": args.n_steps, "noise_scale": args.noise_scale, "git_sha": git_sha(),
               "cases": rows}
        atomic_write(args.json, lambda p: p.write_text(json.dumps(out, indent=1)))


if __name__ == "__main__":
    main()
