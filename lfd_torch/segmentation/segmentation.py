"""From BP-GM-HMM state sequences to steps, routes, attractors and subtask spaces (paper Sec. III-A/B, Table I).

Notation:
    N  demonstrations (sequences), T_i samples each, d state dimension
    S  HMM states (features) of the returned sample; M steps (0-based in code); R routes
    labels   N tensors (T_i,) long, step of every sample
    pieces   N tensors (n_i, 3) long, rows (step, first sample, end sample exclusive) in time order
    routes   R tuples of step indices in execution order; route_of (N,) the route of each demonstration
    attractors  (M, d) g_m
    subtask space A_m: a set of Gaussians over positions (below); log p(x | A_m) in
        :meth:`Segmentation.log_density`.

The model decides (NOTES.md sec. 2). A step of a demonstration is a maximal run of one HMM state: nothing
after the sampler creates, removes, merges or moves a step across a state switch. The steps come from:
    1. the emission (:mod:`.field`): each state is an affine field of motion directions over positions, so a
       state switch is where the direction of motion stops being one smooth function of the position (a corner,
       a reversal, a cusp), not where a Gaussian would like to cut a long leg in two; with ``position_weight``
       the emission also carries a tempered Gaussian on the positions, which keeps distant pieces in different
       states (:mod:`.sampler`, "Position"). By default (``block_emission``) the labelling returned is scored on
       the block means of the positions instead of the local directions (:mod:`.blocks`): a straight state is a
       line with the lever arm of its length, a curved one the affine field within a tolerance; and the positions
       as a mixture over space (``position_mixture``), so a cut along a leg earns nothing from the Gaussians;
    2. a minimum duration: a run of a state lasts at least ``min_length`` samples. This is part of the HMM
       (explicit-duration states, :func:`~lfd_torch.segmentation.transitions.expand_min_duration`), not a
       post-processing rule, and it is what NOTES.md sec. 2 asks of short runs: a sample whose velocity straddles a
       corner cannot open a step of its own;
    3. the sampler works on a coarse grid of n = ceil(T / k) points per sequence (k = ceil(T / ``max_samples``),
       the time stride). Three choices make the observations what the emission assumes:
       (a) velocities: the velocity at t is the least-squares slope of the positions x[t - k .. t + k]
           (:func:`scale_velocities`). Under white position noise sigma it is the minimum-variance linear unbiased
           estimate of a constant velocity, with noise sigma / (dt sqrt(sum_j j^2)) per axis, about 2 (k / 3)^(1/2)
           times less than that of the chord between two grid points (3 times for k = 7): the evidence of a
           direction change grows about 4 k / 3 times, so short legs and mild turns are seen;
       (b) their noise: the reliability weight w_t of the emission (:mod:`.field`) uses that noise sample by
           sample (:func:`velocity_noise`), larger where the window is cut by an end of the sequence. With one
           noise level for all samples, the first and last velocities (the start and end rests) were trusted as if
           they were interior ones, and their random directions opened steps of their own. The position noise
           behind it is fitted as AR(1) (:func:`position_noise_model`): noise correlated over a few samples leaves
           the slopes several times noisier than a white extrapolation from lag-one differences says;
       (c) the grid is equally spaced in path length, not in time (:func:`path_grid`): the path length is the sum
           of the unbiased speed estimates (||v_t||^2 - d sigma_v,t^2)_+^(1/2) dt. A state is a field of
           directions over positions, a geometric object; its likelihood should not depend on how long the robot
           dwells somewhere. On a time grid a minimum-jerk rest at a corner holds several grid points whose
           directions are noise (w_t small but not 0, because the speed estimate is noisy); a state that fits
           those few random directions a little better than both neighbours collects more than the cost of one
           more transition and opens a short extra step at the corner. On the path-length grid a rest holds no
           grid point of its own, a leg gets grid points in proportion to its length whatever its timing, and
           the minimum duration (item 2) becomes a minimum path length: ``min_length`` is read as a fraction of the
           path (D = ceil(min_length n / T) grid points).
       The regressors are the raw positions of the grid samples. Tried and not kept (a one-off patch): the value of
       each velocity's least-squares line at its own sample, whose noise is (2 k + 1)^(1/2) times smaller (a strongly
       curved field turns position noise into direction noise): every switch on 85.4 % of the 280 synthetic cases
       against 86.4 %, the constant-speed scoop unchanged (0 / 1 of 10); the velocity noise dominates there.
       Each switch is then placed at full rate. With the direction emission (``block_emission=False``) by the
       sampler's own likelihood: between the two states that the model put on either side, the change point posterior
       p(t) ∝ exp(sum_{t' < t} l_a(t') + sum_{t' >= t} l_b(t')) / k) over t between the midpoints of the
       neighbouring runs, l the field log-likelihood of the full-rate samples (each weighted 1 / k because k
       full-rate samples carry the information of one grid point) under the fields
       of the two states in the returned sample; the switch is its median. l is the additive noise model of
       :mod:`.field`, u_t ~ t(B_k z_t, Psi_k + c_t I) with c_t = sigma_v,t^2 / s_t^2 the propagated velocity noise,
       of which the sampler's Psi_k / w_t is the conjugate form (the two agree at full speed and for
       Psi_k = sigma_u^2 I). Only the additive form carries no evidence where a sample carries no direction: with
       Psi_k / w_t the ratio of two states' densities tends to (|Psi_b| / |Psi_a|)^(1/2) as w_t -> 0, so every
       sample of a rest voted for the state with the tighter field and the posterior was pulled across the rest
       (switches at dwelling corners 3-4 % of the length off); with Psi_k + c_t I it tends to 1. This cannot create or
       remove a step: it only resolves the time of a switch that the sampler found. At a rest the samples carry no
       direction information (w_t -> 0), the posterior is flat over the rest and the switch falls in its middle.
       With the dwell term (:mod:`.dwell`) the posterior also carries the term's log ratio of a run starting at t,
       averaged over the grid's phase (:func:`_dwell_switch_prior`): which grid interval holds a rest is an
       accident of where the grid points fall, and weighting every t by the interval that contains it put the
       switch in the middle of that interval, up to half a grid spacing (several % of a dwelling leg) from the
       rest when the rest sits near a grid point.
       Under the block emission (the default) the labelling was chosen by the evidence of block means, which has no
       full-rate form, and the direction fields are another likelihood: alone they moved switches by several grid
       intervals from where the block evidence put them (constant-speed scoop, one demonstration, case 0: the first
       switch at sample 215, 188 as below, the truth 193). So the grid interval is the model's and only the place
       inside it is the direction likelihood's: P(tau) = P(j) p(tau | j), P(j) ∝ exp(collapsed score of the labelling
       whose second run starts at grid point j, every other switch as returned) over the positions that keep both
       runs at least D long (:attr:`~.sampler.SamplerResult.switch_scores`, the block components held), and
       p(tau | j) the posterior above restricted to the samples of interval j, (grid[j - 1], grid[j]]
       (:func:`_refine_switch_on_grid`). A rest lies inside one interval (the path-length grid gives it no point),
       so a dwelling corner is placed as before. A full-rate form of the block evidence itself was tried and lost
       the dwelling corners (``experiments/segmentation_studies.md``, "The full-rate switch refinement under the
       block emission's own model").
Known limit (measured, not fixed): a step is what ONE affine direction field describes, so a narrow hairpin
traversed at speed and a reversal at a near-rest are switches to this model whatever a task's semantics say.
On the Baxter scooping demonstration (``lfd_torch.robot.demonstration``, one demonstration, Preprocess defaults)
the generator's scoop stage is a U about 12 cm deep and a few cm wide (down into the sugar, drag, up) and its
transport stage descends onto the cup, tips the spoon with the tip nearly still (0.3-1.5 cm/s at the slowest,
seeds 0-3 without tremor) and lifts away up and back. The model finds 5-7 steps, never 3, on seeds 0-9
(approach, down, drag-and-up, carry, lift away; sometimes the U or the carry cut once more). On the sampler's
grid the emission plus the MNIW field prior of the steps found exceed those of the three ground-truth stages
(each labelling with its posterior-mean fields) by 130-180 nats (``experiments/bench_scooping_segmentation.py
--evidence``), against about 3.4 nats for each extra switch under the default sticky transitions. On seed 0 one
field over the whole U fits its samples at about 0.5 nats each against 2.9 for a straight leg, and its slope
(3-5 on the standardised scale, against a prior standard deviation of 1) costs another ~26 nats of prior
density. No variant tried gives 3 steps on any seed: a 4x looser slope and offset prior (seeds 0-5), quadratic
fields (seeds 0-5), ``max_samples=200`` with affine or quadratic fields, ``stickiness=500``,
``min_length=0.12``, ``direction_noise=0.5`` (seeds 0-3 each). The cue that separates the generator's stages
from those within-stage turns is the 0.2-0.5 s rest before each stage switch, and the path-length grid (item 3c)
deliberately gives a rest no grid point (these figures are of the earlier defaults, ``selection="joint"`` with
directions alone). A fixed charge for a switch made at speed would have to be 65-90 nats to keep the two
within-stage turns; by the same computation (merging two true steps) the true corners of ``straight_const_3d``
(seeds 0-5, 1 demonstration) carry 18-87 nats, those of 30-50 degrees 18-25, so such a charge would remove most
true corners met at speed. The dwell term (:mod:`.dwell`, on by default) lets the data say how much a pause marks
a switch instead: the demonstration's pauses are found as switches, but the learned charge for a switch at speed
(a few nats) does not remove the within-stage cuts, and the count stays 5
(``experiments/bench_scooping_segmentation.py``, results/tables/bench_scooping_segmentation_directions.json;
these figures are the direction emission's; with the block emission, the default since, 5 steps on every seed as
well, results/tables/bench_scooping_segmentation.json). Measured as
turns of the path (``--turns``: the angle between the chords over 1.25 % of the path length on either side), the
cut in the U is a turn at speed of 40-53 degrees, in the range of the constant-speed corners of the synthetic
benchmark (34-148) that the model is required to cut, and the cut over the cup a slow near reversal of 149-172
degrees (the out-and-back families' reversals must be cut too); the turns the model must keep inside a step (the
middles of curved legs and of the scoop hook) are at most 17 degrees.
The synthetic ``scoop_*`` families showed the same limit at the approach-hook corner; with the dwell term the
dwelling variant is found (a pause marks each true corner), the constant-speed one is not (figures of the earlier
defaults, from a one-off analysis
that scores both labellings with the sampler's collapsed score; no project command reproduces them): the hook starts 30-65 degrees
below the approach and turns back up through the approach's direction, so its first third runs within about 30
degrees of the approach; the model puts the first switch there, 25-60 samples after the corner, and its collapsed
score prefers that to the true split by 2-7 nats even with 0.1 % position noise (seeds 0-4, constant and dwelling
timing): a property of the emission, not of the noise. Measured without a gain on the 280 synthetic cases or
without removing the bias: a Gaussian emission (``robust_dof=None``), ``max_samples`` 160, a three times looser
slope prior, and a position term (the NIW evidence of each state's positions, weight 0.1-1), which at weight 1
makes splitting a long curved leg win by 14-21 nats.
Steps across demonstrations are matched by the model's features, not by their order (item 2 of the design):
each demonstration is the sequence of the states of its runs; two demonstrations belong to one route when the
states they share (a longest common subsequence of their run states) cover at least half of the samples of
each, and within a route the run sequences are merged by that alignment into one ordered list of steps (a
progressive alignment: a run whose state matches a step of the route joins it, any other run becomes a step of
its own at its place in the order). So a demonstration may skip a step or add one; it is never cut to a
consensus count. A state may recur in several steps (two runs of one state are two steps). A route is therefore
the merge of its demonstrations' step orders and may hold alternatives one after the other; what a robot can
execute is one of those orders (:attr:`Segmentation.demonstrated_routes`, the skill engine's routes).

Attractor g_m: the mean over the pieces of step m of their last sample (the paper's eq. under Table I writes a
sum; it means the mean); the last step of every route ends at the task attractor ``Demos.attractor``.
On LASA Multi_Models_1-4 g_m is within 2 % of the data span of the nearest of its demonstrations, but 1.6 / 2.9 /
2.5 / 4.5 % from the farthest (``experiments/bench_segmentation_seeds.py``): the demonstrations switch at places
spread along and across their paths, and the mean of points along a curve lies inside it. Tried and not kept
(one-off patches, seed 0): (1) g_m as the mode of the product over pieces of their end-point densities
sum_tau P(tau) N(g; x(tau - 1), noise) with P the change-point posterior below (item 3) over its whole window:
1.1 / 1.6 / 1.1 / 2.7 % from the farthest demonstration, but up to 21 % of the span from every piece's end (the
posterior's tails reach where the paths happen to meet), so a primitive would converge far from where its pieces
end; (2) the same within each switch's central 99 % credible interval: 1.5 / 2.8 / 2.5 / 4.4 % (the posteriors are
narrow, the mode is the mean again); (3) the sample of those intervals that all paths pass nearest (least
squares): 1.6 / 3.3 / 3.3 / 3.7 %. On Multi_Models_4 route {0-3} no point within 5 % of the span of the first
step's four ends is within 2 % of all four demonstrations (the best is 3.1 %): there an attractor at the end of
the step cannot lie on every demonstration.
Subtask space A_m (paper Sec. III-B/IV; NOTES.md sec. 2 reads it as "the emission Gaussian(s) of the state(s) of
step m"). The emission here models directions, not positions, so the position Gaussians are taken from the samples
at the model's resolution:
    (a) stretches: one Gaussian per stretch of ``min_length`` samples of every piece (mean and covariance of the
        stretch plus the position noise variance estimated from the data), owned by the piece's step;
    (b) junctions: one Gaussian per switch, from the samples around it weighted by the posterior probability that
        their step label is wrong, u_t = P(tau <= t) before the switch and P(tau > t) from it on, tau ~ the change
        point posterior of item 3 (weighted mean and covariance plus the noise variance). It belongs to both steps
        of the switch. At a rest the direction reliability w_t -> 0 (:mod:`.field`), the emission cannot tell the
        two states apart, the posterior of tau is flat over the rest and the junction covers it; at a sharp corner
        the posterior is peaked and the junction is a point-sized Gaussian at the corner.
A_m is the set of the Gaussians the model uses for the samples of step m: its stretches, its junctions, and the
most responsible Gaussian (the largest density N(x_t; mu_j, Sigma_j) over all j) of every sample x_t of step m,
whichever step built it (the hard assignment of the samples to the Gaussians, as the Viterbi path is for the
HMM's states). Its density is that of the most responsible member (the classification likelihood),

    p(x | A_m) = max_{j in A_m} N(x; mu_j, Sigma_j),   ``space_weights[m, j]`` = 1 if j in A_m else 0.

Consequences: (i) every training sample x_t of step m lies in A_m in the sense of paper Sec. IV: its most
responsible Gaussian j* is in A_m, so p(x_t | A_m) = max_j N(x_t; mu_j, Sigma_j) >= p(x_t | A_m') for every m'.
(ii) Where two steps occupy the same place (the rest at a junction, an out-and-back leg, two legs crossing) they
share Gaussians and their densities tie there: the position alone cannot tell those steps apart, and a state there
belongs to both. (iii) Away from the data p(x | A_m) falls off like a Gaussian; a point is in A_m only if a
Gaussian built on the data near it is in A_m. Why not the equal-weight mixture of the step's own stretches (the
earlier construction): at a minimum-jerk rest the last samples of step m and the first of step m + 1 are the same
points up to noise; any position density that gives them to one step loses them for the other, and with weights
1 / J_m the shorter step took the whole rest, leaving 5-15 % of the longer step's samples outside its own space.
"""

