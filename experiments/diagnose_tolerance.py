"""Would a smooth direction tolerance separate corners from curves? Evidence of two labellings under a white and
under a correlated (AR(1)) tolerance (issue 7, the next step after ``direction_noise`` was measured).

The field emission of :mod:`lfd_torch.segmentation.field` lets a direction deviate from its state's affine field
by white noise of scale sigma_u (``direction_noise``, 0.2 rad) on top of the propagated velocity noise c_t. A
tight sigma_u finds the mild constant-speed corners of the synthetic families, but cuts LASA's human curves into
more steps (segmentation_studies.md, tables ``bench_segmentation_*_tolerance005.json``): along a human curve the
direction drifts
away from any one affine field, at a corner it jumps. This script scores labellings under emissions in which the
deviation is a smooth process instead,

    u_t = B_k z_t + eta_t + e_t,   e_t ~ N(0, (c_t + tau^2) I),
    eta_t = rho eta_(t-1) + xi_t,  xi_t ~ N(0, q I),  eta at the start of a run ~ N(0, q / (1 - rho^2) I),

with one field B_k ~ N(0, I) per state (every entry a priori 1 on the standardised scale, as the field prior's
slopes and offset) shared by its runs and a fresh eta per run; q = 0 is the white model (the present one with
its tolerance known instead of inverse-Wishart). log p(u | z, labelling) is exact: a Kalman filter over the state
[vec(B_k), eta_t] (:func:`smooth_tolerance_evidence`, tested against the stacked Gaussian density in
``tests/test_diagnose_tolerance.py``). The grid, directions, regressors and c_t are those the sampler used
(c_t = sigma_u^2 (1 / w_t - 1) at the default sigma_u, :mod:`.field`). Built into the model since, in conjugate
form (Kalman-factored, :func:`~lfd_torch.segmentation.field.correlated_tolerance_observations`) and with the same
grid: ``segment(..., tolerance_correlation=None)`` (:mod:`lfd_torch.segmentation.sampler`, "Correlated
tolerance"); this script stays the exact reference.

Labellings: for ``--case FAMILY N_DEMOS SEED`` (the data of ``bench_segmentation.py``) a = the one ``segment``
returns (default settings), b = the truth on the grid; for ``--shape`` (LASA, all 7 demonstrations) a = the
default labelling, b = the labelling at ``--tight`` (``direction_noise``, default 0.05). Printed per model: the
emission gap b - a (nats; the transitions charge about 5 nats per extra switch per demonstration on top) and
each labelling's total, which says which tolerance the data prefer. Then the tolerance learned by type-II
maximum likelihood over :data:`GRID` (rho, the AR scale and the white scale; a uniform prior on the grid): the
setting with the highest score of either labelling, the score being this emission plus the rest of the sampler's
collapsed score (transitions, initial state, features, dwell; ``_collapsed_score_parts`` without its "emission",
with the transition hyperparameters of the default run), and the gap b - a of those scores under it: positive
means b is the better of the two under a learned smooth tolerance. The table in README and
``results/tables/diagnose_tolerance.json``:

    OMP_NUM_THREADS=1 .venv/bin/python experiments/diagnose_tolerance.py --shape Multi_Models_1 Multi_Models_2 \
        Multi_Models_3 Multi_Models_4 --case straight_const_3d 1 1 --case straight_const_3d 4 1 \
        --case straight_const_3d 4 3 --case curved_const_2d 1 6 --case scoop_const_3d 1 0 \
        --case scoop_const_3d 4 1 --json results/tables/diagnose_tolerance.json

and every case the default settings miss (``diagnose_tolerance_missed.json``):

    OMP_NUM_THREADS=1 .venv/bin/python experiments/diagnose_tolerance.py \
        --missed results/tables/bench_segmentation_segment_directions.json --json results/tables/diagnose_tolerance_missed.json
"""

from __future__ import annotations

import argparse
import math

import torch
from torch import Tensor

