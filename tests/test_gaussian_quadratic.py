"""Quadratic-feature form of Gaussian log densities (lfd_torch.gmm.gaussian): w . phi(x - c) against the
Cholesky density kernel, and any quadratic e^T Q e + l^T e + c against its direct evaluation."""

from __future__ import annotations

import pytest
import torch

from lfd_torch.errors import ShapeMismatchError
from lfd_torch.gmm.gaussian import (
    gaussian_log_density,
    gaussian_quadratic_weights,
    quadratic_features,
    quadratic_weights,
)

F64 = torch.float64


@pytest.mark.parametrize("d", [1, 2, 3])
def test_quadratic_weights_reproduce_any_quadratic(d: int) -> None:
    gen = torch.Generator().manual_seed(d)
    K, n = 5, 60
    Q = torch.randn(K, d, d, generator=gen, dtype=F64)  # not symmetric: only Q + Q^T may matter
    lin = torch.randn(K, d, generator=gen, dtype=F64)
    c = torch.randn(K, generator=gen, dtype=F64)
    e = torch.randn(n, d, generator=gen, dtype=F64)
    phi = quadratic_features(e.T.contiguous())
    assert phi.shape == (d * (d + 1) // 2 + d + 1, n)
    got = quadratic_weights(Q, lin, c) @ phi  # (K, n)
    ref = torch.einsum("ni,kij,nj->kn", e, Q, e) + lin @ e.T + c.unsqueeze(-1)
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("d", [1, 2, 3])
def test_gaussian_quadratic_weights_match_the_density_kernel(d: int) -> None:
    gen = torch.Generator().manual_seed(10 + d)
    K = 6
    mean = torch.randn(K, d, generator=gen, dtype=F64)
    L = torch.randn(K, d, d, generator=gen, dtype=F64)
    cov = L @ L.transpose(-1, -2) + 0.1 * torch.eye(d, dtype=F64)
    center = mean.mean(0)
    x = 3 * torch.randn(80, d, generator=gen, dtype=F64)
    got = gaussian_quadratic_weights(mean, cov, center) @ quadratic_features((x - center).T.contiguous())
    torch.testing.assert_close(got.T, gaussian_log_density(x, mean, cov), rtol=1e-11, atol=1e-10)
    # float32 in, float32 out
    w32 = gaussian_quadratic_weights(mean.float(), cov.float(), center.float())
    assert w32.dtype == torch.float32 and quadratic_features(x.float().T.contiguous()).dtype == torch.float32


def test_quadratic_helpers_reject_bad_shapes() -> None:
    with pytest.raises(ShapeMismatchError, match="points"):
        quadratic_features(torch.zeros(3, dtype=F64))
    with pytest.raises(ShapeMismatchError, match="center"):
        eye = torch.eye(2, dtype=F64).expand(2, 2, 2)
        gaussian_quadratic_weights(torch.zeros(2, 2, dtype=F64), eye, torch.zeros(3, dtype=F64))
