"""Independent references for the skill decision engine, the library and its persistence, the stability check and
the push plans, each written against a mutant that the other tests let through: naive per-row loops, Python-float
boundary arithmetic, closed forms of the sampling regions, brute-force distance searches and the documented
argument contracts. Every fixture is a small library learned without the stability check (well under a second)."""

from __future__ import annotations

import dataclasses
import json
import math
import statistics

import pytest
import torch

from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError, StoreError
from lfd_torch.modulation import Modulation
from lfd_torch.skills import (
    Arrival,
    SkillEngine,
    SkillLibrary,
    SkillSettings,
    check_stability,
    random_pushes,
)
from lfd_torch.skills.library import _manifest_digest, _step_pieces
from lfd_torch.skills.stability import stability_samples
from test_skills import _l_task, _two_ways_task

F64 = torch.float64


@pytest.fixture(scope="module")
def small_library() -> SkillLibrary:
    """The two-leg L task (steps 0 and 1, one route), learned without the stability check."""
    demos, seg = _l_task()
    return SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1), check=False)


# ---------------------------------------------------------------------------------------------------- arrival
def test_arrival_settings_reject_what_the_docstring_excludes() -> None:
    """Property: every Arrival field is a non-negative number; radius and slow_radius are positive and finite
    (slow_radius divides the distance in the speed cap), max_speed is positive and may be inf (no cap), min_rate may
    be 0 (no floor); a negative value is refused for every field."""
    Arrival(max_speed=math.inf, min_rate=0.0)  # the two documented ways to disable the cap and the floor
    for field in ("radius", "min_rate", "max_speed", "slow_radius"):
        with pytest.raises(InvalidArgumentError, match=field):
            Arrival(**{field: -0.5})
    for field in ("radius", "slow_radius", "max_speed"):
        with pytest.raises(InvalidArgumentError):
            Arrival(**{field: 0.0})
    for field in ("radius", "slow_radius", "min_rate"):
        with pytest.raises(InvalidArgumentError):
            Arrival(**{field: math.inf})


def test_settings_pass_their_learn_arguments_and_check_the_arrival() -> None:
    """Property: ``SkillSettings.learn_kwargs`` is exactly what the dataclass holds (a check mapping stays a mapping
    of check_stability arguments, the entropy reference is passed through), and a non-Arrival arrival is refused."""
    s = SkillSettings(entropy_quantile=0.5, entropy_reference="reproduction", check={"n_box": 10, "modes": ["none"]})
    assert s.learn_kwargs == {"entropy_quantile": 0.5, "entropy_reference": "reproduction",
                              "check": {"n_box": 10, "modes": ["none"]}}  # fmt: skip
    assert SkillSettings(check=0).learn_kwargs["check"] is False
    with pytest.raises(InvalidArgumentError, match="arrival"):
        SkillSettings(arrival={"radius": 0.01})  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------------- engine
def _ball_on(g0: float, t: float, span: float) -> tuple[float, float]:
    """An Arrival radius and a coordinate x0 with r_a = radius x span = x0 - g0 exactly in floats (x0 - g0 as the
    engine computes it), found by stepping the radius up from t / span one ulp at a time."""
    rad = t / span
    for _ in range(100_000):
        r_a = rad * span
        x0 = g0 + r_a
        if float(torch.tensor(x0, dtype=F64) - torch.tensor(g0, dtype=F64)) == r_a:
            return rad, x0
        rad = math.nextafter(rad, math.inf)
    raise AssertionError("no radius puts a representable state on the sphere")


