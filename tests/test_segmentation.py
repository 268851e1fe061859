"""BP-GM-HMM segmentation (direction-field states, minimum duration, routes): accuracy on data with known switches,
mutants that must fail the same checks, routes, subtask spaces, determinism, API contract and bad input.

Every random draw is seeded through a ``torch.Generator``. The accuracy property used throughout
(:func:`step_accuracy`) is: every demonstration has exactly the true number of steps, and every true switch is found
within 3 % of that demonstration's length.
"""

from __future__ import annotations

import collections
import functools
import inspect
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

import lfd_torch.segmentation.sampler as sampler_module
import lfd_torch.segmentation.segmentation as segmentation_module
from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, StoreError, TooFewSamplesError
from lfd_torch.gmm import niw_log_marginal_likelihood
from lfd_torch.segmentation import (
    BetaProcessHMMSampler,
    BPGMHMMSegmenter,
    FixedSegmenter,
    NoSegmenter,
    SamplerResult,
    Segmentation,
    multi_step_demos,
    runs,
    segment,
)
from lfd_torch.segmentation.segmentation import _steps_from_bounds
from conftest import capture_runs, requires_cuda

F64 = torch.float64
CONF = Path(__file__).resolve().parents[1] / "conf"
FAST = dict(max_samples=40, n_iterations=15, n_chains=2)
SWITCH_TOLERANCE = 0.03  # fraction of a demonstration's length


# ---------------------------------------------------------------------------------------------- helpers
def step_accuracy(seg: Segmentation, switch_times: torch.Tensor, lengths: torch.Tensor) -> tuple[bool, list]:
    """The step property: per demonstration, the true number of steps and every true switch within 3 % of T_i.

    Returns:
        (holds, report) with one report entry per demonstration: the largest switch error as a fraction of T_i,
        or ("count", found, true) when the number of steps is wrong.
    """
    holds, report = True, []
    for i in range(switch_times.shape[0]):
        T = int(lengths[i])
        found, truth = seg.switches(i), switch_times[i].tolist()
        if len(found) != len(truth):
            holds = False
            report.append(("count", len(found) + 1, len(truth) + 1))
            continue
        err = max((abs(a - b) / T for a, b in zip(found, truth)), default=0.0)
        report.append(round(err, 4))
        holds = holds and err <= SWITCH_TOLERANCE
    return holds, report


# (profile, dim, n_demos, n_steps, seed): the full grid, no case left out
ACCURACY_CASES = [
    (profile, dim, n_demos, n_steps, seed)
    for profile in ("min_jerk", "constant")
    for dim in (2, 3)
    for n_demos in (1, 4)
    for n_steps in (3, 4)
    for seed in (0, 1)
]


def _case_id(case: tuple) -> str:
    profile, dim, n_demos, n_steps, seed = case
    return f"{profile}-{dim}d-{n_demos}demos-{n_steps}legs-seed{seed}"


# Known failures of the landed model: listed so that the suite records them and a fix that makes one pass is
# noticed (strict xfail). None on this grid since the sampler's grid is equally spaced in path length (the
# benchmark families still have failures, experiments/bench_segmentation.py).
KNOWN_ACCURACY_FAILURES: set[str] = set()
KNOWN_MEMBERSHIP_FAILURES: set[str] = set()  # none since the subtask spaces share Gaussians (schema 3)


def _cases(known: set[str], reason: str) -> list:
    return [pytest.param(c, marks=pytest.mark.xfail(strict=True, reason=reason)) if _case_id(c) in known else c
            for c in ACCURACY_CASES]


@functools.lru_cache(maxsize=None)
def synthetic(profile: str, dim: int, n_demos: int, n_steps: int, seed: int):
    return multi_step_demos(torch.Generator().manual_seed(seed), n_demos=n_demos, n_steps=n_steps, dim=dim,
                            profile=profile)  # fmt: skip


@functools.lru_cache(maxsize=None)
def segmented(profile: str, dim: int, n_demos: int, n_steps: int, seed: int) -> Segmentation:
    """``segment`` with its default hyperparameters (cached: the accuracy and subtask-space tests share it)."""
    syn = synthetic(profile, dim, n_demos, n_steps, seed)
    return segment(syn.demos, generator=torch.Generator().manual_seed(seed))


# ---------------------------------------------------------------------------------------------- 1. accuracy
@pytest.mark.parametrize("case", _cases(KNOWN_ACCURACY_FAILURES, "known: an extra short step"), ids=_case_id)
def test_steps_and_switches_match_the_truth(case):
    """Property: with the default hyperparameters every demonstration gets the true number of steps and every true
    switch is found within 3 % of the demonstration's length (:func:`step_accuracy`)."""
    syn = synthetic(*case)
    seg = segmented(*case)
    holds, report = step_accuracy(seg, syn.switch_times, syn.demos.lengths)
    assert holds, f"per demonstration (max switch error / T, or wrong step count): {report}"


@pytest.mark.parametrize("case", ACCURACY_CASES[::5], ids=_case_id)
def test_steps_are_maximal_runs_of_hmm_states(case):
    """Property: the result is self-consistent: a step is a maximal run of one HMM state (consecutive pieces have
    different states, every sample of a piece carries its step's state), pieces tile each demonstration in time
    order, and labels agree with the pieces."""
    syn = synthetic(*case)
    seg = segmented(*case)
    for i in range(seg.n_sequences):
        T = int(syn.demos.lengths[i])
        p = seg.pieces[i]
        assert int(p[0, 1]) == 0 and int(p[-1, 2]) == T and torch.equal(p[1:, 1], p[:-1, 2])
        starts, ends, values = runs(seg.states[i])
        assert torch.equal(starts, p[:, 1]) and torch.equal(ends, p[:, 2])
        assert torch.equal(seg.step_state[p[:, 0]], values)
        for step, a, b in p.tolist():
            assert (seg.labels[i][a:b] == step).all()
        assert seg.switches(i) == p[1:, 1].tolist() and seg.step_sequence(i) == p[:, 0].tolist()
        assert set(seg.step_sequence(i)) <= set(seg.routes[int(seg.route_of[i])])


# ---------------------------------------------------------------------------------------------- 2. mutants
MUTATION_CASE = ("constant", 2, 4, 3, 0)

#: The direction emission, named: these tests are about its mechanisms (dwell, tolerance, straight states,
#: the map search's moves on cases it was measured on), whatever ``segment``'s defaults are.
DIRECTIONS = dict(block_emission=False, position_mixture=False)


def collapsed_score(run, res: SamplerResult, s: torch.Tensor, F: torch.Tensor) -> float:
    """The sampler run's collapsed score of the labelling s (N, T) with features F (N, K) under the transition and
    feature hyperparameters of the result ``res``."""
    hyper = [torch.tensor([res.hyperparameters[k]], dtype=run.dtype)
             for k in ("transition_concentration", "stickiness", "feature_mass")]
    return float(run._collapsed_score(s[None], F[None], sampler_module.duration_phases(s[None], run.D), *hyper)[0])


def _blind_result(sequences: list[torch.Tensor], labeller) -> SamplerResult:
    """A SamplerResult whose states come from ``labeller(t, T_i)`` and whose fields are all equal (no data used)."""
    N, d = len(sequences), sequences[0].shape[1]
    T = max(s.shape[0] for s in sequences)
    states = []
    for s in sequences:
        lab = labeller(torch.arange(s.shape[0]), s.shape[0])
        states.append(torch.cat([lab, lab[-1:].expand(T - lab.shape[0])]))
    states = torch.stack(states).to(torch.long)
    K = int(states.max()) + 1
    return SamplerResult(
        states=states, lengths=torch.tensor([s.shape[0] for s in sequences]), features=torch.ones(N, K, dtype=torch.bool),
        field=torch.zeros(K, d, d + 1, dtype=F64), noise=0.04 * torch.eye(d, dtype=F64).expand(K, d, d).clone(),
        centre=torch.zeros(d, dtype=F64), radius=torch.tensor(1.0, dtype=F64), log_prob=0.0,
        trace=torch.zeros(1, 1, dtype=F64), n_features_trace=torch.zeros(1, 1, dtype=torch.long), chain=0,
    )  # fmt: skip


@pytest.mark.parametrize("labeller", ["every-2", "every-4", "every-8", "every-16", "equal-true-count"])
def test_data_blind_labeller_fails_the_step_property(monkeypatch, labeller):
    """Property checked: :func:`step_accuracy` (true step count, switches within 3 % of T). The real sampler passes
    it on this data set; a data-blind labeller that replaces the sampler (a new state every n coarse points, or the
    true number of equal-length steps) must fail it, or the accuracy test could not tell a model from a clock."""
    syn = synthetic(*MUTATION_CASE)
    real_ok, real_report = step_accuracy(segmented(*MUTATION_CASE), syn.switch_times, syn.demos.lengths)
    assert real_ok, real_report  # the property discriminates: the model passes it
    M = syn.n_steps
    if labeller == "equal-true-count":
        def lab(t, T):
            return (t * M) // T
    else:
        n = int(labeller.split("-")[1])

        def lab(t, T):
            return torch.clamp(t // n, max=(T - 1) // n)

    def fake_run(self, sequences, velocities, generator, *args, **kwargs):
        return _blind_result(sequences, lab)

    monkeypatch.setattr(BetaProcessHMMSampler, "run", fake_run)
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(0))
    ok, report = step_accuracy(seg, syn.switch_times, syn.demos.lengths)
    assert not ok, f"a data-blind labeller ({labeller}) passed the step property: {report}"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sampler_with_data_blind_likelihood_fails_the_step_property(monkeypatch, seed):
    """Property checked: :func:`step_accuracy`. With an emission log-likelihood that ignores the data (the direction
    fields' zeros, and the block emission, the default, scored on block means, path lengths and variances that are
    the same for every data set; in the sampler, in its scores of the switches' grid positions and in the switch
    refinement) the state sequences are draws from the prior; they must fail the property that the real sampler
    passes on the same data."""
    syn = synthetic(*MUTATION_CASE)
    real_ok, real_report = step_accuracy(segmented(*MUTATION_CASE), syn.switch_times, syn.demos.lengths)
    assert real_ok, real_report
    original = sampler_module.field_log_likelihood

    def blind(*args, maha_out: bool = False, **kwargs):
        ll, q = original(*args, maha_out=True, **kwargs)
        return (torch.zeros_like(ll), torch.zeros_like(q)) if maha_out else torch.zeros_like(ll)

    monkeypatch.setattr(sampler_module, "field_log_likelihood", blind)
    original_additive = segmentation_module.field_log_likelihood_additive

    def blind_additive(*args, **kwargs):
        return torch.zeros_like(original_additive(*args, **kwargs))

    monkeypatch.setattr(segmentation_module, "field_log_likelihood_additive", blind_additive)
    original_blocks = sampler_module.block_sequence_terms

    def blind_blocks(xbar, sbar, var, zmid, *args, **kwargs):
        steps = torch.arange(sbar.shape[-1], dtype=sbar.dtype).expand_as(sbar)
        return original_blocks(torch.zeros_like(xbar), steps, torch.ones_like(var), torch.zeros_like(zmid), *args,
                               **kwargs)

    monkeypatch.setattr(sampler_module, "block_sequence_terms", blind_blocks)
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(seed))
    ok, report = step_accuracy(seg, syn.switch_times, syn.demos.lengths)
    assert not ok, f"a sampler blind to the data passed the step property: {report}"


