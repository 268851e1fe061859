"""Would a step field that converges to the step's end point separate the steps the affine field merges? (One-off.)

A mixture component can only add flexibility: it can raise the evidence of the true steps but never lower that of a
merge, which keeps the affine slab. Only a constraint every state obeys can make a merge costly. The paper's own
notion of a step is a stable dynamical system converging to its attractor g_m (the mean end point of its pieces), so
this script scores that constraint, as the slab of the spike-and-slab field prior in place of the affine one:

    u_t ~ N(A_k c_t, Psi_k / w_t),   c_t = (x_t - g_k) / (|x_t - g_k|^2 + eps^2)^(1/2),

A_k (d x d, no offset) under the MNIW prior of the affine slab's slope block with mean -I (straight at g_k), g_k the
mean of the last grid points of the runs of k. The straight spike (a constant direction) stays, with weight 1/2.
For every case (a benchmark family, data seed and sampler seed as ``diagnose_segmentation.py``) it prints the field
evidence gap (found - true, nats; Gaussian, with the reliabilities w_t, no Student-t profile) of the labelling the
defaults return and of the true one, under the affine slab and under the convergent one. Negative: the fields
prefer the true steps. The rest of the collapsed score (transitions, dwell, position) is not recomputed.

    OMP_NUM_THREADS=1 .venv/bin/python experiments/diagnose_convergent_fields.py \\
        --case straight_const_3d 4 1 --case scoop_const_3d 4 1 --json gaps.json
"""

from __future__ import annotations

import argparse
import json
import math

import torch

from lfd_torch.segmentation.field import FieldPrior, field_log_marginal_likelihood, field_statistics, straight_field_prior
from diagnose_segmentation import case_labellings


def _evidence(prior: FieldPrior, z: torch.Tensor, u: torch.Tensor, w: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """MNIW evidence of the samples in ``mask`` (n,) of the regression of u (n, d) on z (n, q)."""
    return field_log_marginal_likelihood(prior, *field_statistics(z, u, w, mask.unsqueeze(-1)))[0]


def attractors(run, s: torch.Tensor) -> dict[int, torch.Tensor]:
    """g_k (d,) per state k of the labelling s (N, T): the mean of the field coordinates (``run.obs.z[..., :d]``)
    of the last valid grid point of each run of k."""
    last = torch.zeros_like(run.valid)
    last[:, :-1] = s[:, 1:] != s[:, :-1]
    last |= torch.arange(run.T).unsqueeze(0) == (run.lengths - 1).unsqueeze(1)
    last &= run.valid
    x = run.obs.z[..., : run.d]
    return {k: x[(s == k) & last].mean(0) for k in s[run.valid].unique().tolist()}


def field_evidence(run, s: torch.Tensor, eps: float) -> dict[str, float]:
    """Spike-and-slab field evidence (weight 1/2 each) of the labelling s (N, T) summed over its states, with the
    affine slab and with the convergent one (module docstring)."""
    d = run.d
    z, u, w = run.obs.z.reshape(-1, d + 1), run.obs.u.reshape(-1, d), run.obs.w.reshape(-1)
    valid, labels = run.valid.reshape(-1), s.reshape(-1)
    straight = straight_field_prior(run.prior)
    convergent = FieldPrior(mean=-torch.eye(d, dtype=run.dtype), row_covariance=run.prior.row_covariance[:d, :d],
                            dof=run.prior.dof, scale=run.prior.scale)
    out = {"affine": 0.0, "convergent": 0.0}
    for k, g in attractors(run, s).items():
        mask = ((labels == k) & valid).to(run.dtype)
        r = z[:, :d] - g
        c = r / torch.sqrt((r * r).sum(-1, keepdim=True) + eps**2)
        spike = math.log(0.5) + _evidence(straight, z[:, d:], u, w, mask)
        for name, prior, regressors in (("affine", run.prior, z), ("convergent", convergent, c)):
            out[name] += float(torch.logaddexp(spike, math.log(0.5) + _evidence(prior, regressors, u, w, mask)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--case", nargs=3, action="append", required=True, metavar=("FAMILY", "N_DEMOS", "SEED"))
    ap.add_argument("--eps", type=float, default=0.05, help="softening of the unit direction to g_k (data radii)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    print("| family | demonstrations | seed | true steps | found steps | field gap, affine | field gap, convergent |")
    print("|---|---|---|---|---|---|---|")
    for family, n_demos, seed in args.case:
        seg, run, truth = case_labellings(family, int(seed), int(n_demos))
        found, true = field_evidence(run, seg.sampler.states, args.eps), field_evidence(run, truth, args.eps)
        row = {"family": family, "n_demos": int(n_demos), "seed": int(seed), "true_steps": int(truth.max()) + 1,
               "found_steps": [len(seg.step_sequence(i)) for i in range(run.N)],
               **{f"gap_{k}": round(found[k] - true[k], 1) for k in found}}
        rows.append(row)
        print(f"| {family} | {n_demos} | {seed} | {row['true_steps']} | {row['found_steps']} | {row['gap_affine']} | "
              f"{row['gap_convergent']} |", flush=True)
    if args.json:
        from lfd_torch.store import atomic_write, git_sha

        out = {"eps": args.eps, "git_sha": git_sha(), "cases": rows}
        atomic_write(args.json, lambda p: p.write_text(json.dumps(out, indent=1)))


if __name__ == "__main__":
    main()