def test_the_arrival_ball_is_open_in_every_path(small_library: SkillLibrary) -> None:
    """Property: a step is complete iff ||x - g_m||^2 < r_a^2 (strict: the open ball of the Arrival docstring), in the
    batched decision and in the single-state probe. Reference: the same comparison in Python floats, on states a few
    ulp inside, on and outside the sphere (r_a is made exactly representable as x_0 - g_0, so that one state lies on
    the sphere exactly); for a float64 engine the probe must not round r_a^2 to another precision."""
    lib = small_library
    g = lib.attractors[0]
    for t in (0.01, 0.0123, 0.0171):
        rad, x0 = _ball_on(float(g[0]), t, lib.span)
        eng = SkillEngine(lib, "none", Arrival(radius=rad))
        r2 = eng.arrival_radius * eng.arrival_radius
        xs, want = [], []
        xk = x0
        for _ in range(4):
            xk = math.nextafter(xk, -math.inf)
        for _ in range(9):  # 4 ulp inside .. 4 ulp outside
            x = g.clone()
            x[0] = xk
            e = float(x[0] - g[0])
            xs.append(x)
            want.append(e * e < r2)
            xk = math.nextafter(xk, math.inf)
        assert want == [True] * 4 + [False] * 5  # the fifth state lies on the sphere: e^2 == r_a^2 exactly
        assert float(xs[4][0] - g[0]) ** 2 == r2
        x = torch.stack(xs)
        dec = eng.decide(x, torch.zeros(9, dtype=torch.long), torch.zeros(9, dtype=torch.long))
        assert dec.index.tolist() == [int(w) for w in want], t
        for i in range(9):
            assert eng.tick_probe(x[i])[1][0] == want[i], (t, i)


def test_several_steps_complete_in_one_tick(small_library: SkillLibrary) -> None:
    """Property: step completion is a loop (``while ||x - g_m|| < r_a: j += 1``, module docstring step 2): a state in
    the arrival balls of g_0 and g_1 (a wide ball) finishes both steps in one batched tick and one tree tick.
    Reference: the naive while loop over the route."""
    lib = small_library
    eng = SkillEngine(lib, "none", Arrival(radius=0.8))
    g0, g1 = lib.attractors
    x = torch.stack([0.5 * (g0 + g1), g0 + 0.1 * (g0 - g1), g1 + 2.0 * (g1 - g0)])
    route = lib.routes[0]
    want = []
    for xi in x:
        j = 0
        while j < len(route) and float(torch.linalg.vector_norm(xi - lib.attractors[route[j]])) < eng.arrival_radius:
            j += 1
        want.append(j)
    assert want == [2, 1, 0]
    dec = eng.decide(x, torch.zeros(3, dtype=torch.long), torch.zeros(3, dtype=torch.long))
    assert dec.index.tolist() == want and dec.done.tolist() == [True, False, False]
    assert [eng.tick(xi, step=0).index for xi in x] == want


def test_routes_ending_at_different_attractors_are_refused(small_library: SkillLibrary) -> None:
    """Property: one task has one final attractor; an engine over routes that end at g_0 and at g_1 is refused."""

    class Forked(SkillLibrary):
        @property
        def routes(self) -> tuple[tuple[int, ...], ...]:
            return ((0, 1), (0,))

    lib = small_library
    forked = Forked(lib.segmentation, lib.skills, lib.entropy_quantile, lib.span)
    with pytest.raises(InvalidArgumentError, match="final attractor"):
        SkillEngine(forked, "none")


