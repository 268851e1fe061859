"""Would a position emission with a line's lever arm prefer the true steps the defaults miss? (One-off diagnostic.)

The known-count oracle (``oracle_switches.py``) finds every switch of the constant-speed families when it knows
that a leg is straight and fits the leg's positions. The sampler sees only local slopes. This script scores two
labellings of one case (the defaults' and the truth, both on the sampler's grid) under the emission that the oracle
points to. Nothing in ``lfd_torch`` uses it.

Observations: the means x_j of the samples nearest each grid point (block j holds the samples closer to grid point
j than to its neighbours; m_j samples), standardised as the sampler's positions (:class:`~lfd_torch.segmentation.
field.FieldObservations` centre and radius), with their mean path length s_j (:func:`~lfd_torch.segmentation.
segmentation.path_length` of the sampler's velocities). The increment from block i to i + 1 belongs to the state of
both blocks when they share one. A state moves the position along its field, integrated over the increments it owns:

    x_j = x_0 + sum_k beta_k^T R_kj + W_j + e_j,   e_j ~ N(0, sigma^2 / m_j),   per axis, independent axes,

with the sampler's position noise sigma (``info["position_noise"]``). An increment across a switch belongs to
neither state: the corner lies somewhere between the two grid points, so that increment is a free displacement
(prior N(0, ds^2) per axis), about 3 log(ds / sigma_b) nats per switch. Each state is straight or affine (spike and
slab, probability 1/2 each, every combination of the states summed):
    straight  R_kj = the path length the state owned before block j (scalar), beta_k ~ N(0, 1 / d): a line through
              the state's blocks, continuous at every switch, no tolerance;
    affine    R_kj = sum_i ds_i (z_i + z_(i+1)) / 2 over the increments it owned before block j (z = [x~, 1] the
              sampler's regressors), beta_k ~ the field prior's scales (slope entries N(0, slope_scale^2), offset
              N(0, 1)), with the direction tolerance sigma_u of the defaults as a random walk: W gains N(0, ds_i^2
              sigma_u^2) over each increment the state owns.
x_0 ~ N(x_(first block), 1) per demonstration. All parameters are Gaussian, so the evidence of each combination is
a Gaussian density over all blocks of all demonstrations (coefficients shared by the demonstrations of a state).

For every case (the benchmark's data seed, sampler seed as ``diagnose_segmentation.py``) it prints the number of
steps found and true, the sampler's emission gap (found - true, the collapsed score's emission term), this
emission's gap, the gap of the rest of the sampler's collapsed score (dwell, transitions, initial state, features;
``diagnose_segmentation.py --parts``) and this emission's gap plus that rest; negative: the true steps preferred. With ``--halves`` it also scores the truth with every
step of every demonstration cut in two at its middle grid point (a cut a model should not make).

    OMP_NUM_THREADS=1 .venv/bin/python experiments/diagnose_block_emission.py --case straight_const_3d 1 2 \
        --case scoop_const_3d 4 2 --halves
"""

from __future__ import annotations

import argparse
import itertools
import json
import math

import torch
from torch import Tensor

from lfd_torch.segmentation.blocks import block_means
from lfd_torch.segmentation.segmentation import path_length, scale_velocities, velocity_noise
from diagnose_segmentation import case_labellings, score_gap
from bench_segmentation import case_data


MAX_EXACT_STATES = 8  # above this many states the sum over combinations is replaced by its best term


