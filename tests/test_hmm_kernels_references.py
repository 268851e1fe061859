"""HMM kernels of the BP-GM-HMM (states.py, transitions.py, features.py) against independent references.

References: brute-force enumeration of every state path of tiny HMMs (exact evidence, filtered marginals, MAP path,
posterior over paths), a naive run-age loop over label paths for the minimum-duration (semi-Markov) model, the
sequential Polya urn for the Dirichlet-multinomial, the sequential buffet process for the IBP (Griffiths &
Ghahramani 2011) and Monte Carlo frequencies of backward sampling. Every random test is seeded; the Monte Carlo
tolerances are 5 binomial standard errors plus 5 / n, which a correct sampler exceeds with negligible probability.
"""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from lfd_torch.segmentation.features import ibp_log_prior, sample_ibp
from lfd_torch.segmentation.states import backward_sample, ffbs, forward_filter, forward_log_likelihood, viterbi
from lfd_torch.segmentation.transitions import (
    dirichlet_log_density_rows,
    dirichlet_multinomial_log_prob,
    expand_min_duration,
    free_transitions,
    initial_distribution,
    transition_counts,
    transition_matrix,
)

F64 = torch.float64


# ------------------------------------------------------------------ plain-Python references
def _log(x: float) -> float:
    return math.log(x) if x > 0 else -math.inf


def _logsumexp(values) -> float:
    values = list(values)
    top = max(values)
    if top == -math.inf:
        return -math.inf
    return top + math.log(sum(math.exp(v - top) for v in values))


def _path_log_joint(le, init, P, path) -> float:
    """log p(s, x) of one state path of a plain HMM, a loop over its steps (-inf for an impossible path)."""
    lp = _log(float(init[path[0]])) + float(le[0, path[0]])
    for t in range(1, len(path)):
        lp += _log(float(P[path[t - 1], path[t]])) + float(le[t, path[t]])
    return lp


def _enumerate(le, init, P, length: int) -> dict[tuple[int, ...], float]:
    """log p(s, x_{0:L-1}) of every one of the K^L state paths of one sequence (L = length)."""
    K = le.shape[-1]
    return {path: _path_log_joint(le, init, P, path) for path in itertools.product(range(K), repeat=length)}


def _semi_markov_log_joint(le, init, P, D: int, path) -> float:
    """log p(s, x) of a label path of the explicit-duration HMM with minimum duration D, tracking each run's age:
    a run must last D samples before it may end (a run cut by the end of the sequence may be shorter); once it has,
    the next label follows pi (stay with pi_kk, switch with pi_kj)."""
    lp = _log(float(init[path[0]])) + float(le[0, path[0]])
    age = 1
    for t in range(1, len(path)):
        a, b = path[t - 1], path[t]
        if age < D:
            if a != b:
                return -math.inf
            step = 0.0  # forced: the run goes on with probability 1
        else:
            step = _log(float(P[a, b]))
        lp += step + float(le[t, b])
        age = age + 1 if a == b else 1
    return lp


def _run_phases(path, D: int) -> list[int]:
    """Phase of every sample of a label path: min(run age - 1, D - 1)."""
    out, age = [], 0
    for t, s in enumerate(path):
        age = age + 1 if t > 0 and s == path[t - 1] else 1
        out.append(min(age - 1, D - 1))
    return out


def _encode(paths: torch.Tensor, K: int) -> torch.Tensor:
    """(n, L) labels -> (n,) integers sum_t s_t K^t (one code per path)."""
    return (paths * (K ** torch.arange(paths.shape[-1]))).sum(-1)


def _assert_frequencies(draws: torch.Tensor, posterior: dict[tuple[int, ...], float], K: int, label) -> None:
    """Frequencies of the drawn paths (n, L) against the exact posterior over paths: every path within 5 binomial
    standard errors plus 5 / n, and no draw of a path of probability 0."""
    n = draws.shape[0]
    counts = torch.bincount(_encode(draws, K), minlength=K ** draws.shape[1]).tolist()
    for path, p in posterior.items():
        c = counts[int(_encode(torch.tensor([path]), K)[0])]
        if p == 0.0:
            assert c == 0, (label, path)
        else:
            assert abs(c / n - p) <= 5.0 * math.sqrt(p * (1.0 - p) / n) + 5.0 / n, (label, path, c / n, p)