def test_fractional_memberships_are_weighted_as_the_segmentation_does(small_library: SkillLibrary) -> None:
    """Property: SubtaskBank's log p(x|A_m) is ``Segmentation.log_density`` = max_j [log w_mj + log N(x; mu_j,
    Sigma_j)] also where the membership weights are not 0/1. Reference: the segmentation's own evaluation."""
    lib = small_library
    seg = lib.segmentation
    w = seg.space_weights.clone()
    scale = torch.linspace(0.05, 1.0, w.shape[1], dtype=w.dtype)
    seg2 = dataclasses.replace(seg, space_weights=w * scale)
    lib2 = dataclasses.replace(lib, segmentation=seg2)
    x = 1.5 * torch.randn(200, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
    got = SkillEngine(lib2, "full").log_density(x)
    assert torch.allclose(got, seg2.log_density(x), rtol=1e-12, atol=1e-11)
    assert not torch.allclose(got, seg.log_density(x), rtol=1e-6, atol=1e-6)


def test_subtask_densities_at_every_subtask_gaussian_mean(small_library: SkillLibrary) -> None:
    """Property: SubtaskBank's log p(x|A_m) equals ``Segmentation.log_density`` at the means of every subtask-space
    Gaussian (where a Gaussian outside A_m, were it counted as a member, would dominate step m's maximum).
    Reference: the segmentation's own evaluation."""
    lib = small_library
    seg = lib.segmentation
    x = seg.space_mean[(seg.space_weights > 0).any(0)]
    x = torch.cat([x, x + 0.01])
    assert torch.allclose(SkillEngine(lib, "full").log_density(x), seg.log_density(x), rtol=1e-12, atol=1e-11)


def test_an_explicit_inside_decision_overrides_the_densities(small_library: SkillLibrary) -> None:
    """Property: ``inside`` is the tree's decision and overrides the densities (log p(x|A_m-) is taken as -inf where
    inside), in the single-state ``tick_velocity`` as in the dense ``velocity``. Reference: the dense path, on states
    of leg 1 ticked as robots in step 0 (own < other there) declared inside, in modes large and full."""
    lib = small_library
    x = lib.skills[1].train_positions[20:60:5]
    step = torch.zeros(x.shape[0], dtype=torch.long)
    for mode in ("large", "full"):
        eng = SkillEngine(lib, mode)
        own, other = eng.own_other(x, step)
        assert bool((own < other).all())
        inside = torch.ones_like(step, dtype=torch.bool)
        v, branch = eng.velocity(x, step, torch.zeros_like(inside), inside, (own, other))
        for i in range(x.shape[0]):
            u, b = eng.tick_velocity(x[i], 0, True, (float(own[i]), float(other[i])))
            assert int(b) == int(branch[i]), (mode, i)
            torch.testing.assert_close(u, v[i], rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------------------------------- library
def test_step_duration_is_the_median_piece_duration() -> None:
    """Property: ``Skill.duration`` is the median over a step's pieces of (time of the last sample - time of the
    first), pieces that start late in their demonstration included. Reference: per-piece Python loop and
    ``statistics.median`` on three pieces of distinct durations and start times (median != mean)."""
    seqs, times = [], []
    for t0, dur, n in ((0.7, 1.0, 11), (3.0, 2.0, 21), (10.0, 6.0, 31)):
        u = torch.linspace(0.0, 1.0, n, dtype=F64)
        seqs.append(torch.stack([u, u**2], -1))
        times.append(t0 + dur * u)
    pieces = Demos.from_sequences(seqs, times=times, attractor=torch.tensor([1.0, 1.0], dtype=F64))
    _, _, duration = _step_pieces(pieces)
    want = statistics.median(float(t[-1] - t[0]) for t in times)
    assert want == pytest.approx(2.0)
    assert duration == pytest.approx(want, rel=1e-12)


def test_span_is_the_largest_coordinate_range() -> None:
    """Property: ``SkillLibrary.span`` (the scale of every engine tolerance) is the largest coordinate range of the
    demonstrated positions, on a task whose x range (4) and y range (2) differ. Reference: a per-coordinate loop."""
    demos, seg = _two_ways_task()
    lib = SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(0), check=False)
    x = demos.samples()[0].tolist()
    want = max(max(p[a] for p in x) - min(p[a] for p in x) for a in range(2))
    assert lib.span == pytest.approx(want, rel=1e-15) and want > 3.9


def test_a_library_needs_its_skills_in_step_order_and_a_positive_span(small_library: SkillLibrary) -> None:
    """Property (the SkillLibrary contract): ``skills[m].step == m`` and a finite span > 0."""
    lib = small_library
    with pytest.raises(ShapeMismatchError, match="step order"):
        SkillLibrary(lib.segmentation, tuple(reversed(lib.skills)), lib.entropy_quantile, lib.span)
    for span in (0.0, -1.0, math.inf):
        with pytest.raises(InvalidArgumentError, match="span"):
            SkillLibrary(lib.segmentation, lib.skills, lib.entropy_quantile, span)


def test_reuse_with_another_attractor_is_refused(small_library: SkillLibrary) -> None:
    """Property: a reused primitive must have the attractor g_m of the step it is reused for (learn's docstring)."""
    demos, seg = _l_task()
    with pytest.raises(ShapeMismatchError, match="reuse"):
        SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1), check=False,
                           reuse={0: small_library.skills[1]})  # fmt: skip


