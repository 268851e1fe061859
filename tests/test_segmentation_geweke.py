"""Geweke (2004) successive-conditional check of the whole BP-GM-HMM sampler (slow).

Alternating one MCMC sweep given the data with a fresh draw of the data given the parameters leaves the prior
invariant: the marginal law of the features, emissions and transitions along this chain must be the prior's.
The feature moves (shared flips, reversible-jump births/deaths with data-driven proposals) are the delicate part;
an error in any acceptance ratio shifts the number of features away from the IBP law.

The model needs every sequence to own at least one feature (a sequence with none cannot emit data), so the
reference is the two-parameter IBP conditioned on non-empty rows, estimated by rejection from ``sample_ibp``.
"""

from __future__ import annotations

import math

import pytest
import torch

from lfd_torch.segmentation.emissions import NIWPrior
from lfd_torch.segmentation.features import sample_ibp
from lfd_torch.segmentation.sampler import BetaProcessHMMSampler, _Run
from lfd_torch.segmentation.transitions import initial_distribution, transition_matrix

F64 = torch.float64


def _redraw_data(run: _Run, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """x ~ p(x | F, eta, theta) for every chain: states from the sticky chain, Gaussian emissions.

    Returns:
        x (C, N, T, d) and the states (C, N, T).
    """
    C, N, K = run.F.shape
    P = transition_matrix(run.eta, run.F)  # (C, N, K, K)
    init = initial_distribution(run.F, F64)  # (C, N, K)
    s = torch.zeros(C, N, run.T, dtype=torch.long)
    s[..., 0] = torch.multinomial(init.reshape(C * N, K), 1, generator=gen).reshape(C, N)
    cc, nn = torch.meshgrid(torch.arange(C), torch.arange(N), indexing="ij")
    for t in range(1, run.T):
        rows = P[cc, nn, s[..., t - 1]]  # (C, N, K)
        s[..., t] = torch.multinomial(rows.reshape(C * N, K), 1, generator=gen).reshape(C, N)
    chol = torch.linalg.cholesky(run.cov)  # (C, K, d, d)
    z = torch.randn(C, N, run.T, run.d, 1, generator=gen, dtype=F64)
    ci = torch.arange(C).view(C, 1, 1)
    x = run.mean[ci, s] + (chol[ci, s] @ z).squeeze(-1)  # (C, N, T, d)
    return x, s


def _chain_se(values: torch.Tensor) -> float:
    """Standard error of the overall mean from the spread of independent chains' means; values (C, n)."""
    means = values.mean(1)
    return float(means.std() / math.sqrt(values.shape[0]))


@pytest.mark.slow
def test_geweke_features_and_emissions():
    mass, conc, N = 1.5, 1.0, 2
    cfg = BetaProcessHMMSampler(
        feature_mass=mass, feature_concentration=conc, transition_concentration=1.0, stickiness=2.0,
        n_chains=12, n_initial_features=2,
    )  # fmt: skip
    d = 1
    prior = NIWPrior(
        mean=torch.zeros(d, dtype=F64), kappa=torch.tensor(1.0, dtype=F64), dof=torch.tensor(5.0, dtype=F64),
        scale=torch.eye(d, dtype=F64) * 3.0,
    )  # E[Sigma] = 3 / (5 - 1 - 1) = 1  # fmt: skip
    gen = torch.Generator().manual_seed(7)
    T = 5
    x0 = torch.randn(N, T, d, generator=gen, dtype=F64)
    run = _Run(cfg, x0, torch.full((N,), T), gen, prior)
    C = cfg.n_chains
    # every chain is an independent Geweke chain with its own data set
    xs = x0.unsqueeze(0).repeat(C, 1, 1, 1)

    def set_data(x: torch.Tensor) -> None:
        run.xc = x  # (C, N, T, d): chain c only ever reads x[c]
        run.loge = run._emission(run.mean, run.cov)
        run.ll = run._marginal_all()

    n_iter, burn = 400, 50
    row0, k_plus, sigma, mu = [[] for _ in range(C)], [[] for _ in range(C)], [[] for _ in range(C)], [[] for _ in range(C)]
    for it in range(n_iter):
        run._compact()
        run._shared_moves()
        run._birth_death()
        run._sample_states()
        run._sample_parameters()
        xs, s = _redraw_data(run, gen)
        run.s = s
        set_data(xs)
        if it >= burn:
            for c in range(C):
                owned = run.F[c].any(0)
                row0[c].append(float(run.F[c, 0].sum()))
                k_plus[c].append(float(owned.sum()))
                sigma[c].append(float(run.cov[c, owned, 0, 0].mean()))
                mu[c].append(float(run.mean[c, owned, 0].mean()))
    row0_t, kp_t = torch.tensor(row0), torch.tensor(k_plus)  # (C, n_kept)
    # reference: IBP conditioned on non-empty rows
    ref_gen = torch.Generator().manual_seed(8)
    ref_row0, ref_kp = [], []
    while len(ref_row0) < 40000:
        f = sample_ibp(N, mass, conc, ref_gen)
        if f.shape[1] and bool(f.any(1).all()):
            ref_row0.append(float(f[0].sum()))
            ref_kp.append(float(f.shape[1]))
    ref_row0_m, ref_kp_m = sum(ref_row0) / len(ref_row0), sum(ref_kp) / len(ref_kp)
    for name, got, ref in (("row 0 features", row0_t, ref_row0_m), ("K+", kp_t, ref_kp_m)):
        se = _chain_se(got)
        assert abs(float(got.mean()) - ref) < 4.0 * se + 0.05, (name, float(got.mean()), ref, se)
    # emissions: E[Sigma] = 1 and E[mu] = 0 for every owned feature, whatever the features
    for name, got, ref in (("Sigma", torch.tensor(sigma), 1.0), ("mu", torch.tensor(mu), 0.0)):
        se = _chain_se(got)
        assert abs(float(got.mean()) - ref) < 4.0 * se + 0.05, (name, float(got.mean()), ref, se)