# ---------------------------------------------------------------------------------------------- 3. routes
def _two_path_demos():
    goal = [2.0, 1.0]
    WA = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], goal], dtype=F64)  # east, north, east
    WB = torch.tensor([[0.0, 3.0], [0.0, 2.0], [1.5, 2.0], goal], dtype=F64)  # south, east, south-east
    a = multi_step_demos(torch.Generator().manual_seed(0), n_demos=2, waypoints=WA, profile="constant")
    b = multi_step_demos(torch.Generator().manual_seed(100), n_demos=2, waypoints=WB, profile="constant")
    demos = Demos.from_sequences(a.demos.sequences() + b.demos.sequences(), dt=0.01, attractor=torch.tensor(goal, dtype=F64))
    return demos, (a, b), (WA, WB)


def test_demonstrations_on_different_paths_form_two_routes():
    """Property: two demonstrations along polyline A and two along a clearly different polyline B (no direction
    field in common) are grouped into exactly two routes {0, 1} and {2, 3}; each demonstration gets its path's
    steps and switches (within 3 %); every intermediate attractor lies within 2 % of the data span of the true
    corner and of every one of its pieces' end points; the last step of each route ends at the task attractor."""
    demos, (a, b), (WA, WB) = _two_path_demos()
    seg = segment(demos, generator=torch.Generator().manual_seed(0))
    assert seg.n_routes == 2, seg.routes
    assert seg.route_of.tolist() == [0, 0, 1, 1]
    assert set(seg.routes[0]).isdisjoint(seg.routes[1])
    truth = torch.cat([a.switch_times, b.switch_times])
    ok, report = step_accuracy(seg, truth, demos.lengths)
    assert ok, report
    x = torch.cat(demos.sequences())
    span = float((x.amax(0) - x.amin(0)).norm())
    for r, W in zip(seg.routes, (WA, WB)):
        assert len(r) == W.shape[0] - 1
        for m, corner in zip(r[:-1], W[1:-1]):
            assert float((seg.attractors[m] - corner).norm()) <= 0.02 * span, (m, seg.attractors[m], corner)
            for i in range(seg.n_sequences):
                for step, _, end in seg.pieces[i].tolist():
                    if step == m:
                        assert float((demos.positions[i, end - 1] - seg.attractors[m]).norm()) <= 0.02 * span
        torch.testing.assert_close(seg.attractors[r[-1]], demos.attractor)
    for i in range(4):
        assert seg.step_sequence(i) == list(seg.routes[int(seg.route_of[i])])


def _parallel_route_demos():
    goal = [1.3, 0.0]
    WA = torch.tensor([[-1.0, 0.5], [1.0, 0.5], goal], dtype=F64)  # east along y = 0.5, then a short south-east leg
    WB = torch.tensor([[-1.0, -0.5], [1.0, -0.5], goal], dtype=F64)  # east along y = -0.5, then north-east
    a = multi_step_demos(torch.Generator().manual_seed(0), n_demos=2, waypoints=WA, profile="constant")
    b = multi_step_demos(torch.Generator().manual_seed(100), n_demos=2, waypoints=WB, profile="constant")
    return Demos.from_sequences(a.demos.sequences() + b.demos.sequences(), dt=0.01,
                                attractor=torch.tensor(goal, dtype=F64))


def test_position_term_keeps_states_of_distant_pieces_apart():
    """Property (spatial identification, sampler docstring "Position"): two routes whose legs run in the same
    directions one unit apart share no HMM state when the emission sees the tempered position
    (``position_weight=None``), on 3 of 3 seeds, and still give two routes of two steps. Mutant: with directions
    alone (``position_weight=0``) one field serves both routes on at least one of the same seeds (measured: all 3),
    so the check is the position term's doing."""
    demos = _parallel_route_demos()

    def shared(seg):
        a = set(torch.cat([seg.sampler.states[i, : int(seg.sampler.lengths[i])] for i in (0, 1)]).tolist())
        b = set(torch.cat([seg.sampler.states[i, : int(seg.sampler.lengths[i])] for i in (2, 3)]).tolist())
        return a & b

    for seed in range(3):
        seg = segment(demos, generator=torch.Generator().manual_seed(seed), position_weight=None)
        assert not shared(seg), (seed, shared(seg))
        assert seg.route_of.tolist() == [0, 0, 1, 1] and [len(p) for p in seg.pieces] == [2, 2, 2, 2]
    mutant = [segment(demos, generator=torch.Generator().manual_seed(seed), position_weight=0.0) for seed in range(3)]
    assert any(shared(seg) for seg in mutant)


_DETOUR = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 0.4], [1.0, 0.0], [2.0, 0.5]], dtype=F64)


def _detour_demos(seed: int, other: torch.Tensor) -> Demos:
    """Three demonstrations of A (east), B1 (north), B2 (back south), C (27 degrees north of east), one along the
    waypoints ``other`` (rows of ``_DETOUR``)."""
    full = multi_step_demos(torch.Generator().manual_seed(seed), n_demos=3, waypoints=_DETOUR, profile="constant")
    odd = multi_step_demos(torch.Generator().manual_seed(seed + 100), n_demos=1, waypoints=other, profile="constant")
    return Demos.from_sequences(full.demos.sequences() + odd.demos.sequences(), dt=0.01, attractor=_DETOUR[-1])


def _order_pairs(a, b, wa, wb):  # mutant of ``_lcs``: the k-th run of one sequence matched to the k-th of the other
    return [(k, k) for k in range(min(len(a), len(b)))]


# the settings before the map search, the position term, straight states and the dwell term became the defaults
JOINT_DIRECTIONS = dict(selection="joint", position_weight=0.0, straight_weight=0.0, dwell_cue=False)


@pytest.mark.parametrize("options", [JOINT_DIRECTIONS, {}], ids=["joint_directions", "default"])
def test_demonstration_that_skips_a_step_is_aligned_by_its_states(monkeypatch, options):
    """Property (issue 7, item 2): three demonstrations go A, B1, B2, C (a detour north and back between two legs
    east); a fourth leaves the detour out (A, then C). The model gives the fourth demonstration's two runs the
    states of A and C, and the alignment of the runs by their states puts it on the route's first and last steps:
    one route of four steps, the skipping demonstration on [first, last], on 4 of 4 seeds. Mutant: matching the
    runs by their order puts its C run on B1's step (it fails on every seed), so the check is the alignment by
    states, not by order."""
    def skipped(seed):
        seg = segment(_detour_demos(seed, _DETOUR[[0, 1, 4]]), generator=torch.Generator().manual_seed(seed),
                      **options)  # fmt: skip
        route = list(seg.routes[0]) if seg.n_routes == 1 else []
        return (len(route) == 4 and all(seg.step_sequence(i) == route for i in range(3))
                and seg.step_sequence(3) == [route[0], route[-1]]), (seg.routes, [seg.step_sequence(i) for i in range(4)])

    results = [skipped(seed) for seed in range(4)]
    assert all(ok for ok, _ in results), results
    monkeypatch.setattr(segmentation_module, "_lcs", _order_pairs)
    assert not any(skipped(seed)[0] for seed in range(2))


def test_demonstration_that_repeats_a_step_is_aligned_by_its_states():
    """Property (issue 7, item 2): a fourth demonstration makes the detour of the three others twice (A, B1, B2, B1,
    B2, C). It joins their route; the route holds every run of it as a step in order (six steps, the repeated
    states twice: a state recurs in two steps), and the three others take four of them, chosen by state: A, a B1
    step, a later B2 step (of either copy: both alignments are longest common subsequences), C. Checked on 4 seeds."""
    failures = []
    for seed in range(4):
        seg = segment(_detour_demos(seed, _DETOUR[[0, 1, 2, 3, 2, 3, 4]]), generator=torch.Generator().manual_seed(seed),
                      **DIRECTIONS)
        route = list(seg.routes[0]) if seg.n_routes == 1 else []
        states = [int(seg.step_state[m]) for m in route]
        full = [seg.step_sequence(i) for i in range(3)]
        ok = (len(route) == 6 and seg.step_sequence(3) == route and states[1:3] == states[3:5]
              and len(set(states[:3] + states[5:])) == 4 and all(f == full[0] for f in full)
              and len(full[0]) == 4 and full[0][0] == route[0] and full[0][-1] == route[-1]
              and [int(seg.step_state[m]) for m in full[0]] == [states[k] for k in (0, 1, 2, 5)])
        if not ok:
            failures.append((seed, seg.routes, full, seg.step_sequence(3), states))
    assert not failures, failures


@pytest.mark.xfail(strict=True, reason="a shortcut is not a skip to the model: the shortcut leg is a motion of its "
                   "own (its own state), and the state it shares covers less than half of the demonstration")
def test_demonstration_that_takes_a_shortcut_joins_the_route():
    """Open (a shortcut, not a skip; the skip is tested above): three demonstrations along legs A (east), B (a
    short jog north) and C (11 degrees north of east) and one that goes from A's end straight to the goal (leaving
    out B; its last leg runs at 31 degrees, 20 from C) form one route; the shortcutting demonstration visits the
    route's first and last steps only. Checked for 4 seeds.
    Measured (seeds 0-3): the full demonstrations' states are A, B, A (C is within the 0.2 rad tolerance of A's
    field), the skipping one's A, X with X its own; A covers 46 % of its path, short of the half that
    ``_routes`` asks of the shared states, so on seeds 0, 2, 3 it forms a route of its own (on seed 1 it joins the
    route with its last leg as a step of its own)."""
    W = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 0.4], [2.0, 0.6]], dtype=F64)
    failures = []
    for seed in range(4):
        full = multi_step_demos(torch.Generator().manual_seed(seed), n_demos=3, waypoints=W, profile="constant")
        skip = multi_step_demos(torch.Generator().manual_seed(seed + 100), n_demos=1, waypoints=W[[0, 1, 3]],
                                profile="constant")  # fmt: skip
        demos = Demos.from_sequences(full.demos.sequences() + skip.demos.sequences(), dt=0.01, attractor=W[-1])
        seg = segment(demos, generator=torch.Generator().manual_seed(seed))
        route = list(seg.routes[0]) if seg.n_routes == 1 else None
        if route is None or len(route) != 3 or seg.step_sequence(3) != [route[0], route[2]]:
            failures.append((seed, seg.routes, [seg.step_sequence(i) for i in range(4)]))
    assert not failures, failures


# ---------------------------------------------------------------------------------------------- 4. subtask spaces
@pytest.mark.parametrize("case", _cases(KNOWN_MEMBERSHIP_FAILURES, "known: overlap at rests"), ids=_case_id)
def test_subtask_spaces_contain_their_steps_samples(case):
    """Property (paper Sec. IV): >= 98 % of every step's own samples x satisfy ``membership``, i.e.
    p(x | A_m) >= p(x | A_m-) for their step m (by construction all of them: their most responsible Gaussian is in
    A_m, module docstring of :mod:`lfd_torch.segmentation.segmentation`)."""
    syn = synthetic(*case)
    seg = segmented(*case)
    fractions = []
    for m in range(seg.n_steps):
        pts = torch.cat([syn.demos.positions[i, : int(syn.demos.lengths[i])][seg.labels[i] == m]
                         for i in range(seg.n_sequences)])  # fmt: skip
        fractions.append(round(float(seg.membership(pts)[:, m].double().mean()), 3))
    assert min(fractions) >= 0.98, f"fraction of each step's samples inside its subtask space: {fractions}"


def test_segmentation_holds_normal_tensors_usable_in_autograd(monkeypatch):
    """The sampler runs in inference mode, but what ``segment`` returns holds normal tensors: the sampler's result
    can be edited in place outside inference mode, and gradients of log p(x | A_m) flow to x (a sampler that
    returned its inference tensors fails the first check)."""
    import lfd_torch.segmentation.sampler as sampler_module

    modes, original = [], sampler_module._Run.sample

    def sample(self):
        modes.append(torch.is_inference_mode_enabled())
        return original(self)

    monkeypatch.setattr(sampler_module._Run, "sample", sample)
    syn = synthetic(*ACCURACY_CASES[0])
    segment(syn.demos, generator=torch.Generator().manual_seed(0), n_iterations=2, n_chains=1)
    assert modes == [True]  # the sampler ran in inference mode
    seg = segmented(*ACCURACY_CASES[0])
    res = seg.sampler
    for name in ("states", "lengths", "features", "field", "noise", "centre", "radius", "trace", "n_features_trace"):
        tensor = getattr(res, name)
        assert not tensor.is_inference(), name
        tensor.copy_(tensor.clone())  # an in-place edit outside inference mode
    x = torch.cat(synthetic(*ACCURACY_CASES[0]).demos.sequences()).clone().requires_grad_(True)
    seg.log_density(x).max(-1).values.sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and bool((x.grad != 0).any())