def _hmm_batch(gen: torch.Generator):
    """Six sequences (T = 5, K = 3) with the sampler's kinds of structure: lengths 5, 3, 1, 4, 5, 4; a state a
    sequence does not own (-inf emissions, 0 initial and transition mass); a usable state that cannot explain one
    sample (-inf at one valid step); a forbidden move (P = 0); a sample no state explains (sample 1 of sequence 5:
    its log evidence is -inf and its filtered rows from there on are 0). Padding emissions are garbage (large
    values and -inf) that must be ignored."""
    B, T, K = 6, 5, 3
    le = torch.randn(B, T, K, generator=gen, dtype=F64) * 2.0
    init = torch.rand(B, K, generator=gen, dtype=F64) + 0.05
    P = torch.rand(B, K, K, generator=gen, dtype=F64) + 0.05
    lengths = torch.tensor([5, 3, 1, 4, 5, 4])
    for b, k in ((1, 2), (4, 0)):  # not owned
        le[b, :, k] = -math.inf
        init[b, k] = 0.0
        P[b, :, k] = 0.0
        P[b, k, :] = 0.0
    le[3, 1, 0] = -math.inf  # a usable state that cannot explain this sample
    P[3, 1, 2] = 0.0  # a forbidden move
    le[5, 1, :] = -math.inf  # nothing explains sample 1 of sequence 5
    init = init / init.sum(-1, keepdim=True)
    P = P / P.sum(-1, keepdim=True).clamp_min(1e-300)
    for b in range(B):  # garbage padding
        L = int(lengths[b])
        le[b, L:] = 40.0 * torch.randn(T - L, K, generator=gen, dtype=F64)
        if L < T:
            le[b, L, 0] = -math.inf
    return le, init, P, lengths


# ------------------------------------------------------------------ forward algorithm
def test_forward_filter_equals_path_enumeration_with_padding_and_unusable_states():
    """log p(x) and the filtered marginals p(s_t | x_{0:t}) of forward_filter / forward_log_likelihood against the
    enumeration of all K^L paths (and of all prefixes), for the six kinds of sequence of ``_hmm_batch``: padding
    with garbage emissions is ignored and its filtered rows repeat the last valid one; a sample that no usable state
    explains gives -inf and no NaN."""
    le, init, P, lengths = _hmm_batch(torch.Generator().manual_seed(101))
    B, T, K = le.shape
    filtered, ll = forward_filter(le, init, P, lengths)
    ll_only = forward_log_likelihood(le, init, P, lengths)
    assert not torch.isnan(filtered).any() and not torch.isnan(ll).any()
    for b in range(B):
        L = int(lengths[b])
        ref = _logsumexp(_enumerate(le[b], init[b], P[b], L).values())
        if ref == -math.inf:
            assert ll[b] == -math.inf and ll_only[b] == -math.inf, b
            continue
        assert float(ll[b]) == pytest.approx(ref, abs=1e-10), b
        assert float(ll_only[b]) == pytest.approx(ref, abs=1e-10), b
        for t in range(L):
            prefix = _enumerate(le[b], init[b], P[b], t + 1)
            z = _logsumexp(prefix.values())
            want = [0.0] * K
            for path, lp in prefix.items():
                want[path[-1]] += math.exp(lp - z)
            torch.testing.assert_close(filtered[b, t], torch.tensor(want, dtype=F64), atol=1e-12, rtol=1e-10)
        torch.testing.assert_close(filtered[b, L:], filtered[b, L - 1].expand(T - L, K), atol=0, rtol=0)
    assert ll[5] == -math.inf  # the sequence with an unexplained sample


def test_forward_results_do_not_depend_on_the_padded_length():
    """The same sequences padded to T = 5 and to T = 9 (more garbage padding) have the same log evidence and the same
    filtered rows on their valid samples (metamorphic reference: padding is neutral)."""
    gen = torch.Generator().manual_seed(102)
    le, init, P, lengths = _hmm_batch(gen)
    extra = torch.randn(le.shape[0], 4, le.shape[2], generator=gen, dtype=F64) * 30.0
    le_long = torch.cat([le, extra], 1)
    f5, ll5 = forward_filter(le, init, P, lengths)
    f9, ll9 = forward_filter(le_long, init, P, lengths)
    torch.testing.assert_close(ll9, ll5, atol=1e-12, rtol=0)
    torch.testing.assert_close(forward_log_likelihood(le_long, init, P, lengths), ll5, atol=1e-12, rtol=0)
    for b in range(le.shape[0]):
        L = int(lengths[b])
        torch.testing.assert_close(f9[b, :L], f5[b, :L], atol=1e-14, rtol=0)
        torch.testing.assert_close(f9[b, L:], f5[b, L - 1].expand(9 - L, -1), atol=0, rtol=0)


