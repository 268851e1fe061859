"""Shared fixtures: one torch thread, a fresh seeded generator per test, CUDA marker, the sampler runs of segment."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture
def generator() -> torch.Generator:
    """A CPU generator seeded per test; tests never touch the global RNG."""
    return torch.Generator().manual_seed(20240521)


def cuda_available() -> bool:
    return torch.cuda.is_available()


requires_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")


def capture_runs(monkeypatch) -> list:
    """The sampler runs (``_Run``) that ``segment`` makes from here on, in order (their observations and scoring),
    made outside inference mode so that the test can call their methods."""
    import lfd_torch.segmentation.sampler as sampler_module

    runs = []
    original = sampler_module._Run.sample

    def capture(self):
        runs.append(self)
        return original(self)

    monkeypatch.setattr(sampler_module._Run, "sample", capture)
    monkeypatch.setattr(sampler_module, "_INFERENCE_MODE", False)
    return runs


def certified_primitive(d: int, K: int, seed: int):
    """A certified ``StablePrimitive`` with a goal far from the origin, non-symmetric A_k and P != I:
    A_k = P^-1 (-Q_k / 2 + skew_k), so that A_k^T P + P A_k = -Q_k (float64, drawn from ``seed``)."""
    import numpy as np

    from lfd_torch.ds import StablePrimitive
    from lfd_torch.gmm import GMM

    rng = np.random.default_rng(seed)
    Qr, _ = np.linalg.qr(rng.standard_normal((d, d)))
    P = Qr @ np.diag(np.logspace(0, -1, d)) @ Qr.T
    P = 0.5 * (P + P.T)
    A = []
    for _ in range(K):
        B = rng.standard_normal((d, d))
        Qk = B @ B.T + 0.5 * np.eye(d)
        Sk = rng.standard_normal((d, d))
        A.append(np.linalg.solve(P, -0.5 * Qk + (Sk - Sk.T)))
    g = 3.0 + rng.standard_normal(d)
    means = g + 2.0 * rng.standard_normal((K, d))
    covs = []
    vcovs = []
    for _ in range(K):
        B = rng.standard_normal((d, d))
        covs.append(B @ B.T / d + 0.4 * np.eye(d))
        B = rng.standard_normal((d, d))
        vcovs.append(2.0 * (B @ B.T / d + 0.3 * np.eye(d)))
    w = rng.uniform(0.5, 1.5, K)

    def T(a):
        return torch.tensor(np.asarray(a), dtype=torch.float64)

    gmm = GMM(T(w / w.sum()), T(means), T(covs))
    return StablePrimitive(gmm=gmm, A=T(A), attractor=T(g), P=T(P), velocity_covariances=T(vcovs))