import lfd_torch.segmentation.sampler as sampler_module
from lfd_torch.segmentation.sampler import TOLERANCES
from lfd_torch.data import load_lasa
from lfd_torch.segmentation import runs, segment
from lfd_torch.segmentation.synthetic import FAMILIES
from bench_segmentation import case_data
from diagnose_segmentation import captured_runs

#: (name, rho, q, tau^2): white tolerances 0.2 and 0.05 rad; AR(1) deviations of stationary scale 0.2 or 0.1 rad
#: over a white floor of 0.02 rad.
MODELS = (
    ("white 0.2", 0.0, 0.0, 0.2**2),
    ("white 0.05", 0.0, 0.0, 0.05**2),
    ("AR 0.9, 0.2 + 0.02", 0.9, 0.2**2 * (1 - 0.9**2), 0.02**2),
    ("AR 0.97, 0.2 + 0.02", 0.97, 0.2**2 * (1 - 0.97**2), 0.02**2),
    ("AR 0.9, 0.1 + 0.02", 0.9, 0.1**2 * (1 - 0.9**2), 0.02**2),
)
#: Type-II grid: (rho, stationary scale of the AR deviation, white scale), rad; rho = 0 rows are white only. The
#: settings of the model's learned tolerance (:data:`~lfd_torch.segmentation.sampler.TOLERANCES`), AR rows first.
GRID = tuple(t for t in TOLERANCES if t[0] > 0) + tuple((0.0, 0.0, t[1]) for t in TOLERANCES if t[0] == 0)


def smooth_tolerance_evidence(z: Tensor, u: Tensor, c: Tensor, labels: list[Tensor], rho: Tensor, q: Tensor,
                              tau2: Tensor, field_sd: float = 1.0) -> Tensor:
    """log p(u | z, labelling) under the model of the module docstring, for M parameter settings at once.

    Args:
        z: (N, T, p) regressors; u: (N, T, d) directions; c: (N, T) propagated noise variances.
        labels: N tensors (n_i,), the state of each of the first n_i points of sequence i.
        rho, q, tau2: (M,) AR coefficient, innovation variance and white variance of every setting.
        field_sd: prior standard deviation of every entry of B_k.

    Returns:
        (M,) log evidences (nats).
    """
    d, p = u.shape[-1], z.shape[-1]
    nb = d * p
    n = nb + d
    M = rho.shape[0]
    eye = torch.eye(d, dtype=u.dtype, device=u.device)
    per_state: dict[int, list[tuple[int, int, int]]] = {}
    for i, lab in enumerate(labels):
        starts, ends, values = runs(lab)
        for a, b, k in zip(starts.tolist(), ends.tolist(), values.tolist()):
            per_state.setdefault(k, []).append((i, a, b))
    stationary = torch.where(q > 0, q / (1.0 - rho**2).clamp_min(1e-12), torch.zeros_like(q))
    transition = torch.eye(n, dtype=u.dtype, device=u.device).repeat(M, 1, 1)
    transition[:, nb:, nb:] = rho.view(M, 1, 1) * eye
    total = u.new_zeros(M)
    for pieces in per_state.values():
        mean = u.new_zeros(M, n)
        cov = u.new_zeros(M, n, n)
        cov[:, :nb, :nb] = field_sd**2 * torch.eye(nb, dtype=u.dtype, device=u.device)
        for i, a, b in pieces:
            mean[:, nb:] = 0.0  # a fresh deviation for every run
            cov[:, nb:, :] = 0.0
            cov[:, :, nb:] = 0.0
            cov[:, nb:, nb:] = stationary.view(M, 1, 1) * eye
            for t in range(a, b):
                if t > a:
                    mean = (transition @ mean.unsqueeze(-1)).squeeze(-1)
                    cov = transition @ cov @ transition.transpose(-1, -2)
                    cov[:, nb:, nb:] += q.view(M, 1, 1) * eye
                obs = torch.cat([torch.kron(z[i, t].unsqueeze(0), eye), eye], 1)  # (d, n), vec(B) column-major
                s = obs @ cov @ obs.T + (c[i, t] + tau2).view(M, 1, 1) * eye
                chol = torch.linalg.cholesky(s)
                r = u[i, t] - mean @ obs.T  # (M, d)
                white = torch.linalg.solve_triangular(chol, r.unsqueeze(-1), upper=False).squeeze(-1)
                total = total - 0.5 * white.square().sum(-1) - torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
                total = total - 0.5 * d * math.log(2.0 * math.pi)
                gain = cov @ obs.T @ torch.cholesky_inverse(chol)  # (M, n, d)
                mean = mean + (gain @ r.unsqueeze(-1)).squeeze(-1)
                cov = cov - gain @ obs @ cov
                cov = 0.5 * (cov + cov.transpose(-1, -2))
    return total


