"""Up-front checks of the experiment scripts' Hydra configurations (at the top of each ``run(cfg)``, before fitting).

Every check raises a typed lfd_torch error whose message names the configuration key: :class:`InvalidArgumentError`
for a value out of range or of the wrong kind, :class:`UnknownNameError` for a name outside its valid set.
:func:`is_config_error` tells a configuration error raised during a fit (re-raised by the scripts) from a genuine
fit failure (a solver failure, a bad demonstration: recorded as a failed row).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from lfd_torch.errors import InvalidArgumentError, InvalidDemoError, InvalidGMMError, UnknownNameError
from lfd_torch.utils import check_choice, check_float, check_int

__all__ = [
    "get",
    "positive_float",
    "nonnegative_float",
    "positive_int",
    "nonnegative_int",
    "name_list",
    "rollout_steps",
    "check_entropy_quantile",
    "is_config_error",
]

_MISSING = object()

#: Errors raised during a fit that are the fit's outcome on its data, not a bad setting: a demonstration that fails
#: validation (too few samples in a step, ...) and a fitted mixture that is not a valid density.
FIT_FAILURES: tuple[type[Exception], ...] = (InvalidDemoError, InvalidGMMError)


def get(cfg: DictConfig, key: str) -> Any:
    """The value at the dotted ``key`` (InvalidArgumentError naming it when absent)."""
    value = OmegaConf.select(cfg, key, default=_MISSING)
    if value is _MISSING:
        raise InvalidArgumentError(f"{key} is missing from the configuration")
    return value


def positive_float(cfg: DictConfig, key: str, *, allow_inf: bool = False) -> float:
    """``cfg[key]`` as a finite (or, with ``allow_inf``, infinite) number > 0."""
    return check_float(get(cfg, key), key, low=0.0, low_open=True, allow_inf=allow_inf)  # type: ignore[return-value]


def nonnegative_float(cfg: DictConfig, key: str, *, allow_inf: bool = False) -> float:
    """``cfg[key]`` as a finite (or, with ``allow_inf``, infinite) number >= 0."""
    return check_float(get(cfg, key), key, low=0.0, allow_inf=allow_inf)  # type: ignore[return-value]


def positive_int(cfg: DictConfig, key: str, *, high: int | None = None) -> int:
    """``cfg[key]`` as an integer >= 1 (and <= ``high``)."""
    return check_int(get(cfg, key), key, low=1, high=high)  # type: ignore[return-value]


def nonnegative_int(cfg: DictConfig, key: str, *, high: int | None = None) -> int:
    """``cfg[key]`` as an integer >= 0 (and <= ``high``)."""
    return check_int(get(cfg, key), key, low=0, high=high)  # type: ignore[return-value]


def name_list(cfg: DictConfig, key: str, valid: Iterable[str], *, allow_all: bool = False) -> list[str]:
    """``cfg[key]`` as a non-empty list of distinct names from ``valid`` (``"all"``: every valid name, when
    ``allow_all``).

    Raises:
        InvalidArgumentError: not a list, empty, or with a repeated name.
        UnknownNameError: a name outside ``valid`` (the message lists them).
    """
    valid = tuple(str(v) for v in valid)
    value = get(cfg, key)
    if allow_all and value == "all":
        return list(valid)
    if not isinstance(value, (ListConfig, list, tuple)):
        accepted = "a list of names" + (' or "all"' if allow_all else "")
        raise InvalidArgumentError(f"{key} must be {accepted}, got {value!r}")
    names = list(value)
    if not names:
        raise InvalidArgumentError(f"{key} must name at least one of {', '.join(valid)}; got an empty list")
    for name in names:
        check_choice(name, key, valid)
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise InvalidArgumentError(f"{key} names {', '.join(repeated)} more than once")
    return [str(n) for n in names]


def rollout_steps(cfg: DictConfig, dt_key: str = "dt", budget_key: str = "budget_s") -> int:
    """The rollout step budget ``round(budget_s / dt)`` after checking both are positive finite numbers; at least 1."""
    dt = positive_float(cfg, dt_key)
    budget = positive_float(cfg, budget_key)
    n = int(round(budget / dt))
    if n < 1:
        raise InvalidArgumentError(f"{budget_key} / {dt_key} must give at least one rollout step, got "
                                   f"{budget_key}={budget!r}, {dt_key}={dt!r}")  # fmt: skip
    return n


def check_entropy_quantile(cfg: DictConfig, key: str = "modulation.entropy_quantile",
                           source: str = "skills.entropy_quantile") -> None:  # fmt: skip
    """The small-scale H2 threshold is the skill library's: ``skills.entropy_quantile`` sets it when the library
    is learned, and the engine reads it from there. ``modulation.entropy_quantile`` follows it (an interpolation in
    the experiment configs); a different value would be silently ignored, so it is refused.

    Raises:
        InvalidArgumentError: ``key`` differs from ``source`` (naming both).
    """
    mod = OmegaConf.select(cfg, key, default=_MISSING)
    if mod is _MISSING:
        return
    src = OmegaConf.select(cfg, source, default=_MISSING)
    if src is _MISSING or mod != src:
        raise InvalidArgumentError(
            f"{key}={mod!r} differs from {source}={None if src is _MISSING else src!r}: the small-scale H2 "
            f"threshold is the skill library's, set by {source} when the library is learned ({key} only follows "
            f"it); override {source} instead"
        )


def is_config_error(exc: BaseException) -> bool:
    """Whether an error raised during a fit is a bad setting (an argument out of range, an unknown name) rather than
    the fit's outcome on its data (:data:`FIT_FAILURES`, solver and certificate failures)."""
    return isinstance(exc, (InvalidArgumentError, UnknownNameError)) and not isinstance(exc, FIT_FAILURES)
