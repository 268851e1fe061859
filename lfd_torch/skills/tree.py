"""The task's behaviour tree, built automatically from the segmentation with py_trees (paper Sec. IV, Fig. 3).

Structure (one ``Sequence`` per route under a root ``Selector``, the paper's Fallback; a single route gives a single
Sequence). The routes are the engine's, the step orders the demonstrations executed
(:attr:`~lfd_torch.segmentation.Segmentation.demonstrated_routes`): two ways of writing a stroke are two Sequences,
not one that runs through both::

    Selector "task"
      Sequence "route r"
        ChooseRoute r                      SUCCESS iff r is the robot's route (picked once, at the first tick: the
                                           route whose first subtask space is the most likely at x)
        Selector "step m" (for each step of the route, in order)
          Reached m                        SUCCESS iff step m is complete (completed earlier, or x in the arrival
                                           ball of g_m now: the progress then advances past m)
          Sequence "track m"
            InSubtask m                    SUCCESS iff log p(x|A_m) >= log p(x|A_m-)
            Track m                        RUNNING: primitive m with the small-scale modulation
          Recover m                        RUNNING: primitive m with the large-scale modulation

Memory semantics: every composite is built with ``memory=False``: each tick re-evaluates the tree from the root,
and the progress through the Sequence (which steps are complete) is the robot's state, held in the tree's
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
    def __init__(self, ctx: _Context, route: int):
        super().__init__(f"ChooseRoute {route}", ctx)
        self.route = route

    def update(self) -> Status:
        c = self.ctx
        if c.route < 0:  # the most likely first subtask space, the first route on ties (SkillEngine.choose_route)
            first = [steps[0] for steps in c.engine.routes]
            if len(first) == 1:
                c.route = 0
            else:
                ld = c.probe()[0]
                c.route = max(range(len(first)), key=lambda r: (ld[first[r]], -r))
        return Status.SUCCESS if c.route == self.route else Status.FAILURE


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
        root: the py_trees root (a ``Selector`` over the routes).
        tree: the ``py_trees.trees.BehaviourTree`` that ticks it, with a :class:`DecisionVisitor`.
    """

    def __init__(self, engine: SkillEngine):
        self.engine = engine
        self.ctx = _Context(engine)
        routes = []
        for r, steps in enumerate(engine.routes):
            children: list[py_trees.behaviour.Behaviour] = [ChooseRoute(self.ctx, r)]
            for j, m in enumerate(steps):
                track = py_trees.composites.Sequence(f"track {m}", memory=False,
                                                     children=[InSubtask(self.ctx, m), Track(self.ctx, m)])  # fmt: skip
                children.append(
                    py_trees.composites.Selector(f"step {m}", memory=False,
                                                 children=[Reached(self.ctx, j, m), track, Recover(self.ctx, m)])  # fmt: skip
                )
            routes.append(py_trees.composites.Sequence(f"route {r}", memory=False, children=children))
        self.root = py_trees.composites.Selector("task", memory=False, children=routes)
        self.tree = py_trees.trees.BehaviourTree(self.root)
        self.visitor = DecisionVisitor()
        self.tree.visitors.append(self.visitor)

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
            if len(owners) != 1:
                raise InvalidArgumentError(
                    f"step {step!r} belongs to routes {owners}; pass route= to say which" if owners
                    else f"step {step!r} is in no route"
                )
            route = owners[0]
        if not 0 <= int(route) < len(routes) or step not in routes[route]:
            raise InvalidArgumentError(f"step {step!r} is not in route {route!r}")
        return int(route), routes[route].index(step)

    def ascii(self) -> str:
        """The tree as ASCII art (py_trees' renderer)."""
        return py_trees.display.ascii_tree(self.root)

    def render(self, path: str | Path) -> list[Path]:
        """Write the tree to ``path`` (suffix replaced): ``.txt`` ASCII always, ``.dot`` source, and ``.png`` when
        graphviz's ``dot`` is installed. Returns the files written."""
        from lfd_torch.store import atomic_path

        base = Path(path)
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