def grid_settings(dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor, Tensor]:
    """(rho, q, tau^2) of every :data:`GRID` setting, each (G,): q = scale^2 (1 - rho^2) keeps the AR scale."""
    rho = torch.tensor([g[0] for g in GRID], dtype=dtype)
    q = torch.tensor([g[1] ** 2 * (1.0 - g[0] ** 2) for g in GRID], dtype=dtype)
    return rho, q, torch.tensor([g[2] ** 2 for g in GRID], dtype=dtype)


def _grid_view(run, direction_noise: float) -> tuple[Tensor, Tensor, Tensor]:
    o = run.obs
    c = direction_noise**2 * (1.0 / o.w.clamp_min(1e-8) - 1.0)
    return o.z, o.u, c


def _labels(seg) -> list[Tensor]:
    return [seg.sampler.states[i, : len(seg.info["grid"][i])].cpu() for i in range(seg.n_sequences)]


def _rest_of_score(run, hyper: dict, labels: list[Tensor], features: Tensor) -> float:
    """The sampler's collapsed score of a grid labelling without its emission term (transitions, initial state,
    features, dwell)."""
    s = torch.stack([torch.cat([lab, lab[-1:].expand(run.T - lab.shape[0])]) for lab in labels]).to(run.device)
    h = [torch.tensor([hyper[k]], dtype=run.dtype, device=run.device)
         for k in ("transition_concentration", "stickiness", "feature_mass")]
    phase = sampler_module.duration_phases(s[None], run.D)
    parts = run._collapsed_score_parts(s[None], features[None].to(run.device), phase, *h)
    return float(sum(v[0] for k, v in parts.items() if k != "emission"))


def _score(name: str, run, hyper: dict, a: tuple[list[Tensor], Tensor], b: tuple[list[Tensor], Tensor]) -> dict:
    """a, b: (labels, features) of two labellings of the run's grid."""
    z, u, c = _grid_view(run, 0.2)
    rho, q, tau2 = (torch.tensor([m[j] for m in MODELS], dtype=u.dtype) for j in (1, 2, 3))
    ea = smooth_tolerance_evidence(z, u, c, a[0], rho, q, tau2)
    eb = smooth_tolerance_evidence(z, u, c, b[0], rho, q, tau2)
    extra = [int(runs(y)[0].numel() - runs(x)[0].numel()) for x, y in zip(a[0], b[0])]
    g_rho, g_q, g_tau2 = grid_settings(u.dtype)
    sa = smooth_tolerance_evidence(z, u, c, a[0], g_rho, g_q, g_tau2) + _rest_of_score(run, hyper, *a)
    sb = smooth_tolerance_evidence(z, u, c, b[0], g_rho, g_q, g_tau2) + _rest_of_score(run, hyper, *b)
    best = int(torch.maximum(sa, sb).argmax())
    return {"case": name, "extra_switches_b": extra,
            "models": [{"model": m[0], "gap_b_minus_a": round(float(gb - ga), 1), "total_a": round(float(ga), 1),
                        "total_b": round(float(gb), 1)} for m, ga, gb in zip(MODELS, ea, eb)],
            "learned": {"rho": GRID[best][0], "ar_scale": GRID[best][1], "white_scale": GRID[best][2],
                        "score_gap_b_minus_a": round(float(sb[best] - sa[best]), 1),
                        "white_best": round(float(torch.maximum(sa, sb)[g_rho == 0].max()), 1),
                        "score_best": round(float(torch.maximum(sa, sb)[best]), 1)}}


