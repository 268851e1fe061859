"""The Kalman evidence of experiments/diagnose_tolerance.py against the stacked Gaussian density it must equal."""

import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

from diagnose_tolerance import smooth_tolerance_evidence  # noqa: E402

F64 = torch.float64


def _stacked_log_density(z, u, c, labels, rho, q, tau2, field_sd):
    """log N(vec u; 0, Sigma) with Sigma built entry by entry: the fields' prior covariance between any two samples
    of one state, the AR(1) covariance q rho^|t - s| / (1 - rho^2) between two samples of one run, the white noise."""
    d = u.shape[-1]
    idx = [(i, t, int(labels[i][t])) for i in range(len(labels)) for t in range(labels[i].shape[0])]
    run_id, r = [], 0
    for j, (i, t, k) in enumerate(idx):
        if j > 0 and (idx[j - 1][0] != i or idx[j - 1][2] != k):
            r += 1
        run_id.append(r)
    n = len(idx)
    cov = torch.zeros(n * d, n * d, dtype=F64)
    eye = torch.eye(d, dtype=F64)
    for a, (i, t, k) in enumerate(idx):
        for b, (i2, t2, k2) in enumerate(idx):
            block = torch.zeros(d, d, dtype=F64)
            if k == k2:
                block += field_sd**2 * float(z[i, t] @ z[i2, t2]) * eye
            if run_id[a] == run_id[b] and q > 0:
                block += q * rho ** abs(t - t2) / (1 - rho**2) * eye
            if a == b:
                block += (float(c[i, t]) + tau2) * eye
            cov[a * d : (a + 1) * d, b * d : (b + 1) * d] = block
    x = torch.stack([u[i, t] for i, t, _ in idx]).reshape(-1)
    return float(torch.distributions.MultivariateNormal(torch.zeros(n * d, dtype=F64), cov).log_prob(x))


def test_kalman_evidence_equals_the_stacked_gaussian_density():
    """Property: for random regressors, directions and noise, with two sequences and a state that recurs (one
    field shared by two runs of state 0, a fresh AR deviation per run), the filter's log evidence equals log N of
    all directions stacked, for a white (q = 0) and two AR settings at once."""
    g = torch.Generator().manual_seed(0)
    N, T, d = 2, 7, 2
    z = torch.cat([torch.randn(N, T, d, generator=g, dtype=F64), torch.ones(N, T, 1, dtype=F64)], -1)
    u = torch.randn(N, T, d, generator=g, dtype=F64)
    c = 0.05 + 0.1 * torch.rand(N, T, generator=g, dtype=F64)
    labels = [torch.tensor([0, 0, 0, 1, 1, 0, 0]), torch.tensor([1, 1, 1, 1, 0, 0])]
    settings = [(0.0, 0.0, 0.04), (0.9, 0.02, 0.01), (0.5, 0.1, 0.0004)]
    rho, q, tau2 = (torch.tensor([s[j] for s in settings], dtype=F64) for j in range(3))
    got = smooth_tolerance_evidence(z, u, c, labels, rho, q, tau2, field_sd=0.7)
    want = [_stacked_log_density(z, u, c, labels, *s, field_sd=0.7) for s in settings]
    assert all(math.isfinite(w) for w in want)
    torch.testing.assert_close(got, torch.tensor(want, dtype=F64), rtol=1e-9, atol=1e-8)
    # the settings give different answers (a filter that ignored rho, q or tau2 would not match all three)
    assert min(abs(want[a] - want[b]) for a, b in ((0, 1), (0, 2), (1, 2))) > 0.1, want