@pytest.mark.parametrize("case", ACCURACY_CASES[::3], ids=_case_id)
def test_subtask_density_falls_off_away_from_the_data(case):
    """Property: log p(x | A_m) is finite, and for every step it is lower at points 10 data spans from the data's
    centre than at every one of the step's own samples."""
    syn = synthetic(*case)
    seg = segmented(*case)
    x = torch.cat(syn.demos.sequences())
    span = float((x.amax(0) - x.amin(0)).norm())
    dirs = torch.nn.functional.normalize(torch.randn(32, seg.dim, generator=torch.Generator().manual_seed(0), dtype=F64), dim=-1)
    far = seg.log_density(x.mean(0) + 10.0 * span * dirs)  # (32, M)
    assert torch.isfinite(seg.log_density(x)).all() and torch.isfinite(far).all()
    for m in range(seg.n_steps):
        own = torch.cat([syn.demos.positions[i, : int(syn.demos.lengths[i])][seg.labels[i] == m]
                         for i in range(seg.n_sequences)])  # fmt: skip
        assert float(far[:, m].max()) < float(seg.log_density(own)[:, m].min())


def test_log_density_is_the_best_member_and_other_steps():
    """Property: ``log_density`` equals a per-point reference (scipy) of max over the Gaussians j of A_m of
    log(w_mj N(x; mu_j, Sigma_j)) with 0/1 memberships w, every step owning at least its own stretches, for batched
    input; ``other_log_density`` is the max over the other steps; ``membership`` compares them; a wrong dimension
    raises ShapeMismatchError."""
    from scipy.stats import multivariate_normal

    g = torch.Generator().manual_seed(5)
    syn = multi_step_demos(g, n_demos=2, n_steps=4, samples_per_step=30)
    seg = FixedSegmenter([0.25, 0.5, 0.75])(syn.demos)
    x = torch.randn(5, 7, 2, generator=g, dtype=F64)
    ld = seg.log_density(x)
    assert ld.shape == (5, 7, 4)
    w = seg.space_weights
    assert bool(((w == 0) | (w == 1)).all()) and bool((w.sum(-1) >= 1).all())
    for m in range(4):
        terms = []
        for j in range(seg.space_mean.shape[0]):
            if float(w[m, j]) > 0:
                dist = multivariate_normal(seg.space_mean[j].numpy(), seg.space_covariance[j].numpy())
                terms.append(torch.tensor(dist.logpdf(x.numpy())))
        torch.testing.assert_close(ld[..., m], torch.stack(terms).amax(0))
    other = seg.other_log_density(x)
    for m in range(4):
        torch.testing.assert_close(other[..., m], ld[..., [j for j in range(4) if j != m]].amax(-1))
    assert torch.equal(seg.membership(x), ld >= other)
    with pytest.raises(ShapeMismatchError):
        seg.log_density(torch.zeros(3, 3, dtype=F64))


@pytest.mark.parametrize("case", [c for c in ACCURACY_CASES if c[0] == "constant" and c[4] == 0], ids=_case_id)
def test_subtask_spaces_do_not_swallow_the_other_steps(case):
    """Property: A_m is local. On constant-speed paths (no rest; steps meet only at their corner) at most 10 % of
    the samples of the other steps lie in A_m (the memberships are not a trivial "every Gaussian in every step")."""
    syn = synthetic(*case)
    seg = segmented(*case)
    x = torch.cat(syn.demos.sequences())
    lab = torch.cat(list(seg.labels))
    inside = seg.membership(x)
    shares = [round(float(inside[lab != m, m].double().mean()), 3) for m in range(seg.n_steps)]
    assert max(shares) <= 0.10, f"share of the other steps' samples inside each A_m: {shares}"


def test_junction_gaussians_are_shared_by_the_steps_they_join():
    """Property: for every switch of the HMM segmentation there is a Gaussian that belongs to both steps of the
    switch, centred within 3 % of the data span of the demonstration's position at the switch."""
    syn = synthetic("min_jerk", 2, 1, 3, 0)
    seg = segmented("min_jerk", 2, 1, 3, 0)
    span = float((syn.demos.positions[0].amax(0) - syn.demos.positions[0].amin(0)).norm())
    for a, b, t in zip(seg.step_sequence(0), seg.step_sequence(0)[1:], seg.switches(0)):
        both = (seg.space_weights[a] > 0) & (seg.space_weights[b] > 0)
        assert bool(both.any()), (a, b)
        dist = (seg.space_mean[both] - syn.demos.positions[0, t]).norm(dim=-1)
        assert float(dist.min()) <= 0.03 * span, (a, b, dist.tolist())


# ---------------------------------------------------------------------------------------------- 5. determinism
def test_same_seed_same_result_and_seeds_agree_on_an_easy_case():
    """Property: a fixed generator seed gives identical labels, states, pieces and attractors (fast settings); on an
    easy case (constant speed, 2-D, 4 demonstrations, 3 legs) three different seeds with the default settings give
    the same (true) number of steps."""
    syn = synthetic(*MUTATION_CASE)
    a = segment(syn.demos, generator=torch.Generator().manual_seed(7), **FAST)
    b = segment(syn.demos, generator=torch.Generator().manual_seed(7), **FAST)
    for la, lb, sa, sb, pa, pb in zip(a.labels, b.labels, a.states, b.states, a.pieces, b.pieces):
        assert torch.equal(la, lb) and torch.equal(sa, sb) and torch.equal(pa, pb)
    assert torch.equal(a.attractors, b.attractors) and torch.equal(a.sampler.trace, b.sampler.trace)
    counts = []
    for seed in (7, 8, 9):  # default settings: the ones the acceptance (same count over seeds) is about
        seg = segment(syn.demos, generator=torch.Generator().manual_seed(seed))
        counts.append([len(seg.step_sequence(i)) for i in range(seg.n_sequences)])
    assert counts == [[syn.n_steps] * syn.demos.n_demos] * 3, counts


# ---------------------------------------------------------------------------------------------- API contract
def test_table_one_attractors_are_mean_end_points():
    """Property (paper Table I): the attractor of a step is the mean of its pieces' last samples (the last step's is
    the task attractor); FixedSegmenter rounds fractional boundaries to samples."""
    g = torch.Generator().manual_seed(0)
    x = [torch.randn(8, 2, generator=g, dtype=F64) for _ in range(2)]
    demos = Demos.from_sequences(x)
    seg = _steps_from_bounds(demos, [[0, 3, 6, 8], [0, 2, 5, 8]], {})
    for m, (e1, e2) in enumerate([(2, 1), (5, 4)]):  # 0-based last samples (sequence 1, sequence 2)
        torch.testing.assert_close(seg.attractors[m], 0.5 * (x[0][e1] + x[1][e2]))
    torch.testing.assert_close(seg.attractors[2], demos.attractor)
    assert [lab.tolist() for lab in seg.labels] == [[0, 0, 0, 1, 1, 1, 2, 2], [0, 0, 1, 1, 1, 2, 2, 2]]
    fixed = FixedSegmenter([0.3, 0.7])(demos)  # 8 * 0.3 -> 2, 8 * 0.7 -> 6
    assert [p.tolist() for p in fixed.pieces] == [[[0, 0, 2], [1, 2, 6], [2, 6, 8]]] * 2
    assert fixed.routes == ((0, 1, 2),) and fixed.route_of.tolist() == [0, 0] and fixed.step_state.tolist() == [-1] * 3
    assert len(fixed.table()) == 3 and fixed.table()[1]["n_pieces"] == 2


def test_split_pieces_and_attractors():
    """Property: ``split`` returns one Demos per step whose pieces concatenate back to every demonstration
    (positions and velocities), with the step's attractor; ``end_at_attractor`` appends one resting sample at g_m
    one sampling interval later; mismatched demonstrations raise ShapeMismatchError."""
    syn = multi_step_demos(torch.Generator().manual_seed(1), n_demos=3, n_steps=3, samples_per_step=40)
    seg = FixedSegmenter([0.25, 0.6])(syn.demos)
    parts = seg.split(syn.demos)
    assert len(parts) == 3
    for m, p in enumerate(parts):
        torch.testing.assert_close(p.attractor, seg.attractors[m])
        torch.testing.assert_close(p.lengths, torch.stack([pc[m, 2] - pc[m, 1] for pc in seg.pieces]))
    for i, seq in enumerate(syn.demos.sequences()):
        torch.testing.assert_close(torch.cat([p.sequences()[i] for p in parts]), seq)
        torch.testing.assert_close(torch.cat([p.velocities[i, : int(p.lengths[i])] for p in parts]),
                                   syn.demos.velocities[i, : int(syn.demos.lengths[i])])  # fmt: skip
    rest = seg.split(syn.demos, end_at_attractor=True)
    for m, (p, r) in enumerate(zip(parts, rest)):
        torch.testing.assert_close(r.lengths, p.lengths + 1)
        for i in range(p.n_demos):
            L = int(p.lengths[i])
            torch.testing.assert_close(r.positions[i, :L], p.positions[i, :L])
            torch.testing.assert_close(r.positions[i, L], seg.attractors[m])
            assert float(r.velocities[i, L].abs().max()) == 0.0
            torch.testing.assert_close(r.times[i, L] - r.times[i, L - 1], p.times[i, L - 1] - p.times[i, L - 2])
    with pytest.raises(ShapeMismatchError):
        seg.split(syn.demos[[0, 1]])


def test_no_segmenter_single_step():
    """Property: NoSegmenter gives one step ending at the task attractor, no other region (-inf), one piece each."""
    syn = multi_step_demos(torch.Generator().manual_seed(2), n_demos=2, n_steps=2, samples_per_step=20)
    seg = NoSegmenter()(syn.demos)
    assert seg.n_steps == 1 and seg.routes == ((0,),)
    torch.testing.assert_close(seg.attractors[0], syn.demos.attractor)
    assert torch.isinf(seg.other_log_density(torch.zeros(4, 2, dtype=F64))).all()
    assert len(seg.split(syn.demos)) == 1 and all(seg.switches(i) == [] for i in range(2))


def test_least_squares_velocities_and_their_noise():
    """Property: ``scale_velocities`` is exact on a straight line at constant speed (ends included); on white
    position noise its empirical standard deviation matches ``velocity_noise`` inside the sequence (within 10 %),
    and ``velocity_noise`` is larger where the window is cut by an end."""
    from lfd_torch.segmentation.segmentation import scale_velocities, velocity_noise

    t = torch.arange(200, dtype=F64).unsqueeze(-1) * 0.01
    line = torch.tensor([1.0, -2.0], dtype=F64) + t * torch.tensor([0.5, 3.0], dtype=F64)
    torch.testing.assert_close(scale_velocities(line, 7, 0.01), torch.tensor([[0.5, 3.0]], dtype=F64).expand(200, 2))
    g = torch.Generator().manual_seed(0)
    noise = 0.01 * torch.randn(400, 200, 2, generator=g, dtype=F64)
    v = torch.stack([scale_velocities(e, 7, 0.01) for e in noise])
    sd = v.std(dim=(0, 2))
    ref = velocity_noise(0.01, 200, 7, 0.01)
    assert float((sd[20:-20] / ref[20:-20] - 1).abs().max()) < 0.1
    assert float((sd[:3] / ref[:3] - 1).abs().max()) < 0.1 and float(ref[0]) > 2 * float(ref[100])


