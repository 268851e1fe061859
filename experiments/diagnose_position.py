"""What the tempered position term pays for cutting a leg in two (issue 7; :mod:`lfd_torch.segmentation.sampler`,
"Position").

An L-shaped 2-D path (two straight legs of n grid points each, unit length, at right angles, white noise of
``--noise`` of the span per axis) is scored by the sampler's own position evidence (the tempered NIW evidence of
each state's positions, tau = 1 / 3 as at D = 3, and with ``position_mixture`` the occupancies) under two
labellings: the first leg one state, or cut in half into two states (the second leg one state in both). Printed
per leg length: tau n log 2 (what a Gaussian gains per cut when its covariance is the data's along the leg and
nothing else moves), the gain of the cut with the Gaussian term (the default) and with the mixture term. The
perpendicular spread of a leg is far below the NIW prior's expected covariance (0.05 of the data's variance per
axis), so that axis is prior-dominated and a second state also pays its own normalisation: the default's gain is
well below tau n log 2 and negative on short legs; the mixture's occupancies charge about tau n log 2 more.

    python experiments/diagnose_position.py --json results/tables/diagnose_position.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

import lfd_torch.segmentation.sampler as sampler_module
from lfd_torch.gmm import niw_log_marginal_likelihood


def l_path(n: int, noise: float, seed: int = 5) -> torch.Tensor:
    """(2 n, 2) two legs of n grid points, (0, 0) -> (1, 0) -> (1, 1), plus white noise of std ``noise``."""
    t = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
    legs = torch.cat([torch.stack([t, 0.0 * t], -1), torch.stack([1.0 + 0.0 * t, t], -1)])
    return legs + noise * torch.randn(2 * n, 2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def cut_gain(path: torch.Tensor, n: int, tau: float, mixture: bool) -> float:
    """Position evidence of the first leg cut in half minus that of the first leg as one state (nats)."""
    v = torch.gradient(path, dim=0)[0] / 0.01
    cfg = sampler_module.BetaProcessHMMSampler(n_chains=1, position_weight=tau, position_mixture=mixture)
    x, lengths = sampler_module._pad([path])
    vp, _ = sampler_module._pad([v])
    run = sampler_module._Run(cfg, x, vp, lengths, torch.Generator().manual_seed(0), None, 3, (1e-3, 1e-6))
    one = torch.zeros(1, 2 * n, 3, dtype=torch.float64)
    one[0, :n, 0] = one[0, n:, 2] = 1.0
    two = one.clone()
    two[0, n // 2: n] = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    score = [float(niw_log_marginal_likelihood(run.pos_prior, *run._position_statistics(o)).sum()
                   + run._occupancy_terms(o).sum()) for o in (two, one)]
    return score[0] - score[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--legs", nargs="+", type=int, default=[10, 15, 30, 60, 120], help="grid points per leg")
    ap.add_argument("--noise", nargs="+", type=float, default=[0.003, 0.01], help="noise std / span")
    ap.add_argument("--tau", type=float, default=1.0 / 3.0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    print("| noise | leg (grid points) | tau n log 2 | gain, Gaussian (default) | gain, mixture |")
    print("|---|---|---|---|---|")
    for noise in args.noise:
        for n in args.legs:
            path = l_path(n, noise)
            r = {"noise": noise, "leg": n, "tau_n_log2": args.tau * n * math.log(2.0),
                 "gain_gaussian": cut_gain(path, n, args.tau, False), "gain_mixture": cut_gain(path, n, args.tau, True)}
            rows.append(r)
            print(f"| {noise:g} | {n} | {r['tau_n_log2']:.1f} | {r['gain_gaussian']:.1f} | {r['gain_mixture']:.1f} |")
    if args.json:
        out = Path(args.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(".tmp")
        tmp.write_text(json.dumps({"tau": args.tau, "rows": rows}, indent=1))
        tmp.replace(out)


if __name__ == "__main__":
    main()
