"""The BP-GM-HMM sampler's helpers and map-search moves (lfd_torch.segmentation.sampler) against independent
references: incremental scores against full rescoring of every candidate, candidate sets against plain Python
loops over runs, the selection rules against hand-made inputs, and the hyperparameter ranges against their
documented intervals. Tiny inputs: two short synthetic demonstrations of unequal length, a few states."""

from __future__ import annotations

import collections
import math

import pytest
import torch

import lfd_torch.segmentation.sampler as sm
from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.segmentation import segment
from lfd_torch.segmentation.blocks import block_log_evidence
from lfd_torch.segmentation.synthetic import multi_step_demos
from conftest import capture_runs

F64 = torch.float64
TINY = dict(max_samples=30, n_iterations=3, n_chains=1, selection="joint")
DIRECTIONS = dict(block_emission=False, position_mixture=False, position_weight=0.0, dwell_cue=False,
                  straight_weight=0.0)


def _positions() -> list[torch.Tensor]:
    """Two demonstrations of three steps, the second cut at 3/4 of its samples (unequal lengths, padding)."""
    syn = multi_step_demos(torch.Generator().manual_seed(0), n_demos=2, n_steps=3, dim=2, profile="constant")
    p = syn.demos.positions
    return [p[0], p[1][: int(0.75 * p[1].shape[0])]]


def _tiny_run(monkeypatch, **options):
    """A sampler run (``_Run``) of a tiny segment call, kept for its observations and scoring."""
    runs = capture_runs(monkeypatch)
    seg = segment(_positions(), generator=torch.Generator().manual_seed(0), **{**TINY, **options})
    return runs[-1], seg


def _labelling(run) -> tuple[torch.Tensor, torch.Tensor]:
    """A hand-made labelling of the tiny run's two sequences (lengths 28 and 29, D = 2): runs of odd and even
    lengths, a state revisited within a sequence, states shared and own, padding repeating the last label, and
    sequence 0 owning a feature (4) it does not use."""
    assert run.lengths.tolist() == [28, 29] and run.D == 2
    row0 = [0] * 6 + [1] * 7 + [2] * 5 + [1] * 4 + [3] * 6 + [3]
    row1 = [2] * 5 + [0] * 4 + [3] * 7 + [0] * 3 + [4] * 10
    s = torch.tensor([row0, row1])
    F = torch.tensor([[True, True, True, True, True], [True, False, True, True, True]])
    return s, F


def _hyper(alpha=1.0, kappa=25.0, mass=2.0):
    return [torch.tensor([v], dtype=F64) for v in (alpha, kappa, mass)]


def _full(run, hyper):
    def score(s, F):
        return run._collapsed_score(s, F, sm.duration_phases(s, run.D), *(h.expand(s.shape[0]) for h in hyper))
    return score


def _naive_runs(row: list[int]) -> list[tuple[int, int, int]]:
    out, a = [], 0
    for t in range(1, len(row) + 1):
        if t == len(row) or row[t] != row[a]:
            out.append((a, t, row[a]))
            a = t
    return out


# ---------------------------------------------------------------------------------------------- small helpers
def test_runs_compact_columns_and_pad_against_loops():
    """``_runs`` equals a loop over each valid row; ``_compact_columns`` drops exactly the columns nobody owns and
    maps every label to its rank among the kept ones; ``_pad`` pads with each sequence's last sample and reports
    lengths, and rejects bad input with typed errors."""
    g = torch.Generator().manual_seed(3)
    for _ in range(20):
        N, T = 3, 12
        s = torch.randint(0, 3, (N, T), generator=g)
        s[:, 2:5] = s[:, 2:3]  # some runs longer than one sample
        lengths = torch.randint(1, T + 1, (N,), generator=g)
        got = sm._runs(s, lengths)
        for i in range(N):
            assert got[i] == _naive_runs(s[i, : int(lengths[i])].tolist())
        F = torch.rand(N, 5, generator=g) < 0.4
        s5 = torch.randint(0, 5, (N, T), generator=g)
        kept = [k for k in range(5) if bool(F[:, k].any())]
        s5 = torch.tensor([[kept[int(v) % len(kept)] if kept else 0 for v in row] for row in s5.tolist()])
        if not kept:
            continue
        s2, F2 = sm._compact_columns(s5, F)
        assert F2.tolist() == [[bool(F[i, k]) for k in kept] for i in range(N)]
        assert s2.tolist() == [[kept.index(int(v)) for v in row] for row in s5.tolist()]
    a = torch.randn(5, 2, generator=g, dtype=F64)
    b = torch.randn(3, 2, generator=g, dtype=F64)
    x, lengths = sm._pad([a, b])
    assert lengths.tolist() == [5, 3] and x.shape == (2, 5, 2)
    assert torch.equal(x[0], a) and torch.equal(x[1, :3], b) and torch.equal(x[1, 3:], b[-1].expand(2, 2))
    with pytest.raises(TooFewSamplesError):
        sm._pad([])
    with pytest.raises(TooFewSamplesError):
        sm._pad([a, b[:1]])
    with pytest.raises(ShapeMismatchError):
        sm._pad([a, torch.randn(4, 3, generator=g, dtype=F64)])
    bad = b.clone()
    bad[1, 0] = math.nan
    with pytest.raises(NonFiniteError):
        sm._pad([a, bad])