def test_path_grid_skips_rests():
    """Property: the sampler's grid is equally spaced in path length: a long rest in the middle of a motion holds at
    most one grid point, the grid is increasing and has at most ceil(T / k) points."""
    from lfd_torch.segmentation.segmentation import path_grid, scale_velocities, velocity_noise

    go = torch.linspace(0, 1, 100, dtype=F64)
    x = torch.cat([go, torch.ones(200, dtype=F64), 1 + go]).unsqueeze(-1) * torch.tensor([1.0, 0.5], dtype=F64)
    x = x + 1e-4 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    k = 8
    v = scale_velocities(x, k, 0.01)
    grid = path_grid(v, velocity_noise(1e-4, x.shape[0], k, 0.01), k, 0.01)
    assert bool((grid[1:] > grid[:-1]).all()) and grid.numel() <= math.ceil(x.shape[0] / k)
    assert int(((grid >= 100 + k) & (grid < 300 - k)).sum()) <= 1


def test_runs_helper():
    """Property: ``runs`` returns the maximal runs (start, exclusive end, value) of a label sequence."""
    starts, ends, values = runs(torch.tensor([3, 3, 1, 1, 1, 3, 2]))
    assert starts.tolist() == [0, 2, 5, 6] and ends.tolist() == [2, 5, 6, 7] and values.tolist() == [3, 1, 3, 2]
    starts, ends, values = runs(torch.tensor([4]))
    assert starts.tolist() == [0] and ends.tolist() == [1] and values.tolist() == [4]


def test_save_load_round_trip_and_bad_files(tmp_path):
    """Property: save/load (schema 3) restores every field exactly (log densities and splits agree); a missing,
    foreign or wrong-schema file raises StoreError."""
    syn = multi_step_demos(torch.Generator().manual_seed(3), n_demos=2, n_steps=3, samples_per_step=40)
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(3), **FAST)
    back = Segmentation.load(seg.save(tmp_path / "seg.pt"))
    for name in ("labels", "pieces", "states"):
        assert all(torch.equal(u, v) for u, v in zip(getattr(back, name), getattr(seg, name)))
    for name in ("attractors", "route_of", "space_mean", "space_covariance", "space_weights", "step_state"):
        assert torch.equal(getattr(back, name), getattr(seg, name)), name
    assert back.routes == seg.routes
    x = torch.randn(10, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
    torch.testing.assert_close(back.log_density(x), seg.log_density(x))
    assert [p.n_demos for p in back.split(syn.demos)] == [p.n_demos for p in seg.split(syn.demos)]
    with pytest.raises(StoreError):
        Segmentation.load(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(StoreError):
        Segmentation.load(tmp_path / "junk.pt")
    for version in (1, 2):  # schema 2 stored normalised mixture weights, which read differently now
        old = seg.state_dict() | {"schema_version": version}
        torch.save(old, tmp_path / "old.pt")
        with pytest.raises(StoreError):
            Segmentation.load(tmp_path / "old.pt")
    incomplete = {k: v for k, v in seg.state_dict().items() if k != "pieces"}
    with pytest.raises(StoreError):
        Segmentation.from_state_dict(incomplete)


# ---------------------------------------------------------------------------------------------- bad input
def test_bad_input_typed_errors():
    """Property: invalid input raises the library's typed errors before any sampling."""
    g = torch.Generator().manual_seed(0)
    good = torch.randn(60, 2, generator=g, dtype=F64)
    with pytest.raises(TooFewSamplesError):
        segment([good, good[:7]], generator=g, min_length=5)  # 7 < 2 * 5
    bad = good.clone()
    bad[10, 0] = float("nan")
    with pytest.raises(NonFiniteError):
        segment([good, bad], generator=g)
    with pytest.raises(ShapeMismatchError):
        segment([good, torch.randn(60, 3, generator=g, dtype=F64)], generator=g)
    with pytest.raises(InvalidArgumentError):
        segment([good], generator=g, min_length=0)
    with pytest.raises(InvalidArgumentError):
        segment([good], generator=g, max_samples=4)
    with pytest.raises(InvalidArgumentError, match="tolerance_correlation"):  # needs run starts: D >= 2 grid points
        segment([torch.randn(1000, 2, generator=g, dtype=F64).cumsum(0)], generator=g, min_length=0.01, max_samples=8,
                dwell_cue=False, tolerance_correlation=None)
    with pytest.raises(InvalidArgumentError, match="stickiness"):
        segment([good], generator=g, stickiness=-1.0)
    with pytest.raises(InvalidArgumentError, match="not_a_parameter"):  # a typo in a Hydra config key
        BPGMHMMSegmenter(not_a_parameter=1)
    with pytest.raises(InvalidArgumentError):
        FixedSegmenter([0.5, 0.2])


def test_split_checks_it_is_given_the_segmented_demonstrations(tmp_path):
    """Equal lengths are not enough: split compares each demonstration's first and last sample with those of the
    segmented one, so the same demonstrations in another order are refused, while a float32 copy is accepted and
    a file saved before the end points were kept still splits."""
    from lfd_torch.segmentation.segmentation import Segmentation

    t = torch.linspace(0.0, 1.0, 40, dtype=F64)[:, None]
    demos = Demos.from_sequences([t * torch.tensor([1.0, 0.5], dtype=F64), t * torch.tensor([0.8, -0.3], dtype=F64)])
    seg = FixedSegmenter([0.5])(demos)
    assert seg.endpoints.shape == (2, 2, 2)
    with pytest.raises(ShapeMismatchError, match=r"demonstrations \[0, 1\]"):
        seg.split(demos[[1, 0]])
    assert [d.n_demos for d in seg.split(demos.to(dtype=torch.float32))] == [2, 2]
    back = Segmentation.load(seg.save(tmp_path / "seg.pt"))
    assert torch.equal(back.endpoints, seg.endpoints)
    state = seg.state_dict()
    del state["endpoints"]
    legacy = Segmentation.from_state_dict(state)
    assert legacy.endpoints is None and [d.n_demos for d in legacy.split(demos[[1, 0]])] == [2, 2]


def test_segmentation_api_edges_are_typed_errors():
    """A piece too short to be a demonstration of its own (split names the step and the user's demonstration, not
    the piece's index within the step), an index out of range, a list given to ``split``, a 1-D or mismatched plot:
    each is a typed error naming what is wrong, not a crash inside torch or matplotlib; float32 tensors stay
    float32."""
    from lfd_torch.errors import InvalidIndexError, ShapeMismatchError, TooFewSamplesError
    from lfd_torch.segmentation.plot import plot_segmentation

    line = torch.linspace(0.0, 1.0, 40, dtype=F64)[:, None] * torch.tensor([1.0, 0.5], dtype=F64)
    demos = Demos.from_sequences([line])
    with pytest.raises(TooFewSamplesError, match="step 0 .samples 0..1. has 2 samples"):  # the user's demo 0
        FixedSegmenter([0.04, 0.5])(demos).split(demos)
    assert FixedSegmenter([0.04, 0.5])(demos).split(demos, end_at_attractor=True)[0].lengths.tolist() == [3]
    seg = FixedSegmenter([0.5])(demos)
    assert seg.step_sequence(0) == [0, 1] and seg.switches(0) == [20]
    for bad in (1, -1, 0.0, True):
        with pytest.raises(InvalidIndexError, match="demonstration index"):
            seg.step_sequence(bad)
    with pytest.raises(InvalidArgumentError, match="Demos"):
        seg.split([line])
    with pytest.raises(ShapeMismatchError, match="segmented demonstrations"):
        plot_segmentation(seg, demos[[0, 0]])
    flat = Demos.from_sequences([line[:, :1]])
    with pytest.raises(ShapeMismatchError, match="1-D"):
        plot_segmentation(FixedSegmenter([0.5])(flat), flat)
    assert FixedSegmenter([0.5])([line.float()]).attractors.dtype == torch.float32


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("n_initial_features", 1000), ("n_initial_features", 0), ("n_initial_features", 2.5),
        ("n_chains", 1000), ("n_chains", True), ("n_iterations", 10**6), ("n_iterations", 0),
        ("max_samples", 5000), ("max_samples", 80.0), ("feature_mass", 1e6), ("feature_mass", float("nan")),
        ("stickiness", float("inf")), ("birth_window", 1.5), ("birth_prior_mix", 1.0), ("burn_in", 1.0),
        ("direction_noise", 0.0), ("robust_dof", -1.0), ("progress", 1), ("position_weight", 1.5),
        ("position_weight", float("nan")), ("position_weight", "1/D"), ("straight_weight", 1.0), ("straight_weight", -0.1),
        ("tolerance_correlation", 1.0), ("tolerance_correlation", float("nan")), ("position_mixture", 1),
    ],
)  # fmt: skip
def test_hyperparameters_that_scale_the_cost_are_bounded(name, value):
    """Property (issue 11): a hyperparameter out of its range raises InvalidArgumentError naming it and the
    accepted range, at once (before any sampling: the call with the 1000-feature setting used to run for minutes)."""
    import time

    g = torch.Generator().manual_seed(0)
    demos = multi_step_demos(g, n_demos=3, n_steps=3, samples_per_step=40, profile="constant").demos
    t0 = time.perf_counter()
    with pytest.raises(InvalidArgumentError, match=name) as info:
        segment(demos, generator=g, **{name: value})
    assert time.perf_counter() - t0 < 1.0
    assert "got" in str(info.value) and ("[" in str(info.value) or "(" in str(info.value) or "bool" in str(info.value))


def test_hyperparameter_bounds_accept_their_edges():
    """Property: the range ends themselves are accepted (the check does not reject valid settings)."""
    from lfd_torch.segmentation.sampler import HYPERPARAMETER_RANGES, BetaProcessHMMSampler

    for name, (kind, low, high, low_in, high_in) in HYPERPARAMETER_RANGES.items():
        for edge, inclusive in ((low, low_in), (high, high_in)):
            if inclusive:
                BetaProcessHMMSampler(**{name: kind(edge)})


def test_demonstrations_of_one_repeated_point_raise_a_typed_error():
    """Property (issue 11): a demonstration without motion has no direction to segment: InvalidDemoError naming
    the demonstration, alone or next to a moving one (it used to end in a raw LinAlgError from a Cholesky)."""
    from lfd_torch.errors import InvalidDemoError

    g = torch.Generator().manual_seed(0)
    still = torch.full((120, 2), 0.5, dtype=F64)
    moving = torch.cumsum(torch.randn(120, 2, generator=g, dtype=F64), 0)
    with pytest.raises(InvalidDemoError, match="demonstration 0: does not move"):
        segment([still, still, still], generator=g)
    with pytest.raises(InvalidDemoError, match="demonstration 1: does not move"):
        segment([moving, still], generator=g)


