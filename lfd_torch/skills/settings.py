"""The ``skills`` config group as one object: how libraries are learned and how the engine arrives."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from lfd_torch.errors import InvalidArgumentError
from lfd_torch.skills.arrival import Arrival
from lfd_torch.utils import check_choice, check_float

__all__ = ["SkillSettings"]


@dataclass(frozen=True)
class SkillSettings:
    """Settings of :meth:`SkillLibrary.learn` and of the engine's :class:`~lfd_torch.skills.Arrival` rule.

    Attributes:
        entropy_quantile: threshold H2(x_r) = this quantile of H2 over a step's training states (None: x_r = g_m).
        entropy_reference: ``training`` or ``reproduction`` (see :meth:`SkillLibrary.learn`).
        check: run the stability check at learn time (True, False (or 1, 0), or a mapping of its keyword arguments).
        arrival: the engine's step-completion ball, rate floor and speed cap.
    """

    entropy_quantile: float | None = 1.0
    entropy_reference: str = "training"
    check: Any = True
    arrival: Arrival = field(default_factory=Arrival)

    def __post_init__(self) -> None:
        check_float(self.entropy_quantile, "entropy_quantile", low=0.0, high=1.0, allow_none=True)
        check_choice(self.entropy_reference, "entropy_reference", ("training", "reproduction"))
        flag = isinstance(self.check, int) and self.check in (0, 1)  # bool is an int
        if not (flag or isinstance(self.check, Mapping)):
            raise InvalidArgumentError(f"check must be a bool (or 0, 1) or a mapping of check_stability arguments, "
                                       f"got {self.check!r}")  # fmt: skip
        if not isinstance(self.arrival, Arrival):
            raise InvalidArgumentError(f"arrival must be an Arrival, got {type(self.arrival).__name__}")

    @property
    def learn_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :meth:`SkillLibrary.learn`."""
        check = dict(self.check) if isinstance(self.check, Mapping) else bool(self.check)
        return {"entropy_quantile": self.entropy_quantile, "entropy_reference": self.entropy_reference,
                "check": check}  # fmt: skip
