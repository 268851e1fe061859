"""Skill library, behaviour tree, decision engine, pushes and the stability check (lfd_torch.skills)."""

from __future__ import annotations

import functools
import itertools
import json
import math
import types

import pytest
import torch

from lfd_torch.data.lasa import load_lasa
from lfd_torch.ds import StablePrimitive, fit_lpvds, fit_seds, load_primitive
from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError, StoreError
from lfd_torch.gmm import PCGMMFitter
from lfd_torch.modulation import Branch, Modulation, modulated_velocity, renyi_entropy
from lfd_torch.segmentation import FixedSegmenter, segment
from lfd_torch.segmentation.synthetic import multi_step_demos
from lfd_torch.skills import (
    Arrival,
    SkillEngine,
    SkillLibrary,
    check_stability,
    random_pushes,
    rate_floor,
    speed_cap,
)

F64 = torch.float64


def _l_task(n_demos: int = 2, seed: int = 0):
    """Two legs (down, then right to the goal at the origin), minimum-jerk timing, switch exactly at the corner."""
    corners = torch.tensor([[-1.0, 1.0], [-1.0, 0.0], [0.0, 0.0]], dtype=F64)
    syn = multi_step_demos(torch.Generator().manual_seed(seed), n_demos=n_demos, waypoints=corners,
                           samples_per_step=60, timing_jitter=0.0, waypoint_jitter=0.01, noise=0.002)  # fmt: skip
    demos = syn.demos
    seg = FixedSegmenter([0.5])(demos)
    return demos, seg


@pytest.fixture(scope="module")
def l_library() -> SkillLibrary:
    demos, seg = _l_task()
    return SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1))


@pytest.fixture(scope="module")
def mm3_all() -> tuple:
    demos = load_lasa("Multi_Models_3")
    seg = segment(demos, generator=torch.Generator().manual_seed(0))
    return demos, SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(0), check={"n_box": 400,
                                     "n_near": 100, "n_far": 100})  # fmt: skip


@pytest.fixture(scope="module")
def two_ways_library() -> SkillLibrary:
    demos, seg = _two_ways_task()
    return SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(0), check=False)


@pytest.fixture(scope="module")
def mm3_one() -> tuple:
    demos = load_lasa("Multi_Models_3")[[0]]
    seg = segment(demos, generator=torch.Generator().manual_seed(0))
    return demos, SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(0), check={"n_box": 400,
                                     "n_near": 100, "n_far": 100})  # fmt: skip


# ---------------------------------------------------------------------------------------------- library
def test_learn_fits_one_certified_primitive_per_step(l_library: SkillLibrary) -> None:
    lib = l_library
    l_task_demos = _l_task()[0]
    seg = lib.segmentation
    assert lib.n_steps == seg.n_steps == 2
    for m, s in enumerate(lib.skills):
        assert s.step == m
        assert torch.allclose(s.attractor, seg.attractors[m])
        assert s.primitive.stability_certificate().certified
        # default threshold: the largest H2 over the step's own training states (independent evaluation)
        assert float(s.h2_ref) == pytest.approx(float(renyi_entropy(s.primitive, s.train_positions).max()), rel=1e-12)
        # the step's own samples, without the appended g_m, and the 0.9 quantile of their speeds (the engine's cap)
        x, v, _ = seg.split(l_task_demos)[m].samples()
        assert torch.equal(s.train_positions, x)
        assert s.speed == pytest.approx(float(v.norm(dim=-1).quantile(0.9)), rel=1e-12)
    assert lib.stability is not None and lib.stability["passed"]


def test_entropy_threshold_at_the_attractor_is_the_papers_literal_option() -> None:
    demos, seg = _l_task()
    lib = SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1), entropy_quantile=None, check=False)
    for s in lib.skills:
        assert float(s.h2_ref) == pytest.approx(float(renyi_entropy(s.primitive, s.attractor.unsqueeze(0))[0]))


def test_with_step_and_reuse_do_not_refit_the_other_steps(l_library: SkillLibrary) -> None:
    demos, seg = _l_task()
    calls = []
    base = functools.partial(fit_lpvds, gmm=PCGMMFitter(), lyapunov="pqlf")

    def counting(part, g, *, generator):
        calls.append(tuple(g.tolist()))
        return base(part, g, generator=generator)

    lib2 = SkillLibrary.learn(demos, seg, primitive=counting, generator=torch.Generator().manual_seed(1),
                              reuse={0: l_library.skills[0]}, check=False)  # fmt: skip
    assert calls == [tuple(seg.attractors[1].tolist())]  # only step 1 was fitted
    assert lib2.skills[0].primitive is l_library.skills[0].primitive or torch.equal(
        lib2.skills[0].primitive.A, l_library.skills[0].primitive.A
    )
    seds = fit_seds(seg.split(demos, end_at_attractor=True)[1], seg.attractors[1], n_components=2,
                    generator=torch.Generator().manual_seed(2))  # fmt: skip
    lib3 = l_library.with_step(1, seds)
    assert lib3.skills[0] is l_library.skills[0]
    assert lib3.skills[1].primitive is not l_library.skills[1].primitive and lib3.skills[1].primitive.kind == "SEDS"
    assert lib3.stability is None
    with pytest.raises(ShapeMismatchError, match="g_0"):
        l_library.with_step(0, seds)  # wrong attractor


def test_save_load_round_trip_reproduces_rollouts_bit_for_bit(l_library: SkillLibrary, tmp_path) -> None:
    l_library.save(tmp_path / "lib")
    lib2 = SkillLibrary.load(tmp_path / "lib")
    x0 = torch.tensor([[-1.2, 1.3], [-0.5, 0.6], [0.3, -0.4]], dtype=F64)
    a = SkillEngine(l_library, "full").rollout(x0, dt=0.01, n_steps=1500)
    b = SkillEngine(lib2, "full").rollout(x0, dt=0.01, n_steps=1500)
    assert torch.equal(a.result.positions, b.result.positions)
    assert torch.equal(a.branches, b.branches) and torch.equal(a.steps, b.steps)
    assert lib2.stability == json.loads(json.dumps(l_library.stability))


