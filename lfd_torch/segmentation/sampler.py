"""MCMC for the Beta-process Gaussian-emission HMM (BP-GM-HMM, paper Sec. III-A).

Notation:
    C  independent chains, N sequences, T padded length (after optional subsampling), d state dimension
    K  feature slots shared by all chains (grown and compacted as features are born and die)
    features  (C, N, K) bool   f_i per chain
    field     (C, K, d, d + 1), noise (C, K, d, d)   direction-field emission of each feature (:mod:`.field`)
    weights   (C, N, K, K)      sticky transition weights eta (paper eq. 3, see transitions.py)
    states    (C, N, T) long    hidden state sequences

One sweep (Fox, Hughes, Sudderth & Jordan 2014, AOAS 8(3); state-sequence marginalised feature moves):
    1. shared features: for every sequence i and every feature k owned by another sequence, a Metropolis-Hastings
       flip of f_ik scored by p(x^(i) | f_i, eta^(i), theta) with the states summed out (forward algorithm) and the
       IBP conditional m_{-i,k} / (c + N - 1);
    2. unique features: reversible-jump birth / death of a feature owned by sequence i alone. A birth draws theta* from
       the NIW posterior of a random window W of x^(i) (mixed with the prior); the window is an auxiliary variable
       that the reverse (death) move redraws from r(W | theta), the windows weighted by their fit to theta. This keeps
       the data-driven proposal exactly reversible: the ratio carries r(W | theta*) / (p(W) q(theta* | W));
    3. blocked Gibbs draw of every state sequence by forward filtering / backward sampling;
    4. conjugate draws of the emissions (NIW) and transition weights (Dirichlet/Gamma);
    5. optionally, gamma | F (conjugate Gamma) and alpha, kappa (random-walk Metropolis on their logarithm, given
       pi), then the auxiliary transition weights (outside the owned blocks, row totals) redrawn under the new values.
All moves are batched over chains. Move 1 computes the likelihoods of all flips of a block of features for all
sequences in one forward pass and then decides sequence by sequence (the IBP couples the rows through m_{-i,k});
move 2 is batched over sequences too (unique features of different sequences do not interact); move 3 over chains
and sequences. The chain with the best joint log probability (over the samples after burn-in) is returned.

Which sample (``selection``), among the sweeps of every chain after burn-in. :func:`lfd_torch.segmentation.segment`
defaults to "map" with the position term, straight states, the dwell term and learned gamma, alpha and kappa (move
5; sections below; the sampler class itself to "joint" with directions alone and fixed values).
    "joint": the highest joint log probability. Its collapsed score (every continuous parameter integrated
        out: MNIW evidence of each state's directions, Dirichlet-multinomial sticky transitions, IBP prior) is
        reported too.
    "collapsed": the highest collapsed score. Measured (``experiments/segmentation_studies.md``,
        "The sampler's options, measured"): more seed-stable than "joint" where the evidence is clear, but it
        under-segments single demonstrations under this prior.
    "modal": per sequence the number of runs (pieces) most frequent over all kept samples of all chains (the
        posterior mode of each demonstration's step count, ties to the smaller), and among the samples with those
        counts (or, if none has all of them, with most of them) the highest joint log probability: a Bayes estimate
        of the count under 0-1 loss, which averages over the posterior instead of following its best draw.
        Measured: it shares the collapsed choice's bias (same file).
    "map": a local mode of the collapsed posterior p(s, F | u, z): from every chain's best collapsed sample, a
        coordinate ascent of the collapsed score (Viterbi relabelling under the posterior-mean parameters, iterated
        until it stops raising the score before any other move is tried; merge two states, alone or followed by a
        relabelling; reassign one state's runs in one sequence to another or a new state; as a last resort, split
        one state by cutting its runs in halves, then relabel (in the last ascent, the best such split also
        polished by switch moves); :meth:`_Run._climb_to_mode`), then from the best of the chains' results the same
        ascent with one more move (move one switch of one sequence, or remove one run and place the switch between
        its neighbours), returned with the posterior-mean fields of its labelling. The merge is the move of
        split-merge samplers for the BP-HMM (Hughes, Fox & Sudderth 2012): it leaves a mode in which one
        step is carried by two states, which the one-feature-at-a-time moves cannot join. Taken greedily, as a mode
        search, chains that reached one basin end at one labelling. Alone it under-segments single
        demonstrations (a field across a mild corner beats two); the position term, straight states and the dwell
        term below are what make it the default (measured: same file).

Why the tolerance sigma_u (``direction_noise``) is set, not learned. A tolerance shared by all states and learned
from the data (type-II maximum likelihood, or a hyperprior) would be the principled cure for "no single tolerance
gives both", but the data do not pick a usable value: the collapsed score of the mode found rises monotonically
as sigma_u falls, on LASA and on the synthetic demonstrations alike, and the tight tolerance breaks LASA's human
curves into steps that change with the seed (measured: ``experiments/segmentation_studies.md``, "The sampler's options,
measured"). The tolerance is a statement of what one step is: directions within about 0.2 rad (RMS) of one affine
field. What separates a synthetic corner from a LASA curve is how the direction leaves the field: at a corner it
jumps, along a human curve it drifts. A tolerance that is a smooth process along the path charges a jump and not a
drift: "Correlated tolerance" below.

Correlated tolerance (``tolerance_correlation`` rho;
:func:`~lfd_torch.segmentation.field.correlated_tolerance_observations`, the derivation there). Within a run the
deviation of the direction from its state's field is AR(1), eta_t = rho
eta_(t-1) + xi_t, with a fresh stationary deviation of scale sigma at the run's first sample, plus white noise
(the propagated velocity noise and a floor tau^2, in units of the innovations' covariance Psi_k, prior mean
(1 - rho^2) sigma^2 I, so that every factor stays a conjugate MNIW regression). A scalar Kalman filter of the
deviation factors a run's density into one-step predictions: a sample of age a in its run (0 at its first
sample) is the regression of u_t minus the filter's prediction from the run's earlier directions on z_t minus the
same combination of their regressors, with weight 1 / S_t (its predictive variance in units of Psi_k); exact for
runs up to :data:`~lfd_torch.segmentation.field.TOLERANCE_MEMORY` + 1 grid points, beyond that the filter starts that
many points back. Ages depend on the labelling, so the collapsed score sees every sample in the view of its age
(:meth:`_Run._score_view`; the views are computed once per tolerance and gathered, :meth:`_Run._stats`), the shift
and reassignment scores see it through the candidates' labels, and the Viterbi relabelling (a proposal, confirmed by
the score) gives phase 0 of the explicit-duration states the age-0 view and later phases the oldest one (so it needs
a minimum duration D >= 2). The filter predicts through a direction that carries no information (a pause: w_t ~ 0),
so a corner taken at rest is still a jump of the deviation; the Prais-Winsten form built first (commit 58b575a),
which conditioned on the last noisy direction alone, let a run's deviation restart there and absorbed such corners.
The Student t (``robust_dof``) stays, for the directions no field explains (the chord across a corner,
:mod:`.field`), which a tight tolerance makes costly. rho = 0, sigma = ``direction_noise`` and tau = 0 is the white
emission, the default (``tolerance_correlation=0``), and its scores
are unchanged. The tolerance acts through the collapsed score, i.e. the map search and ``selection="collapsed"``;
the chains sample the white model and only seed the search; the fields returned with the result are the default
white tolerance's posterior means of the labelling (the change-point refinement of :mod:`.segmentation` uses
them). ``tolerance_correlation=None`` learns (rho, sigma, tau) with the labelling: type-II maximum likelihood over
:data:`TOLERANCES` (65 white and AR settings, the grid ``experiments/diagnose_tolerance.py`` scores exactly; a
uniform prior), alternated with the map search from the white map search's mode until the tolerance stays, i.e. a
coordinate ascent of the collapsed score in (s, F, rho, sigma, tau) (:meth:`_Run._learn_tolerance`); the scores of
one labelling under two tolerances are densities of the same directions, so they compare. Measured: more switches
found than the white default, but not seed-stable on LASA Multi_Models_1 and over the time budget on
Multi_Models_3, so an option (``experiments/segmentation_variants.py``; details in
``experiments/segmentation_studies.md``).

Position (``position_weight`` tau; NIW kernels of :mod:`lfd_torch.gmm`). An affine direction field is defined over
the whole space, so with directions alone one state may carry two pieces far apart whose directions one field
fits (on LASA Multi_Models_4 one state served the first legs of both routes, the routes were grouped as one and
a step's attractor, the mean of end points on both routes, fell 26 % of the data span away from either path).
The paper's emission is a Gaussian on the state because it "captures spatial information"; here it is the
product of the direction field and a tempered Gaussian on the standardised position,

    p(u_t, x_t | s_t = k) = t(u_t; B_k z_t, Psi_k / w_t) N(x~_t; mu_k, Sigma_k)^tau,   (mu_k, Sigma_k) ~ NIW,

NIW prior from the standardised positions (:func:`~lfd_torch.gmm.niw_prior_from_data`, expected state covariance
0.05 of the data's variance per axis). Why tempered: the positions of a path are not independent draws around a
centre; along a run they are the integral of its directions, which the field already scores, so counting every
grid point as an independent position observation would double count them, and a Gaussian would then gain about
log 2 nats per sample by splitting a long leg in two (:mod:`.field`). The new spatial information is about one
point per shortest step, so tau = 1 / D by default (``position_weight=None``, D the minimum duration in grid
samples): a leg of n grid points counts as n / D position observations. Tempering keeps every update
conjugate (the NIW statistics are weighted by tau; the collapsed score adds the tempered NIW evidence of each
state's positions, the joint log probability the NIW density of (mu_k, Sigma_k)); births draw (mu*, Sigma*)
from the tempered posterior of the same window as the field. ``position_weight=0`` is the direction-only model
(nothing is drawn for the positions; the sampler's default). Not neutral about cuts: if only the variance along
a leg traversed at an even pace mattered, cutting it in two would gain (n / D) log 2 nats for a leg of n grid
points; a leg's perpendicular spread is far below the prior's expected covariance and the second state pays its
own normalisation, so the measured gain is -1.1 to -0.8 nats on legs of 10-15 grid points, 0.1 at 30 and 3.2-3.8 at
60 (tau 1/3; ``experiments/diagnose_position.py``, table ``diagnose_position.json``): about neutral or a charge on the
80-point grid, a pull toward cuts only on long legs. Its weight, and the mixture form ``position_mixture=True``
(each state's tempered Gaussian times its occupancy pi_ik of sequence i, pi_i integrated out under a Chinese
restaurant process of concentration 1 over the tempered counts x_ik = tau n_ik: per state sum_i log Gamma(x_ik),
plus the labelling-free -sum_i log Gamma(1 + tau n_i); :meth:`_Run._occupancy_terms`; the Viterbi proposal adds tau
log of the predictive occupancies; it acts through the collapsed score), move which mild corners are found, both
ways; the mixture charges a cut about tau n log 2 nats more. A spatial term neutral about a cut along a leg of any
length is open (measured: ``experiments/segmentation_studies.md``).

Straight states (``straight_weight`` rho; :func:`~lfd_torch.segmentation.field.field_mixture_evidence`). Under the
affine prior alone every state pays the Occam factor of its d x d slope entries, about d^2 / 2 log(n s^2 / sigma^2)
nats (n samples, s the spread of their positions): a straight leg, whose field is its offset alone, pays it for
parameters it does not use, so two straight legs pay it twice, while one field bent across a mild corner pays it
once; that is the under-segmentation of single demonstrations described under "map". The collapsed score can
instead use the spike-and-slab prior that a reviewer of the method would write down for "a step is a straight or
a curved motion": with probability rho the slope is exactly 0 (a constant direction field, MNIW on the offset
regressor alone), else it is the affine MNIW, so a state's evidence is rho p(u | straight) + (1 - rho)
p(u | affine) and its posterior-mean field the two posterior means weighted by P(straight | u) (used by the
Viterbi relabelling and the Student-t profile). The MCMC moves still sample the affine model: the mixture acts
through the collapsed score, i.e. in ``selection="map"`` (whose chains only seed the mode search) and
``"collapsed"``. rho = 0.5 says nothing about which kind is more common. Measured: it cuts straight legs met at speed
by a single demonstration and keeps LASA seed-stable (``experiments/segmentation_studies.md``).

Slope scale (``slope_scale`` s1, ``slope_scale_mix`` s2; :func:`~lfd_torch.segmentation.field.field_prior`). The
MNIW prior gives a field's slope entries a standard deviation of s1 per radius of the data: s1 = 1 lets a field
turn the direction by about a radian per radius, a tighter curve (the scoop's hook, about 7) pays for its slope
and a gentle one pays a small Occam factor. How tightly a step curves is not known in advance, so with s2 > 0 the
collapsed score's affine slab is the equal mixture of the two scales, p(u | z, affine) = (p(u | z, s1) +
p(u | z, s2)) / 2, both exact MNIW evidences, the posterior-mean field the two posterior means weighted by their
posterior probabilities (:func:`~lfd_torch.segmentation.field.field_mixture_evidence`); the chains sample s1 alone.
Measured (``experiments/segmentation_variants.py``): s2 = 3 gains two of the 280 synthetic cases and loses none,
keeps every LASA demonstration's count on 10 of 10 seeds, and changes nothing on the held-out families (one case
gained, one lost); s1 = 3 alone gains more (8 of the 280 and 9 of the 80 held-out cases, mostly straight legs) but
loses 3 single curved demonstrations and 3 held-out cases with four demonstrations: a shift of the prior toward
straight fields, not a better model of both.

Rotation fields (``rotation_weight`` r; :func:`~lfd_torch.segmentation.field.rotation_field_evidence`). Every
change of the slope prior above moves cases between merged and split curves, because a looser slope serves a merge
as much as a true arc. A circular arc is a rigid rotation field, u = W x~ + b with W skew-symmetric: d (d - 1) / 2
rates and d offsets (3 + 3 in 3-D) against the affine field's 12, and one rate carries the turn where the affine
slope spends two entries (so the prior charges a tight circle once, not twice). Two arcs meeting at a corner, or an
arc and a straight leg, are no single rotation. So with r > 0 the collapsed score's slab is the mixture (1 - r)
affine + r rotation (a normal-inverse-gamma regression with an isotropic tolerance, exact evidence), which raises
the evidence of a true arc and not that of a merge; r = 0.5 says nothing about which kind is more common. The
chains sample the affine model; the mixture acts through the collapsed score. Measured
(``experiments/segmentation_variants.py``, row "rotation fields"): r = 0.5 gains 4 of the 280 synthetic cases and
loses none, keeps every LASA demonstration's count on 10 of 10 seeds, but loses 3 held-out cases and gains 1 (the
three: single demonstrations of straight legs whose rounded corner is merged, a wide fillet and its legs being close
to one arc), and LASA takes 5.4 s median and 9.8 s at the slowest against 4.0 / 6.5 s, near the 10 s budget.

Block emission (``block_emission``; :mod:`.blocks`). The direction emission sees one local slope per grid point
and treats them as independent, so a straight leg's direction is known to about sigma_dir / sqrt(n) from n grid
points, where a line through its samples knows it n / 3 times better. A known-count oracle that fits lines finds the
mild corners and the scoop's hook that the sampler merges (``experiments/oracle_switches.py``). With
``block_emission`` the collapsed score replaces the direction emission (its evidence, Student-t profile and
reliability Jacobian) by the Gaussian evidence of the increments of the block means. A straight state is a line
with no tolerance (each demonstration its own small turn); a curved state is the affine field with the tolerance
``block_tolerance`` as a random walk of the position (each demonstration its own offset); an increment across a
switch is a free displacement. Each state is straight or curved as the direction emission's spike-and-slab
posterior says, then switched one state at a time while that raises the evidence plus the components' log prior (a
profile over the components). With ``slope_scale_mix`` s2 > 0 a curved state is curved at ``slope_scale`` or at s2
(prior 1/4 each, straight 1/2), profiled the same way: the block evidence does not factor over the states (a
demonstration's own coefficients and its blocks' shared noise couple them), so the equal mixture of the
direction emission would be a sum over 2^K combinations.
The chains sample the direction model, which only seeds the search and proposes its relabellings; the shift and
reassignment moves rank their candidates by the block evidence itself (each candidate changes one sequence, whose
share alone is recomputed, the components held at the current labelling's, :meth:`_Run._block_deltas`), where ranking
them by the direction emission's terms left LASA Multi_Models_1 at modes 9-28 nats below the best one on 4 of 10
seeds (one-off runs; ``experiments/segmentation_studies.md``, "Block emission: a search scored by the block
evidence"). For the same reason the shift move also proposes births of a switch (:meth:`_Run._birth_spans`: a run's end
or start given to a state that follows or precedes it in another demonstration, or to a new state): the Viterbi
relabelling, the only other source of new switches, places them under the direction emission's fields (LASA
Multi_Models_1: demonstration 6 in one step on 3 of 10 seeds, 6-10 nats below the best two-step mode;
two steps on 10 of 10 with births). The tempered
position term goes with it in its mixture form (``position_mixture``; :func:`~lfd_torch.segmentation.segment`'s
default pair): as plain Gaussians the position term's gain from cutting a long leg cut the scoop's transfer arc twice
more on its four-demonstration case 2, and without any position term LASA Multi_Models_4's two routes fall into one.
Measured: rows "block emission" and "defaults" of ``experiments/segmentation_variants.py`` and
``experiments/segmentation_studies.md``, "Block emission" and "Block emission with positions as a mixture over
space".

Dwell (``dwell``, :mod:`lfd_torch.segmentation.dwell`, the derivation there). The path-length grid hides how long
the demonstrator spends somewhere, and a pause is where one subtask ends and the next begins. The model also
explains the log time between grid points, c_t = mu + delta b_t + noise, b_t = 1 at the first point of a run, with
(mu, delta, sigma^2) ~ NIG learned with the states: an emission of phase 0 of the explicit-duration states, so it
enters the forward pass, FFBS, the Gibbs draw, the joint log probability, the collapsed score and the map search
exactly. Nothing fixes how much a pause counts: where the data pause at their corners delta is ~2 (a start at
speed then pays about delta^2 / (2 sigma^2) ~ 10 nats); at constant speed ~0.4 (only the dip of the estimated
speed where a velocity window straddles a corner). It is what finds the corners at which a demonstrator pauses
(measured: ``experiments/segmentation_studies.md``).

Demonstrations' own offsets (``demo_offset`` v; :func:`~lfd_torch.segmentation.field.demo_offset_statistics`). Two
demonstrations of one step are two instances of one primitive: their legs are a little displaced and turned against
each other (the synthetic generators jitter every corner by 2 % of the shorter leg), so with several demonstrations
one field per state must absorb their differences in its tolerance, and a tolerance tight enough to see a mild
corner then cuts a curved leg shared by four demonstrations once more. In the collapsed score each demonstration i
may add its own offset Delta_ik ~ N(0, v Psi_k) to the field of state k, B_ik = B_k + Delta_ik e_p^T (e_p the offset
regressor): a constant turn of the directions of a straight leg, a displacement of the centre of an arc. Integrated
out, it leaves the MNIW regression on B_k with the same Psi_k and a rank-one correction of every sequence's
statistics (Woodbury), so the score stays exact and conjugate; with one demonstration it only widens the offset's
prior. The sampler's own moves keep one field per state. Measured: with a tight tolerance it keeps a curved leg
shared by several demonstrations in one step, but LASA is not seed-stable at that tolerance and the held-out
families lose, so v = 0 is the default (``experiments/segmentation_variants.py``,
``experiments/segmentation_studies.md``).

Subsampling (done by :func:`lfd_torch.segmentation.segment`, ``max_samples``) bounds T: the forward recursion is
sequential in T, so the cost of a sweep is about (number of feature blocks + 2) x T small batched operations.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, fields

import numpy as np
import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.utils import check_float, check_generator, check_int
from lfd_torch.gmm import (
    NIWPrior,
    gaussian_log_density,
    niw_log_density,
    niw_log_marginal_likelihood,
    niw_posterior,
    niw_prior_from_data,
    sample_gamma,
    sample_niw,
    sufficient_statistics,
)
from lfd_torch.segmentation.field import (
    FieldPrior,
    correlated_tolerance_observations,
    correlated_tolerance_prior,
    demo_offset_statistics,
    field_log_density,
    field_log_likelihood,
    field_mixture_evidence,
    field_mixture_posterior_mean,
    field_observations,
    field_posterior,
    field_prior,
    field_statistics,
    sample_field,
)
from lfd_torch.segmentation.dwell import (
    PACE_RATIOS,
    dwell_evidence,
    dwell_log_likelihood,
    dwell_log_prob,
    dwell_mask,
    dwell_posterior,
    dwell_start,
    dwell_prior,
    posterior_summary,
)
from lfd_torch.segmentation.blocks import (
    DEMO_SPREAD,
    BlockMeans,
    BlockTerms,
    block_sequence_terms,
    check_block_variances,
    combine_block_terms,
    state_slots,
)
from lfd_torch.segmentation.features import ibp_log_prior, shared_log_odds, unique_feature_rate
from lfd_torch.segmentation.states import _ffbs, _forward_log_likelihood, used_states, viterbi
from lfd_torch.segmentation.transitions import (
    dirichlet_log_density_rows,
    dirichlet_multinomial_log_prob,
    initial_distribution,
    sample_transition_weights_posterior,
    sample_transition_weights_prior,
    expand_min_duration,
    free_transitions,
    transition_counts,
    transition_matrix,
)

__all__ = ["SamplerResult", "BetaProcessHMMSampler", "HYPERPARAMETER_RANGES", "check_hyperparameters"]

_NEG_INF = float("-inf")
_LOOKAHEAD = 4  # map search: merges tried with a relabelling after them when no merge alone raises the score
_SHIFT_CHUNK = 512  # map search: shift candidates scored per batch (memory ~ chunk x N T x 3)
_BIRTH_FRACTIONS = (1 / 3, 1 / 2, 2 / 3)  # map search, shared births: where the runs next to a state are cut
_POLISH_STEPS = 3  # map search: most shift moves that polish the best split (each ~0.1 s on 7 LASA demonstrations)
_SETTLE_STEPS = 10  # map search: most relabellings that settle the best look-ahead merge (each ~10 ms on 7 LASA demos)
_POSITION_SCALE = 0.05  # prior expected covariance of a state's positions / the data's variance, per axis
_SHARE_CACHE = 20_000  # block emission: distinct sequence shares kept (_sequence_terms); LASA Multi_Models_3: +130 MB peak
# block emission: rounds of one-state component switches (each K evaluations), until none raises the evidence; a
# cap of 2 left a labelling with three states started straight scored 133 thousand nats low (the scooping
# demonstration, seed 4), which hid the stage switch at its pause from the map search
_COMPONENT_ROUNDS = 64
_BLOCK = 2  # features whose flips share one batched forward pass (2^2 - 1 = 3 variants per sequence)
# The sampler runs in inference mode. Diagnostics and tests that keep a run (``_Run``) to call its methods afterwards
# turn it off while they capture runs, so that the run's state is made of normal tensors (an inference tensor cannot
# be updated in place outside inference mode); the results are the same.
_INFERENCE_MODE = True


@dataclass(frozen=True, eq=False)
class SamplerResult:
    """The best sample of a BP-GM-HMM run.

    Attributes:
        states: (N, T) long state labels on the sampled grid (padding repeats the last valid label); labels index
            the K features below.
        lengths: (N,) valid samples per sequence on the sampled grid.
        features: (N, K) bool feature matrix F.
        field: (K, d, d + 1) direction field of every state on the standardised positions (:mod:`.field`).
        noise: (K, d, d) direction noise covariance of every state.
        centre: (d,) and radius: () standardisation of the positions, x~ = (x - centre) / radius.
        log_prob: joint log probability of the returned sample (the sampled fields, noise and transition weights
            included; with ``selection="joint"`` the chain and sweep with the highest one is returned).
        collapsed_log_prob: log p(u, s, F | z) of the returned (s, F), every continuous parameter integrated out
            (:meth:`_Run._collapsed_score`): comparable across samples with different numbers of states (the
            criterion of ``selection="collapsed"``).
        trace: (C, n_iterations) joint log probability of every chain after every sweep.
        n_features_trace: (C, n_iterations) number of features owned by at least one sequence.
        chain: index of the chain the sample comes from.
        hyperparameters: final (mass, transition_concentration, stickiness) of that chain.
        acceptance: acceptance rates of the moves {"shared", "birth", "death"}.
        switch_scores: with the block emission, per sequence and switch of ``states`` (in time order), (j0, scores):
            the collapsed score (:meth:`_Run._switch_scores`) of the labelling with that switch's second run
            starting at grid point j0 + w instead, w = 0 .. W - 1 (W,), every run at least the minimum duration
            long; None without the block emission.
    """

    states: Tensor
    lengths: Tensor
    features: Tensor
    field: Tensor
    noise: Tensor
    centre: Tensor
    radius: Tensor
    log_prob: float
    trace: Tensor
    n_features_trace: Tensor
    chain: int
    collapsed_log_prob: float = math.nan
    hyperparameters: dict[str, float] = field(default_factory=dict)
    acceptance: dict[str, float] = field(default_factory=dict)
    switch_scores: list[list[tuple[int, Tensor]]] | None = None

    @property
    def n_features(self) -> int:
        return self.field.shape[0]


#: Accepted range of every sampler hyperparameter: (kind, low, high, low inclusive, high inclusive). The upper
#: bounds keep the cost finite where a hyperparameter scales it (issue 11); measured on 3 sequences x 120 samples,
#: 2-D, one thread: n_initial_features 4 / 32 / 64 -> 1.4 / 3.4 / 19.6 s (the forward pass is O(T (K D)^2) in the
#: number of features K, and the shared moves run K / 2 of them per sweep); feature_mass 2 / 1e3 / 1e6 -> 1.4 / 3.5
#: / 11.8 s with 5 / 23 / 70 features (every birth is accepted once gamma is large); n_chains 4 / 32 -> 1.4 / 3.2 s
#: (batched); n_iterations is linear (about 35 ms per sweep there).
HYPERPARAMETER_RANGES: dict[str, tuple[type, float, float, bool, bool]] = {
    "feature_mass": (float, 0.0, 100.0, False, True),
    "feature_concentration": (float, 0.0, 1e3, False, True),
    "transition_concentration": (float, 0.0, 1e6, False, True),
    "stickiness": (float, 0.0, 1e6, True, True),
    "direction_noise": (float, 0.0, 2.0, False, True),
    "extra_dof": (float, 0.0, 1e6, False, True),
    "robust_dof": (float, 0.0, 1e6, False, True),
    "position_weight": (float, 0.0, 1.0, True, True),
    "straight_weight": (float, 0.0, 1.0, True, False),
    "slope_scale": (float, 0.0, 1e3, False, True),
    "slope_scale_mix": (float, 0.0, 1e3, True, True),
    "rotation_weight": (float, 0.0, 1.0, True, False),
    "tolerance_correlation": (float, 0.0, 1.0, True, False),
    "demo_offset": (float, 0.0, 1e3, True, True),
    "block_tolerance": (float, 0.0, 2.0, False, True),
    "n_chains": (int, 1, 64, True, True),
    "n_iterations": (int, 1, 10_000, True, True),
    "burn_in": (float, 0.0, 1.0, True, False),
    "n_initial_features": (int, 1, 32, True, True),
    "birth_window": (float, 0.0, 1.0, False, True),
    "birth_prior_mix": (float, 0.0, 1.0, False, False),
}


#: The tolerances (rho, sigma, tau) among which ``tolerance_correlation=None`` chooses (module docstring,
#: "Correlated tolerance"): the correlation of consecutive deviations, their stationary scale and the white floor
#: (rad); rho = 0 rows are white tolerances sigma alone.
TOLERANCES = tuple((0.0, sigma, 0.0) for sigma in (0.02, 0.05, 0.1, 0.2, 0.4)) + tuple(
    (rho, sigma, tau) for rho in (0.8, 0.9, 0.95, 0.97, 0.99) for sigma in (0.05, 0.1, 0.2, 0.4)
    for tau in (0.01, 0.02, 0.05))

#: How the returned sample is chosen among the chains' sweeps after burn-in (module docstring, "Which sample").
SELECTIONS = ("joint", "collapsed", "modal", "map")


def check_hyperparameters(**values: object) -> None:
    """Raise InvalidArgumentError naming the first hyperparameter outside :data:`HYPERPARAMETER_RANGES` (booleans
    ``resample_hyperparameters``, ``position_mixture``, ``dwell_pace``, ``block_emission`` and ``progress`` must be bool; ``robust_dof``,
    ``position_weight`` and ``tolerance_correlation`` may be None; ``selection`` is one of :data:`SELECTIONS`)."""
    for name, value in values.items():
        if name == "selection":
            if value not in SELECTIONS:
                raise InvalidArgumentError(f"selection must be one of {SELECTIONS}, got {value!r}")
            continue
        if name in ("resample_hyperparameters", "progress", "position_mixture", "dwell_pace", "block_emission"):
            if not isinstance(value, bool):
                raise InvalidArgumentError(f"{name} must be a bool, got {value!r}")
            continue
        if name in ("robust_dof", "position_weight", "tolerance_correlation") and value is None:
            continue
        kind, low, high, low_in, high_in = HYPERPARAMETER_RANGES[name]
        ok_type = isinstance(value, numbers.Integral) if kind is int else isinstance(value, numbers.Real)
        ok_type = ok_type and not isinstance(value, bool)
        ok = ok_type and math.isfinite(value) and (value >= low if low_in else value > low)
        ok = ok and (value <= high if high_in else value < high)
        if not ok:
            what = "an integer" if kind is int else "a number"
            lo, hi = ("[" if low_in else "(") + f"{low:g}", f"{high:g}" + ("]" if high_in else ")")
            extra = " or None" if name in ("robust_dof", "position_weight", "tolerance_correlation") else ""
            raise InvalidArgumentError(f"{name} must be {what} in {lo}, {hi}{extra}, got {value!r}")


class BetaProcessHMMSampler:
    """Markov chain Monte Carlo for the BP-GM-HMM (see the module docstring for the moves).

    Args:
        feature_mass: gamma, mass of the Beta process (expected features per sequence).
        feature_concentration: c, concentration of the Beta process (paper eq. 1 alpha).
        transition_concentration: alpha of the sticky Dirichlet rows (paper eq. 3 beta).
        stickiness: kappa, extra weight on self-transitions (paper eq. 3).
        direction_noise: prior expected standard deviation of the direction noise of a state's field
            (:func:`~lfd_torch.segmentation.field.field_prior`).
        extra_dof: nu0 - d - 1 of the field prior (its weight).
        slope_scale: prior standard deviation of a field's slope entries per radius of the data
            (:func:`~lfd_torch.segmentation.field.field_prior`).
        slope_scale_mix: s >= 0: in the collapsed score, the affine fields' slope prior is an equal mixture of the
            scales ``slope_scale`` and s (module docstring, "Slope scale"; with ``block_emission`` each curved
            state's scale is profiled, "Block emission"); 0: ``slope_scale`` alone.
        rotation_weight: r in [0, 1): in the collapsed score (so ``selection="map"``) the affine slab is the mixture
            (1 - r) affine + r rigid rotation (module docstring, "Rotation fields"); 0: affine alone.
        robust_dof: nu of the Student-t direction emission (None: Gaussian), see :mod:`.field`.
        position_weight: tau of the tempered position term of the emission (module docstring, "Position"), in
            [0, 1]; None: 1 / D, D the minimum duration in grid samples; 0: directions alone.
        position_mixture: the tempered position term of the collapsed score is that of a mixture over space
            (each state's Gaussian times its weight in the sequence, the weights integrated out): cutting a leg no
            longer raises the positions' density (module docstring, "Position"); acts through ``selection="map"``.
        straight_weight: rho in [0, 1), prior probability that a state's field is straight (slope 0) in the
            collapsed score, so in ``selection="map"`` (module docstring, "Straight states"); 0: affine fields only.
        tolerance_correlation: rho in [0, 1), the correlation of consecutive deviations of a direction from its
            state's field in the collapsed score (module docstring, "Correlated tolerance"); 0: white (independent)
            deviations; None: chosen with the labelling among :data:`TOLERANCES` (``selection="map"``).
        dwell_pace: with the dwell term, the collapsed score also gives every run its own pace level
            (:mod:`.dwell`, "Pace of a run"; the chains' moves keep the run-free dwell term).
        block_emission: in the collapsed score (so ``selection="map"``) the states' motion is scored on the block
            means of the positions instead of the grid directions (module docstring, "Block emission"); needs the
            ``blocks`` of :meth:`run`.
        block_tolerance: sigma_u (rad) of the curved states under ``block_emission``: their directions' deviation
            from the field, a random walk of the position (:mod:`.blocks`); straight states have none.
        demo_offset: v >= 0, in the collapsed score (so ``selection="map"``) every demonstration adds its own offset
            Delta ~ N(0, v Psi_k) to the field of each state it visits (module docstring, "Demonstrations' own
            offsets"); 0: one field per state for all demonstrations.
        n_chains: independent chains C (run batched).
        n_iterations: sweeps per chain.
        burn_in: fraction of the sweeps discarded before the best sample is searched.
        n_initial_features: shared features every sequence owns at the start (drawn from random data windows).
        birth_window: length of the birth proposal's data window as a fraction of the sequence length.
        birth_prior_mix: probability that the birth proposal draws theta* from the prior instead of the window
            posterior (keeps the reverse death move possible for features far from the data).
        resample_hyperparameters: also sample gamma, alpha and kappa.
        selection: "joint" (default here; ``segment`` defaults to "map") returns the sample with the highest joint
            log probability, "collapsed" the one with the highest collapsed score, "modal" the best joint sample with the posterior-modal number of runs
            per sequence, "map" a local mode of the collapsed posterior reached from the chains' best samples
            (module docstring, "Which sample").
        progress: show a tqdm progress bar.
    """

    def __init__(
        self,
        *,
        feature_mass: float = 2.0,
        feature_concentration: float = 1.0,
        transition_concentration: float = 1.0,
        stickiness: float = 25.0,
        direction_noise: float = 0.2,
        extra_dof: float = 2.0,
        slope_scale: float = 1.0,
        slope_scale_mix: float = 0.0,
        rotation_weight: float = 0.0,
        robust_dof: float | None = 4.0,
        position_weight: float | None = 0.0,
        position_mixture: bool = False,
        straight_weight: float = 0.0,
        tolerance_correlation: float | None = 0.0,
        dwell_pace: bool = False,
        demo_offset: float = 0.0,
        block_emission: bool = False,
        block_tolerance: float = 0.1,
        n_chains: int = 4,
        n_iterations: int = 100,
        burn_in: float = 0.5,
        n_initial_features: int = 4,
        birth_window: float = 0.1,
        birth_prior_mix: float = 0.1,
        resample_hyperparameters: bool = False,
        selection: str = "joint",
        progress: bool = False,
    ) -> None:
        check_hyperparameters(
            feature_mass=feature_mass, feature_concentration=feature_concentration,
            transition_concentration=transition_concentration, stickiness=stickiness,
            direction_noise=direction_noise, extra_dof=extra_dof, slope_scale=slope_scale,
            slope_scale_mix=slope_scale_mix, rotation_weight=rotation_weight, robust_dof=robust_dof,
            position_weight=position_weight, position_mixture=position_mixture, straight_weight=straight_weight,
            tolerance_correlation=tolerance_correlation, dwell_pace=dwell_pace, demo_offset=demo_offset,
            block_emission=block_emission, block_tolerance=block_tolerance, n_chains=n_chains,
            n_iterations=n_iterations, burn_in=burn_in, n_initial_features=n_initial_features,
            birth_window=birth_window, birth_prior_mix=birth_prior_mix,
            resample_hyperparameters=resample_hyperparameters, selection=selection, progress=progress,
        )  # fmt: skip
        self.selection = selection
        self.feature_mass = float(feature_mass)
        self.feature_concentration = float(feature_concentration)
        self.transition_concentration = float(transition_concentration)
        self.stickiness = float(stickiness)
        self.direction_noise = float(direction_noise)
        self.robust_dof = None if robust_dof is None else float(robust_dof)
        self.position_weight = None if position_weight is None else float(position_weight)
        self.position_mixture = bool(position_mixture)
        self.straight_weight = float(straight_weight)
        self.tolerance_correlation = None if tolerance_correlation is None else float(tolerance_correlation)
        self.dwell_pace = bool(dwell_pace)
        self.demo_offset = float(demo_offset)
        self.block_emission = bool(block_emission)
        self.block_tolerance = float(block_tolerance)
        self.extra_dof = float(extra_dof)
        self.slope_scale = float(slope_scale)
        self.slope_scale_mix = float(slope_scale_mix)
        self.rotation_weight = float(rotation_weight)
        self.n_chains = int(n_chains)
        self.n_iterations = int(n_iterations)
        self.burn_in = float(burn_in)
        self.n_initial_features = int(n_initial_features)
        self.birth_window = float(birth_window)
        self.birth_prior_mix = float(birth_prior_mix)
        self.resample_hyperparameters = bool(resample_hyperparameters)
        self.progress = bool(progress)

    # ------------------------------------------------------------------ public
    def run(
        self, sequences: list[Tensor], velocities: list[Tensor], generator: torch.Generator,
        prior: FieldPrior | None = None, min_duration: int = 1, velocity_noise: Tensor | float = 0.0,
        speed_floor: float = 0.0, dwell: list[Tensor] | None = None, blocks: BlockMeans | None = None,
    ) -> SamplerResult:
        """Sample the BP-GM-HMM posterior of a set of sequences.

        Args:
            sequences: N position tensors (T_i, d), T_i >= 2, all with the same d, dtype and device.
            velocities: N velocity tensors (T_i, d) of the same sequences.
            generator: source of all randomness (on the sequences' device).
            prior: MNIW prior of the state fields; None uses :func:`field_prior` with ``direction_noise``.
            velocity_noise, speed_floor: of :func:`~lfd_torch.segmentation.field.field_observations`.
            min_duration: D, shortest run of a state in samples of the given grid
                (:func:`~lfd_torch.segmentation.transitions.expand_min_duration`).
            dwell: N tensors (T_i,), the dwell covariate c of every grid point (:mod:`.dwell`); given, the model
                also explains it (module docstring, "Dwell"; needs D >= 2). None: directions alone.
            blocks: the block means of the sequences' grid points (:class:`BlockMeans`), needed with
                ``block_emission``.

        Returns:
            SamplerResult of the best sample.
        """
        check_generator(generator, where="BetaProcessHMMSampler.run")
        for name, seqs in (("sequences", sequences), ("velocities", velocities)):
            if not isinstance(seqs, (list, tuple)) or not all(isinstance(t, Tensor) for t in seqs):
                raise ShapeMismatchError(f"{name} must be a list of (T_i, d) tensors")
        dtypes = {t.dtype for t in (*sequences, *velocities)}
        if len(dtypes) != 1:
            raise ShapeMismatchError(f"sequences and velocities must share one dtype, got {sorted(map(str, dtypes))}")
        x, lengths = _pad(sequences)
        v, lengths_v = _pad(velocities, "velocities")
        if v.shape != x.shape or not torch.equal(lengths, lengths_v):
            raise ShapeMismatchError("velocities must have the shapes of the sequences")
        # a state's run lasts at least D samples: every sequence must hold one (a larger D leaves no labelling)
        check_int(min_duration, "min_duration", low=1, high=int(lengths.min()))
        check_float(speed_floor, "speed_floor", low=0.0)
        c = None
        if dwell is not None:
            if len(dwell) != len(sequences) or any(ci.shape != (si.shape[0],) for ci, si in zip(dwell, sequences)):
                raise ShapeMismatchError("dwell must hold one (T_i,) tensor per sequence")
            c = x.new_zeros(x.shape[:2])
            for i, ci in enumerate(dwell):
                if not bool(torch.isfinite(ci).all()):
                    raise NonFiniteError("dwell contains NaN or Inf", i)
                c[i, : ci.shape[0]] = ci
        if self.block_emission and blocks is None:
            raise InvalidArgumentError("block_emission needs the blocks of the sequences (BlockMeans)")
        # No gradient flows through a sampler: inference mode skips autograd's bookkeeping on its many small ops
        # (about 8 % of a LASA Multi_Models_3 run, the same result; one-off timing), and the result is cloned into
        # normal tensors, which callers may use in autograd.
        with torch.inference_mode(_INFERENCE_MODE):
            run = _Run(self, x, v, lengths, generator, prior, min_duration, (velocity_noise, speed_floor), c, blocks)
            result = run.sample()
        return _normal_tensors(result)


def _normal_tensors(result: SamplerResult) -> SamplerResult:
    """``result`` with every tensor (fields and hyperparameter values) cloned outside inference mode."""
    def normal(value):
        return value.clone() if isinstance(value, Tensor) else value

    tensors = {f.name: normal(getattr(result, f.name)) for f in fields(result)}
    tensors["hyperparameters"] = {k: normal(v) for k, v in result.hyperparameters.items()}
    return SamplerResult(**tensors)


def _compact_columns(s: Tensor, F: Tensor) -> tuple[Tensor, Tensor]:
    """Drop the feature columns nobody owns from F (N, K) and relabel s (N, T) to the remaining ones."""
    cols = F.any(0)
    remap = torch.cumsum(cols.long(), 0) - 1
    return remap[s], F[:, cols]


def _runs(s: Tensor, lengths: Tensor) -> list[list[tuple[int, int, int]]]:
    """Per sequence of the labels s (N, T) and its length, its runs as (first, end, state) (lists, on the CPU)."""
    s_cpu, n = s.cpu(), lengths.cpu().tolist()
    out = []
    for i, length in enumerate(n):
        row = s_cpu[i, :length]
        starts = [0] + (torch.nonzero(row[1:] != row[:-1]).reshape(-1) + 1).tolist()
        out.append(list(zip(starts, starts[1:] + [length], row[starts].tolist())))
    return out


def duration_phases(s: Tensor, min_duration: int) -> Tensor:
    """(..., T) long: samples since the current run of the labels s (..., T) began, capped at D - 1 (the phase of the
    explicit-duration states, :func:`~lfd_torch.segmentation.transitions.expand_min_duration`)."""
    t = torch.arange(s.shape[-1], device=s.device).expand_as(s)
    start = torch.ones_like(s, dtype=torch.bool)
    start[..., 1:] = s[..., 1:] != s[..., :-1]
    first = torch.where(start, t, torch.zeros_like(t)).cummax(-1).values
    return (t - first).clamp_max(int(min_duration) - 1)


def _pad(sequences: list[Tensor], name: str = "sequences") -> tuple[Tensor, Tensor]:
    if len(sequences) == 0:
        raise TooFewSamplesError("no sequence to segment")
    d = sequences[0].shape[-1]
    for i, s in enumerate(sequences):
        if s.ndim != 2 or s.shape[-1] != d:
            raise ShapeMismatchError(f"{name} must be (T_i, {d}), got {tuple(s.shape)}", i)
        if s.shape[0] < 2:
            raise TooFewSamplesError(f"has {s.shape[0]} samples, at least 2 are needed", i)
        if not torch.isfinite(s).all():
            raise NonFiniteError(f"{name} contain NaN or Inf", i)
    T = max(s.shape[0] for s in sequences)
    x = torch.stack([torch.cat([s, s[-1:].expand(T - s.shape[0], d)]) for s in sequences])
    lengths = torch.tensor([s.shape[0] for s in sequences], dtype=torch.long, device=x.device)
    return x, lengths


class _ShareBank:
    """The block-evidence shares a run has scored (:meth:`_Run._sequence_terms`), by row key: for each number r of
    states a row uses, its (r q, r q) gram, (r q, d) proj and const stacked in tensors that grow by doubling, so
    that the shares of many rows are read by one gather each. ``index`` maps a row's key to (r, slot)."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self.index: dict[bytes, tuple[int, int]] = {}
        self.banks: dict[int, list] = {}  # r -> [gram (cap, w, w), proj (cap, w, d), const (cap,), rows filled]

    def gather(self, r: int, slots: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        gram, proj, const, _ = self.banks[r]
        return gram[slots], proj[slots], const[slots]

    def add(self, r: int, names: list[bytes], gram: Tensor, proj: Tensor, const: Tensor) -> None:
        n = len(names)
        if r not in self.banks:
            self.banks[r] = [gram.new_empty(0, *gram.shape[1:]), proj.new_empty(0, *proj.shape[1:]),
                             const.new_empty(0), 0]
        bank = self.banks[r]
        filled = bank[3]
        if filled + n > bank[2].shape[0]:  # grow to at least twice the rows
            cap = max(2 * (filled + n), 64)
            bank[:3] = [torch.cat([t[:filled], t.new_empty(cap - filled, *t.shape[1:])]) for t in bank[:3]]
        bank[0][filled: filled + n], bank[1][filled: filled + n], bank[2][filled: filled + n] = gram, proj, const
        bank[3] = filled + n
        self.index.update((name, (r, filled + k)) for k, name in enumerate(names))


class _Run:
    """Mutable state of one sampler run (all chains batched)."""

    def __init__(
        self, cfg: BetaProcessHMMSampler, x: Tensor, v: Tensor, lengths: Tensor, generator: torch.Generator,
        prior: FieldPrior | None, min_duration: int, noise: tuple[Tensor | float, float], dwell: Tensor | None = None,
        blocks: BlockMeans | None = None,
    ) -> None:
        self.cfg = cfg
        self.gen = generator
        self.x = x  # (N, T, d)
        self.N, self.T, self.d = x.shape
        self.C = cfg.n_chains
        self.lengths = lengths
        self.dtype, self.device = x.dtype, x.device
        self.valid = torch.arange(self.T, device=self.device).unsqueeze(0) < lengths.unsqueeze(1)  # (N, T)
        self.obs = field_observations(x, v, self.valid, velocity_noise=noise[0], direction_noise=cfg.direction_noise,
                                      speed_floor=noise[1])
        if prior is None:
            prior = field_prior(self.d, direction_noise=cfg.direction_noise, extra_dof=cfg.extra_dof,
                                slope_scale=cfg.slope_scale, dtype=self.dtype, device=self.device)
        self.prior = prior
        # second slope scale of the affine slab in the collapsed score (module docstring, "Slope scale")
        self.wide_prior = None if cfg.slope_scale_mix == 0 else field_prior(
            self.d, direction_noise=cfg.direction_noise, extra_dof=cfg.extra_dof, slope_scale=cfg.slope_scale_mix,
            dtype=self.dtype, device=self.device)
        self._set_tolerance(cfg.tolerance_correlation or 0.0)
        self.mass = torch.full((self.C,), cfg.feature_mass, dtype=self.dtype, device=self.device)
        self.alpha = torch.full((self.C,), cfg.transition_concentration, dtype=self.dtype, device=self.device)
        self.kappa = torch.full((self.C,), cfg.stickiness, dtype=self.dtype, device=self.device)
        self.window = (lengths.to(self.dtype) * cfg.birth_window).round().long().clamp_min(min(self.d + 2, 4))
        self.window = torch.minimum(self.window, lengths)
        self.accept = {"shared": [0, 0], "birth": [0, 0], "death": [0, 0]}
        self.D = int(min_duration)
        if cfg.tolerance_correlation != 0.0 and self.D < 2:
            raise InvalidArgumentError("tolerance_correlation other than 0 needs min_duration >= 2 (a run's first "
                                       "sample is the first phase of the explicit-duration states)")
        # tempered position term (module docstring, "Position"): tau = 0 leaves it out (and draws nothing for it)
        self.tau = 1.0 / self.D if cfg.position_weight is None else cfg.position_weight
        self.pos = self.obs.z[..., : self.d]  # (N, T, d) standardised positions
        self.pos_prior = niw_prior_from_data(self.pos[self.valid], covariance_scale=_POSITION_SCALE)
        self.loc = self.spread = None  # (C, K, d), (C, K, d, d) position Gaussians when tau > 0
        self._deltas_base = None  # _block_deltas: the profile and shares of the labelling it last scored against
        self._share_bank = _ShareBank()  # _sequence_terms: the shares scored so far, by row
        self.blocks = None  # block emission (module docstring): xbar, sbar, var (N, T, .), zmid (N, T - 1, p)
        if cfg.block_emission:
            self.blocks = self._standardised_blocks(blocks)
        # dwell term (module docstring, "Dwell"): c (N, T), its mask, and every chain's (mu, delta), sigma^2
        self.dwell = dwell
        self.dwell_ll = None  # (C, N, T, 2) log N(c_t; mu + delta b, sigma^2), b = 0, 1
        if dwell is not None:
            self.dwell_mask = dwell_mask(lengths, self.T, self.D)
            self.dwell_prior = dwell_prior(self.dtype, self.device)
            self.pace_ratios = PACE_RATIOS if cfg.dwell_pace else (0.0,)
            beta, noise = dwell_start(dwell[..., self.dwell_mask])  # neutral: no dwell effect yet
            self.dwell_beta = beta.expand(self.C, 2).clone()
            self.dwell_noise = noise.expand(self.C).clone()
            self.dwell_ll = dwell_log_likelihood(dwell, self.dwell_mask, self.dwell_beta, self.dwell_noise)
        self._initialise()

    # ------------------------------------------------------------------ helpers
    def _set_tolerance(self, rho: float, sigma: float | None = None, tau: float = 0.0) -> None:
        """Use the tolerance (rho, sigma, tau) in the collapsed score and the map search (module docstring,
        "Correlated tolerance"): its prior and the views of the observations by age in a run. (0, None,
        0) is the white tolerance of the sampler (``tolerance_correlation=0``)."""
        sigma = self.cfg.direction_noise if sigma is None else float(sigma)
        self.rho, self.sigma, self.tau_white = float(rho), sigma, float(tau)
        self.score_prior = correlated_tolerance_prior(self.prior, self.rho, sigma / self.cfg.direction_noise)
        self.wide_score_prior = None if self.wide_prior is None else correlated_tolerance_prior(
            self.wide_prior, self.rho, sigma / self.cfg.direction_noise)
        views = correlated_tolerance_observations(self.obs, self.rho, self.cfg.direction_noise, sigma, tau)
        n = self.N * self.T
        # (ages, n, .) every view stacked: a sample of age a in its run is seen in view a (:meth:`_score_view`)
        self.ar_views = tuple(torch.stack([v[i].reshape(n, *v[i].shape[2:]) for v in views]) for i in range(3))
        self.ar_start = tuple(a[:1] for a in self.ar_views)
        self.ar_cont = tuple(a[-1:] for a in self.ar_views)  # the Viterbi proposal's view of a later phase
        x = torch.cat([self.ar_start[1], self.ar_start[0]], -1)  # (1, n, d + p): [u_t, z_t] in the first view
        self.white_outer = (x.unsqueeze(-1) * x.unsqueeze(-2)).flatten(-2)  # (1, n, (d + p)^2), _profile_scales

    def _score_view(self, s: Tensor) -> tuple[Tensor | None, Tensor, Tensor]:
        """What the collapsed score's field evidence sees of labellings s (B, N, T): every sample's age in its run
        (B, N T), capped at the filter's memory (None for a white tolerance, where it does not matter), the weights w
        (B, N T) and the per-sample log Jacobian d / 2 log w (B, N T), 0 on padding
        (:func:`correlated_tolerance_observations`; the views are shared by all labellings: :meth:`_stats`)."""
        B, n = s.shape[0], self.N * self.T
        valid = self.valid.reshape(1, n)
        if self.rho == 0.0:
            age, w = None, self.ar_start[2].expand(B, n)
        else:
            age = duration_phases(s, self.ar_views[2].shape[0]).reshape(B, n)
            w = self.ar_views[2].gather(0, age)
        jac = 0.5 * self.d * torch.log(w.clamp_min(1e-300)) * valid
        return age, w, jac

    def _viewed(self, age: Tensor | None) -> tuple[Tensor, Tensor]:
        """Regressors (1 or B, n, p) and directions (1 or B, n, d) of every sample in the view of its age."""
        if age is None:
            return self.ar_start[0], self.ar_start[1]
        z, u = self.ar_views[0], self.ar_views[1]
        return (z.gather(0, age.unsqueeze(-1).expand(*age.shape, z.shape[-1])),
                u.gather(0, age.unsqueeze(-1).expand(*age.shape, u.shape[-1])))

    def _stats(self, age: Tensor | None, w: Tensor, onehot: Tensor) -> tuple[Tensor, ...]:
        """Field statistics (:func:`field_statistics`) of labellings onehot (B, n, K) with weights w (B, n), each
        sample in the view of its age (B, n) (None: the white view); with ``demo_offset``, those of
        :func:`demo_offset_statistics` (n = N T)."""
        return self._field_terms(age, w, onehot)[0]

    def _field_terms(self, age: Tensor | None, w: Tensor, onehot: Tensor) -> tuple[tuple[Tensor, ...], Tensor]:
        """:meth:`_stats` and the per-state log-determinant term (B, K) of the demonstrations' own offsets, which
        the field evidence adds (0 without them)."""
        z, u = self._viewed(age)
        ratio = self.cfg.demo_offset
        if ratio == 0.0:
            stats = field_statistics(z, u, w, onehot)
            return stats, torch.zeros_like(stats[0])
        N = self.N
        per_sequence = field_statistics(z.unflatten(-2, (N, -1)), u.unflatten(-2, (N, -1)), w.unflatten(-1, (N, -1)),
                                        onehot.unflatten(-2, (N, -1)))
        return demo_offset_statistics(*per_sequence, ratio)

    def _standardised_blocks(self, blocks: BlockMeans) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The block means, path lengths and noise variances on the positions' standardised scale, padded (N, T, .),
        and the increments' midpoint regressors (N, T - 1, p)."""
        if len(blocks.means) != self.N or any(int(m.shape[0]) != int(n) for m, n in zip(blocks.means, self.lengths)):
            raise ShapeMismatchError("blocks must hold one block per grid point of every sequence")
        radius, centre = self.obs.radius, self.obs.centre
        xbar = self.x.new_zeros(self.N, self.T, self.d)
        sbar = self.x.new_zeros(self.N, self.T)
        var = self.x.new_ones(self.N, self.T)
        for i, (m, l, c) in enumerate(zip(blocks.means, blocks.lengths, blocks.counts)):
            n = m.shape[0]
            xbar[i, :n] = (m.to(self.x) - centre) / radius
            xbar[i, n:] = xbar[i, n - 1]
            sbar[i, :n] = l.to(self.x) / radius
            sbar[i, n:] = sbar[i, n - 1]
            var[i, :n] = (blocks.noise / radius) ** 2 / c.to(self.x)
        zmid = 0.5 * (self.obs.z[:, 1:] + self.obs.z[:, :-1])
        check_block_variances(var, self.valid)
        return xbar, sbar, var, zmid

    def _block_evidence(self, s: Tensor, age: Tensor | None, w: Tensor, onehot: Tensor) -> Tensor:
        """(B,) the block emission of the labellings s (B, N, T) (:mod:`.blocks`) with each state's component
        profiled (:meth:`_block_profile`), plus the components' log prior (:meth:`_component_log_prior`)."""
        best, kind, used = self._block_profile(s, age, w, onehot)
        return best + self._component_log_prior(kind, used).sum(-1)

    def _component_log_prior(self, kind: Tensor, used: Tensor) -> Tensor:
        """(..., K) log prior of each used state's component ``kind`` (..., K) (0 straight, 1 curved, 2 curved at
        ``slope_scale_mix``), 0 for unused states: 1/2 straight, 1/2 curved, with ``slope_scale_mix`` the curved
        half split equally between the two slope scales."""
        curved = math.log(0.25) if self.cfg.slope_scale_mix > 0 else math.log(0.5)
        lp = torch.full(kind.shape, math.log(0.5), dtype=self.dtype, device=kind.device)
        lp = lp.masked_fill(kind != 0, curved)  # float64 constants: torch.where on Python floats rounds to float32
        return torch.where(used, lp, torch.zeros_like(lp))

    def _block_scales(self, kind: Tensor) -> Tensor:
        """(..., K) each state's slope scale: ``slope_scale_mix`` for component 2, else ``slope_scale``."""
        cfg = self.cfg
        return torch.full(kind.shape, cfg.slope_scale, dtype=self.dtype, device=kind.device).masked_fill(
            kind == 2, cfg.slope_scale_mix)

    def _block_profile(self, s: Tensor, age: Tensor | None, w: Tensor, onehot: Tensor
                       ) -> tuple[Tensor, Tensor, Tensor]:
        """The block evidence (B,) of :meth:`_block_evidence` without the components' prior, the (B, K) components
        it profiles to (0 straight, 1 curved, 2 curved at ``slope_scale_mix``) and the (B, K) states in use.

        From the direction emission's spike-and-slab choice (straight or curved at ``slope_scale``), each round
        scores every used state switched to each other component on its own and keeps, per labelling, the switch
        that raises the evidence plus the components' log prior the most (a profile over the components, as the
        Student-t scales are profiled). A switch between straight and curved recomputes the shares of the
        sequences that use the state; a switch of the slope scale alone changes the shared prior only."""
        stats, _ = self._field_terms(age, w, onehot)
        log_straight = field_mixture_evidence(self.score_prior, *stats, self.cfg.straight_weight,
                                              self.wide_score_prior, self.cfg.rotation_weight)[1]  # (B, K)
        used = stats[0] > 0  # (B, K)
        B, K = used.shape
        mix = self.cfg.slope_scale_mix > 0
        uses = used_states(s, self.valid, K)  # (B, N, K)
        kind = torch.where((log_straight > math.log(0.5)) & used, 0, 1)
        eye = torch.eye(K, dtype=torch.bool, device=s.device)
        lp = self._component_log_prior(torch.arange(3, device=s.device), torch.ones(3, dtype=torch.bool,
                                                                                    device=s.device))
        N = s.shape[1]
        best = s.new_zeros(B, dtype=self.dtype)
        active = torch.arange(B, device=s.device)  # labellings whose components changed in the last round
        for r in range(_COMPONENT_ROUNDS):
            A = active.numel()
            sa, ka, ua = s[active], kind[active], used[active]
            # each state j flipped between straight and curved on its own: only the sequences that use j change;
            # their shares and the current ones are computed in one call
            b, j, n = torch.nonzero(uses[active].transpose(1, 2), as_tuple=True)  # (P,) (labelling, state, sequence)
            trial = ka[b] == 0
            trial[torch.arange(b.numel(), device=s.device), j] ^= True
            both = self._sequence_terms(torch.cat([torch.arange(N, device=s.device).repeat(A), n]),
                                        torch.cat([sa.flatten(0, 1), sa[b, n]]),
                                        torch.cat([(ka == 0).repeat_interleave(N, 0), trial]))
            base = BlockTerms(*(t[: A * N].view(A, N, *t.shape[2:]) for t in (both.gram, both.proj, both.const,
                                                                              both.at)), both.columns)
            new = both[A * N:]
            total = base.totals()
            if r == 0:
                best = combine_block_terms(*total, slope_scale=self._block_scales(ka))
            flat = b * K + j
            out = [tot.repeat_interleave(K, 0) for tot in total]
            old = base[b, n]  # the same rows as ``new`` (same sequence, same labels): the same columns ``at``
            BlockTerms(new.gram[:, 0] - old.gram, new.proj[:, 0] - old.proj, new.const[:, 0] - old.const, old.at,
                       new.columns).add_to(*out, flat)

            def scored(terms: list[Tensor], c: int) -> Tensor:
                """(A, K) evidence with state j (row j) at component c, the others as they are."""
                at = torch.where(eye, c, ka.unsqueeze(1))  # (A, K, K)
                return combine_block_terms(*terms, slope_scale=self._block_scales(at).flatten(0, 1)).view(A, K)

            flipped = scored(out, 1)  # to straight (the scale is then unused) or to curved at slope_scale
            none = torch.full_like(flipped, -math.inf)
            values = [torch.where(ka == 0, none, flipped), torch.where(ka == 0, flipped, none)]
            if mix:
                same = [tot.repeat_interleave(K, 0) for tot in total]
                values[1] = torch.where(ka == 2, scored(same, 1), values[1])
                values.append(torch.where(ka == 0, scored(out, 2), torch.where(ka == 1, scored(same, 2), none)))
            change = lp[: len(values)] - lp[ka].unsqueeze(-1)  # (A, K, C) the prior's change
            gain = torch.stack(values, -1) + change
            gain = torch.where(ua.unsqueeze(-1), gain, torch.full_like(gain, -math.inf))
            top, at = gain.flatten(1).max(-1)
            better = top > best[active] + 1e-9
            if not bool(better.any()):
                break
            C = gain.shape[-1]
            j, c = at // C, at % C
            best[active] = torch.where(better, top - change.flatten(1).gather(1, at[:, None])[:, 0], best[active])
            kind[active] = torch.where(torch.nn.functional.one_hot(j, K).bool() & better.unsqueeze(-1),
                                       c.unsqueeze(-1), ka)
            active = active[better]
        if mix:  # then the slope scales alone (the shares stay; only the shared prior changes), to convergence
            both = self._sequence_terms(torch.arange(N, device=s.device).repeat(B), s.flatten(0, 1),
                                        (kind == 0).repeat_interleave(N, 0))
            total = BlockTerms(*(t.view(B, N, *t.shape[2:]) for t in (both.gram, both.proj, both.const, both.at)),
                               both.columns).totals()
            same = [tot.repeat_interleave(K, 0) for tot in total]
            for _ in range(K):
                at = (eye.unsqueeze(0) & (kind != 0).unsqueeze(1)) ^ (kind == 2).unsqueeze(1)  # (B, K, K) j rescaled
                rescaled = combine_block_terms(*same, slope_scale=self._block_scales(
                    torch.where(at, 2, 1)).flatten(0, 1)).view(B, K)
                gain = torch.where(used & (kind != 0), rescaled, torch.full_like(rescaled, -math.inf))  # equal priors
                top, j = gain.max(-1)
                better = top > best + 1e-9
                if not bool(better.any()):
                    break
                best = torch.where(better, top, best)
                hit = torch.nn.functional.one_hot(j, K).bool() & better.unsqueeze(-1)
                kind = torch.where(hit, 3 - kind, kind)  # 1 <-> 2
        return best, kind, used

    def _sequence_terms(self, seq: Tensor, rows: Tensor, straight: Tensor) -> BlockTerms:
        """Shares (P, 1) of the block evidence (:func:`~.blocks.block_sequence_terms`) of sequences ``seq`` (P,)
        labelled ``rows`` (P, T) with the states' components ``straight`` (P, K). A share depends on the labels only
        through which of the sequence's increments share a state and that state's component, so rows equal up to
        an order-keeping renaming of the states (the same sequence in candidates that differ elsewhere, or whose
        labels a merge shifted) are computed once: each row is written with its used states' ranks, and the
        distinct ones are scored, or taken from the run's cache of the shares it has scored (the map search scores
        the same sequence labellings again and again: 21 of the 56 thousand rows of a LASA Multi_Models_3 run are
        distinct; the cache, at most ``_SHARE_CACHE`` rows, is emptied when full). Measured on that run (one-off,
        sampler seeds 0 and 1, alternated twice): 12.9 / 14.0 and 11.9 / 13.1 s without the cache, 10.3 / 11.7 and
        9.9 / 11.3 s with it. The cache (:class:`_ShareBank`) keeps the shares stacked by the number of states a row
        uses, so that a batch's hits are read by one gather per count, and a row's name drops the components of
        the states it does not use, which also deduplicates the batch (seeds 0-2 alternated with the per-row
        cache: 9.7 / 11.2 / 10.1 s against 9.9 / 11.8 / 10.2 s, the same scores; one-off)."""
        P, T = rows.shape
        K = straight.shape[-1]
        p = self.d + 1
        valid = self.valid[seq]
        uses = used_states(rows, valid, K)  # (P, K)
        order, rank = state_slots(uses)  # used states first, by index
        R = order.shape[-1]
        canon = torch.where(valid, torch.gather(rank, -1, rows), 0)
        key = torch.cat([seq.unsqueeze(-1), canon, torch.gather(straight, -1, order).long()], -1)
        # a row's name: its key up to the components of the states it uses (those of unused slots do not count)
        n_used = uses.sum(-1).tolist()
        distinct: dict[bytes, int] = {}
        first: list[int] = []  # the first row of each distinct name
        inverse_rows = []
        for j, (k, r) in enumerate(zip(key.cpu().numpy(), n_used)):
            name = k[: T + 1 + r].tobytes()
            if name not in distinct:
                distinct[name] = len(first)
                first.append(j)
            inverse_rows.append(distinct[name])
        names = list(distinct)
        key = key[torch.tensor(first, device=rows.device)]
        inverse = torch.tensor(inverse_rows, device=rows.device)
        U, q = key.shape[0], 1 + p
        used = [n_used[j] for j in first]  # states each distinct row uses
        bank = self._share_bank
        found = [bank.index.get(name) for name in names]  # (r, slot) of the rows scored before
        gram = key.new_zeros(U, R * q, R * q, dtype=self.dtype)
        proj = key.new_zeros(U, R * q, self.d, dtype=self.dtype)
        const = key.new_zeros(U, dtype=self.dtype)
        hits: dict[int, tuple[list[int], list[int]]] = {}
        for i, f in enumerate(found):
            if f is not None:
                group = hits.setdefault(f[0], ([], []))
                group[0].append(i)
                group[1].append(f[1])
        for r, (idx, slots) in hits.items():  # rows using r states fill the first r slots
            at, w = torch.tensor(idx, device=rows.device), r * q
            gram[at, :w, :w], proj[at, :w], const[at] = bank.gather(r, torch.tensor(slots, device=rows.device))
        missing = [i for i, f in enumerate(found) if f is None]
        if missing:
            m = torch.tensor(missing, device=rows.device)
            u = key[m, 0]
            terms = block_sequence_terms(*(t[u].unsqueeze(1) for t in self.blocks), self.valid[u].unsqueeze(1),
                                         key[m, 1: T + 1].unsqueeze(1), key[m, T + 1:].bool(),
                                         **self._block_options())
            if len(bank.index) + len(missing) > _SHARE_CACHE:
                bank.clear()
            new: dict[int, list[int]] = {}
            for j, i in enumerate(missing):
                new.setdefault(used[i], []).append(j)
            for r, js in new.items():
                at, jt, w = m[js], torch.tensor(js, device=rows.device), r * q
                g, pr, c = terms.gram[jt, 0, :w, :w], terms.proj[jt, 0, :w], terms.const[jt, 0]
                gram[at, :w, :w], proj[at, :w], const[at] = g, pr, c
                bank.add(r, [names[missing[j]] for j in js], g, pr, c)
        at = (order.unsqueeze(-1) * q + torch.arange(q, device=rows.device)).view(P, 1, R * q)
        return BlockTerms(gram[inverse].unsqueeze(1), proj[inverse].unsqueeze(1), const[inverse].unsqueeze(1), at,
                          K * q)

    def _block_options(self) -> dict:
        return {"tolerance": self.cfg.block_tolerance, "spread": DEMO_SPREAD, "slope_scale": self.cfg.slope_scale}

    def _block_deltas(self, s: Tensor, cand_s: Tensor, seq: Tensor, K: int, switched: bool = False) -> Tensor:
        """(P,) change of :meth:`_block_evidence` from the labelling s (N, T) to the candidates cand_s (P, N, T) over
        K states, each differing from s in its sequence ``seq`` alone, with every state keeping the component that s
        profiles to; label K - 1, when s does not use it, is a new state and takes the component of the state s has
        where a candidate first uses it (whose runs it receives), or with ``switched`` the better of that and the
        other one (straight <-> curved at ``slope_scale``). Only the changed sequence's share is recomputed
        (:func:`~.blocks.block_sequence_terms`); the map search confirms a move by the full score, which profiles
        the components anew.

        Why ``switched``: a new state has no component of its own yet, and the one it inherits can make a birth look
        worse than the full profile scores it, so that it is never confirmed (benchmark family scoop_const_3d, one
        demonstration, case 7: from two runs, the approach carrying the hook's first half as a curve, the birth of a
        straight approach scores 508.1 nats in full and switched, 497.4 at best inherited, against 499.4 now;
        ``tests/test_segmentation_blocks.py::test_births_of_a_new_state_are_scored_with_its_component_free``).
        The existing states keep theirs: switching the component of whichever state a move feeds as well found the
        same labellings on the three single constant-speed scoops that changed (cases 0, 1, 7) and cost 7-33 % more
        time on LASA Multi_Models_1-4 (`bench_segmentation_seeds.py`, medians, one-off, not stored). The
        variant costs a second batch of shares for the births of a new state, so the shift step asks for it only
        when no candidate rises without it."""
        N, T = s.shape
        valid = self.valid
        cached = self._deltas_base
        view = (K, self.rho, self.sigma, self.tau_white)  # the profile starts from the direction emission's choice
        if cached is not None and cached[1] == view and torch.equal(cached[0], s):
            kind, base, total, current, prior, uses = cached[2:]
        else:  # the shift and reassignment moves score their candidates in chunks, each against the same s
            onehot = torch.nn.functional.one_hot(s, K).to(self.dtype) * valid.unsqueeze(-1).to(self.dtype)
            age, w, _ = self._score_view(s[None])
            kind = self._block_profile(s[None], age, w.expand(1, -1), onehot.reshape(1, N * T, K))[1][0]  # (K,)
            base = block_sequence_terms(*self.blocks, valid, s[None], kind[None] == 0, **self._block_options())
            total = base.totals()  # (1, ...)
            current = combine_block_terms(*total, slope_scale=self._block_scales(kind[None]))  # (1,)
            base = base[0]  # (N, ...)
            uses = used_states(s, valid, K)  # (N, K)
            prior = self._component_log_prior(kind, uses.any(0)).sum()
            self._deltas_base = (s.clone(), view, kind, base, total, current, prior, uses)
        others = uses.sum(0)  # (K,) sequences that use each state
        new_state = not bool((s == K - 1).any())

        out = []
        for part in range(0, seq.numel(), _SHIFT_CHUNK):
            cs, sq = cand_s[part: part + _SHIFT_CHUNK], seq[part: part + _SHIFT_CHUNK]
            P = sq.numel()
            at = torch.arange(P, device=self.device)
            kd = kind.unsqueeze(0).expand(P, K).clone()
            rows = cs[at, sq]  # (P, T)
            if new_state:
                first = (rows == K - 1).to(torch.uint8).argmax(-1)  # (P,) 0 where unused: any component
                kd[:, K - 1] = kind[s[sq, first]]
            row_uses = used_states(rows, valid[sq], K)  # (P, K)
            used = (others - uses[sq].long() + row_uses.long()) > 0

            def evidence(idx: Tensor, kk: Tensor) -> Tensor:
                """Block evidence plus the components' prior of the candidates ``idx`` with components kk."""
                tot = [t.expand(idx.numel(), *t.shape[1:]).clone() for t in total]
                rank = torch.arange(idx.numel(), device=self.device)
                self._sequence_terms(sq[idx], rows[idx], kk == 0)[:, 0].add_to(*tot, rank)
                base[sq[idx]].add_to(*tot, rank, -1.0)
                return (combine_block_terms(*tot, slope_scale=self._block_scales(kk))
                        + self._component_log_prior(kk, used[idx]).sum(-1))

            ev = evidence(at, kd)
            if switched and new_state:  # the new state at the other component (only its sequence uses it)
                flip = torch.nonzero((rows == K - 1).any(-1)).view(-1)
                if flip.numel():
                    kf = kd[flip].clone()
                    kf[:, K - 1] = torch.where(kf[:, K - 1] == 0, 1, 0)
                    ev = ev.index_put((flip,), torch.maximum(ev[flip], evidence(flip, kf)))
            out.append(ev - current - prior)
        return torch.cat(out)

    def _field_evidence(self, age: Tensor | None, w: Tensor, onehot: Tensor) -> Tensor:
        """(B, K) the states' field evidence (spike-and-slab, :func:`field_mixture_evidence`)."""
        stats, extra = self._field_terms(age, w, onehot)
        return field_mixture_evidence(self.score_prior, *stats, self.cfg.straight_weight,
                                      self.wide_score_prior, self.cfg.rotation_weight)[0] + extra

    def _rand(self, *shape: int) -> Tensor:
        return torch.rand(*shape, generator=self.gen, dtype=self.dtype, device=self.device)

    def _gamma_prior_weights(self, shape: tuple[int, ...], K: int) -> Tensor:
        view = (-1, *([1] * (len(shape) + 2)))
        return sample_transition_weights_prior(
            (self.C, *shape), K, self.alpha.view(view), self.kappa.view(view), self.gen, dtype=self.dtype,
            device=self.device,
        )  # fmt: skip

    def _emission(self, field: Tensor, noise: Tensor, loc: Tensor | None = None,
                  spread: Tensor | None = None) -> Tensor:
        """(C, N, T, K) log emission densities of every sample under every slot; field (C, K, d, p), noise (C, K, d, d),
        and (when tau > 0) the position Gaussians loc (C, K, d), spread (C, K, d, d)."""
        C, K = field.shape[:2]
        z, u, w, pos = self._flat_observations()
        ll = field_log_likelihood(z, u, w, field, noise, self.cfg.robust_dof)
        if self.tau > 0:
            ll = ll + self.tau * gaussian_log_density(pos, loc, spread)
        return ll.reshape(C, self.N, self.T, K)

    def _chain_view(self, t: Tensor, dims: int) -> Tensor:
        """Observations with a leading chain axis: (1, ...) when shared by all chains (a tensor of ``dims``
        dimensions), as they are (C, ...) when every chain has its own (the Geweke test's successive-conditional
        chains, which redraw the data per chain). Only the sampling moves read per-chain observations; the collapsed
        score and the map search assume shared ones."""
        return t if t.dim() > dims else t.unsqueeze(0)

    def _flat_observations(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """z (1 or C, N T, p), u (., N T, d), w (., N T), positions (., N T, d)."""
        o = self.obs
        return (self._chain_view(o.z, 3).flatten(1, 2), self._chain_view(o.u, 3).flatten(1, 2),
                self._chain_view(o.w, 2).flatten(1, 2), self._chain_view(self.pos, 3).flatten(1, 2))

    def _position_statistics(self, onehot: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Tempered NIW statistics (tau n, tau sum x, tau sum x x^T) of the positions per state; onehot (B, N T, K)."""
        return sufficient_statistics(self._chain_view(self.pos, 3).flatten(1, 2), onehot * self.tau)

    def _occupancies(self, onehot: Tensor) -> Tensor | None:
        """(B, N, K) tempered occupancies tau n_ik of the labellings onehot (B, N T, K) under ``position_mixture``;
        None without it."""
        if not (self.tau > 0 and self.cfg.position_mixture):
            return None
        B, _, K = onehot.shape
        return self.tau * onehot.reshape(B, self.N, self.T, K).sum(2)

    def _occupancy_terms(self, onehot: Tensor) -> Tensor:
        """(B, K) per-state part of the tempered occupancy evidence of ``position_mixture`` (module docstring,
        "Position"): sum over sequences of log Gamma(tau n_ik) over the states a sequence visits (0 without it);
        onehot (B, N T, K)."""
        x = self._occupancies(onehot)
        if x is None:
            return onehot.new_zeros(onehot.shape[0], onehot.shape[-1])
        return torch.where(x > 0, torch.lgamma(x.clamp_min(1e-12)), torch.zeros_like(x)).sum(1)

    def _occupancy_constant(self) -> float:
        """The labelling-free part of the occupancy evidence: -sum_i log Gamma(1 + tau n_i)."""
        if not (self.tau > 0 and self.cfg.position_mixture):
            return 0.0
        return -float(torch.lgamma(1.0 + self.tau * self.lengths.to(self.dtype)).sum())

    def _occupancy_log_weights(self, onehot: Tensor) -> Tensor:
        """(B, N, 1, K) tau log pi_ik, the predictive occupancies (tau n_ik + 1 / K) / (tau n_i + 1) of the
        Viterbi proposal under ``position_mixture`` (0 without it); onehot (B, N T, K)."""
        x = self._occupancies(onehot)
        if x is None:
            return onehot.new_zeros(onehot.shape[0], self.N, 1, onehot.shape[-1])
        pi = (x + 1.0 / x.shape[-1]) / (x.sum(-1, keepdim=True) + 1.0)
        return (self.tau * torch.log(pi)).unsqueeze(2)

    def _marginal(self, features: Tensor, weights: Tensor, log_emission: Tensor, lengths: Tensor,
                  dwell_ll: Tensor | None = None) -> Tensor:
        """log p(x | f, eta, theta), states summed out. features (B, K), weights (B, K, K), log_emission (B, T, K),
        dwell_ll (B, T, 2) or None (:meth:`_expand`)."""
        D = self.D
        le = self._expand(log_emission, features, lengths, dwell_ll)
        init, P = expand_min_duration(initial_distribution(features, self.dtype), transition_matrix(weights, features), D)
        ll = _forward_log_likelihood(le, init, P, lengths)
        return torch.where(features.any(-1), ll, torch.full_like(ll, _NEG_INF))

    def _expand(self, log_emission: Tensor, features: Tensor, lengths: Tensor, dwell_ll: Tensor | None,
                first_emission: Tensor | None = None) -> Tensor:
        """(B, T, K D) log emissions of the phase-expanded states from those of the states (B, T, K): slots not in
        the features (B, K) get -inf; with the dwell term, phase 0 (a run's first point) adds dwell_ll[..., 1] and
        the other phases dwell_ll[..., 0] (module docstring, "Dwell"); phase 0 emits ``first_emission`` (B, T, K)
        when given (a correlated tolerance, module docstring); the last run is completed."""
        D = self.D
        unused = ~features.unsqueeze(-2)
        le = log_emission.masked_fill(unused, _NEG_INF).repeat_interleave(D, -1)  # (B, T, K D), a new tensor
        phases = le.unflatten(-1, (-1, D))  # (B, T, K, D), a view of it, edited in place below
        if first_emission is not None:
            phases[..., 0] = first_emission.masked_fill(unused, _NEG_INF)
        if dwell_ll is not None:
            phases[..., 0] += dwell_ll[..., 1:2]
            phases[..., 1:] += dwell_ll[..., 0:1].unsqueeze(-1)
        return self._complete_last_run(le, lengths)

    def _flat_dwell(self, *expand: int) -> Tensor | None:
        """The chains' dwell terms (C, N, T, 2) with the rows flattened as the callers' batches: (C N [x expand],
        T, 2), or None without the dwell term."""
        if self.dwell_ll is None:
            return None
        ll = self.dwell_ll
        for e in expand:
            ll = ll.unsqueeze(2).expand(*ll.shape[:2], e, *ll.shape[2:]).flatten(1, 2)
        return ll.flatten(0, 1)

    def _complete_last_run(self, log_emission: Tensor, lengths: Tensor) -> Tensor:
        """Forbid ending inside the forced phases: the last run of a sequence lasts at least D samples too.

        log_emission (B, T, K D) on the phase-expanded states, edited in place; the last valid sample may only be
        emitted from a last phase (D - 1), which is the semi-Markov model's end condition (a run is complete when
        it ends).
        """
        D = self.D
        if D <= 1:
            return log_emission
        B, T, KD = log_emission.shape
        not_last_phase = (torch.arange(KD, device=self.device) % D) != D - 1  # (K D,)
        at_end = torch.arange(T, device=self.device).unsqueeze(0) == (lengths - 1).unsqueeze(1)  # (B, T)
        return log_emission.masked_fill_(at_end.unsqueeze(-1) & not_last_phase, _NEG_INF)

    def _marginal_all(self) -> Tensor:
        C, N, K = self.F.shape
        ll = self._marginal(
            self.F.reshape(C * N, K), self.eta.reshape(C * N, K, K), self.loge.reshape(C * N, self.T, K),
            self.lengths.repeat(C), self._flat_dwell(),
        )  # fmt: skip
        return ll.reshape(C, N)

    def _prior_draw(self, *batch: int) -> tuple[Tensor, Tensor]:
        p = self.prior
        d, q = p.mean.shape[-2:]
        expanded = FieldPrior(mean=p.mean.expand(*batch, d, q), row_covariance=p.row_covariance.expand(*batch, q, q),
                              dof=p.dof.expand(batch), scale=p.scale.expand(*batch, d, d))
        return sample_field(expanded, self.gen)

    def _prior_draw_position(self, *batch: int) -> tuple[Tensor, Tensor]:
        p = self.pos_prior
        d = self.d
        return sample_niw(NIWPrior(mean=p.mean.expand(*batch, d), kappa=p.kappa.expand(batch), dof=p.dof.expand(batch),
                                   scale=p.scale.expand(*batch, d, d)), self.gen)

    # ------------------------------------------------------------------ initialisation
    def _initialise(self) -> None:
        C, N, K = self.C, self.N, self.cfg.n_initial_features
        # features from the posteriors of random windows of random sequences (all chains and features at once)
        seq = torch.randint(N, (C, K), generator=self.gen, device=self.device)
        n_start = (self.lengths - self.window + 1)[seq].to(self.dtype)
        start = (self._rand(C, K) * n_start).floor().long()
        post, pos_post = self._window_posterior(seq, start)
        self.field, self.noise = sample_field(post, self.gen)  # (C, K, d, p), (C, K, d, d)
        if self.tau > 0:
            self.loc, self.spread = sample_niw(pos_post, self.gen)  # (C, K, d), (C, K, d, d)
        self.F = torch.ones(C, N, K, dtype=torch.bool, device=self.device)
        self.eta = self._gamma_prior_weights((N,), K)
        self.loge = self._emission(self.field, self.noise, self.loc, self.spread)
        self.ll = self._marginal_all()
        self.s = torch.zeros(C, N, self.T, dtype=torch.long, device=self.device)
        self.phase = torch.zeros_like(self.s)
        self._sample_states()

    # ------------------------------------------------------------------ slot management
    def _compact(self) -> None:
        """Relabel each chain's slots so its owned features come first, then drop the slots no chain needs.

        Chains are independent, so a slot index means a different feature in each chain; K becomes the largest
        number of features a single chain owns (not the union over chains), which keeps the K x K transition
        products small.
        """
        owned = self.F.any(1)  # (C, K)
        K_new = int(owned.sum(-1).max())
        perm = torch.argsort((~owned).to(torch.int8), dim=-1, stable=True)  # (C, K): owned slots first
        if K_new == self.F.shape[-1] and bool((perm == torch.arange(perm.shape[-1], device=self.device)).all()):
            return
        inverse = torch.argsort(perm, dim=-1)
        C, N, K = self.F.shape
        keep = perm[:, :K_new]  # (C, K_new)
        self.F = self.F.gather(-1, keep.view(C, 1, K_new).expand(C, N, K_new))
        q = self.field.shape[-1]
        self.field = self.field.gather(1, keep.view(C, K_new, 1, 1).expand(C, K_new, self.d, q))
        self.noise = self.noise.gather(1, keep.view(C, K_new, 1, 1).expand(C, K_new, self.d, self.d))
        if self.tau > 0:
            self.loc = self.loc.gather(1, keep.view(C, K_new, 1).expand(C, K_new, self.d))
            self.spread = self.spread.gather(1, keep.view(C, K_new, 1, 1).expand(C, K_new, self.d, self.d))
        eta = self.eta.gather(2, keep.view(C, 1, K_new, 1).expand(C, N, K_new, K))
        self.eta = eta.gather(3, keep.view(C, 1, 1, K_new).expand(C, N, K_new, K_new))
        self.loge = self.loge.gather(-1, keep.view(C, 1, 1, K_new).expand(C, N, self.T, K_new))
        self.s = inverse.gather(1, self.s.reshape(C, -1)).reshape(C, N, self.T)  # phases are unchanged

    def _grow(self, n_free: int) -> None:
        """Make sure every chain has at least ``n_free`` slots it does not use."""
        free = (~self.F.any(1)).sum(-1)  # (C,)
        extra = int((n_free - free).clamp_min(0).max())
        if extra == 0:
            return
        K = self.F.shape[-1]
        m, s = self._prior_draw(self.C, extra)
        self.field = torch.cat([self.field, m], 1)
        self.noise = torch.cat([self.noise, s], 1)
        loc = spread = None
        if self.tau > 0:
            loc, spread = self._prior_draw_position(self.C, extra)
            self.loc, self.spread = torch.cat([self.loc, loc], 1), torch.cat([self.spread, spread], 1)
        self.F = torch.cat([self.F, self.F.new_zeros(self.C, self.N, extra)], -1)
        new_eta = self._gamma_prior_weights((self.N,), K + extra)
        new_eta[:, :, :K, :K] = self.eta
        self.eta = new_eta
        self.loge = torch.cat([self.loge, self._emission(m, s, loc, spread)], -1)

    # ------------------------------------------------------------------ moves
    def _shared_moves(self) -> None:
        """MH flips of every f_ik whose feature another sequence owns.

        Row i's likelihood depends on f_i only, and f_i changes only through its own decisions. Features are taken
        in random blocks of ``_BLOCK``; for a block, the likelihood of every subset of flips of every (chain,
        sequence) comes from one batched forward pass (2^b - 1 variants per row). The decisions then run feature by
        feature and sequence by sequence, each reading the likelihood of its current subset, with the IBP
        conditional m_{-i,k} / (c + N - 1) of the current matrix: an exact sequential Metropolis-Hastings scan
        with b times fewer forward passes.
        """
        C, N, K = self.F.shape
        c_conc = self.cfg.feature_concentration
        order = torch.randperm(K, generator=self.gen, device=self.device)
        order = order[self.F.any(1).any(0)[order]].tolist()  # slots some sequence owns
        # IBP log odds log m - log(c + N - 1 - m) of owning a feature m other sequences own, m = 1..N - 1 (read at
        # max(m, 1); entry 0, and entry 1 when N = 1, are never used by an eligible flip)
        m_others = torch.arange(max(N, 2), dtype=self.dtype, device="cpu").clamp_min(1)  # read on the host
        log_odds = shared_log_odds(m_others, N, c_conc).numpy()
        for start in range(0, len(order), _BLOCK):
            block = order[start : start + _BLOCK]
            b = len(block)
            n_sub = 2**b
            masks = torch.tensor([[(s >> j) & 1 for j in range(b)] for s in range(1, n_sub)], dtype=torch.bool,
                                 device=self.device)  # (n_sub - 1, b)  # fmt: skip
            flip = torch.zeros(n_sub - 1, K, dtype=torch.bool, device=self.device)
            flip[:, block] = masks
            f_var = self.F.unsqueeze(2) ^ flip.view(1, 1, n_sub - 1, K)  # (C, N, n_sub - 1, K)
            # a feature no sequence of a chain owns stays unowned there through the scan (a flip needs another
            # owner): the subsets that flip it are never read, and only the others are scored
            live = self.F[:, :, block].any(1)  # (C, b)
            need = ~(masks.unsqueeze(0) & ~live.unsqueeze(1)).any(-1)  # (C, n_sub - 1)
            rows = need.unsqueeze(1).expand(C, N, n_sub - 1).reshape(-1)
            ll_var = torch.full((C * N * (n_sub - 1),), _NEG_INF, dtype=self.dtype, device=self.device)
            if bool(rows.any()):
                dwell = self._flat_dwell(n_sub - 1)
                ll_var[rows] = self._marginal(
                    f_var.reshape(-1, K)[rows],
                    self.eta.unsqueeze(2).expand(C, N, n_sub - 1, K, K).reshape(-1, K, K)[rows],
                    self.loge.unsqueeze(2).expand(C, N, n_sub - 1, self.T, K).reshape(-1, self.T, K)[rows],
                    self.lengths.view(1, N, 1).expand(C, N, n_sub - 1).reshape(-1)[rows],
                    None if dwell is None else dwell[rows],
                )
            ll_var = ll_var.view(C, N, n_sub - 1)
            table = torch.cat([self.ll.unsqueeze(-1), ll_var], -1)  # (C, N, n_sub): index = subset bit mask
            log_u = torch.log(self._rand(b, C, N))
            # the scan's decisions are on (C,) vectors: in NumPy on the host, where a tensor op's overhead would be
            # most of their cost (the values are the tensors' own: the same decisions)
            tab, lu = table.cpu().numpy(), log_u.cpu().numpy()
            f_blk = self.F[:, :, block].cpu().numpy()  # (C, N, b), edited in place, written back after the scan
            n_own = self.F.sum(-1).cpu().numpy()  # (C, N)
            state = np.zeros((C, N), dtype=np.int64)
            chains = np.arange(C)
            n_acc = n_tried = 0
            for j in range(b):
                for i in torch.randperm(N, generator=self.gen, device=self.device).tolist():
                    own = f_blk[:, i, j]
                    others = f_blk[:, :, j].sum(1) - own
                    eligible = (others > 0) & ~(own & (n_own[:, i] == 1))
                    odds = log_odds[np.maximum(others, 1)]
                    cur = state[:, i]
                    prop = cur ^ (1 << j)
                    with np.errstate(invalid="ignore"):  # -inf - -inf where neither subset has a usable state
                        log_a = tab[chains, i, prop] - tab[chains, i, cur] + np.where(own, -odds, odds)
                    ok = eligible & (lu[j, :, i] < log_a)  # NaN compares false: not accepted, as with tensors
                    n_acc += int(ok.sum())
                    n_tried += int(eligible.sum())
                    f_blk[:, i, j] = own ^ ok
                    state[:, i] = np.where(ok, prop, cur)
                    n_own[:, i] += np.where(ok, np.where(own, -1, 1), 0)
            self.accept["shared"][0] += n_acc
            self.accept["shared"][1] += n_tried
            self.F[:, :, block] = torch.from_numpy(f_blk).to(self.device)
            state_t = torch.from_numpy(state).to(self.device)
            self.ll = table.gather(-1, state_t.unsqueeze(-1)).squeeze(-1)

    def _window_posterior(self, seq: Tensor, start: Tensor) -> tuple[FieldPrior, NIWPrior | None]:
        """Field posterior (and, when tau > 0, tempered position posterior) of the windows x^(seq)[start : start +
        L_seq]; seq and start (...) long."""
        Lmax = int(self.window.max())
        offs = torch.arange(Lmax, device=self.device)
        idx = (start.unsqueeze(-1) + offs).clamp_max(self.T - 1)  # (..., Lmax)
        mask = (offs < self.window[seq].unsqueeze(-1)).to(self.dtype)  # (..., Lmax)
        sq = seq.unsqueeze(-1)
        o = self.obs
        # seq (C, ...): with per-chain observations every chain reads its own
        ci = torch.arange(self.C, device=self.device).view(-1, *([1] * (sq.dim() - 1))) if o.w.dim() > 2 else 0
        cz, cu, cw, cp = (self._chain_view(t, n) for t, n in ((o.z, 3), (o.u, 3), (o.w, 2), (self.pos, 3)))
        counts, szz, suz, suu = field_statistics(cz[ci, sq, idx], cu[ci, sq, idx], cw[ci, sq, idx], mask.unsqueeze(-1))
        post = field_posterior(self.prior, counts[..., 0], szz[..., 0, :, :], suz[..., 0, :, :], suu[..., 0, :, :])
        if self.tau <= 0:
            return post, None
        n, sx, sxx = sufficient_statistics(cp[ci, sq, idx], self.tau * mask.unsqueeze(-1))
        return post, niw_posterior(self.pos_prior, n[..., 0], sx[..., 0, :], sxx[..., 0, :, :])

    def _log_window_scores(self, field: Tensor, noise: Tensor, loc: Tensor | None, spread: Tensor | None) -> Tensor:
        """log r(W | theta_ci) over the window starts of every sequence: (C, N, T), -inf on invalid starts.

        r weights a window by exp(mean log density of its samples under theta, the emission's); field (C, N, d, p).
        """
        ll = self._emission_one(field, noise, loc, spread)[..., 0]  # (C, N, T)
        csum = torch.cat([ll.new_zeros(self.C, self.N, 1), ll.cumsum(-1)], dim=-1)  # (C, N, T + 1)
        starts = torch.arange(self.T, device=self.device)
        end = (starts.view(1, -1) + self.window.view(-1, 1)).clamp_max(self.T)  # (N, T)
        score = (csum.gather(-1, end.expand(self.C, -1, -1)) - csum[..., : self.T]) / self.window.view(1, -1, 1)
        valid = starts.view(1, -1) <= (self.lengths - self.window).view(-1, 1)  # (N, T)
        return torch.log_softmax(score.masked_fill(~valid, _NEG_INF), dim=-1)

    def _emission_one(self, field: Tensor, noise: Tensor, loc: Tensor | None, spread: Tensor | None) -> Tensor:
        """(C, N, T, 1) log emission of every sample of sequence i under the parameter of (c, i): field (C, N, d, p),
        noise (C, N, d, d), loc (C, N, d), spread (C, N, d, d)."""
        o = self.obs
        ll = field_log_likelihood(self._chain_view(o.z, 3), self._chain_view(o.u, 3), self._chain_view(o.w, 2),
                                  field.unsqueeze(2), noise.unsqueeze(2), self.cfg.robust_dof)
        if self.tau > 0:
            ll = ll + self.tau * gaussian_log_density(self._chain_view(self.pos, 3), loc.unsqueeze(2),
                                                      spread.unsqueeze(2))
        return ll

    def _birth_death(self) -> None:
        """Reversible-jump birth or death of one unique feature in every (chain, sequence), all in parallel.

        Moves of different sequences do not interact (a unique feature of sequence i is not owned by any other
        sequence, and the IBP ratio of a unique birth, gamma c / ((c + N - 1)(u_i + 1)), involves row i only), so
        they are proposed and accepted jointly.
        """
        C, N = self.C, self.N
        self._grow(N)
        K = self.F.shape[-1]
        others = self.F.sum(1, keepdim=True) - self.F.long()  # (C, N, K)
        unique = self.F & (others == 0)
        n_unique = unique.sum(-1)
        n_own = self.F.sum(-1)
        birth = self._rand(C, N) < 0.5
        death = ~birth & (n_unique > 0) & (n_own > 1)
        active = birth | death
        rate = unique_feature_rate(1.0, self.cfg.feature_concentration, N) * self.mass.view(C, 1)
        n_start = (self.lengths - self.window + 1).to(self.dtype)  # (N,)
        # birth: window W ~ uniform, theta* ~ q(. | W), one free slot per (c, i)
        start_b = (self._rand(C, N) * n_start).floor().long()
        seq_all = torch.arange(N, device=self.device).expand(C, N)
        post, pos_post = self._window_posterior(seq_all, start_b)
        mp, sp = sample_field(post, self.gen)
        m0, s0 = self._prior_draw(C, N)
        from_prior = self._rand(C, N) < self.cfg.birth_prior_mix
        mean_b = torch.where(from_prior[..., None, None], m0, mp)
        cov_b = torch.where(from_prior[..., None, None], s0, sp)
        loc_b = spread_b = loc_d = spread_d = loc_t = spread_t = None
        if self.tau > 0:  # the position Gaussian is part of theta*: drawn from the same window, or the prior
            loc_w, spread_w = sample_niw(pos_post, self.gen)
            l0, c0 = self._prior_draw_position(C, N)
            loc_b = torch.where(from_prior[..., None], l0, loc_w)
            spread_b = torch.where(from_prior[..., None, None], c0, spread_w)
        free = ~self.F.any(1)  # (C, K)
        rank = free.long().cumsum(-1) - 1
        target = torch.arange(N, device=self.device).view(1, N, 1)
        slot_b = torch.argmax((free.unsqueeze(1) & (rank.unsqueeze(1) == target)).long(), -1)  # (C, N)
        # death: a unique feature chosen uniformly, auxiliary window W ~ r(. | theta)
        pick = torch.rand(C, N, K, generator=self.gen, dtype=self.dtype, device=self.device).masked_fill(~unique, -1.0)
        slot_d = torch.argmax(pick, -1)
        cidx = torch.arange(C, device=self.device).view(C, 1)
        mean_d, cov_d = self.field[cidx, slot_d], self.noise[cidx, slot_d]
        # one set of window scores for the parameter each move is about
        mean_t = torch.where(birth[..., None, None], mean_b, mean_d)
        cov_t = torch.where(birth[..., None, None], cov_b, cov_d)
        if self.tau > 0:
            loc_d, spread_d = self.loc[cidx, slot_d], self.spread[cidx, slot_d]
            loc_t = torch.where(birth[..., None], loc_b, loc_d)
            spread_t = torch.where(birth[..., None, None], spread_b, spread_d)
        log_r_all = self._log_window_scores(mean_t, cov_t, loc_t, spread_t)  # (C, N, T)
        start_d = torch.multinomial(torch.exp(log_r_all).reshape(C * N, self.T), 1, generator=self.gen).reshape(C, N)
        start_t = torch.where(birth, start_b, start_d)
        log_r = log_r_all.gather(-1, start_t.unsqueeze(-1)).squeeze(-1)
        post_t, pos_post_t = self._window_posterior(seq_all, start_t)
        eps = self.cfg.birth_prior_mix
        log_prior_theta = field_log_density(mean_t, cov_t, self.prior)
        log_q_window = field_log_density(mean_t, cov_t, post_t)
        if self.tau > 0:
            log_prior_theta = log_prior_theta + niw_log_density(loc_t, spread_t, self.pos_prior)
            log_q_window = log_q_window + niw_log_density(loc_t, spread_t, pos_post_t)
        log_q = torch.logaddexp(math.log1p(-eps) + log_q_window, math.log(eps) + log_prior_theta)
        n_big = torch.where(birth, n_unique + 1, n_unique).clamp_min(1).to(self.dtype)
        log_extra = torch.log(rate) - torch.log(n_big) + log_prior_theta - log_q + log_r + torch.log(n_start)
        # proposed feature rows and emission columns
        slot = torch.where(birth, slot_b, slot_d)
        f_new = self.F.clone()
        f_new.scatter_(-1, slot.unsqueeze(-1), birth.unsqueeze(-1))
        le_b = self._emission_one(mean_b, cov_b, loc_b, spread_b)  # (C, N, T, 1)
        le_new = self.loge.clone()
        le_new.scatter_(-1, slot_b.view(C, N, 1, 1).expand(C, N, self.T, 1), le_b)
        ll_new = self._marginal(
            f_new.reshape(C * N, K), self.eta.reshape(C * N, K, K), le_new.reshape(C * N, self.T, K), self.lengths.repeat(C),
            self._flat_dwell(),
        ).reshape(C, N)
        log_a = ll_new - self.ll + torch.where(birth, log_extra, -log_extra)
        ok = active & (torch.log(self._rand(C, N)) < log_a)
        for name, mask in (("birth", birth), ("death", death)):
            self.accept[name][0] += int((ok & mask).sum())
            self.accept[name][1] += int(mask.sum())
        if not bool(ok.any()):
            return
        self.F = torch.where(ok.unsqueeze(-1), f_new, self.F)
        self.ll = torch.where(ok, ll_new, self.ll)
        born = ok & birth
        if bool(born.any()):
            c_idx, i_idx = torch.nonzero(born, as_tuple=True)
            sb = slot_b[c_idx, i_idx]
            self.field[c_idx, sb] = mean_b[c_idx, i_idx]
            self.noise[c_idx, sb] = cov_b[c_idx, i_idx]
            if self.tau > 0:
                self.loc[c_idx, sb] = loc_b[c_idx, i_idx]
                self.spread[c_idx, sb] = spread_b[c_idx, i_idx]
            self.loge = self._emission(self.field, self.noise, self.loc, self.spread)

    def _sample_states(self) -> None:
        C, N, K = self.F.shape
        f = self.F.reshape(C * N, K)
        D = self.D
        lengths = self.lengths.repeat(C)
        le = self._expand(self.loge.reshape(C * N, self.T, K), f, lengths, self._flat_dwell())
        init, P = expand_min_duration(initial_distribution(f, self.dtype), transition_matrix(self.eta.reshape(C * N, K, K), f), D)
        lengths = self.lengths.repeat(C)
        es = _ffbs(le, init, P, lengths, self.gen).reshape(C, N, self.T)
        self.s, self.phase = es // D, es % D

    def _sample_parameters(self) -> None:
        C, N, K = self.F.shape
        onehot = torch.nn.functional.one_hot(self.s, K).to(self.dtype) * self.valid.unsqueeze(-1).to(self.dtype)
        o = self.obs
        w = o.w.expand(C, N, self.T)
        if self.cfg.robust_dof is not None:  # Student t as a scale mixture: lambda_t | state, residual
            nu = self.cfg.robust_dof
            _, q = field_log_likelihood(self._chain_view(o.z, 3), self._chain_view(o.u, 3), self._chain_view(o.w, 2),
                                        self.field.unsqueeze(1), self.noise.unsqueeze(1), nu, maha_out=True)  # (C, N, T, K)
            q_s = q.gather(-1, self.s.unsqueeze(-1)).squeeze(-1)
            shape = torch.full_like(q_s, 0.5 * (nu + self.d))
            lam = sample_gamma(shape, self.gen) / (0.5 * (nu + q_s))
            w = w * lam
        z, u, _, _ = self._flat_observations()
        stats = field_statistics(z, u, w.reshape(C, N * self.T), onehot.reshape(C, N * self.T, K))
        self.field, self.noise = sample_field(field_posterior(self.prior, *stats), self.gen)
        if self.tau > 0:
            pos_stats = self._position_statistics(onehot.reshape(C, N * self.T, K))
            self.loc, self.spread = sample_niw(niw_posterior(self.pos_prior, *pos_stats), self.gen)
        trans = transition_counts(self.s, self.lengths.expand(C, N), K, free_transitions(self.phase, self.D)).to(self.dtype)
        self.eta = sample_transition_weights_posterior(
            trans, self.F, self.alpha.view(C, 1, 1, 1), self.kappa.view(C, 1, 1, 1), self.gen
        )
        if self.dwell is not None:  # (mu, delta, sigma^2) | phases: the NIG posterior (module docstring, "Dwell")
            beta, noise = sample_field(dwell_posterior(self.dwell_prior, self.dwell, self.dwell_mask, self.phase),
                                       self.gen)  # (C, 1, 1, 2), (C, 1, 1, 1)
            self.dwell_beta, self.dwell_noise = beta.reshape(C, 2), noise.reshape(C)
            self.dwell_ll = dwell_log_likelihood(self.dwell, self.dwell_mask, self.dwell_beta, self.dwell_noise)
        self.loge = self._emission(self.field, self.noise, self.loc, self.spread)
        self.ll = self._marginal_all()

    def _sample_hyperparameters(self) -> None:
        C, N, K = self.F.shape
        c_conc = self.cfg.feature_concentration
        # gamma | F ~ Gamma(1 + K+, 1 + sum_n c / (c + n - 1))  (Gamma(1, 1) prior)
        k_plus = (self.F.any(1)).sum(-1).to(self.dtype)
        harmonic = sum(c_conc / (c_conc + j) for j in range(N))
        self.mass = sample_gamma(1.0 + k_plus, self.gen) / (1.0 + harmonic)
        # alpha, kappa | pi: random-walk Metropolis on the log, Gamma(1, 0.01) priors (vague)
        P = transition_matrix(self.eta, self.F)
        for name in ("alpha", "kappa"):
            cur = getattr(self, name)
            prop = cur * torch.exp(0.3 * torch.randn(C, generator=self.gen, dtype=self.dtype, device=self.device))
            def log_post(a_val: Tensor, k_val: Tensor) -> Tensor:
                out = torch.stack([
                    dirichlet_log_density_rows(P[c], self.F[c], float(a_val[c]), float(k_val[c])).sum() for c in range(C)
                ])
                return out - 0.01 * a_val - 0.01 * k_val
            a_cur, k_cur = self.alpha, self.kappa
            a_new, k_new = (prop, k_cur) if name == "alpha" else (a_cur, prop)
            log_a = log_post(a_new, k_new) - log_post(a_cur, k_cur) + torch.log(prop) - torch.log(cur)
            ok = torch.log(self._rand(C)) < log_a
            setattr(self, name, torch.where(ok, prop, cur))
        # The weights outside the owned blocks and the row totals S_j of the owned blocks are auxiliary variables with
        # the sticky Gamma prior given (alpha, kappa) (transitions.py); pi does not depend on them. Redraw them under
        # the new (alpha, kappa), keeping pi: without this, features switched on later would get weights drawn
        # under stale hyperparameters.
        fresh = self._gamma_prior_weights((N,), K)  # (C, N, K, K) under the current alpha, kappa
        f = self.F.to(self.dtype)
        block = f.unsqueeze(-1) * f.unsqueeze(-2)
        total = (fresh * block).sum(-1, keepdim=True)  # S_j ~ Gamma(sum of the owned shapes of row j)
        self.eta = torch.where(block > 0, P * total, fresh)

    def _joint_log_prob(self) -> Tensor:
        C, N, K = self.F.shape
        f = self.F
        le = torch.gather(self.loge, -1, self.s.unsqueeze(-1)).squeeze(-1)  # (C, N, T)
        lp = (le * self.valid).sum((-1, -2))
        P = transition_matrix(self.eta, f)  # (C, N, K, K)
        init = initial_distribution(f, self.dtype)
        lp = lp + torch.log(torch.gather(init, -1, self.s[..., :1]).squeeze(-1)).sum(-1)
        prev, nxt = self.s[..., :-1], self.s[..., 1:]
        trans = P.gather(-2, prev.unsqueeze(-1).expand(C, N, self.T - 1, K)).gather(-1, nxt.unsqueeze(-1)).squeeze(-1)
        free = free_transitions(self.phase, self.D) & self.valid[:, 1:]  # forced phase moves have probability 1
        lp = lp + (torch.log(trans.clamp_min(1e-300)) * free).sum((-1, -2))
        owned = f.any(1)  # (C, K)
        lp = lp + (field_log_density(self.field, self.noise, self.prior) * owned).sum(-1)
        if self.tau > 0:
            lp = lp + (niw_log_density(self.loc, self.spread, self.pos_prior) * owned).sum(-1)
        if self.dwell is not None:
            lp = lp + dwell_log_prob(self.dwell_prior, self.dwell, self.dwell_mask, self.phase, self.dwell_beta,
                                     self.dwell_noise)
        for c in range(C):
            lp[c] = lp[c] + ibp_log_prior(f[c], self.mass[c], self.cfg.feature_concentration).to(self.dtype)
            lp[c] = lp[c] + dirichlet_log_density_rows(P[c], f[c], float(self.alpha[c]), float(self.kappa[c])).sum()
        return lp

    def _collapsed_log_prob(self) -> Tensor:
        """(C,) collapsed score of every chain's current (s, F): :meth:`_collapsed_score`."""
        return self._collapsed_score(self.s, self.F, self.phase, self.alpha, self.kappa, self.mass)

    def _profile_scales(self, age: Tensor | None, w: Tensor, onehot: Tensor) -> Tensor:
        """(B, n) Student-t scales lambda_t at their conditional mode given the posterior-mean field of the labelling
        ``onehot`` (B, n, K) (samples seen as :meth:`_score_view` says, weights w): the mode of Gamma((nu + d) / 2,
        (nu + q_t) / 2), q_t the squared Mahalanobis residual."""
        nu, d = self.cfg.robust_dof, self.d
        mean, psi = field_mixture_posterior_mean(self.score_prior, *self._stats(age, w, onehot),
                                                 self.cfg.straight_weight, self.wide_score_prior,
                                                 self.cfg.rotation_weight)
        B, n, K = onehot.shape
        prec = torch.cholesky_inverse(torch.linalg.cholesky(psi))  # (B, K, d, d)
        if age is None:
            # one view for all labellings: q_t = (u_t - B z_t)^T P (u_t - B z_t) = x_t^T M x_t with x_t = [u_t, z_t],
            # M = [[P, -P B], [-B^T P, B^T P B]] (P = Psi^-1), as one GEMM of the samples' outer products x_t x_t^T
            # against every state's M (n, (d+p)^2) @ ((d+p)^2, B K); each sample keeps its own state's
            pb = prec @ mean
            m = torch.cat([torch.cat([prec, -pb], -1), torch.cat([-pb.transpose(-1, -2), mean.transpose(-1, -2) @ pb],
                                                                  -1)], -2)  # (B, K, d + p, d + p)
            q_all = (self.white_outer[0] @ m.reshape(B * K, -1).T).view(n, B, K).transpose(0, 1)
            q = (q_all * onehot).sum(-1)
        else:  # every labelling its own view: the residual under each sample's own state (padding rows: q = 0)
            own_field = (onehot @ mean.flatten(-2)).unflatten(-1, mean.shape[-2:])  # (B, n, d, p)
            own_prec = (onehot @ prec.flatten(-2)).unflatten(-1, (d, d))
            z, u = self._viewed(age)
            r = u - (own_field @ z.unsqueeze(-1)).squeeze(-1)  # (B, n, d)
            q = (r.unsqueeze(-2) @ own_prec @ r.unsqueeze(-1)).reshape(B, n)
        return max(nu + d - 2.0, 1e-3) / (nu + w * q)

    def _state_terms(self, onehot: Tensor, s: Tensor) -> Tensor:
        """(B, K) the per-state terms of :meth:`_collapsed_score` for the labelling ``onehot`` (B, N T, K) (0 on
        padding) of the labels s (B or 1, N, T): the reliability Jacobian and Student-t profile terms of each state's
        samples, its field evidence and its tempered position evidence. Each depends on the samples of its own state
        alone (with a tolerance correlation, also on which of them start a run). With the block emission only the
        position terms: the block evidence couples the states (:meth:`_block_deltas`)."""
        B, n, K = onehot.shape
        if self.blocks is not None:
            lp = onehot.new_zeros(B, K)
            if self.tau > 0:
                lp = lp + niw_log_marginal_likelihood(self.pos_prior, *self._position_statistics(onehot))
                lp = lp + self._occupancy_terms(onehot)
            return lp
        age, w, jac = self._score_view(s)
        w = w.expand(B, n)
        lp = (onehot * jac.unsqueeze(-1)).sum(-2)
        nu = self.cfg.robust_dof
        if nu is not None:
            lam = self._profile_scales(age, w, onehot)
            half = 0.5 * nu
            log_gamma = half * math.log(half) - math.lgamma(half) + (half - 1.0) * torch.log(lam) - half * lam
            lp = lp + (onehot * (log_gamma + 0.5 * self.d * torch.log(lam)).unsqueeze(-1)).sum(-2)
            w = w * lam
        lp = lp + self._field_evidence(age, w, onehot)
        if self.tau > 0:
            lp = lp + niw_log_marginal_likelihood(self.pos_prior, *self._position_statistics(onehot))
            lp = lp + self._occupancy_terms(onehot)
        return lp

    def _collapsed_score(self, s: Tensor, F: Tensor, phase: Tensor, alpha: Tensor, kappa: Tensor,
                         mass: Tensor) -> Tensor:
        """(B,) log p(u, s, F | z) with the fields, their noise and the transition weights integrated out: the sum
        of :meth:`_collapsed_score_parts`. s, phase (B, N, T) long, F (B, N, K) bool; alpha, kappa, mass (B,).
        Reported with the returned sample (``SamplerResult.collapsed_log_prob``); the objective of
        ``selection="map"`` (module docstring, "Which sample")."""
        return sum(self._collapsed_score_parts(s, F, phase, alpha, kappa, mass).values())

    def _collapsed_score_parts(self, s: Tensor, F: Tensor, phase: Tensor, alpha: Tensor, kappa: Tensor,
                               mass: Tensor, block: bool = True) -> dict[str, Tensor]:
        """The terms of :meth:`_collapsed_score`, each (B,): "emission" (the states' field evidence with the
        Student-t profile, the reliability Jacobian and the tempered position evidence), "dwell" (0 without the
        dwell term), "transitions", "initial" and "features" (the IBP prior of F). ``block=False``: the emission
        without the block emission's evidence (the map search scores its changes by :meth:`_block_deltas`).

        Terms: the IBP prior of F; per sequence the
        uniform initial state and the Dirichlet-multinomial of the free transitions,
        sum_j [log Gamma(A_j) - log Gamma(A_j + n_j) + sum_k (log Gamma(a_jk + n_jk) - log Gamma(a_jk))] with
        a_jk = alpha + kappa delta_jk over the owned features; per state the MNIW evidence of its samples
        (:func:`~lfd_torch.segmentation.field.field_log_marginal_likelihood`). The Student-t scale variables
        lambda_t are set to their conditional mode given the posterior-mean field of the labelling itself (a
        profile over lambda), so the score is a function of (s, F) alone.
        """
        B, N, K = F.shape
        T, d = self.T, self.d
        valid = self.valid.to(self.dtype)
        onehot = (torch.nn.functional.one_hot(s, K).to(self.dtype) * valid.unsqueeze(-1)).reshape(B, N * T, K)
        age, w, jac = self._score_view(s)
        lp = jac.sum(-1)
        parts = {}
        nu = self.cfg.robust_dof
        if self.blocks is not None:  # the states' motion on the block means instead of the grid directions
            lp = self._block_evidence(s, age, w, onehot) if block else lp.new_zeros(B)
        elif nu is not None:
            lam = self._profile_scales(age, w, onehot)
            half = 0.5 * nu
            log_gamma = half * math.log(half) - math.lgamma(half) + (half - 1.0) * torch.log(lam) - half * lam
            flat_valid = valid.reshape(1, N * T)
            lp = lp + ((log_gamma + 0.5 * d * torch.log(lam)) * flat_valid).sum(-1)
            w = w * lam
        if self.blocks is None:
            lp = lp + self._field_evidence(age, w, onehot).sum(-1)
        if self.tau > 0:  # the tempered NIW evidence of each state's positions (and of its occupancies)
            lp = lp + niw_log_marginal_likelihood(self.pos_prior, *self._position_statistics(onehot)).sum(-1)
            lp = lp + self._occupancy_terms(onehot).sum(-1) + self._occupancy_constant()
        parts["emission"] = lp
        parts["dwell"] = (lp.new_zeros(B) if self.dwell is None
                          else dwell_evidence(self.dwell_prior, self.dwell, self.dwell_mask, phase,
                                         self.pace_ratios))
        counts = transition_counts(s, self.lengths.expand(B, N), K, free_transitions(phase, self.D)).to(self.dtype)
        parts["transitions"] = dirichlet_multinomial_log_prob(counts, F, alpha.view(B, 1, 1, 1),
                                                              kappa.view(B, 1, 1, 1)).sum(-1)
        parts["initial"] = -torch.log(F.sum(-1).clamp_min(1).to(self.dtype)).sum(-1)  # uniform initial state
        parts["features"] = ibp_log_prior(F, mass, self.cfg.feature_concentration).to(self.dtype).expand(B)
        return parts

    # ------------------------------------------------------------------ driver
    def sample(self) -> SamplerResult:
        cfg = self.cfg
        n_iter = cfg.n_iterations
        trace = torch.empty(self.C, n_iter, dtype=self.dtype, device="cpu")  # diagnostics are kept on the CPU
        n_feat = torch.empty(self.C, n_iter, dtype=torch.long, device="cpu")
        start_keep = int(cfg.burn_in * n_iter)
        best_lp = torch.full((self.C,), _NEG_INF, dtype=self.dtype, device=self.device)
        best: list[dict | None] = [None] * self.C
        kept: list[dict] = []  # selection="modal": every kept sample (it is chosen after the last sweep)
        iterator = range(n_iter)
        if cfg.progress:
            from tqdm.auto import tqdm

            iterator = tqdm(iterator, desc="BP-GM-HMM sweeps", leave=False)
        for it in iterator:
            self._compact()
            self._shared_moves()
            self._birth_death()
            self._compact()  # drop the free slots the births did not use before the O(K^2) steps
            self._sample_states()
            self._sample_parameters()
            if cfg.resample_hyperparameters:
                self._sample_hyperparameters()
            joint = self._joint_log_prob()
            trace[:, it] = joint.cpu()
            n_feat[:, it] = self.F.any(1).sum(-1).cpu()
            if it >= start_keep and cfg.selection == "modal":
                n_runs = self._runs_per_sequence()
                for c in range(self.C):
                    kept.append({**self._snapshot(c), "joint": float(joint[c]), "runs": n_runs[c],
                                 "phase": self.phase[c].clone(), "chain": c})
            elif it >= start_keep:
                collapsed = self._collapsed_log_prob() if cfg.selection in ("collapsed", "map") else None
                lp = joint if collapsed is None else collapsed
                better = lp > best_lp
                if collapsed is None and bool(better.any()):  # reported with the sample: only for a new best
                    collapsed = self._collapsed_log_prob()
                for c in torch.nonzero(better).reshape(-1).tolist():
                    best_lp[c] = lp[c]
                    best[c] = {**self._snapshot(c), "joint": float(joint[c]), "collapsed": float(collapsed[c])}
        if cfg.selection == "modal":
            snap = self._modal_sample(kept)
            c_best = snap["chain"]
        elif cfg.selection == "map":
            starts = [b for b in best if b is not None]
            polished = [self._climb_to_mode(b, shifts=False) for b in starts]
            c_best = max(range(len(polished)), key=lambda c: polished[c]["collapsed"])
            # the best mode, its boundaries moved too
            snap = self._climb_to_mode(polished[c_best], shifts=True, settled=True)
            if cfg.tolerance_correlation is None:
                snap = self._learn_tolerance(snap)
            if (self.rho, self.sigma, self.tau_white) != (0.0, cfg.direction_noise, 0.0):
                # the fields reported are the default white tolerance's posterior means of the labelling
                tol = self.rho, self.sigma, self.tau_white
                self._set_tolerance(0.0)
                field_w, noise_w = self._posterior_mean_fields(snap["states"], snap["features"].shape[-1])
                self._set_tolerance(*tol)
                snap = {**snap, "field": field_w, "noise": noise_w}
            snap = {**snap, "hyper": {**snap["hyper"], "tolerance_correlation": self.rho,
                                      "tolerance_scale": self.sigma, "tolerance_floor": self.tau_white}}
        else:
            c_best = int(torch.argmax(best_lp))
            snap = best[c_best]
        assert snap is not None
        acceptance = {k: (v[0] / v[1] if v[1] else float("nan")) for k, v in self.accept.items()}
        switch_scores = None if self.blocks is None else self._switch_scores(snap)
        return SamplerResult(
            states=snap["states"],
            lengths=self.lengths.clone(),
            features=snap["features"],
            field=snap["field"],
            noise=snap["noise"],
            centre=self.obs.centre,
            radius=self.obs.radius,
            log_prob=snap["joint"],
            collapsed_log_prob=snap["collapsed"],
            trace=trace,
            n_features_trace=n_feat,
            chain=c_best,
            hyperparameters={**snap["hyper"], **self._dwell_summary(snap["states"])},
            acceptance=acceptance,
            switch_scores=switch_scores,
        )

    def _switch_scores(self, snap: dict) -> list[list[tuple[int, Tensor]]]:
        """:attr:`SamplerResult.switch_scores` of the labelling of ``snap``: every admissible position of each
        switch, the other switches where they are, scored as the shift move scores its candidates
        (:meth:`_shift_scores`: the collapsed score's change, the block emission's components held)."""
        s, F = snap["states"], snap["features"]
        hyper = [torch.tensor([snap["hyper"][k]], dtype=self.dtype, device=self.device)
                 for k in ("transition_concentration", "stickiness", "feature_mass")]
        score = self._collapsed_score(s[None], F[None], duration_phases(s[None], self.D), *hyper)[0]
        D = self.D
        spans = []  # (sequence, first sample of run r, end of run r + 1, a, b, first j0, last j)
        runs = _runs(s, self.lengths)
        for i, run in enumerate(runs):
            for (lo, c, a), (_, hi, b) in zip(run[:-1], run[1:]):
                spans.append((i, lo, hi, a, b, min(lo + D, c), max(hi - D, c)))
        out: list[list[tuple[int, Tensor]]] = [[] for _ in runs]
        if not spans:
            return out
        sp = torch.tensor(spans, dtype=torch.long, device=self.device)
        seq, lo, hi, a, b, j0, j1 = sp.unbind(1)
        width = j1 - j0 + 1
        owner, rows = self._moved_switches(s, seq, lo, hi, a, b, j0, j1)
        P = owner.numel()
        cand = s.unsqueeze(0).expand(P, -1, -1).clone()
        cand[torch.arange(P, device=self.device), seq[owner]] = rows
        cand_f = F.unsqueeze(0).expand(P, -1, -1)
        touched = torch.stack([a[owner], b[owner], torch.full_like(a[owner], -1)], 1)
        scores = torch.cat([self._shift_scores(s, F, *part, score, hyper)
                            for part in zip(*(x.split(_SHIFT_CHUNK) for x in (cand, cand_f, seq[owner], touched)))])
        for i, start, first, n in zip(seq.tolist(), j0.tolist(), (width.cumsum(0) - width).tolist(), width.tolist()):
            out[i].append((start, scores[first : first + n].cpu()))
        return out

    def _best_tolerance(self, snap: dict) -> float:
        """Set the tolerance of :data:`TOLERANCES` under which the labelling of ``snap`` has the highest collapsed
        score (type-II maximum likelihood of (rho, sigma, tau) given (s, F), a uniform prior on the grid); return
        that score."""
        hyper = [torch.tensor([snap["hyper"][k]], dtype=self.dtype, device=self.device)
                 for k in ("transition_concentration", "stickiness", "feature_mass")]
        s, F = snap["states"][None], snap["features"][None]
        phase = duration_phases(s, self.D)
        scores = []
        for tol in TOLERANCES:
            self._set_tolerance(*tol)
            scores.append(float(self._collapsed_score(s, F, phase, *hyper)[0]))
        best = max(range(len(scores)), key=scores.__getitem__)
        self._set_tolerance(*TOLERANCES[best])
        return scores[best]

    def _learn_tolerance(self, snap: dict) -> dict:
        """``tolerance_correlation=None``: coordinate ascent of the collapsed score over (s, F) and the tolerance
        (rho, sigma, tau) (module docstring, "Correlated tolerance") from a mode of the map search under the present
        tolerance: the labelling of ``snap`` scored under every tolerance of :data:`TOLERANCES`; under a better one
        the map search goes on from it; until the tolerance stays."""
        for _ in range(len(TOLERANCES)):
            current = (self.rho, self.sigma, self.tau_white)
            if self._best_tolerance(snap) <= snap["collapsed"] + 1e-9 * abs(snap["collapsed"]):
                self._set_tolerance(*current)
                break  # the current tolerance is (one of) the best: a mode in (s, F, rho, sigma, tau)
            snap = self._climb_to_mode(self._climb_to_mode(snap, shifts=False), shifts=True, settled=True)
        return snap

    def _climb_to_mode(self, snap: dict, shifts: bool = True, settled: bool = False) -> dict:
        """``selection="map"``: coordinate ascent of the collapsed score from a sample (module docstring).

        Moves, each kept only when the collapsed score :meth:`_collapsed_score` rises, repeated until none does (a
        local mode of p(s, F | u, z)). Each round tries them in the order below and starts the next round as soon
        as one is kept, so the relabelling, the cheapest move and the one kept most often, is iterated to its fixed
        point before any of the costlier moves, whose candidates are scored by the hundred, is tried (order and
        measurements: ``experiments/segmentation_studies.md``, "Order of the moves"):
            relabel: the Viterbi state sequences of every sequence under the posterior means of the fields, noise
                and transition weights given the current labelling (features it owns but no longer uses dropped);
            merge: all K (K - 1) / 2 merges of a pair of states (the runs of k relabelled j, f_j <- f_j or f_k, slot
                k dropped) scored in one batched call, the best one taken; when none raises the score, the
                ``_LOOKAHEAD`` best are tried once more with a relabelling after them (two moves as one); in the
                chains' ascents (without ``shifts``), when none of those does either, the first of them (the best
                merge by its own score) relabelled on while that raises its score (at most ``_SETTLE_STEPS`` times,
                :meth:`_settle`): a merge judged once the relabelling has settled, as the ascent judges every other
                move (LASA Sshape, sampler seed 0: a merge that needs 5 relabellings to rise above a 6-state mode,
                and 5 steps instead of 6; only in the chains' ascents because the last ascent, whose rounds mostly
                end in a shift, would repeat it in every round: settling all ``_LOOKAHEAD`` merges in every ascent
                cost 0.7-3.4 s per LASA run of 7 demonstrations, the first one in the chains' ascents 0.04-0.24 s,
                one-off measurements);
            reassign: in one sequence, the runs of one state given to another state or to a new one (the best of all
                such moves, scored in one batched call as the current score plus the change of the terms the move
                touches, :meth:`_reassignment_scores`, then confirmed by the full score): the partial merges and
                splits of state sharing;
            shift (:meth:`_shifts`, with ``shifts`` and only when none of the above raises the score): in one
                sequence, one switch moved by up to D grid points, or one run removed and the switch between its
                neighbours placed within D grid points of it (all such moves scored in one batched call as the
                current score plus the change of the terms they touch, :meth:`_shift_scores`; the improving moves
                with disjoint regions taken at once, else the best of every sequence, else the best alone, confirmed
                by the full score, :meth:`_shift_step`; under the block emission, when no candidate rises, they
                are scored again with a new state's component free, :meth:`_block_deltas`;
                shift steps are repeated while they raise the score before
                the round starts again, since after a shift the cheaper moves rarely rise: LASA Multi_Models_3,
                block emission, sampler seeds 0-3: the same labellings, 0.3-1.0 s less of 10-13 s, one-off
                timings): the change-point
                moves of a segmentation sampler (move a boundary; delete a segment), which the moves above make
                only through the Viterbi relabelling under fields fitted to the old boundaries. Without it the
                search stopped at a labelling whose boundaries its own fields held in place (benchmark family
                scoop_const_3d, one demonstration, case 0: a short third run 3.8 nats below the best two-run
                labelling, kept on 2 of 10 sampler seeds; 10 of 10 find the two runs with it). The sampler climbs
                every chain without it and then the best chain's mode with it (on LASA Multi_Models_3 shifts on
                all four chains doubled the time of ``segment``);
            split (only when none of the above raises the score): one state's runs cut in halves, the second halves
                a new state, then a relabelling; states tried most used first, the first that raises the score
                kept. It is the split of split-merge samplers taken greedily: without it a chain that had carried
                two consecutive steps by one state could not separate them (LASA Multi_Models_3 with the position
                term: 6 steps on route {0-3} on 5 of 10 seeds without it, at commit 2f6f509, and 9 with it).
                With ``shifts``, when no split raises the score, the best relabelled split is polished by shift
                moves alone (each raising its score, until it is above the current labelling, at most
                ``_POLISH_STEPS``) and kept if it then is: the relabelling places the new switches from fields fitted
                to the halves, a grid point or two off, and the split pays for that before the shifts recover it
                (LASA Multi_Models_1 with ``tolerance_correlation=None``: route {0-2} in 4 steps on 7 of 10 seeds, a
                mode 1.3 nats below the 5 steps the other three reach, without it; 5 steps on 10 of 10 with it). The
                cap bounds the time it adds where it fails (every sequence's best switch moves in one step; on 7
                LASA demonstrations a step costs about 0.1 s);
            shared birth (with ``shifts`` under the block emission, only when none of the above raises the score,
                :meth:`_shared_birth_step`): where the runs that follow (or precede) one state carry different
                states in different sequences, their first (last) third, half or two thirds given to one new state,
                then the best reassignment, the best polished by shifts. A step the demonstrations share that no one
                state carries is two moves away, each of which lowers the score alone (LASA Multi_Models_4, sampler
                seed 4: the birth 6.6 nats below the mode, then demonstration 3's last state given to the others'
                5.6 above it; route {0-3} in 3 steps on seeds 4 and 6 without the move, 4 with it).
        The look-ahead and split candidates are relabelled and scored as one batch each, then taken in order (the
        first that raises the score), which gives the same ascent as one at a time. The moves are deterministic, so
        two evaluations that would find nothing are skipped, with the same ascent: ``settled`` (``snap`` is the
        result of an ascent without ``shifts``) starts the first round at the shift step, and a shift step is not
        tried again at the labelling where the last one found nothing. The fields returned with it are
        those posterior means; the joint log probability of a polished sample is
        not defined (no sampled parameters): nan.
        """
        s, F = snap["states"], snap["features"]
        hyper = [torch.tensor([snap["hyper"][k]], dtype=self.dtype, device=self.device)
                 for k in ("transition_concentration", "stickiness", "feature_mass")]

        def score_of(s_b: Tensor, f_b: Tensor) -> Tensor:
            batch = [h.expand(s_b.shape[0]) for h in hyper]
            return self._collapsed_score(s_b, f_b, duration_phases(s_b, self.D), *batch)

        score = score_of(s[None], F[None])[0]
        skip = settled  # the relabel, merge and reassign moves found nothing at snap
        stuck: tuple[Tensor, Tensor] | None = None  # where the last shift step found nothing
        while True:
            moved = False
            if not skip:
                s2, F2 = self._viterbi_relabel(s, F, float(hyper[0]), float(hyper[1]))
                if not (torch.equal(s2, s) and torch.equal(F2, F)):
                    sc = score_of(s2[None], F2[None])[0]
                    if bool(sc > score):
                        s, F, score, moved = s2, F2, sc, True
            K = F.shape[-1]
            if K >= 2 and not moved and not skip:
                pairs = torch.combinations(torch.arange(K, device=self.device), 2)  # (P, 2), j < k
                j, k = pairs[:, 0].view(-1, 1, 1), pairs[:, 1].view(-1, 1, 1)
                P = pairs.shape[0]
                merged = torch.where(s == k, j, s)
                cand_s = merged - (merged > k).long()
                f = F.unsqueeze(0).expand(P, -1, -1).clone()
                f[torch.arange(P, device=self.device), :, pairs[:, 0]] |= F[:, pairs[:, 1]].T
                keep = torch.arange(K - 1, device=self.device).unsqueeze(0)
                keep = keep + (keep >= pairs[:, 1:]).long()  # (P, K - 1): every slot but k
                cand_f = torch.gather(f, 2, keep.unsqueeze(1).expand(P, F.shape[0], K - 1))
                sc = score_of(cand_s, cand_f)
                b = int(torch.argmax(sc))
                if bool(sc[b] > score):
                    s, F, score, moved = cand_s[b], cand_f[b], sc[b], True
                else:  # look one move further: the best merges, each followed by a relabelling (the first that
                    # raises the score, in the order of the merge scores; relabelled and scored as one batch)
                    top = torch.argsort(sc, descending=True)[:_LOOKAHEAD]
                    relabelled = self._viterbi_relabel_batch(cand_s[top], cand_f[top], float(hyper[0]),
                                                             float(hyper[1]))
                    looked = list(zip(*relabelled, self._scores_by_width(relabelled, score_of)))
                    for s2, F2, sc2 in looked:
                        if bool(sc2 > score):
                            s, F, score, moved = s2, F2, sc2, True
                            break
                    if not moved and not shifts:  # the first of them relabelled on while that raises its score
                        s2, F2, sc2 = self._settle(*looked[0], hyper, score_of)
                        if bool(sc2 > score):
                            s, F, score, moved = s2, F2, sc2, True
            cand = self._reassignments(s, F) if not moved and not skip else None
            skip = False
            if cand is not None:
                sc = self._reassignment_scores(s, F, *cand, score, hyper)
                b = int(torch.argmax(sc))
                if bool(sc[b] > score):  # confirmed by the full score, so every kept score is one
                    s2, F2 = _compact_columns(cand[0][b], cand[1][b])
                    sc2 = score_of(s2[None], F2[None])[0]
                    if bool(sc2 > score):
                        s, F, score, moved = s2, F2, sc2, True
            tried = shifts and not moved and not (stuck is not None and torch.equal(stuck[0], s)
                                                  and torch.equal(stuck[1], F))
            step = self._shift_step(s, F, score, hyper, score_of) if tried else None
            while step is not None:  # shifts on while they raise the score, then every move again
                (s, F, score), moved = step, True
                step = self._shift_step(s, F, score, hyper, score_of)
            if tried:
                stuck = (s, F)
            splits = self._splits(s, F) if not moved else []
            if splits:  # last resort: split one state, its runs cut in two halves, then relabel (the first of
                # them, most used state first, that raises the score; relabelled and scored as one batch)
                relabelled = self._viterbi_relabel_batch(torch.stack([c[0] for c in splits]),
                                                         torch.stack([c[1] for c in splits]), float(hyper[0]),
                                                         float(hyper[1]))
                scores = self._scores_by_width(relabelled, score_of)
                for s2, F2, sc2 in zip(*relabelled, scores):
                    if bool(sc2 > score):
                        s, F, score, moved = s2, F2, sc2, True
                        break
                if shifts and not moved:  # the best split, its switches then moved by shifts alone while they raise
                    # its score: kept if it ends above the current labelling (a split whose new switches the
                    # relabelling placed a few grid points off pays for that before the shifts recover it)
                    b = int(torch.argmax(torch.stack(scores)))
                    step = self._polish(relabelled[0][b], relabelled[1][b], scores[b], score, hyper, score_of)
                    if step is not None:  # the ascent goes on from it with every move
                        (s, F, score), moved = step, True
            if shifts and not moved and self.blocks is not None:
                step = self._shared_birth_step(s, F, score, hyper, score_of)
                if step is not None:
                    (s, F, score), moved = step, True
            if not moved:
                break
        field, noise = self._posterior_mean_fields(s, F.shape[-1])
        return {**snap, "states": s, "features": F, "field": field, "noise": noise, "joint": math.nan,
                "collapsed": float(score)}

    def _shared_births(self, s: Tensor, F: Tensor) -> list[tuple[Tensor, Tensor]]:
        """Candidates of the shared-birth move of :meth:`_climb_to_mode`: for each state j, side (the runs that
        follow j, or precede it) and fraction f in ``_BIRTH_FRACTIONS``, in every sequence each such run at least
        2 D grid points long gives its first (following) or last (preceding) share f to one new state, owned by the
        sequences that receive it (at least two). Only where those runs carry different states: the step that the
        sequences share there is then carried by no one state, which no other move gives them (where the runs are one
        state, the split move cuts them)."""
        N, K = F.shape
        D = int(self.D)
        runs = _runs(s, self.lengths)
        out = []
        for j in range(K):
            for after in (True, False):
                for f in _BIRTH_FRACTIONS:
                    s2, owners, cut_states = s.clone(), set(), set()
                    for i, rr in enumerate(runs):
                        for r, (_, _, state) in enumerate(rr):
                            nb = r + 1 if after else r - 1
                            if state != j or not 0 <= nb < len(rr) or rr[nb][1] - rr[nb][0] < 2 * D:
                                continue
                            a, e, other = rr[nb]
                            cut_states.add(other)
                            cut = min(max(a + round(f * (e - a)), a + D), e - D)
                            if after:
                                s2[i, a:cut] = K
                            else:
                                s2[i, cut:e] = K
                            owners.add(i)
                    if len(owners) >= 2 and len(cut_states) >= 2:
                        F2 = torch.nn.functional.pad(F, (0, 1))
                        F2[sorted(owners), K] = True
                        out.append((s2, F2))
        return out

    def _shared_birth_step(self, s: Tensor, F: Tensor, score: Tensor, hyper: list[Tensor], score_of
                           ) -> tuple[Tensor, Tensor, Tensor] | None:
        """The shared-birth move of :meth:`_climb_to_mode` from (s, F) of collapsed score ``score``: the
        candidates of :meth:`_shared_births` scored in one batch; the ``_LOOKAHEAD`` best are taken in order, each
        kept when it raises the score, else followed by its best reassignment (:meth:`_reassignments`, ranked by
        :meth:`_reassignment_scores`, scored in full), kept when that raises it; when none does, the best of all
        these is polished by shift moves, as the best split is. The new (s, F, score) or None."""
        cand = self._shared_births(s, F)
        if not cand:
            return None
        sc = score_of(torch.stack([c[0] for c in cand]), torch.stack([c[1] for c in cand]))
        tried = []
        for b in torch.argsort(sc, descending=True)[:_LOOKAHEAD].tolist():
            s2, F2 = _compact_columns(*cand[b])
            tried.append((s2, F2, sc[b]))
            if bool(sc[b] > score):
                return tried[-1]
            moves = self._reassignments(s2, F2)
            if moves is None:
                continue
            ranked = self._reassignment_scores(s2, F2, *moves, sc[b], hyper)
            r = int(torch.argmax(ranked))
            if bool(ranked[r] > sc[b]):
                s3, F3 = _compact_columns(moves[0][r], moves[1][r])
                tried.append((s3, F3, score_of(s3[None], F3[None])[0]))
                if bool(tried[-1][2] > score):
                    return tried[-1]
        # the best of them, its switches moved by shifts alone while they raise its score (the births cut at fixed
        # fractions of the runs): kept if it ends above the current labelling
        return self._polish(*max(tried, key=lambda t: float(t[2])), score, hyper, score_of)

    def _polish(self, s: Tensor, F: Tensor, sc: Tensor, score: Tensor, hyper: list[Tensor], score_of
                ) -> tuple[Tensor, Tensor, Tensor] | None:
        """A candidate (s, F) of collapsed score ``sc`` below the current ``score``, its switches moved by shift
        steps alone while they raise its score, at most ``_POLISH_STEPS``: the first (s, F, score) above ``score``,
        or None."""
        for _ in range(_POLISH_STEPS):
            step = self._shift_step(s, F, sc, hyper, score_of)
            if step is None:
                return None
            s, F, sc = step
            if bool(sc > score):
                return s, F, sc
        return None

    def _settle(self, s: Tensor, F: Tensor, score: Tensor, hyper: list[Tensor], score_of
                ) -> tuple[Tensor, Tensor, Tensor]:
        """(s, F) of collapsed score ``score`` relabelled (:meth:`_viterbi_relabel`) while that raises its score, at
        most ``_SETTLE_STEPS`` times: the labelling and score where the relabelling stops."""
        for _ in range(_SETTLE_STEPS):
            s2, F2 = self._viterbi_relabel(s, F, float(hyper[0]), float(hyper[1]))
            if torch.equal(s2, s) and torch.equal(F2, F):
                break
            sc2 = score_of(s2[None], F2[None])[0]
            if not bool(sc2 > score):
                break
            s, F, score = s2, F2, sc2
        return s, F, score

    def _shift_step(self, s: Tensor, F: Tensor, score: Tensor, hyper: list[Tensor], score_of
                    ) -> tuple[Tensor, Tensor, Tensor] | None:
        """One shift move of :meth:`_climb_to_mode` from (s, F) of collapsed score ``score``. The candidates are
        scored as the current score plus the change of the terms a shift touches; then, confirmed by the full score
        ``score_of``, the first that raises it of: every improving shift whose region (:meth:`_shifts`) is disjoint
        from those of better ones in its sequence, all at once (a sequence's switches far apart move together);
        every sequence's best shift at once (each changes its own sequence); the best alone. The new (s, F,
        score), or None when no shift raises the score.

        Moving every disjoint switch at once is a blocked coordinate step: the changes of distant switches of one
        sequence barely interact, so their gains nearly add, and one step (one full score) replaces as many single
        ones (LASA Multi_Models_3: 13 shift steps of about 0.18 s each in the last ascent of sampler seed 1, one
        switch per sequence at a time; one-off measurement)."""
        if self.blocks is not None:  # a free column: a birth may give a run's end or start to a new state (when
            # births of several sequences are taken at once they share it, which the full score then judges)
            F = torch.nn.functional.pad(F, (0, 1))
        shifted = self._shifts(s, F)
        if shifted is None:
            return None
        cand_s, cand_f, seq, touched, region = shifted

        def scores(at: Tensor | None = None, switched: bool = False) -> Tensor:
            parts = (cand_s, cand_f, seq, touched) if at is None else (cand_s[at], cand_f[at], seq[at], touched[at])
            return torch.cat([self._shift_scores(s, F, *part, score, hyper, switched)
                              for part in zip(*(x.split(_SHIFT_CHUNK) for x in parts))])

        sc = scores()
        if self.blocks is not None and not bool((sc > score).any()):
            # then the births of a new state (the free column) with its component free (:meth:`_block_deltas`;
            # the other candidates' scores do not change)
            born = torch.nonzero((cand_s[torch.arange(seq.numel(), device=self.device), seq]
                                  == F.shape[-1] - 1).any(-1)).view(-1)
            if born.numel():
                sc = sc.index_put((born,), scores(born, switched=True))  # the better of the two per birth
        picks = self._disjoint_shifts(sc, seq, region, score)  # best first
        best, seen = [], set()  # each sequence's best: its first pick
        for b in picks:
            if int(seq[b]) not in seen:
                seen.add(int(seq[b]))
                best.append(b)
        tries = [picks] + [pick for pick in ([best] if len(best) > 1 else []) + ([best[:1]] if best else [])
                           if len(pick) < len(picks)]
        for pick in tries:
            if not pick:
                continue
            s2 = s.clone()
            for b in pick:
                i, (lo, hi) = int(seq[b]), region[b].tolist()
                s2[i, lo:hi] = cand_s[b, i, lo:hi]
            F2 = F.clone()
            for i in {int(seq[b]) for b in pick}:  # padding repeats the last label; the features are the states
                # the sequence uses now (a birth: the new one too)
                s2[i] = torch.where(self.valid[i], s2[i], s2[i, int(self.lengths[i]) - 1])
                F2[i] = used_states(s2[i], self.valid[i], F.shape[-1])
            s2, F2 = _compact_columns(s2, F2)
            sc2 = score_of(s2[None], F2[None])[0]
            if bool(sc2 > score):
                return s2, F2, sc2
        return None

    @staticmethod
    def _disjoint_shifts(sc: Tensor, seq: Tensor, region: Tensor, score: Tensor) -> list[int]:
        """Indices of the improving shifts (scores ``sc`` above ``score``), best first, each kept when its region
        (P, 2) is disjoint from those of the better ones kept in its sequence ``seq`` (P,)."""
        up = torch.nonzero(sc > score).reshape(-1)
        kept: dict[int, list[tuple[int, int]]] = {}
        out = []
        for b in up[torch.argsort(sc[up], descending=True)].tolist():
            i, (lo, hi) = int(seq[b]), region[b].tolist()
            taken = kept.setdefault(i, [])
            if all(hi <= lo2 or lo >= hi2 for lo2, hi2 in taken):
                taken.append((lo, hi))
                out.append(b)
        return out

    def _splits(self, s: Tensor, F: Tensor) -> list[tuple[Tensor, Tensor]]:
        """The split move of :meth:`_climb_to_mode`, one candidate per state k, most used first: the second half
        (in time) of every run of k becomes a new state owned by the sequences that own k; the relabelling after it
        moves the new switches to where the fields change."""
        N, K = F.shape
        t = torch.arange(self.T, device=self.device).expand(N, -1)
        change = torch.cat([torch.zeros(N, 1, dtype=torch.long, device=self.device),
                            (s[:, 1:] != s[:, :-1]).long()], 1)
        rid = change.cumsum(1)  # (N, T) run index within each sequence
        big = self.T + 1
        first = torch.full((N, self.T), big, dtype=torch.long, device=self.device).scatter_reduce(
            1, rid, t, "amin", include_self=True)
        last = torch.full((N, self.T), -1, dtype=torch.long, device=self.device).scatter_reduce(
            1, rid, torch.where(self.valid, t, torch.full_like(t, -1)), "amax", include_self=True)
        mid = (first + last + 1) // 2  # (N, runs)
        second = t >= mid.gather(1, rid)  # (N, T): in the second half of its run
        used = (torch.nn.functional.one_hot(s, K).to(self.dtype) * self.valid.unsqueeze(-1)).sum((0, 1))
        out = []
        for k in torch.argsort(used, descending=True).tolist():
            if float(used[k]) < 2 * self.D:  # each half must hold a run of the minimum duration
                continue
            s2 = torch.where((s == k) & second, torch.full_like(s, K), s)
            out.append((s2, torch.cat([F, F[:, k : k + 1]], 1)))
        return out

    def _shifts(self, s: Tensor, F: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        """The shift move of :meth:`_climb_to_mode`: (P, N, T) labels and (P, N, K) features, each with the
        boundaries of one sequence changed in one place, every run at least D long:
            a switch moved by up to D grid points;
            a run removed, the switch between its neighbours placed within D grid points of it (or, when both
                neighbours are one state or the run is the first or last, its samples given to its neighbour).
        A state a sequence no longer uses is dropped from its features (a column nobody owns then scores as
        absent). Also the (P,) sequence of each move, the (P, 3) states whose samples it changes (-1: none) and the
        (P, 2) grid points [lo, hi) of the runs it rewrites (moves of one sequence whose regions are disjoint
        compose: each keeps its runs at least D long and the labels at its region's ends). None without a switch."""
        D = self.D
        spans: list[tuple[int, ...]] = []  # (seq, lo, hi, a, b, first c', last c', removed state or -1)
        runs = _runs(s, self.lengths)
        for i, run in enumerate(runs):
            starts, ends, values = (list(x) for x in zip(*run))
            R = len(values)
            for r in range(R - 1):  # the switch between runs r and r + 1, moved by at most D
                lo, hi, a, b, c = starts[r], ends[r + 1], values[r], values[r + 1], ends[r]
                spans.append((i, lo, hi, a, b, max(lo + D, c - D), min(hi - D, c + D), -1))
            for r in range(R):  # run r removed
                if R == 1:
                    continue
                lo, hi = starts[max(r - 1, 0)], ends[min(r + 1, R - 1)]
                if r == 0 or r == R - 1 or values[r - 1] == values[r + 1]:
                    a = values[r - 1] if r > 0 else values[r + 1]
                    spans.append((i, lo, hi, a, a, hi, hi, values[r]))
                else:  # the new switch within D of the removed run
                    spans.append((i, lo, hi, values[r - 1], values[r + 1], max(lo + D, starts[r] - D),
                                  min(hi - D, ends[r] + D), values[r]))
        if self.blocks is not None:
            spans += self._birth_spans(runs, F.shape[-1])
        if not spans:
            return None
        sp = torch.tensor(spans, dtype=torch.long, device=self.device)  # (W, 8)
        seq, lo, hi, a, b, c0, c1, m = sp.unbind(1)
        owner, rows = self._moved_switches(s, seq, lo, hi, a, b, c0, c1)
        seq, lo, hi, a, b, m = seq[owner], lo[owner], hi[owner], a[owner], b[owner], m[owner]
        rows = torch.where(self.valid[seq], rows, torch.gather(rows, 1, (self.lengths[seq] - 1).unsqueeze(1)))
        changed = (rows != s[seq]).any(1)  # drop candidates equal to the current labelling
        seq, rows = seq[changed], rows[changed]
        touched = torch.stack([a, torch.where(b == a, torch.full_like(b, -1), b), m], 1)[changed]
        region = torch.stack([lo, hi], 1)[changed]
        P = seq.numel()
        if P == 0:
            return None
        p = torch.arange(P, device=self.device)
        cand = s.unsqueeze(0).expand(P, -1, -1).clone()
        cand[p, seq] = rows
        K = F.shape[-1]
        used = used_states(rows, self.valid[seq], K)  # (P, K)
        cand_f = F.unsqueeze(0).expand(P, -1, -1).clone()
        cand_f[p, seq] = used  # the states it keeps (and, after a birth, the state it gains)
        return cand, cand_f, seq, touched, region

    def _birth_spans(self, runs: list[list[tuple[int, int, int]]], K: int) -> list[tuple[int, ...]]:
        """Births of a switch for :meth:`_shifts` (block emission): in one sequence, a run of state a at least 2D
        long cut at any grid point leaving both parts D long, its end given to a state b that follows a in some
        sequence or to a new state, or its start to a state b that precedes a somewhere or to a new state, as spans
        (seq, lo, hi, first label, second label, first c', last c', -1). The new state is label K - 1, which the
        labelling must not use (a free column of F); ``runs`` as :func:`_runs`. The shift's moves and deaths only move or remove switches,
        and the Viterbi relabelling that proposes new ones places them under the direction emission's fields."""
        D, new = self.D, K - 1
        follows = {(a, b) for r in runs for (_, _, a), (_, _, b) in zip(r, r[1:])}
        spans = []
        for i, r in enumerate(runs):
            for q, (lo, hi, a) in enumerate(r):
                if hi - lo < 2 * D:
                    continue
                nxt = r[q + 1][2] if q + 1 < len(r) else None
                prv = r[q - 1][2] if q > 0 else None
                for b in sorted({b for x, b in follows if x == a and b != a and b != nxt}) + [new]:
                    spans.append((i, lo, hi, a, b, lo + D, hi - D, -1))
                for b in sorted({x for x, b in follows if b == a and x != a and x != prv}) + [new]:
                    spans.append((i, lo, hi, b, a, lo + D, hi - D, -1))
        return spans

    def _moved_switches(self, s: Tensor, seq: Tensor, lo: Tensor, hi: Tensor, a: Tensor, b: Tensor, c0: Tensor,
                        c1: Tensor) -> tuple[Tensor, Tensor]:
        """For each region (W,) of sequence ``seq``, grid points [lo, hi), every relabelling a before and b from a
        grid point c in [c0, c1]: the (P,) region of each and its (P, T) relabelled sequence."""
        width = (c1 - c0 + 1).clamp_min(0)
        owner = torch.repeat_interleave(torch.arange(seq.numel(), device=self.device), width)  # (P,)
        offset = torch.arange(owner.numel(), device=self.device) - torch.repeat_interleave(width.cumsum(0) - width,
                                                                                              width)
        new = (c0[owner] + offset).unsqueeze(1)  # first grid point of b in the region
        tt = torch.arange(self.T, device=self.device).unsqueeze(0)
        inside = (tt >= lo[owner].unsqueeze(1)) & (tt < hi[owner].unsqueeze(1))
        rows = torch.where(inside, torch.where(tt < new, a[owner].unsqueeze(1), b[owner].unsqueeze(1)), s[seq[owner]])
        return owner, rows

    def _shift_scores(self, s: Tensor, F: Tensor, cand_s: Tensor, cand_f: Tensor, seq: Tensor, touched: Tensor,
                      score: Tensor, hyper: list[Tensor], switched: bool = False) -> Tensor:
        """(P,) collapsed scores of the shift candidates of :meth:`_shifts`, as the current ``score`` of (s, F)
        plus the change of the terms a move touches: the per-state terms (:meth:`_state_terms`) of the (P, 3)
        ``touched`` states (-1: none), the transitions and initial state of sequence ``seq``, the dwell term and
        the IBP prior. Equal to :meth:`_collapsed_score` of the candidates up to rounding, but for the components of
        the block emission, held (a new state's inherited, or with ``switched`` the better of both;
        :meth:`_block_deltas`), where the full score profiles them anew."""
        N, T, K = self.N, self.T, F.shape[-1]
        P = seq.numel()
        valid = self.valid.reshape(-1)
        onehot = torch.nn.functional.one_hot(s.reshape(-1), K).to(self.dtype) * valid.to(self.dtype).unsqueeze(-1)
        base = torch.cat([self._state_terms(onehot.unsqueeze(0), s[None])[0], onehot.new_zeros(1)])  # (K + 1,), -1: 0
        cols = (cand_s.reshape(P, N * T, 1) == touched.unsqueeze(1)) & valid.view(1, -1, 1)  # (P, N T, 3)
        lp = score + self._state_terms(cols.to(self.dtype), cand_s).sum(-1) - base[touched].sum(-1)
        alpha, kappa = (h.view(1, 1, 1, 1) for h in hyper[:2])
        p = torch.arange(P, device=self.device)
        rows = torch.cat([cand_s[p, seq], s[seq]]).unsqueeze(1)  # (2P, 1, T)
        f_rows = torch.cat([cand_f[p, seq], F[seq]]).unsqueeze(1)  # (2P, 1, K)
        counts = transition_counts(rows, self.lengths[seq].repeat(2).unsqueeze(1), K,
                                   free_transitions(duration_phases(rows, self.D), self.D)).to(self.dtype)
        trans = dirichlet_multinomial_log_prob(counts, f_rows, alpha, kappa).sum(-1)  # (2P,)
        init = -torch.log(f_rows.sum(-1).clamp_min(1).to(self.dtype)).sum(-1)
        lp = lp + (trans[:P] - trans[P:]) + (init[:P] - init[P:])
        if self.dwell is not None:
            ev = dwell_evidence(self.dwell_prior, self.dwell, self.dwell_mask,
                                duration_phases(torch.cat([cand_s, s[None]]), self.D), self.pace_ratios)
            lp = lp + ev[:P] - ev[P:]
        if self.blocks is not None:
            lp = lp + self._block_deltas(s, cand_s, seq, K, switched)
        ibp = ibp_log_prior(cand_f, hyper[2].expand(P), self.cfg.feature_concentration).to(self.dtype)
        return lp + ibp - ibp_log_prior(F, hyper[2], self.cfg.feature_concentration).to(self.dtype)

    def _reassignments(self, s: Tensor, F: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor] | None:
        """The reassign move of :meth:`_climb_to_mode`: every (sequence i, state k it uses, state j != k or a new
        one) with the runs of k in sequence i relabelled j; (P, N, T) labels, (P, N, K + 1) features (the last
        column is the new state's) and the moves' (P,) i, k, j."""
        N, K = F.shape
        used = used_states(s, self.valid, K)  # (N, K)
        i, k, j = torch.nonzero(used.unsqueeze(-1).expand(N, K, K + 1), as_tuple=True)
        keep = j != k
        i, k, j = i[keep], k[keep], j[keep]
        if i.numel() == 0:
            return None
        P = i.numel()
        cand_s = s.unsqueeze(0).expand(P, -1, -1).clone()
        p = torch.arange(P, device=self.device)
        rows = cand_s[p, i]  # (P, T)
        cand_s[p, i] = torch.where(rows == k.unsqueeze(-1), j.unsqueeze(-1), rows)
        cand_f = torch.cat([F, torch.zeros(N, 1, dtype=F.dtype, device=F.device)], 1).unsqueeze(0).repeat(P, 1, 1)
        cand_f[p, i, k] = False
        cand_f[p, i, j] = True
        return cand_s, cand_f, i, k, j

    def _reassignment_scores(self, s: Tensor, F: Tensor, cand_s: Tensor, cand_f: Tensor, i: Tensor, k: Tensor,
                             j: Tensor, score: Tensor, hyper: list[Tensor]) -> Tensor:
        """(P,) collapsed scores of the reassignment candidates of :meth:`_reassignments`, as the current
        ``score`` of (s, F) plus the change of the terms a move touches: the per-state terms
        (:meth:`_state_terms`) of states k and j, the transitions and initial state of sequence i, and the IBP
        prior. Equal to :meth:`_collapsed_score` of the candidates up to rounding; it only evaluates the two
        states' samples instead of all K states' for every candidate."""
        N, T, K = self.N, self.T, F.shape[-1]
        P = i.numel()
        valid = self.valid.reshape(-1)
        flat = s.reshape(-1)
        onehot = torch.nn.functional.one_hot(flat, K).to(self.dtype) * valid.to(self.dtype).unsqueeze(-1)
        base = torch.cat([self._state_terms(onehot.unsqueeze(0), s[None])[0], onehot.new_zeros(1)])  # (K + 1,), new: 0
        in_i = torch.arange(N, device=self.device).repeat_interleave(T).unsqueeze(0) == i.unsqueeze(-1)  # (P, N T)
        old_k = (flat.unsqueeze(0) == k.unsqueeze(-1)) & valid
        new_j = ((flat.unsqueeze(0) == j.unsqueeze(-1)) & valid) | (old_k & in_i)
        # state k after the move depends on (i, k) alone: its terms once per pair, the labels of the pair's first
        # move (its remaining samples lie outside sequence i, so their ages are those of every move of the pair)
        pairs, inverse = torch.unique(i * K + k, return_inverse=True)
        first = torch.full_like(pairs, P).scatter_reduce_(0, inverse, torch.arange(P, device=self.device), "amin")
        kept_k = (old_k & ~in_i)[first].unsqueeze(-1).to(self.dtype)  # (U, N T, 1)
        lp = (score + self._state_terms(kept_k, cand_s[first])[inverse, 0]
              + self._state_terms(new_j.unsqueeze(-1).to(self.dtype), cand_s)[:, 0] - base[k] - base[j])
        alpha, kappa = (h.view(1, 1, 1, 1) for h in hyper[:2])
        rows = torch.cat([cand_s[torch.arange(P, device=self.device), i], s[i]]).unsqueeze(1)  # (2P, 1, T)
        f_rows = torch.cat([cand_f[torch.arange(P, device=self.device), i],
                            torch.nn.functional.pad(F[i], (0, 1))]).unsqueeze(1)  # (2P, 1, K + 1)
        counts = transition_counts(rows, self.lengths[i].repeat(2).unsqueeze(1), K + 1,
                                   free_transitions(duration_phases(rows, self.D), self.D)).to(self.dtype)
        trans = dirichlet_multinomial_log_prob(counts, f_rows, alpha, kappa).sum(-1)  # (2P,)
        init = -torch.log(f_rows.sum(-1).clamp_min(1).to(self.dtype)).sum(-1)
        lp = lp + (trans[:P] - trans[P:]) + (init[:P] - init[P:])
        if self.dwell is not None:  # the dwell evidence depends on where runs start in every sequence
            ev = dwell_evidence(self.dwell_prior, self.dwell, self.dwell_mask,
                                duration_phases(torch.cat([cand_s, s[None]]), self.D), self.pace_ratios)
            lp = lp + ev[:P] - ev[P:]
        if self.blocks is not None:
            lp = lp + self._block_deltas(s, cand_s, i, K + 1)
        ibp = ibp_log_prior(cand_f, hyper[2].expand(P), self.cfg.feature_concentration).to(self.dtype)
        return lp + ibp - ibp_log_prior(F, hyper[2], self.cfg.feature_concentration).to(self.dtype)

    def _viterbi_relabel(self, s: Tensor, F: Tensor, alpha: float, kappa: float) -> tuple[Tensor, Tensor]:
        """The relabel move of :meth:`_climb_to_mode`: (N, T) Viterbi labels and (N, K) features, unused slots of
        every sequence dropped and empty columns removed."""
        K, D = F.shape[-1], self.D
        field, noise = self._posterior_mean_fields(s, K)
        le, le_first = self._run_emissions(field[None, None], noise[None, None])
        le, le_first = le[0], None if le_first is None else le_first[0]
        if self.tau > 0:
            pos = self.tau * gaussian_log_density(self.pos, *self._posterior_mean_positions(s, K))
            onehot = torch.nn.functional.one_hot(s, K).to(self.dtype) * self.valid.to(self.dtype).unsqueeze(-1)
            pos = pos + self._occupancy_log_weights(onehot.reshape(1, self.N * self.T, K))[0]
            le = le + pos
            le_first = None if le_first is None else le_first + pos
        counts = transition_counts(s, self.lengths, K, free_transitions(duration_phases(s, D), D)).to(self.dtype)
        f = F.to(self.dtype)
        owned = f.unsqueeze(-1) * f.unsqueeze(-2)  # (N, K, K)
        prior = alpha + kappa * torch.eye(K, dtype=self.dtype, device=self.device)
        pi = (prior + counts) * owned  # posterior mean of the sticky Dirichlet rows, up to normalisation
        pi = pi / pi.sum(-1, keepdim=True).clamp_min(torch.finfo(self.dtype).tiny)
        dwell_ll = self._posterior_mean_dwell(s[None])
        le = self._expand(le, F, self.lengths, None if dwell_ll is None else dwell_ll[0], le_first)
        init, P = expand_min_duration(initial_distribution(F, self.dtype), pi, D)
        s_new = viterbi(le, init, P, self.lengths) // D
        used = used_states(s_new, self.valid, K)  # (N, K)
        return _compact_columns(s_new, used)

    def _viterbi_relabel_batch(self, s: Tensor, F: Tensor, alpha: float, kappa: float
                               ) -> tuple[list[Tensor], list[Tensor]]:
        """:meth:`_viterbi_relabel` of B labellings s (B, N, T) with features F (B, N, K) in one batch: the
        relabelled (N, T) labels and (N, K_b) features of each (K_b may differ between them)."""
        B, K, D = s.shape[0], F.shape[-1], self.D
        N, T = self.N, self.T
        valid = self.valid.to(self.dtype).unsqueeze(-1)
        onehot = (torch.nn.functional.one_hot(s, K).to(self.dtype) * valid).reshape(B, N * T, K)
        age, w, _ = self._score_view(s)
        if self.cfg.robust_dof is not None:
            w = w * self._profile_scales(age, w, onehot)
        field, noise = field_mixture_posterior_mean(self.score_prior, *self._stats(age, w, onehot),
                                                    self.cfg.straight_weight, self.wide_score_prior,
                                                    self.cfg.rotation_weight)  # (B, K, d, p), (B, K, d, d)
        le, le_first = self._run_emissions(field[:, None], noise[:, None])  # (B, N, T, K)
        if self.tau > 0:
            post = niw_posterior(self.pos_prior, *self._position_statistics(onehot))
            cov = post.scale / (post.dof - self.d - 1.0)[..., None, None]
            pos = self.tau * gaussian_log_density(self.pos, post.mean[:, None], cov[:, None])
            pos = pos + self._occupancy_log_weights(onehot)
            le = le + pos
            le_first = None if le_first is None else le_first + pos
        lengths = self.lengths.expand(B, N)
        counts = transition_counts(s, lengths, K, free_transitions(duration_phases(s, D), D)).to(self.dtype)
        f = F.to(self.dtype)
        owned = f.unsqueeze(-1) * f.unsqueeze(-2)  # (B, N, K, K)
        prior = alpha + kappa * torch.eye(K, dtype=self.dtype, device=self.device)
        pi = (prior + counts) * owned
        pi = pi / pi.sum(-1, keepdim=True).clamp_min(torch.finfo(self.dtype).tiny)
        dwell_ll = self._posterior_mean_dwell(s)
        le = self._expand(le.flatten(0, 1), F.flatten(0, 1), lengths.reshape(-1),
                          None if dwell_ll is None else dwell_ll.flatten(0, 1),
                          None if le_first is None else le_first.flatten(0, 1))
        init, P = expand_min_duration(initial_distribution(F, self.dtype), pi, D)
        s_new = (viterbi(le, init.flatten(0, 1), P.flatten(0, 1), lengths.reshape(-1)) // D).unflatten(0, (B, N))
        used = used_states(s_new, self.valid, K)  # (B, N, K)
        out = [_compact_columns(s_new[b], used[b]) for b in range(B)]
        return [o_[0] for o_ in out], [o_[1] for o_ in out]

    @staticmethod
    def _scores_by_width(labellings: tuple[list[Tensor], list[Tensor]], score_of) -> list[Tensor]:
        """Scores of labellings with different numbers of states, batched per number of states."""
        states, features = labellings
        out: list[Tensor | None] = [None] * len(states)
        for K in sorted({f.shape[-1] for f in features}):
            idx = [b for b, f in enumerate(features) if f.shape[-1] == K]
            sc = score_of(torch.stack([states[b] for b in idx]), torch.stack([features[b] for b in idx]))
            for b, v in zip(idx, sc):
                out[b] = v
        return out

    def _posterior_mean_fields(self, s: Tensor, K: int) -> tuple[Tensor, Tensor]:
        """(K, d, p) posterior-mean fields and (K, d, d) noise of a labelling s (N, T), as in
        :meth:`_collapsed_score` (with a tolerance correlation, Psi is the innovations' covariance)."""
        N, T = self.N, self.T
        onehot = (torch.nn.functional.one_hot(s, K).to(self.dtype) * self.valid.to(self.dtype).unsqueeze(-1))
        onehot = onehot.reshape(1, N * T, K)
        age, w, _ = self._score_view(s[None])
        if self.cfg.robust_dof is not None:
            w = w * self._profile_scales(age, w, onehot)
        mean, psi = field_mixture_posterior_mean(self.score_prior, *self._stats(age, w, onehot),
                                                 self.cfg.straight_weight, self.wide_score_prior,
                                                 self.cfg.rotation_weight)
        return mean[0], psi[0]

    def _run_emissions(self, field: Tensor, noise: Tensor) -> tuple[Tensor, Tensor | None]:
        """(B, N, T, K) log densities of every sample under fields (B, 1, K, d, p) and noise (B, 1, K, d, d) as a
        sample of a run in its oldest view (:data:`~lfd_torch.segmentation.field.TOLERANCE_MEMORY` points or more
        into it), and (with a tolerance correlation; else None) as a run's first sample."""
        shape = (1, self.N, self.T)
        z, u, w = (a.reshape(*shape, *a.shape[2:]) for a in self.ar_cont)
        le = field_log_likelihood(z, u, w, field, noise, self.cfg.robust_dof)
        if self.rho == 0.0:
            return le, None
        z, u, w = (a.reshape(*shape, *a.shape[2:]) for a in self.ar_start)
        return le, field_log_likelihood(z, u, w, field, noise, self.cfg.robust_dof)

    def _posterior_mean_dwell(self, s: Tensor) -> Tensor | None:
        """(B, N, T, 2) dwell terms under the posterior means of (mu, delta) and sigma^2 given the labellings s
        (B, N, T) (as the fields in :meth:`_posterior_mean_fields`); None without the dwell term."""
        if self.dwell is None:
            return None
        post = dwell_posterior(self.dwell_prior, self.dwell, self.dwell_mask, duration_phases(s, self.D))
        noise = post.scale.reshape(-1) / (post.dof.reshape(-1) - 2.0)
        return dwell_log_likelihood(self.dwell, self.dwell_mask, post.mean.reshape(-1, 2), noise)

    def _dwell_summary(self, s: Tensor) -> dict[str, float]:
        """Posterior means of mu, delta and sigma of the dwell term given one labelling s (N, T); {} without it."""
        if self.dwell is None:
            return {}
        return posterior_summary(dwell_posterior(self.dwell_prior, self.dwell, self.dwell_mask,
                                                 duration_phases(s[None], self.D)))

    def _posterior_mean_positions(self, s: Tensor, K: int) -> tuple[Tensor, Tensor]:
        """(K, d) posterior means and (K, d, d) posterior-mean covariances of the position Gaussians of a labelling
        s (N, T) (tau > 0)."""
        onehot = (torch.nn.functional.one_hot(s, K).to(self.dtype) * self.valid.to(self.dtype).unsqueeze(-1))
        post = niw_posterior(self.pos_prior, *self._position_statistics(onehot.reshape(1, self.N * self.T, K)))
        return post.mean[0], (post.scale / (post.dof - self.d - 1.0)[..., None, None])[0]

    def _runs_per_sequence(self) -> Tensor:
        """(C, N) long: runs of one state in every sequence (its number of pieces) in the current sample."""
        change = (self.s[..., 1:] != self.s[..., :-1]) & self.valid[:, 1:]
        return change.sum(-1) + 1

    def _modal_sample(self, kept: list[dict]) -> dict:
        """The sample of ``selection="modal"`` (module docstring, "Which sample") with its collapsed score."""
        runs = torch.stack([k["runs"] for k in kept])  # (S, N)
        modal = torch.stack([torch.bincount(runs[:, i]).argmax() for i in range(runs.shape[1])])  # ties: fewer
        agree = (runs == modal).sum(-1)
        joint = torch.tensor([k["joint"] for k in kept], dtype=self.dtype, device=runs.device)
        score = torch.where(agree == agree.max(), joint, torch.full_like(joint, _NEG_INF))
        snap = kept[int(torch.argmax(score))]
        c = snap["chain"]
        hyper = [torch.tensor([snap["hyper"][k]], dtype=self.dtype, device=self.device)
                 for k in ("transition_concentration", "stickiness", "feature_mass")]
        collapsed = self._collapsed_score(snap["states"][None], snap["features"][None], snap["phase"][None], *hyper)
        return {**snap, "collapsed": float(collapsed[0]), "chain": c}

    def _snapshot(self, c: int) -> dict:
        """Copy of chain c with its slots relabelled to the features it owns (in order of first use)."""
        owned = self.F[c].any(0)
        keep = torch.nonzero(owned).reshape(-1)
        remap = torch.full((self.F.shape[-1],), -1, dtype=torch.long, device=self.device)
        remap[keep] = torch.arange(keep.numel(), device=self.device)
        states = remap[self.s[c]]
        return {
            "states": states,
            "features": self.F[c][:, keep].clone(),
            "field": self.field[c, keep].clone(),
            "noise": self.noise[c, keep].clone(),
            "hyper": {
                "feature_mass": float(self.mass[c]),
                "transition_concentration": float(self.alpha[c]),
                "stickiness": float(self.kappa[c]),
            },
        }
