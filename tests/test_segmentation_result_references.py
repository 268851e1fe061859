"""The segmentation result after the sampler against hand-derived references: the progressive route alignment's use
of the coverage accumulated by earlier demonstrations, the median convention of the change-point posterior, the
coverage fractions that route grouping receives from ``segment``, and ``split``'s checks and its appended sample
for the shortest pieces. Every random draw is seeded; float64 throughout.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import lfd_torch.segmentation.segmentation as S
from lfd_torch.data import Demos
from lfd_torch.errors import ShapeMismatchError
from lfd_torch.segmentation import FixedSegmenter, multi_step_demos, segment

F64 = torch.float64


# ---------------------------------------------------------------------------------------------- route alignment
@pytest.mark.parametrize(
    "seqs, fracs, want",
    [
        # A = (5, 6, 5) is the skeleton; B = (5, 6) matches A's first 5 and the 6 (0.3 + 0.5 + 0.1 + 0.5 = 1.4
        # against 0.6 + 0.5 = 1.1 for the second 5 alone), so the first 5 carries 0.3 + 0.5 = 0.8 > 0.6: C = (5)
        # joins the first 5 (0.8 + 1 > 0.6 + 1), not the one A alone weighs more
        ([[5, 6, 5], [5, 6], [5]], [[0.3, 0.1, 0.6], [0.5, 0.5], [1.0]], ([5, 6, 5], [[0, 1, 2], [0, 1], [0]])),
        # the mirror image: B = (6, 5) matches the 6 and the second 5, which then carries 0.8 > 0.6
        ([[5, 6, 5], [6, 5], [5]], [[0.6, 0.1, 0.3], [0.5, 0.5], [1.0]], ([5, 6, 5], [[0, 1, 2], [1, 2], [2]])),
    ],
)
def test_align_route_matches_later_runs_by_the_coverage_accumulated_so_far(seqs, fracs, want):
    """Hand-derived (module docstring, progressive alignment): a route step's weight in the weighted LCS is the sum
    of the coverage fractions of every run already aligned to it, so a third demonstration whose single run could
    join either of two steps of its state joins the one the first two demonstrations cover most together. Every
    optimum here is unique (no tie-break involved)."""
    assert S._align_route(seqs, fracs) == want


# ---------------------------------------------------------------------------------------------- change point
@pytest.mark.parametrize("width", [2, 3, 4, 7, 8])
def test_flat_change_point_posterior_puts_the_switch_at_its_lower_median(width):
    """Reference (module docstring, item 3 and :func:`_refine_switch`): where the two states' likelihoods agree the
    posterior over tau = lo .. hi (width = hi - lo + 1 values) is flat, and the switch is its median, the smallest
    tau with P(tau' <= tau) >= 1/2 (an exact 1/2 at an even width counts): lo + ceil(width / 2) - 1; every sample's
    doubt is its distance in posterior mass from the switch, (t - lo + 1) / width before it, 1 - that from it on."""
    lo, hi = 5, 5 + width - 1
    ll = torch.zeros(20, 2, dtype=F64)
    switch, doubt = S._refine_switch(ll, 0, 1, lo, hi, 3)
    want = lo + (width + 1) // 2 - 1
    assert switch == want
    cdf = [(t - lo + 1) / width for t in range(lo, hi)]
    np.testing.assert_allclose(doubt.numpy(), [c if t < want else 1.0 - c for t, c in zip(range(lo, hi), cdf)],
                               rtol=0, atol=1e-15)


# ---------------------------------------------------------------------------------------------- routes in segment
def test_segment_gives_route_grouping_each_runs_share_of_its_demonstration(monkeypatch):
    """Reference (module docstring, routes): the coverage that groups demonstrations into routes is, for every run
    of a demonstration, its number of full-rate samples over the demonstration's length, so each demonstration's
    fractions sum to 1 and equal (end - start) / T_i of the pieces ``segment`` returns (unequal lengths)."""
    seen = []
    original = S._routes

    def spy(seqs, fracs):
        seen.append(([list(s) for s in seqs], [list(f) for f in fracs]))
        return original(seqs, fracs)

    monkeypatch.setattr(S, "_routes", spy)
    syn = multi_step_demos(torch.Generator().manual_seed(3), n_demos=2, n_steps=3, samples_per_step=40)
    seqs = syn.demos.sequences()
    demos = Demos.from_sequences([seqs[0], seqs[1][:-20]], dt=0.01, attractor=syn.demos.attractor)
    seg = segment(demos, generator=torch.Generator().manual_seed(3), max_samples=40, n_iterations=15, n_chains=2)
    assert len(seen) == 1
    _, fracs = seen[0]
    for i in range(seg.n_sequences):
        T = int(demos.lengths[i])
        want = [(b - a) / T for _, a, b in seg.pieces[i].tolist()]
        assert fracs[i] == pytest.approx(want, rel=0, abs=1e-15)
        assert sum(fracs[i]) == pytest.approx(1.0, abs=1e-12)


# ---------------------------------------------------------------------------------------------- split
def test_split_end_at_attractor_of_a_two_sample_piece_repeats_its_only_interval():
    """Reference (``split`` docstring): the appended sample comes one last sampling interval of the piece after its
    last sample, also for a piece of two samples (its only interval t_1 - t_0, uneven times), at g_m with zero
    velocity."""
    t = torch.tensor(np.cumsum(np.random.default_rng(21).uniform(0.01, 0.05, 40)))
    x = torch.stack([t, 0.5 * t.square()], -1)
    demos = Demos.from_sequences([x], times=[t])
    seg = FixedSegmenter([0.05])(demos)  # round(0.05 * 40) = 2: the first piece is samples 0, 1
    assert seg.pieces[0].tolist() == [[0, 0, 2], [1, 2, 40]]
    first = seg.split(demos, end_at_attractor=True)[0]
    assert int(first.lengths[0]) == 3
    assert float(first.times[0, 2]) == pytest.approx(float(t[1] + (t[1] - t[0])), rel=1e-12)
    torch.testing.assert_close(first.positions[0, 2], seg.attractors[0])
    assert float(first.velocities[0, 2].abs().max()) == 0.0


def test_split_refuses_other_lengths_even_where_the_end_points_match():
    """Property (``split`` docstring: the demonstrations that were segmented, same number and lengths): a
    demonstration that starts and ends where the segmented one does but holds one sample more (its last point
    repeated) is refused with ShapeMismatchError, with the end points kept and without them (a file saved before
    they were kept)."""
    t = torch.linspace(0.0, 1.0, 40, dtype=F64)
    x = torch.stack([t, torch.sin(3.0 * t)], -1)
    y = torch.stack([t, -t], -1)
    seg = FixedSegmenter([0.5])(Demos.from_sequences([x, y], dt=0.025))
    longer = Demos.from_sequences([torch.cat([x, x[-1:]]), y], dt=0.025)  # same first and last sample
    torch.testing.assert_close(S._endpoints(longer), seg.endpoints)
    with pytest.raises(ShapeMismatchError, match="lengths"):
        seg.split(longer)
    legacy = dataclasses.replace(seg, endpoints=None)
    with pytest.raises(ShapeMismatchError, match="lengths"):
        legacy.split(longer)