@pytest.mark.parametrize("damage", ["missing", "truncated", "flipped", "foreign_manifest", "bad_json", "schema"])
def test_damaged_library_files_raise_store_error_naming_the_file(l_library: SkillLibrary, tmp_path, damage) -> None:
    root = tmp_path / "lib"
    l_library.save(root)
    target = root / "step_1.pt"
    if damage == "missing":
        target.unlink()
    elif damage == "truncated":
        target.write_bytes(target.read_bytes()[:100])
    elif damage == "flipped":
        raw = bytearray(target.read_bytes())
        raw[len(raw) // 2] ^= 0x01
        target.write_bytes(bytes(raw))
    elif damage == "foreign_manifest":
        target = root / "manifest.json"
        target.write_text(json.dumps({"kind": "something else"}))
    elif damage == "bad_json":
        target = root / "manifest.json"
        target.write_text("{not json")
    else:
        target = root / "manifest.json"
        man = json.loads(target.read_text())
        man["schema_version"] = 999
        target.write_text(json.dumps(man))
    with pytest.raises(StoreError, match=target.name):
        SkillLibrary.load(root)


@pytest.mark.parametrize("edit", [{"span": 1e-3}, {"entropy_quantile": 0.5}, {"stability": {"passed": True}},
                                  {"info": {}}])
def test_an_edited_manifest_is_detected(l_library: SkillLibrary, tmp_path, edit) -> None:
    """The manifest carries a digest of its own content: an edited value (span sets the engine's arrival radius)
    is a StoreError naming the manifest, not a library that loads with it."""
    root = tmp_path / "lib"
    l_library.save(root)
    SkillLibrary.load(root)  # the untouched copy loads
    man = json.loads((root / "manifest.json").read_text())
    man.update(edit)
    (root / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(StoreError, match="manifest.json"):
        SkillLibrary.load(root)


def test_the_manifest_digest_survives_the_json_round_trip() -> None:
    """The digest is taken of the content as JSON reads it back: integer keys (sorted as numbers before writing,
    as strings after reading), tuples and NaN give the same digest at save and at load."""
    from lfd_torch.skills.library import _manifest_digest

    manifest = {"info": {2: 1.0, 10: math.nan, "routes": (1, 2)}, "span": 0.5}
    digest = _manifest_digest(manifest)
    back = json.loads(json.dumps({**manifest, "digest": digest}, indent=2, allow_nan=True))
    assert _manifest_digest(back) == digest


@pytest.mark.parametrize("value", ["abc", -1.0, None])
def test_a_schema_1_manifest_with_a_bad_span_is_a_store_error(l_library: SkillLibrary, tmp_path, value) -> None:
    """Libraries of schema 1 (no manifest digest) are still read, with their values checked."""
    root = tmp_path / "lib"
    l_library.save(root)
    man = json.loads((root / "manifest.json").read_text())
    man.pop("digest")
    man["schema_version"] = 1
    (root / "manifest.json").write_text(json.dumps(man))
    SkillLibrary.load(root)
    man["span"] = value
    (root / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(StoreError, match="span"):
        SkillLibrary.load(root)


def test_bad_dtype_or_device_on_load_blames_the_argument(l_library: SkillLibrary, tmp_path) -> None:
    root = tmp_path / "lib"
    l_library.save(root)
    with pytest.raises(InvalidArgumentError, match="dtype"):
        SkillLibrary.load(root, dtype=torch.float16)
    with pytest.raises(InvalidArgumentError, match="device"):
        SkillLibrary.load(root, device="bogus")
    with pytest.raises(InvalidArgumentError, match="dtype"):
        load_primitive(root / "step_0.pt", dtype=torch.float16)


# ---------------------------------------------------------------------------------------------- tree vs vectorised
def _random_pairs(lib: SkillLibrary, n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random (x, route, index): a third uniform in a box twice the data span, a third near an attractor of the
    route (inside and just outside the arrival ball), a third near the training data of a random step."""
    x_all = torch.cat([s.train_positions for s in lib.skills])
    lo, hi = x_all.amin(0), x_all.amax(0)
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    routes = lib.routes
    route = torch.randint(0, len(routes), (n,), generator=gen)
    length = torch.tensor([len(r) for r in routes])[route]
    index = (torch.rand(n, generator=gen, dtype=F64) * length).long()
    step = torch.tensor([routes[int(r)][int(j)] for r, j in zip(route, index)])
    x = c + 2 * h * (2 * torch.rand(n, 2, generator=gen, dtype=F64) - 1)
    third = n // 3
    r_a = Arrival().radius * lib.span
    g = lib.attractors[step[:third]]
    x[:third] = g + 2 * r_a * (2 * torch.rand(third, 2, generator=gen, dtype=F64) - 1)
    for i in range(third, 2 * third):
        data = lib.skills[int(step[i])].train_positions
        x[i] = data[int(torch.randint(0, data.shape[0], (1,), generator=gen))] + 0.02 * lib.span * torch.randn(
            2, generator=gen, dtype=F64
        )
    return x, route, index


def test_step_batch_takes_back_the_progress_it_returns(l_library: SkillLibrary) -> None:
    """A closed loop feeds ``Decision.route`` / ``.index`` back; a finished row's index is its route's length (done),
    which the next call must accept (it was rejected when the bound was the longest route - 1)."""
    from lfd_torch.errors import InvalidIndexError

    eng = SkillEngine(l_library, "full")
    x = l_library.skills[0].train_positions[:4].clone()
    v, dec, _ = eng.step_batch(x)
    for _ in range(4000):
        x = x + 0.01 * v
        v, dec, _ = eng.step_batch(x, dec.route, dec.index)
        if bool(dec.done.all()):
            break
    assert bool(dec.done.all()) and dec.index.tolist() == [len(l_library.routes[int(r)]) for r in dec.route]
    v2, dec2, _ = eng.step_batch(x, dec.route, dec.index)  # done rows stay done, at rest
    assert bool(dec2.done.all()) and torch.equal(dec2.index, dec.index)
    with pytest.raises(InvalidIndexError, match="index"):
        eng.step_batch(x, dec.route, dec.index + 1)


@pytest.mark.parametrize("which", ["l_library", "mm3_all", "two_ways_library"])
@pytest.mark.parametrize("mode", ["none", "full"])
def test_vectorised_decisions_equal_the_py_trees_tick(which: str, mode: str, request) -> None:
    lib = request.getfixturevalue(which)
    lib = lib[1] if isinstance(lib, tuple) else lib
    eng = SkillEngine(lib, mode)
    gen = torch.Generator().manual_seed(3)
    x, route, index = _random_pairs(lib, 1500, gen)
    v, dec, branch = eng.step_batch(x, route, index)
    fresh = torch.full_like(route, -1)
    v0, dec0, branch0 = eng.step_batch(x, fresh, torch.zeros_like(index))  # new tasks: the tree picks the route
    n_done = n_advanced = 0
    for i in range(x.shape[0]):
        r, j = int(route[i]), int(index[i])
        t = eng.tick(x[i], step=lib.routes[r][j], route=r)
        assert (t.route, t.index, t.done) == (int(dec.route[i]), int(dec.index[i]), bool(dec.done[i]))
        assert int(t.branch) == int(branch[i])
        # rounding only: the batched and per-row paths sum the entropy terms in different orders
        assert torch.allclose(t.velocity, v[i], rtol=1e-10, atol=1e-10), (t.velocity - v[i], t.branch)
        n_done += t.done
        n_advanced += t.index > j
        if i % 5 == 0:
            t0 = eng.tick(x[i])
            assert (t0.route, t0.index, int(t0.branch)) == (int(dec0.route[i]), int(dec0.index[i]), int(branch0[i]))
    assert n_advanced > 0  # the sample exercises step completion
    if lib.n_steps > 1 and mode == "full":
        assert bool((branch == int(Branch.LARGE_SCALE)).any())


def test_tick_records_decisions_and_stops_at_the_goal(l_library: SkillLibrary, tmp_path) -> None:
    eng = SkillEngine(l_library, "full")
    start = l_library.skills[0].train_positions[0]
    t = eng.tick(start)
    names = [n for n, _ in t.decisions]
    assert names[:2] == ["ChooseRoute 0", "Reached 0"] and "task" == names[-1]
    assert t.step == 0 and not t.done and torch.linalg.vector_norm(t.velocity) > 0
    last = l_library.n_steps - 1
    t = eng.tick(l_library.skills[last].attractor.clone(), step=last)
    assert t.done and t.step is None and torch.count_nonzero(t.velocity) == 0 and t.branch is Branch.AT_GOAL
    files = eng.tree.render(tmp_path / "tree")
    text = (tmp_path / "tree.txt").read_text()
    assert "step 0" in text and "Recover 1" in text and len(files) >= 2
    with pytest.raises(InvalidArgumentError):
        eng.tick(start, step=7)


# ---------------------------------------------------------------------------------------------- rollouts
def _lyapunov_rates(lib: SkillLibrary, out) -> torch.Tensor:
    """dV_m/dt = 2 (x - g_m)^T P_m x_dot at every valid moving sample, m the active step."""
    res = out.result
    x, v, steps = res.positions, res.velocities, out.steps
    g = lib.attractors[steps]
    P = torch.stack([s.primitive.P for s in lib.skills])[steps]
    e = x - g
    rate = 2 * torch.einsum("btd,btde,bte->bt", e, P, v)
    moving = res.mask & (torch.linalg.vector_norm(v, dim=-1) > 0)
    return rate[moving]


def test_rollout_completes_every_step_in_order(l_library: SkillLibrary) -> None:
    eng = SkillEngine(l_library, "full")
    gen = torch.Generator().manual_seed(5)
    x0 = torch.tensor([-1.0, 1.0], dtype=F64) + 0.6 * torch.randn(64, 2, generator=gen, dtype=F64)
    out = eng.rollout(x0, dt=0.01, n_steps=3000)
    assert bool(out.done.all()) and bool(out.result.converged.all())
    assert bool((out.steps[:, 1:] >= out.steps[:, :-1]).all())  # progress never goes back
    end = out.result.positions[torch.arange(64), out.result.lengths - 1]
    assert float(torch.linalg.vector_norm(end - l_library.segmentation.attractors[-1], dim=-1).max()) < eng.arrival_radius
    assert bool((_lyapunov_rates(l_library, out) < 0).all())


def test_pushes_are_labelled_by_where_they_land(l_library: SkillLibrary) -> None:
    eng = SkillEngine(l_library, "full")
    B = 64
    x0 = l_library.skills[0].train_positions[:1].expand(B, 2).clone()
    plan = random_pushes(B, generator=torch.Generator().manual_seed(7), n_pushes=2, window=(20, 120),
                         magnitude=(0.1 * l_library.span, 0.8 * l_library.span))  # fmt: skip
    out = eng.rollout(x0, dt=0.01, n_steps=3000, pushes=plan)
    assert bool(out.done.all())
    applied = [p for p in out.pushes if p["applied"]]
    assert {p["kind"] for p in applied} == {"large", "small"}
    for p in applied:
        b, k = p["row"], p["sample"]
        x = out.result.positions[b, k]
        step = torch.tensor([p["step"]])
        own, other = eng.own_other(x.unsqueeze(0), step)
        if p["kind"] == "large":
            assert float(own) < float(other)
        else:
            assert float(own) >= float(other) and p["data_distance"] >= plan.away
    # the same seed gives the same pushes
    again = eng.rollout(x0, dt=0.01, n_steps=3000, pushes=random_pushes(
        B, generator=torch.Generator().manual_seed(7), n_pushes=2, window=(20, 120),
        magnitude=(0.1 * l_library.span, 0.8 * l_library.span)))  # fmt: skip
    assert torch.equal(again.result.positions, out.result.positions)
    # a plan for another number of robots is refused before the rollout (it crashed inside torch at the first push)
    with pytest.raises(ShapeMismatchError, match="pushes"):
        eng.rollout(x0[:3], dt=0.01, n_steps=200, pushes=plan)


def test_subtask_spaces_tell_the_steps_apart(l_library: SkillLibrary) -> None:
    """A state on the middle of one leg is inside its own step's subtask space and outside the other's: the
    large-scale branch can fire (it would never fire if the spaces tied everywhere)."""
    eng = SkillEngine(l_library, "full")
    x = torch.tensor([[-1.0, 0.5], [-0.5, 0.0]], dtype=F64)  # middle of leg 0, middle of leg 1
    own0, other0 = eng.own_other(x, torch.tensor([0, 0]))
    own1, other1 = eng.own_other(x, torch.tensor([1, 1]))
    assert float(own0[0]) > float(other0[0]) and float(own0[1]) < float(other0[1])
    assert float(own1[1]) > float(other1[1]) and float(own1[0]) < float(other1[0])
    _, branch = eng.velocity(x, torch.tensor([1, 0]), torch.tensor([False, False]))
    assert branch.tolist() == [int(Branch.LARGE_SCALE)] * 2


def test_speed_cap_rescales_speed_only() -> None:
    gen = torch.Generator().manual_seed(0)
    u = torch.randn(500, 3, generator=gen, dtype=F64) * torch.logspace(-4, 2, 500, dtype=F64).unsqueeze(-1)
    r = torch.rand(500, generator=gen, dtype=F64) * 2
    out = speed_cap(u, r, 5.0, 1.0)
    cos = torch.nn.functional.cosine_similarity(out, u, dim=-1)
    assert torch.allclose(cos, torch.ones_like(cos))
    speed = torch.linalg.vector_norm(out, dim=-1)
    assert bool((speed <= 5.0 * r.clamp(max=1.0) * (1 + 1e-12)).all())
    below = torch.linalg.vector_norm(u, dim=-1) <= 5.0 * r.clamp(max=1.0)
    assert torch.equal(out[below], u[below])  # under the cap nothing changes
    assert torch.equal(speed_cap(u, r, math.inf, 1.0)[r > 0], u[r > 0])


def test_rate_floor_is_the_minimum_norm_correction() -> None:
    """dV/dt <= -rho V after the correction, with equality where it acts; untouched where v is fast enough; the
    correction is the minimum-norm one (checked against cvxpy-free closed form: any other admissible delta along
    a random direction is longer)."""
    gen = torch.Generator().manual_seed(1)
    d, n = 3, 400
    L = torch.randn(d, d, generator=gen, dtype=F64)
    P = L @ L.T + 0.2 * torch.eye(d, dtype=F64)
    e = torch.randn(n, d, generator=gen, dtype=F64)
    v = torch.randn(n, d, generator=gen, dtype=F64)
    rho = 0.7
    u = rate_floor(v, e, P, rho)
    V = torch.einsum("ni,ij,nj->n", e, P, e)
    rate_v = 2 * torch.einsum("ni,ij,nj->n", e, P, v)
    rate_u = 2 * torch.einsum("ni,ij,nj->n", e, P, u)
    acts = rate_v > -rho * V
    assert bool(acts.any() and (~acts).any())
    assert torch.allclose(rate_u[acts], -rho * V[acts], rtol=1e-10, atol=1e-12)
    assert torch.equal(u[~acts], v[~acts])
    # minimum norm: the admissible set is a half-space {delta: 2 (P e)^T delta <= -need}; its closest point is
    # along P e, so a delta with a component orthogonal to P e that is also admissible is longer
    Pe = e @ P
    delta = (u - v)[acts]
    w = torch.randn(int(acts.sum()), d, generator=gen, dtype=F64)
    w = w - (w * Pe[acts]).sum(-1, keepdim=True) / (Pe[acts] ** 2).sum(-1, keepdim=True) * Pe[acts]
    other = delta + 0.1 * w
    assert bool((torch.linalg.vector_norm(other, dim=-1) > torch.linalg.vector_norm(delta, dim=-1)).all())
    assert torch.equal(rate_floor(v[:3], torch.zeros(3, d, dtype=F64), P, rho), v[:3])


def test_rate_floor_and_speed_cap_in_the_feature_major_layout() -> None:
    """``dim=0`` with a precomputed P e (the engine's (d, n) layout) equals the (n, d) form transposed; P e is
    required for a leading vector axis."""
    gen = torch.Generator().manual_seed(2)
    d, n = 3, 300
    L = torch.randn(n, d, d, generator=gen, dtype=F64)
    P = L @ L.transpose(-1, -2) + 0.2 * torch.eye(d, dtype=F64)
    e, v = torch.randn(n, d, generator=gen, dtype=F64), torch.randn(n, d, generator=gen, dtype=F64)
    rho = torch.rand(n, generator=gen, dtype=F64)
    Pe = (P @ e.unsqueeze(-1)).squeeze(-1)
    got = rate_floor(v.T.contiguous(), e.T.contiguous(), None, rho, dim=0, Pe=Pe.T.contiguous())
    assert torch.allclose(got.T, rate_floor(v, e, P, rho), rtol=1e-14, atol=1e-14)
    r = torch.rand(n, generator=gen, dtype=F64)
    capped = speed_cap(v.T.contiguous(), r, 0.5, 0.7, dim=0)
    assert torch.allclose(capped.T, speed_cap(v, r, 0.5, 0.7), rtol=1e-14, atol=0)
    with pytest.raises(InvalidArgumentError, match="Pe"):
        rate_floor(v.T, e.T, P, rho, dim=0)


def test_single_state_shaping_equals_rate_floor_and_speed_cap() -> None:
    """``shape_single`` (the single-state tick's Python-float form) equals ``speed_cap(rate_floor(...))`` sample by
    sample: where the floor acts and where not, under and over the cap, at e = 0 and without a cap."""
    from lfd_torch.skills.arrival import shape_single

    gen = torch.Generator().manual_seed(4)
    d, n = 3, 400
    L = torch.randn(d, d, generator=gen, dtype=F64)
    P = L @ L.T + 0.2 * torch.eye(d, dtype=F64)
    e = torch.randn(n, d, generator=gen, dtype=F64) * torch.logspace(-3, 1, n, dtype=F64).unsqueeze(-1)
    e[:4] = 0
    v = torch.randn(n, d, generator=gen, dtype=F64) * 3
    tiny = torch.finfo(F64).tiny
    for v_hi in (2.0, math.inf):
        want = speed_cap(rate_floor(v, e, P, 0.7), torch.linalg.vector_norm(e, dim=-1), v_hi, 0.5)
        Pe = e @ P
        for i in range(n):
            u = shape_single(v[i].tolist(), e[i].tolist(), Pe[i].tolist(), 0.7, v_hi, 0.5, tiny)
            torch.testing.assert_close(torch.tensor(u, dtype=F64), want[i], rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("mode", ["none", "large", "small", "full"])
def test_single_state_velocity_equals_the_dense_one(mode: str, l_library: SkillLibrary, tmp_path) -> None:
    """``SkillEngine.tick_velocity`` (the tree's drive leaves: one step's tables, Python-float modulation and
    shaping) against the dense batched ``velocity`` row by row, with the tree's subtask decision and densities
    from ``tick_probe``, in every mode and in float32."""
    gen = torch.Generator().manual_seed(11)
    x, route, index = _random_pairs(l_library, 300, gen)
    l_library.save(tmp_path / "lib")
    for lib, tol in ((l_library, 1e-12), (SkillLibrary.load(tmp_path / "lib", dtype=torch.float32), 1e-5)):
        eng = SkillEngine(lib, mode)
        xs = x.to(lib.dtype)
        dec = eng.decide(xs, route, index)
        v, branch = eng.velocity(xs, dec.step, dec.done, dec.inside)
        for i in torch.nonzero(~dec.done).reshape(-1).tolist():
            m = int(dec.step[i])
            ld, _ = eng.tick_probe(xs[i])
            other = max(val for k, val in enumerate(ld) if k != m)
            assert (ld[m] >= other) == bool(dec.inside[i])
            u, b = eng.tick_velocity(xs[i], m, bool(dec.inside[i]), (ld[m], other))
            assert int(b) == int(branch[i]), i
            assert u.dtype == lib.dtype
            torch.testing.assert_close(u, v[i], rtol=tol, atol=tol)


def test_a_crawling_primitive_arrives_in_bounded_time_with_the_rate_floor(l_library: SkillLibrary) -> None:
    """Slow every primitive by 1e-3 (still certified): without the rate floor the task does not finish in the
    budget, with it it does, within the bound ln(V(x0) / (lambda_min(P) r_a^2)) / rho of every step; dV/dt < 0."""
    import dataclasses

    slow = l_library
    for s in l_library.skills:
        p = s.primitive
        slow = slow.with_step(s.step, dataclasses.replace(p, A=p.A * 1e-3))
    x0 = l_library.skills[0].train_positions[:4].clone()
    off = SkillEngine(slow, "none", Arrival(min_rate=0.0)).rollout(x0, dt=0.01, n_steps=2000)
    eng = SkillEngine(slow, "none", Arrival(min_rate=1.0))
    on = eng.rollout(x0, dt=0.01, n_steps=2000)
    assert not bool(off.done.any())
    assert bool(on.done.all())
    # time spent in each step <= the exponential-rate bound from the state where the step began
    for b in range(x0.shape[0]):
        for m, s in enumerate(slow.skills):
            ks = torch.nonzero(on.steps[b, : on.result.lengths[b]] == m).reshape(-1)
            e0 = on.result.positions[b, ks[0]] - s.attractor
            V0 = float(e0 @ s.primitive.P @ e0)
            lam = float(torch.linalg.eigvalsh(s.primitive.P)[0])
            bound = math.log(max(V0, 1e-300) / (lam * eng.arrival_radius**2)) / float(eng._rate[m])
            assert (ks.numel() - 1) * 0.01 <= max(bound, 0.0) + 0.02
    assert bool((_lyapunov_rates(slow, on) < 0).all())


# ---------------------------------------------------------------------------------------------- stability check
def test_stability_check_passes_and_catches_a_field_that_climbs_v(l_library: SkillLibrary, monkeypatch) -> None:
    rep = check_stability(l_library, n_box=300, n_near=100, n_far=100)
    assert rep.passed and rep.worst_margin < 0 and set(rep.margins) == {"none", "large", "small", "full"}
    original = SkillEngine.velocity

    def climbing(self, x, step, done, inside=None):
        v, b = original(self, x, step, done, inside)
        far = torch.linalg.vector_norm(x - self.goals[step], dim=-1) > 0.5 * self.library.span
        return torch.where(far.unsqueeze(-1), -v, v), b

    monkeypatch.setattr(SkillEngine, "velocity", climbing)
    bad = check_stability(l_library, modes=["none"], n_box=300, n_near=100, n_far=100)
    assert not bad.passed and bad.worst_margin > 0 and bad.worst_region in ("box", "far")


# ---------------------------------------------------------------------------------------------- LASA acceptance
@pytest.mark.parametrize("which", ["mm3_one", "mm3_all"])
def test_mm3_every_start_finishes_the_task_under_pushes(which: str, request) -> None:
    """1,000 random starts in a box twice the data span, modes none and full, random large and small pushes:
    every row finishes the whole task at the final attractor within the budget, no NaN, every dV/dt < 0."""
    demos, lib = request.getfixturevalue(which)
    x_all = demos.samples()[0]
    lo, hi = x_all.amin(0), x_all.amax(0)
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    B = 1000
    x0 = c + 2 * h * (2 * torch.rand(B, 2, generator=torch.Generator().manual_seed(11), dtype=F64) - 1)
    for mode in ("none", "full"):
        plan = random_pushes(B, generator=torch.Generator().manual_seed(12), n_pushes=2, window=(50, 500),
                             magnitude=(0.1 * lib.span, 0.3 * lib.span))  # fmt: skip
        out = SkillEngine(lib, mode).rollout(x0, dt=0.01, n_steps=4000, pushes=plan)
        assert bool(out.done.all()), f"{mode}: {int((~out.done).sum())} rows did not finish"
        assert bool(torch.isfinite(out.result.positions).all())
        assert bool((_lyapunov_rates(lib, out) < 0).all())
        assert sum(p["applied"] for p in out.pushes) > B  # pushes did happen
    assert lib.stability["passed"]


@pytest.mark.parametrize("which", ["mm3_one", "mm3_all"])
def test_replayed_training_states_rarely_take_the_large_scale_branch(which: str, request) -> None:
    _, lib = request.getfixturevalue(which)
    shares = SkillEngine(lib, "full").replay_large_share()
    assert max(shares) <= 0.02, shares


def test_engine_arguments_are_checked(l_library: SkillLibrary) -> None:
    with pytest.raises(InvalidArgumentError):
        SkillEngine(object())  # type: ignore[arg-type]
    with pytest.raises(InvalidArgumentError):
        Arrival(radius=0)
    with pytest.raises(InvalidArgumentError):
        Arrival(max_speed=0.0)
    eng = SkillEngine(l_library, Modulation(mode="small"))
    with pytest.raises(ShapeMismatchError):
        eng.rollout(torch.zeros(3, 3, dtype=F64), dt=0.01, n_steps=10)
    with pytest.raises(InvalidArgumentError):
        random_pushes(4, generator=torch.Generator(), window=(0, 10), magnitude=(1.0, 2.0))
    assert math.isfinite(eng.arrival_radius)


def test_stacked_evaluation_equals_each_primitive(l_library: SkillLibrary) -> None:
    from lfd_torch.skills.stack import PrimitiveStack

    lib = l_library
    stack = PrimitiveStack([s.primitive for s in lib.skills], dtype=F64, device=torch.device("cpu"))
    gen = torch.Generator().manual_seed(4)
    x = 2 * torch.randn(300, 2, generator=gen, dtype=F64)
    step = torch.randint(0, lib.n_steps, (300,), generator=gen)
    f, h2 = stack.evaluate(x, step, entropy=True)
    for m, s in enumerate(lib.skills):
        rows = step == m
        assert torch.allclose(f[rows], s.primitive(x[rows]), rtol=1e-10, atol=1e-12)
        assert torch.allclose(h2[rows], renyi_entropy(s.primitive, x[rows]), rtol=1e-10, atol=1e-10)


def test_sorted_stack_evaluation_equals_the_padded_one(l_library: SkillLibrary) -> None:
    """The step-grouped quadratic-feature evaluation (large batches) equals each primitive and the padded stack,
    from the data out to states where every exponent underflows (the clamped exponentials)."""
    from lfd_torch.skills.stack import PrimitiveStack

    lib = l_library
    stack = PrimitiveStack([s.primitive for s in lib.skills], dtype=F64, device=torch.device("cpu"))
    gen = torch.Generator().manual_seed(14)
    x = torch.cat([0.3 * torch.randn(400, 2, generator=gen, dtype=F64),
                   30 * torch.randn(100, 2, generator=gen, dtype=F64)])  # fmt: skip
    step = torch.randint(0, lib.n_steps, (500,), generator=gen)
    need = torch.rand(500, generator=gen) < 0.5
    key = 2 * step + need.long()
    perm = torch.argsort(key)
    bounds = [0] + torch.bincount(key, minlength=2 * lib.n_steps).cumsum(0).tolist()
    groups = [(m, bounds[2 * m], bounds[2 * m + 1], bounds[2 * m + 2]) for m in range(lib.n_steps)]
    e = (x[perm] - lib.attractors[step[perm]]).T.contiguous()
    f, h2 = stack.evaluate_sorted(e, groups)
    f0, h0 = stack.evaluate(x[perm], step[perm], entropy=True)
    assert torch.allclose(f.T, f0, rtol=1e-11, atol=1e-12)
    rows = need[perm]
    assert bool(rows.any()) and bool((~rows).any())
    assert torch.allclose(h2[rows], h0[rows], rtol=1e-12, atol=1e-9)
    assert bool((h2[~rows] == -math.inf).all())  # not evaluated where not asked for
    for m, s in enumerate(lib.skills):
        sel = step[perm] == m
        assert torch.allclose(f.T[sel], s.primitive(x[perm][sel]), rtol=1e-11, atol=1e-12)


def _reference_tick(lib: SkillLibrary, mod: Modulation, arrival: Arrival, x: torch.Tensor, route: int, index: int):
    """One state ticked by hand from the public pieces: ``Segmentation.log_density``, the arrival ball, the
    primitive's own f and ``renyi_entropy``, the checked ``modulated_velocity``, ``rate_floor`` and ``speed_cap``
    with the constants the Arrival docstring defines. Returns (route, index, step, done, inside, u, branch)."""
    ld = lib.segmentation.log_density(x.unsqueeze(0))[0].tolist()
    routes = lib.routes
    if route < 0:  # the most likely first subtask space, the first route on ties
        route = max(range(len(routes)), key=lambda r: (ld[routes[r][0]], -r))
    steps = routes[route]
    j = index
    while j < len(steps) and float(torch.linalg.vector_norm(x - lib.attractors[steps[j]])) < arrival.radius * lib.span:
        j += 1
    done = j >= len(steps)
    m = steps[min(j, len(steps) - 1)]
    own, other = ld[m], max([v for k, v in enumerate(ld) if k != m], default=-math.inf)
    inside = own >= other and not done
    if done:
        return route, j, m, True, False, torch.zeros_like(x), int(Branch.AT_GOAL)
    skill = lib.skills[m]
    prim, xb = skill.primitive, x.unsqueeze(0)
    h2 = renyi_entropy(prim, xb) if mod.uses_entropy else None
    res = modulated_velocity(xb, prim(xb), prim.attractor, log_p_own=own, log_p_other=-math.inf if inside else other,
                             h2=h2, h2_ref=skill.h2_ref, mode=mod.mode, lambda_limit=mod.lambda_limit,
                             radial_floor=mod.radial_floor)  # fmt: skip
    e = xb - prim.attractor
    u = rate_floor(res.velocity, e, prim.P, arrival.min_rate / max(skill.duration, 1e-9))
    r = torch.linalg.vector_norm(e, dim=-1)
    u = speed_cap(u, r, arrival.max_speed * skill.speed, arrival.slow_radius * lib.span)
    return route, j, m, False, inside, u[0], int(res.branch[0])


@pytest.mark.parametrize("mode", ["none", "large", "small", "full"])
def test_batched_tick_equals_a_per_row_reference(mode: str, mm3_all) -> None:
    """The optimised batched tick (SubtaskBank densities, step-grouped velocities) against a straightforward
    per-row tick on 2,000 random states of Multi_Models_3 (all seven demonstrations, 2 routes; a quarter of them
    new tasks): the same route, progress, step, subtask decision and branch for every row, and the same velocity to
    rounding, in the large-batch (grouped) path and in the small-batch (dense) one; in mode full the py_trees tick
    agrees too.
    The velocity tolerance is rounding: the stack's H2 (e^T Q_ij e) and ``renyi_entropy`` (whitened pairwise
    differences) differ by ~2e-10 relative, as they did before this path existed, and the small-scale gain
    exp(H2(x_r) - H2(x)) turns that into a relative error of ~|H2| x 2e-10 in the velocity (3e-9 measured on
    this library), hence rtol 1e-8."""
    from lfd_torch.skills.engine import GROUPED_MIN_ROWS

    lib = mm3_all[1]
    eng = SkillEngine(lib, mode)
    n = 2000
    x, route, index = _random_pairs(lib, n, torch.Generator().manual_seed(7))
    fresh = torch.arange(n) % 4 == 0
    route, index = torch.where(fresh, -1, route), torch.where(fresh, 0, index)
    v, dec, branch = eng.step_batch(x, route, index)
    k = GROUPED_MIN_ROWS // 2  # the dense path, block by block
    dense = [eng.velocity(x[i : i + k], dec.step[i : i + k], dec.done[i : i + k], dec.inside[i : i + k])
             for i in range(0, n, k)]  # fmt: skip
    v_dense, b_dense = torch.cat([d[0] for d in dense]), torch.cat([d[1] for d in dense])
    assert torch.equal(b_dense, branch)
    assert torch.allclose(v_dense, v, rtol=1e-11, atol=1e-12)
    for i in range(n):
        r, j, m, done, inside, u, b = _reference_tick(lib, eng.modulation, eng.arrival, x[i], int(route[i]),
                                                      int(index[i]))  # fmt: skip
        got = (int(dec.route[i]), int(dec.index[i]), int(dec.step[i]), bool(dec.done[i]), bool(dec.inside[i]))
        assert got == (r, j, m, done, inside), i
        assert int(branch[i]) == b, i
        assert torch.allclose(v[i], u, rtol=1e-8, atol=1e-12), i
        if mode == "full":
            t = eng.tick(x[i], step=None if fresh[i] else lib.routes[r][int(index[i])], route=None if fresh[i] else r)
            assert (t.route, t.index, t.done, int(t.branch)) == (r, j, done, b), i
            # rounding: log p(x|A_m) reaches ~-1e5 here and the large-scale gain exp(other - own) turns the last-bit
            # differences of a (J d, 3) x (3, 1) and a (J d, 3) x (3, B) product into up to ~1e-11 relative
            assert torch.allclose(t.velocity, v[i], rtol=1e-10, atol=1e-12), i
    counts = torch.bincount(branch.long(), minlength=4)
    assert int(counts[int(Branch.AT_GOAL)]) > 0 and bool((dec.index > index.clamp_min(0)).any())  # steps complete
    if mode in ("large", "full"):
        assert int(counts[int(Branch.LARGE_SCALE)]) > 100
    if mode in ("small", "full"):
        assert int(counts[int(Branch.SMALL_SCALE)]) > 100


def test_batched_tick_equals_the_per_row_reference_in_3d() -> None:
    """The same check on a 3-D two-leg task (general d in the feature-major layout and the quadratic features)."""
    corners = torch.tensor([[-1.0, 1.0, 0.5], [-1.0, 0.0, 0.2], [0.0, 0.0, 0.0]], dtype=F64)
    syn = multi_step_demos(torch.Generator().manual_seed(0), n_demos=2, waypoints=corners, samples_per_step=60,
                           timing_jitter=0.0, waypoint_jitter=0.01, noise=0.002)  # fmt: skip
    lib = SkillLibrary.learn(syn.demos, FixedSegmenter([0.5])(syn.demos), generator=torch.Generator().manual_seed(1))
    gen = torch.Generator().manual_seed(2)
    n = 600
    data = torch.cat([s.train_positions for s in lib.skills])
    near = data[torch.randint(0, data.shape[0], (n // 2,), generator=gen)]
    noise = 0.02 * torch.randn(n // 2, 3, generator=gen, dtype=F64)
    x = torch.cat([torch.randn(n // 2, 3, generator=gen, dtype=F64), near + noise])
    index = torch.randint(0, 2, (n,), generator=gen)
    for mode in ("none", "large", "small", "full"):
        eng = SkillEngine(lib, mode)
        v, dec, branch = eng.step_batch(x, torch.zeros_like(index), index)
        for i in range(n):
            r, j, m, done, inside, u, b = _reference_tick(lib, eng.modulation, eng.arrival, x[i], 0, int(index[i]))
            assert (j, m, done, inside, b) == (int(dec.index[i]), int(dec.step[i]), bool(dec.done[i]),
                                               bool(dec.inside[i]), int(branch[i])), (mode, i)  # fmt: skip
            assert torch.allclose(v[i], u, rtol=1e-9, atol=1e-12), (mode, i)
        if mode == "full":
            counts = torch.bincount(branch.long(), minlength=4)
            assert int(counts[int(Branch.LARGE_SCALE)]) > 50 and int(counts[int(Branch.SMALL_SCALE)]) > 50


def test_subtask_bank_equals_the_segmentation_density(mm3_all) -> None:
    """SubtaskBank (the engine's densities) against ``Segmentation.log_density`` near the data, in a box and far
    away; a Gaussian shared by two steps ties own and other exactly in both (such ties are common here)."""
    lib = mm3_all[1]
    eng = SkillEngine(lib, "full")
    gen = torch.Generator().manual_seed(8)
    x, route, index = _random_pairs(lib, 3000, gen)
    x = torch.cat([x, 1e4 * torch.randn(50, 2, generator=gen, dtype=F64)])
    ref = lib.segmentation.log_density(x)
    got = eng.log_density(x)
    assert got.shape == ref.shape
    assert torch.allclose(got, ref, rtol=1e-12, atol=1e-11)
    step = torch.randint(0, lib.n_steps, (x.shape[0],), generator=gen)
    own, other = eng.own_other(x, step)
    own_ref = ref.gather(1, step[:, None])[:, 0]
    other_ref = lib.segmentation.other_log_density(x).gather(1, step[:, None])[:, 0]
    ties = own_ref == other_ref
    assert int(ties.sum()) > 10
    assert torch.equal(own == other, ties)
    assert torch.equal(own >= other, own_ref >= other_ref)


@pytest.mark.skipif(not __import__("shutil").which("g++"), reason="torch.compile needs a C++ compiler")
def test_compiled_tick_equals_the_eager_tick(l_library: SkillLibrary) -> None:
    eager = SkillEngine(l_library, "full")
    compiled = SkillEngine(l_library, "full", compile_tick=True)
    x, route, index = _random_pairs(l_library, 40, torch.Generator().manual_seed(9))
    for i in range(x.shape[0]):
        step = l_library.routes[int(route[i])][int(index[i])]
        a, b = eager.tick(x[i], step=step), compiled.tick(x[i], step=step)
        assert (a.step, a.done, a.branch) == (b.step, b.done, b.branch)
        assert torch.allclose(a.velocity, b.velocity, rtol=1e-12, atol=1e-12)


def test_assign_steps_is_monotone_and_follows_the_segmentation(l_library: SkillLibrary) -> None:
    demos, seg = _l_task()
    eng = SkillEngine(l_library, "full")
    route, steps = eng.assign_steps(demos.positions, demos.mask)
    assert bool((steps[:, 1:] >= steps[:, :-1]).all())
    for i in range(demos.n_demos):
        agree = (steps[i, : demos.lengths[i]] == seg.labels[i]).double().mean()
        assert float(agree) >= 0.9
    # a trajectory that stays on the first leg is assigned to step 0 (the assignment follows the data)
    half = demos.positions[:, : int(demos.lengths.min()) // 2 - 5]
    _, steps_half = eng.assign_steps(half)
    assert float((steps_half == 0).double().mean()) >= 0.95


def test_assign_steps_is_the_best_left_to_right_path() -> None:
    """On short trajectories the assignment is the left-to-right path (start at the route's first step, stay or
    move one step on, no skips, end anywhere) of the largest sum of log p(x_t | A_m), found by enumerating every
    such path."""
    demos, seg = _l_task()
    eng = SkillEngine(SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1), check=False), "full")
    g = torch.Generator().manual_seed(4)
    T = 9
    idx = torch.sort(torch.randint(0, int(demos.lengths[0]), (3, T), generator=g), -1).values
    x = demos.positions[0][idx] + 0.05 * torch.randn(3, T, demos.dim, generator=g, dtype=F64)
    route, steps = eng.assign_steps(x)
    ld = eng.log_density(x.reshape(-1, demos.dim)).view(3, T, -1)
    for b in range(3):
        r = eng.routes[int(route[b])]
        best, best_path = -math.inf, None
        for moves in itertools.product((0, 1), repeat=T - 1):
            pos = [0, *itertools.accumulate(moves)]
            if pos[-1] >= len(r):
                continue
            score = sum(float(ld[b, t, r[p]]) for t, p in enumerate(pos))
            if score > best:
                best, best_path = score, [r[p] for p in pos]
        assert steps[b].tolist() == best_path, (b, steps[b].tolist(), best_path)


def test_reproduction_reference_keeps_the_nominal_motion_unmodulated(l_library: SkillLibrary) -> None:
    demos, seg = _l_task()
    lib = SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1), entropy_reference="reproduction",
                             check=False)  # fmt: skip
    for a, b in zip(lib.skills, l_library.skills):
        assert float(a.h2_ref) >= float(b.h2_ref) - 1e-6 * (1 + abs(float(b.h2_ref)))
    out = SkillEngine(lib, "small").rollout(demos.start_points, dt=0.01, n_steps=3000)
    valid = out.result.mask
    assert not bool((out.branches[valid] == int(Branch.SMALL_SCALE)).any())
    with pytest.raises(LookupError):
        SkillLibrary.learn(demos, seg, generator=torch.Generator(), entropy_reference="nope", check=False)


def test_an_interrupted_save_keeps_the_library_already_there(l_library: SkillLibrary, tmp_path, monkeypatch) -> None:
    """The files are staged and moved into place, manifest last: a save that fails while writing (here the second
    primitive) leaves the library that was in the folder loadable and unchanged, and other files there alone."""
    root = tmp_path / "lib"
    l_library.save(root)
    (root / "demos.pt").write_bytes(b"an experiment's own file")
    before = {p.name: p.read_bytes() for p in root.iterdir()}
    original, calls = StablePrimitive.save, []

    def failing(self, path):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return original(self, path)

    demos, _ = _l_task(seed=1)  # another library (other data), saved over the first one
    other = SkillLibrary.learn(demos, FixedSegmenter([0.4])(demos), generator=torch.Generator().manual_seed(2))
    monkeypatch.setattr(StablePrimitive, "save", failing)
    with pytest.raises(KeyboardInterrupt):
        other.save(root)
    monkeypatch.setattr(StablePrimitive, "save", original)
    assert {p.name: p.read_bytes() for p in root.iterdir()} == before  # no staging folder left either
    SkillLibrary.load(root)
    with pytest.raises(StoreError, match="directory"):
        l_library.save(root / "manifest.json")


def test_first_route_takes_the_first_of_tied_routes() -> None:
    """Routes that begin with the same step tie exactly at every x: the batched running maximum picks the first of
    them, as choose_route's argmax does (torch.argmax returns the first maximum)."""
    stub = types.SimpleNamespace(_first=torch.tensor([1, 0, 1, 2, 0]))  # routes 0/2 and 1/4 share their first step
    ld = torch.randn(3, 64, generator=torch.Generator().manual_seed(0), dtype=F64)  # (M, B)
    got = SkillEngine._first_route_fm(stub, ld)
    want = ld.T[:, stub._first].argmax(-1)
    assert torch.equal(got, want) and set(got.tolist()) <= {0, 1, 3}


def test_tree_leaves_break_ties_as_the_engine_does() -> None:
    """The py_trees leaves on exact ties: ChooseRoute takes the first of the routes whose first subtask spaces are
    equally likely (as SkillEngine.choose_route), InSubtask counts log p(x|A_m) = log p(x|A_m-) as inside
    (the engine's own >= other)."""
    from py_trees.common import Status

    from lfd_torch.skills.tree import ChooseRoute, InSubtask, _Context

    def context(ld: list[float], routes: list[list[int]]) -> _Context:
        engine = types.SimpleNamespace(routes=routes, tick_probe=lambda x: (ld, [False] * len(ld)))
        ctx = _Context(engine)  # type: ignore[arg-type]
        ctx.reset(torch.zeros(2, dtype=F64), -1, 0)
        return ctx

    for routes in ([[1, 2], [0, 2], [1, 0]], [[0, 2], [1, 2], [1, 0]]):  # route 0 ties with 1 (equal density), 2
        ctx = context([-1.0, -1.0, -5.0], routes)
        assert [ChooseRoute(ctx, [r]).update() for r in range(3)] == [Status.SUCCESS, Status.FAILURE, Status.FAILURE]
    ctx = context([-1.0, -1.0, -5.0], [[2], [1]])  # no tie: the likelier first space wins
    assert [ChooseRoute(ctx, [r]).update() for r in range(2)] == [Status.FAILURE, Status.SUCCESS]
    ctx = context([-2.0, -2.0, -7.0], [[0, 1, 2]])
    assert InSubtask(ctx, 0).update() == Status.SUCCESS and ctx.densities[0] == (-2.0, -2.0)
    assert InSubtask(ctx, 2).update() == Status.FAILURE and ctx.densities[2] == (-7.0, -2.0)


def _two_ways_task() -> tuple:
    """Three demonstrations from (-2, 0) to the goal (2, 0): a straight lead-in to (-1, 0), then over the top
    (demonstrations 0 and 2, through (0, 1)) or underneath (demonstration 1, through (0, -1)) to (1, 0), then a
    straight lead-out. Segmented by hand into steps 0 (lead-in), 1 (top), 2 (bottom), 3 (lead-out) with the
    segmentation's own assembly, so the one route is the merge (0, 1, 2, 3) of the orders (0, 1, 3) and (0, 2, 3)."""
    from lfd_torch.data import Demos
    from lfd_torch.segmentation.segmentation import _assemble

    n = 50
    u = torch.linspace(0.0, 1.0, n + 1, dtype=F64)[:-1]
    lead_in = torch.stack([-2.0 + u, torch.zeros_like(u)], -1)
    lead_out = torch.stack([1.0 + torch.linspace(0.0, 1.0, n, dtype=F64), torch.zeros(n, dtype=F64)], -1)
    phi = torch.pi * (1.0 - u)
    seqs, pieces, states = [], [], []
    for i, side in enumerate((1.0, -1.0, 1.0)):
        arc = torch.stack([phi.cos(), side * phi.sin()], -1)
        seqs.append(torch.cat([lead_in, arc, lead_out]) + 0.001 * i)
        step = 1 if side > 0 else 2
        pieces.append([(0, 0, n), (step, n, 2 * n), (3, 2 * n, 3 * n)])
        states.append(torch.cat([torch.full((n,), m, dtype=torch.long) for m in (0, step, 3)]))
    demos = Demos.from_sequences(seqs, dt=0.02, attractor=torch.tensor([2.0, 0.0], dtype=F64))
    seg = _assemble(demos, pieces, [[0, 1, 2, 3]], [0, 0, 0], states, [0, 1, 2, 3], 5, 1e-6, None, {})
    return demos, seg


def test_demonstrated_routes_are_the_orders_the_demonstrations_execute() -> None:
    """A route merges its demonstrations' step orders; demonstrated_routes lists each order once, the most
    demonstrated first, completed by the route's last step where a demonstration ends before it."""
    import dataclasses

    _, seg = _two_ways_task()
    assert seg.routes == ((0, 1, 2, 3),)
    assert seg.demonstrated_routes == ((0, 1, 3), (0, 2, 3))
    p = [torch.tensor(rows) for rows in ([[0, 0, 50], [2, 50, 150]], [[0, 0, 50], [1, 50, 100], [3, 100, 150]],
                                         [[0, 0, 50], [2, 50, 150]])]  # fmt: skip
    short = dataclasses.replace(seg, pieces=tuple(p))  # two end with step 2: (0, 2) completed to (0, 2, 3)
    assert short.demonstrated_routes == ((0, 2, 3), (0, 1, 3))


def test_the_engine_executes_a_demonstrated_order_not_the_merged_route() -> None:
    """From starts around the demonstrations' the engine visits the steps of one order a demonstration executed,
    (0, 1, 3) or (0, 2, 3) (the way on picked at the end of the lead-in), never both the top and the bottom way (the
    merged route (0, 1, 2, 3) would drive from the top's end back to the bottom's start); every rollout finishes at
    the goal, and without modulation each order is taken from some start."""
    demos, seg = _two_ways_task()
    lib = SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(0), check=False)
    assert lib.routes == ((0, 1, 3), (0, 2, 3))
    gen = torch.Generator().manual_seed(4)
    x0 = torch.tensor([-2.0, 0.0], dtype=F64) + 0.3 * (2 * torch.rand(12, 2, generator=gen, dtype=F64) - 1)
    for mode in ("none", "full"):
        out = SkillEngine(lib, mode).rollout(x0, dt=0.02, n_steps=2000)
        assert bool(out.done.all())
        taken = set()
        for b in range(x0.shape[0]):
            visited = torch.unique_consecutive(out.steps[b, : int(out.result.lengths[b])]).tolist()
            assert visited in ([0, 1, 3], [0, 2, 3]), visited
            assert visited == list(lib.routes[int(out.routes[b])])
            taken.add(tuple(visited))
        if mode == "none":  # with the modulation these starts all arrive where A_1 is the likelier
            assert len(taken) == 2, taken


def test_the_way_on_is_picked_where_the_routes_part() -> None:
    """Routes (0, 1, 3) and (0, 2, 3) share step 0. A robot on route 0 that completes step 0 goes on with the way
    whose next subtask space is the more likely at its state (A_1: route 0, A_2: route 1), in the vectorised engine
    and in the py_trees tick alike; before the arrival, and on a route without a branching, the route stays. The old
    engine kept the route picked at the start whatever the state at the branching."""
    demos, seg = _two_ways_task()
    eng = SkillEngine(SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(0), check=False), "none")
    g0 = eng.goals[0]
    gen = torch.Generator().manual_seed(5)
    angle = 2 * math.pi * torch.rand(64, generator=gen, dtype=F64)
    radius = 0.95 * eng.arrival_radius * torch.rand(64, generator=gen, dtype=F64).sqrt()
    x = g0 + radius.unsqueeze(-1) * torch.stack([angle.cos(), angle.sin()], -1)  # inside the arrival ball of g_0
    ld = eng.log_density(x)
    want = torch.where(ld[:, 1] >= ld[:, 2], 0, 1)
    assert 0 < int(want.sum()) < 64  # both ways are taken from this sample
    zeros = torch.zeros(64, dtype=torch.long)
    route, index, done = eng.advance(x, zeros, zeros)
    assert torch.equal(route, want) and bool((index == 1).all()) and not bool(done.any())
    for start in (0, 1):  # a robot already on route 1 is re-picked the same way
        route, _, _ = eng.advance(x, torch.full_like(zeros, start), zeros)
        assert torch.equal(route, want)
    for i in range(0, 64, 4):
        t = eng.tick(x[i], step=0, route=0)
        assert (t.route, t.index, t.step) == (int(want[i]), 1, eng.routes[int(want[i])][1])
    t = eng.tick(x[0])  # a new task: the routes share step 0, the step alone says where the robot is
    assert eng.tick(x[0], step=0).route == int(want[0]) and (t.route, t.index) == (int(want[0]), 1)
    with pytest.raises(InvalidArgumentError, match="different steps before"):
        eng.tick(x[0], step=3)  # the last step follows step 1 on one route and step 2 on the other
    far = x + torch.tensor([-0.5, 0.0], dtype=F64)  # outside the ball: step 0 goes on, the route stays
    route, index, _ = eng.advance(far, zeros + 1, zeros)
    assert bool((route == 1).all()) and bool((index == 0).all())
    near_g1 = eng.goals[1].expand(4, 2)  # completing step 1 of route 0: no branching after it
    route, index, _ = eng.advance(near_g1, zeros[:4], zeros[:4] + 1)
    assert bool((route == 0).all()) and bool((index == 2).all())


def test_the_way_on_keeps_the_own_route_on_ties_else_takes_the_first() -> None:
    """SkillEngine._way_on_fm against a per-row loop over the routes (0, 1, 3), (0, 2, 3), (0, 2, 4, 3) at position 1,
    on densities with exact ties between A_1 and A_2 in a third of the rows: the own route unless another way's next
    space is strictly likelier, then the first route of the likeliest way."""
    routes = ((0, 1, 3), (0, 2, 3), (0, 2, 4, 3))
    L = 4
    stub = types.SimpleNamespace(
        _continuation=torch.tensor([[[len(q) > j and q[:j] == r[:j] for q in routes] for j in range(L)]
                                    for r in routes]),
        _route_steps=torch.tensor([list(r) + [r[-1]] * (L - len(r)) for r in routes]))  # fmt: skip
    gen = torch.Generator().manual_seed(6)
    B = 90
    ld = torch.randn(5, B, generator=gen, dtype=F64)
    ld[2, ::3] = ld[1, ::3]  # ties of the two ways on
    route = torch.randint(0, 3, (B,), generator=gen)
    got = SkillEngine._way_on_fm(stub, ld, route, torch.ones(B, dtype=torch.long))
    for b in range(B):
        own = int(route[b])
        best = max(float(ld[routes[q][1], b]) for q in range(3))
        ties = [q for q in range(3) if float(ld[routes[q][1], b]) == best]
        want = own if own in ties else ties[0]
        assert int(got[b]) == want, (b, own)


def test_the_tree_branches_where_the_routes_part_and_ends_a_route_that_stops_there() -> None:
    """The tree of routes (0, 1), (0, 1, 2, 1) and (0, 3, 1) (a route that ends where another goes on): the shared
    step 0 once, a Selector after it with the ways on, and after step 1 a branch that ends route 0's task while
    route 1 goes on with step 2. Ticked on stub densities, the tree finishes route 0 at g_1, drives route 1 on to
    step 2 from the same state, and picks the way on after step 0 by the next subtask space (ties: the own route)."""
    from py_trees.common import Status

    from lfd_torch.skills.tree import SkillTree

    ld = [0.0, -1.0, -3.0, -2.0]
    arrived = [False] * 4
    def velocity(x, m, inside, densities):  # the step as the velocity: says which leaf drove the robot
        return torch.full((2,), float(m)), Branch.SMALL_SCALE

    stub = types.SimpleNamespace(routes=((0, 1), (0, 1, 2, 1), (0, 3, 1)), tick_probe=lambda x: (ld, arrived),
                                 tick_velocity=velocity)
    tree = SkillTree(stub)  # type: ignore[arg-type]
    names = [c.name for c in tree.root.children]
    assert names == ["routes 0,1,2"]
    shared = tree.root.children[0].children
    assert [c.name for c in shared] == ["ChooseRoute 0,1,2", "step 0", "after step 0"]
    ways = shared[2].children
    assert [c.name for c in ways] == ["routes 0,1", "route 2"]
    assert [c.name for c in ways[0].children] == ["ChooseRoute 0,1", "step 1", "after step 1"]
    assert [c.name for c in ways[0].children[2].children] == ["route 0", "route 1"]
    assert [c.name for c in ways[0].children[2].children[0].children] == ["ChooseRoute 0"]

    def tick(route: int, index: int) -> tuple[int, int, Tensor | None, bool]:
        tree.ctx.reset(torch.zeros(2, dtype=F64), route, index)
        tree._tick_once()
        return tree.ctx.route, tree.ctx.index, tree.ctx.velocity, tree.root.status is Status.SUCCESS

    arrived[:] = [False, True, False, False]  # at g_1
    r, j, _, done = tick(0, 1)
    assert (r, j, done) == (0, 2, True)  # route 0 is done
    r, j, v, done = tick(1, 1)
    assert (r, j, done) == (1, 2, False) and float(v[0]) == 2.0  # route 1 goes on with step 2
    arrived[:] = [True, False, False, False]  # at g_0: the way on is the likelier of A_1 (routes 0, 1) and A_3
    for own in (0, 1, 2):
        assert tick(own, 0)[:2] == ((own if own < 2 else 0), 1)
    ld[:] = [0.0, -2.0, -3.0, -1.0]
    assert [tick(own, 0)[0] for own in (0, 1, 2)] == [2, 2, 2]
    ld[:] = [0.0, -1.0, -3.0, -1.0]  # a tie: each robot keeps its own way
    assert [tick(own, 0)[0] for own in (0, 1, 2)] == [0, 1, 2]


def test_assign_steps_tells_routes_with_the_same_first_step_apart() -> None:
    """Two ways of the task begin with the same step: each demonstration is assigned its own way (route and steps
    as segmented, up to a few samples at each switch), which the first sample alone cannot tell; a single-route
    assignment is unchanged (tested above against an enumeration)."""
    demos, seg = _two_ways_task()
    eng = SkillEngine(SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(0), check=False), "none")
    route, steps = eng.assign_steps(demos.positions, demos.mask)
    assert route.tolist() == [0, 1, 0]
    for i in range(demos.n_demos):
        assert torch.unique_consecutive(steps[i]).tolist() == list(eng.routes[int(route[i])])
        assert float((steps[i] != seg.labels[i]).double().mean()) < 0.05
