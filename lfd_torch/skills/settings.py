"""The ``skills`` config group as one object: how libraries are learned and how the engine arrives."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from lfd_torch.errors import InvalidArgumentError
from lfd_torch.skills.arrival import Arrival

__all__ = ["SkillSettings"]


@dataclass(frozen=True)
class SkillSettings:
    """Settings of :meth:`SkillLibrary.learn` and of the engine's :class:`~lfd_torch.skills.Arrival` rule.

    Attributes:
        entropy_quantile: threshold H2(x_r) = this quantile of H2 over a step's training states (None: x_r = g_m).
        entropy_reference: ``training`` or ``reproduction`` (see :meth:`SkillLibrary.learn`).
        check: run the stability check at learn time (True, False, or its keyword arguments).
        arrival: the engine's step-completion ball, rate floor and speed cap.
    """

    entropy_quantile: float | None = 1.0
    entropy_reference: str = "training"
    check: Any = True
    arrival: Arrival = field(default_factory=Arrival)

    def __post_init__(self) -> None:
        if not isinstance(self.arrival, Arrival):
            raise InvalidArgumentError(f"arrival must be an Arrival, got {type(self.arrival).__name__}")

    @property
    def learn_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :meth:`SkillLibrary.learn`."""
        check = dict(self.check) if hasattr(self.check, "items") else bool(self.check)
        return {"entropy_quantile": self.entropy_quantile, "entropy_reference": self.entropy_reference,
                "check": check}  # fmt: skip
