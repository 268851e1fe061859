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
