"""Seeded random pushes of robots during a task, labelled by what they do to the decision engine.

A push at sample k displaces the robot by ``magnitude`` along a random direction. Its label says where it must land,
relative to the robot's active step m at that moment (which is only known during the run, so the direction is
drawn then, by the engine's rollout hook, from the plan's own generator; every rollout of a plan starts that
generator from the state it had when the plan was drawn, so a plan reused in another rollout of the same robots
gives the same run):

* ``large``: outside A_m (log p(x|A_m) < log p(x|A_m-)): the large-scale branch must bring the robot back;
* ``small``: inside A_m but at least ``away`` from every training position of step m: away from the
  demonstrations, where the small-scale (entropy) branch acts;
* ``random``: any direction (the first draw).

For a labelled push ``n_candidates`` directions are drawn and the first that satisfies the label is used; if none
does (e.g. a large push from deep inside a wide A_m), the push is skipped and logged as such. Rows whose task is
already done are not pushed. Every push, applied or skipped, is in :attr:`PushPlan.log`.

Notation: B robots, P pushes per robot, d state dimension; magnitudes and ``away`` in data units.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, UnknownNameError

if TYPE_CHECKING:
    from lfd_torch.skills.engine import SkillEngine

__all__ = ["PUSH_KINDS", "PushPlan", "random_pushes"]

#: Labels of a push; ``mixed`` in :func:`random_pushes` draws ``large`` or ``small`` with equal probability.
PUSH_KINDS = ("random", "large", "small")


@dataclass(eq=False)
class PushPlan:
    """Pushes of B robots (module docstring), applied by :meth:`~lfd_torch.skills.SkillEngine.rollout`.

    Attributes:
        steps: (B, P) long sample index of each push (distinct within a row).
        magnitudes: (B, P) displacement lengths (units).
        kinds: (B, P) long index into :data:`PUSH_KINDS`.
        generator: the generator the plan was drawn from. The push directions come from a copy of its state at
            the plan's creation, rewound by :meth:`begin_run` at the start of every rollout: a run neither consumes
            ``generator`` nor depends on what is drawn from it later, and a reused plan reproduces its run.
        away: smallest distance of a ``small`` push's landing point to the step's training positions (units).
        n_candidates: directions tried for a labelled push.
        log: one dict per push: row, sample, kind, step, applied, magnitude, landing distance to the data (every run
            of the plan appends its own; the rollout reports only those of its run).
    """

    steps: Tensor
    magnitudes: Tensor
    kinds: Tensor
    generator: torch.Generator
    away: float
    n_candidates: int = 64
    log: list[dict[str, Any]] = field(default_factory=list)

    @property
    def last_step(self) -> int:
        """The last sample at which a push acts (-1 without pushes)."""
        return int(self.steps.max()) if self.steps.numel() else -1

    def __post_init__(self) -> None:
        self._samples = frozenset(self.steps.reshape(-1).tolist())
        self._start_state = self.generator.get_state()  # the directions' stream of every run starts here
        self._directions = torch.Generator(device=self.generator.device)
        self._directions.set_state(self._start_state)

    def begin_run(self) -> int:
        """Rewind the push directions to the plan's creation (every run of the plan draws the same ones) and return
        the position in :attr:`log` where this run's entries begin; called by the rollout before its first sample."""
        self._directions.set_state(self._start_state)
        return len(self.log)

    def apply(self, k: int, x: Tensor, engine: SkillEngine, state: dict[str, Tensor]) -> Tensor | None:
        """The displaced (B, d) state after the pushes scheduled at sample k, or None when none acts."""
        if k not in self._samples:
            return None
        hit = (self.steps == k) & ~state["done"].unsqueeze(-1).to(self.steps.device)
        if not bool(hit.any()):
            return None
        rows, cols = torch.nonzero(hit, as_tuple=True)
        n, d, C = rows.numel(), x.shape[-1], self.n_candidates
        dirs = torch.randn((n, C, d), generator=self._directions, dtype=x.dtype, device=self._directions.device)
        dirs = (dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)).to(x.device)
        mag = self.magnitudes[rows, cols].to(x)
        cand = x[rows].unsqueeze(1) + mag.view(n, 1, 1) * dirs  # (n, C, d)
        step = state["step"][rows]
        flat_step = step.repeat_interleave(C)
        own, other = engine._own_other(cand.reshape(n * C, d).to(**engine._f), flat_step)  # the run's: checked
        inside = (own >= other).view(n, C)
        dist = torch.empty(n, C, dtype=x.dtype, device=x.device)
        for m in torch.unique(step).tolist():
            sel = torch.nonzero(step == m).reshape(-1)
            data = engine.library.skills[m].train_positions.to(x)
            dist[sel] = torch.cdist(cand[sel].reshape(-1, d), data).amin(-1).view(-1, C)
        kind = self.kinds[rows, cols].to(x.device)
        ok = torch.where(
            (kind == 1).unsqueeze(-1), ~inside,
            torch.where((kind == 2).unsqueeze(-1), inside & (dist >= self.away), torch.ones_like(inside)),
        )  # fmt: skip
        found = ok.any(-1)
        first = ok.to(torch.int8).argmax(-1)
        y = x.clone()
        take = torch.nonzero(found).reshape(-1)
        y[rows[take]] = cand[take, first[take]]
        for i in range(n):
            c = int(first[i])
            self.log.append({
                "row": int(rows[i]), "sample": int(k), "kind": PUSH_KINDS[int(kind[i])], "step": int(step[i]),
                "applied": bool(found[i]), "magnitude": float(mag[i]),
                "data_distance": float(dist[i, c]) if bool(found[i]) else math.nan,
            })  # fmt: skip
        return y if take.numel() else None


