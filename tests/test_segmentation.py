"""BP-GM-HMM sampler and Segmentation: reproducibility, synthetic switch points, API contract, bad input."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from lfd_torch.data import Demos
from lfd_torch.errors import NonFiniteError, ShapeMismatchError, TooFewSamplesError
from lfd_torch.segmentation import (
    BetaProcessHMMSampler,
    BPGMHMMSegmenter,
    FixedSegmenter,
    NoSegmenter,
    Segmentation,
    multi_step_demos,
    runs,
    segment,
)
from lfd_torch.segmentation.segmentation import _absorb_short, _best_split, _steps_from_bounds
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
    torch.testing.assert_close(seg.attractors[0], syn.demos.end_points.mean(0))
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