def synthetic_case(family: str, n_demos: int, seed: int) -> dict:
    """a = the default labelling, b = the truth on the sampler's grid."""
    syn = case_data(family, seed, n_demos)
    with captured_runs() as captured:
        seg = segment(syn.demos, generator=torch.Generator().manual_seed(seed))
    truth = [(torch.tensor(seg.info["grid"][i]).unsqueeze(-1) >= syn.switch_times[i].cpu().unsqueeze(0)).sum(-1)
             for i in range(n_demos)]
    M = int(syn.switch_times.shape[1]) + 1
    return _score(f"{family} {n_demos} {seed}", captured[-1], seg.sampler.hyperparameters,
                  (_labels(seg), seg.sampler.features), (truth, torch.ones(n_demos, M, dtype=torch.bool)))


def lasa_case(shape: str, tight: float) -> dict:
    """a = the default labelling of all 7 demonstrations, b = the one at direction_noise = tight (seed 0)."""
    demos = load_lasa(shape)
    with captured_runs() as captured:
        seg = segment(demos, generator=torch.Generator().manual_seed(0))
    tight_seg = segment(demos, generator=torch.Generator().manual_seed(0), direction_noise=tight)
    return _score(f"{shape} (b: direction_noise={tight})", captured[-1], seg.sampler.hyperparameters,
                  (_labels(seg), seg.sampler.features), (_labels(tight_seg), tight_seg.sampler.features))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shape", nargs="*", default=[], help="LASA shapes (all 7 demonstrations)")
    ap.add_argument("--tight", type=float, default=0.05, help="direction_noise of labelling b of a LASA shape")
    ap.add_argument("--case", nargs=3, action="append", default=[], metavar=("FAMILY", "N_DEMOS", "SEED"))
    ap.add_argument("--missed", default=None, metavar="TABLE",
                    help="also every case of this bench_segmentation.py --json table whose switches were not all found")
    ap.add_argument("--json", default=None, help="write the rows to this JSON file")
    args = ap.parse_args()
    if args.missed:
        import json

        rows_in = json.loads(open(args.missed).read())["synthetic"]
        args.case += [[r["family"], r["n_demos"], r["seed"]] for r in rows_in
                      if r.get("method", "segment") == "segment" and not r["all_switches"]]
    for family, _, _ in args.case:
        if family not in FAMILIES:
            ap.error(f"unknown family {family!r}")
    if not (args.shape or args.case):
        ap.error("give --shape and/or --case")
    torch.set_num_threads(1)
    rows = [lasa_case(s, args.tight) for s in args.shape]
    rows += [synthetic_case(f, int(n), int(seed)) for f, n, seed in args.case]
    print("| labellings (a -> b) | extra switches of b | " + " | ".join(m[0] for m in MODELS) + " |")
    print("|---|---|" + "---|" * len(MODELS))
    for r in rows:
        cells = [f"{m['gap_b_minus_a']} ({m['total_a']})" for m in r["models"]]
        print(f"| {r['case']} | {r['extra_switches_b']} | " + " | ".join(cells) + " |")
    print("\ncells: emission gap b - a in nats (total of a); about 5 nats per extra switch per demonstration come on "
          "top from the transitions")
    print("\n| labellings (a -> b) | learned (rho, AR scale, white scale) | score gap b - a under it | best score | "
          "best with a white tolerance |")
    print("|---|---|---|---|---|")
    for r in rows:
        lr = r["learned"]
        print(f"| {r['case']} | {lr['rho']}, {lr['ar_scale']}, {lr['white_scale']} | {lr['score_gap_b_minus_a']} | "
              f"{lr['score_best']} | {lr['white_best']} |")
    if args.json:
        import json

        from lfd_torch.store import atomic_write, git_sha

        out = {"models": [list(m) for m in MODELS], "grid": [list(g) for g in GRID], "tight": args.tight,
               "git_sha": git_sha(), "rows": rows}
        atomic_write(args.json, lambda p: p.write_text(json.dumps(out, indent=1)))


if __name__ == "__main__":
    main()