def test_learn_passes_the_check_arguments_to_the_stability_check() -> None:
    """Property: ``check={...}`` runs check_stability with those arguments: the stored report lists only the modes
    asked for and the sample count asked for."""
    demos, seg = _l_task()
    lib = SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1),
                             check={"modes": ["none"], "n_box": 40, "n_near": 10, "n_far": 10})  # fmt: skip
    assert set(lib.stability["margins"]) == {"none"} and lib.stability["n_samples"] == 60


def test_a_manifest_that_omits_a_needed_file_is_a_store_error(small_library: SkillLibrary, tmp_path) -> None:
    """Property: load checks that the manifest lists every file a library needs (segmentation, skills and one file
    per step), not only the ones it lists: a manifest with a valid digest that leaves out step_1.pt (whose file is
    then read unchecked) is a StoreError naming it."""
    root = tmp_path / "lib"
    small_library.save(root)
    man = json.loads((root / "manifest.json").read_text())
    del man["files"]["step_1.pt"]
    man["digest"] = _manifest_digest(man)
    (root / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(StoreError, match="step_1.pt"):
        SkillLibrary.load(root)


def test_a_library_loaded_in_another_dtype_is_entirely_in_it(small_library: SkillLibrary, tmp_path) -> None:
    """Property: ``load(dtype=float32)`` (no device given) gives every floating tensor of the library in float32:
    primitives, thresholds, training positions and the segmentation. Reference: a walk over the fields."""
    small_library.save(tmp_path / "lib")
    lib = SkillLibrary.load(tmp_path / "lib", dtype=torch.float32)
    seg = lib.segmentation
    tensors = [seg.attractors, seg.space_mean, seg.space_covariance, seg.space_weights]
    for s in lib.skills:
        tensors += [s.h2_ref, s.train_positions, s.primitive.A, s.primitive.P, s.primitive.attractor]
    assert [t.dtype for t in tensors] == [torch.float32] * len(tensors)


# ---------------------------------------------------------------------------------------------------- stability
def test_stability_samples_fill_the_three_regions(small_library: SkillLibrary) -> None:
    """Property: box samples are uniform in the data's bounding box grown by box_scale about its centre (in it, and
    outside the data box with probability 1 - box_scale^-d); near samples are uniform in the ball of radius
    near_radius x span about g_m (inside it, P(r < R/2) = 2^-d); far samples lie at exactly far_scale x span from the
    box centre. Reference: the closed forms, with binomial tolerances (n = 4000)."""
    lib = small_library
    n = 4000
    x, region = stability_samples(lib, 1, generator=torch.Generator().manual_seed(0), n_box=n, n_near=n, n_far=50,
                                  box_scale=1.5, near_radius=0.05, far_scale=100.0)  # fmt: skip
    data = torch.cat([s.train_positions for s in lib.skills])
    lo, hi = data.amin(0), data.amax(0)
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    box, near, far = x[region == 0], x[region == 1], x[region == 2]
    assert box.shape[0] == near.shape[0] == n and far.shape[0] == 50
    assert bool(((box - c).abs() <= 1.5 * h * (1 + 1e-12)).all())
    out = float(((box < lo) | (box > hi)).any(-1).double().mean())
    assert abs(out - (1 - 1.5**-2)) < 0.04
    r = torch.linalg.vector_norm(near - lib.attractors[1], dim=-1) / (0.05 * lib.span)
    assert bool((r <= 1 + 1e-12).all())
    assert abs(float((r < 0.5).double().mean()) - 0.25) < 0.03
    dist = torch.linalg.vector_norm(far - c, dim=-1)
    assert torch.allclose(dist, torch.full_like(dist, 100.0 * lib.span), rtol=1e-12)


def test_stability_report_equals_a_direct_evaluation_of_the_engine_field(small_library: SkillLibrary) -> None:
    """Property: the report's per-step margins are the largest cosine between grad V_m and the field of an engine
    with the given arrival and modulation settings, on the samples of ``stability_samples`` (drawn step after step
    from one generator seeded with ``seed``). Reference: a per-row Python loop over the engine's velocities, with
    settings far from the defaults (a strong rate floor, a low speed cap, other modulation constants)."""
    lib = small_library
    arrival = Arrival(min_rate=40.0, max_speed=0.2)
    kw = {"n_box": 60, "n_near": 20, "n_far": 20}
    modes = ["none", "full"]
    rep = check_stability(lib, modes=modes, arrival=arrival, lambda_limit=1.5, radial_floor=0.6, seed=3, **kw)
    gen = torch.Generator().manual_seed(3)
    samples = [stability_samples(lib, m, generator=gen, **kw)[0] for m in range(lib.n_steps)]
    worst = -math.inf
    for mode in modes:
        eng = SkillEngine(lib, Modulation(mode=mode, lambda_limit=1.5, radial_floor=0.6), arrival)
        for m, x in enumerate(samples):
            u, _ = eng.velocity(x, torch.full((x.shape[0],), m), torch.zeros(x.shape[0], dtype=torch.bool))
            P, g = lib.skills[m].primitive.P.tolist(), lib.attractors[m].tolist()
            cos = []
            for xi, ui in zip(x.tolist(), u.tolist()):
                e = [a - b for a, b in zip(xi, g)]
                pe = [sum(P[i][j] * e[j] for j in range(2)) for i in range(2)]
                dv = 2 * sum(a * b for a, b in zip(pe, ui))
                den = 2 * math.hypot(*pe) * math.hypot(*ui)
                cos.append(dv / den if den > 0 else 0.0)
            assert rep.margins[mode][m] == pytest.approx(max(cos), rel=1e-9, abs=1e-12), (mode, m)
            worst = max(worst, max(cos))
    assert rep.worst_margin == pytest.approx(worst, rel=1e-9, abs=1e-12)
    default = check_stability(lib, modes=modes, seed=3, **kw)
    assert max(abs(a - b) for k in modes for a, b in zip(rep.margins[k], default.margins[k])) > 1e-3


def test_stability_check_evaluates_the_modulation_it_is_given(small_library: SkillLibrary, monkeypatch) -> None:
    """Property: check_stability evaluates, in every mode asked for, the field of an engine built with the given
    ``lambda_limit`` and ``radial_floor`` (its per-step maxima need not move with them on this library, so the
    engines are observed directly). Reference: the arguments themselves, recorded by a spy on the velocity calls."""
    seen = []
    original = SkillEngine.velocity

    def spy(self: SkillEngine, *args: object, **kwargs: object) -> tuple[torch.Tensor, torch.Tensor]:
        seen.append((self.modulation.mode, self.modulation.lambda_limit, self.modulation.radial_floor))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(SkillEngine, "velocity", spy)
    check_stability(small_library, modes=["small", "full"], lambda_limit=1.5, radial_floor=0.6, n_box=20, n_near=5,
                    n_far=5)  # fmt: skip
    assert sorted(set(seen)) == [("full", 1.5, 0.6), ("small", 1.5, 0.6)]
    assert len(seen) == 2 * small_library.n_steps


# ---------------------------------------------------------------------------------------------------- pushes
def test_push_plan_draws_distinct_samples_in_the_window_and_magnitudes_in_range() -> None:
    """Property (random_pushes' docstring): P pushes per robot at distinct samples of the inclusive window, sorted,
    magnitudes uniform in [low, high] (their range nearly filled), and a window of exactly P samples is enough."""
    plan = random_pushes(300, generator=torch.Generator().manual_seed(0), n_pushes=3, window=(30, 36),
                         magnitude=(0.5, 0.7))  # fmt: skip
    s = plan.steps
    assert bool(((s >= 30) & (s <= 36)).all()) and bool((s[:, 1:] > s[:, :-1]).all())
    assert set(s.reshape(-1).tolist()) == set(range(30, 37))
    mag = plan.magnitudes
    assert bool(((mag >= 0.5) & (mag <= 0.7)).all()) and float(mag.min()) < 0.51 and float(mag.max()) > 0.69
    exact = random_pushes(5, generator=torch.Generator().manual_seed(1), n_pushes=2, window=(5, 6), magnitude=(1, 1))
    assert exact.steps.tolist() == [[5, 6]] * 5
    with pytest.raises(InvalidArgumentError, match="window"):
        random_pushes(5, generator=torch.Generator(), n_pushes=3, window=(5, 6), magnitude=(1.0, 1.0))


def _push_state(done: list[bool]) -> dict:
    """The rollout state PushPlan.apply reads: every row in step 0, ``done`` as given."""
    return {"done": torch.tensor(done), "step": torch.zeros(len(done), dtype=torch.long)}


def test_rows_whose_task_is_done_are_not_pushed(small_library: SkillLibrary) -> None:
    """Property: a push never acts on a row whose task is done (module docstring): such rows keep their state and
    have no log entry. Reference: the done mask row by row."""
    lib = small_library
    eng = SkillEngine(lib, "full")
    B = 6
    x = lib.skills[0].train_positions[:B].clone()
    plan = random_pushes(B, generator=torch.Generator().manual_seed(2), n_pushes=1, window=(10, 10),
                         magnitude=(0.2, 0.3), kinds="random")  # fmt: skip
    done = [i % 2 == 1 for i in range(B)]
    y = plan.apply(10, x, eng, _push_state(done))
    assert y is not None
    assert sorted(p["row"] for p in plan.log) == [i for i in range(B) if not done[i]]
    for i in range(B):
        assert torch.equal(y[i], x[i]) == done[i], i


def test_small_pushes_land_away_from_the_step_data(small_library: SkillLibrary) -> None:
    """Property: a ``small`` push lands inside A_m and at least ``away`` from every training position of step m.
    Reference: a brute-force distance to the step's training positions, from states on the data pushed by a distance
    comparable to ``away`` (so that many candidate directions land too close)."""
    lib = small_library
    eng = SkillEngine(lib, "full")
    data = lib.skills[0].train_positions
    B = 40
    x = data[torch.linspace(5, data.shape[0] - 20, B).long()].clone()
    plan = random_pushes(B, generator=torch.Generator().manual_seed(3), n_pushes=1, window=(10, 10),
                         magnitude=(0.3, 0.3), kinds="small", away=0.2, n_candidates=64)  # fmt: skip
    y = plan.apply(10, x, eng, _push_state([False] * B))
    assert y is not None
    applied = 0
    for p in plan.log:
        if not p["applied"]:
            continue
        applied += 1
        b = p["row"]
        dist = min(math.dist(y[b].tolist(), q) for q in data.tolist())
        assert dist >= 0.2, (b, dist)
        own, other = eng.own_other(y[b].unsqueeze(0), torch.tensor([0]))
        assert float(own) >= float(other)
    assert applied >= B // 2