def case_blocks(seg, run, syn, length: str = "speed") -> list[dict]:
    """Per demonstration: standardised block means, path lengths, counts, regressors z (n, p) of the grid points.
    ``length``: "speed" the mean path length of each block's samples (the sampler's speed estimates), "chord" the
    cumulative lengths of the chords between consecutive block means, each less its noise bias."""
    out = []
    k_of = seg.info["strides"]
    sigma, rho = seg.info["position_noise"], seg.info["noise_correlation"]
    centre, radius = run.obs.centre, float(run.obs.radius)
    for i in range(run.N):
        T = int(syn.demos.lengths[i])
        x = syn.demos.positions[i, :T].to(torch.float64)
        t = syn.demos.times[i, :T].to(torch.float64)
        dt = float((t[1:] - t[:-1]).median())
        k = int(k_of[i])
        v = scale_velocities(x, k, dt)
        noise = velocity_noise(sigma, T, k, dt, rho=rho).to(x)
        L = path_length(v, noise, dt)
        xb, sb, mb = block_means(x, torch.tensor(seg.info["grid"][i]), L)
        n = xb.shape[0]
        xs, noise = (xb - centre) / radius, sigma / radius
        if length == "chord":  # the path length along the block means, less the noise's share of each chord
            sq = (xs[1:] - xs[:-1]).square().sum(-1) - xs.shape[-1] * noise**2 * (1 / mb[1:] + 1 / mb[:-1])
            chord = sq.clamp_min(0.0).sqrt()
            s = torch.cat([xs.new_zeros(1), chord.cumsum(0)])
        else:
            s = sb / radius
        out.append({"x": xs, "s": s, "m": mb, "z": run.obs.z[i, :n], "noise": noise})
    return out


