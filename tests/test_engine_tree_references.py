"""Independent references for the skill decision engine (lfd_torch.skills.engine) and its behaviour tree, each
written against a mutant that the other tests let through: Python-float arrival tests, naive per-row loops over
the routes with ``Segmentation.log_density`` as the subtask densities, and the tree's tick as a second opinion.

Libraries: the two-leg L task of ``test_skills`` (steps 0 and 1), learned without the stability check (under a
second), and the same library executed along hand-written step orders (routes) through a subclass whose
``routes`` property returns them; the engine and the tree are built from that property alone."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from lfd_torch.modulation import Branch
from lfd_torch.skills import Arrival, SkillEngine, SkillLibrary
from lfd_torch.skills.engine import GROUPED_MIN_ROWS
from test_skills import _l_task
from test_skills_references import _ball_on

F64 = torch.float64


@pytest.fixture(scope="module")
def l_lib() -> SkillLibrary:
    """The two-leg L task: step 0 from (-1, 1) down to g_0 ~ (-1, 0), step 1 right to g_1 ~ (0, 0); one route."""
    demos, seg = _l_task()
    return SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1), check=False)


def _with_routes(lib: SkillLibrary, routes: tuple[tuple[int, ...], ...]) -> SkillLibrary:
    """The same skills and subtask spaces, executed along ``routes`` (the library's ``routes`` property)."""
    cls = type("RoutedLibrary", (SkillLibrary,), {"routes": property(lambda self: routes)})
    return cls(**{f.name: getattr(lib, f.name) for f in dataclasses.fields(lib)})


def _naive_progress(lib: SkillLibrary, r_a: float, x: torch.Tensor, route: tuple[int, ...], j: int) -> tuple[int, bool]:
    """Paper Sec. IV / engine docstring item 2 on one route without branchings: while ||x - g_m|| < r_a, j += 1."""
    while j < len(route) and float(torch.linalg.vector_norm(x - lib.attractors[route[j]])) < r_a:
        j += 1
    return j, j >= len(route)


# ---------------------------------------------------------------------------------------------- switching
def test_reached_is_the_open_arrival_ball(l_lib: SkillLibrary) -> None:
    """Property: ``SkillEngine.reached`` (step m complete) is ||x - g_m||^2 < r_a^2, strict, as the decision and the
    probe take it. Reference: the comparison in Python floats on states a few ulp inside, exactly on and outside
    the sphere (r_a made exactly representable as x_0 - g_0), for both steps."""
    for m in (0, 1):
        g = l_lib.attractors[m]
        rad, x0 = _ball_on(float(g[0]), 0.0123, l_lib.span)
        eng = SkillEngine(l_lib, "none", Arrival(radius=rad))
        r2 = eng.arrival_radius * eng.arrival_radius
        xk = x0
        for _ in range(3):
            xk = math.nextafter(xk, -math.inf)
        xs, want = [], []
        for _ in range(7):  # 3 ulp inside .. 3 ulp outside; the fourth lies on the sphere
            x = g.clone()
            x[0] = xk
            e = float(x[0] - g[0])
            xs.append(x)
            want.append(e * e < r2)
            xk = math.nextafter(xk, math.inf)
        assert want == [True] * 3 + [False] * 4, m
        got = eng.reached(torch.stack(xs), torch.full((7,), m, dtype=torch.long))
        assert got.tolist() == want, m
        assert [eng.tick_probe(x)[1][m] for x in xs] == want, m


def test_a_finished_route_that_others_extend_stays_finished(l_lib: SkillLibrary) -> None:
    """Property (engine docstring item 2, tree docstring 'a route that ends where others go on ... its task is
    done'): routes (0, 1), (0, 1, 0, 1), (0, 1, 1) part after step 1, where route 0 ends. A robot on route 0 that
    reaches g_1 is done and keeps route 0 (the way on is re-picked only where a step remains), while robots on
    routes 1 and 2 pick their way on there. Reference: the naive while loop for route 0, the tree's tick, and
    the way on by hand (the likelier of A_0 and A_1 at x among the continuations, own route on ties)."""
    routes = ((0, 1), (0, 1, 0, 1), (0, 1, 1))
    lib = _with_routes(l_lib, routes)
    eng = SkillEngine(lib, "full")
    assert eng.routes == routes
    gen = torch.Generator().manual_seed(11)
    B = 24
    ang = 2 * math.pi * torch.rand(B, generator=gen, dtype=F64)
    rad = 0.9 * eng.arrival_radius * torch.rand(B, generator=gen, dtype=F64)
    x = lib.attractors[1] + rad.unsqueeze(-1) * torch.stack([ang.cos(), ang.sin()], -1)  # in the ball of g_1
    ld = lib.segmentation.log_density(x)
    for r0 in (0, 1, 2):
        route = torch.full((B,), r0, dtype=torch.long)
        dec = eng.decide(x, route, torch.ones(B, dtype=torch.long))
        for i in range(B):
            if r0 == 0:
                want_r = 0
                want_j, want_done = _naive_progress(lib, eng.arrival_radius, x[i], routes[0], 1)
            else:  # continuations at position 2: route 1 (step 0) and route 2 (step 1)
                cand = {1: float(ld[i, 0]), 2: float(ld[i, 1])}
                best = max(cand.values())
                want_r = r0 if cand[r0] >= best else min(q for q in cand if cand[q] == best)
                want_j, want_done = _naive_progress(lib, eng.arrival_radius, x[i], routes[want_r], 1)
            got = (int(dec.route[i]), int(dec.index[i]), bool(dec.done[i]))
            assert got == (want_r, want_j, want_done), (r0, i)
            t = eng.tick(x[i], step=1, route=r0)
            assert (t.route, t.index, t.done) == got, (r0, i)
    assert bool(eng.decide(x, torch.zeros(B, dtype=torch.long), torch.ones(B, dtype=torch.long)).done.all())


# ---------------------------------------------------------------------------------------------- route choice
def test_choose_route_is_the_most_likely_first_subtask_space(l_lib: SkillLibrary) -> None:
    """Property (choose_route docstring, engine docstring item 1): the route whose first subtask space is the most
    likely at x, the first such route on ties. Reference: a naive loop over the routes (1,) and (0, 1) with
    ``Segmentation.log_density`` on states along both legs and around them; on given densities with exact ties
    (routes (1,), (0, 1), (0, 1): the first of the tied) by the same loop; the first tick of the tree agrees."""
    routes = ((1,), (0, 1))
    eng = SkillEngine(_with_routes(l_lib, routes), "none")
    gen = torch.Generator().manual_seed(12)
    data = torch.cat([s.train_positions for s in l_lib.skills])
    x = data[torch.randint(0, data.shape[0], (60,), generator=gen)] + 0.2 * torch.randn(60, 2, generator=gen, dtype=F64)
    ld = l_lib.segmentation.log_density(x)

    def naive(row: list[float], rs) -> int:
        best = 0
        for r in range(1, len(rs)):
            if row[rs[r][0]] > row[rs[best][0]]:
                best = r
        return best

    want = [naive(ld[i].tolist(), routes) for i in range(x.shape[0])]
    assert 0 < sum(want) < len(want)  # both routes are picked from this sample
    assert eng.choose_route(x).tolist() == want
    assert [eng.tick(x[i]).route for i in range(0, 60, 3)] == want[::3]
    tied_routes = ((1,), (0, 1), (0, 1))
    tied = SkillEngine(_with_routes(l_lib, tied_routes), "none")
    lds = torch.tensor([[-1.0, -1.0], [-1.0, -2.0], [-3.0, -2.0], [0.0, 0.0]], dtype=F64)
    got = tied.choose_route(x[:4], lds)
    assert got.tolist() == [naive(row, tied_routes) for row in lds.tolist()] == [0, 1, 0, 0]


# ---------------------------------------------------------------------------------------------- modulation branch
def test_large_batches_honour_an_explicit_inside_decision(l_lib: SkillLibrary) -> None:
    """Property (velocity docstring: ``inside`` is x in A_m as decided by the tree; eq. 9's branch): in the
    step-grouped path of >= GROUPED_MIN_ROWS rows, rows declared inside never take the large-scale branch even where
    log p(x|A_m) < log p(x|A_m-) (states of leg 1 ticked as robots in step 0), rows declared outside do there, and
    every row equals the single-state tick_velocity with the same decision. Reference: a per-row loop."""
    x = l_lib.skills[1].train_positions
    n = GROUPED_MIN_ROWS + 16
    noise = 1e-3 * torch.randn(n, 2, generator=torch.Generator().manual_seed(13), dtype=F64)
    x = x[torch.arange(n) % x.shape[0]] + noise
    step = torch.zeros(n, dtype=torch.long)
    for mode in ("large", "full"):
        eng = SkillEngine(l_lib, mode)
        own, other = eng.own_other(x, step)
        assert int((own < other).sum()) > n // 2
        inside = torch.arange(n) % 2 == 0
        v, branch = eng.velocity(x, step, torch.zeros(n, dtype=torch.bool), inside, (own, other))
        for i in range(n):
            want_large = (not bool(inside[i])) and float(own[i]) < float(other[i])
            assert (int(branch[i]) == int(Branch.LARGE_SCALE)) == want_large, (mode, i)
            u, b = eng.tick_velocity(x[i], 0, bool(inside[i]), (float(own[i]), float(other[i])))
            assert int(b) == int(branch[i]), (mode, i)
            torch.testing.assert_close(v[i], u, rtol=1e-9, atol=1e-12)


def test_exact_density_ties_are_inside_in_every_path(l_lib: SkillLibrary) -> None:
    """Property (eq. 9: the small-scale branch where p(x|A_m) >= p(x|A_m-), a tie included): with both steps given
    the same subtask space (the union of their Gaussians, so log p(x|A_0) == log p(x|A_1) exactly), no state is
    a large-scale disturbance: ``decide`` calls every state inside, ``replay_large_share`` is 0, and the step-grouped
    velocity of >= GROUPED_MIN_ROWS rows (inside left to the engine, as a rollout calls it) takes the small-scale
    branch exactly where H2(x) > H2(x_r). Reference: ``renyi_entropy`` per row against the step's threshold and the
    single-state tick_velocity with the tree's decision (inside)."""
    from lfd_torch.modulation import renyi_entropy

    seg = l_lib.segmentation
    union = seg.space_weights.amax(0, keepdim=True).expand_as(seg.space_weights).clone()
    lib = dataclasses.replace(l_lib, segmentation=dataclasses.replace(seg, space_weights=union))
    eng = SkillEngine(lib, "full")
    gen = torch.Generator().manual_seed(14)
    n = GROUPED_MIN_ROWS + 44
    step = torch.randint(0, 2, (n,), generator=gen)
    pick = torch.randint(0, 120, (n,), generator=gen)  # both steps have >= 120 training states
    x = torch.stack([lib.skills[int(m)].train_positions[int(k)] for m, k in zip(step, pick)])
    scale = torch.where(torch.arange(n) % 2 == 0, 0.002, 0.15).to(F64).unsqueeze(-1)  # on the step's data / away
    x = x + scale * torch.randn(n, 2, generator=gen, dtype=F64)
    own, other = eng.own_other(x, step)
    assert torch.equal(own, other)
    dec = eng.decide(x, torch.zeros(n, dtype=torch.long), step)
    assert bool((dec.inside | dec.done).all())
    assert eng.replay_large_share() == [0.0, 0.0]
    v, branch = eng.velocity(x, step, torch.zeros(n, dtype=torch.bool))
    n_small = 0
    for i in range(n):
        m = int(step[i])
        skill = lib.skills[m]
        h2 = float(renyi_entropy(skill.primitive, x[i : i + 1])[0])
        ref = float(skill.h2_ref)
        if abs(h2 - ref) > 1e-8:
            want = Branch.SMALL_SCALE if h2 > ref else Branch.UNMODULATED
            assert int(branch[i]) == int(want), i
            n_small += want == Branch.SMALL_SCALE
        u, b = eng.tick_velocity(x[i], m, True, (float(own[i]), float(other[i])))
        assert int(b) == int(branch[i]), i
        torch.testing.assert_close(v[i], u, rtol=1e-8, atol=1e-12)
    assert 50 < n_small < n - 50  # both branches are exercised