# ------------------------------------------------------------------ Viterbi
def test_viterbi_equals_the_enumerated_map_path_with_unusable_states():
    """viterbi against the argmax of log p(s, x) over all K^L paths (the MAP is unique for these random inputs), on
    the possible sequences of ``_hmm_batch`` (unusable states, a -inf emission of a usable state, a forbidden move,
    garbage padding); the padding repeats the last valid state."""
    le, init, P, lengths = _hmm_batch(torch.Generator().manual_seed(103))
    keep = torch.tensor([0, 1, 2, 3, 4])  # sequence 5 is impossible: no MAP path
    le, init, P, lengths = le[keep], init[keep], P[keep], lengths[keep]
    got = viterbi(le, init, P, lengths)
    T = le.shape[1]
    for b in range(len(keep)):
        L = int(lengths[b])
        joint = _enumerate(le[b], init[b], P[b], L)
        ranked = sorted(joint.values(), reverse=True)
        assert ranked[0] - ranked[1] > 1e-6  # unique MAP
        best = max(joint, key=joint.get)
        assert got[b, :L].tolist() == list(best), b
        assert got[b, L:].tolist() == [best[-1]] * (T - L), b


def test_viterbi_breaks_ties_towards_the_lower_state_index():
    """'Ties go to the lower state index': (1) when every path has the same probability (uniform initial
    distribution and transitions, equal emissions) the decoded path is all zeros, whatever the length; (2) with
    states 0 and 1 exact copies of each other (same emissions, transitions symmetric under the swap 0 <-> 1) the MAP
    is attained by a path and its swap, and the decoder (lowest final state, then the lowest predecessor at every
    step back) returns the one with the lower state where they last differ (reference: enumeration, the tied MAP
    paths ordered from the last sample backwards)."""
    B, T, K = 3, 5, 3
    le = torch.zeros(B, T, K, dtype=F64)
    init = torch.full((B, K), 1.0 / K, dtype=F64)
    P = torch.full((B, K, K), 1.0 / K, dtype=F64)
    lengths = torch.tensor([5, 3, 1])
    got = viterbi(le, init, P, lengths)
    assert got.tolist() == [[0] * T] * B
    gen = torch.Generator().manual_seed(104)
    B = 8
    le = torch.randn(B, T, K, generator=gen, dtype=F64) * 2.0
    le[..., 1] = le[..., 0]
    init = torch.rand(B, K, generator=gen, dtype=F64) + 0.1
    init[:, 1] = init[:, 0]
    init = init / init.sum(-1, keepdim=True)
    a, s, x, y, u, v = (torch.rand(B, generator=gen, dtype=F64) + 0.1 for _ in range(6))
    P = torch.stack([torch.stack([a, s, x], -1), torch.stack([s, a, x], -1), torch.stack([y, y, u + v], -1)], -2)
    P = P / P.sum(-1, keepdim=True)  # invariant under swapping states 0 and 1
    lengths = torch.tensor([5, 5, 5, 5, 4, 4, 3, 2])
    got = viterbi(le, init, P, lengths)
    n_swapped_ties = 0
    for b in range(B):
        L = int(lengths[b])
        joint = _enumerate(le[b], init[b], P[b], L)
        top = max(joint.values())
        tied = [path for path, lp in joint.items() if lp >= top - 1e-9]
        assert all(lp < top - 1e-6 for path, lp in joint.items() if path not in tied)  # only exact ties
        want = min(tied, key=lambda path: path[::-1])
        assert got[b, :L].tolist() == list(want), (b, tied)
        n_swapped_ties += len(tied) > 1 and want[-1] == 2
    assert n_swapped_ties > 0  # some tie is decided at a predecessor, not only at the last sample


# ------------------------------------------------------------------ backward sampling
@pytest.mark.parametrize("log", [False, True])
def test_backward_sampling_frequencies_match_the_enumerated_posterior(log):
    """backward_sample(forward_filter(...)) draws whole paths from p(s | x): 20000 draws per sequence against the
    enumerated posterior over all K^L paths, for the possible sequences of ``_hmm_batch`` (lengths 5, 3, 1, 4, 5;
    unusable states and forbidden moves never drawn); the padding repeats the last valid state. The impossible
    sequence 5 (all-zero filtered rows) has no posterior, but its labels stay in 0..K-1 and it does not break
    the batch. The same in logarithms (``log=True`` for both)."""
    le, init, P, lengths = _hmm_batch(torch.Generator().manual_seed(105))
    B, T, K = le.shape
    filtered, _ = forward_filter(le, init, P, lengths, log=log)
    n = 20000
    gen = torch.Generator().manual_seed(205)
    draws = backward_sample(filtered.repeat(n, 1, 1), P.repeat(n, 1, 1), lengths.repeat(n), gen, log=log
                            ).reshape(n, B, T)
    assert int(draws.min()) >= 0 and int(draws.max()) < K
    for b in range(B - 1):
        L = int(lengths[b])
        joint = _enumerate(le[b], init[b], P[b], L)
        z = _logsumexp(joint.values())
        _assert_frequencies(draws[:, b, :L], {p: math.exp(lp - z) for p, lp in joint.items()}, K, b)
        assert (draws[:, b, L:] == draws[:, b, L - 1 : L]).all(), b