from __future__ import annotations

import functools
import math
import numbers
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from lfd_torch.data import Demos
from lfd_torch.data.demos import MIN_SAMPLES
from lfd_torch.errors import (
    InvalidArgumentError,
    InvalidDemoError,
    InvalidIndexError,
    NonFiniteError,
    ShapeMismatchError,
    SolverError,
    StoreError,
    TooFewSamplesError,
)
from lfd_torch.gmm import GaussianBank, gaussian_log_density
from lfd_torch.segmentation.blocks import BlockMeans, block_means
from lfd_torch.segmentation.dwell import dwell_covariate
from lfd_torch.segmentation.field import field_log_likelihood_additive, field_observations
from lfd_torch.segmentation.sampler import BetaProcessHMMSampler, SamplerResult
from lfd_torch.utils import FLOAT_DTYPES, check_path, check_tensor

__all__ = [
    "Segmentation",
    "segment",
    "BPGMHMMSegmenter",
    "FixedSegmenter",
    "NoSegmenter",
    "runs",
    "resolve_min_length",
    "SegmentationWarning",
    "SCHEMA_VERSION",
]


class SegmentationWarning(UserWarning):
    """A segmentation result a user should look at (e.g. a demonstration that forms a route of its own)."""


SCHEMA_VERSION = 3
DEFAULT_MIN_LENGTH = 0.04  # shortest step, fraction of a demonstration (``segment``'s default)
MAX_GRID = 1000  # largest ``max_samples``: the sweep costs O(T (K D)^2) with D ~ min_length T (T^3 in T)