def block_evidence(data: list[dict], labels: Tensor, *, tolerance: float = 0.2, slope_scale: float = 1.0,
                   demo_spread: float = 0.0, components: tuple[int, ...] | None = None) -> float:
    """log p(block means | labelling) summed over the 2^K straight / affine combinations (module docstring), each
    with prior probability 2^-K (for more than MAX_EXACT_STATES states the log density of the best combination
    found by coordinate ascent instead, an upper bound of the sum when that is the best; the halves of LASA's
    labellings are scored so, which overstates what cutting gains); with ``components`` (0 straight, 1 affine per state, in increasing state order)
    the log density of that combination alone (no prior term)."""
    d = data[0]["x"].shape[-1]
    p = d + 1
    states = sorted({int(v) for i, blk in enumerate(data) for v in labels[i, : blk["x"].shape[0]].tolist()})
    N = len(data)
    sizes = [blk["x"].shape[0] for blk in data]
    offsets = [0] + list(itertools.accumulate(sizes))
    total = offsets[-1]
    # per state and demonstration: increments owned, their ds and mid regressors
    owned = {}
    for i, blk in enumerate(data):
        n = sizes[i]
        lab = labels[i, :n]
        ds = (blk["s"][1:] - blk["s"][:-1]).clamp_min(0.0)  # (n - 1,)
        zmid = 0.5 * (blk["z"][1:] + blk["z"][:-1])  # (n - 1, p)
        for st in states:  # an increment across a switch belongs to neither state (below)
            mask = ((lab[1:] == st) & (lab[:-1] == st)).to(ds)
            owned[(st, i)] = (ds * mask, zmid)
    y = torch.cat([blk["x"] for blk in data])  # (total, d)
    base = torch.diag(torch.cat([torch.full((sizes[i],), data[i]["noise"] ** 2, dtype=y.dtype) / data[i]["m"]
                                for i in range(N)]))
    x0_cols = torch.zeros(total, N, dtype=y.dtype)
    mean = torch.zeros(total, d, dtype=y.dtype)
    for i in range(N):
        x0_cols[offsets[i]: offsets[i + 1], i] = 1.0
        mean[offsets[i]: offsets[i + 1]] = data[i]["x"][0]
    # regressors of each state under both components, and its random-walk covariance under the affine one
    straight_cols, affine_cols, walk = {}, {}, {}
    for st in states:
        cs = torch.zeros(total, 1 + N, dtype=y.dtype)  # the shared direction, then each demonstration's own
        ca = torch.zeros(total, p, dtype=y.dtype)
        cw = torch.zeros(total, total, dtype=y.dtype)
        for i in range(N):
            ds, zmid = owned[(st, i)]
            o, n = offsets[i], sizes[i]
            cs[o + 1: o + n, 0] = ds.cumsum(0)
            cs[o + 1: o + n, 1 + i] = ds.cumsum(0)
            ca[o + 1: o + n] = (ds.unsqueeze(-1) * zmid).cumsum(0)
            var = torch.cat([torch.zeros(1, dtype=y.dtype), (ds * tolerance) ** 2]).cumsum(0)  # (n,) walk variance
            cw[o: o + n, o: o + n] = torch.minimum(var.unsqueeze(0), var.unsqueeze(1))
        straight_cols[st], affine_cols[st], walk[st] = cs, ca, cw
    # the corner lies somewhere between the two grid points of a switch: the increment across it is a free
    # displacement, prior N(0, ds^2) per axis, carried by every later block of its demonstration
    free_cols, free_var = [], []
    for i, blk in enumerate(data):
        n, o = sizes[i], offsets[i]
        lab = labels[i, :n]
        ds = (blk["s"][1:] - blk["s"][:-1]).clamp_min(1e-9)
        for j in (lab[1:] != lab[:-1]).nonzero().squeeze(-1).tolist():
            col = torch.zeros(total, 1, dtype=y.dtype)
            col[o + j + 1: o + n, 0] = 1.0
            free_cols.append(col)
            free_var.append(float(ds[j]) ** 2)
    prior_straight = torch.tensor([1.0 / d] + [demo_spread**2] * N, dtype=y.dtype)
    prior_affine = torch.tensor([slope_scale**2] * d + [1.0], dtype=y.dtype)
    def combo_ll(combo: tuple[int, ...]) -> float:
        cols = [x0_cols] + free_cols
        var = [torch.ones(N, dtype=y.dtype), torch.tensor(free_var, dtype=y.dtype)]
        cov = base.clone()
        for st, c in zip(states, combo):
            if c == 0:
                cols.append(straight_cols[st]); var.append(prior_straight)
            else:
                cols.append(affine_cols[st]); var.append(prior_affine)
                cov = cov + walk[st]
        X = torch.cat(cols, 1)
        cov = cov + (X * torch.cat(var)) @ X.T
        chol = torch.linalg.cholesky(cov)
        r = torch.linalg.solve_triangular(chol, y - mean, upper=False)
        logdet = 2.0 * torch.log(torch.diagonal(chol)).sum()
        return float(-0.5 * (r * r).sum() - 0.5 * d * (logdet + total * math.log(2 * math.pi)))

    if components is not None:
        return combo_ll(tuple(components))
    K = len(states)
    if K <= MAX_EXACT_STATES:
        scores = [combo_ll(c) for c in itertools.product((0, 1), repeat=K)]
        return float(torch.logsumexp(torch.tensor(scores, dtype=torch.float64), 0)) + K * math.log(0.5)
    # too many combinations: the best one found by coordinate ascent from all affine, whose log density is an upper
    # bound of the sum's when it is the largest term (the sum of 2^K terms of weight 2^-K is at most the largest)
    combo, best = [1] * K, combo_ll(tuple([1] * K))
    improved = True
    while improved:
        improved = False
        for k in range(K):
            trial = combo.copy()
            trial[k] = 1 - trial[k]
            value = combo_ll(tuple(trial))
            if value > best:
                combo, best, improved = trial, value, True
    return best


