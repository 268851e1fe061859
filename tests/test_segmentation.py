"""BP-GM-HMM sampler and Segmentation: reproducibility, synthetic switch points, API contract, bad input."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.segmentation import (
    BetaProcessHMMSampler,
    BPGMHMMSegmenter,
    FixedSegmenter,
    NoSegmenter,
    Segmentation,
    SegmentationWarning,
    multi_step_demos,
    runs,
    segment,
)
from lfd_torch.segmentation.segmentation import _absorb_short, _best_split, _consensus, _steps_from_bounds
from conftest import requires_cuda

F64 = torch.float64
CONF = Path(__file__).resolve().parents[1] / "conf"
FAST = dict(n_iterations=20, n_chains=2)


def boundary_errors(seg: Segmentation, truth: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """|nearest found boundary - true switch| / T_i for every true switch of every sequence."""
    errs = []
    for i in range(truth.shape[0]):
        found = seg.boundaries[i, 1:-1]
        for t in truth[i].tolist():
            errs.append(float((found - t).abs().min()) / float(lengths[i]) if found.numel() else 1.0)
    return torch.tensor(errs)


# ---------------------------------------------------------------------------------------------- sampler
def test_sampler_reproducible_for_fixed_seed():
    syn = multi_step_demos(torch.Generator().manual_seed(3), n_demos=3, n_steps=3, samples_per_step=30)
    seqs = syn.demos.sequences()
    sampler = BetaProcessHMMSampler(n_iterations=6, n_chains=2)
    a = sampler.run(seqs, torch.Generator().manual_seed(11))
    b = sampler.run(seqs, torch.Generator().manual_seed(11))
    c = sampler.run(seqs, torch.Generator().manual_seed(12))
    assert torch.equal(a.states, b.states) and torch.equal(a.trace, b.trace) and torch.equal(a.mean, b.mean)
    assert not torch.equal(a.trace, c.trace)
    assert a.trace.shape == (2, 6) and torch.isfinite(a.trace).all()
    assert a.features.shape == (3, a.n_features) and a.features.any(1).all()
    # every label indexes a feature its sequence owns
    for i in range(3):
        assert a.features[i, a.states[i, : int(a.lengths[i])]].all()


def test_sampler_finds_well_separated_clusters(generator):
    # piecewise-constant sequences visiting 3 well separated points: the best sample has 3 states and the switch
    # times exactly (a check on the whole chain, not only the kernels)
    centers = torch.tensor([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]], dtype=F64)
    seqs, truth = [], []
    for i in range(3):
        lens = [20 + 3 * i, 25, 18 + i]
        lab = torch.cat([torch.full((n,), k) for k, n in enumerate(lens)])
        seqs.append(centers[lab] + 0.2 * torch.randn(len(lab), 2, generator=generator, dtype=F64))
        truth.append(lab)
    res = BetaProcessHMMSampler(n_iterations=25, n_chains=2).run(seqs, generator)
    for i in range(3):
        s = res.states[i, : len(truth[i])]
        _, _, values = runs(s)
        assert values.numel() == 3 and values.unique().numel() == 3
        starts, _, _ = runs(truth[i])
        torch.testing.assert_close(runs(s)[0], starts)
    # the returned sample is the best one after burn-in (half of the 25 sweeps) over both chains
    assert res.log_prob == pytest.approx(float(res.trace[:, 12:].max()))


# ---------------------------------------------------------------------------------------------- synthetic steps
@pytest.mark.parametrize("profile,seed", [("min_jerk", 1), ("constant", 2)])
def test_synthetic_switch_points_found(profile, seed):
    syn = multi_step_demos(torch.Generator().manual_seed(seed), n_demos=4, n_steps=4, profile=profile, samples_per_step=70)
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(seed), **FAST)
    assert seg.n_steps == syn.n_steps
    err = boundary_errors(seg, syn.switch_times, syn.demos.lengths)
    assert float(err.median()) <= 0.03
    # attractors are the corners (up to the jitter of the waypoints, sd 0.03, and the boundary error)
    torch.testing.assert_close(seg.attractors, syn.waypoints[1:], atol=0.1, rtol=0)


def test_revisited_region_is_the_same_state():
    # W0 -> W1 -> W2 -> W3 -> W1 -> W4: the corner W1 is reached at the end of step 1 and of step 4
    # (every leg turns by >= 76 degrees, so each leg is a step)
    W = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, 0.0], [2.0, 0.5]], dtype=F64)
    syn = multi_step_demos(torch.Generator().manual_seed(0), waypoints=W, n_demos=4, samples_per_step=80)
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(0), **FAST)
    assert seg.n_steps == 5
    for i in range(4):
        first, second = syn.switch_times[i, 0] - 1, syn.switch_times[i, 3] - 1
        assert int(seg.states[i][first]) == int(seg.states[i][second])
    shared = set(seg.step_states()[0]) & set(seg.step_states()[3])
    assert shared, "the state of region W1 belongs to both steps that end there"


def test_long_straight_leg_is_one_step(generator):
    # one straight constant-speed leg: the HMM uses several Gaussians along it, the segment level merges them
    W = torch.tensor([[0.0, 0.0], [3.0, 0.0]], dtype=F64)
    syn = multi_step_demos(generator, waypoints=W, n_demos=3, profile="constant", samples_per_step=150)
    seg = segment(syn.demos, generator=generator, **FAST)
    assert seg.sampler is not None and seg.sampler.n_features >= 2
    assert seg.n_steps == 1


# ---------------------------------------------------------------------------------------------- result API
def test_table_one_attractors_are_mean_end_points():
    # Paper Table I: two sequences of 8 samples whose steps end at samples 3/6/8 and 2/5/8 (1-based)
    g = torch.Generator().manual_seed(0)
    x = [torch.randn(8, 2, generator=g, dtype=F64) for _ in range(2)]
    demos = Demos.from_sequences(x)
    seg = _steps_from_bounds(demos, [[0, 3, 6, 8], [0, 2, 5, 8]], {})
    ends = [(2, 1), (5, 4), (7, 7)]  # 0-based last samples (sequence 1, sequence 2)
    for m, (e1, e2) in enumerate(ends):
        torch.testing.assert_close(seg.attractors[m], 0.5 * (x[0][e1] + x[1][e2]))
    assert [lab.tolist() for lab in seg.labels] == [[0, 0, 0, 1, 1, 1, 2, 2], [0, 0, 1, 1, 1, 2, 2, 2]]
    fixed = FixedSegmenter([0.3, 0.7])(demos)  # 8 * 0.3 -> 2, 8 * 0.7 -> 6
    assert fixed.boundaries.tolist() == [[0, 2, 6, 8], [0, 2, 6, 8]]


def test_split_pieces_and_attractors(generator):
    syn = multi_step_demos(generator, n_demos=3, n_steps=3, samples_per_step=40)
    seg = FixedSegmenter([0.25, 0.6])(syn.demos)
    parts = seg.split(syn.demos)
    assert len(parts) == 3
    for m, p in enumerate(parts):
        torch.testing.assert_close(p.attractor, seg.attractors[m])
        torch.testing.assert_close(p.lengths, seg.boundaries[:, m + 1] - seg.boundaries[:, m])
    for i, seq in enumerate(syn.demos.sequences()):
        torch.testing.assert_close(torch.cat([p.sequences()[i] for p in parts]), seq)
        torch.testing.assert_close(torch.cat([p.velocities[i, : int(p.lengths[i])] for p in parts]),
                                   syn.demos.velocities[i, : int(syn.demos.lengths[i])])  # fmt: skip
    with pytest.raises(ShapeMismatchError):
        seg.split(syn.demos[[0, 1]])


def test_log_density_batched_and_other_steps(generator):
    syn = multi_step_demos(generator, n_demos=2, n_steps=4, samples_per_step=30)
    seg = FixedSegmenter([0.25, 0.5, 0.75])(syn.demos)
    x = torch.randn(5, 7, 2, generator=generator, dtype=F64)
    ld = seg.log_density(x)
    assert ld.shape == (5, 7, 4)
    # per-point loop reference: mixture over the step's Gaussians
    from scipy.stats import multivariate_normal

    for m in range(4):
        terms = []
        for s in range(seg.state_mean.shape[0]):
            w = float(seg.step_weights[m, s])
            if w > 0:
                dist = multivariate_normal(seg.state_mean[s].numpy(), seg.state_covariance[s].numpy())
                terms.append(math.log(w) + torch.tensor(dist.logpdf(x.numpy())))
        torch.testing.assert_close(ld[..., m], torch.logsumexp(torch.stack(terms), 0))
    other = seg.other_log_density(x)
    for m in range(4):
        rest = [j for j in range(4) if j != m]
        torch.testing.assert_close(other[..., m], ld[..., rest].amax(-1))
    assert torch.equal(seg.membership(x), ld >= other)
    with pytest.raises(ShapeMismatchError):
        seg.log_density(torch.zeros(3, 3, dtype=F64))


def test_no_segmenter_single_step(generator):
    syn = multi_step_demos(generator, n_demos=2, n_steps=2, samples_per_step=20)
    seg = NoSegmenter()(syn.demos)
    assert seg.n_steps == 1
    torch.testing.assert_close(seg.attractors[0], syn.demos.attractor)  # the single step ends at the task goal
    assert torch.isinf(seg.other_log_density(torch.zeros(4, 2, dtype=F64))).all()
    assert len(seg.split(syn.demos)) == 1


# ---------------------------------------------------------------------------------------------- helpers
def test_absorb_short_runs_picks_better_neighbour():
    states = torch.tensor([0, 0, 0, 0, 1, 2, 2, 2, 2])
    le = torch.zeros(9, 3, dtype=F64)
    le[4, 2] = 1.0  # sample 4 is better explained by state 2
    out = _absorb_short(states, 2, le)
    assert out.tolist() == [0, 0, 0, 0, 2, 2, 2, 2, 2]


def test_best_split_finds_corner(generator):
    t = torch.linspace(0, 1, 50, dtype=F64)
    leg1 = torch.stack([t, 0 * t], -1)
    leg2 = torch.stack([1 + 0 * t[1:], t[1:]], -1)
    x = torch.cat([leg1, leg2]) + 1e-4 * torch.randn(99, 2, generator=generator, dtype=F64)
    tau, _ = _best_split(x, 3)
    assert abs(tau - 50) <= 1


# ---------------------------------------------------------------------------------------------- bad input
def test_bad_input_typed_errors(generator):
    good = torch.randn(60, 2, generator=generator, dtype=F64)
    with pytest.raises(TooFewSamplesError):
        segment([good, good[:7]], generator=generator, min_length=5)
    bad = good.clone()
    bad[10, 0] = float("nan")
    with pytest.raises(NonFiniteError):
        segment([good, bad], generator=generator)
    with pytest.raises(ShapeMismatchError):
        segment([good, torch.randn(60, 3, generator=generator, dtype=F64)], generator=generator)
    with pytest.raises(TypeError):
        BPGMHMMSegmenter(not_a_parameter=1)
    with pytest.raises(ValueError):
        FixedSegmenter([0.5, 0.2])


def test_single_sequence_is_segmented(generator):
    syn = multi_step_demos(generator, n_demos=1, n_steps=3, samples_per_step=60, profile="constant")
    seg = segment(syn.demos, generator=generator, **FAST)
    assert seg.n_sequences == 1 and seg.n_steps == 3
    assert float(boundary_errors(seg, syn.switch_times, syn.demos.lengths).max()) <= 0.03


# ---------------------------------------------------------------------------------------------- configs
@pytest.mark.parametrize("option", ["bp_gm_hmm", "fixed", "none"])
def test_segmentation_configs_instantiate_and_run(option, generator):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name=f"segmentation/{option}")
    node = cfg.segmentation
    if option == "bp_gm_hmm":
        node.n_iterations = 4
        node.n_chains = 1
    segmenter = instantiate(node)
    syn = multi_step_demos(generator, n_demos=2, n_steps=3, samples_per_step=40)
    seg = segmenter(syn.demos, generator=generator)
    assert isinstance(seg, Segmentation)
    assert seg.boundaries.shape[0] == 2 and (seg.boundaries[:, -1] == syn.demos.lengths).all()
    assert math.isfinite(float(seg.attractors.sum()))


def test_segment_lasa_experiment_runs(tmp_path):
    import sys

    sys.path.insert(0, str(CONF.parent / "experiments"))
    import segment_lasa

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(
            config_name="segment_lasa",
            overrides=[
                "shapes=[Multi_Models_3]", "synthetic_3d.n_steps=3", "synthetic_3d.samples_per_step=40",
                "synthetic_3d.n_demos=2", "segmentation.n_iterations=3", "segmentation.n_chains=1",
                f"paths.root={tmp_path}", f"+out_dir={tmp_path}",
            ],
        )  # fmt: skip
    out = segment_lasa.run(cfg)
    table = out["table"]
    # Multi_Models_3 has two routes (4 demos from the left, 3 from the top right) plus the 3-D set
    assert set(table["shape"]) == {"Multi_Models_3_route1", "Multi_Models_3_route2", "synthetic_3d"}
    assert (table.groupby("shape")["trajectory"].max() == table.groupby("shape")["n_steps"].first()).all()
    assert all(Path(p).exists() for p in out["written"])
    assert (tmp_path / "results" / "tables" / "segment_lasa.parquet").exists()


def test_hyperparameter_resampling_and_progress(generator):
    syn = multi_step_demos(generator, n_demos=3, n_steps=3, samples_per_step=30)
    res = BetaProcessHMMSampler(n_iterations=8, n_chains=2, resample_hyperparameters=True, progress=True).run(
        syn.demos.sequences(), generator
    )
    h = res.hyperparameters
    assert all(v > 0 and math.isfinite(v) for v in h.values())
    assert h["feature_mass"] != 2.0  # drawn from its conditional, not left at the default
    assert torch.isfinite(res.trace).all()


def test_save_load_round_trip(tmp_path, generator):
    syn = multi_step_demos(generator, n_demos=2, n_steps=3, samples_per_step=40)
    seg = segment(syn.demos, generator=generator, n_iterations=4, n_chains=1)
    path = seg.save(tmp_path / "seg.pt")
    back = Segmentation.load(path)
    assert torch.equal(back.boundaries, seg.boundaries) and torch.equal(back.attractors, seg.attractors)
    x = torch.randn(10, 2, generator=generator, dtype=F64)
    torch.testing.assert_close(back.log_density(x), seg.log_density(x))
    assert [p.n_demos for p in back.split(syn.demos)] == [2] * seg.n_steps


@pytest.mark.cuda
@requires_cuda
def test_segment_on_cuda():
    syn = multi_step_demos(torch.Generator().manual_seed(0), n_demos=3, n_steps=3, samples_per_step=50, profile="constant")
    demos = syn.demos.to(device="cuda")
    seg = segment(demos, generator=torch.Generator(device="cuda").manual_seed(0), **FAST)
    assert seg.n_steps == 3 and seg.attractors.device.type == "cuda"
    assert seg.log_density(demos.positions).shape == (*demos.positions.shape[:2], 3)
    assert seg.boundaries.device.type == "cuda" and seg.labels[0].device.type == "cuda"
    parts = seg.split(demos, end_at_attractor=True)
    assert parts[-1].positions.device.type == "cuda"
    torch.testing.assert_close(parts[-1].attractor, demos.attractor)


# ---------------------------------------------------------------------------------------------- review fixes
def test_one_dimensional_data_raise_a_typed_error(generator):
    # the segment-level line model needs d >= 2 (every 1-D path is a line): a typed error, not ZeroDivisionError
    t = torch.linspace(0, 1, 60, dtype=F64)
    seqs = [torch.cat([t, 1 + 0 * t, 1 - t]).unsqueeze(-1) + 0.01 * torch.randn(180, 1, generator=generator, dtype=F64)]
    with pytest.raises(InvalidArgumentError, match="d >= 2"):
        segment(seqs, generator=generator, n_iterations=2, n_chains=1)
    # the segmenters without line stages accept 1-D data
    seg = FixedSegmenter([1 / 3, 2 / 3])(seqs)
    assert seg.n_steps == 3 and seg.dim == 1
    assert NoSegmenter()(seqs).n_steps == 1


def test_last_attractor_is_the_task_goal_and_pieces_can_end_at_rest(generator):
    syn = multi_step_demos(generator, n_demos=3, n_steps=3, samples_per_step=50, profile="constant")
    goal = syn.waypoints[-1]
    ends = torch.stack([s[-1] for s in syn.demos.sequences()])
    assert float((ends.mean(0) - goal).norm()) > 1e-4  # noisy end points: their mean is not the goal
    seg = segment(syn.demos, generator=generator, **FAST)
    torch.testing.assert_close(seg.attractors[-1], goal)
    # from a list of tensors (no attractor given) the goal is the mean end point, as Demos defines it
    seg_list = segment(syn.demos.sequences(), generator=torch.Generator().manual_seed(0), **FAST)
    torch.testing.assert_close(seg_list.attractors[-1], ends.mean(0))
    plain = seg.split(syn.demos)
    rest = seg.split(syn.demos, end_at_attractor=True)
    for m, (p, r) in enumerate(zip(plain, rest)):
        torch.testing.assert_close(r.lengths, p.lengths + 1)
        for i in range(p.n_demos):
            L = int(p.lengths[i])
            torch.testing.assert_close(r.positions[i, :L], p.positions[i, :L])
            torch.testing.assert_close(r.positions[i, L], seg.attractors[m])
            assert float(r.velocities[i, L].abs().max()) == 0.0
            torch.testing.assert_close(r.times[i, L] - r.times[i, L - 1], p.times[i, L - 1] - p.times[i, L - 2])
        torch.testing.assert_close(r.attractor, seg.attractors[m])


def test_consensus_count_is_reported_and_warned():
    # three sequences with 3 straight legs, one that goes straight to the goal (2 legs, skipping a corner)
    g = torch.Generator().manual_seed(0)
    W = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=F64)
    tau = torch.linspace(0, 1, 41, dtype=F64)[1:].unsqueeze(-1)

    def path(corners: torch.Tensor) -> torch.Tensor:
        legs = [corners[:1]] + [corners[m] + tau * (corners[m + 1] - corners[m]) for m in range(len(corners) - 1)]
        x = torch.cat(legs)
        return x + 0.003 * torch.randn(x.shape, generator=g, dtype=F64)

    seqs = [path(W) for _ in range(3)] + [path(W[[0, 1, 3]])]
    bounds = [[0, 41, 81, 121]] * 3 + [[0, 41, 81]]
    with pytest.warns(SegmentationWarning, match=r"sequences \[3\] had \[2\] steps"):
        out, forced, equal_cut = _consensus(seqs, bounds, floor_var=1e-4, min_length=5)
    assert [len(b) - 1 for b in out] == [3, 3, 3, 3] and forced == {3: 2} and equal_cut == []
    # a sequence too short to split into the consensus count is cut evenly, and that is reported too
    short = path(W[[0, 3]])[:25]  # 25 samples, min_length 10: at most 2 steps
    with pytest.warns(SegmentationWarning, match="cut evenly"):
        out, forced, equal_cut = _consensus(seqs[:3] + [short], bounds[:3] + [[0, 25]], floor_var=1e-4, min_length=10)
    assert forced == {3: 1} and equal_cut == [3] and len(out[3]) == 4
    # no warning when every sequence agrees, and segment() records the decisions in info
    with warnings.catch_warnings():
        warnings.simplefilter("error", SegmentationWarning)
        _, forced, equal_cut = _consensus(seqs[:3], bounds[:3], floor_var=1e-4, min_length=5)
    assert forced == {} and equal_cut == []
    syn = multi_step_demos(torch.Generator().manual_seed(2), n_demos=2, n_steps=2, samples_per_step=40)
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(0), **FAST)
    assert isinstance(seg.info["forced_to_consensus"], dict) and isinstance(seg.info["equal_cut_fallback"], list)


def test_max_samples_is_documented_as_a_resolution_parameter():
    # the BIC merge runs on the subsampled sequences, so max_samples changes step counts: users must be told
    text = (CONF / "segmentation" / "bp_gm_hmm.yaml").read_text()
    line = next(ln for ln in text.splitlines() if ln.startswith("max_samples:"))
    assert "resolution" in line and "step count" in line.lower()
    assert "resolution" in segment.__doc__.split("max_samples:")[1].split("straightness_tolerance:")[0]


def test_hyperparameter_step_redraws_auxiliary_transition_weights():
    # the weights outside the owned blocks (and the row totals) are prior draws given (alpha, kappa); after alpha
    # and kappa move they must follow the new values, while pi on the owned blocks stays unchanged
    from lfd_torch.segmentation.sampler import _Run
    from lfd_torch.segmentation.transitions import transition_matrix

    g = torch.Generator().manual_seed(4)
    x = torch.randn(3, 20, 2, generator=g, dtype=F64)
    cfg = BetaProcessHMMSampler(n_chains=64, n_initial_features=2, transition_concentration=1.0, stickiness=2.0)
    run = _Run(cfg, x, torch.full((3,), 20), g, None)
    run._grow(3)  # free (unowned) slots: their weights are auxiliary
    run.alpha = torch.full((64,), 40.0, dtype=F64)  # as if the hyperparameters had moved far since the last draw
    pi_before = transition_matrix(run.eta, run.F)
    run._sample_hyperparameters()
    torch.testing.assert_close(transition_matrix(run.eta, run.F), pi_before)
    f = run.F.to(F64)
    off = (1 - f.unsqueeze(-1) * f.unsqueeze(-2)) * (1 - torch.eye(run.F.shape[-1], dtype=F64))  # unowned, j != k
    ratio = (run.eta * off).sum((1, 2, 3)) / off.sum((1, 2, 3)) / run.alpha  # E[eta_jk] = alpha off the diagonal
    assert abs(float(ratio.mean()) - 1.0) < 0.05, float(ratio.mean())


@pytest.mark.parametrize("seed", [1, 3])
def test_synthetic_steps_follow_the_hmm_state_switches(seed):
    # Steps are runs of HMM states: every boundary lies within the local refinement radius of a switch of the
    # sampled state sequence, so the corners are found only if the sampler's switches are near them. At a coarse
    # resolution (max_samples=30, ~7 points per leg) a labeller that ignores the data (a new label every few
    # points) leaves corners out of reach of every candidate; the BP-GM-HMM puts its switches at the corners.
    W = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 2.0]], dtype=F64)
    syn = multi_step_demos(torch.Generator().manual_seed(seed), waypoints=W, n_demos=3, samples_per_step=60,
                           profile="constant")  # fmt: skip
    seg = segment(syn.demos, generator=torch.Generator().manual_seed(seed), max_samples=30, min_length=0.02, **FAST)
    assert seg.n_steps == 4
    for i in range(3):
        switches = torch.tensor(seg.info["hmm_switches"][i], dtype=torch.long)
        torch.testing.assert_close(runs(seg.states[i])[0][1:], switches)  # the switches of the returned states
        inner = seg.boundaries[i, 1:-1]
        dist = (inner.unsqueeze(-1) - switches.unsqueeze(0)).abs().amin(-1)
        assert int(dist.max()) <= seg.info["refine_radius"][i]
    err = boundary_errors(seg, syn.switch_times, syn.demos.lengths)
    assert float(err.max()) <= 0.035, err