# ---------------------------------------------------------------------------------------------- result
@dataclass(frozen=True, eq=False)
class Segmentation:
    """Steps of a set of demonstrations (see the module docstring for notation).

    Attributes:
        labels: N tensors (T_i,) long, step of every sample.
        pieces: N tensors (n_i, 3) long, (step, start, end) of each piece of demonstration i in time order.
        attractors: (M, d) g_m.
        routes: R tuples of step indices in execution order.
        route_of: (N,) long route of every demonstration.
        space_mean: (J, d) means of the Gaussians of the subtask spaces.
        space_covariance: (J, d, d).
        space_weights: (M, J) membership of the Gaussians in the subtask spaces (1: Gaussian j belongs to A_m, 0: it
            does not; a Gaussian may belong to several steps); log p(x | A_m) = max_j log(w_mj N_j(x)).
        states: N tensors (T_i,) long HMM state of every sample (the step index when there is no HMM).
        step_state: (M,) long HMM state of every step (-1 without an HMM).
        sampler: the sampler's result (trace, acceptance), None without an HMM.
        info: free-form diagnostics (timings, strides, noise estimates).
        endpoints: (N, 2, d) first and last sample of every segmented demonstration, against which :meth:`split`
            checks the demonstrations it is given (None in files saved before it was kept).
    """

    labels: tuple[Tensor, ...]
    pieces: tuple[Tensor, ...]
    attractors: Tensor
    routes: tuple[tuple[int, ...], ...]
    route_of: Tensor
    space_mean: Tensor
    space_covariance: Tensor
    space_weights: Tensor
    states: tuple[Tensor, ...]
    step_state: Tensor
    sampler: SamplerResult | None = None
    info: dict[str, Any] = field(default_factory=dict)
    endpoints: Tensor | None = None

    @property
    def n_steps(self) -> int:
        return self.attractors.shape[0]

    @property
    def n_sequences(self) -> int:
        return len(self.labels)

    @property
    def n_routes(self) -> int:
        return len(self.routes)

    @property
    def dim(self) -> int:
        return self.attractors.shape[1]

    def switches(self, i: int) -> list[int]:
        """First samples of the pieces of demonstration i after its first (its step switches)."""
        return self.pieces[self._sequence(i)][1:, 1].tolist()

    def step_sequence(self, i: int) -> list[int]:
        """Steps demonstration i visits, in time order."""
        return self.pieces[self._sequence(i)][:, 0].tolist()

    @functools.cached_property
    def demonstrated_routes(self) -> tuple[tuple[int, ...], ...]:
        """The step orders the demonstrations execute: each distinct :meth:`step_sequence`, completed by its route's
        last step when it ends before it (every route ends at the task attractor). In route order; within a route
        the orders most demonstrations execute first, then by first appearance.

        A route is the merge of its demonstrations' step orders (module docstring), so where they skip different
        steps it holds alternatives one after the other (digit strokes written two ways: (0, 3, 4) and (0, 1, 2, 4)
        make the route (0, 1, 2, 3, 4)); executing the merged route visits both alternatives. These orders are the
        Sequence nodes a behaviour tree can execute; the choice among them is the Fallback's (paper Sec. III-B).
        With one order per route they are the routes.
        """
        orders: list[tuple[int, ...]] = []
        for r, route in enumerate(self.routes):
            count: dict[tuple[int, ...], int] = {}
            for i in range(self.n_sequences):
                if int(self.route_of[i]) != r:
                    continue
                seq = tuple(self.step_sequence(i))
                if seq[-1] != route[-1]:
                    seq = seq + (route[-1],)
                count[seq] = count.get(seq, 0) + 1  # dicts keep first appearance, sorted() is stable
            orders.extend(sorted(count, key=lambda s: -count[s]) or [route])
        return tuple(orders)

    def _sequence(self, i: int) -> int:
        if isinstance(i, bool) or not isinstance(i, numbers.Integral) or not 0 <= i < self.n_sequences:
            raise InvalidIndexError(f"i must be a demonstration index in 0..{self.n_sequences - 1}, got {i!r}")
        return int(i)

    def log_density(self, x: Tensor) -> Tensor:
        """log p(x | A_m) = max_j [log w_mj + log N(x; mu_j, Sigma_j)] for every step (module docstring).

        Args:
            x: (..., d) states, real floating point, finite.

        Returns:
            (..., M) log densities.

        Raises:
            InvalidArgumentError: x is not a real floating-point tensor. ShapeMismatchError: its last axis is not d.
            NonFiniteError: it holds NaN or Inf.
        """
        if not isinstance(x, Tensor):
            raise InvalidArgumentError(f"x must be a torch.Tensor of shape (..., {self.dim}), got {type(x).__name__}")
        if x.ndim == 0 or x.shape[-1] != self.dim:
            raise ShapeMismatchError(f"x has shape {tuple(x.shape)}, the segmentation needs (..., {self.dim})")
        if not x.dtype.is_floating_point:
            raise InvalidArgumentError(f"x must hold real floating-point numbers, got {x.dtype}")
        from lfd_torch.utils import safe_magnitude

        if not bool((x.abs() <= safe_magnitude(x.dtype)).all()):  # squared distances of larger x overflow
            raise NonFiniteError(f"x contains NaN, Inf or a magnitude above {safe_magnitude(x.dtype):.3g}")
        lead = x.shape[:-1]
        flat = x.reshape(-1, self.dim).to(self.space_mean)
        bank, index, logw = self._density_tables
        comp = bank.log_density_fm(flat.T)  # (J, n), feature-major
        # each step gathers only its own Gaussians, (M, J_m max, n) instead of the dense (n, M, J); the reduction
        # runs over a middle axis with the points contiguous (several times faster than over a short last axis)
        members = comp.index_select(0, index.reshape(-1)).view(*index.shape, -1) + logw.unsqueeze(-1)
        out = members.amax(1).T  # (n, M): the most responsible member
        return out.reshape(*lead, self.n_steps)

    @functools.cached_property
    def _density_tables(self) -> tuple[GaussianBank, Tensor, Tensor]:
        """The subtask-space Gaussians with cached factors, and per step the indices of its Gaussians (M, J_max)
        with their log weights (-inf on padding)."""
        w = self.space_weights.to(self.space_mean)
        rows = [torch.nonzero(w[m] > 0).reshape(-1) for m in range(w.shape[0])]
        width = max(1, max(r.numel() for r in rows))
        index = torch.zeros((len(rows), width), dtype=torch.long, device=w.device)
        logw = torch.full((len(rows), width), float("-inf"), dtype=w.dtype, device=w.device)
        for m, r in enumerate(rows):
            index[m, : r.numel()] = r
            logw[m, : r.numel()] = torch.log(w[m, r])
        return GaussianBank(self.space_mean, self.space_covariance), index, logw

    def other_log_density(self, x: Tensor) -> Tensor:
        """log p(x | A_m-) = the largest log p(x | A_m') over the other steps m' != m (NOTES.md sec. 2).

        With a single step there is no other region: -inf.

        Args:
            x: (..., d).

        Returns:
            (..., M).
        """
        ld = self.log_density(x)
        M = self.n_steps
        if M == 1:
            return torch.full_like(ld, float("-inf"))
        eye = torch.eye(M, dtype=torch.bool, device=ld.device)
        masked = ld.unsqueeze(-2).masked_fill(eye, float("-inf"))  # (..., M, M): row m hides m
        return masked.amax(-1)

    def membership(self, x: Tensor) -> Tensor:
        """(..., M) bool: x lies in A_m, i.e. p(x | A_m) >= p(x | A_m-) (the test of paper Sec. IV)."""
        return self.log_density(x) >= self.other_log_density(x)

    def split(self, demos: Demos, *, end_at_attractor: bool = False) -> list[Demos]:
        """Cut every demonstration into its steps.

        A piece ends where its demonstration reaches the step switch, not exactly at g_m (g_m is the mean of the
        pieces' end points, or the task attractor for the last step of a route), and its last velocity is the
        demonstration's velocity there. Primitives fitted to the pieces must tolerate that, or use
        ``end_at_attractor=True``.

        Args:
            demos: the demonstrations that were segmented (same number and lengths).
            end_at_attractor: (bool) append one sample at g_m with zero velocity to every piece of step m, one time
                step (the piece's last sampling interval) after its last sample.

        Returns:
            M ``Demos``; entry m holds the pieces of step m (in demonstration order, a demonstration that visits
            the step twice gives two pieces), with attractor g_m; velocities and times are the original ones.

        Raises:
            InvalidArgumentError: ``demos`` is not a Demos, or ``end_at_attractor`` not a bool.
            ShapeMismatchError: other demonstrations than the segmented ones. TooFewSamplesError: a piece of fewer
                than 2 samples without ``end_at_attractor``.
        """
        if not isinstance(demos, Demos):
            raise InvalidArgumentError(f"demos must be the segmented Demos, got {type(demos).__name__} (build one with "
                                       "Demos.from_sequences)")
        if not isinstance(end_at_attractor, bool):  # "no" or 0.0 would read as True or False silently
            raise InvalidArgumentError(f"end_at_attractor must be a bool, got {end_at_attractor!r}")
        if demos.n_demos != self.n_sequences:
            raise ShapeMismatchError(f"{demos.n_demos} demonstrations, the segmentation has {self.n_sequences}")
        seg_lengths = torch.tensor([int(lab.shape[0]) for lab in self.labels], device="cpu")
        if not torch.equal(demos.lengths.cpu(), seg_lengths):
            raise ShapeMismatchError("demonstration lengths differ from the segmented ones")
        if self.endpoints is not None:  # the same demonstrations in the same order (equal lengths are not enough)
            given = _endpoints(demos).to(torch.float64).cpu()
            kept = self.endpoints.to(torch.float64).cpu()
            scale = float(kept.abs().max()) + 1e-12
            off = ((given - kept).abs().amax((1, 2)) > 1e-5 * scale).nonzero().view(-1).tolist()
            if off:
                raise ShapeMismatchError(f"demonstrations {off} do not start and end where the segmented ones do "
                                         "(other data, or another order)")
        out = []
        for m in range(self.n_steps):
            pos, vel, tms = [], [], []
            for i in range(self.n_sequences):
                for step, a, b in self.pieces[i].tolist():
                    if step != m:
                        continue
                    p, v, t = demos.positions[i, a:b], demos.velocities[i, a:b], demos.times[i, a:b]
                    if end_at_attractor:
                        dt = t[-1] - t[-2] if b - a > 1 else t.new_tensor(1.0)
                        p = torch.cat([p, self.attractors[m].to(p).unsqueeze(0)])
                        v = torch.cat([v, torch.zeros_like(v[:1])])
                        t = torch.cat([t, (t[-1] + dt).unsqueeze(0)])
                    if p.shape[0] < MIN_SAMPLES:  # named here: Demos would only say "demonstration k" of the step
                        raise TooFewSamplesError(f"its piece of step {m} (samples {a}..{b - 1}) has {p.shape[0]} "
                                                 f"samples, a piece needs at least {MIN_SAMPLES} (use "
                                                 "end_at_attractor=True, or longer steps)", i)
                    pos.append(p)
                    vel.append(v)
                    tms.append(t)
            out.append(
                Demos.from_sequences(
                    pos, times=tms, velocities=vel, attractor=self.attractors[m].to(demos.positions),
                    dtype=demos.dtype, device=demos.device,
                )  # fmt: skip
            )
        return out

    # ------------------------------------------------------------------ persistence
    def state_dict(self) -> dict[str, Any]:
        """Plain dict of tensors and lists (no sampler result, no info), for ``torch.save``."""
        return {
            "schema_version": SCHEMA_VERSION,
            "labels": [t.cpu() for t in self.labels],
            "pieces": [t.cpu() for t in self.pieces],
            "attractors": self.attractors.cpu(),
            "routes": [list(r) for r in self.routes],
            "route_of": self.route_of.cpu(),
            "space_mean": self.space_mean.cpu(),
            "space_covariance": self.space_covariance.cpu(),
            "space_weights": self.space_weights.cpu(),
            "states": [t.cpu() for t in self.states],
            "step_state": self.step_state.cpu(),
            **({} if self.endpoints is None else {"endpoints": self.endpoints.cpu()}),
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> Segmentation:
        """Inverse of :meth:`state_dict`.

        Raises:
            StoreError: another schema; a missing or unknown key; an entry of the wrong type, shape, dtype or device;
                or one out of range or inconsistent with the others (M steps, J Gaussians, N demonstrations of T_i
                samples, d dimensions: :func:`_check_state`), naming the key.
            NonFiniteError: NaN or Inf in a float tensor (attractors, space_*, endpoints), naming the key.
        """
        if not isinstance(state, dict) or state.get("schema_version") != SCHEMA_VERSION:
            got = state.get("schema_version") if isinstance(state, dict) else type(state).__name__
            raise StoreError(f"segmentation schema {got!r}, expected {SCHEMA_VERSION}")
        _check_state(state)
        return cls(
            labels=tuple(state["labels"]), pieces=tuple(state["pieces"]), attractors=state["attractors"],
            routes=tuple(tuple(int(m) for m in r) for r in state["routes"]), route_of=state["route_of"],
            space_mean=state["space_mean"], space_covariance=state["space_covariance"],
            space_weights=state["space_weights"], states=tuple(state["states"]), step_state=state["step_state"],
            endpoints=state.get("endpoints"),
        )  # fmt: skip

    def save(self, path: str | Path) -> Path:
        """Write :meth:`state_dict` atomically with ``torch.save``, with the SHA-256 of its content
        (:func:`lfd_torch.store.checksum.payload_digest`) checked by :meth:`load`.

        Raises:
            StoreError: ``path`` is not a str or os.PathLike (naming it), or writing failed.
        """
        from lfd_torch.store import atomic_save
        from lfd_torch.store.checksum import DIGEST_KEY, payload_digest

        path = check_path(path, "path", error=StoreError)
        state = self.state_dict()
        state[DIGEST_KEY] = payload_digest(state)
        return atomic_save(path, lambda tmp: torch.save(state, tmp), what="segmentation file")

    @classmethod
    def load(cls, path: str | Path) -> Segmentation:
        """Read a file written by :meth:`save`; a damaged, altered or foreign file raises StoreError naming it."""
        from lfd_torch.store.checksum import verify_digest

        try:
            state = torch.load(path, weights_only=True)
        except Exception as exc:  # missing, truncated or foreign file
            raise StoreError(f"cannot read a segmentation from {str(path)!r}: {exc}") from exc
        if not isinstance(state, dict):
            raise StoreError(f"{str(path)!r} does not hold a segmentation state dict")
        verify_digest(state, f"segmentation file {str(path)!r}")
        try:
            return cls.from_state_dict(state)
        except (StoreError, NonFiniteError) as exc:  # a file holding NaN is a damaged file to the caller
            raise StoreError(f"{str(path)!r}: {exc}") from exc

    def table(self) -> list[dict[str, Any]]:
        """One row per step: index, route, HMM state, attractor, number of pieces, mean start/end fraction."""
        rows = []
        for m in range(self.n_steps):
            starts, ends = [], []
            for i in range(self.n_sequences):
                T = float(self.labels[i].shape[0])
                for step, a, b in self.pieces[i].tolist():
                    if step == m:
                        starts.append(a / T)
                        ends.append(b / T)
            route = next(r for r, steps in enumerate(self.routes) if m in steps)
            row: dict[str, Any] = {"step": m + 1, "route": route, "state": int(self.step_state[m])}
            for j, v in enumerate(self.attractors[m].tolist()):
                row[f"g_{j}"] = v
            row["n_pieces"] = len(starts)
            row["mean_start_fraction"] = sum(starts) / max(len(starts), 1)
            row["mean_end_fraction"] = sum(ends) / max(len(ends), 1)
            rows.append(row)
        return rows


# ---------------------------------------------------------------------------------------------- helpers
def runs(labels: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Maximal runs of equal labels.

    Args:
        labels: (T,) long, T >= 1.

    Returns:
        starts (R,), ends (R,) (exclusive) and values (R,).

    Raises:
        ShapeMismatchError: ``labels`` is not a non-empty 1-D integer tensor.
    """
    if not isinstance(labels, Tensor) or labels.ndim != 1 or labels.numel() == 0 or labels.is_floating_point() \
            or labels.is_complex():  # fmt: skip
        shape = tuple(labels.shape) if isinstance(labels, Tensor) else type(labels).__name__
        raise ShapeMismatchError(f"labels must be a non-empty 1-D integer tensor (T,), got {shape}")
    change = torch.nonzero(labels[1:] != labels[:-1]).reshape(-1) + 1
    starts = torch.cat([change.new_zeros(1), change])
    ends = torch.cat([change, change.new_tensor([labels.shape[0]])])
    return starts, ends, labels[starts]


def resolve_min_length(min_length: float, length: int) -> int:
    """Minimum step length in samples: ``min_length`` samples if >= 1, else that fraction of ``length`` (>= 3)."""
    number = isinstance(min_length, numbers.Real) and not isinstance(min_length, bool)
    whole = number and math.isfinite(min_length) and (min_length < 1 or min_length == int(min_length))
    if not (whole and min_length > 0):
        raise InvalidArgumentError(f"min_length must be a fraction in (0, 1) or a whole number of samples >= 1, "
                                   f"got {min_length!r}")
    n = int(min_length) if min_length >= 1 else int(math.ceil(min_length * length))
    return max(n, 3)


def scale_velocities(x: Tensor, stride: int, dt: float, half_width: int | None = None) -> Tensor:
    """Least-squares velocities at the time scale of the model's grid.

    The velocity at sample t is the slope of the straight line fitted (least squares) to the positions
    x[t - h .. t + h], h = ``half_width`` (default: the stride k, so the window spans the two grid intervals
    around the grid point), shortened at the ends. Under white position noise of standard deviation sigma per axis
    this is the minimum-variance linear unbiased estimate of a constant velocity over the window; its noise is
    sigma / (dt sqrt(sum_j j^2)), sum_j j^2 = h (h + 1) (2 h + 1) / 3 (:func:`velocity_noise`). A window of one
    stride on either side means that at most two grid points see a corner.

    Args:
        x: (T, d) positions at the full rate; stride: k >= 1; dt: sampling interval (s).

    Returns:
        (T, d) velocities.
    """
    T = x.shape[0]
    h = stride if half_width is None else int(half_width)
    idx = torch.arange(T, device=x.device)
    lo, hi = (idx - h).clamp_min(0), (idx + h).clamp_max(T - 1) + 1  # window [lo, hi)
    j = idx.to(x.dtype)
    zero = x.new_zeros(1)
    c0 = torch.cat([zero, torch.ones_like(j).cumsum(0)])
    c1 = torch.cat([zero, j.cumsum(0)])
    c2 = torch.cat([zero, (j * j).cumsum(0)])
    cx = torch.cat([x.new_zeros(1, x.shape[1]), x.cumsum(0)])
    cjx = torch.cat([x.new_zeros(1, x.shape[1]), (j.unsqueeze(-1) * x).cumsum(0)])
    n, s1, s2 = c0[hi] - c0[lo], c1[hi] - c1[lo], c2[hi] - c2[lo]
    sx, sjx = cx[hi] - cx[lo], cjx[hi] - cjx[lo]
    denom = (n * s2 - s1 * s1).clamp_min(torch.finfo(x.dtype).tiny)
    return (n.unsqueeze(-1) * sjx - s1.unsqueeze(-1) * sx) / (denom.unsqueeze(-1) * dt)


def velocity_noise(sigma_x: float, length: int, stride: int, dt: float, half_width: int | None = None,
                   rho: float = 0.0) -> Tensor:
    """(T,) standard deviation per axis of every velocity of :func:`scale_velocities` under position noise of
    standard deviation ``sigma_x`` per axis and lag-one correlation ``rho`` (AR(1), :func:`position_noise_model`;
    0: white).

    The least-squares slope through n samples at times j dt is sum_j a_j x_j with a_j = (j - jbar) / sum_j (j -
    jbar)^2, so its noise variance is sigma^2 / dt^2 sum_ij a_i a_j rho^|i - j|; for white noise sigma^2 / (dt^2
    sum_j (j - jbar)^2), sum_j (j - jbar)^2 = n (n^2 - 1) / 12: h (h + 1) (2 h + 1) / 3 inside the sequence, less
    where the window is cut by an end (a velocity there is noisier, and its direction is trusted less, :mod:`.field`).
    """
    h = stride if half_width is None else int(half_width)
    idx = torch.arange(length, dtype=torch.float64, device="cpu")
    n = (idx + h).clamp_max(length - 1) - (idx - h).clamp_min(0) + 1
    # sum_j (j - jbar)^2 is at least 1/2 for n >= 2 (a two-sample window at an end when h = 1: the slope is a
    # difference, of noise sqrt(2) sigma / dt); the floor only keeps a one-sample window (h = 0) finite
    if rho == 0.0:
        sjj = (n * (n * n - 1.0) / 12.0).clamp_min(0.5)
        return sigma_x / (dt * sjj.sqrt())
    gain = {}  # window length -> sum_ij a_i a_j rho^|i - j|
    for m in sorted({int(v) for v in n.tolist()}):
        j = torch.arange(m, dtype=torch.float64, device="cpu")
        a = (j - j.mean()) / max(float((j - j.mean()).square().sum()), 0.5)
        gain[m] = float(a @ (rho ** (j.unsqueeze(0) - j.unsqueeze(1)).abs()) @ a)
    return sigma_x * torch.tensor([gain[int(v)] for v in n.tolist()], dtype=torch.float64, device="cpu").sqrt() / dt


def path_length(velocity: Tensor, noise: Tensor, dt: float) -> Tensor:
    """(T,) estimated path length travelled up to every sample: the cumulative sum of the unbiased speed estimates
    s_t = (||v_t||^2 - d sigma_v,t^2)_+^(1/2) times dt (``velocity`` (T, d), ``noise`` (T,) its noise per axis)."""
    d = velocity.shape[-1]
    speed = (velocity.square().sum(-1) - d * noise.square()).clamp_min(0.0).sqrt()
    return torch.cumsum(speed * dt, 0)


def _grid_levels(velocity: Tensor, noise: Tensor, stride: int, dt: float) -> tuple[Tensor, Tensor, Tensor]:
    """The path length (T,) at every sample, the grid's samples (n,) and their levels (n,): of the ceil(T / k) levels
    (j + 1/2) L / ceil(T / k), each grid sample is the first sample reaching one, with the first such level (a
    sample whose path covers two levels gives one point). Without motion: every k-th sample, levels 0, k, 2k, ..."""
    T = velocity.shape[0]
    n = max(1, math.ceil(T / stride))
    length = path_length(velocity, noise, dt)
    total = float(length[-1])
    if not total > 0.0:
        idx = torch.arange(0, T, stride, device=velocity.device)
        return length, idx, idx.to(length.dtype)
    targets = (torch.arange(n, dtype=length.dtype, device=velocity.device) + 0.5) * (total / n)
    idx = torch.searchsorted(length, targets).clamp_max(T - 1)
    kept, inverse = torch.unique(idx, return_inverse=True)
    level = torch.full(kept.shape, float("inf"), dtype=length.dtype, device=length.device)
    return length, kept, level.scatter_reduce(0, inverse, targets, reduce="amin")


def path_grid(velocity: Tensor, noise: Tensor, stride: int, dt: float) -> Tensor:
    """The sampler's grid: ceil(T / k) samples equally spaced in estimated path length (module docstring, item 3).

    The path length is :func:`path_length`, so a rest (s_t ~ 0) occupies no grid point of its own and a leg gets
    grid points in proportion to its length, whatever its timing. Without motion (a path of length 0) the grid is
    every k-th sample.

    Args:
        velocity: (T, d) velocities (:func:`scale_velocities`); noise: (T,) their noise per axis
            (:func:`velocity_noise`); stride: k; dt: sampling interval.

    Returns:
        (n,) increasing long sample indices, n <= ceil(T / k).
    """
    return _grid_levels(velocity, noise, stride, dt)[1]


def time_at_length(length: Tensor, times: Tensor, levels: Tensor) -> Tensor:
    """(...) the instant at which the path length first reaches each level: with i the first sample whose
    ``length`` L_i >= l, t = t_(i-1) + (l - L_(i-1)) / (L_i - L_(i-1)) (t_i - t_(i-1)), linear in path length
    between the two samples (t_0 for l <= L_0, t_(T-1) beyond the end). ``length`` (T,) :func:`path_length`,
    ``times`` (T,) s, ``levels`` (...)."""
    T = length.shape[0]
    i = torch.searchsorted(length, levels).clamp_max(T - 1)
    prev = (i - 1).clamp_min(0)
    span = length[i] - length[prev]
    frac = ((levels - length[prev]) / torch.where(span > 0, span, torch.ones_like(span))).clamp(0.0, 1.0)
    frac = torch.where((i > 0) & (span > 0), frac, torch.ones_like(frac))
    t = times.to(length.dtype)
    return t[prev] + frac * (t[i] - t[prev])


def grid_crossings(velocity: Tensor, noise: Tensor, stride: int, dt: float, times: Tensor) -> tuple[Tensor, Tensor]:
    """The instants (n,) s at which the estimated path length reaches the levels (n,) of :func:`path_grid`'s points.

    Grid point j is the first sample whose path length reaches its level l_j (the first of the levels that give the
    same sample: where one sample's path covers two levels the grid keeps one point); its instant is
    :func:`time_at_length` of that level. The sample times themselves round every gap between grid points to whole
    samples; at a stride of one or two samples (a 10-25 Hz recording) that rounding is the whole gap, and the
    dwell covariate (:mod:`.dwell`) read the gaps of two samples that a noisy speed estimate leaves where the grid
    drops a level as pauses (10 Hz, revisit_const_2d, 4 demonstrations: 7 steps for 4). The covariate is the pace
    between these instants, time over path length.

    Args: as :func:`path_grid`, and times (T,) the sample times (s). Without motion: the times of the grid's samples
        and their sample indices as levels.
    """
    length, _, level = _grid_levels(velocity, noise, stride, dt)
    return _crossings(length, level, times), level


def _crossings(length: Tensor, level: Tensor, times: Tensor) -> Tensor:
    """(n,) instants of :func:`grid_crossings` from :func:`_grid_levels`' path length and levels."""
    if not float(length[-1]) > 0.0:  # no motion: the levels are the grid's sample indices
        return times[level.long()].to(length.dtype)
    return time_at_length(length, times, level)


def position_noise(sequences: Sequence[Tensor]) -> float:
    """Standard deviation of white position noise per axis, from second differences (robust: MAD).

    For x_t = y_t + e_t with a smooth y sampled fast enough, x_{t+1} - 2 x_t + x_{t-1} ~ e-part with variance
    6 sigma^2; the median absolute deviation (scaled by 1.4826) ignores the few large values at corners.
    """
    return _second_difference_scales(sequences, (1,))[0] / math.sqrt(6.0)


def _second_difference_scales(sequences: Sequence[Tensor], lags: Sequence[int]) -> list[float]:
    """Robust standard deviation (MAD scaled by 1.4826) of x_{t+L} - 2 x_t + x_{t-L} over every axis and sequence,
    for every lag L (0 where no sequence is long enough)."""
    out = []
    for L in lags:
        d2 = [(s[2 * L:] - 2.0 * s[L:-L] + s[: -2 * L]).reshape(-1) for s in sequences if s.shape[0] > 2 * L]
        out.append(float(1.4826 * torch.cat(d2).abs().median()) if d2 else 0.0)
    return out


NOISE_MODELS = ("ar1", "white")  # ``segment``'s noise_model
NOISE_LAGS = (1, 2, 3, 4)  # lags of the second differences that :func:`position_noise_model` fits
MAX_NOISE_CORRELATION = 0.8  # rho^L must decay over NOISE_LAGS to tell the noise from a random walk or the signal
NOISE_FIT_VARIANCE = 10.0  # n x relative variance of a MAD variance estimate of n overlapping second differences
NOISE_TEST_CHI2 = 10.83  # chi-square (1 degree of freedom) at p = 0.001: correlated noise only when the data show it
#: the least position noise ``segment`` assumes, as a fraction of the data's span (the diagonal of their bounding
#: box): noise-free data (generated or simulated paths) estimate a noise of 0 or of rounding size, under which the
#: block evidence's variances vanish and its Cholesky factors fail; positions are never known better than this (1 um
#: on a 1 m task). It binds on no recorded set here: LASA's smoothest shape estimates 1.4e-6, MNIST strokes 1.5e-5,
#: the scooping demonstrations 2e-5, the benchmark families 2.9e-3 or more.
NOISE_FLOOR = 1e-6


def position_noise_model(sequences: Sequence[Tensor]) -> tuple[float, float]:
    """(sigma, rho): standard deviation per axis and lag-one correlation of the position noise, AR(1).

    Why not white only (:func:`position_noise`): a sensor's or a filter's noise is rarely white at the sampling
    rate, and the velocities of :func:`scale_velocities` average over 2 k + 1 samples, so correlated noise leaves
    them far noisier than the white extrapolation from lag-one differences says (for rho = 0.5 the lag-one
    differences see 0.65 sigma and the slope noise is another 1.7 times larger). Directions at a pause are then
    trusted (:mod:`.field`) and a switch at a dwelling corner is drawn off the pause (``experiments/
    bench_segmentation.py --noise-correlation 0.5``: every switch on the straight 2-D legs with pauses, 4
    demonstrations, in 6 of 10 cases under the white estimate, 10 of 10 with this model; 81 against 78 % of all 280).

    Model: x = y + e with e AR(1) and y smooth; the second difference at lag L has variance
    sigma^2 2 (1 - rho^L)(3 - rho^L) + S L^4, the last term the signal's (y'' L^2 dt^2)^2. Its robust variances at
    the lags :data:`NOISE_LAGS` are fitted in relative least squares, (sigma^2, S) >= 0 for every rho on a grid of
    0.01 in [0, 0.8]: beyond, rho^L hardly decays over lags 1-4, the noise's differences grow about linearly in L
    like a random walk's, and a smooth signal whose differences are not exactly L^4 was read as such noise (rho
    0.98 on a noise-free curve); a stronger correlation is read as 0.8, still far closer than white.

    White or AR(1) is a test, not a preference: the fit at rho = 0 (white noise plus signal) is kept, with the white
    lag-one estimate of :func:`position_noise` as before, unless the best rho lowers the relative residual by more
    than the chi-square quantile at p = 0.001 (1 degree of freedom) times the sampling variance of the relative
    residuals, about 10 / n for n differences (the relative variance of a MAD variance estimate is 5.4 / n for
    independent Gaussian values, MAD's efficiency being 0.37; neighbouring second differences share samples,
    which about halves n). Smooth recordings whose short-lag differences are signal (LASA: their variances grow as
    L^4) stay white, and AR(1) noise with rho 0.3-0.7 at 1 % of a leg is detected
    (tests/test_segmentation_noise.py).
    """
    v = torch.tensor(_second_difference_scales(sequences, NOISE_LAGS), dtype=torch.float64, device="cpu").square()
    white = position_noise(sequences)
    if not bool((v > 0).all()):
        return white, 0.0
    lags = torch.tensor(NOISE_LAGS, dtype=torch.float64, device="cpu")
    rhos = torch.arange(0.0, MAX_NOISE_CORRELATION + 0.005, 0.01, dtype=torch.float64, device="cpu")  # (R,)
    powers = rhos.unsqueeze(-1) ** lags  # (R, L)
    X = torch.stack([2.0 * (1.0 - powers) * (3.0 - powers), (lags**4).expand_as(powers)], -1) / v.unsqueeze(-1)
    ones = torch.ones_like(v)
    # non-negative least squares in two unknowns, every rho at once: both terms, or one alone, of the fits >= 0
    both = torch.linalg.lstsq(X, ones.expand(X.shape[0], -1).unsqueeze(-1)).solution.squeeze(-1)  # (R, 2)
    alone = (X * ones.unsqueeze(-1)).sum(-2) / X.square().sum(-2)  # (R, 2): each term by itself
    cand = torch.stack([both, torch.stack([alone[:, 0], torch.zeros_like(rhos)], -1),
                        torch.stack([torch.zeros_like(rhos), alone[:, 1]], -1)], 1)  # (R, 3, 2)
    res = ((X.unsqueeze(1) @ cand.unsqueeze(-1)).squeeze(-1) - 1.0).square().sum(-1)  # (R, 3)
    res = torch.where((cand >= 0).all(-1), res, torch.full_like(res, math.inf))
    best_res, pick = res.min(-1)  # (R,)
    i = int(torch.argmin(best_res))
    sigma, rho, res_min = math.sqrt(float(cand[i, int(pick[i]), 0])), float(rhos[i]), float(best_res[i])
    n = sum(int(s[2:].numel()) for s in sequences if s.shape[0] > 2)
    if rho > 0.0 and sigma > 0.0 and (float(best_res[0]) - res_min) / (NOISE_FIT_VARIANCE / n) > NOISE_TEST_CHI2:
        return sigma, rho
    return white, 0.0


def _lcs(a: list[int], b: list[int], wa: list[float], wb: list[float]) -> list[tuple[int, int]]:
    """Weighted longest common subsequence of two state sequences: matched index pairs (weight wa + wb)."""
    n, m = len(a), len(b)
    best = [[0.0] * (m + 1) for _ in range(n + 1)]
    for i in range(n - 1, -1, -1):
        for j in range(m - 1, -1, -1):
            cand = max(best[i + 1][j], best[i][j + 1])
            if a[i] == b[j]:
                cand = max(cand, wa[i] + wb[j] + best[i + 1][j + 1])
            best[i][j] = cand
    pairs, i, j = [], 0, 0
    while i < n and j < m:
        if a[i] == b[j] and best[i][j] == wa[i] + wb[j] + best[i + 1][j + 1]:
            pairs.append((i, j))
            i, j = i + 1, j + 1
        elif best[i + 1][j] >= best[i][j + 1]:
            i += 1
        else:
            j += 1
    return pairs


def _routes(seqs: list[list[int]], fracs: list[list[float]]) -> list[list[int]]:
    """Group demonstrations whose shared states cover at least half of each (connected components)."""
    N = len(seqs)
    parent = list(range(N))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(N):
        for j in range(i + 1, N):
            pairs = _lcs(seqs[i], seqs[j], fracs[i], fracs[j])
            cover_i = sum(fracs[i][a] for a, _ in pairs)
            cover_j = sum(fracs[j][b] for _, b in pairs)
            if min(cover_i, cover_j) >= 0.5:
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(N):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values(), key=lambda g: g[0])


def _align_route(seqs: list[list[int]], fracs: list[list[float]]) -> tuple[list[int], list[list[int]]]:
    """Progressive alignment of the run states of one route's demonstrations.

    Returns:
        the state of every step of the route in order, and for every demonstration the route step of each run.
    """
    order = sorted(range(len(seqs)), key=lambda i: -len(seqs[i]))  # start from the richest sequence
    steps = list(seqs[order[0]])
    weight = list(fracs[order[0]])
    assign: dict[int, list[int]] = {order[0]: list(range(len(steps)))}
    ids = list(range(len(steps)))  # stable id of every position of `steps`
    next_id = len(steps)
    for i in order[1:]:
        pairs = dict((b, a) for a, b in _lcs(steps, seqs[i], weight, fracs[i]))
        new_steps, new_weight, new_ids, mine = [], [], [], []
        pos = 0
        for r, state in enumerate(seqs[i]):
            if r in pairs:
                a = pairs[r]
                while pos <= a:
                    new_steps.append(steps[pos]); new_weight.append(weight[pos]); new_ids.append(ids[pos])  # noqa: E702
                    pos += 1
                new_weight[-1] += fracs[i][r]
                mine.append(ids[a])
            else:
                new_steps.append(state); new_weight.append(fracs[i][r]); new_ids.append(next_id)  # noqa: E702
                mine.append(next_id)
                next_id += 1
        while pos < len(steps):
            new_steps.append(steps[pos]); new_weight.append(weight[pos]); new_ids.append(ids[pos])  # noqa: E702
            pos += 1
        steps, weight, ids = new_steps, new_weight, new_ids
        assign[i] = mine
    index = {sid: m for m, sid in enumerate(ids)}
    return steps, [[index[sid] for sid in assign[i]] for i in range(len(seqs))]


def _refine_switch(ll: Tensor, a: int, b: int, lo: int, hi: int, stride: int,
                   log_prior: Tensor | None = None) -> tuple[int, Tensor]:
    """Median of the change-point posterior between states a | b on t in [lo, hi] (module docstring, item 3).

    ``log_prior`` (T,): a log weight of every full-rate switch time (the dwell term's, :mod:`.dwell`), or None.

    Returns:
        the switch (first sample of b) and the posterior probability that sample t, lo <= t < hi, is on the other
        side of it than its label says: P(tau <= t) before the switch, P(tau > t) from it on ((hi - lo,)).
    """
    return _switch_posterior(_change_point_scores(ll, a, b, lo, hi, stride, log_prior), lo, hi)


def _change_point_scores(ll: Tensor, a: int, b: int, lo: int, hi: int, stride: int,
                         log_prior: Tensor | None = None) -> Tensor:
    """(hi - lo + 1,) log weight of the switch times tau = lo .. hi of :func:`_refine_switch`."""
    seg = ll[lo:hi]  # (L, K)
    diff = (seg[:, a] - seg[:, b]) / stride  # evidence for a over b of every full-rate sample
    # score(t) = sum_{t' < t} diff(t') (+ const): samples before t with a, from t on with b
    score = torch.cat([diff.new_zeros(1), diff.cumsum(0)])  # t = lo .. hi
    if log_prior is not None:
        score = score + log_prior[lo : hi + 1]
    return score


def _refine_switch_on_grid(ll: Tensor, a: int, b: int, grid: Tensor, j0: int, grid_scores: Tensor, first: int,
                           last: int, stride: int, log_prior: Tensor | None = None) -> tuple[int, int, Tensor]:
    """Median of the change-point posterior between states a | b whose grid interval is the model's (module
    docstring, item 3): P(tau) = P(j) p(tau | j), P(j) ∝ exp(``grid_scores``[j - j0]) the collapsed score of the
    labelling whose second run starts at grid point j, p(tau | j) the posterior of :func:`_refine_switch` restricted
    to tau in (grid[j - 1], grid[j]]; tau clipped to [first, last].

    Returns:
        lo, the window's first sample, and the switch and doubts of :func:`_refine_switch` over [lo, hi].
    """
    lo, hi, w = _grid_switch_window(grid, j0, grid_scores.numel(), first, last)
    score = _change_point_scores(ll, a, b, lo, hi, stride, log_prior)
    n = grid_scores.numel()
    top = score.new_full((n,), -math.inf).scatter_reduce(0, w, score, "amax")
    within = score - top[w]
    log_norm = score.new_zeros(n).index_add_(0, w, within.exp()).log()  # -inf for an interval clipped away
    grid_scores = grid_scores.to(score)
    present = torch.isfinite(log_norm)
    log_grid = grid_scores - torch.logsumexp(grid_scores[present], 0)
    return (lo, *_switch_posterior(within - log_norm[w] + log_grid[w], lo, hi))


def _grid_switch_window(grid: Tensor, j0: int, n: int, first: int, last: int) -> tuple[int, int, Tensor]:
    """The window [lo, hi] of the switch times of grid positions j0 .. j0 + n - 1 (the second run starting at grid
    point j puts tau in (grid[j - 1], grid[j]]), clipped to [first, last], and each tau's position index (w in
    0 .. n - 1) ((hi - lo + 1,) long)."""
    lo = max(int(grid[j0 - 1]) + 1, first)
    hi = max(min(int(grid[j0 + n - 1]), last), lo)
    tau = torch.arange(lo, hi + 1, device=grid.device)
    # w with grid[j0 + w - 1] < tau <= grid[j0 + w]
    w = torch.searchsorted(grid[j0 : j0 + n].contiguous(), tau).clamp_max(n - 1)
    return lo, hi, w


def _switch_posterior(score: Tensor, lo: int, hi: int) -> tuple[int, Tensor]:
    """Median and label doubts (:func:`_refine_switch`) of the change-point posterior of log weights ``score``
    (hi - lo + 1,) over tau = lo .. hi."""
    post = torch.softmax(score, 0)
    cdf = post.cumsum(0)  # cdf[j] = P(tau <= lo + j)
    half = post.new_tensor([0.5])
    cut = int(torch.searchsorted(cdf, half).clamp_max(hi - lo))
    in_b = cdf[:-1]  # P(sample lo + j belongs to b) = P(tau <= lo + j)
    j = torch.arange(hi - lo, device=score.device)
    doubt = torch.where(j < cut, in_b, 1.0 - in_b).clamp(0.0, 1.0)
    return lo + cut, doubt


def _dwell_switch_prior(length: Tensor, times: Tensor, grid_times: Tensor, grid_levels: Tensor,
                        params: dict[str, float], n_phases: int = 16) -> Tensor:
    """(T + 1,) log weight of a switch at every full-rate sample tau under the dwell term (:mod:`.dwell`).

    On the grid a switch makes a run start at a grid point j, and the term's log ratio there is
    r(c_j) = log N(c_j; mu + delta, sigma^2) - log N(c_j; mu, sigma^2) (posterior means given the returned
    labelling), c_j = log(time between grid points j - 1 and j / median). At full rate tau lies somewhere inside a
    grid interval, and where is an accident of the grid's phase (the grid starts half a spacing h into the path).
    So the weight of tau is r averaged over that phase: with the interval [L(tau) - phi, L(tau) - phi + h] in path
    length L (:func:`path_length`, h = L / n the mean spacing of the grid's n points, one level where the grid kept
    every level), phi uniform on [0, h) (``n_phases`` midpoints), the time it takes gives c and
    the weight is log mean_phi exp(r(c)). A rest then gets a plateau of weight whatever the grid, and the median
    of the change-point posterior falls in its middle, not at the grid point that happened to follow it. The
    times are those at which the path length reaches the interval's ends (:func:`time_at_length`), as the grid's
    own are (:func:`grid_crossings`), and c is the interval's pace over the grid's median pace.

    Args:
        length: (T,) path length at every sample; times: (T,) sample times (s); grid_times, grid_levels: (n,) the
            grid points' instants and path lengths (:func:`grid_crossings`; their median pace is c's unit).
    """
    mu, delta, var = params["dwell_mean"], params["dwell_shift"], params["dwell_noise"] ** 2
    T, n = length.shape[0], grid_times.numel()
    h = float(length[-1]) / n  # the grid's mean spacing in path length
    if not h > 0.0:  # no motion: no interval has a pace, every switch time weighs the same
        return length.new_zeros(T + 1)
    pace = (grid_times[1:] - grid_times[:-1]) / (grid_levels[1:] - grid_levels[:-1])
    scale = h * pace.median() if pace.numel() else times.new_tensor(1.0)
    at = length[torch.arange(T + 1, device=length.device).clamp_max(T - 1)]  # (T + 1,) L(tau)
    phi = (torch.arange(n_phases, dtype=length.dtype, device=length.device) + 0.5) * (h / n_phases)
    lo = (at.unsqueeze(-1) - phi).clamp_min(float(length[0]))  # (T + 1, P)
    hi = (lo + h).clamp_max(float(length[-1]))
    c = torch.log((time_at_length(length, times, hi) - time_at_length(length, times, lo)).clamp_min(1e-6 * scale)
                  / scale)
    ratio = (delta * (c - mu) - 0.5 * delta**2) / var
    return torch.logsumexp(ratio, -1) - math.log(n_phases)


def _subtask_spaces(
    demos: Demos, pieces: list[list[tuple[int, int, int]]], M: int, stretch: int, noise_var: float,
    junctions: list[list[tuple[int, Tensor]]] | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Gaussians of every stretch of ``stretch`` samples of every piece and their membership in the steps.

    Returns:
        means (J, d), covariances (J, d, d) and the (M, J) 0/1 membership: Gaussian j belongs to A_m when it is a
        stretch of step m or the most responsible Gaussian of at least one sample of step m (module docstring).
    """
    d = demos.dim
    means, covs, owner = [], [], []
    x_all = demos.samples()[0]
    floor = noise_var + float(x_all.var(0).sum()) * 1e-6 + torch.finfo(demos.dtype).eps
    eye = torch.eye(d, dtype=demos.dtype, device=demos.device)
    pts_of_step: list[list[Tensor]] = [[] for _ in range(M)]
    for i, plist in enumerate(pieces):
        for step, a, b in plist:
            pts_of_step[step].append(demos.positions[i, a:b])
            n = b - a
            n_str = max(1, n // stretch)
            edges = [a + round(j * n / n_str) for j in range(n_str + 1)]
            for s0, s1 in zip(edges[:-1], edges[1:]):
                pts = demos.positions[i, s0:s1]
                mu = pts.mean(0)
                c = pts - mu
                cov = c.T @ c / max(pts.shape[0], 1) + floor * eye
                means.append(mu)
                covs.append(0.5 * (cov + cov.T))
                owner.append(step)
    shared: list[tuple[int, int]] = []  # (step before, step after) of every junction Gaussian
    for i, plist in enumerate(pieces):
        for r, (lo, doubt) in enumerate(junctions[i] if junctions is not None else []):
            u = doubt.to(demos.dtype)
            total = float(u.sum())
            if total <= 0.0:
                continue
            pts = demos.positions[i, lo : lo + u.shape[0]]
            mu = (u.unsqueeze(-1) * pts).sum(0) / total
            c = pts - mu
            cov = (u.unsqueeze(-1) * c).T @ c / total + floor * eye
            means.append(mu)
            covs.append(0.5 * (cov + cov.T))
            shared.append((plist[r][0], plist[r + 1][0]))
    mean, cov = torch.stack(means), torch.stack(covs)
    owner_t = torch.tensor(owner, device=demos.device)
    member = torch.zeros(M, mean.shape[0], dtype=torch.bool, device=demos.device)
    member[:, : len(owner)] = torch.nn.functional.one_hot(owner_t, M).T.bool()  # the step's own stretches
    for j, (a, b) in enumerate(shared):
        member[a, len(owner) + j] = member[b, len(owner) + j] = True
    for m in range(M):
        if pts_of_step[m]:
            best = gaussian_log_density(torch.cat(pts_of_step[m]), mean, cov).argmax(-1)  # (n_m,)
            member[m, best] = True
    return mean, cov, member.to(demos.dtype)


def _check_demos(demos: Demos | Sequence[Tensor], min_len_param: float) -> Demos:
    if not isinstance(demos, Demos):
        if isinstance(demos, (str, bytes)) or not isinstance(demos, Sequence) or len(demos) == 0:
            raise InvalidArgumentError(f"demos must be a Demos or a non-empty list of (T_i, d) tensors, got {demos!r}")
        first = demos[0]
        dtype = first.dtype if isinstance(first, Tensor) and first.dtype in FLOAT_DTYPES else torch.float64
        try:  # float32 tensors stay float32, as a float32 Demos does
            demos = Demos.from_sequences(list(demos), dtype=dtype)  # typed errors on shape / NaN / too short
        except InvalidDemoError as exc:  # same type, the message names the argument
            raise type(exc)(f"demos: {exc.problem}", exc.demo_index) from exc
    for i, n in enumerate(demos.lengths.tolist()):
        m = resolve_min_length(min_len_param, n)
        if n < 2 * m:
            raise TooFewSamplesError(f"has {n} samples; segmenting demos needs at least 2 * min_length = {2 * m}", i)
    return demos


def _assemble(
    demos: Demos,
    pieces: list[list[tuple[int, int, int]]],
    routes: list[list[int]],
    route_of: list[int],
    states_full: list[Tensor],
    step_state: list[int],
    stretch: int,
    noise_var: float,
    sampler: SamplerResult | None,
    info: dict[str, Any],
    junctions: list[list[tuple[int, Tensor]]] | None = None,
) -> Segmentation:
    M = len(step_state)
    dev = demos.device
    labels = []
    ends = torch.zeros(M, demos.dim, dtype=demos.dtype, device=dev)
    count = torch.zeros(M, dtype=demos.dtype, device=dev)
    for i, plist in enumerate(pieces):
        lab = torch.zeros(int(demos.lengths[i]), dtype=torch.long, device=dev)
        for step, a, b in plist:
            lab[a:b] = step
            ends[step] += demos.positions[i, b - 1]
            count[step] += 1
        labels.append(lab)
    attractors = ends / count.clamp_min(1.0).unsqueeze(-1)
    for r in routes:
        attractors[r[-1]] = demos.attractor.to(attractors)  # every route ends at the task's goal
    mean, cov, weights = _subtask_spaces(demos, pieces, M, stretch, noise_var, junctions)
    return Segmentation(
        labels=tuple(labels),
        pieces=tuple(torch.tensor(p, dtype=torch.long, device=dev).reshape(-1, 3) for p in pieces),
        attractors=attractors,
        routes=tuple(tuple(r) for r in routes),
        route_of=torch.tensor(route_of, dtype=torch.long, device=dev),
        space_mean=mean,
        space_covariance=cov,
        space_weights=weights,
        states=tuple(s.to(dev) for s in states_full),
        step_state=torch.tensor(step_state, dtype=torch.long, device=dev),
        sampler=sampler,
        info=info,
        endpoints=_endpoints(demos),
    )


#: the keys of :meth:`Segmentation.state_dict` (``endpoints`` may be absent: files saved before it was kept)
_STATE_KEYS = ("schema_version", "labels", "pieces", "attractors", "routes", "route_of", "space_mean",
               "space_covariance", "space_weights", "states", "step_state")


def _check_state(state: dict[str, Any]) -> None:
    """Check a segmentation state dict (:meth:`Segmentation.state_dict`, schema 3) before it becomes a Segmentation.

    Keys: those of :data:`_STATE_KEYS`, optionally ``endpoints`` and the file's digest, no other. attractors (M, d),
    space_mean (J, d), space_covariance (J, d, d) positive definite (a Cholesky factor exists), space_weights (M, J)
    >= 0 with a positive entry in every row, endpoints (N, 2, d): float tensors of one dtype and device, finite (M, J,
    N, d >= 1). labels and states: N long (T_i,) tensors on that device; pieces: N long (n_i, 3) tensors of (step,
    start, end) that tile 0..T_i in order, each sample's label its piece's step; step_state (M,) long >= -1; routes:
    R non-empty lists of steps 0..M-1 that hold every step; route_of (N,) long 0..R-1, whose route holds the steps
    of the demonstration's pieces.

    Raises:
        StoreError: naming the key of the first problem. NonFiniteError: NaN or Inf in a float tensor, naming it.
    """
    from lfd_torch.store.checksum import DIGEST_KEY

    missing = [k for k in _STATE_KEYS if k not in state]
    if missing:
        raise StoreError(f"segmentation state lacks {', '.join(map(repr, missing))}")
    extra = sorted(map(repr, set(state) - set(_STATE_KEYS) - {"endpoints", DIGEST_KEY}))
    if extra:
        raise StoreError(f"segmentation state has unknown keys {', '.join(extra)} (a file of another version or "
                         "program)")

    def floats(key: str, shape: tuple[int | None, ...], hint: str, like: Tensor | None = None) -> Tensor:
        value = state[key]
        try:  # a shape, dtype or device problem is the file's; NaN or Inf stays NonFiniteError (naming the key)
            check_tensor(value, f"segmentation state: {key}", ndim=len(shape), bounded=False, shape_hint=hint,
                         dtype=None if like is None else like.dtype, device=None if like is None else like.device)
        except ShapeMismatchError as exc:
            raise StoreError(str(exc)) from exc
        if any(m != n if n is not None else m == 0 for m, n in zip(value.shape, shape)):  # free sizes >= 1
            raise StoreError(f"segmentation state: {key} must have shape {hint}, got {tuple(value.shape)}")
        return value

    def longs(key: str, value: Any, shape: tuple[int | None, ...], hint: str, device: torch.device) -> Tensor:
        if not (isinstance(value, Tensor) and value.dtype == torch.long and value.ndim == len(shape)
                and all(n is None or m == n for m, n in zip(value.shape, shape)) and value.device == device):
            got = (f"{value.dtype} of shape {tuple(value.shape)} on {value.device}" if isinstance(value, Tensor)
                   else type(value).__name__)
            raise StoreError(f"segmentation state: {key} must be a long tensor of shape {hint} on {device}, got {got}")
        return value

    def sequence(key: str) -> list[Any]:
        value = state[key]
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
            raise StoreError(f"segmentation state: {key} must be a list, got {type(value).__name__}")
        return list(value)

    attractors = floats("attractors", (None, None), "(M, d)")
    M, d = attractors.shape
    dev = attractors.device
    labels = sequence("labels")
    N = len(labels)
    if N == 0:
        raise StoreError("segmentation state: labels must hold one tensor per demonstration, got none")
    labels = [longs(f"labels[{i}]", lab, (None,), "(T_i,)", dev) for i, lab in enumerate(labels)]
    for i, lab in enumerate(labels):
        if lab.numel() == 0 or not bool(((lab >= 0) & (lab < M)).all()):
            raise StoreError(f"segmentation state: labels[{i}] must be a non-empty tensor of steps 0..{M - 1} (M = "
                             f"{M}, the rows of attractors)")
    for key in ("pieces", "states"):
        if len(sequence(key)) != N:
            raise StoreError(f"segmentation state: {key} holds {len(state[key])} entries, labels {N} (one per "
                             "demonstration each)")
    for i, (s, lab) in enumerate(zip(state["states"], labels)):
        longs(f"states[{i}]", s, (lab.shape[0],), f"({lab.shape[0]},)", dev)
    pieces = [longs(f"pieces[{i}]", p, (None, 3), "(n_i, 3)", dev) for i, p in enumerate(state["pieces"])]
    for i, (p, lab) in enumerate(zip(pieces, labels)):
        step, start, end = p.unbind(-1)
        tiled = (p.shape[0] > 0 and int(start[0]) == 0 and int(end[-1]) == lab.shape[0]
                 and torch.equal(start[1:], end[:-1]) and bool((end > start).all()))
        if not tiled or not bool(((step >= 0) & (step < M)).all()):
            raise StoreError(f"segmentation state: pieces[{i}] must be rows (step 0..{M - 1}, start, end) that cover "
                             f"samples 0..{lab.shape[0] - 1} of labels[{i}] in order (M = {M}, the rows of "
                             "attractors)")
        if not torch.equal(torch.repeat_interleave(step, end - start), lab):
            raise StoreError(f"segmentation state: labels[{i}] differ from the steps of pieces[{i}]")
    step_state = longs("step_state", state["step_state"], (M,), f"(M,) = ({M},) (M: the rows of attractors)", dev)
    if not bool((step_state >= -1).all()):
        raise StoreError("segmentation state: step_state must hold HMM states >= 0 (or -1 without an HMM)")
    routes = sequence("routes")
    ok = len(routes) > 0
    for r in routes:
        ok = ok and not isinstance(r, (str, bytes)) and isinstance(r, (list, tuple)) and len(r) > 0 and all(
            isinstance(m, numbers.Integral) and not isinstance(m, bool) and 0 <= m < M for m in r)
    if not ok or {int(m) for r in routes for m in r} != set(range(M)):
        raise StoreError(f"segmentation state: routes must be non-empty lists of steps 0..{M - 1} that hold every "
                         f"step (M = {M}, the rows of attractors), got {routes!r:.200}")
    route_of = longs("route_of", state["route_of"], (N,), f"(N,) = ({N},) (N: the entries of labels)", dev)
    if not bool(((route_of >= 0) & (route_of < len(routes))).all()):
        raise StoreError(f"segmentation state: route_of must hold routes 0..{len(routes) - 1}")
    for i, p in enumerate(pieces):
        if not set(p[:, 0].tolist()) <= {int(m) for m in routes[int(route_of[i])]}:
            raise StoreError(f"segmentation state: route_of[{i}] is a route without the steps of pieces[{i}]")
    mean = floats("space_mean", (None, d), f"(J, d) = (J, {d}) (d: the columns of attractors)", like=attractors)
    J = mean.shape[0]
    cov = floats("space_covariance", (J, d, d), f"(J, d, d) = ({J}, {d}, {d}) (J: the rows of space_mean)",
                 like=attractors)
    if not bool((torch.linalg.cholesky_ex(cov).info == 0).all()):  # as GaussianBank checks it
        raise StoreError("segmentation state: space_covariance must be symmetric positive definite")
    weights = floats("space_weights", (M, J), f"(M, J) = ({M}, {J}) (M: the rows of attractors, J: of space_mean)",
                     like=attractors)
    if not (bool((weights >= 0).all()) and bool((weights > 0).any(-1).all())):
        raise StoreError("segmentation state: space_weights must be >= 0 with a Gaussian (a positive entry) for "
                         "every step")
    if state.get("endpoints") is not None:
        floats("endpoints", (N, 2, d), f"(N, 2, d) = ({N}, 2, {d}) (N: the entries of labels, d: the columns of "
               "attractors)", like=attractors)


def _endpoints(demos: Demos) -> Tensor:
    """(N, 2, d) the first and last valid sample of every demonstration."""
    last = (demos.lengths - 1).to(demos.positions.device)
    rows = torch.arange(demos.n_demos, device=demos.positions.device)
    return torch.stack([demos.positions[:, 0], demos.positions[rows, last]], 1)


def _steps_from_bounds(demos: Demos, bounds: list[list[int]], info: dict[str, Any]) -> Segmentation:
    """Segmentation without an HMM: the same boundaries-defined steps in every demonstration, one route."""
    M = len(bounds[0]) - 1
    pieces = [[(m, b[m], b[m + 1]) for m in range(M)] for b in bounds]
    states = [torch.cat([torch.full((b[m + 1] - b[m],), m, dtype=torch.long, device=demos.device) for m in range(M)]) for b in bounds]
    # the resolution of the subtask-space Gaussians: the default minimum step of the HMM (a whole piece as one
    # Gaussian would let a step take a whole leg of another when one of its samples is best explained by it)
    stretch = max(3, min(resolve_min_length(DEFAULT_MIN_LENGTH, n) for n in demos.lengths.tolist()))
    noise = position_noise([s.to(torch.float64) for s in demos.sequences()])
    return _assemble(demos, pieces, [list(range(M))], [0] * len(bounds), states, [-1] * M, stretch, noise**2,
                     None, info)


# ---------------------------------------------------------------------------------------------- entry points
def segment(
    demos: Demos | Sequence[Tensor],
    *,
    generator: torch.Generator,
    min_length: float = DEFAULT_MIN_LENGTH,
    max_samples: int = 80,
    direction_noise: float = 0.2,
    extra_dof: float = 30.0,
    slope_scale: float = 1.0,
    slope_scale_mix: float = 0.0,
    rotation_weight: float = 0.0,
    robust_dof: float | None = 4.0,
    position_weight: float | None = None,
    position_mixture: bool = True,
    straight_weight: float = 0.5,
    tolerance_correlation: float | None = 0.0,
    dwell_cue: bool = True,
    dwell_pace: bool = False,
    demo_offset: float = 0.0,
    block_emission: bool = True,
    block_tolerance: float = 0.1,
    noise_model: str = "ar1",
    feature_mass: float = 2.0,
    feature_concentration: float = 1.0,
    transition_concentration: float = 1.0,
    stickiness: float = 25.0,
    n_chains: int = 4,
    n_iterations: int = 40,
    burn_in: float = 0.5,
    n_initial_features: int = 4,
    birth_window: float = 0.1,
    birth_prior_mix: float = 0.1,
    resample_hyperparameters: bool = True,
    selection: str = "map",
    progress: bool = False,
) -> Segmentation:
    """Segment demonstrations into steps with the BP-GM-HMM (no number of steps is given).

    Args:
        demos: N demonstrations (a ``Demos`` or a list of (T_i, d) tensors, d >= 2); only positions and times
            are used (velocities are re-estimated at the model's time scale, :func:`scale_velocities`).
        generator: source of all randomness (CPU generator for CPU data).
        min_length: shortest step (the HMM's minimum state duration), samples (>= 1) or fraction of each
            sequence's length (< 1); every sequence needs at least 2 * min_length samples. On the sampler's
            path-length grid it is the same fraction of the path (module docstring, item 3).
        max_samples: points per sequence on the sampler's grid, at most (time stride k = ceil(T_i / max_samples),
            ceil(T_i / k) points equally spaced in path length, module docstring item 3); 8..1000 (a sweep costs
            O(T (K D)^2) on a grid of T points with D ~ min_length T, so about T^3; 3 x 1200 samples, 2-D:
            80 / 200 / 400 -> 1.1 / 2.4 / 3.9 s).
        direction_noise: tolerance of a state's direction field, the prior expected direction noise (unit
            vectors, ~radians).
        extra_dof: weight of that prior expectation (pseudo-observations of the noise covariance).
        slope_scale: prior standard deviation of a field's slope per radius of the data (:func:`.field.field_prior`;
            1: a field turns the direction by about a radian per radius). Measured, not the default: 3 trades
            straight and multi-demonstration cases against single curved demonstrations
            (experiments/segmentation_studies.md).
        slope_scale_mix: s >= 0: in the collapsed score (so ``selection="map"``) the affine fields' slope prior is an
            equal mixture of the scales ``slope_scale`` and s, so that a state may curve gently or tightly
            (:mod:`.sampler`, "Slope scale"; with ``block_emission`` each curved state's scale is profiled,
            "Block emission"); 0: ``slope_scale`` alone.
        rotation_weight: r in [0, 1): in the collapsed score the affine slab is the mixture (1 - r) affine + r
            rigid rotation, which fits a circular arc with fewer parameters and no merge better
            (:mod:`.sampler`, "Rotation fields"); 0: affine alone.
        position_weight: tau of the tempered position Gaussian of every state, in [0, 1]; None: 1 / D (D the
            minimum duration in grid samples, the default); 0: directions alone (:mod:`.sampler`, "Position").
        position_mixture: the position term as a mixture over space, each state's Gaussian times its occupancy
            of the sequence (integrated out), so that cutting a leg does not raise the positions' density
            (:mod:`.sampler`, "Position"); acts through ``selection="map"``. On by default, with ``block_emission``
            (the pair was measured together, experiments/segmentation_studies.md, "Block emission with positions as
            a mixture over space"); off, the Gaussians reward cutting a long leg.
        straight_weight: prior probability that a state's field is straight (slope 0) in the collapsed score, in
            [0, 1); it acts through ``selection="map"`` (:mod:`.sampler`, "Straight states"); 0: every field affine.
        tolerance_correlation: rho in [0, 1), the correlation of consecutive deviations of a direction from its
            step's field in the collapsed score, so in ``selection="map"`` (:mod:`.sampler`, "Correlated
            tolerance"); 0: independent deviations; None: chosen with the labelling (type-II over a grid).
        dwell_cue: the model also explains the time spent between grid points, with a learned shift at the first
            point of a run (:mod:`.dwell`): a pause marks a step boundary as far as the data show it. Needs a
            minimum duration of at least 2 grid points. Where fewer than 2 grid points can start a run (short
            demonstrations, or ``min_length`` near half of one) the term starts from a finite fallback
            (:func:`~.dwell.dwell_log_likelihood`), so that such demonstrations segment (usually into one step)
            instead of failing.
        dwell_pace: with ``dwell_cue``, the collapsed score (so ``selection="map"``) also gives every run its own
            pace level (:mod:`.dwell`, "Pace of a run"): a change of pace where the directions change is evidence of
            a switch. Measured, not the default: it finds more constant-speed corners, but cuts a one-step LASA
            route in two on only some seeds (experiments/segmentation_studies.md, "A pace level per run").
        block_emission: in the collapsed score (so ``selection="map"``) the states' motion is scored on the block
            means of the positions around the grid points (:mod:`.blocks`): a straight state is a line through
            them, with the lever arm of its length, a curved one an affine field with the direction tolerance.
            The default (with ``position_mixture``); False scores the least-squares directions alone, the earlier
            default (``block_emission=False, position_mixture=False``; README, "Segmentation").
        block_tolerance: with ``block_emission``, the curved states' direction tolerance sigma_u (rad), a random
            walk of the position along a run (:mod:`.blocks`).
        demo_offset: v >= 0: in the collapsed score (so ``selection="map"``) every demonstration adds its own offset
            ~ N(0, v Psi) to the field of each state it visits (:mod:`.sampler`, "Demonstrations' own offsets"); 0:
            one field per state. Measured, not the default: with a tight tolerance it keeps a curved leg shared by
            several demonstrations in one step, but LASA is not seed-stable at that tolerance
            (experiments/segmentation_studies.md, "Each demonstration's own offset").
        noise_model: the position noise behind the velocities' noise (the direction reliabilities of :mod:`.field`
            and the path-length grid): "ar1" (default) white or correlated, fitted by
            :func:`position_noise_model`; "white": white, from lag-one second differences (:func:`position_noise`;
            the earlier default, the same estimate wherever the fit finds no correlation that matters).
        resample_hyperparameters: also sample the feature mass gamma, the transition concentration alpha and the
            stickiness kappa (their given values are the chains' starting points; :mod:`.sampler`, move 5): how
            often a demonstration switches is learned from it, not fixed. Against the fixed values (the sampler
            class's default) on the synthetic benchmark: one more single scoop with pauses segmented right (a
            search failure with them), one single constant-speed scoop less seed-stable
            (experiments/segmentation_studies.md, "Earlier settings").
        Remaining keyword arguments: see :class:`BetaProcessHMMSampler`; their accepted ranges (upper bounds where
            a hyperparameter scales the cost, with the measured cost) are
            :data:`~lfd_torch.segmentation.sampler.HYPERPARAMETER_RANGES`.

    Returns:
        Segmentation; ``info`` holds timings, the strides, the grid (full-rate sample of every grid point), the
        minimum duration on the grid, the position noise estimate (``position_noise``, ``noise_correlation``), the
        interior velocity noise and the coarse runs.

    Raises:
        InvalidArgumentError: 1-D data or a hyperparameter out of its range (the message names it and the range).
        TooFewSamplesError: a sequence shorter than 2 * min_length.
        InvalidDemoError: a demonstration that does not move (one repeated point).
        SolverError: a linear-algebra failure inside the sampler (the cause chained).
    """
    # every hyperparameter first (typed errors naming it, before any work; the bounds keep the cost finite)
    if not isinstance(generator, torch.Generator):
        raise InvalidArgumentError(f"generator must be a torch.Generator, got {generator!r}")
    integral = isinstance(max_samples, numbers.Integral) and not isinstance(max_samples, bool)
    if not (integral and 8 <= max_samples <= MAX_GRID):
        raise InvalidArgumentError(f"max_samples must be an integer in [8, {MAX_GRID}], got {max_samples!r}")
    if not isinstance(dwell_cue, bool):
        raise InvalidArgumentError(f"dwell_cue must be a bool, got {dwell_cue!r}")
    if noise_model not in NOISE_MODELS:
        raise InvalidArgumentError(f"noise_model must be one of {NOISE_MODELS}, got {noise_model!r}")
    sampler = BetaProcessHMMSampler(
        feature_mass=feature_mass, feature_concentration=feature_concentration,
        transition_concentration=transition_concentration, stickiness=stickiness,
        direction_noise=direction_noise, extra_dof=extra_dof, slope_scale=slope_scale,
        slope_scale_mix=slope_scale_mix, rotation_weight=rotation_weight, robust_dof=robust_dof,
        position_weight=position_weight, position_mixture=position_mixture, tolerance_correlation=tolerance_correlation,
        dwell_pace=dwell_pace, demo_offset=demo_offset, block_emission=block_emission,
        block_tolerance=block_tolerance,
        straight_weight=straight_weight, n_chains=n_chains, n_iterations=n_iterations, burn_in=burn_in, n_initial_features=n_initial_features,
        birth_window=birth_window, birth_prior_mix=birth_prior_mix,
        resample_hyperparameters=resample_hyperparameters, selection=selection, progress=progress,
    )  # fmt: skip
    demos = _check_demos(demos, min_length)
    if demos.dim < 2:
        raise InvalidArgumentError(
            "BP-GM-HMM segmentation needs d >= 2: its states are fields of motion directions, and a 1-D path has "
            "only two; use FixedSegmenter or NoSegmenter for 1-D data"
        )
    t0 = time.perf_counter()
    seqs_full = [s.to(torch.float64) for s in demos.sequences()]
    for i, s in enumerate(seqs_full):
        if not bool((s != s[:1]).any()):
            raise InvalidDemoError("does not move (every sample is the same point): its motion has no direction, "
                                   "so the BP-GM-HMM has nothing to segment", i)
    times = [demos.times[i, : int(demos.lengths[i])].to(torch.float64) for i in range(demos.n_demos)]
    dts = [float((t[1:] - t[:-1]).median()) for t in times]
    strides = [max(1, math.ceil(s.shape[0] / max_samples)) for s in seqs_full]
    if noise_model == "ar1":
        sigma_x, rho_x = position_noise_model(seqs_full)
    else:
        sigma_x, rho_x = position_noise(seqs_full), 0.0
    points = torch.cat(seqs_full)
    sigma_x = max(sigma_x, NOISE_FLOOR * float((points.amax(0) - points.amin(0)).norm()))
    vel_full = [scale_velocities(s, k, dt) for s, k, dt in zip(seqs_full, strides, dts)]
    speeds = torch.cat([v.norm(dim=-1) for v in vel_full])
    s_floor = 1e-3 * float(speeds.median())  # noise-free data: directions are unreliable only at rest
    sigma_v_full = [velocity_noise(sigma_x, s.shape[0], k, dt, rho=rho_x).to(s)
                    for s, k, dt in zip(seqs_full, strides, dts)]
    sigma_v = [float(sv.min()) for sv in sigma_v_full]  # inside the sequences
    grid_levels = [_grid_levels(v, sv, k, dt) for v, sv, k, dt in zip(vel_full, sigma_v_full, strides, dts)]
    grid = [g for _, g, _ in grid_levels]  # path_grid of every sequence
    xs = [s[g] for s, g in zip(seqs_full, grid)]
    vs = [v[g] for v, g in zip(vel_full, grid)]
    min_lens = [resolve_min_length(min_length, s.shape[0]) for s in seqs_full]
    duration = max(1, min(math.ceil(m * g.shape[0] / s.shape[0]) for m, g, s in zip(min_lens, grid, seqs_full)))
    n_max = max(x.shape[0] for x in xs)
    sigma_v_t = torch.stack([torch.cat([sv[g], sv[g][-1:].expand(n_max - g.shape[0])])
                             for sv, g in zip(sigma_v_full, grid)])  # (N, T) on the grid, padded
    dwell = None
    if dwell_cue:
        if duration < 2:
            raise InvalidArgumentError(f"dwell_cue needs a minimum duration of at least 2 grid points, got {duration} "
                                       "(raise min_length or max_samples)")
        crossing = [(_crossings(length, lv, t), lv) for (length, _, lv), t in zip(grid_levels, times)]
        dwell = [dwell_covariate(c, torch.arange(c.shape[0], device=c.device), lv) for c, lv in crossing]
    if tolerance_correlation != 0.0 and duration < 2:
        raise InvalidArgumentError(f"tolerance_correlation other than 0 needs a minimum duration of at least 2 grid "
                                   f"points, got {duration} (raise min_length or max_samples)")
    blocks = None
    if block_emission:
        parts = [block_means(s, g, length) for s, g, (length, _, _) in zip(seqs_full, grid, grid_levels)]
        blocks = BlockMeans([m for m, _, _ in parts], [l for _, l, _ in parts], [c for _, _, c in parts], sigma_x)
    try:
        result = sampler.run(xs, vs, generator, min_duration=duration, velocity_noise=sigma_v_t,
                             speed_floor=s_floor, dwell=dwell, blocks=blocks)
    except torch.linalg.LinAlgError as exc:  # a degenerate field posterior (e.g. data without any spread)
        raise SolverError(f"the BP-GM-HMM sampler failed on these demonstrations: {exc}") from exc
    t1 = time.perf_counter()
    info_dwell = {k: v for k, v in result.hyperparameters.items() if k.startswith("dwell_")}
    # full-rate state sequences: the coarse runs, each switch placed by the change-point posterior
    runs_all: list[list[tuple[int, int, int]]] = []  # (state, start, end) at full rate
    states_full = []
    junctions: list[list[tuple[int, Tensor]]] = []  # per switch: (first sample, label doubt of each sample)
    for i, (xf, vf, k) in enumerate(zip(seqs_full, vel_full, strides)):
        Ti = xf.shape[0]
        n_c = xs[i].shape[0]
        st = result.states[i, :n_c]
        starts, _, values = runs(st)
        obs = field_observations(xf.unsqueeze(0), vf.unsqueeze(0), torch.ones(1, Ti, dtype=torch.bool,
                                 device=xf.device), velocity_noise=sigma_v_full[i].unsqueeze(0),
                                 direction_noise=direction_noise, speed_floor=s_floor, centre=result.centre,
                                 radius=result.radius)
        ll = field_log_likelihood_additive(obs.z, obs.u, obs.w, result.field.unsqueeze(0), result.noise.unsqueeze(0),
                                           robust_dof, direction_noise=direction_noise)[0]
        cuts = [0]
        junc: list[tuple[int, Tensor]] = []
        coarse = grid[i][starts].tolist()  # full-rate sample of every run's first grid point
        switch_prior = None if not info_dwell else _dwell_switch_prior(
            grid_levels[i][0], times[i], *crossing[i], info_dwell)
        for r in range(1, len(coarse)):
            lo = max(cuts[-1] + 1, (coarse[r - 1] + coarse[r]) // 2)
            hi = min(Ti - 1, (coarse[r] + (coarse[r + 1] if r + 1 < len(coarse) else Ti)) // 2)
            if hi <= lo:
                cuts.append(min(max(coarse[r], cuts[-1] + 1), Ti - 1))
                junc.append((cuts[-1], xf.new_zeros(0)))
                continue
            if result.switch_scores is not None:
                # the model's posterior over the grid interval, the direction likelihood within each interval
                j0, grid_score = result.switch_scores[i][r - 1]
                lo, cut, doubt = _refine_switch_on_grid(ll, int(values[r - 1]), int(values[r]), grid[i], j0,
                                                        grid_score, cuts[-1] + 1, Ti - 1, k, switch_prior)
            else:
                cut, doubt = _refine_switch(ll, int(values[r - 1]), int(values[r]), lo, hi, k, switch_prior)
            cuts.append(cut)
            junc.append((lo, doubt))
        cuts.append(Ti)
        junctions.append(junc)
        rl = [(int(values[r]), cuts[r], cuts[r + 1]) for r in range(len(cuts) - 1)]
        runs_all.append(rl)
        states_full.append(torch.cat([torch.full((b - a,), s, dtype=torch.long, device=xf.device) for s, a, b in rl]))
    # steps across demonstrations: routes by shared states, then a progressive alignment within each route
    seqs = [[s for s, _, _ in rl] for rl in runs_all]
    fracs = [[(b - a) / rl[-1][2] for _, a, b in rl] for rl in runs_all]
    groups = _routes(seqs, fracs)
    pieces: list[list[tuple[int, int, int]]] = [[] for _ in seqs]
    routes, route_of, step_state = [], [0] * len(seqs), []
    for r, members in enumerate(groups):
        states_r, assign = _align_route([seqs[i] for i in members], [fracs[i] for i in members])
        offset = len(step_state)
        step_state.extend(states_r)
        routes.append(list(range(offset, offset + len(states_r))))
        for i, steps_i in zip(members, assign):
            route_of[i] = r
            pieces[i] = [(offset + m, a, b) for m, (_, a, b) in zip(steps_i, runs_all[i])]
    info = {
        "sampler_seconds": t1 - t0,
        "postprocess_seconds": time.perf_counter() - t1,
        "strides": strides,
        "min_duration": duration,
        "position_noise": sigma_x,
        "noise_correlation": rho_x,
        "velocity_noise": sigma_v,
        "coarse_runs": [[(s, int(torch.searchsorted(g, a))) for s, a, _ in rl] for rl, g in zip(runs_all, grid)],
        "grid": [g.tolist() for g in grid],
        "log_prob": result.log_prob,
        "collapsed_log_prob": result.collapsed_log_prob,
        "chain": result.chain,
        "dwell": info_dwell,
    }
    stretch = max(3, min(min_lens))
    return _assemble(demos, pieces, routes, route_of, states_full, step_state, stretch, sigma_x**2, result, info,
                     junctions)


class BPGMHMMSegmenter:
    """Config-friendly BP-GM-HMM segmenter: keyword arguments of :func:`segment` are fixed at construction.

    ``BPGMHMMSegmenter(**cfg)(demos, generator=g)`` equals ``segment(demos, generator=g, **cfg)``.
    """

    def __init__(self, **hyperparameters: Any) -> None:
        import inspect

        valid = set(inspect.signature(segment).parameters) - {"demos", "generator"}
        unknown = set(hyperparameters) - valid
        if unknown:
            raise InvalidArgumentError(f"unknown hyperparameters {sorted(unknown)} of segment(); "
                                       f"valid: {sorted(valid)}")
        self.hyperparameters = dict(hyperparameters)

    def __call__(self, demos: Demos | Sequence[Tensor], *, generator: torch.Generator) -> Segmentation:
        return segment(demos, generator=generator, **self.hyperparameters)


class FixedSegmenter:
    """Hand-given boundaries (ablations).

    Args:
        boundaries: inner boundaries as fractions of each demonstration's length in (0, 1), increasing; the same
            for every demonstration. ``[]`` gives one step.
    """

    def __init__(self, boundaries: Sequence[float] = ()) -> None:
        try:
            b = [float(v) for v in boundaries]
        except (TypeError, ValueError) as exc:
            msg = f"boundaries must be increasing fractions in (0, 1), got {boundaries!r}"
            raise InvalidArgumentError(msg) from exc
        if any(not 0 < v < 1 for v in b) or any(b2 <= b1 for b1, b2 in zip(b, b[1:])):
            raise InvalidArgumentError(f"boundaries must be increasing fractions in (0, 1), got {b}")
        self.boundaries = b

    def __call__(self, demos: Demos | Sequence[Tensor], *, generator: torch.Generator | None = None) -> Segmentation:
        demos = _check_demos(demos, 3)
        bounds = []
        for i, n in enumerate(demos.lengths.tolist()):
            b = [0] + [int(round(f * n)) for f in self.boundaries] + [n]
            if any(b2 - b1 < 1 for b1, b2 in zip(b, b[1:])):
                raise TooFewSamplesError(f"a fixed step would be empty (length {n})", i)
            bounds.append(b)
        return _steps_from_bounds(demos, bounds, {"method": "fixed"})


class NoSegmenter:
    """One step per demonstration (the whole task is one primitive)."""

    def __call__(self, demos: Demos | Sequence[Tensor], *, generator: torch.Generator | None = None) -> Segmentation:
        demos = _check_demos(demos, 3)
        bounds = [[0, n] for n in demos.lengths.tolist()]
        return _steps_from_bounds(demos, bounds, {"method": "none"})