def test_share_bank_gather_returns_what_add_stored_across_growth():
    """``_ShareBank``: rows added in batches of several widths r (growing past the initial capacity) are read
    back by gather at the slots ``index`` names, and ``clear`` empties it."""
    g = torch.Generator().manual_seed(4)
    bank = sm._ShareBank()
    stored = {}
    for batch in range(12):
        for r in (1, 2, 3):
            n = 1 + batch % 5 + 4 * (r == 2) * batch
            w = 2 * r
            gram = torch.randn(n, w, w, generator=g, dtype=F64)
            proj = torch.randn(n, w, 2, generator=g, dtype=F64)
            const = torch.randn(n, generator=g, dtype=F64)
            names = [f"{batch}-{r}-{j}".encode() for j in range(n)]
            bank.add(r, names, gram, proj, const)
            stored.update((name, (r, gram[j], proj[j], const[j])) for j, name in enumerate(names))
    assert set(bank.index) == set(stored)
    for r in (1, 2, 3):
        names = [name for name, v in stored.items() if v[0] == r]
        assert all(bank.index[name][0] == r for name in names)
        slots = torch.tensor([bank.index[name][1] for name in names])
        gram, proj, const = bank.gather(r, slots)
        for j, name in enumerate(names):
            assert torch.equal(gram[j], stored[name][1]) and torch.equal(proj[j], stored[name][2])
            assert float(const[j]) == float(stored[name][3])
    bank.clear()
    assert bank.index == {} and bank.banks == {}


def test_disjoint_shifts_against_a_greedy_loop():
    """``_Run._disjoint_shifts``: the improving moves (strictly above the score), best first, each kept when its
    region [lo, hi) does not overlap (sharing an end point is not an overlap) those kept before it in its own
    sequence; regions of different sequences never conflict."""
    g = torch.Generator().manual_seed(5)
    for _ in range(30):
        P = 25
        seq = torch.randint(0, 3, (P,), generator=g)
        lo = torch.randint(0, 8, (P,), generator=g) * 2
        hi = lo + 2 * torch.randint(1, 4, (P,), generator=g)  # even ends: many regions only touch
        region = torch.stack([lo, hi], 1)
        sc = torch.randperm(P, generator=g).to(F64) / P
        score = torch.tensor(0.3, dtype=F64)
        sc[0] = 0.3  # equal to the score: not improving
        want, kept = [], collections.defaultdict(list)
        for b in sorted(range(P), key=lambda b: -float(sc[b])):
            if not float(sc[b]) > 0.3:
                continue
            i, a, e = int(seq[b]), int(lo[b]), int(hi[b])
            if all(e <= a2 or a >= e2 for a2, e2 in kept[i]):
                kept[i].append((a, e))
                want.append(b)
        assert sm._Run._disjoint_shifts(sc, seq, region, score) == want


