"""Fuzz tests: malformed input to public entry points gives a typed lfd_torch error or a correct result.

Seeded (hypothesis derandomised), bounded example counts, < 60 s in total. Each property names what it checks.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lfd_torch.data import Demos
from lfd_torch.errors import LfdError
from lfd_torch.metrics import cosine_dissimilarity, dtw_distance, swept_area, velocity_error
from lfd_torch.modulation import modulated_velocity
from lfd_torch.preprocess import Preprocess
from lfd_torch.rollout import rollout

FUZZ = settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])

SPECIAL = [0.0, 1.0, -1.0, 1e300, -1e300, math.nan, math.inf, -math.inf, 1e-300]
DTYPES = [torch.float64, torch.float32, torch.float16, torch.int64, torch.bool]


@st.composite
def tensors(draw, max_rank: int = 3, max_side: int = 6):
    """Tensors of random rank, sides (including 0), dtype and special values."""
    rank = draw(st.integers(0, max_rank))
    shape = tuple(draw(st.integers(0, max_side)) for _ in range(rank))
    dtype = draw(st.sampled_from(DTYPES))
    n = int(torch.tensor(shape).prod()) if shape else 1
    values = draw(st.lists(st.sampled_from(SPECIAL) | st.floats(-10, 10), min_size=n, max_size=n))
    t = torch.tensor(values, dtype=torch.float64).reshape(shape)
    if dtype in (torch.int64, torch.bool):
        t = torch.nan_to_num(t, nan=0.0, posinf=0.0, neginf=0.0).clamp(-10, 10)
    return t.to(dtype)


def _typed_or_ok(fn, check=None):
    """Run fn: a typed LfdError is fine; any other exception fails; a result must pass ``check``."""
    try:
        out = fn()
    except LfdError:
        return None
    if check is not None:
        check(out)
    return out


def _finite(out) -> None:
    ts = out if isinstance(out, (tuple, list)) else [out]
    for t in ts:
        if isinstance(t, torch.Tensor) and t.is_floating_point():
            assert bool(torch.isfinite(t).all()), "a result with NaN/Inf was returned silently"


@st.composite
def sequences(draw):
    """(T, d) float sequences of plausible size with special values (NaN, Inf, huge) at random places."""
    T, d = draw(st.integers(1, 8)), draw(st.integers(0, 3))
    dtype = draw(st.sampled_from(DTYPES))
    values = draw(st.lists(st.floats(-10, 10) | st.sampled_from(SPECIAL), min_size=T * d, max_size=T * d))
    t = torch.tensor(values, dtype=torch.float64).reshape(T, d)
    return t.to(dtype) if dtype.is_floating_point else torch.nan_to_num(t, nan=0.0, posinf=0.0, neginf=0.0).to(dtype)


@FUZZ
@given(tensors())
def test_demos_from_malformed_sequences(x) -> None:
    """Demos.from_sequences on tensors of any rank: typed error or a valid set whose positions are finite."""
    _typed_or_ok(lambda: Demos.from_sequences([x]), lambda d: _finite(d.positions[d.mask]))


@FUZZ
@given(st.lists(sequences(), min_size=1, max_size=3))
def test_demos_from_sequences_with_special_values(xs) -> None:
    """Demos.from_sequences on (T, d) sequences: typed error or finite positions, velocities and times."""
    _typed_or_ok(lambda: Demos.from_sequences(xs),
                 lambda d: _finite((d.positions[d.mask], d.velocities[d.mask], d.times[d.mask])))  # fmt: skip


@FUZZ
@given(st.dictionaries(st.sampled_from(["window", "polyorder", "n_samples", "subsample_step", "screen_threshold",
                                        "resample_mode", "smoothing"]),
                       st.sampled_from([-3, -1, 0, 1, 2, 3, 4, 5, 2.5, None, "x", True, 1e9])))  # fmt: skip
def test_preprocess_hyperparameters(kwargs) -> None:
    """Preprocess(...): bad hyperparameters are typed errors at construction; good ones run on a small set."""
    demos = Demos.from_sequences([torch.linspace(0, 1, 40, dtype=torch.float64).unsqueeze(-1).expand(40, 2) ** 2])
    try:
        pre = Preprocess(**kwargs)
    except LfdError:
        return
    _typed_or_ok(lambda: pre(demos), lambda d: _finite(d.positions[d.mask]))


@FUZZ
@given(tensors(max_rank=3), tensors(max_rank=3))
def test_metrics_on_malformed_pairs(a, b) -> None:
    """E1, E2, E3, DTWD: typed error or finite values."""
    for fn in (velocity_error, cosine_dissimilarity, swept_area, dtw_distance):
        _typed_or_ok(lambda fn=fn: fn(a, b), _finite)


@FUZZ
@given(tensors(max_rank=3), st.sampled_from([0.01, 0.0, -1.0, math.nan, math.inf]), st.integers(-2, 20))
def test_rollout_with_malformed_starts_and_steps(x0, dt, n_steps) -> None:
    """rollout(-x): typed error or finite trajectories, never farther from 0 than where they started (dt <= 0.01
    on the contraction x_dot = -x)."""

    def check(r):
        _finite(r.positions)
        norms = r.positions.abs().amax(-1)  # (B, T): the largest coordinate, so huge finite starts do not overflow
        assert bool((norms <= norms[:, :1] * (1 + 1e-9)).all()), "a rollout of x_dot = -x moved away from 0"

    _typed_or_ok(lambda: rollout(lambda x: -x, x0, dt, n_steps), check)


@FUZZ
@given(tensors(max_rank=2), tensors(max_rank=2), tensors(max_rank=1),
       st.sampled_from(["none", "large", "small", "full", "bogus"]))  # fmt: skip
def test_modulation_with_malformed_inputs(x, f, g, mode) -> None:
    """modulated_velocity: typed error or finite velocities."""
    _typed_or_ok(lambda: modulated_velocity(x, f, g, log_p_own=0.0, log_p_other=-1.0, h2=1.0, h2_ref=0.5,
                                            mode=mode).velocity, _finite)  # fmt: skip


@pytest.fixture(scope="module")
def library():
    from lfd_torch.segmentation import FixedSegmenter
    from lfd_torch.segmentation.synthetic import multi_step_demos
    from lfd_torch.skills import SkillLibrary

    corners = torch.tensor([[-1.0, 1.0], [-1.0, 0.0], [0.0, 0.0]], dtype=torch.float64)
    demos = multi_step_demos(torch.Generator().manual_seed(0), n_demos=2, waypoints=corners, samples_per_step=40,
                             timing_jitter=0.0).demos  # fmt: skip
    return SkillLibrary.learn(demos, FixedSegmenter([0.5])(demos), generator=torch.Generator().manual_seed(1),
                              check=False)  # fmt: skip


@FUZZ
@given(x=tensors(max_rank=2, max_side=4), step=st.sampled_from([None, 0, 1, 2, -1, 1.5, "a"]))
def test_engine_tick_and_decide_with_malformed_states(library, x, step) -> None:
    """SkillEngine.tick / decide / rollout: typed error or a finite velocity."""
    from lfd_torch.skills import SkillEngine

    eng = SkillEngine(library, "full")
    _typed_or_ok(lambda: eng.tick(x, step=step).velocity, _finite)
    _typed_or_ok(lambda: eng.decide(x).step)
    _typed_or_ok(lambda: eng.rollout(x, dt=0.01, n_steps=5).result.positions, _finite)


@FUZZ
@given(st.integers(0, 5), st.binary(min_size=1, max_size=1))
def test_damaged_library_files_are_store_errors(library, tmp_path_factory, which, byte) -> None:
    """A byte changed anywhere in any file of a saved library gives StoreError on load."""
    from lfd_torch.errors import StoreError
    from lfd_torch.skills import SkillLibrary

    root = tmp_path_factory.mktemp("lib")
    library.save(root)
    files = sorted(p for p in root.iterdir() if p.is_file())
    target = files[which % len(files)]
    raw = bytearray(target.read_bytes())
    pos = (which * 7919) % len(raw)
    if raw[pos] == byte[0]:
        return
    raw[pos] = byte[0]
    target.write_bytes(bytes(raw))
    with pytest.raises(StoreError):
        SkillLibrary.load(root)


@FUZZ
@given(st.integers(0, 10_000), st.integers(1, 255))
def test_single_byte_flips_in_saved_primitives_are_detected(library, tmp_path_factory, where, delta) -> None:
    """Every single-byte change of a saved primitive file gives StoreError (checksum or format), never a model."""
    from lfd_torch.ds import load_primitive
    from lfd_torch.errors import StoreError

    root = tmp_path_factory.mktemp("prim")
    path = library.skills[0].primitive.save(root / "p.pt")
    raw = bytearray(path.read_bytes())
    pos = where % len(raw)
    raw[pos] = (raw[pos] + delta) % 256
    path.write_bytes(bytes(raw))
    try:
        load_primitive(path)
    except (StoreError, LfdError):
        return
    # torch's zip container ignores some bytes (e.g. padding, local headers): a load that succeeds must then be
    # the unchanged model
    again = load_primitive(path)
    assert torch.equal(again.A, library.skills[0].primitive.A)


@FUZZ
@given(st.integers(0, 100_000), st.integers(1, 255))
def test_single_byte_flips_in_saved_segmentations_are_detected(library, tmp_path_factory, where, delta) -> None:
    """Every single-byte change of a saved segmentation gives StoreError, or loads the unchanged content."""
    from lfd_torch.errors import StoreError
    from lfd_torch.segmentation import Segmentation

    root = tmp_path_factory.mktemp("seg")
    path = library.segmentation.save(root / "s.pt")
    raw = bytearray(path.read_bytes())
    pos = where % len(raw)
    raw[pos] = (raw[pos] + delta) % 256
    path.write_bytes(bytes(raw))
    try:
        seg = Segmentation.load(path)
    except (StoreError, LfdError):
        return
    assert torch.equal(seg.space_mean, library.segmentation.space_mean)
    assert all(torch.equal(a, b) for a, b in zip(seg.labels, library.segmentation.labels))


# ---------------------------------------------------------------------------------------------- entry points the
# malformed-input audit (experiments/audit_inputs.py) found weak: hyperparameters of the fitters, primitives'
# inputs, the store's paths, aggregate, pushes and stability-check arguments.
VALUES = st.sampled_from([-3, -1, 0, 1, 2, 3, 2.5, 1e9, 10**9, math.nan, math.inf, None, "2", True, [2], (0,)])


@pytest.fixture(scope="module")
def tiny():
    """Three 2-D demonstrations of 30 samples and an LPV-DS fitted to them (K = 2)."""
    from lfd_torch.ds import fit_lpvds
    from lfd_torch.gmm import EMFitter

    t = torch.linspace(0, 3, 30, dtype=torch.float64)
    seqs = [torch.stack([a * 10 * torch.exp(-t) * torch.cos(t), a * 5 * torch.exp(-t)], -1) for a in (1.0, 0.8, 1.2)]
    demos = Demos.from_sequences(seqs, dt=0.1)
    model = fit_lpvds(demos, gmm=EMFitter(n_components=2, max_iter=10), generator=torch.Generator().manual_seed(0))
    return demos, model


def _raises_typed(fn) -> None:
    with pytest.raises(LfdError):
        fn()


@FUZZ
@given(st.sampled_from(["n_components", "max_iter", "n_init", "tol", "reg_covar", "kmeans_iter"]), VALUES)
def test_em_hyperparameters(tiny, name, value) -> None:
    """fit_em: a hyperparameter of the wrong type or range is a typed error naming it; a valid one gives a GMM."""
    from lfd_torch.gmm import fit_em

    x = tiny[0].samples()[0]
    kw = {"n_components": 2, "max_iter": 5, name: value}
    ints = {"n_components": 1, "max_iter": 0, "n_init": 1, "kmeans_iter": 0}
    if name in ints:
        valid = isinstance(value, int) and not isinstance(value, bool) and ints[name] <= value <= 1000
        valid = valid and (name != "n_components" or value <= x.shape[0])
    else:
        valid = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0
    if not valid:
        with pytest.raises(LfdError, match=name):
            fit_em(x, generator=torch.Generator().manual_seed(0), **kw)
        return
    gmm = fit_em(x, generator=torch.Generator().manual_seed(0), **kw)
    assert gmm.n_components == kw["n_components"] and bool(torch.isfinite(gmm.means).all())


@settings(max_examples=15, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(["n_components", "max_iter", "max_restarts", "em_n_init", "eps", "reg", "tolerance_grad"]),
       st.sampled_from([0, -1, 2.5, "2", True, None, math.nan, math.inf, 10**12]))  # fmt: skip
def test_seds_hyperparameters_are_typed_errors(tiny, name, value) -> None:
    """fit_seds: n_components=2.5 no longer fits K=2, max_iter=0 no longer returns the EM start: typed errors."""
    from lfd_torch.ds import fit_seds

    if name == "n_components" and value is None:
        return  # None selects K with PC-GMM: a valid (and slower) path
    number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if name in ("eps", "reg", "tolerance_grad"):
        valid = number and (value >= 0 if name == "tolerance_grad" else value > 0)
    else:
        low, high = {"n_components": (1, 90), "max_iter": (1, 100_000), "max_restarts": (0, 1000),
                     "em_n_init": (1, 1000)}[name]  # fmt: skip
        valid = isinstance(value, int) and not isinstance(value, bool) and low <= value <= high
    kw = {"n_components": 2, "max_iter": 5, name: value}
    if valid:  # possibly extreme (eps = 1e12): a certified model, or a typed error
        _typed_or_ok(lambda: fit_seds(tiny[0], generator=torch.Generator().manual_seed(0), **kw),
                     lambda m: m.stability_certificate().certified or pytest.fail("uncertified SEDS returned"))
        return
    with pytest.raises(LfdError, match=name):
        fit_seds(tiny[0], generator=torch.Generator().manual_seed(0), **kw)


@FUZZ
@given(tensors(max_rank=3, max_side=4))
def test_primitive_call_on_malformed_positions(tiny, x) -> None:
    """model(x), V(x), dV/dt(x): a typed error naming x, or finite values, for any tensor (NaN, huge, int ...)."""
    model = tiny[1]
    for fn in (model, model.lyapunov, model.lyapunov_derivative):
        try:
            out = fn(x)
        except LfdError as exc:
            assert "x" in str(exc)
            continue
        _finite(out)


@FUZZ
@given(st.sampled_from([None, 3, "", b"x", 1.5, [1]]))
def test_store_paths_of_the_wrong_type(tiny, path) -> None:
    """save / load / write_table / read_table / collect with a path that is not a path: StoreError, never a crash."""
    from lfd_torch.ds import load_primitive
    from lfd_torch.errors import StoreError
    from lfd_torch.store import collect, read_table

    for fn in (lambda: tiny[1].save(path), lambda: load_primitive(path), lambda: read_table(path),
               lambda: collect(path)):  # fmt: skip
        with pytest.raises(StoreError):
            fn()


@FUZZ
@given(tensors(max_rank=2), st.one_of(st.none(), tensors(max_rank=2)))
def test_aggregate_on_malformed_values(values, counts) -> None:
    """aggregate: typed error or a finite value."""
    from lfd_torch.metrics import aggregate

    _typed_or_ok(lambda: aggregate(values, counts), _finite)


@FUZZ
@given(st.sampled_from(["window", "n_samples", "step", "threshold", "position_tol"]), VALUES)
def test_regularize_functions_reject_bad_arguments(tiny, name, value) -> None:
    """smooth / resample / subsample / screen_dimensions / trim_still_tail: typed errors or a valid set."""
    from lfd_torch import preprocess as pp

    d = tiny[0]
    call = {
        "window": lambda: pp.moving_average(d, value),
        "n_samples": lambda: pp.resample(d, value),
        "step": lambda: pp.subsample(d, value),
        "threshold": lambda: pp.screen_dimensions(d, value),
        "position_tol": lambda: pp.trim_still_tail(d, value, 0.1),
    }[name]
    _typed_or_ok(call, lambda out: _finite(out.positions[out.mask]))


@FUZZ
@given(st.sampled_from(["n_rows", "n_pushes", "window", "magnitude", "kinds", "away", "n_candidates"]),
       st.sampled_from([-1, 0, 2.5, "ab", None, (4, 1), (1.5, 3), (math.nan, 1.0), 10**12, ()]))  # fmt: skip
def test_random_pushes_arguments(name, value) -> None:
    """random_pushes: typed error or a plan whose steps lie in the window and magnitudes in the range."""
    from lfd_torch.skills import random_pushes

    kw = dict(n_rows=2, generator=torch.Generator().manual_seed(0), window=(1, 6), magnitude=(0.1, 0.2))
    kw[name] = value

    def check(plan) -> None:
        lo, hi = kw["window"]
        assert bool(((plan.steps >= lo) & (plan.steps <= hi)).all())
        _finite(plan.magnitudes)

    _typed_or_ok(lambda: random_pushes(**kw), check)


@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(tensors(max_rank=3, max_side=6), tensors(max_rank=3, max_side=6), st.sampled_from(["pcgmm", "damm", "em"]))
def test_gmm_fitters_on_malformed_samples(x, x_dot, method) -> None:
    """PC-GMM / DAMM / EM fitters on any tensors: a typed error, or a GMM with finite parameters of x's dimension."""
    from lfd_torch.gmm import DAMMFitter, EMFitter, PCGMMFitter

    fitter = {"pcgmm": PCGMMFitter(n_iter=2), "damm": DAMMFitter(n_iter=2), "em": EMFitter(n_components=1)}[method]

    def check(gmm) -> None:
        assert gmm.dim == x.shape[-1]
        _finite((gmm.weights, gmm.means, gmm.covariances))

    _typed_or_ok(lambda: fitter(x, x_dot, generator=torch.Generator().manual_seed(0)), check)