def test_malformed_arguments_raise_typed_errors_naming_them(tmp_path):
    """Property (issue 11): demos, generator, min_length, FixedSegmenter boundaries, the x of
    ``Segmentation.log_density`` and a foreign file given to ``Segmentation.load`` raise typed lfd_torch errors
    whose message names the argument (or the file), never a builtin error or a silent result."""
    from lfd_torch.errors import LfdError

    g = torch.Generator().manual_seed(0)
    demos = multi_step_demos(g, n_demos=2, n_steps=3, samples_per_step=40, profile="constant").demos
    calls = {
        "demos": [lambda: segment(None, generator=g), lambda: segment(3, generator=g), lambda: segment([], generator=g),
                  lambda: segment("abc", generator=g), lambda: segment([torch.zeros(5, 2, dtype=F64)], generator=g)],
        "generator": [lambda: segment(demos, generator=None), lambda: segment(demos, generator=0)],
        "min_length": [lambda: segment(demos, generator=g, min_length=1.5),
                       lambda: segment(demos, generator=g, min_length=float("nan"))],
        "boundaries": [lambda: FixedSegmenter([1.5]), lambda: FixedSegmenter(["a"]),
                       lambda: FixedSegmenter([0.6, 0.4])],
    }  # fmt: skip
    for name, fns in calls.items():
        for fn in fns:
            with pytest.raises(LfdError, match=name):
                fn()
    seg = FixedSegmenter([1 / 3, 2 / 3])(demos)
    x = demos.positions[0, :5]
    bad_x = [(x.tolist(), InvalidArgumentError), (x.numpy(), InvalidArgumentError), (None, InvalidArgumentError),
             (torch.tensor(1.0, dtype=F64), ShapeMismatchError), (x[:, :1], ShapeMismatchError),
             (x.to(torch.complex128), InvalidArgumentError), (x.long(), InvalidArgumentError),
             (x.clone().fill_(float("nan")), NonFiniteError), (x.clone().fill_(float("inf")), NonFiniteError)]
    for bad, err in bad_x:
        with pytest.raises(err, match="x"):
            seg.log_density(bad)
    assert seg.log_density(x).shape == (5, 3)  # the valid call still works
    foreign = tmp_path / "foreign.pt"
    torch.save({"schema_version": 1}, foreign)
    with pytest.raises(StoreError, match="foreign.pt"):
        Segmentation.load(foreign)


def test_one_dimensional_data_raise_a_typed_error():
    """Property: 1-D data (a direction field has only two directions) raise InvalidArgumentError naming d >= 2;
    the segmenters without an HMM accept them."""
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 1, 60, dtype=F64)
    seqs = [torch.cat([t, 1 + 0 * t, 1 - t]).unsqueeze(-1) + 0.01 * torch.randn(180, 1, generator=g, dtype=F64)]
    with pytest.raises(InvalidArgumentError, match="d >= 2"):
        segment(seqs, generator=g, n_iterations=2, n_chains=1)
    seg = FixedSegmenter([1 / 3, 2 / 3])(seqs)
    assert seg.n_steps == 3 and seg.dim == 1
    assert NoSegmenter()(seqs).n_steps == 1


# ---------------------------------------------------------------------------------------------- configs
def test_segmenter_equals_segment_with_the_same_hyperparameters():
    """Property: ``BPGMHMMSegmenter(**cfg)(demos, generator=g)`` equals ``segment(demos, generator=g, **cfg)``."""
    syn = synthetic(*MUTATION_CASE)
    cfg = dict(FAST, stickiness=20.0, min_length=0.05)
    a = BPGMHMMSegmenter(**cfg)(syn.demos, generator=torch.Generator().manual_seed(4))
    b = segment(syn.demos, generator=torch.Generator().manual_seed(4), **cfg)
    assert all(torch.equal(u, v) for u, v in zip(a.labels, b.labels)) and torch.equal(a.attractors, b.attractors)


def test_bp_gm_hmm_config_matches_segment_signature():
    """Property: the keys of conf/segmentation/bp_gm_hmm.yaml are ``segment``'s keyword arguments one for one (as the
    file says), with ``segment``'s defaults as values, and the instantiated partial runs."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="segmentation/bp_gm_hmm")
    node = cfg.segmentation
    keys = {k for k in node.keys() if not str(k).startswith("_")}
    valid = set(inspect.signature(segment).parameters) - {"demos", "generator"}
    assert keys == valid, f"not accepted: {sorted(keys - valid)}, missing: {sorted(valid - keys)}"
    defaults = {k: inspect.signature(segment).parameters[k].default for k in valid}
    assert {k: node[k] for k in keys} == defaults
    node.n_iterations = 4
    node.n_chains = 1
    syn = multi_step_demos(torch.Generator().manual_seed(6), n_demos=2, n_steps=3, samples_per_step=40)
    seg = instantiate(node)(syn.demos, generator=torch.Generator().manual_seed(6))
    assert isinstance(seg, Segmentation) and seg.n_sequences == 2


@pytest.mark.parametrize("option", ["fixed", "none"])
def test_ablation_configs_instantiate_and_run(option):
    """Property: the FixedSegmenter / NoSegmenter configs instantiate and give pieces that tile every demo."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name=f"segmentation/{option}")
    segmenter = instantiate(cfg.segmentation)
    syn = multi_step_demos(torch.Generator().manual_seed(6), n_demos=2, n_steps=3, samples_per_step=40)
    seg = segmenter(syn.demos, generator=torch.Generator().manual_seed(6))
    assert isinstance(seg, Segmentation)
    for i in range(2):
        assert int(seg.pieces[i][-1, 2]) == int(syn.demos.lengths[i]) and int(seg.pieces[i][0, 1]) == 0
    assert math.isfinite(float(seg.attractors.sum()))


# ---------------------------------------------------------------------------------------------- CUDA
@pytest.mark.cuda
@requires_cuda
def test_segment_on_cuda():
    """Property: on CUDA data with a CUDA generator the result lives on the device, gets the true steps of an easy
    case, and its densities and splits work there."""
    syn = multi_step_demos(torch.Generator().manual_seed(0), n_demos=3, n_steps=3, samples_per_step=80, profile="constant")
    demos = syn.demos.to(device="cuda")
    seg = segment(demos, generator=torch.Generator(device="cuda").manual_seed(0))
    ok, report = step_accuracy(seg, syn.switch_times, syn.demos.lengths)
    assert ok, report
    assert seg.attractors.device.type == "cuda" and seg.labels[0].device.type == "cuda"
    assert seg.pieces[0].device.type == "cuda" and seg.route_of.device.type == "cuda"
    assert seg.log_density(demos.positions).shape == (*demos.positions.shape[:2], seg.n_steps)
    parts = seg.split(demos, end_at_attractor=True)
    assert parts[-1].positions.device.type == "cuda"
    torch.testing.assert_close(parts[-1].attractor, demos.attractor)