def random_pushes(
    n_rows: int,
    *,
    generator: torch.Generator,
    n_pushes: int = 2,
    window: tuple[int, int],
    magnitude: tuple[float, float],
    kinds: str | Sequence[str] = "mixed",
    away: float | None = None,
    n_candidates: int = 64,
) -> PushPlan:
    """Draw a push plan: P pushes per robot at distinct samples in ``window``, magnitudes uniform in ``magnitude``.

    Args:
        n_rows: B robots.
        generator: the plan's randomness (times, magnitudes and kinds now; directions during the run).
        n_pushes: P pushes per robot (>= 0).
        window: (first, last) sample index, inclusive, with last - first + 1 >= P.
        magnitude: (low, high) displacement length (units), 0 < low <= high.
        kinds: ``mixed`` (large or small, equally likely), one of :data:`PUSH_KINDS`, or a sequence of P labels.
        away: least distance of a small push's landing point to the step's data (default low / 2).
        n_candidates: directions tried for a labelled push.

    Raises:
        InvalidArgumentError: a count, window or magnitude out of range. UnknownNameError: an unknown kind.
    """
    from lfd_torch.utils import check_cost, check_float, check_generator, check_int

    check_generator(generator)
    for name, v, lo in (("n_rows", n_rows, 1), ("n_pushes", n_pushes, 0), ("n_candidates", n_candidates, 1)):
        check_int(v, name, low=lo, high=10**6)
    if isinstance(window, (str, bytes)) or not isinstance(window, Sequence) or len(window) != 2:
        raise InvalidArgumentError(f"window must be (first, last) sample indices, got {window!r}")
    first, last = (check_int(w, "window entry", low=1) for w in window)
    if last - first + 1 < n_pushes:
        raise InvalidArgumentError(f"window {window!r} must start at >= 1 and hold n_pushes = {n_pushes} distinct "
                                   "samples")  # fmt: skip
    check_cost("window", float(n_rows) * (last - first + 1), 1e8, "random draws (n_rows x window width)")
    if isinstance(magnitude, (str, bytes)) or not isinstance(magnitude, Sequence) or len(magnitude) != 2:
        raise InvalidArgumentError(f"magnitude must be (low, high), got {magnitude!r}")
    lo_m, hi_m = (check_float(v, "magnitude entry") for v in magnitude)
    if not (math.isfinite(hi_m) and 0 < lo_m <= hi_m):
        raise InvalidArgumentError(f"magnitude must be (low, high) with 0 < low <= high, got {magnitude!r}")
    check_float(away, "away", low=0.0, allow_none=True)
    if not isinstance(kinds, (str, Sequence)):
        raise InvalidArgumentError(f"kinds must be a push kind or a sequence of them, got {kinds!r}")
    dev = generator.device
    width = last - first + 1
    order = torch.rand((n_rows, width), generator=generator, device=dev).argsort(-1)[:, :n_pushes]
    steps = (order + first).sort(-1).values
    mags = lo_m + (hi_m - lo_m) * torch.rand((n_rows, n_pushes), generator=generator, dtype=torch.float64, device=dev)
    if isinstance(kinds, str) and kinds == "mixed":
        kind_t = 1 + (torch.rand((n_rows, n_pushes), generator=generator, device=dev) < 0.5).long()
    else:
        labels = [kinds] * n_pushes if isinstance(kinds, str) else list(kinds)
        if len(labels) != n_pushes:
            raise InvalidArgumentError(f"kinds lists {len(labels)} labels for {n_pushes} pushes")
        for lab in labels:
            if lab not in PUSH_KINDS:
                raise UnknownNameError("push kind (kinds)", str(lab), (*PUSH_KINDS, "mixed"))
        kind_t = torch.tensor([PUSH_KINDS.index(lab) for lab in labels], device=dev).expand(n_rows, n_pushes).clone()
    return PushPlan(steps, mags, kind_t, generator, lo_m / 2 if away is None else float(away), n_candidates)
