"""Solving cvxpy problems with named solvers, an ordered fallback and a checked status.

Every convex program of :mod:`lfd_torch.ds` goes through :func:`solve_problem`: it tries the solvers in the
given order (Clarabel first, SCS as fallback by default), accepts only the status ``optimal`` and raises
:class:`~lfd_torch.errors.SolverError` listing every attempt otherwise. Callers verify the solution afterwards
(positive definiteness, stability margins) in float64; a solver's word alone never certifies a model.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import cvxpy as cp

from lfd_torch.errors import InvalidArgumentError, SolverError

__all__ = ["DEFAULT_SOLVERS", "solve_problem", "normalize_solvers", "normalize_solver_options"]

#: Solvers tried in order when none are named.
DEFAULT_SOLVERS: tuple[str, ...] = ("CLARABEL", "SCS")


def normalize_solvers(solvers: str | Sequence[str]) -> tuple[str, ...]:
    """``"CLARABEL"`` or ``["CLARABEL", "SCS"]`` -> upper-case tuple; an empty list is an error.

    Raises:
        InvalidArgumentError: ``solvers`` is not a string or a sequence of strings, or is empty.
    """
    if isinstance(solvers, str):
        names: tuple[Any, ...] = (solvers,)
    elif isinstance(solvers, Sequence):
        names = tuple(solvers)
    else:
        raise InvalidArgumentError(f"solvers must be a solver name or a sequence of names, got {solvers!r}")
    if not names or not all(isinstance(n, str) for n in names):
        raise InvalidArgumentError(f"solvers must name at least one solver, e.g. ('CLARABEL', 'SCS'), got {solvers!r}")
    return tuple(n.upper() for n in names)


def normalize_solver_options(solver_options: Mapping[str, Mapping[str, Any]] | None) -> dict[str, dict[str, Any]]:
    """``{solver: {option: value}}`` with upper-case solver names.

    Raises:
        InvalidArgumentError: not a mapping of solver names to mappings of option names.
    """
    if solver_options is None:
        return {}
    if not isinstance(solver_options, Mapping):
        raise InvalidArgumentError(f"solver_options must be a mapping {{solver: {{option: value}}}}, got "
                                   f"{solver_options!r}")  # fmt: skip
    out: dict[str, dict[str, Any]] = {}
    for name, opts in solver_options.items():
        if not isinstance(name, str) or not isinstance(opts, Mapping) or not all(isinstance(k, str) for k in opts):
            raise InvalidArgumentError(f"solver_options[{name!r}] must be a mapping of option names to values, got "
                                       f"{opts!r}")  # fmt: skip
        out[name.upper()] = dict(opts)
    return out


def solve_problem(
    problem: cp.Problem,
    solvers: str | Sequence[str] = DEFAULT_SOLVERS,
    solver_options: Mapping[str, Mapping[str, Any]] | None = None,
    *,
    what: str = "convex program",
) -> str:
    """Solve ``problem`` with the first solver that reports ``optimal``.

    Args:
        problem: a cvxpy problem (parameters already set).
        solvers: solver names tried in order.
        solver_options: optional ``{solver name: {option: value}}`` passed to ``problem.solve``.
        what: name of the program in error messages.

    Returns:
        The name of the solver whose solution is in the problem's variables.

    Raises:
        SolverError: no solver reached status ``optimal`` (the message lists each attempt and its outcome).
        InvalidArgumentError: malformed ``solvers`` or ``solver_options``, options for a solver that is not tried,
            or an option a solver does not know.
    """
    options = normalize_solver_options(solver_options)
    names = normalize_solvers(solvers)
    unused = sorted(set(options) - set(names))
    if unused:  # a misspelt solver, or one not tried: its options would be dropped without a word
        raise InvalidArgumentError(f"solver_options name {unused}, which are not among the solvers tried {list(names)}")
    attempts: list[str] = []
    for name in names:
        try:
            with warnings.catch_warnings():  # "Solution may be inaccurate": the status is checked below
                warnings.simplefilter("ignore", UserWarning)
                # no warm start: a cached program would otherwise start from the previous fit's solution, and
                # the result (to the solver's tolerance) would depend on what was solved before in the process
                problem.solve(solver=name, **{"warm_start": False, **options.get(name, {})})
        except TypeError as exc:  # an option the solver does not know: the caller's mistake, not a solver failure
            raise InvalidArgumentError(f"solver_options[{name!r}] = {options.get(name, {})!r}: {exc}") from exc
        except (cp.error.SolverError, cp.error.DCPError, ValueError, ArithmeticError, RuntimeError) as exc:
            attempts.append(f"{name}: {type(exc).__name__}: {exc}")
            continue
        if problem.status == cp.OPTIMAL:
            return name
        attempts.append(f"{name}: status {problem.status}")
    raise SolverError(f"{what} not solved to optimality (solvers={list(names)}, solver_options="
                      f"{options}); " + "; ".join(attempts))  # fmt: skip