def test_segment_lasa_refuses_publish_in_a_multirun(tmp_path):
    """experiments/segment_lasa.py: publish=true in a Hydra multirun would let every job overwrite the published
    table and figures, so the job fails before it segments anything (like experiments/lasa_benchmark.py)."""
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "experiments" / "segment_lasa.py"
    proc = subprocess.run(
        [sys.executable, str(script), "-m", "publish=true", f"hydra.sweep.dir={tmp_path / 'sweep'}"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode != 0
    assert "publish=true in a multirun" in proc.stderr + proc.stdout
    assert not (tmp_path / "results").exists()


def _run_on(path: torch.Tensor, min_duration: int = 3, **options) -> "sampler_module._Run":
    """A one-chain sampler state on one 2-D path (its grid points) for scoring labellings; ``options`` of the
    sampler."""
    v = torch.gradient(path, dim=0)[0] / 0.01
    cfg = sampler_module.BetaProcessHMMSampler(**{"extra_dof": 30.0, "n_chains": 1, **options})
    x, lengths = sampler_module._pad([path])
    vp, _ = sampler_module._pad([v])
    return sampler_module._Run(cfg, x, vp, lengths, torch.Generator().manual_seed(0), None, min_duration,
                               (1e-3, 1e-6))  # fmt: skip


@pytest.mark.parametrize("corner", [False, True])
def test_collapsed_evidence_prefers_one_state_per_leg(corner):
    """The collapsed score (fields, noise and transitions integrated out) prefers one state on a straight leg and
    two at a 90-degree corner: the evidence of the direction fields decides, not the number of states."""
    g = torch.Generator().manual_seed(3)
    t = torch.linspace(0.0, 1.0, 30, dtype=torch.float64)
    first = torch.stack([t, torch.zeros_like(t)], -1)
    second = torch.stack([1.0 + t[1:], torch.zeros_like(t[1:])], -1) if not corner else \
        torch.stack([torch.ones_like(t[1:]), t[1:]], -1)
    path = torch.cat([first, second]) + 1e-3 * torch.randn(59, 2, generator=g, dtype=torch.float64)
    run = _run_on(path)
    split = torch.cat([torch.zeros(30, dtype=torch.long), torch.ones(29, dtype=torch.long)]).view(1, 1, -1)
    one = torch.zeros_like(split)
    phases = torch.cat([torch.arange(30).clamp_max(2), torch.arange(29).clamp_max(2)]).view(1, 1, -1)
    scores = [float(run._collapsed_score(s, torch.ones(1, 1, k, dtype=torch.bool), ph, run.alpha, run.kappa,
                                         run.mass)) for s, k, ph in ((split, 2, phases), (one, 1, torch.arange(59).clamp_max(2).view(1, 1, -1)))]  # fmt: skip
    assert (scores[0] > scores[1]) == corner


def test_position_mixture_occupancy_is_the_chinese_restaurant_process_of_the_labels():
    """At tau = 1 the occupancy evidence of ``position_mixture`` (per state sum_i log Gamma(n_ik), plus the
    labelling-free -sum_i log Gamma(1 + n_i)) is log p(s) of a Chinese restaurant process with concentration 1,
    here the product of its sequential predictive probabilities (a naive loop over the samples)."""
    g = torch.Generator().manual_seed(2)
    n, K = 40, 4
    path = torch.cumsum(torch.randn(n, 2, generator=g, dtype=torch.float64), 0)
    run = _run_on(path, position_weight=1.0, position_mixture=True)
    labels = torch.randint(0, K - 1, (n,), generator=g)  # state K - 1 unused
    onehot = torch.nn.functional.one_hot(labels, K).to(torch.float64).unsqueeze(0)
    score = float(run._occupancy_terms(onehot).sum()) + run._occupancy_constant()
    ref, seen = 0.0, collections.Counter()
    for t, k in enumerate(labels.tolist()):
        ref += math.log((seen[k] if seen[k] else 1.0) / (t + 1.0))
        seen[k] += 1
    assert score == pytest.approx(ref, abs=1e-9)
    off = _run_on(path, position_weight=1.0, position_mixture=False)
    assert float(off._occupancy_terms(onehot).abs().sum()) == 0.0 and off._occupancy_constant() == 0.0


@pytest.mark.parametrize("n", [30, 120])
def test_position_mixture_charges_a_cut_leg_its_occupancy_and_keeps_distant_pieces_apart(n):
    """The tempered position evidence (module docstring, "Position") of a leg cut into two states, against one
    state: as a mixture over space (``position_mixture``) the occupancies charge the cut about tau n log 2 nats
    more than the Gaussians alone do, so it gains nothing on a leg of a path (L-shaped, the leg half of it), while
    two pieces of one state far apart still gain far more by their own states than the occupancies cost."""
    tau = 1.0 / 3.0
    t = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
    noise = 1e-2 * torch.randn(2 * n, 2, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    path = torch.cat([torch.stack([t, 0.0 * t], -1), torch.stack([1.0 + 0.0 * t, t], -1)]) + noise
    apart = path.clone()
    apart[n // 2: n, 0] += 5.0  # the leg's second half moved away
    one = torch.zeros(1, 2 * n, 3, dtype=torch.float64)
    one[0, :n, 0] = one[0, n:, 2] = 1.0
    two = one.clone()
    two[0, n // 2: n] = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)

    def gain(p, mixture):
        run = _run_on(p, position_weight=tau, position_mixture=mixture)
        return [float(niw_log_marginal_likelihood(run.pos_prior, *run._position_statistics(o)).sum()
                      + run._occupancy_terms(o).sum()) for o in (two, one)]

    with_mix, without = (a - b for a, b in (gain(path, True), gain(path, False)))
    charge = without - with_mix
    # log Gamma(x) + log Gamma(x) - log Gamma(2 x) = -2 x log 2 + O(log x), x = tau n / 2
    assert charge == pytest.approx(tau * n * math.log(2.0), abs=0.5 * math.log(tau * n) + 1.5)
    assert with_mix < 0.0
    far = gain(apart, True)
    assert far[0] - far[1] > 10.0


def test_collapsed_selection_returns_the_best_collapsed_score_of_the_same_chains():
    """selection does not change the chains (no extra randomness), only which of their sweeps is returned: the
    collapsed choice has the highest collapsed score among them, the joint choice the highest joint one."""
    syn = synthetic(*MUTATION_CASE)
    joint = segment(syn.demos, generator=torch.Generator().manual_seed(0), selection="joint")
    coll = segment(syn.demos, generator=torch.Generator().manual_seed(0), selection="collapsed")
    assert coll.info["collapsed_log_prob"] >= joint.info["collapsed_log_prob"]
    assert joint.info["log_prob"] >= coll.info["log_prob"]
    with pytest.raises(InvalidArgumentError, match="selection"):
        segment(syn.demos, generator=torch.Generator().manual_seed(0), selection="best")


def test_modal_selection_returns_a_sample_with_the_posterior_modal_step_counts(monkeypatch):
    """selection="modal": per sequence, the number of runs most frequent over every kept sweep of every chain
    (counted here by a naive loop over the recorded state sequences), and among the samples with those counts
    the highest joint log probability; the chains are the same as with the joint choice."""
    syn = synthetic(*MUTATION_CASE)
    record: list[list[list[int]]] = []
    original = sampler_module._Run._joint_log_prob

    def recording(self):
        out = original(self)
        counts = []
        for c in range(self.C):
            row = []
            for i in range(self.N):
                states = self.s[c, i, : int(self.lengths[i])].tolist()
                row.append(1 + sum(a != b for a, b in zip(states, states[1:])))
            counts.append(row)
        record.append(counts)
        return out

    monkeypatch.setattr(sampler_module._Run, "_joint_log_prob", recording)
    modal = segment(syn.demos, generator=torch.Generator().manual_seed(0), selection="modal")
    kept = record[len(record) // 2 :]  # burn_in 0.5 of 40 sweeps
    assert len(record) == 40
    expected = []
    for i in range(syn.demos.n_demos):
        tally = collections.Counter(row[i] for sweep in kept for row in sweep)
        top = max(tally.values())
        expected.append(min(n for n, k in tally.items() if k == top))
    got = [len(runs) for runs in modal.info["coarse_runs"]]
    assert got == expected
    record.clear()
    joint = segment(syn.demos, generator=torch.Generator().manual_seed(0), selection="joint")
    assert joint.info["log_prob"] >= modal.info["log_prob"]
    assert math.isfinite(modal.info["collapsed_log_prob"])


def test_duration_phases_count_samples_since_the_run_began_capped_at_d_minus_one():
    """duration_phases against a naive loop over a batch of random label sequences."""
    gen = torch.Generator().manual_seed(3)
    s = torch.randint(0, 3, (4, 5, 40), generator=gen)
    s = torch.repeat_interleave(s, 2, dim=-1)  # runs of 2 and more
    for D in (1, 3, 6):
        got = sampler_module.duration_phases(s, D)
        for idx in torch.cartesian_prod(torch.arange(4), torch.arange(5)).tolist():
            row, c, want = s[tuple(idx)].tolist(), 0, []
            for t in range(len(row)):
                c = 0 if t == 0 or row[t] != row[t - 1] else c + 1
                want.append(min(c, D - 1))
            assert got[tuple(idx)].tolist() == want


@pytest.mark.parametrize(("position_weight", "straight_weight", "dwell_cue"),
                         [(0.0, 0.0, False), (None, 0.0, False), (None, 0.5, False), (None, 0.5, True)],
                         ids=["directions", "with_position", "with_straight_states", "with_dwell"])
def test_map_selection_is_a_local_mode_of_the_collapsed_posterior_under_merges(monkeypatch, position_weight,
                                                                               straight_weight, dwell_cue):
    """selection="map": no merge of two states of the returned sample, no reassignment of one state's runs in
    one sequence and no split of one state (its runs cut in halves, found here in a loop over runs, then the
    model's relabelling) raises its collapsed score (every candidate scored one at a time here), the reported
    score is that of the returned labelling, and it is at least that of the best sampled one (selection="collapsed",
    the same chains); with and without the position term, and with the spike-and-slab (straight or affine) field
    prior, and with the dwell term."""
    syn = synthetic(*MUTATION_CASE)
    runs = capture_runs(monkeypatch)
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(0), selection="map",
                  position_weight=position_weight, straight_weight=straight_weight, dwell_cue=dwell_cue)
    run, res = runs[-1], seg.sampler
    best = segment(syn.demos, generator=torch.Generator().manual_seed(0), selection="collapsed",
                   position_weight=position_weight, straight_weight=straight_weight, dwell_cue=dwell_cue)
    assert best.info["collapsed_log_prob"] <= seg.info["collapsed_log_prob"] + 1e-9
    assert math.isnan(seg.info["log_prob"])
    hyper = [torch.tensor([res.hyperparameters[k]], dtype=run.dtype)
             for k in ("transition_concentration", "stickiness", "feature_mass")]

    def score(s, F):
        return float(run._collapsed_score(s[None], F[None], sampler_module.duration_phases(s[None], run.D), *hyper)[0])

    s, F = res.states, res.features
    here = score(s, F)
    assert here == pytest.approx(seg.info["collapsed_log_prob"], abs=1e-6)
    K = F.shape[1]
    assert K >= 2
    for j in range(K):
        for k in range(j + 1, K):
            s2 = s.clone()
            s2[s == k] = j
            s2[s2 > k] -= 1
            F2 = F.clone()
            F2[:, j] |= F[:, k]
            F2 = torch.cat([F2[:, :k], F2[:, k + 1 :]], 1)
            assert score(s2, F2) <= here + 1e-9, (j, k)
    # nor does giving the runs of one state of one sequence to another state, or to a new one
    for i in range(run.N):
        n_i = int(run.lengths[i])
        for k in sorted(set(s[i, :n_i].tolist())):
            for j in range(K + 1):
                if j == k:
                    continue
                s2 = s.clone()
                s2[i][s[i] == k] = j
                F2 = torch.cat([F, torch.zeros(run.N, 1, dtype=torch.bool)], 1)
                F2[i, k], F2[i, j] = False, True
                assert score(s2, F2) <= here + 1e-9, (i, k, j)
    # nor does a split: the second half of every run of state k becomes a new state, then the Viterbi relabelling
    for k in range(K):
        s2 = s.clone()
        for i in range(run.N):
            n_i = int(run.lengths[i])
            t = 0
            while t < n_i:
                end = t
                while end + 1 < n_i and int(s[i, end + 1]) == int(s[i, t]):
                    end += 1
                if int(s[i, t]) == k:
                    s2[i, (t + end + 1) // 2 : end + 1] = K
                    if end == n_i - 1:
                        s2[i, n_i:] = K  # padding repeats the last valid label
                t = end + 1
        F2 = torch.cat([F, F[:, k : k + 1]], 1)
        s3, F3 = run._viterbi_relabel(s2, F2, float(hyper[0]), float(hyper[1]))
        assert score(s3, F3) <= here + 1e-9, k
    # nor does moving one switch by up to D grid points (both runs kept at least D long), or removing one run and
    # placing the switch between its neighbours within D of it: every candidate built here with plain loops
    D = run.D
    n_shift = 0
    for i in range(run.N):
        n_i = int(run.lengths[i])
        row = s[i, :n_i].tolist()
        bounds = [0] + [t for t in range(1, n_i) if row[t] != row[t - 1]] + [n_i]
        R = len(bounds) - 1
        spans = [(bounds[r], bounds[r + 2], row[bounds[r]], row[bounds[r + 1]], bounds[r + 1], bounds[r + 1])
                 for r in range(R - 1)]
        spans += [(bounds[r - 1], bounds[r + 2], row[bounds[r - 1]], row[bounds[r + 1]], bounds[r], bounds[r + 1])
                  for r in range(1, R - 1)]
        for lo, hi, a, b, first, last in spans:
            for c in range(max(lo + D, first - D), min(hi - D, last + D) + 1):
                s2 = s.clone()
                s2[i, lo:c], s2[i, c:hi] = a, b
                if hi == n_i:
                    s2[i, n_i:] = b
                if torch.equal(s2, s):
                    continue
                F2 = F.clone()
                for k in range(K):
                    F2[i, k] = F[i, k] and bool((s2[i, :n_i] == k).any())
                s3, F3 = sampler_module._compact_columns(s2, F2)
                sc = score(s3, F3)
                assert score(s2, F2) == pytest.approx(sc, abs=1e-8)  # a column nobody owns scores as absent
                assert sc <= here + 1e-9, (i, lo, hi, c)
                n_shift += 1
    assert n_shift > 0
    # the fields returned with it are fitted to its labelling: each predicts the directions of its own samples
    assert res.field.shape[0] == K and torch.isfinite(res.noise).all()
    o = run.obs
    for k in range(K):
        own = (s == k) & run.valid
        if own.any():
            pred = torch.einsum("ij,nj->ni", res.field[k], o.z[own])
            cos = torch.nn.functional.cosine_similarity(pred, o.u[own], dim=-1)
            assert float(cos.median()) > 0.9, k


@pytest.mark.parametrize(("position_weight", "straight_weight", "dwell_cue", "tolerance", "demo_offset"),
                         [(0.0, 0.0, False, None, 0.0), (None, 0.0, False, None, 0.0), (None, 0.5, False, None, 0.0),
                          (None, 0.5, True, None, 0.0), (None, 0.5, True, (0.9, 0.1, 0.02), 0.0),
                          (None, 0.5, True, (0.9, 0.1, 0.02), 16.0)],
                         ids=["directions", "with_position", "with_straight_states", "with_dwell",
                              "with_correlated_tolerance", "with_demo_offsets"])
def test_map_search_batched_scores_equal_the_full_score_one_candidate_at_a_time(monkeypatch, position_weight,
                                                                                straight_weight, dwell_cue, tolerance,
                                                                                demo_offset):
    """The mode search's shortcuts (``_Run._climb_to_mode``) against the plain computation: the reassignment
    and shift scores updated from the current score by the terms a move touches equal ``_collapsed_score`` of every
    candidate, and the batched Viterbi relabelling of several labellings (the look-ahead and split candidates)
    equals relabelling them one at a time; on the returned labelling and on each of its splits (more states,
    other runs). With a correlated tolerance (rho, sigma) too, where a sample's term depends on whether it starts
    a run, and with the demonstrations' own offsets (per-sequence statistics)."""
    syn = synthetic(*MUTATION_CASE)
    runs = capture_runs(monkeypatch)
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(0), **DIRECTIONS, selection="map",
                  position_weight=position_weight, straight_weight=straight_weight, dwell_cue=dwell_cue,
                  tolerance_correlation=0.0 if tolerance is None else None, demo_offset=demo_offset)
    run, res = runs[-1], seg.sampler
    if tolerance is not None:
        run._set_tolerance(*tolerance)
    hyper = [torch.tensor([res.hyperparameters[k]], dtype=run.dtype)
             for k in ("transition_concentration", "stickiness", "feature_mass")]

    def score(s, F):
        return run._collapsed_score(s, F, sampler_module.duration_phases(s, run.D), *(h.expand(s.shape[0])
                                                                                     for h in hyper))

    s, F = res.states, res.features
    splits = run._splits(s, F)
    assert len(splits) >= 2
    batch = run._viterbi_relabel_batch(torch.stack([c[0] for c in splits]), torch.stack([c[1] for c in splits]),
                                       float(hyper[0]), float(hyper[1]))
    labellings = [(s, F)]
    for (s2, F2), s_b, F_b in zip(splits, *batch):
        s1, F1 = run._viterbi_relabel(s2, F2, float(hyper[0]), float(hyper[1]))
        assert torch.equal(s_b, s1) and torch.equal(F_b, F1)
        labellings.append(sampler_module._compact_columns(s2, F2))
    for s_, F_ in labellings:
        cand = run._reassignments(s_, F_)
        fast = run._reassignment_scores(s_, F_, *cand, score(s_[None], F_[None])[0], hyper)
        full = score(cand[0], cand[1])
        assert torch.allclose(fast, full, rtol=0, atol=1e-8), float((fast - full).abs().max())
        shifted = run._shifts(s_, F_)  # the shift move's scores, updated by the terms it touches
        fast = run._shift_scores(s_, F_, *shifted[:4], score(s_[None], F_[None])[0], hyper)
        full = score(shifted[0], shifted[1])
        assert torch.allclose(fast, full, rtol=0, atol=1e-8), float((fast - full).abs().max())


@pytest.mark.parametrize("block_emission", [False, True], ids=["directions", "blocks"])
def test_shift_moves_with_disjoint_regions_compose(monkeypatch, block_emission):
    """The shift step moves every improving switch whose region is disjoint from better ones at once
    (``_Run._disjoint_shifts``): each candidate of ``_Run._shifts`` differs from the current labelling only inside
    its region [lo, hi), so candidates of one sequence with disjoint regions compose, and the composition keeps every
    run at least D grid points long (the semi-Markov minimum), on the returned labelling and on each of its splits.
    The picks are best first and pairwise disjoint within a sequence, and a candidate overlapping a better pick is
    left out."""
    syn = synthetic(*MUTATION_CASE)
    runs = capture_runs(monkeypatch)
    options = dict(block_emission=True, position_weight=None, position_mixture=True) if block_emission else {}
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(0), selection="map", **options)
    run, res = runs[-1], seg.sampler
    s0, F0 = res.states, res.features
    labellings = [(s0, F0)] + [sampler_module._compact_columns(*c) for c in run._splits(s0, F0)]
    gen = torch.Generator().manual_seed(1)
    for s, F in labellings:
        Fp = torch.nn.functional.pad(F, (0, 1)) if block_emission else F
        cand_s, _, seq, _, region = run._shifts(s, Fp)
        t = torch.arange(run.T)
        inside = (t >= region[:, :1]) & (t < region[:, 1:])  # (P, T)
        rows = cand_s[torch.arange(seq.numel()), seq]
        assert not ((rows != s[seq]) & ~inside & run.valid[seq]).any()  # changes stay inside the region
        sc = torch.rand(seq.numel(), generator=gen, dtype=torch.float64)
        picks = run._disjoint_shifts(sc, seq, region, torch.tensor(0.25, dtype=torch.float64))
        assert picks and all(float(sc[a]) >= float(sc[b]) for a, b in zip(picks, picks[1:]))
        composed = s.clone()
        for i in range(run.N):
            mine = [b for b in picks if int(seq[b]) == i]
            for a in mine:
                for b in mine:
                    if a != b:
                        assert int(region[a, 1]) <= int(region[b, 0]) or int(region[b, 1]) <= int(region[a, 0])
            for b in mine:
                lo, hi = region[b].tolist()
                composed[i, lo:hi] = cand_s[b, i, lo:hi]
        left_out = [b for b in torch.nonzero(sc > 0.25).view(-1).tolist() if b not in picks]
        for b in left_out:  # each overlaps a better pick of its sequence
            assert any(int(seq[a]) == int(seq[b]) and float(sc[a]) > float(sc[b])
                       and int(region[a, 0]) < int(region[b, 1]) and int(region[b, 0]) < int(region[a, 1])
                       for a in picks)
        for i, rr in enumerate(sampler_module._runs(composed, run.lengths)):
            assert all(e - a >= run.D for a, e, _ in rr), (i, rr)


@pytest.mark.parametrize("tolerance", [None, (0.9, 0.1, 0.02)], ids=["white", "correlated_tolerance"])
def test_student_t_profile_scales_equal_a_loop_over_samples(monkeypatch, tolerance):
    """``_Run._profile_scales`` (every sample's squared Mahalanobis residual as one GEMM of its outer product
    [u_t, z_t][u_t, z_t]^T against each state's quadratic form) against a loop: per sample, the residual under
    its own state's posterior-mean field, q_t = w_t r_t^T E[Psi]^-1 r_t, lambda_t = (nu + d - 2) / (nu + q_t);
    0-weight padding gives nu + d - 2 over nu. On the returned labelling and on one of its splits; with a
    correlated tolerance each sample is seen in the view of its age in its run."""
    from lfd_torch.segmentation.field import field_mixture_posterior_mean

    syn = synthetic(*MUTATION_CASE)
    runs = capture_runs(monkeypatch)
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(0), selection="map")
    run, res = runs[-1], seg.sampler
    if tolerance is not None:
        run._set_tolerance(*tolerance)
    nu, d = run.cfg.robust_dof, run.d
    labellings = [res.states[None], run._splits(res.states, res.features)[0][0][None]]
    for s in labellings:
        K = int(s.max()) + 1
        onehot = (torch.nn.functional.one_hot(s, K).to(run.dtype) * run.valid.unsqueeze(-1)).reshape(1, -1, K)
        age, w, _ = run._score_view(s)
        got = run._profile_scales(age, w, onehot)[0]
        mean, psi = field_mixture_posterior_mean(run.score_prior, *run._stats(age, w, onehot),
                                                 run.cfg.straight_weight)
        z, u = run._viewed(age)
        labels, valid = s.reshape(-1), run.valid.reshape(-1)
        for t in range(labels.numel()):
            q = 0.0
            if valid[t]:
                k = int(labels[t])
                r = u[0, t] - mean[0, k] @ z[0, t]
                q = float(w.expand(1, -1)[0, t] * (r @ torch.linalg.solve(psi[0, k], r)))
            assert float(got[t]) == pytest.approx((nu + d - 2.0) / (nu + q), rel=1e-10, abs=1e-12), t


def test_map_search_shift_move_removes_a_run_its_fields_held_in_place(monkeypatch):
    """The shift move of the map search (``_Run._shifts``: remove a run and place the switch between its neighbours
    anywhere in the three runs), on the case that motivated it (benchmark family scoop_const_3d, one
    demonstration, data case 0, sampler seed 0): without the move the search stops at 3 runs, with it it returns
    2 runs whose collapsed score, under the same hyperparameters, is above the 3-run labelling's; so the move
    finds a better mode of the same posterior (the model decides, not the move)."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "experiments"))
    from bench_segmentation import data_seed

    from lfd_torch.segmentation.synthetic import FAMILIES

    syn = FAMILIES["scoop_const_3d"](torch.Generator().manual_seed(data_seed("scoop_const_3d", 0)), 1)
    captured = capture_runs(monkeypatch)
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(0), **DIRECTIONS)
    run, res = captured[-1], seg.sampler
    monkeypatch.setattr(sampler_module._Run, "_shifts", lambda self, s, F: None)
    without = segment(syn.demos, generator=torch.Generator().manual_seed(0), **DIRECTIONS)
    assert len(seg.switches(0)) == 1 and len(without.switches(0)) == 2, (seg.switches(0), without.switches(0))
    gap = (collapsed_score(run, res, res.states, res.features)
           - collapsed_score(run, res, without.sampler.states, without.sampler.features))
    assert gap > 1.0, gap


def test_map_search_polished_split_reaches_the_mode_the_split_alone_misses(monkeypatch):
    """The polished split of the map search (``_Run._climb_to_mode``: when no split raises the score, the best
    relabelled split, its switches moved by shift moves while they raise its score, kept when it ends above the
    current labelling), on a case of the kind that motivated it (LASA Multi_Models_1, all 7 demonstrations,
    ``tolerance_correlation=None``, sampler seed 2; seed 0 before the relabelling was iterated first). Without it
    the search returns route {0-2} in 4 steps; the ascent with it, from that labelling under the same
    hyperparameters and tolerance, reaches 5 steps on every demonstration of the route and a higher collapsed
    score: a better mode of the same posterior."""
    from lfd_torch.data import load_lasa

    steps = sampler_module._POLISH_STEPS
    monkeypatch.setattr(sampler_module, "_POLISH_STEPS", 0)
    runs = capture_runs(monkeypatch)
    seg = segment(load_lasa("Multi_Models_1"), generator=torch.Generator().manual_seed(2), **DIRECTIONS,
                  tolerance_correlation=None)
    run, res = runs[-1], seg.sampler

    def runs_of(states):
        return [int((states[i, 1 : int(run.lengths[i])] != states[i, : int(run.lengths[i]) - 1]).sum()) + 1
                for i in range(run.N)]

    before = runs_of(res.states)
    assert before[:3] == [4, 4, 4], before
    monkeypatch.setattr(sampler_module, "_POLISH_STEPS", steps)
    snap = {"states": res.states, "features": res.features, "hyper": res.hyperparameters}
    after = run._climb_to_mode(snap, shifts=True)
    assert runs_of(after["states"])[:3] == [5, 5, 5], runs_of(after["states"])
    assert runs_of(after["states"])[3:] == before[3:]
    assert after["collapsed"] > seg.info["collapsed_log_prob"] + 1.0, (after["collapsed"],
                                                                        seg.info["collapsed_log_prob"])


def test_map_search_skips_only_moves_known_to_find_nothing(monkeypatch):
    """Two evaluations the map search skips (``_Run._climb_to_mode``) are savings, not changes: the last ascent
    starts from the best chain's mode of the ascent without shifts (``settled``), so its first round begins at the
    shift step; from that mode, the ascent that tries every move in its first round reaches the same labelling and
    score. And no ascent tries a shift step again at the labelling where the last one found nothing (two shift
    steps in a row at one labelling, both finding nothing: on benchmark family scoop_const_3d, one demonstration,
    case 0, sampler seed 0, the search before the change did so once)."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "experiments"))
    from bench_segmentation import case_data

    runs = capture_runs(monkeypatch)
    climbs, steps = [], []
    climb, shift_step = sampler_module._Run._climb_to_mode, sampler_module._Run._shift_step

    def recorded_climb(self, snap, shifts=True, settled=False):
        out = climb(self, snap, shifts, settled)
        climbs.append((snap, shifts, settled, out))
        return out

    def recorded_step(self, s, F, *args):
        out = shift_step(self, s, F, *args)
        steps.append((s.clone(), F.clone(), out is None))
        return out

    monkeypatch.setattr(sampler_module._Run, "_climb_to_mode", recorded_climb)
    monkeypatch.setattr(sampler_module._Run, "_shift_step", recorded_step)
    seg = segment(case_data("scoop_const_3d", 0, 1).demos, generator=torch.Generator().manual_seed(0))
    last = [c for c in climbs if c[1]]
    assert len(last) == 1 and last[0][2], [(c[1], c[2]) for c in climbs]
    start, _, _, kept = last[0]
    assert torch.equal(kept["states"], seg.sampler.states)
    assert not any(torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]) and a[2] and b[2]
                   for a, b in zip(steps, steps[1:]))
    full = climb(runs[-1], start, True, False)  # every move tried in the first round
    assert torch.equal(full["states"], kept["states"]) and torch.equal(full["features"], kept["features"])
    assert full["collapsed"] == kept["collapsed"]


def test_map_search_scores_merges_and_reassignments_only_where_the_relabelling_has_stopped(monkeypatch):
    """Order of the map search's moves (``_Run._climb_to_mode``): a round ends at the first move kept, so the costly
    merge and reassignment candidates are scored only on a labelling whose Viterbi relabelling does not raise the
    collapsed score. Checked on every such scoring of a segmentation of LASA Multi_Models_2 (all 7 demonstrations,
    all chains' ascents and the last one), where the relabelling is kept several rounds in a row (trying every move
    in every round, the order before e353bed, scores reassignments 4 times on a labelling the relabelling raises by
    up to 0.9 nats); and the result is a local mode: neither the relabelling nor any reassignment raises it."""
    from lfd_torch.data import load_lasa

    runs = capture_runs(monkeypatch)
    checked = []
    original = sampler_module._Run._reassignment_scores

    def score_of(run, s, F, hyper):
        return run._collapsed_score(s[None], F[None], sampler_module.duration_phases(s[None], run.D), *hyper)[0]

    def relabelling_gain(run, s, F, score, hyper):
        s2, F2 = run._viterbi_relabel(s, F, float(hyper[0]), float(hyper[1]))
        if torch.equal(s2, s) and torch.equal(F2, F):
            return 0.0
        return float(score_of(run, s2, F2, hyper) - score)

    def checked_scores(self, s, F, cand_s, cand_f, i, k, j, score, hyper):
        checked.append(relabelling_gain(self, s, F, score, hyper))
        return original(self, s, F, cand_s, cand_f, i, k, j, score, hyper)

    monkeypatch.setattr(sampler_module._Run, "_reassignment_scores", checked_scores)
    seg = segment(load_lasa("Multi_Models_2"), generator=torch.Generator().manual_seed(0))
    assert len(checked) >= 5, len(checked)  # every ascent scores reassignments at least in its last round
    assert max(checked) <= 1e-9, checked
    run, res = runs[-1], seg.sampler
    hyper = [torch.tensor([res.hyperparameters[k]], dtype=run.dtype)
             for k in ("transition_concentration", "stickiness", "feature_mass")]
    score = score_of(run, res.states, res.features, hyper)
    assert relabelling_gain(run, res.states, res.features, score, hyper) <= 1e-9
    cand = run._reassignments(res.states, res.features)
    assert float(original(run, res.states, res.features, *cand, score, hyper).max()) <= float(score) + 1e-9


def test_map_search_settled_lookahead_merge_reaches_the_mode_one_relabelling_misses(monkeypatch):
    """The settled look-ahead of the map search (``_Run._settle``: in the chains' ascents, when no merge raises the
    score, alone or followed by one relabelling, the best of those relabelled on while that raises its score), on the
    case that motivated it (LASA Sshape, all 7 demonstrations, sampler seed 0). Without it (``_SETTLE_STEPS = 0``)
    the search returns 6 steps per demonstration; with it 5, the count of seeds 1-9, at a collapsed score more
    than 1 nat higher under the returned hyperparameters: a better mode of the same posterior."""
    from lfd_torch.data import load_lasa

    demos = load_lasa("Sshape")
    runs = capture_runs(monkeypatch)
    seg = segment(demos, generator=torch.Generator().manual_seed(0), **DIRECTIONS)
    run, res = runs[-1], seg.sampler
    monkeypatch.setattr(sampler_module, "_SETTLE_STEPS", 0)
    without = segment(demos, generator=torch.Generator().manual_seed(0), **DIRECTIONS)
    assert [len(seg.step_sequence(i)) for i in range(7)] == [5] * 7
    assert [len(without.step_sequence(i)) for i in range(7)] == [6] * 7
    gap = (collapsed_score(run, res, res.states, res.features)
           - collapsed_score(run, res, without.sampler.states, without.sampler.features))
    assert gap > 1.0, gap


def test_learned_tolerance_finds_the_mild_corner_the_white_tolerance_merges(monkeypatch):
    """Property (issue 7, "Correlated tolerance" of the sampler docstring): on the benchmark case where the white
    default merges a 38-degree constant-speed corner (straight_const_3d, one demonstration, data case 8: 4 steps of
    5), learning the tolerance with the labelling (``tolerance_correlation=None``) returns the 4 steps, every switch
    within 3 % of the length; the labelling is a mode in the tolerance too: no setting of the grid scores it higher,
    and under the chosen setting it scores above the white default's labelling."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "experiments"))
    from bench_segmentation import data_seed

    from lfd_torch.segmentation.synthetic import FAMILIES

    syn = FAMILIES["straight_const_3d"](torch.Generator().manual_seed(data_seed("straight_const_3d", 8)), 1)
    white = segment(syn.demos, generator=torch.Generator().manual_seed(8), **DIRECTIONS)
    captured = capture_runs(monkeypatch)
    learned = segment(syn.demos, generator=torch.Generator().manual_seed(8), **DIRECTIONS, tolerance_correlation=None)
    run, res = captured[-1], learned.sampler
    true = syn.switch_times[0].tolist()
    n = int(syn.demos.lengths[0])
    assert len(white.switches(0)) == len(true) - 1
    found = learned.switches(0)
    assert len(found) == len(true) and all(abs(a - b) <= 0.03 * n for a, b in zip(found, true)), (found, true)
    hyper = [torch.tensor([res.hyperparameters[k]], dtype=run.dtype)
             for k in ("transition_concentration", "stickiness", "feature_mass")]

    def score(r):
        s, F = r.states[None], r.features[None]
        return float(run._collapsed_score(s, F, sampler_module.duration_phases(s, run.D), *hyper)[0])

    chosen = (res.hyperparameters["tolerance_correlation"], res.hyperparameters["tolerance_scale"],
              res.hyperparameters["tolerance_floor"])
    grid = []
    for tol in sampler_module.TOLERANCES:
        run._set_tolerance(*tol)
        grid.append(score(res))
    run._set_tolerance(*chosen)
    best = score(res)
    assert max(grid) <= best + 1e-6
    assert best > score(white.sampler)


def test_straight_states_cut_single_demonstrations_of_straight_legs(monkeypatch):
    """Property (issue 7, "Straight states" of the sampler docstring): a single demonstration of straight legs met
    at speed (benchmark family straight_const_2d, cases 0 and 5, where the affine-only mode merges legs: 3 and 4
    steps found of 5) gets every step and every switch within 3 % of its length with the spike-and-slab prior
    (map, position term, straight_weight=0.5); the mutant with affine fields only (straight_weight=0) must merge
    on both cases, so the check is the prior, not the case."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "experiments"))
    from bench_segmentation import data_seed

    from lfd_torch.segmentation.synthetic import FAMILIES

    def found_all(seed, straight_weight):
        syn = FAMILIES["straight_const_2d"](torch.Generator().manual_seed(data_seed("straight_const_2d", seed)), 1)
        seg = segment(syn.demos, generator=torch.Generator().manual_seed(seed), **DIRECTIONS, selection="map",
                      position_weight=None, straight_weight=straight_weight, dwell_cue=False)  # fmt: skip
        found = seg.pieces[0][1:, 1].to(torch.float64)
        true = syn.switch_times[0].to(torch.float64)
        tol = 0.03 * int(seg.labels[0].shape[0])
        return len(found) == len(true) and bool(((found - true).abs() <= tol).all()), found.tolist(), true.tolist()

    with_straight = [found_all(seed, 0.5) for seed in (0, 5)]
    assert all(ok for ok, *_ in with_straight), with_straight
    affine_only = [found_all(seed, 0.0) for seed in (0, 5)]
    assert not any(ok for ok, *_ in affine_only), affine_only


def test_refine_switch_on_grid_mixes_the_grid_posterior_with_the_change_point_posterior_within_each_interval():
    """_refine_switch_on_grid against a plain loop: the grid position j of the second run (j0 .. j0 + 3) has
    probability softmax(grid scores), the switch tau lies in (grid[j - 1], grid[j]] with probability within that
    interval proportional to _refine_switch's exp(sum_{lo <= t < tau} (ll_a - ll_b) / stride + log_prior(tau)); the
    switch is the median of the mixture, a sample's doubt the probability that it lies on the other side. The
    direction evidence alone (a strong pull to tau = 30) cannot move the switch out of the intervals the grid scores
    favour; with ``first`` clipping the first interval the others keep their grid probabilities."""
    from lfd_torch.segmentation.segmentation import _refine_switch_on_grid

    g = torch.Generator().manual_seed(5)
    T, K, a, b, stride = 48, 2, 0, 1, 3
    grid = torch.arange(1, T, 4)  # grid points 1, 5, 9, ...
    ll = 0.3 * torch.randn(T, K, generator=g, dtype=F64)
    ll[:30, a] += 1.0  # the direction likelihood alone puts the switch at 30
    ll[30:, b] += 1.0
    j0, grid_scores = 4, torch.tensor([0.5, 2.0, 1.0, -3.0], dtype=F64)  # intervals (13, 17], (17, 21], ..
    for first, log_prior in ((0, None), (15, None), (0, 0.4 * torch.randn(T + 1, generator=g, dtype=F64))):
        lo, switch, doubt = _refine_switch_on_grid(ll, a, b, grid, j0, grid_scores, first, T - 1, stride, log_prior)
        taus, weights = [], []
        kept = [w for w in range(4) if int(grid[j0 + w]) >= first]
        p_grid = np.exp([float(grid_scores[w]) for w in kept])
        p_grid /= p_grid.sum()
        for w, pj in zip(kept, p_grid):
            ts = [t for t in range(int(grid[j0 + w - 1]) + 1, int(grid[j0 + w]) + 1) if t >= first]
            sc = [sum(float(ll[t, a] - ll[t, b]) for t in range(ts[0] if not taus else taus[0], tau)) / stride
                  + (0.0 if log_prior is None else float(log_prior[tau])) for tau in ts]
            top = max(sc)
            e = [math.exp(v - top) for v in sc]
            taus += ts
            weights += [pj * v / sum(e) for v in e]
        assert lo == taus[0] and taus == list(range(taus[0], taus[-1] + 1))
        cdf = list(itertools.accumulate(weights))
        want = taus[0] + next(j for j, c in enumerate(cdf) if c >= 0.5)
        assert switch == want, (first, switch, want)
        assert 13 < switch <= 29  # never at the direction evidence's 30
        want_doubt = [cdf[t - lo] if t < want else 1.0 - cdf[t - lo] for t in range(lo, taus[-1])]
        np.testing.assert_allclose(doubt.numpy(), want_doubt, rtol=1e-9, atol=1e-12)


def test_refine_switch_is_the_median_of_a_written_out_change_point_posterior():
    """_refine_switch against a plain loop over every switch time tau in [lo, hi]: p(tau) proportional to
    exp(sum_{lo <= t < tau} (ll_a(t) - ll_b(t)) / stride + log_prior(tau)); the switch is the smallest tau with
    P(<= tau) >= 1/2, and a sample's doubt the probability that it lies on the other side of it."""
    from lfd_torch.segmentation.segmentation import _refine_switch

    g = torch.Generator().manual_seed(3)
    T, K, a, b, lo, hi = 40, 3, 2, 0, 7, 31
    ll = torch.randn(T, K, generator=g, dtype=F64)
    ll[lo:19, a] += 0.8  # a before about 19, b after
    ll[19:hi, b] += 0.8
    for stride, log_prior in ((1, None), (3, None), (2, 0.5 * torch.randn(T + 1, generator=g, dtype=F64))):
        switch, doubt = _refine_switch(ll, a, b, lo, hi, stride, log_prior)
        scores = []
        for tau in range(lo, hi + 1):
            sc = sum(float(ll[t, a] - ll[t, b]) for t in range(lo, tau)) / stride
            scores.append(sc + (0.0 if log_prior is None else float(log_prior[tau])))
        top = max(scores)
        w = [math.exp(sc - top) for sc in scores]
        p = [v / sum(w) for v in w]
        cdf = list(itertools.accumulate(p))
        want = lo + next(j for j, c in enumerate(cdf) if c >= 0.5)
        assert switch == want, (stride, switch, want)
        want_doubt = [cdf[t - lo] if t < want else 1.0 - cdf[t - lo] for t in range(lo, hi)]
        np.testing.assert_allclose(doubt.numpy(), want_doubt, rtol=1e-9, atol=1e-12)