def halves(labels: Tensor, lengths: Tensor) -> Tensor:
    """Every run of every sequence cut in two at its middle (the second half of state k a new state shared by the
    demonstrations: k + the number of states)."""
    out = labels.clone()
    shift = int(labels.max()) + 1
    for i in range(labels.shape[0]):
        n = int(lengths[i])
        lab = labels[i, :n]
        starts = [0] + [t for t in range(1, n) if lab[t] != lab[t - 1]] + [n]
        for a, b in zip(starts[:-1], starts[1:]):
            if b - a >= 4:
                out[i, (a + b) // 2: b] = int(lab[a]) + shift
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--case", nargs=3, action="append", default=[], metavar=("FAMILY", "N_DEMOS", "SEED"))
    ap.add_argument("--halves", action="store_true")
    ap.add_argument("--lasa", nargs="+", default=[], metavar="SHAPE",
                    help="LASA shapes (all 7 demonstrations, sampler seed 0): the returned labelling against its halves")
    ap.add_argument("--tolerance", type=float, default=0.2, help="the affine states' direction tolerance (rad)")
    ap.add_argument("--length", choices=("speed", "chord"), default="speed",
                    help="the path length of the blocks (case_blocks)")
    ap.add_argument("--demo-spread", type=float, default=0.0,
                    help="a straight state's direction in each demonstration: the shared one plus N(0, spread^2)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    print("| family | demos | seed | true steps | found steps | sampler emission gap | block emission gap | "
          "rest of the score | block emission + rest |" + (" halves - truth |" if args.halves else ""))
    print("|---|---|---|---|---|---|---|---|---|" + ("---|" if args.halves else ""))
    for family, n_demos, seed in args.case:
        n_demos, seed = int(n_demos), int(seed)
        seg, run, truth = case_labellings(family, seed, n_demos)
        syn = case_data(family, seed, n_demos)
        data = case_blocks(seg, run, syn, args.length)
        found_ev = block_evidence(data, seg.sampler.states, tolerance=args.tolerance, demo_spread=args.demo_spread)
        true_ev = block_evidence(data, truth, tolerance=args.tolerance, demo_spread=args.demo_spread)
        parts = score_gap(family, seed, n_demos)["gap_parts"]
        sampler_gap = parts["emission"]
        rest = round(sum(v for k, v in parts.items() if k != "emission"), 1)  # dwell, transitions, initial, features
        row = {"family": family, "n_demos": n_demos, "seed": seed, "true_steps": int(truth.max()) + 1,
               "found_steps": [len(seg.step_sequence(i)) for i in range(run.N)],
               "sampler_emission_gap": sampler_gap, "block_gap": round(found_ev - true_ev, 1), "rest_gap": rest,
               "block_total_gap": round(found_ev - true_ev + rest, 1)}
        line = (f"| {family} | {n_demos} | {seed} | {row['true_steps']} | {row['found_steps']} | {sampler_gap} | "
                f"{row['block_gap']} | {rest} | {row['block_total_gap']} |")
        if args.halves:
            row["halves_gain"] = round(block_evidence(data, halves(truth, run.lengths), tolerance=args.tolerance, demo_spread=args.demo_spread) - true_ev, 1)
            line += f" {row['halves_gain']} |"
        rows.append(row)
        print(line, flush=True)
    for shape in args.lasa:
        from lfd_torch.data.lasa import load_lasa
        from diagnose_segmentation import captured_runs
        from lfd_torch.segmentation import segment

        demos = load_lasa(shape)
        with captured_runs() as runs:
            seg = segment(demos, generator=torch.Generator().manual_seed(0))
        run = runs[-1]
        data = case_blocks(seg, run, type("Case", (), {"demos": demos})(), args.length)
        found = seg.sampler.states
        ev = block_evidence(data, found, tolerance=args.tolerance, demo_spread=args.demo_spread)
        gain = block_evidence(data, halves(found, run.lengths), tolerance=args.tolerance, demo_spread=args.demo_spread) - ev
        steps = [len(seg.step_sequence(i)) for i in range(run.N)]
        rows.append({"lasa": shape, "found_steps": steps, "halves_gain": round(gain, 1)})
        print(f"| {shape} | 7 | 0 | - | {steps} | - | - | - | - | {gain:.1f} |", flush=True)
    if args.json:
        from lfd_torch.store import atomic_write, git_sha

        atomic_write(args.json, lambda p: p.write_text(json.dumps({"git_sha": git_sha(), "cases": rows}, indent=1)))


if __name__ == "__main__":
    main()
