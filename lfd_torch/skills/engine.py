"""Skill decision engine: which step, which modulation branch, what velocity (paper Sec. IV, Fig. 3).

State of a robot: its position x and its progress (route r, index j into the route's step list); the active step is
m = routes[r][j]. The routes are the library's (:attr:`~lfd_torch.skills.SkillLibrary.routes`): the step orders the
demonstrations executed, so a route never runs through two alternatives that different demonstrations took. A tick

  1. picks the route at the first tick: the route whose first subtask space is the most likely at x (the first
     such route on ties, i.e. the most demonstrated order among those that begin with that step);
  2. completes steps: while ||x - g_m|| < r_a (the arrival ball, :mod:`~lfd_torch.skills.arrival`), j advances;
     after the last step of the route the task is done (velocity 0). Where the routes that ran the same steps so
     far continue with different steps (a branching: two ways the demonstrations went on from there), the
     completion also re-picks the way on: the continuation whose next subtask space is the most likely at x,
     the robot's own route on ties (then the first route that continues with the winning step). So the choice
     among orders that share their first steps is made where they part, on the state the robot has there, not
     at the start (the paper's Fallback at every branching; the tree's junction Selectors);
  3. chooses the branch: x in A_m (log p(x|A_m) >= log p(x|A_m-)) -> the primitive with the small-scale
     modulation, else the large-scale recovery (what each branch does in mode ``none``/``large``/``small``/``full``
     is in :mod:`lfd_torch.modulation.policy`);
  4. returns u = cap(M(x) f_m(x) + delta) (rate floor and speed cap of :mod:`~lfd_torch.skills.arrival`).

The behaviour tree of :mod:`~lfd_torch.skills.tree` is the source of these decisions for a single state
(:meth:`SkillEngine.tick`); :meth:`SkillEngine.decide` is its vectorised equivalent for B states, which a test checks
decision for decision against the py_trees tick.

Single-state tick (:meth:`SkillEngine.tick`, a control loop's hot path, where the cost of each tensor call, not the
arithmetic, dominates). The leaves decide on one probe per tick (:meth:`SkillEngine.tick_probe`: every step's
log p(x|A_m) from :class:`SubtaskBank` and its arrival test, turned into Python floats once); the drive leaf then
evaluates only its own step's primitive and, off the large-scale branch, its H2 (:meth:`SkillEngine.tick_velocity`,
~10 small kernels on tables precomputed per step) and applies the modulation, rate floor and speed cap to those
few d-vectors in Python floats, with the formulas of the tensor functions. The decisions are those of the batched
densities' kernel; tests check velocities and branches against the dense batched path and the reference.

Batched hot path (:meth:`SkillEngine.step_batch`, the rollout's field). The log densities of all subtask spaces
come from :class:`SubtaskBank` (one whitening product for every Gaussian, a max per step), feature-major (M, B), in
row blocks of :data:`CHUNK`. Batches of at least :data:`GROUPED_MIN_ROWS` rows then sort the live rows by (step,
needs H2) and evaluate only what each row's decision uses: its own step's primitive (one small product per step
present, :meth:`~lfd_torch.skills.stack.PrimitiveStack.evaluate_sorted`) and H2 only on rows that can take the
small-scale branch; the modulation, rate floor and speed cap run once over all live rows in the (d, B) layout.
A test checks decisions, branches and velocities against a per-row reference built from the public pieces.

:meth:`SkillEngine.rollout` integrates B robots with :func:`lfd_torch.rollout.rollout` (its hook holds the per-row
progress, ``can_stop`` lets a row stop only when its task is done) and returns the active step and the branch of
every sample.

Notation: B robots, d state dimension, M steps, R routes, L longest route; T = n_steps + 1 samples.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, InvalidIndexError, NonFiniteError, ShapeMismatchError
from lfd_torch.gmm.gaussian import GaussianBank
from lfd_torch.metrics._checks import check_finite, resolve_mask
from lfd_torch.modulation import Branch, Modulation, modulated_velocity_single, modulated_velocity_unchecked
from lfd_torch.rollout import MAX_STORED_VALUES, Disturbance, RolloutResult, rollout
from lfd_torch.skills.arrival import Arrival, rate_floor, shape_single, speed_cap
from lfd_torch.skills.library import SkillLibrary
from lfd_torch.skills.stack import PrimitiveStack
from lfd_torch.utils import check_cost, check_int, check_tensor

__all__ = ["CHUNK", "GROUPED_MIN_ROWS", "Decision", "EngineRollout", "SkillEngine", "SubtaskBank", "TickResult"]

#: Rows per block in batched evaluations (the Gaussians x rows intermediates of a block stay in the CPU cache).
CHUNK = 1024

#: Batches of at least this many rows take the step-grouped velocity path (rows sorted by step, one matrix product
#: per step present); smaller ones (a control tick) evaluate every step for every row and keep their own. Measured
#: crossover on Multi_Models_3 (14 steps, all present): equal cost at 256 rows, grouped 2.5x faster at 1,000.
GROUPED_MIN_ROWS = 256


def _first_max(rows: Tensor) -> tuple[Tensor, Tensor]:
    """(R, B) -> the maximum over R and the first row that reaches it, (B,) each: a running strict maximum, since
    argmax over a leading axis is a slow strided kernel on CPUs."""
    best, chosen = rows[0], torch.zeros(rows.shape[1], dtype=torch.long, device=rows.device)
    for r in range(1, rows.shape[0]):
        better = rows[r] > best
        chosen = torch.where(better, r, chosen)
        best = torch.where(better, rows[r], best)
    return best, chosen


def _single_fields(x: Tensor, g: Tensor, P: Tensor, W: Tensor, b: Tensor, c: Tensor, A: Tensor, Qh: Tensor,
                   const: Tensor, S: Tensor, *, entropy: bool) -> Tensor:  # fmt: skip
    """[f_m(x), e, P_m e, -H2_m(x) (if ``entropy``)] of one state x (d,), e = x - g_m: the tensor part of
    :meth:`SkillEngine.tick_velocity`, from the step's tables (g_m, P_m and
    :meth:`~lfd_torch.skills.stack.PrimitiveStack.single_tables`); what ``compile_tick`` compiles."""
    d = x.shape[0]
    e = x - g
    log_w = c - (torch.addmv(b, W, x).view(d, -1) ** 2).sum(0)  # (K,) log pi_k + log N(x; mu_k, Sigma_k)
    f = torch.softmax(log_w, 0) @ (A @ e).view(-1, d)  # means A_k e (A_k x - A_k g_m would cancel near g_m)
    if not entropy:
        return torch.cat([f, e, P @ e])
    terms = torch.addmv(torch.addmv(const, Qh, torch.outer(e, e).view(-1)), S, log_w)
    return torch.cat([f, e, P @ e, torch.logsumexp(terms, 0).view(1)])


class SubtaskBank:
    """log p(x|A_m) of every step for many points (the decision's hot path).

    ``Segmentation.log_density`` defines log p(x|A_m) = max_j [log w_mj + log N(x; mu_j, Sigma_j)] over the
    Gaussians of the subtask spaces. Here the J Gaussians that belong to some step form one
    :class:`~lfd_torch.gmm.GaussianBank` (the kernel the segmentation uses, so the values are the segmentation's),
    evaluated once for all of them, and each step takes the max over its own members, gathered into an
    (M, J_max, n) block (padding repeats a member, which leaves the max unchanged). Every Gaussian is evaluated once,
    so a Gaussian shared by two steps gives exactly equal values to both (the ties of ``own >= other`` are kept).
    The quadratic-feature form (one (J, F) product) would be cheaper but loses eps |mu - c|^2 / sigma^2 (~1e-10
    nats for these narrow subtask Gaussians) where the whitened form loses eps |mu| / sigma.

    Args:
        segmentation: the :class:`~lfd_torch.segmentation.Segmentation` (space_mean, space_covariance,
            space_weights).
        dtype, device: of the evaluation.
    """

    def __init__(self, segmentation: Any, *, dtype: torch.dtype, device: torch.device | str):
        f = {"dtype": dtype, "device": device}
        mean = segmentation.space_mean.to(**f)
        cov = segmentation.space_covariance.to(**f)
        w = segmentation.space_weights.to(**f)  # (M, J)
        M = w.shape[0]
        used = torch.nonzero((w > 0).any(0)).reshape(-1)
        self.n_steps = M
        self._gauss = GaussianBank(mean[used], cov[used]) if used.numel() else None
        self._n_used = used.numel()
        position = torch.full((w.shape[1],), -1, dtype=torch.long, device=device)
        position[used] = torch.arange(used.numel(), device=device)
        members = [torch.nonzero(w[m] > 0).reshape(-1) for m in range(M)]
        width = max(1, max(r.numel() for r in members))
        index = torch.zeros((M, width), dtype=torch.long, device=device)
        logw = torch.full((M, width), -math.inf, **f)
        for m, r in enumerate(members):
            if r.numel():
                pad = torch.cat([r, r[:1].expand(width - r.numel())])
                index[m] = position[pad]
                logw[m] = w[m, pad].log()
        self._index = index.reshape(-1)
        self._width = width
        self._logw = logw.unsqueeze(-1)  # (M, J_max, 1)
        self._plain = bool((logw == 0).all())  # 0/1 memberships: no weight to add
        self._empty = used.numel() == 0

    def log_density_fm(self, xt: Tensor) -> Tensor:
        """(d, n) feature-major points -> (M, n) log p(x|A_m); rows in blocks of :data:`CHUNK`."""
        n = xt.shape[1]
        if self._empty:
            return torch.full((self.n_steps, n), -math.inf, dtype=xt.dtype, device=xt.device)
        if n > CHUNK:
            return torch.cat([self.log_density_fm(xt[:, i : i + CHUNK]) for i in range(0, n, CHUNK)], dim=1)
        comp = self._gauss.log_density_fm(xt)  # (J', n) log N(x; mu_j, Sigma_j)
        block = comp.index_select(0, self._index).view(self.n_steps, self._width, n)
        if not self._plain:
            block = block + self._logw
        return block.amax(1)


class Decision(NamedTuple):
    """Decisions of a tick for B states (all (B,) tensors).

    Attributes:
        route: long, chosen route.
        index: long, position of the active step in the route (= route length when done).
        step: long, active step m (the route's last step when done).
        done: bool, the whole task is complete.
        inside: bool, x in A_m (False where done).
    """

    route: Tensor
    index: Tensor
    step: Tensor
    done: Tensor
    inside: Tensor


class TickResult(NamedTuple):
    """One single-state tick through the behaviour tree.

    Attributes:
        velocity: (d,) commanded velocity (units/s).
        route: chosen route.
        index: position of the active step in the route (route length when done).
        step: active step m (None when done).
        branch: modulation branch taken.
        done: the task is complete.
        decisions: ``(behaviour name, status name)`` of every behaviour ticked, in tick order (the visitor's log).
    """

    velocity: Tensor
    route: int
    index: int
    step: int | None
    branch: Branch
    done: bool
    decisions: tuple[tuple[str, str], ...]


@dataclass(frozen=True, eq=False)
class EngineRollout:
    """Result of :meth:`SkillEngine.rollout`.

    Attributes:
        result: the :class:`~lfd_torch.rollout.RolloutResult` (positions, velocities, lengths, converged = task done).
        steps: (B, T) long active step of every sample (frozen samples repeat the last one).
        branches: (B, T) int8 :class:`~lfd_torch.modulation.Branch` of every sample (AT_GOAL once done).
        routes: (B,) long route of every row.
        done: (B,) bool, every step completed (same as ``result.converged``).
        pushes: log of the pushes applied (``PushPlan.log``), empty without pushes.
    """

    result: RolloutResult
    steps: Tensor
    branches: Tensor
    routes: Tensor
    done: Tensor
    pushes: tuple[dict[str, Any], ...] = ()


class SkillEngine:
    """Decision engine over a :class:`~lfd_torch.skills.SkillLibrary` (module docstring).

    Args:
        library: the skills, their segmentation (routes, subtask spaces) and thresholds.
        modulation: a :class:`~lfd_torch.modulation.Modulation` or its mode name (``none``, ``large``, ``small``,
            ``full``).
        arrival: step completion ball, rate floor and speed cap (:class:`~lfd_torch.skills.arrival.Arrival`).
        compile_tick: compile the tensor part of the single-state velocity (:meth:`tick_velocity`) with
            ``torch.compile`` (fixed shapes, one graph per entropy setting for every step): a few seconds on the
            first ticks, then one fused call instead of ~10 small kernels, for devices where kernel launches
            dominate; on a CPU the eager kernels cost less than a compiled call's entry (measured on
            ``experiments/bench_engine.py``). Needs a C++ compiler on a CPU; results equal the eager ones to
            rounding. The batched paths stay eager.

    Attributes:
        tree: the py_trees behaviour tree (:class:`~lfd_torch.skills.tree.SkillTree`).
        arrival_radius: r_a in data units.
    """

    def __init__(
        self,
        library: SkillLibrary,
        modulation: Modulation | str = "full",
        arrival: Arrival | None = None,
        *,
        compile_tick: bool = False,
    ):
        if not isinstance(library, SkillLibrary):
            raise InvalidArgumentError(f"library must be a SkillLibrary, got {type(library).__name__}")
        self.library = library
        self.modulation = modulation if isinstance(modulation, Modulation) else Modulation(mode=modulation)
        self.arrival = arrival if arrival is not None else Arrival()
        if not isinstance(self.arrival, Arrival):
            raise InvalidArgumentError(f"arrival must be an Arrival, got {type(self.arrival).__name__}")
        f = {"dtype": library.dtype, "device": library.device}
        self._f = f
        self.segmentation = library.segmentation
        routes = [tuple(r) for r in library.routes]
        if not routes or any(len(r) == 0 for r in routes):
            raise InvalidArgumentError("the library's segmentation has an empty route")
        self.routes = tuple(routes)
        L = max(len(r) for r in routes)
        self._route_steps = torch.tensor([list(r) + [r[-1]] * (L - len(r)) for r in routes], device=f["device"])
        self._route_len = torch.tensor([len(r) for r in routes], device=f["device"])
        self._first = self._route_steps[:, 0]
        # continuation[r, j, q]: route q ran the steps of route r before position j and has a step at j;
        # branching[r, j]: those continuations differ in their step at j (where re-choosing can change the way on)
        cont = [[[len(q) > j and q[:j] == r[:j] for q in routes] for j in range(L)] for r in routes]
        self._continuation = torch.tensor(cont, dtype=torch.bool, device=f["device"])  # (R, L, R)
        ways_on = [[{q[j] for q, c in zip(routes, row[j]) if c} for j in range(L)] for row in cont]
        self._branching = torch.tensor([[len(w) > 1 for w in row] for row in ways_on], device=f["device"])
        self._any_branching = bool(self._branching.any())
        self.goals = library.attractors.to(**f)  # (M, d)
        span = library.span
        self.arrival_radius = self.arrival.radius * span
        self._slow_radius = self.arrival.slow_radius * span
        self._v_hi = torch.tensor([self.arrival.max_speed * s.speed for s in library.skills], **f)
        self._rate = torch.tensor([self.arrival.min_rate / max(s.duration, 1e-9) for s in library.skills], **f)
        self._P = torch.stack([s.primitive.P.to(**f) for s in library.skills])
        self._h2_ref = torch.stack([s.h2_ref.to(**f) for s in library.skills])
        finals = self.goals[self._route_steps[torch.arange(len(routes)), self._route_len - 1]]
        if not torch.allclose(finals, finals[:1].expand_as(finals)):
            raise InvalidArgumentError("the routes end at different attractors; one task has one final attractor")
        self.final_attractor = finals[0]
        self._stack = PrimitiveStack([s.primitive for s in library.skills], **f)
        self._origin = torch.zeros(library.dim, **f)
        self._bank = SubtaskBank(self.segmentation, **f)
        d = library.dim
        self._goals_fm = self.goals.T.contiguous()  # (d, M)
        self._P_fm = self._P.reshape(-1, d * d).T.contiguous()  # (d*d, M): rows (a, b) of P_m
        # single-state tick (:meth:`tick_probe`, :meth:`tick_velocity`): per-step tables and constants, no gathers
        M = library.n_steps
        self._tick_tables = [(self.goals[m], self._P[m], *self._stack.single_tables(m)) for m in range(M)]
        self._tick_consts = list(zip(self._h2_ref.tolist(), self._rate.tolist(), self._v_hi.tolist()))
        self._tick_r2 = torch.tensor(self.arrival_radius**2, dtype=f["dtype"]).item()  # as a tensor compares it
        self._tiny = torch.finfo(f["dtype"]).tiny
        self._tick_fields = torch.compile(_single_fields, dynamic=False) if compile_tick else _single_fields
        from lfd_torch.skills.tree import SkillTree

        self.tree = SkillTree(self)

    # ------------------------------------------------------------------ building blocks
    @property
    def dim(self) -> int:
        return self.library.dim

    def _check_x(self, x: Tensor, name: str = "x") -> Tensor:
        if not isinstance(x, Tensor) or not x.is_floating_point():
            raise ShapeMismatchError(f"{name} must be a floating-point tensor, got {type(x).__name__}")
        if x.ndim != 2 or x.shape[-1] != self.dim:
            raise ShapeMismatchError(f"{name} must have shape (B, {self.dim}), got {tuple(x.shape)}")

        if x.shape[0] == 0:
            raise ShapeMismatchError(f"{name} must hold at least one state, got shape {tuple(x.shape)}")
        check_tensor(x, name)  # float32/64, finite, below the overflow magnitude
        return x.to(**self._f)

    def _check_step(self, step: Tensor, B: int, name: str = "step") -> Tensor:
        """``step`` (B,) integer tensor of steps in 0..M-1, as long on the engine's device (as :meth:`_check_x`)."""
        self._check_int_vector(step, B, name)
        M = self.library.n_steps
        bad = (step < 0) | (step >= M)
        if bool(bad.any()):
            raise InvalidIndexError(f"{name} entries must lie in 0..{M - 1} (the library's steps), got "
                                    f"{int(step[bad][0])} (row {int(torch.nonzero(bad)[0])})")  # fmt: skip
        return step.to(device=self._f["device"], dtype=torch.long)

    @staticmethod
    def _check_int_vector(t: Tensor, B: int | None, name: str) -> Tensor:
        """``t`` if it is a (B,) integer tensor (of any length where B is None: a 1-D one); ShapeMismatchError naming
        ``name`` otherwise (steps, routes, progress indices)."""
        want = "B" if B is None else B
        if not isinstance(t, Tensor) or t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
            raise ShapeMismatchError(f"{name} must be a ({want},) integer tensor, got "
                                     f"{getattr(t, 'dtype', type(t).__name__)}")  # fmt: skip
        if t.ndim != 1 or (B is not None and t.shape[0] != B):
            raise ShapeMismatchError(f"{name} must have shape ({want},), got {tuple(t.shape)}")
        return t

    @staticmethod
    def _check_flags(flags: Tensor, B: int, name: str) -> Tensor:
        """``flags`` (B,) bool tensor (done, inside)."""
        if not isinstance(flags, Tensor) or flags.dtype != torch.bool:
            raise ShapeMismatchError(f"{name} must be a ({B},) bool tensor, got "
                                     f"{getattr(flags, 'dtype', type(flags).__name__)}")  # fmt: skip
        if flags.shape != (B,):
            raise ShapeMismatchError(f"{name} must have shape ({B},), got {tuple(flags.shape)}")
        return flags

    def _check_ld(self, ld: Tensor | None, B: int) -> Tensor | None:
        """Precomputed (B, M) log densities (``ld`` of :meth:`own_other`, :meth:`choose_route`, :meth:`advance`):
        -inf allowed (a state outside every subtask space), NaN not."""

        if ld is None:
            return None
        return self._check_log_densities(ld, "ld", (B, self.library.n_steps), " (log_density(x))")

    def _check_log_densities(self, t: Tensor, name: str, shape: tuple[int, ...], what: str = "") -> Tensor:
        """Precomputed log densities ``t`` of ``shape`` (``ld``, :meth:`velocity`'s ``densities``) in the engine's
        dtype and device: -inf allowed (a state outside every subtask space), NaN not.

        Raises:
            ShapeMismatchError: not a float tensor of ``shape`` (the message adds ``what``). NonFiniteError: NaN.
        """
        check_tensor(t, name, ndim=len(shape), finite=False, shape_hint=str(shape))
        if t.shape != shape:
            raise ShapeMismatchError(f"{name} must have shape {shape}{what}, got {tuple(t.shape)}")
        if bool(torch.isnan(t).any()):
            raise NonFiniteError(f"{name} contains NaN")
        return t.to(**self._f)

    def log_density(self, x: Tensor) -> Tensor:
        """(..., M) log p(x|A_m) of states x (..., d) (``Segmentation.log_density``, evaluated by
        :class:`SubtaskBank`)."""

        check_tensor(x, "x", min_ndim=1, last_dim=self.dim, shape_hint=f"(..., {self.dim})")
        return self._log_density(x)

    def _log_density(self, x: Tensor) -> Tensor:
        """:meth:`log_density` of checked states."""
        lead = x.shape[:-1]
        flat = x.reshape(-1, self.dim).to(**self._f)
        return self._bank.log_density_fm(flat.T).T.reshape(*lead, self._bank.n_steps)

    @staticmethod
    def _own_other_fm(ld: Tensor, step: Tensor) -> tuple[Tensor, Tensor]:
        """(M, B) feature-major log densities -> log p(x|A_m), log p(x|A_m-) of the rows' steps, (B,) each."""
        idx = step.unsqueeze(0)
        own = ld.gather(0, idx).squeeze(0)
        if ld.shape[0] == 1:
            return own, torch.full_like(own, -math.inf)
        return own, ld.scatter(0, idx, -math.inf).amax(0)

    def own_other(self, x: Tensor, step: Tensor, ld: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """log p(x|A_m) and log p(x|A_m-) of the given steps: (B,) each, from one density evaluation (``ld``:
        precomputed (B, M) :meth:`log_density`)."""
        x = self._check_x(x)
        step = self._check_step(step, x.shape[0])
        ld = self._check_ld(ld, x.shape[0])
        if ld is None:
            return self._own_other(x, step)
        return self._own_other_fm(ld.T, step)

    def _own_other(self, x: Tensor, step: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`own_other` of checked states (B, d) and steps (B,) (the rollout's pushes, :meth:`velocity`)."""
        return self._own_other_fm(self._bank.log_density_fm(x.T), step)

    def choose_route(self, x: Tensor, ld: Tensor | None = None) -> Tensor:
        """(B,) route whose first subtask space is the most likely at x (the first such route on ties)."""
        x = self._check_x(x)
        ld = self._check_ld(ld, x.shape[0])
        if len(self.routes) == 1:
            return torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
        ld = self._log_density(x) if ld is None else ld
        return ld[:, self._first].argmax(-1)  # (B, R) -> (B,)

    def _first_route_fm(self, ld: Tensor) -> Tensor:
        """(M, B) log densities -> (B,) :meth:`choose_route` (the first route on ties, :func:`_first_max`)."""
        return _first_max(ld.index_select(0, self._first))[1]  # (R, B) -> (B,)

    def reached(self, x: Tensor, step: Tensor) -> Tensor:
        """(B,) bool: ||x - g_m|| < r_a."""
        x = self._check_x(x)
        e = x - self.goals[self._check_step(step, x.shape[0])]
        return (e * e).sum(-1) < self.arrival_radius**2

    def advance(
        self, x: Tensor, route: Tensor | None, index: Tensor | None, ld: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Route choice (rows with route < 0), step completion and the way on at branchings (module docstring, items
        1-2); returns route, index, done (B,). ``route`` and ``index`` as in :meth:`decide`."""
        x = self._check_x(x)
        B = x.shape[0]
        self._check_progress(route, index, B)
        ld = self._check_ld(ld, B)
        dev = x.device
        route = torch.full((B,), -1, dtype=torch.long, device=dev) if route is None else route.to(dev).long()
        index = torch.zeros(B, dtype=torch.long, device=dev) if index is None else index.to(dev).long()
        return self._advance_fm(x.T, route, index, None if ld is None else ld.T)

    def _advance_fm(
        self, xt: Tensor, route: Tensor, index: Tensor, ld: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`advance` on feature-major (d, B) states and (M, B) log densities (None: evaluated if needed)."""
        if bool((route < 0).any()):
            if len(self.routes) == 1:
                chosen = torch.zeros_like(route)
            else:
                ld = self._bank.log_density_fm(xt) if ld is None else ld
                chosen = self._first_route_fm(ld)
            route = torch.where(route < 0, chosen, route)
        length = self._route_len[route]
        r2 = self.arrival_radius**2
        L = self._route_steps.shape[1]
        for _ in range(L):
            active = index < length
            step = self._route_steps[route, torch.minimum(index, length - 1)]
            e = xt - self._goals_fm.index_select(1, step)
            hit = active & ((e * e).sum(0) < r2)
            if not bool(hit.any()):
                break
            index = index + hit.long()
            if self._any_branching:
                at = hit & (index < length) & self._branching[route, index.clamp_max(L - 1)]
                if bool(at.any()):
                    ld = self._bank.log_density_fm(xt) if ld is None else ld
                    route = torch.where(at, self._way_on_fm(ld, route, index.clamp_max(L - 1)), route)
                    length = self._route_len[route]
        return route, index, index >= length

    def _way_on_fm(self, ld: Tensor, route: Tensor, index: Tensor) -> Tensor:
        """(M, B) log densities, (B,) routes and positions -> (B,) the route to go on with from position ``index``
        (module docstring, item 2): among the continuations of each row's route there, the one whose step at
        ``index`` has the most likely subtask space; the row's own route on ties, else the first such route."""
        cont = self._continuation[route, index].T  # (R, B)
        dens = ld.gather(0, self._route_steps.index_select(1, index)).masked_fill(~cont, -math.inf)  # (R, B)
        best, chosen = _first_max(dens)
        own = dens.gather(0, route.unsqueeze(0)).squeeze(0)
        return torch.where(own >= best, route, chosen)

    def active_step(self, route: Tensor, index: Tensor) -> Tensor:
        """(B,) active step routes[route][index] (the last step once done) of rows on a route (route >= 0)."""
        B = self._check_int_vector(route, None, "route").shape[0]
        if index is None:
            raise ShapeMismatchError(f"index must be a ({B},) integer tensor, got None")
        self._check_progress(route, index, B)
        if bool((route < 0).any()):
            raise InvalidIndexError(f"route entries must lie in 0..{len(self.routes) - 1} (a chosen route), got "
                                    f"{route.tolist()}")  # fmt: skip
        dev = self._route_len.device
        return self._active_step(route.to(dev).long(), index.to(dev).long())

    def _active_step(self, route: Tensor, index: Tensor) -> Tensor:
        """:meth:`active_step` of checked progress."""
        length = self._route_len[route]
        return self._route_steps[route, torch.minimum(index, length - 1)]

    def decide(self, x: Tensor, route: Tensor | None = None, index: Tensor | None = None) -> Decision:
        """Vectorised tick decisions for B states (the py_trees tick's equivalent; module docstring).

        Args:
            x: (B, d) positions.
            route: (B,) long route, -1 (or None for all) where it is still to be chosen.
            index: (B,) long progress in the route (None: 0).
        """
        x = self._check_x(x)
        self._check_progress(route, index, x.shape[0])
        return self._decide(x, route, index)[0]

    def _check_progress(self, route: Tensor | None, index: Tensor | None, B: int) -> None:
        """route (B,) in -1..R-1 and index (B,) integer tensors (or None); index in 0..len(route) for a row on a
        route (its length: done, as :class:`Decision` returns it) and in 0..(longest route) for a row on none."""
        longest = max(len(r) for r in self.routes)
        for name, t in (("route", route), ("index", index)):
            if t is not None:
                self._check_int_vector(t, B, name)
        if route is not None and bool(((route < -1) | (route >= len(self.routes))).any()):
            raise InvalidIndexError(f"route entries must lie in -1..{len(self.routes) - 1}, got {route.tolist()}")
        if index is not None:
            lengths = torch.tensor([len(r) for r in self.routes] + [longest], device=index.device)
            hi = lengths[route.to(index.device).long()] if route is not None else lengths[-1].expand(B)  # -1: none
            if bool(((index < 0) | (index > hi)).any()):
                raise InvalidIndexError(f"index entries must lie in 0..len(route) (0..{longest} on no route), got "
                                        f"{index.tolist()} for routes {None if route is None else route.tolist()}")

    def _decide(
        self, x: Tensor, route: Tensor | None, index: Tensor | None
    ) -> tuple[Decision, tuple[Tensor, Tensor]]:
        """:meth:`decide` on checked states, with the (own, other) log densities it used."""
        B = x.shape[0]
        dev = x.device
        route = torch.full((B,), -1, dtype=torch.long, device=dev) if route is None else route.to(dev).long()
        index = torch.zeros(B, dtype=torch.long, device=dev) if index is None else index.to(dev).long()
        xt = x.T.contiguous()  # (d, B): reductions over d run over contiguous rows
        ld = self._bank.log_density_fm(xt)  # (M, B)
        route, index, done = self._advance_fm(xt, route, index, ld)
        step = self._active_step(route, index)
        own, other = self._own_other_fm(ld, step)
        return Decision(route, index, step, done, (own >= other) & ~done), (own, other)

    def velocity(
        self,
        x: Tensor,
        step: Tensor,
        done: Tensor,
        inside: Tensor | None = None,
        densities: tuple[Tensor, Tensor] | None = None,
        *,
        shaping: bool = True,
    ) -> tuple[Tensor, Tensor]:
        """Commanded velocity and branch of B states in their active steps.

        Fewer than :data:`GROUPED_MIN_ROWS` rows (a control tick): every step's primitive at every row
        (:meth:`~lfd_torch.skills.stack.PrimitiveStack.evaluate`); more: the step-grouped path (module docstring).
        Both compute the same formulas and agree to rounding.

        Args:
            x: (B, d) positions.
            step: (B,) long active steps.
            done: (B,) bool rows whose task is complete (velocity 0, branch AT_GOAL).
            inside: (B,) bool x in A_m, as decided by the tree; None evaluates it here.
            densities: precomputed (log p(x|A_m), log p(x|A_m-)), (B,) each.
            shaping: apply the arrival rate floor and speed cap (False: the modulated primitive M(x) f_m(x) alone,
                the field of the paper's E1/E2).

        Returns:
            (B, d) velocities (units/s) and (B,) int8 branches.
        """

        x = self._check_x(x)
        B = x.shape[0]
        step = self._check_step(step, B)
        done = self._check_flags(done, B, "done").to(x.device)
        inside = None if inside is None else self._check_flags(inside, B, "inside").to(x.device)
        if densities is not None:
            if not isinstance(densities, (tuple, list)) or len(densities) != 2:
                raise InvalidArgumentError("densities must be a pair (log p(x|A_m), log p(x|A_m-)) of (B,) tensors, "
                                           f"got {type(densities).__name__}")  # fmt: skip
            densities = tuple(self._check_log_densities(t, name, (B,))
                              for name, t in zip(("densities[0]", "densities[1]"), densities))  # fmt: skip
        if not isinstance(shaping, bool):
            raise InvalidArgumentError(f"shaping must be a bool, got {shaping!r}")
        return self._velocity(x, step, done, inside, densities, shaping)

    def _velocity(
        self,
        x: Tensor,
        step: Tensor,
        done: Tensor,
        inside: Tensor | None = None,
        densities: tuple[Tensor, Tensor] | None = None,
        shaping: bool = True,
    ) -> tuple[Tensor, Tensor]:
        """:meth:`velocity` of checked arguments (the rollout's field, :meth:`step_batch`, the stability check)."""
        B = x.shape[0]
        if B >= GROUPED_MIN_ROWS:
            return self._velocity_grouped(x, step, done, inside, densities, shaping)
        mod = self.modulation
        f, h2 = self._stack.evaluate(x, step, entropy=mod.uses_entropy)
        own = other = None
        if mod.uses_subtask_densities:
            own, other = self._own_other(x, step) if densities is None else densities
            if inside is None:
                inside = own >= other
            other = torch.where(inside, torch.full_like(other, -math.inf), other)  # the tree's decision rules
        e = x - self.goals[step]  # the modulation is translation invariant: evaluate it around g_m = 0
        res = modulated_velocity_unchecked(e, f, self._origin, own, other, h2, self._h2_ref[step], mod.mode,
                                           mod.lambda_limit, mod.radial_floor)  # fmt: skip
        u = res.velocity
        if shaping:
            r = torch.linalg.vector_norm(e, dim=-1)
            u = rate_floor(u, e, self._P[step], self._rate[step])
            u = speed_cap(u, r, self._v_hi[step], self._slow_radius)
        u = torch.where(done.unsqueeze(-1), torch.zeros_like(u), u)
        branch = torch.where(done, torch.full_like(res.branch, int(Branch.AT_GOAL)), res.branch)
        return u, branch

    def _velocity_grouped(
        self,
        x: Tensor,
        step: Tensor,
        done: Tensor,
        inside: Tensor | None,
        densities: tuple[Tensor, Tensor] | None,
        shaping: bool,
    ) -> tuple[Tensor, Tensor]:
        """:meth:`velocity` of a large batch: the same formulas, evaluated only where a row needs them.

        Rows are sorted by (step, needs H2) and laid out feature-major (d, n); each step present costs one small
        matrix product for its primitive and one for its entropy (:meth:`PrimitiveStack.evaluate_sorted`), and H2
        is evaluated only on the rows that can take the small-scale branch (in A_m in mode ``full``, every live row
        in mode ``small``). Finished rows are skipped (velocity 0, AT_GOAL). The modulation, rate floor and speed
        cap then run once over all live rows.
        """
        mod = self.modulation
        B, d = x.shape
        M = self.library.n_steps
        own = other = None
        if mod.uses_subtask_densities:
            if densities is None:
                own, other = self._own_other_fm(self._bank.log_density_fm(x.T.contiguous()), step)
            else:
                own, other = densities
            if inside is None:
                inside = own >= other
        live = ~done
        if mod.uses_entropy:
            need = live & inside if mod.uses_subtask_densities else live
        else:
            need = torch.zeros_like(live)
        key = torch.where(live, 2 * step + need.long(), torch.full_like(step, 2 * M))
        perm = torch.argsort(key)
        bounds = [0] + torch.bincount(key, minlength=2 * M + 1).cumsum(0).tolist()
        groups = [(m, bounds[2 * m], bounds[2 * m + 1], bounds[2 * m + 2])
                  for m in range(M) if bounds[2 * m + 2] > bounds[2 * m]]  # fmt: skip
        n = bounds[2 * M]  # live rows, sorted first
        rows = perm[:n]
        ms = step.index_select(0, rows)
        e = x.T.index_select(1, rows) - self._goals_fm.index_select(1, ms)  # (d, n) x - g_m
        f, h2 = self._stack.evaluate_sorted(e, groups)
        if own is not None:
            own = own.index_select(0, rows)
            other = torch.where(inside.index_select(0, rows), -math.inf, other.index_select(0, rows))
        h2_ref = self._h2_ref.index_select(0, ms) if mod.uses_entropy else None
        res = modulated_velocity_unchecked(e, f, self._origin.unsqueeze(-1), own, other, h2, h2_ref, mod.mode,
                                           mod.lambda_limit, mod.radial_floor, dim=0)  # fmt: skip
        u = res.velocity
        if shaping:
            Pe = (self._P_fm.index_select(1, ms).view(d, d, n) * e.unsqueeze(0)).sum(1)  # P_m e
            u = rate_floor(u, e, None, self._rate.index_select(0, ms), dim=0, Pe=Pe)
            u = speed_cap(u, (e * e).sum(0).sqrt(), self._v_hi.index_select(0, ms), self._slow_radius, dim=0)
        out = torch.zeros_like(x)
        out.index_copy_(0, rows, u.T)
        branch = torch.full((B,), int(Branch.AT_GOAL), dtype=torch.int8, device=x.device)
        branch.index_copy_(0, rows, res.branch)
        return out, branch

    # ------------------------------------------------------------------ single-state tick
    def tick_probe(self, x: Tensor) -> tuple[list[float], list[bool]]:
        """log p(x|A_m) of every step (:class:`SubtaskBank`, as :meth:`log_density`) and whether x lies in each
        step's arrival ball (:meth:`reached`), at one checked state x (d,) in the engine's dtype and device: the
        quantities the tree's leaves decide on, as Python lists from one evaluation (one device sync)."""
        M = self._bank.n_steps
        e = x - self.goals
        vals = torch.cat([self._bank.log_density_fm(x.view(-1, 1)).view(-1), (e * e).sum(-1)]).tolist()
        return vals[:M], [v < self._tick_r2 for v in vals[M:]]

    def tick_velocity(
        self, x: Tensor, step: int, inside: bool, densities: tuple[float, float] | None
    ) -> tuple[Tensor, Branch]:
        """:meth:`velocity` of one checked state x (d,) in step ``step`` (not done), for the tree's drive leaves.

        The tensor part (f_m(x), H2_m(x) only where the branch can use it, e = x - g_m, P_m e) is one short
        evaluation with the step's own tables (:meth:`~lfd_torch.skills.stack.PrimitiveStack.single_tables`,
        compiled with ``compile_tick``); the modulation, rate floor and speed cap of those few d-vectors then run
        in Python floats (:func:`~lfd_torch.modulation.modulated_velocity_single`,
        :func:`~lfd_torch.skills.arrival.shape_single`: the tensor formulas in the same order; a float32 engine's
        velocity is rounded to float32 once, at the end).

        Args:
            x: (d,) position.
            step: the active step m.
            inside: x in A_m, as decided by the tree.
            densities: (log p(x|A_m), log p(x|A_m-)) as floats; needed by modes ``large`` and ``full``.

        Returns:
            (d,) velocity and the branch.
        """
        mod = self.modulation
        own = other = None
        outside = False
        if mod.uses_subtask_densities:
            if densities is None:
                raise InvalidArgumentError(f"densities are required in modulation mode {mod.mode!r}")
            own, other = densities
            other = -math.inf if inside else other  # the tree's decision rules
            outside = own < other
        entropy = mod.uses_entropy and not outside  # H2 only matters off the large-scale branch
        vals = self._tick_fields(x, *self._tick_tables[step], entropy=entropy).tolist()
        d = x.shape[0]
        f, e, Pe = vals[:d], vals[d : 2 * d], vals[2 * d : 3 * d]
        h2_ref, rate, v_hi = self._tick_consts[step]
        u, branch = modulated_velocity_single(e, f, own, other, -vals[3 * d] if entropy else None, h2_ref, mod.mode,
                                              mod.lambda_limit, mod.radial_floor)  # fmt: skip
        u = shape_single(u, e, Pe, rate, v_hi, self._slow_radius, self._tiny)
        return torch.tensor(u, **self._f), branch

    # ------------------------------------------------------------------ public ticks
    def tick(self, x: Tensor, step: int | None = None, route: int | None = None) -> TickResult:
        """One control tick for a single state through the py_trees behaviour tree.

        Args:
            x: (d,) position.
            step: the active step m of the robot (None: a new task, the tree picks the route).
            route: its route (needed only when ``step`` belongs to several routes that run different steps
                before it).
        """
        return self.tree.tick(x, step=step, route=route)

    def step_batch(self, x: Tensor, route: Tensor | None = None, index: Tensor | None = None) -> tuple[Tensor, Decision, Tensor]:
        """Batched tick for B robots: velocities (B, d), the decisions (new progress) and branches (B,)."""
        x = self._check_x(x)
        self._check_progress(route, index, x.shape[0])
        dec, densities = self._decide(x, route, index)
        v, branch = self._velocity(x, dec.step, dec.done, dec.inside, densities)
        return v, dec, branch

    def rollout(
        self,
        x0: Tensor,
        *,
        dt: float,
        n_steps: int,
        method: str = "euler",
        pushes: Any | None = None,
        disturbances: Iterable[Disturbance] | Disturbance | None = None,
    ) -> EngineRollout:
        """Run B robots through the whole task from x0 with :func:`lfd_torch.rollout.rollout`.

        A row stops when its task is done (inside the arrival ball of the final attractor); the per-row progress
        lives in the rollout's hook, which also applies the state-dependent pushes of ``pushes``
        (:class:`~lfd_torch.skills.disturbances.PushPlan`).

        Args:
            x0: (B, d) start states.
            dt: time step (s).
            n_steps: step budget.
            method: ``euler`` or ``rk4``.
            pushes: optional push plan (labelled large / small pushes, applied by the hook).
            disturbances: optional open-loop :class:`~lfd_torch.rollout.Disturbance` specs.

        Returns:
            :class:`EngineRollout`.
        """
        from lfd_torch.skills.disturbances import PushPlan

        x0 = self._check_x(x0, "x0")
        check_int(n_steps, "n_steps", low=1)
        check_cost("n_steps", 2.0 * (n_steps + 1) * x0.shape[0] * x0.shape[1], MAX_STORED_VALUES, "stored values")
        if pushes is not None and not isinstance(pushes, PushPlan):
            raise InvalidArgumentError(f"pushes must be a PushPlan (random_pushes(...)) or None, got {type(pushes).__name__}")
        B = x0.shape[0]
        if pushes is not None and pushes.steps.shape[0] != B:
            raise ShapeMismatchError(f"pushes plans {pushes.steps.shape[0]} robots (random_pushes(n=...)), x0 holds "
                                     f"{B}")  # fmt: skip
        dev = x0.device
        T = int(n_steps) + 1
        log_start = pushes.begin_run() if pushes is not None else 0  # this run's pushes, directions from the start
        route = torch.full((B,), -1, dtype=torch.long, device=dev)
        index = torch.zeros(B, dtype=torch.long, device=dev)
        state = {"route": route, "index": index, "done": torch.zeros(B, dtype=torch.bool, device=dev),
                 "step": torch.zeros(B, dtype=torch.long, device=dev), "pending": None, "last": -1}  # fmt: skip
        steps_log = torch.zeros((T, B), dtype=torch.long, device=dev)
        branch_log = torch.full((T, B), int(Branch.AT_GOAL), dtype=torch.int8, device=dev)

        def hook(k: int, x: Tensor, active: Tensor) -> Tensor | None:
            y = None
            if pushes is not None:
                y = pushes.apply(k, x, self, state)
            xs = x if y is None else y
            r, j, done = self._advance_fm(xs.T, state["route"], state["index"])
            state.update(route=r, index=j, done=done, step=self._active_step(r, j), pending=k, last=k)
            steps_log[k] = state["step"]
            return y

        def field(x: Tensor) -> Tensor:
            done = state["done"]
            if bool(done.any()):  # finished rows stay in the working set (the hook sees them): skip their field
                rows = torch.nonzero(~done).reshape(-1)
                v = torch.zeros_like(x)
                br = torch.full((B,), int(Branch.AT_GOAL), dtype=torch.int8, device=dev)
                if rows.numel():
                    v_live, b_live = self._velocity(x.index_select(0, rows), state["step"][rows], done[rows])
                    v.index_copy_(0, rows, v_live)
                    br.index_copy_(0, rows, b_live)
            else:
                v, br = self._velocity(x, state["step"], done)
            if state["pending"] is not None:
                branch_log[state["pending"]] = br
                state["pending"] = None
            return v

        res = rollout(
            field, x0, dt, n_steps, method=method, attractor=self.final_attractor, position_tol=self.arrival_radius,
            velocity_tol=math.inf, hook=hook, can_stop=lambda k: state["done"],
            hook_until=-1 if pushes is None else int(pushes.last_step), disturbances=disturbances,
        )  # fmt: skip
        last = state["last"]
        if last + 1 < T:  # the run ended early: every row is frozen in its final state
            steps_log[last + 1 :] = steps_log[last]
            branch_log[last + 1 :] = int(Branch.AT_GOAL)
        log = tuple(pushes.log[log_start:]) if pushes is not None else ()
        return EngineRollout(res, steps_log.T.contiguous(), branch_log.T.contiguous(), state["route"], res.converged, log)

    def assign_steps(self, x: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Step of every sample of B trajectories, monotone in time, from the subtask spaces.

        The most likely left-to-right path over the steps of any route: per route the Viterbi path of a chain over
        its steps (start at its first step, stay or move to the next one, no skips, end anywhere) with emission
        log p(x_t | A_m), and the route whose path scores highest (the first on ties). Routes that begin with the
        same step (two ways a task was demonstrated) are told apart by the whole trajectory, not by its first
        sample. Used to evaluate a step's velocity field on a demonstration that the engine did not drive (E1, E2
        of a test demonstration).

        Args:
            x: (B, T, d) positions.
            mask: (B, T) valid samples (prefix-valid); None: all.

        Returns:
            (B,) routes and (B, T) long steps (padding repeats the last valid step).
        """

        check_tensor(x, "x", ndim=3, last_dim=self.dim, finite=False, shape_hint=f"(B, T, {self.dim})")
        if x.shape[0] == 0 or x.shape[1] == 0:
            raise ShapeMismatchError(f"x must hold at least one trajectory of at least one sample, got shape "
                                     f"{tuple(x.shape)}")  # fmt: skip
        x = x.to(**self._f)
        B, T, _ = x.shape
        mask = resolve_mask(mask, None, B, T, x.device, min_samples=1)  # bool (B, T), a valid sample in every row
        if bool((mask[:, 1:] & ~mask[:, :-1]).any()):
            raise InvalidArgumentError("mask must be prefix-valid (True on the first samples of each row, then False)")
        check_finite("x", x, mask)  # padding is not read
        lengths = mask.sum(-1)
        R, L = self._route_steps.shape
        ld = self._log_density(x.reshape(-1, self.dim)).view(B, T, -1)
        # every (trajectory, route) pair is one row of the recursion: B R rows, trajectory-major
        steps_of = self._route_steps.repeat(B, 1)  # (B R, L), padded with the last step
        length = self._route_len.repeat(B)  # (B R,)
        ld, mask, lengths = (t.repeat_interleave(R, 0) for t in (ld, mask, lengths))
        B = B * R
        pos = torch.arange(L, device=x.device)
        emit = ld.gather(-1, steps_of.unsqueeze(1).expand(B, T, L))  # (B R, T, L)
        emit = emit.masked_fill((pos >= length.unsqueeze(-1)).unsqueeze(1), -math.inf)  # beyond the route
        neg = torch.full((B, 1), -math.inf, **self._f)
        score = torch.where(pos == 0, emit[:, 0], torch.full_like(emit[:, 0], -math.inf))
        moved = torch.zeros((B, T, L), dtype=torch.bool, device=x.device)
        for t in range(1, T):  # a left-to-right Viterbi recursion is sequential in t; vectorised over B and L
            prev = torch.cat([neg, score[:, :-1]], dim=1)
            move = prev > score
            new = torch.maximum(score, prev) + emit[:, t]
            live = mask[:, t].unsqueeze(-1)
            score = torch.where(live, new, score)
            moved[:, t] = move & live
        score = score.masked_fill(pos >= length.unsqueeze(-1), -math.inf)
        j = score.argmax(-1)  # (B R,) the best path's last position in each route
        best = score.gather(-1, j.unsqueeze(-1)).squeeze(-1)
        route = best.view(-1, R).argmax(-1)  # (B,), the first route on ties
        rows = torch.arange(route.shape[0], device=x.device) * R + route
        j, moved, steps_of, mask, lengths = j[rows], moved[rows], steps_of[rows], mask[rows], lengths[rows]
        out = torch.empty((rows.shape[0], T), dtype=torch.long, device=x.device)
        for t in range(T - 1, -1, -1):
            out[:, t] = j
            j = j - (moved[:, t].gather(-1, j.unsqueeze(-1)).squeeze(-1) & (t < lengths)).long()
        steps = steps_of.gather(-1, out)
        last = steps.gather(-1, (lengths - 1).clamp_min(0).unsqueeze(-1))
        return route, torch.where(mask, steps, last)

    def replay_large_share(self) -> list[float]:
        """Share of each step's own training states on which the large-scale branch fires (mode ``full``).

        Each state is ticked as a robot in that step (issue item: subtask spaces that hold their own data).
        """
        shares = []
        for s in self.library.skills:
            x = s.train_positions.to(**self._f)
            step = torch.full((x.shape[0],), s.step, dtype=torch.long, device=x.device)
            own, other = self._own_other(x, step)
            shares.append(float((own < other).double().mean()))
        return shares

