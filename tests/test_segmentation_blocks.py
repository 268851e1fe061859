"""The block emission (lfd_torch.segmentation.blocks): block means and the Gaussian evidence of the increments."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError
from lfd_torch.segmentation import segment
from lfd_torch.segmentation.blocks import BlockMeans, block_log_evidence, block_means
from lfd_torch.segmentation.sampler import BetaProcessHMMSampler


def test_block_means_are_the_means_of_the_samples_nearest_each_grid_point():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(50, 2, generator=g, dtype=torch.float64)
    length = torch.rand(50, generator=g, dtype=torch.float64).cumsum(0)
    grid = torch.tensor([0, 7, 15, 22, 30, 41, 49])
    means, lengths, counts = block_means(x, grid, length)
    for j, t in enumerate(grid.tolist()):  # naive: every sample to its nearest grid point, ties to the later one
        near = [i for i in range(50) if min(range(7), key=lambda k: (abs(i - int(grid[k])), -k)) == j]
        assert counts[j] == len(near)
        assert torch.allclose(means[j], x[near].mean(0)) and torch.allclose(lengths[j], length[near].mean())
    with pytest.raises(ShapeMismatchError):
        block_means(x, grid, length[:-1])


def test_block_evidence_is_the_gaussian_of_its_written_out_model():
    """Two sequences, a straight state then a curved one: the evidence is log N(y; 0, Omega + X Lambda X^T) of the
    increments, with every column and covariance entry written out here by loops (scipy as the reference)."""
    g = torch.Generator().manual_seed(1)
    N, T, d = 2, 7, 2
    p = d + 1
    xbar = torch.randn(N, T, d, generator=g, dtype=torch.float64).cumsum(1) * 0.1
    sbar = torch.rand(N, T, generator=g, dtype=torch.float64).cumsum(1) * 0.1
    var = 0.01 + 0.01 * torch.rand(N, T, generator=g, dtype=torch.float64)
    z = torch.cat([torch.randn(N, T, d, generator=g, dtype=torch.float64), torch.ones(N, T, 1, dtype=torch.float64)], -1)
    zmid = 0.5 * (z[:, 1:] + z[:, :-1])
    valid = torch.ones(N, T, dtype=torch.bool)
    valid[1, 6] = False  # the second sequence is one point shorter
    labels = torch.tensor([[[0, 0, 0, 1, 1, 1, 1], [0, 0, 1, 1, 1, 1, 1]]])
    straight = torch.tensor([[True, False]])
    tol, spread, slope = 0.2, 0.05, 1.0
    mine = float(block_log_evidence(xbar, sbar, var, zmid, valid, labels, straight, tolerance=tol, spread=spread,
                                    slope_scale=slope)[0])

    M = T - 1
    rows = [(i, j) for i in range(N) for j in range(M)]
    names = ["b"] + [f"b{i}" for i in range(N)] + [f"B{a}" for a in range(p)] + [f"c{i}" for i in range(N)]
    prior = {"b": 1.0 / d, **{f"b{i}": spread**2 for i in range(N)}, **{f"B{a}": slope**2 for a in range(d)},
             f"B{d}": 1.0, **{f"c{i}": spread**2 for i in range(N)}}
    X = np.zeros((len(rows), len(names)))
    omega = np.zeros((len(rows), len(rows)))
    for r, (i, j) in enumerate(rows):
        ok = bool(valid[i, j] and valid[i, j + 1])
        if not ok:
            omega[r, r] = 1.0
            continue
        ds = float(sbar[i, j + 1] - sbar[i, j])
        omega[r, r] = float(var[i, j] + var[i, j + 1])
        if j + 1 < M and bool(valid[i, j + 2]):
            omega[r, r + 1] = omega[r + 1, r] = -float(var[i, j + 1])
        a, b = int(labels[0, i, j]), int(labels[0, i, j + 1])
        if a != b:
            omega[r, r] += ds**2  # the corner: a free displacement
        elif a == 0:  # straight
            X[r, names.index("b")] = ds
            X[r, names.index(f"b{i}")] = ds
        else:  # curved: the field on the midpoint regressors, the demonstration's offset, the tolerance
            for k in range(p):
                X[r, names.index(f"B{k}")] = ds * float(zmid[i, j, k])
            X[r, names.index(f"c{i}")] = ds
            omega[r, r] += (ds * tol) ** 2
    cov = omega + X @ np.diag([prior[n] for n in names]) @ X.T
    y = np.stack([(xbar[i, j + 1] - xbar[i, j]).numpy() if bool(valid[i, j] and valid[i, j + 1]) else np.zeros(d)
                  for i, j in rows])
    ref = sum(multivariate_normal(np.zeros(len(rows)), cov).logpdf(y[:, a]) for a in range(d))
    assert mine == pytest.approx(ref, abs=1e-8)


def test_block_emission_options_are_checked():
    with pytest.raises(InvalidArgumentError, match="block_tolerance"):
        BetaProcessHMMSampler(block_emission=True, block_tolerance=0.0)
    with pytest.raises(InvalidArgumentError, match="block_emission"):
        BetaProcessHMMSampler(block_emission=1)
    x = [torch.linspace(0, 1, 40, dtype=torch.float64).unsqueeze(-1).expand(40, 2).clone()]
    with pytest.raises(InvalidArgumentError, match="blocks"):
        BetaProcessHMMSampler(block_emission=True, n_iterations=2).run(x, x, torch.Generator().manual_seed(0))
    bad = BlockMeans([torch.zeros(3, 2, dtype=torch.float64)], [torch.zeros(3, dtype=torch.float64)],
                     [torch.ones(3, dtype=torch.float64)], 0.01)
    with pytest.raises(ShapeMismatchError):
        BetaProcessHMMSampler(block_emission=True, n_iterations=2).run(x, x, torch.Generator().manual_seed(0),
                                                                       blocks=bad)


def test_block_emission_finds_the_mild_corner_the_direction_emission_merges():
    """straight_const_3d, one demonstration, data case 2 of the benchmark: a 34-degree corner between legs of 20 and
    7 grid points. The defaults merge it; the block emission (no position term) finds all four switches within 3 %
    of the length."""
    from lfd_torch.segmentation.synthetic import FAMILIES

    import zlib

    seed = (zlib.crc32(b"straight_const_3d") + 7919 * 2) % (2**31)  # bench_segmentation.data_seed(family, 2)
    syn = FAMILIES["straight_const_3d"](torch.Generator().manual_seed(seed), 1)
    truth = syn.switch_times[0].tolist()
    T = int(syn.demos.lengths[0])
    for block, expected in ((False, 3), (True, 4)):
        seg = segment(syn.demos, generator=torch.Generator().manual_seed(2), block_emission=block,
                      position_weight=0.0 if block else None)
        cuts = [int(a) for _, a, _ in seg.pieces[0].tolist()][1:]
        assert len(cuts) == expected, (block, cuts)
    assert all(abs(c - t) <= 0.03 * T for c, t in zip(cuts, truth)), (cuts, truth)