# ------------------------------------------------------------------ minimum duration (explicit-duration HMM)
def _semi_markov_batch(gen: torch.Generator, K: int, T: int, lengths: list[int]):
    B = len(lengths)
    le = torch.randn(B, T, K, generator=gen, dtype=F64) * 1.5
    features = torch.ones(B, K, dtype=torch.bool)
    if K > 2:
        features[1, K - 1] = False  # a sequence that does not own the last slot
    weights = torch.rand(B, K, K, generator=gen, dtype=F64) + 0.1
    init = torch.rand(B, K, generator=gen, dtype=F64) + 0.1
    init = init * features
    init = init / init.sum(-1, keepdim=True)
    P = transition_matrix(weights, features)
    le = torch.where(features.unsqueeze(1), le, torch.full_like(le, -math.inf))
    return le, init, P, torch.tensor(lengths)


@pytest.mark.parametrize("D", [2, 3, 4])
def test_min_duration_expansion_likelihood_and_map_equal_semi_markov_enumeration(D):
    """expand_min_duration: the forward evidence and the Viterbi path of the phase-expanded HMM (emissions
    repeat_interleave(D)) equal those of a naive run-age loop over every label path of the explicit-duration model
    (runs last at least D samples, except one cut by the end; after D samples the chain follows pi), with lengths
    shorter than T and a slot a sequence does not own; the expanded chain is row-stochastic on the usable states
    and its Viterbi phases are the run ages."""
    K, T = 3, 6
    le, init, P, lengths = _semi_markov_batch(torch.Generator().manual_seed(106 + D), K, T, [6, 6, 4, 2])
    init_x, P_x = expand_min_duration(init, P, D)
    assert init_x.shape == (4, K * D) and P_x.shape == (4, K * D, K * D)
    usable = (init > 0).repeat_interleave(D, -1)  # the phases of the owned features
    rows = P_x.sum(-1)
    torch.testing.assert_close(rows[usable], torch.ones_like(rows[usable]), atol=1e-14, rtol=0)
    le_x = le.repeat_interleave(D, -1)
    ll = forward_log_likelihood(le_x, init_x, P_x, lengths)
    decoded = viterbi(le_x, init_x, P_x, lengths)
    for b in range(4):
        L = int(lengths[b])
        joint = {path: _semi_markov_log_joint(le[b], init[b], P[b], D, path)
                 for path in itertools.product(range(K), repeat=L)}
        assert float(ll[b]) == pytest.approx(_logsumexp(joint.values()), abs=1e-10), b
        best = max(joint, key=joint.get)
        assert (decoded[b, :L] // D).tolist() == list(best), b
        assert (decoded[b, :L] % D).tolist() == _run_phases(best, D), b
    # D = 1 is the plain HMM
    same_init, same_P = expand_min_duration(init, P, 1)
    assert torch.equal(same_init, init) and torch.equal(same_P, P)


def test_min_duration_backward_sampling_frequencies_match_semi_markov_enumeration():
    """FFBS on the phase-expanded chain (D = 3, K = 2) draws label paths from the explicit-duration posterior:
    20000 draws against the enumerated posterior of the run-age loop, for a full-length and a padded sequence;
    every drawn phase is the run age (min(age - 1, D - 1)) and the padding repeats the last expanded state."""
    K, T, D = 2, 7, 3
    le, init, P, lengths = _semi_markov_batch(torch.Generator().manual_seed(107), K, T, [7, 5])
    init_x, P_x = expand_min_duration(init, P, D)
    le_x = le.repeat_interleave(D, -1)
    filtered, _ = forward_filter(le_x, init_x, P_x, lengths)
    n = 20000
    gen = torch.Generator().manual_seed(207)
    draws = backward_sample(filtered.repeat(n, 1, 1), P_x.repeat(n, 1, 1), lengths.repeat(n), gen).reshape(n, 2, T)
    for b in range(2):
        L = int(lengths[b])
        joint = {path: _semi_markov_log_joint(le[b], init[b], P[b], D, path)
                 for path in itertools.product(range(K), repeat=L)}
        z = _logsumexp(joint.values())
        labels = draws[:, b, :L] // D
        _assert_frequencies(labels, {p: math.exp(lp - z) for p, lp in joint.items()}, K, b)
        for path in torch.unique(labels, dim=0).tolist():
            rows = (labels == torch.tensor(path)).all(-1)
            assert (draws[rows, b, :L] % D == torch.tensor(_run_phases(path, D))).all(), (b, path)
        assert (draws[:, b, L:] == draws[:, b, L - 1 : L]).all()


def _min_duration_labelling(gen: torch.Generator, K: int, T: int, D: int) -> list[int]:
    """A random labelling whose runs last at least D samples (D plus a Geometric(0.4) number of extra samples, the
    last run cut by T); consecutive runs may repeat a state (a self-transition after D samples)."""
    out: list[int] = []
    while len(out) < T:
        state = int(torch.randint(0, K, (1,), generator=gen))
        u = float(torch.rand((), generator=gen, dtype=F64))
        n = D + int(math.log1p(-u) // math.log(0.6))  # D + Geometric failures, by inverse CDF
        out += [state] * n
    return out[:T]


def test_free_transition_counts_equal_a_run_age_loop_on_random_labellings():
    """transition_counts with free_transitions of the run-age phases (D = 1, 2, 3) against a plain loop that counts
    a move j -> k when it is a switch or when the run has already lasted D samples, within each sequence's length
    (padding labels arbitrary), for random labellings of the minimum-duration model with leading batch dimensions."""
    gen = torch.Generator().manual_seed(108)
    K, T = 4, 11
    for D in (1, 2, 3):
        states = torch.tensor([[_min_duration_labelling(gen, K, T, D) for _ in range(3)] for _ in range(2)])
        lengths = torch.randint(1, T + 1, (2, 3), generator=gen)
        phases = torch.tensor([[_run_phases(states[a, i].tolist(), D) for i in range(3)] for a in range(2)])
        got = transition_counts(states, lengths, K, free_transitions(phases, D))
        want = torch.zeros(2, 3, K, K, dtype=F64)
        for a, i in itertools.product(range(2), range(3)):
            age = 1
            for t in range(1, int(lengths[a, i])):
                j, k = int(states[a, i, t - 1]), int(states[a, i, t])
                if j != k or age >= D:
                    want[a, i, j, k] += 1
                age = age + 1 if j == k else 1
        torch.testing.assert_close(got, want, atol=0, rtol=0)
        if D == 1:
            torch.testing.assert_close(transition_counts(states, lengths, K), want, atol=0, rtol=0)


# ------------------------------------------------------------------ transition-row densities
def test_dirichlet_multinomial_equals_the_sequential_polya_urn():
    """dirichlet_multinomial_log_prob(transition_counts(s)) is the probability of the ordered transitions of s with
    the sticky rows integrated out: the product over the moves, in order, of the Polya urn predictive
    (a_jk + n_jk so far) / (A_j + n_j so far), a_jk = alpha + kappa delta_jk over the owned features (plain loop),
    for random labellings on random feature sets, batched hyperparameters included."""
    gen = torch.Generator().manual_seed(109)
    K, T, B = 4, 12, 5
    features = torch.rand(B, K, generator=gen) < 0.7
    features[:, 0] = True
    features[3] = torch.tensor([True, False, False, False])  # a single owned feature: every move has probability 1
    alphas = torch.tensor([0.3, 1.0, 2.5, 0.8, 4.0], dtype=F64)
    kappas = torch.tensor([0.0, 5.0, 1.5, 3.0, 10.0], dtype=F64)
    states = torch.zeros(B, T, dtype=torch.long)
    for b in range(B):
        own = torch.nonzero(features[b]).flatten()
        states[b] = own[torch.randint(0, len(own), (T,), generator=gen)]
    lengths = torch.tensor([12, 7, 1, 12, 9])
    counts = transition_counts(states, lengths, K)
    got = dirichlet_multinomial_log_prob(counts, features, alphas.view(B, 1, 1), kappas.view(B, 1, 1))
    for b in range(B):
        own = [k for k in range(K) if features[b, k]]
        n = {(j, k): 0 for j in own for k in own}
        ref = 0.0
        for t in range(1, int(lengths[b])):
            j, k = int(states[b, t - 1]), int(states[b, t])
            a_jk = float(alphas[b]) + float(kappas[b]) * (j == k)
            a_j = len(own) * float(alphas[b]) + float(kappas[b])
            ref += math.log((a_jk + n[j, k]) / (a_j + sum(n[j, m] for m in own)))
            n[j, k] += 1
        assert float(got[b]) == pytest.approx(ref, abs=1e-10), b
        single = dirichlet_multinomial_log_prob(counts[b], features[b], float(alphas[b]), float(kappas[b]))
        assert float(single) == pytest.approx(ref, abs=1e-10), b
    assert float(got[3]) == 0.0 and float(got[2]) == 0.0


def test_dirichlet_rows_log_density_against_a_naive_formula_with_degenerate_rows():
    """dirichlet_log_density_rows against the Dirichlet log density written out with math.lgamma, row by row:
    sum_j [lgamma(A_j) - sum_k lgamma(a_jk) + sum_k (a_jk - 1) log pi_jk] over the owned j, k, including a sequence
    that owns one feature (a point mass: log density 0) and one that owns none (0)."""
    gen = torch.Generator().manual_seed(110)
    K, alpha, kappa = 4, 0.6, 2.5
    features = torch.tensor([[True, True, False, True], [False, False, True, False], [False] * 4, [True] * 4])
    weights = torch.rand(4, K, K, generator=gen, dtype=F64) + 0.05
    pi = transition_matrix(weights, features)
    got = dirichlet_log_density_rows(pi, features, alpha, kappa)
    for b in range(4):
        own = [k for k in range(K) if features[b, k]]
        ref = 0.0
        for j in own:
            a = [alpha + kappa * (k == j) for k in own]
            ref += math.lgamma(sum(a)) - sum(math.lgamma(x) for x in a)
            ref += sum((x - 1.0) * math.log(float(pi[b, j, k])) for x, k in zip(a, own))
        assert float(got[b]) == pytest.approx(ref, abs=1e-10), b
    assert float(got[1]) == 0.0 and float(got[2]) == 0.0


def test_initial_distribution_and_transition_rows_of_unowned_features():
    """transition_matrix rows are the normalised owned weights (naive loop), rows and columns of unowned features
    are 0, a sequence without features gets all-zero rows (no NaN); initial_distribution is uniform on the owned
    features and 0 (not NaN) for a sequence that owns none."""
    gen = torch.Generator().manual_seed(111)
    K = 4
    features = torch.tensor([[True, False, True, True], [False] * 4, [True] * 4])
    weights = torch.rand(3, K, K, generator=gen, dtype=F64) + 0.1
    pi = transition_matrix(weights, features)
    init = initial_distribution(features, F64)
    assert not torch.isnan(pi).any() and not torch.isnan(init).any()
    for b in range(3):
        own = [k for k in range(K) if features[b, k]]
        for j in range(K):
            for k in range(K):
                want = 0.0
                if j in own and k in own:
                    want = float(weights[b, j, k]) / sum(float(weights[b, j, m]) for m in own)
                assert float(pi[b, j, k]) == pytest.approx(want, abs=1e-15)
            assert float(init[b, j]) == (1.0 / len(own) if j in own else 0.0)


# ------------------------------------------------------------------ Indian buffet process
def _buffet_class_probability(k10: int, k01: int, k11: int, mass: float, c: float) -> float:
    """p of the equivalence class of a 2-row IBP matrix with k10 columns owned by row 0 only, k01 by row 1 only and
    k11 by both, from the sequential buffet: row 0 takes Poisson(gamma) dishes, row 1 each of them with probability
    1 / (1 + c) (Binomial) and Poisson(gamma c / (1 + c)) new ones."""
    k0 = k10 + k11
    rate1 = mass * c / (1.0 + c)
    return (math.exp(-mass) * mass**k0 / math.factorial(k0) * math.comb(k0, k11) * (1.0 / (1.0 + c)) ** k11
            * (c / (1.0 + c)) ** k10 * math.exp(-rate1) * rate1**k01 / math.factorial(k01))


def _two_row_matrix(k10: int, k01: int, k11: int, pad: int = 0) -> torch.Tensor:
    cols = [[True, False]] * k10 + [[False, True]] * k01 + [[True, True]] * k11 + [[False, False]] * pad
    return torch.tensor(cols, dtype=torch.bool).reshape(-1, 2).T.contiguous()


def test_ibp_log_prior_equals_the_sequential_buffet_for_two_rows():
    """ibp_log_prior of every 2-row class with up to 4 columns of each pattern equals the probability of the class
    under the sequential buffet (Poisson x Binomial x Poisson, closed form), for two (gamma, c); unowned columns
    and the column order do not matter."""
    for mass, c in ((1.7, 0.8), (0.6, 3.0)):
        for k10, k01, k11 in itertools.product(range(5), repeat=3):
            F = _two_row_matrix(k10, k01, k11, pad=2)
            want = math.log(_buffet_class_probability(k10, k01, k11, mass, c))
            got = float(ibp_log_prior(F, mass, c))
            assert got == pytest.approx(want, abs=1e-10), (mass, c, k10, k01, k11)
            if F.shape[1] > 1:
                perm = torch.randperm(F.shape[1], generator=torch.Generator().manual_seed(k10 + 5 * k01 + 25 * k11))
                assert float(ibp_log_prior(F[:, perm], mass, c)) == pytest.approx(got, abs=1e-12)


def test_ibp_log_prior_sums_to_one_over_three_row_classes():
    """The class probabilities of the two-parameter IBP sum to 1: over all 3-row classes with up to 3 columns of each
    of the 7 nonzero patterns (4^7 classes, one batched call), the sum of exp(ibp_log_prior) is 1 up to the truncated
    tail (gamma = 0.3, c = 1.3: every pattern's count is Poisson with mean below 0.12, the tail is below 1e-4)."""
    mass, c, cap = 0.3, 1.3, 3
    patterns = [p for p in itertools.product([False, True], repeat=3) if any(p)]
    width = len(patterns) * cap
    mats = []
    for counts in itertools.product(range(cap + 1), repeat=len(patterns)):
        cols = [p for p, n in zip(patterns, counts) for _ in range(n)]
        cols += [(False, False, False)] * (width - len(cols))
        mats.append(cols)
    F = torch.tensor(mats, dtype=torch.bool).transpose(1, 2)  # (classes, 3, width)
    total = float(torch.logsumexp(ibp_log_prior(F, mass, c), 0).exp())
    assert total == pytest.approx(1.0, abs=1e-4) and total <= 1.0 + 1e-12


def test_sample_ibp_class_frequencies_match_the_buffet_probabilities():
    """sample_ibp(N = 2): frequencies of the drawn classes (k10, k01, k11) over 20000 draws against their closed-form
    probabilities (which ibp_log_prior reproduces, test above), 5 standard errors plus 5 / n per class."""
    gen = torch.Generator().manual_seed(112)
    mass, c, n = 1.2, 0.7, 20000
    counts: dict[tuple[int, int, int], int] = {}
    for _ in range(n):
        F = sample_ibp(2, mass, c, gen)
        key = (int((F[0] & ~F[1]).sum()), int((~F[0] & F[1]).sum()), int((F[0] & F[1]).sum()))
        counts[key] = counts.get(key, 0) + 1
    for key in itertools.product(range(4), repeat=3):
        p = _buffet_class_probability(*key, mass, c)
        assert abs(counts.get(key, 0) / n - p) <= 5.0 * math.sqrt(p * (1.0 - p) / n) + 5.0 / n, (key, p)


@pytest.mark.parametrize("switch", [1e-305, 1e-310])
def test_forward_exact_when_the_last_sample_has_a_tiny_mass(switch):
    """A switch of probability 1e-305 (a normal number, above the recursion's clamp) or 1e-310 (subnormal, clamped)
    forced by the emissions at the very last sample of the padded tensor, where no later step can carry a clamped
    remainder: the log evidence is exact (enumeration: log of the switch's probability), from forward_log_likelihood
    and forward_filter, with and without a padding column after it. (Before the fix the subnormal case recorded the
    clamped mass as the smallest normal number: too high by log(tiny / mass), about 5.4 nats.)"""
    T = 4
    le = torch.full((1, T, 2), -1000.0, dtype=F64)
    le[:, : T - 1, 0] = 0.0
    le[:, T - 1, 1] = 0.0
    P = torch.tensor([[[1 - switch, switch], [switch, 1 - switch]]], dtype=F64)
    init = torch.tensor([[1.0, 0.0]], dtype=F64)
    lengths = torch.tensor([T])
    want = _logsumexp(_enumerate(le[0], init[0], P[0], T).values())
    assert want == pytest.approx(math.log(switch), abs=1e-9)
    assert float(forward_log_likelihood(le, init, P, lengths)[0]) == pytest.approx(want, abs=1e-9)
    assert float(forward_filter(le, init, P, lengths)[1][0]) == pytest.approx(want, abs=1e-9)
    padded = torch.cat([le, torch.zeros(1, 1, 2, dtype=F64)], 1)  # one padding column carries the rest
    assert float(forward_log_likelihood(padded, init, P, lengths)[0]) == pytest.approx(want, abs=1e-9)


# ------------------------------------------------------------------ the recursion's numerical edge cases
def test_forward_finite_when_the_only_possible_state_is_800_nats_behind():
    """Two absorbing states (P = I), sample 0 favours state 0 and sample 1 state 1, each by 800 nats: both paths
    cost 800 nats, the log evidence is -800 (enumeration), not -inf; the same through the phase-expanded chain of a
    minimum duration D = 3 (forced moves) against the semi-Markov enumeration, whose filtered marginals must be the
    enumerated ones (before the fix the scaled emissions underflowed: -inf and all-zero filtered rows). In the same
    batch an ordinary row keeps its value and a row that no state can explain stays -inf."""
    le = torch.tensor([[[0.0, -800.0], [-800.0, 0.0]]], dtype=F64)
    init = torch.tensor([[0.5, 0.5]], dtype=F64)
    P = torch.eye(2, dtype=F64).unsqueeze(0)
    want = _logsumexp(_enumerate(le[0], init[0], P[0], 2).values())
    assert want == pytest.approx(-800.0, abs=1e-9)
    assert float(forward_log_likelihood(le, init, P, torch.tensor([2]))[0]) == pytest.approx(want, abs=1e-9)

    D, T = 3, 3
    pi = torch.tensor([[0.6, 0.4], [0.3, 0.7]], dtype=F64)
    rows = torch.tensor([[[0.0, -800.0], [-800.0, 0.0], [0.0, 0.0]],  # only (0, 0, 0) or (1, 1, 1), 800 nats each
                         [[0.0, -1.0], [-0.5, -2.0], [-1.0, 0.0]],  # ordinary
                         [[0.0, -math.inf], [-math.inf, 0.0], [0.0, 0.0]]], dtype=F64)  # nothing explains it
    init2 = torch.tensor([[0.5, 0.5]], dtype=F64).expand(3, 2)
    ei, eP = expand_min_duration(init2, pi.expand(3, 2, 2), D)
    ele = rows.repeat_interleave(D, -1)
    lengths = torch.full((3,), T)
    filtered, ll = forward_filter(ele, ei, eP, lengths)
    for b in range(3):
        joint = {path: _semi_markov_log_joint(rows[b], init2[b], pi, D, path)
                 for path in itertools.product(range(2), repeat=T)}
        assert float(ll[b]) == pytest.approx(_logsumexp(joint.values()), abs=1e-9)
        assert float(forward_log_likelihood(ele, ei, eP, lengths)[b]) == pytest.approx(float(ll[b]), abs=1e-12)
    assert float(ll[0]) == pytest.approx(-800.0, abs=1e-9) and ll[2] == -math.inf  # two paths of 1/2 e^-800
    # filtered p(phase-expanded state at t | x_0..t) of the 800-nat row: all of it on the run of one label
    for t in range(T):
        labels = filtered[0, t].view(2, D).sum(-1)
        joint_t = [_logsumexp(_semi_markov_log_joint(rows[0, : t + 1], init2[0], pi, D, path)
                              for path in itertools.product(range(2), repeat=t + 1) if path[-1] == k) for k in range(2)]
        ref = torch.tensor(joint_t, dtype=F64)
        torch.testing.assert_close(labels, torch.softmax(ref, 0), atol=1e-9, rtol=0)


def test_backward_draws_possible_paths_when_the_only_possible_state_is_800_nats_behind():
    """The 800-nat case of the test above, D = 3: every FFBS draw (ffbs) is one of the two possible paths, labels
    (0, 0, 0) or (1, 1, 1) with phases (0, 1, 2), in the enumerated proportions 1/2 : 1/2 (5 standard errors); in
    probabilities alone (forward_filter, backward_sample) the draws ending in label 1 find no predecessor
    (p(s_0 = 1 | x_0) = e^-800 underflows) and give the impossible path (5, 4, 5). An ordinary row drawn in the same
    batch gets the probability-space draws: the same as backward_sample's with the same generator."""
    D, T = 3, 3
    pi = torch.tensor([[0.6, 0.4], [0.3, 0.7]], dtype=F64)
    rows = torch.tensor([[[0.0, -800.0], [-800.0, 0.0], [0.0, 0.0]]], dtype=F64)
    ei, eP = expand_min_duration(torch.tensor([[0.5, 0.5]], dtype=F64), pi[None], D)
    lengths = torch.tensor([T])
    n = 4000
    ele = rows.repeat_interleave(D, -1).repeat(n, 1, 1)
    filtered, _ = forward_filter(ele, ei.repeat(n, 1), eP.repeat(n, 1, 1), lengths.repeat(n))
    plain = backward_sample(filtered, eP.repeat(n, 1, 1), lengths.repeat(n), torch.Generator().manual_seed(3))
    assert bool((plain[:, 0] == 2 * D - 1).any())  # impossible paths (5, 4, 5): no run starts in phase 2
    draws = ffbs(ele, ei.repeat(n, 1), eP.repeat(n, 1, 1), lengths.repeat(n), torch.Generator().manual_seed(3))
    labels = draws // D
    assert bool(((labels == 0).all(1) | (labels == 1).all(1)).all())  # one run each
    assert bool((draws % D == torch.arange(T)).all())  # its phases 0, 1, 2
    share = float((labels[:, 0] == 1).double().mean())
    assert abs(share - 0.5) <= 5.0 * math.sqrt(0.25 / n)
    # an ordinary row: ffbs gives backward_sample's draws
    ordinary = torch.tensor([[[0.0, -1.0], [-0.5, -2.0], [-1.0, 0.0]]], dtype=F64).repeat_interleave(D, -1)
    f2, _ = forward_filter(ordinary, ei, eP, lengths)
    ref = backward_sample(f2, eP, lengths, torch.Generator().manual_seed(5))
    assert torch.equal(ffbs(ordinary, ei, eP, lengths, torch.Generator().manual_seed(5)), ref)