# ---------------------------------------------------------------------------------------------- candidate sets
@pytest.mark.parametrize("short_state", [False, True], ids=["all_long", "one_state_used_3_times"])
def test_splits_are_the_second_halves_of_every_run_most_used_state_first(monkeypatch, short_state):
    """``_Run._splits``: one candidate per state used at least 2 D times (valid samples), most used first; each gives
    the second half (the later ceil(n / 2) samples of a run of n, as the map-selection test of
    test_segmentation.py cuts them) of every run of that state to a new last column
    owned by the sequences that own the state."""
    run, _ = _tiny_run(monkeypatch, **DIRECTIONS)
    s, F = _labelling(run)
    if short_state:  # state 4 on 3 grid points only (D <= 3 < 2 D): no split of it
        s[1, 22:] = 1
        F[1, 1] = True
    N, K = F.shape
    usage = collections.Counter()
    for i in range(N):
        for t in range(int(run.lengths[i])):
            usage[int(s[i, t])] += 1
    order = sorted((k for k in range(K) if usage[k] >= 2 * run.D), key=lambda k: (-usage[k], k))
    got = run._splits(s, F)
    assert len(got) == len(order)
    got_states = []
    for s2, F2 in got:
        want_k = None
        for k in range(K):
            ref = s.clone()
            for i in range(N):
                n = int(run.lengths[i])
                for a, e, state in _naive_runs(s[i, :n].tolist()):
                    if state == k:
                        ref[i, e - (e - a + 1) // 2: e] = K
                        if e == n:
                            ref[i, n:] = K
            if torch.equal(ref[run.valid], s2[run.valid]):
                want_k = k
        assert want_k is not None
        assert torch.equal(F2, torch.cat([F, F[:, want_k: want_k + 1]], 1))
        got_states.append(want_k)
    assert short_state == (4 not in order)
    # ties in use are not ordered by the docstring: compare the use counts in order
    assert [usage[k] for k in got_states] == [usage[k] for k in order]
    assert sorted(got_states) == sorted(order)


def _naive_shifts(s, lengths, D):
    """Every shift candidate of the map search by plain loops: (sequence, new valid row, touched set, region)."""
    out = []
    for i in range(s.shape[0]):
        n = int(lengths[i])
        row = s[i, :n].tolist()
        rr = _naive_runs(row)
        R = len(rr)
        for r in range(R - 1):  # a switch moved by at most D, both runs kept at least D long
            lo, c, hi = rr[r][0], rr[r][1], rr[r + 1][1]
            a, b = rr[r][2], rr[r + 1][2]
            for c2 in range(c - D, c + D + 1):
                if c2 - lo >= D and hi - c2 >= D:
                    out.append((i, row[:lo] + [a] * (c2 - lo) + [b] * (hi - c2) + row[hi:], {a, b}, (lo, hi)))
        for r in range(R if R > 1 else 0):  # a run removed
            lo, hi = rr[max(r - 1, 0)][0], rr[min(r + 1, R - 1)][1]
            gone = rr[r][2]
            if r == 0 or r == R - 1 or rr[r - 1][2] == rr[r + 1][2]:
                a = rr[r - 1][2] if r > 0 else rr[r + 1][2]
                out.append((i, row[:lo] + [a] * (hi - lo) + row[hi:], {a, gone}, (lo, hi)))
            else:
                a, b = rr[r - 1][2], rr[r + 1][2]
                for c2 in range(rr[r][0] - D, rr[r][1] + D + 1):
                    if c2 - lo >= D and hi - c2 >= D:
                        out.append((i, row[:lo] + [a] * (c2 - lo) + [b] * (hi - c2) + row[hi:], {a, b, gone},
                                    (lo, hi)))
    return [c for c in out if c[1] != s[c[0], : int(lengths[c[0]])].tolist()]


def test_shift_candidates_equal_a_loop_over_switches_and_runs(monkeypatch):
    """``_Run._shifts`` (direction emission, no births): the candidates are exactly the loop's moves of one switch by
    up to D and removals of one run (the new switch within D of it, both new runs at least D long; the
    neighbours' state where the run is at an end or between two runs of one state), none equal to the labelling;
    each changes one sequence inside its region, pads with the last valid label, owns exactly the states that
    sequence then uses, and names the states whose samples it changes."""
    run, _ = _tiny_run(monkeypatch, **DIRECTIONS)
    s, F = _labelling(run)
    cand_s, cand_f, seq, touched, region = run._shifts(s, F)
    got = []
    for b in range(seq.numel()):
        i = int(seq[b])
        n = int(run.lengths[i])
        others = [j for j in range(run.N) if j != i]
        assert torch.equal(cand_s[b, others], s[others]) and torch.equal(cand_f[b, others], F[others])
        assert (cand_s[b, i, n:] == cand_s[b, i, n - 1]).all()
        row = cand_s[b, i, :n].tolist()
        assert cand_f[b, i].tolist() == [k in row for k in range(F.shape[1])]
        t_set = {int(k) for k in touched[b] if int(k) >= 0}
        got.append((i, tuple(row), frozenset(t_set), tuple(region[b].tolist())))
    want = [(i, tuple(row), frozenset(t), reg) for i, row, t, reg in _naive_shifts(s, run.lengths, run.D)]
    assert sorted(got, key=repr) == sorted(want, key=repr)
    # the touched states cover every state whose samples change
    for i, row, t, _ in got:
        old = s[i, : len(row)].tolist()
        assert {v for v, w in zip(old, row) if v != w} | {w for v, w in zip(old, row) if v != w} <= set(t)


def test_birth_spans_equal_a_loop(monkeypatch):
    """``_Run._birth_spans``: for every run at least 2 D long, its end given to each state that follows its state
    somewhere (not its state, not its own successor) and to the new state, and its start to each state that precedes
    it somewhere (not its predecessor) and to the new state, the cut leaving both parts at least D long."""
    run, _ = _tiny_run(monkeypatch, **DIRECTIONS)
    s, F = _labelling(run)
    K = F.shape[1] + 1
    runs = sm._runs(s, run.lengths)
    pairs = set()
    for rr in runs:
        for x, y in zip(rr, rr[1:]):
            pairs.add((x[2], y[2]))
    D, want = run.D, []
    for i, rr in enumerate(runs):
        for q, (lo, hi, a) in enumerate(rr):
            if hi - lo < 2 * D:
                continue
            nxt = rr[q + 1][2] if q + 1 < len(rr) else None
            prv = rr[q - 1][2] if q > 0 else None
            for b in [b for b in range(K - 1) if (a, b) in pairs and b != a and b != nxt] + [K - 1]:
                want.append((i, lo, hi, a, b, lo + D, hi - D, -1))
            for b in [b for b in range(K - 1) if (b, a) in pairs and b != a and b != prv] + [K - 1]:
                want.append((i, lo, hi, b, a, lo + D, hi - D, -1))
    got = run._birth_spans(runs, K)
    assert sorted(got) == sorted(want) and len(got) == len(want)
    assert any(sp[3] != K - 1 and sp[4] != K - 1 for sp in got)  # shared births exist here


def test_reassignment_candidates_equal_a_loop(monkeypatch):
    """``_Run._reassignments``: every (sequence i, state k it uses, j != k among the K states and a new one), the
    runs of k in sequence i relabelled j, sequence i then owning j and not k (other features and sequences
    unchanged, the new column owned by nobody else)."""
    run, _ = _tiny_run(monkeypatch, **DIRECTIONS)
    s, F = _labelling(run)
    N, K = F.shape
    cand_s, cand_f, i_, k_, j_ = run._reassignments(s, F)
    want = {}
    for i in range(N):
        for k in sorted(set(s[i, : int(run.lengths[i])].tolist())):
            for j in range(K + 1):
                if j == k:
                    continue
                s2 = s.clone()
                s2[i][s[i] == k] = j
                F2 = torch.cat([F, torch.zeros(N, 1, dtype=torch.bool)], 1)
                F2[i, k], F2[i, j] = False, True
                want[(i, k, j)] = (s2, F2)
    got = list(zip(i_.tolist(), k_.tolist(), j_.tolist()))
    assert sorted(got) == sorted(want) and len(got) == len(want)
    for b, key in enumerate(got):
        assert torch.equal(cand_s[b], want[key][0]) and torch.equal(cand_f[b], want[key][1]), key


@pytest.mark.parametrize("second", [False, True], ids=["mixed_runs", "short_and_same_neighbours"])
def test_shared_birth_candidates_equal_a_loop(monkeypatch, second):
    """``_Run._shared_births``: for each state j, side (the runs after or before j's runs) and fraction f in 1/3, 1/2,
    2/3, every such neighbouring run at least 2 D long gives its first (after) or last (before) share, cut at
    round(f n) clamped to leave both parts at least D long, to one new state owned by exactly the sequences that
    receive it; a candidate only when at least two sequences receive it from at least two different states."""
    run, _ = _tiny_run(monkeypatch, **DIRECTIONS)
    s, F = _labelling(run)
    if second:  # state 0 followed by a run of 3 < 2 D in sequence 0; state 2 followed by state 1 in both
        s = torch.tensor([[0] * 6 + [1] * 3 + [2] * 9 + [1] * 11, [0] * 7 + [3] * 8 + [2] * 6 + [1] * 8])
        F = torch.tensor([[True, True, True, False], [True] * 4])
    N, K = F.shape
    D = run.D
    want = []
    for j in range(K):
        for after in (True, False):
            for f in (1 / 3, 1 / 2, 2 / 3):
                s2, owners, sources = s.clone(), set(), set()
                for i in range(N):
                    rr = _naive_runs(s[i, : int(run.lengths[i])].tolist())
                    for r in range(len(rr)):
                        nb = r + 1 if after else r - 1
                        if rr[r][2] != j or nb < 0 or nb >= len(rr):
                            continue
                        a, e, other = rr[nb]
                        if e - a < 2 * D:
                            continue
                        cut = a + round(f * (e - a))
                        cut = max(a + D, min(e - D, cut))
                        if after:
                            s2[i, a:cut] = K
                        else:
                            s2[i, cut:e] = K
                        owners.add(i)
                        sources.add(other)
                if len(owners) >= 2 and len(sources) >= 2:
                    F2 = torch.cat([F, torch.tensor([[i in owners] for i in range(N)])], 1)
                    want.append((s2, F2))
    got = run._shared_births(s, F)
    assert len(want) == (3 if second else 9) and len(got) == len(want)  # (state, side) pairs x 3 fractions
    for (s1, F1), (s2, F2) in zip(got, want):
        assert torch.equal(s1, s2) and torch.equal(F1, F2)


def test_runs_per_sequence_and_snapshot_against_loops(monkeypatch):
    """``_Run._runs_per_sequence`` counts each chain's runs per sequence over its valid samples (a loop over the
    labels); ``_Run._snapshot`` keeps a chain's owned features in slot order, relabels its states to them, and takes
    their fields, noise and hyperparameters."""
    run, _ = _tiny_run(monkeypatch, **DIRECTIONS, n_chains=2)
    s, F = _labelling(run)
    C, N, T, d = 2, run.N, run.T, run.d
    K = 7
    g = torch.Generator().manual_seed(6)
    slots = [[1, 3, 4, 5, 6], [0, 2, 3, 5, 6]]  # chain c puts state k of the hand-made labelling in slot slots[c][k]
    run.s = torch.stack([torch.tensor(sl)[s] for sl in slots])
    run.s[1, 0, 28] = 0  # padding of chain 1, sequence 0: a label that is not counted
    run.F = torch.zeros(C, N, K, dtype=torch.bool)
    for c in range(C):
        for k in range(F.shape[1]):
            run.F[c, :, slots[c][k]] = F[:, k]
    run.field = torch.randn(C, K, d, d + 1, generator=g, dtype=F64)
    run.noise = torch.randn(C, K, d, d, generator=g, dtype=F64)
    run.mass, run.alpha, run.kappa = (torch.tensor([1.0, 2.0], dtype=F64) * v for v in (1.5, 3.0, 11.0))
    got = run._runs_per_sequence()
    for c in range(C):
        for i in range(N):
            row = run.s[c, i, : int(run.lengths[i])].tolist()
            assert int(got[c, i]) == len(_naive_runs(row)), (c, i)
    for c in range(C):
        snap = run._snapshot(c)
        owned = [k for k in range(K) if bool(run.F[c, :, k].any())]
        assert owned == slots[c]
        assert snap["states"][run.valid].tolist() == [owned.index(int(v)) for v in run.s[c][run.valid]]
        assert torch.equal(snap["features"], run.F[c][:, owned])
        assert torch.equal(snap["field"], run.field[c, owned]) and torch.equal(snap["noise"], run.noise[c, owned])
        assert snap["hyper"] == {"feature_mass": 1.5 * (c + 1), "transition_concentration": 3.0 * (c + 1),
                                 "stickiness": 11.0 * (c + 1)}


def test_occupancy_evidence_is_the_ewens_formula(monkeypatch):
    """``position_mixture``: the occupancy terms plus the labelling-free constant equal, per sequence, the Ewens
    (Chinese restaurant, concentration 1) probability of the tempered counts x_ik = tau n_ik,
    log prod_k Gamma(x_ik) - log Gamma(1 + x_i) summed over sequences; the Viterbi proposal's weights are
    tau log((x_ik + 1 / K) / (x_i + 1))."""
    run, _ = _tiny_run(monkeypatch, block_emission=False, position_mixture=True, position_weight=0.3,
                       dwell_cue=False)
    s, F = _labelling(run)
    N, T, K = run.N, run.T, F.shape[1]
    onehot = (torch.nn.functional.one_hot(s, K).to(F64) * run.valid.unsqueeze(-1)).reshape(1, N * T, K)
    tau = 0.3
    want, weights = 0.0, torch.zeros(N, K, dtype=F64)
    for i in range(N):
        n_i = int(run.lengths[i])
        counts = collections.Counter(s[i, :n_i].tolist())
        want += sum(math.lgamma(tau * n) for n in counts.values()) - math.lgamma(1 + tau * n_i)
        for k in range(K):
            weights[i, k] = tau * math.log((tau * counts.get(k, 0) + 1 / K) / (tau * n_i + 1))
    got = float(run._occupancy_terms(onehot).sum()) + run._occupancy_constant()
    assert got == pytest.approx(want, abs=1e-9)
    assert torch.allclose(run._occupancy_log_weights(onehot)[0, :, 0], weights, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------------- incremental scores
@pytest.mark.parametrize("options", [
    dict(DIRECTIONS),
    dict(DIRECTIONS, robust_dof=None),
    dict(block_emission=False, position_mixture=True, position_weight=None, dwell_cue=True, straight_weight=0.5),
    dict(block_emission=False, position_mixture=False, position_weight=0.3, dwell_cue=True, straight_weight=0.5,
         tolerance_correlation=0.9),
], ids=["directions", "gaussian", "position_mixture_dwell_straight", "correlated_tolerance"])
def test_shift_and_reassignment_scores_equal_full_rescoring(monkeypatch, options):
    """``_Run._shift_scores`` and ``_Run._reassignment_scores`` (the current score plus the change of the terms a move
    touches) equal ``_Run._collapsed_score`` of every candidate computed from scratch, on a hand-made labelling
    with an owned-but-unused feature and on one of its splits, under several emission options."""
    run, _ = _tiny_run(monkeypatch, **options)
    s0, F0 = _labelling(run)
    hyper = _hyper(alpha=1.7, kappa=9.0, mass=1.3)
    score = _full(run, hyper)
    split = sm._compact_columns(*run._splits(s0, F0)[1])
    for s, F in [(s0, F0), split]:
        here = score(s[None], F[None])[0]
        cand = run._shifts(s, F)
        fast = run._shift_scores(s, F, *cand[:4], here, hyper)
        full = score(cand[0], cand[1])
        assert torch.allclose(fast, full, rtol=0, atol=1e-8), float((fast - full).abs().max())
        cand = run._reassignments(s, F)
        fast = run._reassignment_scores(s, F, *cand, here, hyper)
        full = score(cand[0], cand[1])
        assert torch.allclose(fast, full, rtol=0, atol=1e-8), float((fast - full).abs().max())


def test_block_deltas_follow_the_labelling_they_are_asked_about(monkeypatch):
    """``_Run._block_deltas`` under the block emission, asked about a second labelling after a first (its cached
    profile must not leak): each candidate's delta equals ``block_log_evidence`` of the candidate minus that of the
    current labelling, every state held at the current labelling's profiled component (a new state at that of
    the state whose samples it receives), plus the change of the used states' component log prior."""
    run, _ = _tiny_run(monkeypatch, block_emission=True, position_weight=0.0, dwell_cue=False)
    # close to the demonstrations' steps, so that the profile makes states 0 and 2 straight and 1 and 3 curved
    s_a = torch.tensor([[2] * 8 + [0] * 9 + [1] * 6 + [3] * 6, [2] * 12 + [0] * 12 + [1] * 5])
    F_a = torch.tensor([[True] * 4, [True, True, True, False]])
    s_b = s_a.clone()
    s_b[1, 11] = 0  # the second labelling: one switch moved by one grid point (same states, same K)
    F_b = F_a
    log_prior = torch.tensor([math.log(0.5), math.log(0.5)], dtype=F64)

    def reference(s, F, cand, rows_seq):
        N, T = s.shape
        K = F.shape[1]
        k = K + 1
        onehot = torch.nn.functional.one_hot(s, K).to(F64) * run.valid.unsqueeze(-1)
        age, w, _ = run._score_view(s[None])
        kind = run._block_profile(s[None], age, w.expand(1, -1), onehot.reshape(1, N * T, K))[1][0]
        kd = torch.cat([kind, torch.ones(1, dtype=kind.dtype)]).expand(cand.shape[0], k).clone()
        rows = cand[torch.arange(cand.shape[0]), rows_seq]
        first = (rows == k - 1).to(torch.uint8).argmax(-1)
        kd[:, k - 1] = kind[s[rows_seq, first]]

        def ev(lab, kk):
            return block_log_evidence(*run.blocks, run.valid, lab, kk == 0, **run._block_options())

        def prior(lab, kk):
            used = (torch.nn.functional.one_hot(lab, k).bool() & run.valid.unsqueeze(-1)).flatten(-3, -2).any(-2)
            return (log_prior[kk.clamp_max(1)] * used).sum(-1)

        return ev(cand, kd) - ev(s[None], kd[:1]) + prior(cand, kd) - prior(s[None], kd[:1])

    kinds = []
    for s, F in [(s_a, F_a), (s_b, F_b), (s_a, F_a)]:
        N, T = s.shape
        onehot = torch.nn.functional.one_hot(s, F.shape[1]).to(F64) * run.valid.unsqueeze(-1)
        age, w, _ = run._score_view(s[None])
        kinds.append(run._block_profile(s[None], age, w.expand(1, -1), onehot.reshape(1, N * T, -1))[1][0].tolist())
        cs, _, i, _, _ = run._reassignments(s, F)
        fast = run._block_deltas(s, cs, i, F.shape[1] + 1)
        ref = reference(s, F, cs, i)
        assert torch.allclose(fast, ref, rtol=0, atol=1e-7), float((fast - ref).abs().max())
    assert kinds[0] == [0, 1, 0, 1]  # both components among the states a new state may inherit


def test_component_log_prior_and_block_scales(monkeypatch):
    """``_Run._component_log_prior``: log 1/2 for a used straight state, log 1/2 for a used curved one (log 1/4 for
    each of the two curved scales with ``slope_scale_mix``), 0 for unused states; ``_Run._block_scales``:
    ``slope_scale_mix`` for component 2, ``slope_scale`` otherwise."""
    for mix in (0.0, 7.0):
        run, _ = _tiny_run(monkeypatch, block_emission=True, slope_scale=0.4, slope_scale_mix=mix, dwell_cue=False)
        kind = torch.tensor([[0, 1, 2, 0, 1], [2, 2, 0, 1, 0]])
        used = torch.tensor([[True, True, True, False, False], [True, False, True, True, True]])
        curved = math.log(0.25) if mix > 0 else math.log(0.5)
        want = [[(math.log(0.5) if c == 0 else curved) if u else 0.0 for c, u in zip(kr, ur)]
                for kr, ur in zip(kind.tolist(), used.tolist())]
        got = run._component_log_prior(kind, used)
        # exact in float64 (they were built by torch.where on Python floats, i.e. in float32: 2e-9 nats off per
        # state, and a slope scale of 0.4 read 0.4000000059604645)
        assert got.dtype == F64 and torch.equal(got, torch.tensor(want, dtype=F64))
        scales = run._block_scales(kind)
        want = torch.tensor([[mix if c == 2 else 0.4 for c in kr] for kr in kind.tolist()], dtype=F64)
        assert scales.dtype == F64 and torch.equal(scales, want)


# ---------------------------------------------------------------------------------------------- selection rules
def test_modal_sample_picks_the_modal_run_counts_then_the_best_joint(monkeypatch):
    """``_Run._modal_sample`` on a hand-made list of kept samples: per sequence the most frequent run count (ties to
    the smaller, checked with a Counter), and among the samples with the most sequences at that count, the highest
    joint log probability; its collapsed score is that of its own labelling."""
    run, _ = _tiny_run(monkeypatch, **DIRECTIONS)
    s, F = _labelling(run)
    hyper = {"feature_mass": 1.5, "transition_concentration": 2.0, "stickiness": 10.0}
    # (runs of seq 0, runs of seq 1, joint); seq 0: 3 and 5 tie (three each) -> 3; seq 1: 4 most frequent
    spec = [(3, 4, -10.0), (5, 4, -1.0), (3, 2, -0.5), (5, 4, -2.0), (3, 6, -3.0), (6, 4, -0.1), (5, 2, 0.0),
            (2, 4, -4.0), (3, 4, -7.0)]
    labs = [(s, F), sm._compact_columns(*run._splits(s, F)[0])]
    kept = []
    for c, (r0, r1, joint) in enumerate(spec):
        lab_s, lab_f = labs[c % 2]
        kept.append({"states": lab_s, "features": lab_f, "field": None, "noise": None, "hyper": hyper,
                     "joint": joint, "runs": torch.tensor([r0, r1]), "phase": sm.duration_phases(lab_s, run.D),
                     "chain": c})
    modal = []
    for i in range(2):
        count = collections.Counter(int(k["runs"][i]) for k in kept)
        top = max(count.values())
        modal.append(min(v for v, n in count.items() if n == top))
    assert modal == [3, 4]
    agree = [sum(int(k["runs"][i]) == modal[i] for i in range(2)) for k in kept]
    best = max((c for c in range(len(kept)) if agree[c] == max(agree)), key=lambda c: kept[c]["joint"])
    assert best == 8
    got = run._modal_sample(kept)
    assert got["chain"] == best and got["joint"] == kept[best]["joint"]
    lab_s, lab_f = labs[best % 2]
    want = _full(run, _hyper(2.0, 10.0, 1.5))(lab_s[None], lab_f[None])[0]
    assert got["collapsed"] == pytest.approx(float(want), abs=1e-9)
    # with no sample at both modal counts, those at most of them
    kept2 = [dict(k) for k in kept if not (int(k["runs"][0]) == 3 and int(k["runs"][1]) == 4)]
    kept2 += [dict(kept[0], runs=torch.tensor([3, 2]), joint=-50.0, chain=99)] * 2
    count0 = collections.Counter(int(k["runs"][0]) for k in kept2)
    count1 = collections.Counter(int(k["runs"][1]) for k in kept2)
    m0 = min(v for v, n in count0.items() if n == max(count0.values()))
    m1 = min(v for v, n in count1.items() if n == max(count1.values()))
    agree = [(int(k["runs"][0]) == m0) + (int(k["runs"][1]) == m1) for k in kept2]
    best2 = max((c for c in range(len(kept2)) if agree[c] == max(agree)), key=lambda c: kept2[c]["joint"])
    assert run._modal_sample(kept2)["chain"] == kept2[best2]["chain"]


def test_map_selection_is_a_local_mode_under_shifts(monkeypatch):
    """selection="map" on a tiny case: its reported collapsed score is that of its labelling, and no shift candidate
    (built by plain loops, :func:`_naive_shifts`) scores higher (merges, reassignments and splits:
    ``tests/test_segmentation.py::test_map_selection_is_a_local_mode_of_the_collapsed_posterior_under_merges``)."""
    runs = capture_runs(monkeypatch)
    seg = segment(_positions(), generator=torch.Generator().manual_seed(1), max_samples=30, n_iterations=4,
                  n_chains=2, selection="map", block_emission=False, position_mixture=False)
    run, res = runs[-1], seg.sampler
    hyper = [torch.tensor([res.hyperparameters[k]], dtype=F64)
             for k in ("transition_concentration", "stickiness", "feature_mass")]
    score = _full(run, hyper)
    s, F = res.states, res.features
    here = float(score(s[None], F[None])[0])
    assert here == pytest.approx(res.collapsed_log_prob, abs=1e-7)
    K = F.shape[1]
    n = 0
    for i, row, _, _ in _naive_shifts(s, run.lengths, run.D):
        s2 = s.clone()
        s2[i, : len(row)] = torch.tensor(row)
        s2[i, len(row):] = row[-1]
        F2 = F.clone()
        F2[i] = torch.tensor([k in row for k in range(K)])
        s3, F3 = sm._compact_columns(s2, F2)
        assert float(score(s3[None], F3[None])[0]) <= here + 1e-9, (i, row)
        n += 1
    assert n > 0


# ---------------------------------------------------------------------------------------------- results, ranges
def test_sampler_result_n_features_and_normal_tensors():
    """``SamplerResult.n_features`` is the number of states K (fields' first axis, here K != d and K != N), and
    ``_normal_tensors`` turns every tensor, those among the hyperparameters included, into normal tensors with the
    same values, leaving the other fields as they are."""
    K, d, N, T = 3, 2, 4, 5
    with torch.inference_mode():
        r = sm.SamplerResult(
            states=torch.zeros(N, T, dtype=torch.long), lengths=torch.full((N,), T), features=torch.ones(N, K,
                                                                                                            dtype=torch.bool),
            field=torch.randn(K, d, d + 1, dtype=F64), noise=torch.eye(d, dtype=F64).expand(K, d, d).clone(),
            centre=torch.zeros(d, dtype=F64), radius=torch.tensor(2.0, dtype=F64), log_prob=-3.0,
            trace=torch.zeros(1, 2, dtype=F64), n_features_trace=torch.zeros(1, 2, dtype=torch.long), chain=1,
            collapsed_log_prob=-4.0, hyperparameters={"alpha": torch.tensor(1.5, dtype=F64), "kappa": 2.0},
            acceptance={"birth": 0.5})
    assert r.n_features == K
    out = sm._normal_tensors(r)
    for f in ("states", "lengths", "features", "field", "noise", "centre", "radius", "trace", "n_features_trace"):
        a, b = getattr(out, f), getattr(r, f)
        assert not a.is_inference() and torch.equal(a, b), f
    assert not out.hyperparameters["alpha"].is_inference() and float(out.hyperparameters["alpha"]) == 1.5
    assert out.hyperparameters["kappa"] == 2.0 and out.acceptance == {"birth": 0.5}
    assert (out.log_prob, out.collapsed_log_prob, out.chain) == (-3.0, -4.0, 1)
    out.field.add_(1.0)  # usable in place: a normal tensor


# documented intervals (the sampler's docstring, the module docstring): name -> (low, high, low in, high in, int)
DOCUMENTED = {
    "straight_weight": (0.0, 1.0, True, False, False),
    "rotation_weight": (0.0, 1.0, True, False, False),
    "tolerance_correlation": (0.0, 1.0, True, False, False),
    "position_weight": (0.0, 1.0, True, True, False),
    "slope_scale_mix": (0.0, 1e3, True, True, False),
    "demo_offset": (0.0, 1e3, True, True, False),
    "burn_in": (0.0, 1.0, True, False, False),
    "birth_prior_mix": (0.0, 1.0, False, False, False),
    "birth_window": (0.0, 1.0, False, True, False),
    "feature_mass": (0.0, 100.0, False, True, False),
    "direction_noise": (0.0, 2.0, False, True, False),
    "stickiness": (0.0, 1e6, True, True, False),
    "n_chains": (1, 64, True, True, True),
    "n_iterations": (1, 10_000, True, True, True),
    "n_initial_features": (1, 32, True, True, True),
}


@pytest.mark.parametrize("name", sorted(sm.HYPERPARAMETER_RANGES))
def test_check_hyperparameters_accepts_its_interval_and_rejects_the_rest(name):
    """``check_hyperparameters``: each hyperparameter is accepted at its bounds exactly when the bound is inclusive
    (intervals from the docstrings where they state one), inside them, and rejected outside, at NaN / inf, as a
    bool, as a string, and (integer kinds) as a float, with an InvalidArgumentError naming it."""
    kind, low, high, low_in, high_in = sm.HYPERPARAMETER_RANGES[name]
    if name in DOCUMENTED:
        assert (low, high, low_in, high_in, kind is int) == DOCUMENTED[name]

    def ok(v):
        sm.check_hyperparameters(**{name: v})

    def bad(v):
        with pytest.raises(InvalidArgumentError, match=name):
            sm.check_hyperparameters(**{name: v})

    (ok if low_in else bad)(kind(low))
    (ok if high_in else bad)(kind(high))
    ok(kind(low + 1) if kind is int else 0.5 * (low + high))
    if kind is int:
        bad(low - 1)
        bad(high + 1)
        bad(float(low) + 0.5)
    else:
        bad(low - 1e-9 * max(1.0, abs(low)) - 1e-12)
        bad(high * (1 + 1e-9) + 1e-12)
        bad(math.nan)
        bad(math.inf)
    bad(True)
    bad("1")
    if name in ("robust_dof", "position_weight", "tolerance_correlation"):
        ok(None)
    else:
        bad(None)


def test_check_hyperparameters_flags_and_selection():
    """The boolean flags must be bools and ``selection`` one of the four documented rules."""
    for flag in ("resample_hyperparameters", "progress", "position_mixture", "dwell_pace", "block_emission"):
        sm.check_hyperparameters(**{flag: True})
        sm.check_hyperparameters(**{flag: False})
        for v in (1, 0, "yes", None):
            with pytest.raises(InvalidArgumentError, match=flag):
                sm.check_hyperparameters(**{flag: v})
    for sel in ("joint", "collapsed", "modal", "map"):
        sm.check_hyperparameters(selection=sel)
    for sel in ("MAP", "mode", None):
        with pytest.raises(InvalidArgumentError, match="selection"):
            sm.check_hyperparameters(selection=sel)
