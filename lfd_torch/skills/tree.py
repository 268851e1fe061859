"""The task's behaviour tree, built automatically from the segmentation with py_trees (paper Sec. IV, Fig. 3).

Structure: the routes (the engine's, the step orders the demonstrations executed,
:attr:`~lfd_torch.segmentation.Segmentation.demonstrated_routes`) merged where they share their first steps, a
Fallback (``Selector``) wherever they part. Two ways of writing a stroke are two branches, not one Sequence that
runs through both; a single route gives a single Sequence. For routes (0, 1, 3) and (0, 2, 3)::

    Selector "task"
      Sequence "routes 0,1"
        ChooseRoute 0,1                    SUCCESS iff the robot's route is one of these (picked at the first tick:
                                           the route whose first subtask space is the most likely at x, the first
                                           on ties)
        Selector "step 0"                  (one per step shared by these routes, in order)
          Reached 0                        SUCCESS iff step m is complete (completed earlier, or x in the arrival
                                           ball of g_m now: the progress then advances past m and, where the routes
                                           part next, re-picks the way on, :meth:`_Context.way_on`)
          Sequence "track 0"
            InSubtask 0                    SUCCESS iff log p(x|A_m) >= log p(x|A_m-)
            Track 0                        RUNNING: primitive m with the small-scale modulation
          Recover 0                        RUNNING: primitive m with the large-scale modulation
        Selector "after step 0"            where the routes part: one branch per way on, in route order
          Sequence "route 0"
            ChooseRoute 0
            Selector "step 1" ... Selector "step 3"
          Sequence "route 1"
            ChooseRoute 1
            Selector "step 2" ... Selector "step 3"

A route that ends where others go on has a branch of its ``ChooseRoute`` alone (SUCCESS: its task is done).

Memory semantics: every composite is built with ``memory=False``: each tick re-evaluates the tree from the root,
and the progress (the route and which of its steps are complete) is the robot's state, held in the tree's
context (the blackboard's role), not in the composites. A completed step therefore stays complete (``Reached``
returns SUCCESS for it whatever x is), which is what a ``memory=True`` Sequence would give, while a tick is a pure
function of (x, route, progress): the vectorised :meth:`~lfd_torch.skills.SkillEngine.decide` can take exactly
the same decisions, and a test checks that it does.

The condition leaves decide on the densities and arrival tests of every step at x, evaluated once per tick at
the first leaf that needs them (:meth:`~lfd_torch.skills.SkillEngine.tick_probe`, Python floats): a leaf's test is
then a comparison, not a tensor call and a device sync of its own.

Decisions are recorded by :class:`DecisionVisitor` (a py_trees visitor), never printed. :meth:`SkillTree.render`
writes the tree as ASCII (and, with graphviz installed, as an image).
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import py_trees
import torch
from py_trees.common import Status
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError
from lfd_torch.modulation import Branch

if TYPE_CHECKING:
    from lfd_torch.skills.engine import SkillEngine, TickResult

__all__ = ["DecisionVisitor", "SkillTree"]


class _Context:
    """What the behaviours of one tree share (the blackboard's role): the state being ticked and its results."""

    def __init__(self, engine: SkillEngine):
        self.engine = engine
        self.x: Tensor | None = None  # (d,), the engine's dtype and device
        self.route = -1
        self.index = 0
        self.velocity: Tensor | None = None
        self.branch = Branch.AT_GOAL
        self.densities: dict[int, tuple[float, float]] = {}  # step -> (log p(x|A_m), log p(x|A_m-)) this tick
        self._probe: tuple[list[float], list[bool]] | None = None

    def reset(self, x: Tensor, route: int, index: int) -> None:
        self.x, self.route, self.index = x, route, index
        self.velocity, self.branch = None, Branch.AT_GOAL
        self.densities = {}
        self._probe = None

    def way_on(self) -> None:
        """At a branching of the routes (the routes that ran the robot's steps so far continue with different steps
        at its position), the route to go on with: the one whose next subtask space is the most likely at x, the
        robot's own on ties, else the first (:meth:`SkillEngine._way_on_fm`)."""
        routes, r, j = self.engine.routes, self.route, self.index
        if j >= len(routes[r]):
            return
        ways = [q for q, steps in enumerate(routes) if len(steps) > j and steps[:j] == routes[r][:j]]
        if len({routes[q][j] for q in ways}) < 2:
            return
        ld = self.probe()[0]
        best = max(ld[routes[q][j]] for q in ways)
        if ld[routes[r][j]] < best:
            self.route = next(q for q in ways if ld[routes[q][j]] == best)

    def probe(self) -> tuple[list[float], list[bool]]:
        """log p(x|A_m) and arrival of every step at x (:meth:`SkillEngine.tick_probe`), evaluated once per tick at
        the first leaf that needs them."""
        if self._probe is None:
            self._probe = self.engine.tick_probe(self.x)
        return self._probe


class DecisionVisitor(py_trees.visitors.VisitorBase):
    """Records ``(behaviour name, status name)`` of every behaviour ticked, in order (cleared each tick)."""

    def __init__(self) -> None:
        super().__init__(full=False)
        self.decisions: list[tuple[str, str]] = []

    def initialise(self) -> None:
        self.decisions = []

    def run(self, behaviour: py_trees.behaviour.Behaviour) -> None:
        self.decisions.append((behaviour.name, behaviour.status.name))


class _Leaf(py_trees.behaviour.Behaviour):
    def __init__(self, name: str, ctx: _Context):
        super().__init__(name=name)
        self.ctx = ctx


class ChooseRoute(_Leaf):
    """SUCCESS iff the robot's route is one of ``routes`` (a robot without one gets it here, at its first tick)."""

    def __init__(self, ctx: _Context, routes: list[int]):
        super().__init__(f"ChooseRoute {','.join(map(str, routes))}", ctx)
        self.routes = frozenset(routes)

    def update(self) -> Status:
        c = self.ctx
        if c.route < 0:  # the most likely first subtask space, the first route on ties (SkillEngine.choose_route)
            first = [steps[0] for steps in c.engine.routes]
            if len(first) == 1:
                c.route = 0
            else:
                ld = c.probe()[0]
                c.route = max(range(len(first)), key=lambda r: (ld[first[r]], -r))
        return Status.SUCCESS if c.route in self.routes else Status.FAILURE


class Reached(_Leaf):
    def __init__(self, ctx: _Context, position: int, step: int):
        super().__init__(f"Reached {step}", ctx)
        self.position, self.step = position, step

    def update(self) -> Status:
        c = self.ctx
        if c.index > self.position:
            return Status.SUCCESS
        if c.probe()[1][self.step]:  # ||x - g_m|| < r_a
            c.index = self.position + 1
            c.way_on()
            return Status.SUCCESS
        return Status.FAILURE


class InSubtask(_Leaf):
    def __init__(self, ctx: _Context, step: int):
        super().__init__(f"InSubtask {step}", ctx)
        self.step = step

    def update(self) -> Status:
        ld = self.ctx.probe()[0]
        own = ld[self.step]
        other = max((v for k, v in enumerate(ld) if k != self.step), default=-math.inf)
        self.ctx.densities[self.step] = (own, other)
        return Status.SUCCESS if own >= other else Status.FAILURE


class _Drive(_Leaf):
    inside = True

    def __init__(self, name: str, ctx: _Context, step: int):
        super().__init__(f"{name} {step}", ctx)
        self.step = step

    def update(self) -> Status:
        c = self.ctx
        c.velocity, c.branch = c.engine.tick_velocity(c.x, self.step, self.inside, c.densities.get(self.step))
        return Status.RUNNING


class Track(_Drive):
    """Primitive m with the small-scale modulation (x in A_m)."""

    inside = True

    def __init__(self, ctx: _Context, step: int):
        super().__init__("Track", ctx, step)


class Recover(_Drive):
    """Primitive m with the large-scale modulation (x outside A_m)."""

    inside = False

    def __init__(self, ctx: _Context, step: int):
        super().__init__("Recover", ctx, step)


class SkillTree:
    """The behaviour tree of an engine's library (module docstring) and its single-state tick.

    Attributes:
        root: the py_trees root (a ``Selector`` over the ways the routes begin).
        tree: the ``py_trees.trees.BehaviourTree`` that ticks it, with a :class:`DecisionVisitor`.
    """

    def __init__(self, engine: SkillEngine):
        self.engine = engine
        self.ctx = _Context(engine)
        self.root = py_trees.composites.Selector("task", memory=False,
                                                 children=self._ways(list(range(len(engine.routes))), 0))  # fmt: skip
        self.tree = py_trees.trees.BehaviourTree(self.root)
        self.visitor = DecisionVisitor()
        self.tree.visitors.append(self.visitor)

    def _ways(self, routes: list[int], j: int) -> list[py_trees.behaviour.Behaviour]:
        """One branch per way on from position j of ``routes`` (which share their steps before j), in route order:
        a Sequence of ChooseRoute, the steps its routes share and, where they part, a Selector of their ways on."""
        steps = self.engine.routes
        groups: dict[int | None, list[int]] = {}  # step at j (None: the route ends) -> routes
        for r in routes:
            groups.setdefault(steps[r][j] if len(steps[r]) > j else None, []).append(r)
        branches = []
        for members in groups.values():
            children: list[py_trees.behaviour.Behaviour] = [ChooseRoute(self.ctx, members)]
            k = j
            while all(len(steps[r]) > k for r in members) and len({steps[r][k] for r in members}) == 1:
                children.append(self._step(k, steps[members[0]][k]))
                k += 1
            if any(len(steps[r]) > k for r in members):  # the routes part (or one ends) at k
                children.append(py_trees.composites.Selector(f"after step {steps[members[0]][k - 1]}", memory=False,
                                                             children=self._ways(members, k)))  # fmt: skip
            name = f"route{'s' if len(members) > 1 else ''} {','.join(map(str, members))}"
            branches.append(py_trees.composites.Sequence(name, memory=False, children=children))
        return branches

    def _step(self, position: int, m: int) -> py_trees.behaviour.Behaviour:
        """The Selector of step m at ``position`` of its routes: Reached, else track inside A_m, else recover."""
        track = py_trees.composites.Sequence(f"track {m}", memory=False,
                                             children=[InSubtask(self.ctx, m), Track(self.ctx, m)])  # fmt: skip
        children = [Reached(self.ctx, position, m), track, Recover(self.ctx, m)]
        return py_trees.composites.Selector(f"step {m}", memory=False, children=children)

    def tick(self, x: Tensor, *, step: int | None = None, route: int | None = None) -> TickResult:
        """Tick the tree once for the single state x in step ``step`` (None: start of the task)."""
        from lfd_torch.skills.engine import TickResult

        eng = self.engine
        if not isinstance(x, Tensor) or x.shape != (eng.dim,):
            raise ShapeMismatchError(f"x must have shape ({eng.dim},), got {getattr(x, 'shape', type(x).__name__)}")
        from lfd_torch.utils import check_int, check_tensor

        check_tensor(x, "x")  # float32/64, finite, below the overflow magnitude
        check_int(step, "step", low=0, allow_none=True)
        check_int(route, "route", low=0, allow_none=True)
        c = self.ctx
        c.reset(x.to(**eng._f), *self._progress(step, route))
        self._tick_once()
        done = self.root.status is Status.SUCCESS
        if done:
            c.velocity = torch.zeros(eng.dim, **eng._f)
            c.branch = Branch.AT_GOAL
        steps = eng.routes[c.route]
        active = None if done else steps[c.index]
        return TickResult(c.velocity, c.route, c.index, active, c.branch, done, tuple(self.visitor.decisions))

    def _tick_once(self) -> None:
        """``BehaviourTree.tick`` for trees whose visitors are all partial (``full=False``), as this one's are: the
        visitors see the behaviours ticked, in order. ``BehaviourTree.tick`` also walks the whole tree afterwards
        for full visitors, ~90 nodes here, a third of the tick's time even when there is none."""
        visitors = self.tree.visitors
        if any(v.full for v in visitors) or self.tree.pre_tick_handlers or self.tree.post_tick_handlers:
            self.tree.tick()
            return
        for v in visitors:
            v.initialise()
        for node in self.root.tick():
            for v in visitors:
                node.visit(v)
        for v in visitors:
            v.finalise()

    def _progress(self, step: int | None, route: int | None) -> tuple[int, int]:
        routes = self.engine.routes
        if step is None:
            if route is None:
                return -1, 0
            if not 0 <= int(route) < len(routes):
                raise InvalidArgumentError(f"route must be in 0..{len(routes) - 1}, got {route!r}")
            return int(route), 0
        if route is None:
            owners = [r for r, steps in enumerate(routes) if step in steps]
            if not owners:
                raise InvalidArgumentError(f"step {step!r} is in no route")
            # routes that run the same steps up to this one share the robot's progress: the first stands for them
            # (the way on is picked where they part)
            heads = {routes[r][: routes[r].index(step) + 1] for r in owners}
            if len(heads) != 1:
                raise InvalidArgumentError(f"step {step!r} belongs to routes {owners} with different steps before "
                                           "it; pass route= to say which")
            route = owners[0]
        if not 0 <= int(route) < len(routes) or step not in routes[route]:
            raise InvalidArgumentError(f"step {step!r} is not in route {route!r}")
        return int(route), routes[route].index(step)

    def ascii(self) -> str:
        """The tree as ASCII art (py_trees' renderer)."""
        return py_trees.display.ascii_tree(self.root)

    def render(self, path: str | Path) -> list[Path]:
        """Write the tree to ``path`` (suffix replaced): ``.txt`` ASCII always, ``.dot`` source, and ``.png`` when
        graphviz's ``dot`` is installed. Returns the files written.

        Raises:
            StoreError: ``path`` is not a str or os.PathLike (naming it), or writing failed.
        """
        from lfd_torch.errors import StoreError
        from lfd_torch.store import atomic_path
        from lfd_torch.utils import check_path

        base = check_path(path, "path", error=StoreError)
        written = []
        with atomic_path(base.with_suffix(".txt")) as tmp:
            tmp.write_text(self.ascii())
        written.append(base.with_suffix(".txt"))
        graph = py_trees.display.dot_tree(self.root)
        with atomic_path(base.with_suffix(".dot")) as tmp:
            tmp.write_text(graph.to_string())
        written.append(base.with_suffix(".dot"))
        if shutil.which("dot"):
            with atomic_path(base.with_suffix(".png")) as tmp:
                graph.write_png(str(tmp))
            written.append(base.with_suffix(".png"))
        return written

    def __repr__(self) -> str:
        return f"SkillTree(routes={len(self.engine.routes)}, steps={self.engine.library.n_steps})"