@FUZZ
@given(tensors(max_rank=2, max_side=4), st.sampled_from([None, "route", "index"]),
       st.sampled_from([torch.tensor([5, 0]), torch.tensor([0]), torch.tensor([0.5, 0.0]), torch.tensor([-1, 9]),
                        "abc", None]))  # fmt: skip
def test_engine_step_batch_with_malformed_progress(library, x, which, value) -> None:
    """SkillEngine.step_batch / decide: malformed states, routes or indices give typed errors, else finite output."""
    from lfd_torch.skills import SkillEngine

    eng = SkillEngine(library, "full")
    kw = {} if which is None else {which: value}
    if which == "index":
        kw["route"] = torch.zeros(2, dtype=torch.long)
    _typed_or_ok(lambda: eng.step_batch(x, **kw)[0], _finite)


@FUZZ
@given(tensors(max_rank=2, max_side=4), tensors(max_rank=1, max_side=3))
def test_goal_direction_and_small_scale_factor(x, g) -> None:
    """goal_direction(x, g) and small_scale_factor: typed error or finite unit vectors / factors in [0, 1]."""
    from lfd_torch.modulation import goal_direction, small_scale_factor

    _typed_or_ok(lambda: goal_direction(x, g).unit, _finite)

    def in_unit_interval(lam) -> None:  # NaN entries of h2 propagate (an unchecked kernel); the others lie in [0, 1]
        ok = lam[torch.isfinite(x)] if lam.shape == x.shape else lam
        assert bool(((ok >= 0) & (ok <= 1)).all())

    _typed_or_ok(lambda: small_scale_factor(x, 0.5), in_unit_interval)


@pytest.fixture(scope="module")
def plant():
    from lfd_torch.robot import BaxterPlant

    return BaxterPlant()


@FUZZ
@given(tensors(max_rank=2, max_side=8), st.sampled_from([None, 0, -1, 2.5, "3", 10**9, 1]))
def test_plant_commands_and_steps(plant, q, n_substeps) -> None:
    """BaxterPlant.set_command / apply_force / step: typed errors for malformed joint vectors, forces and counts."""
    from lfd_torch.robot import NEUTRAL_POSE

    _typed_or_ok(lambda: plant.set_command(q, torch.zeros(7, dtype=torch.float64)))
    _typed_or_ok(lambda: plant.apply_force("left_hand", q))
    plant.reset(torch.tensor(NEUTRAL_POSE, dtype=torch.float64))
    _typed_or_ok(lambda: plant.step(n_substeps))
