"""Config-friendly fitters: one frozen dataclass per method whose fields are the method's hyperparameters.

The fields are validated at construction, by the very checks the fit function runs (``check_*_hyperparameters``),
so a bad value in a config fails when the fitter is built, not at the first fit.

Every fitter is called the same way, ``fitter(x, x_dot, *, generator) -> GMM``, so LPV-DS can take any of
them from ``conf/gmm/<method>.yaml`` (``_target_`` + the fields below, one for one). Methods that ignore
velocities (EM, EM+BIC) accept and ignore ``x_dot``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, fields

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError
from lfd_torch.gmm.damm import check_damm_hyperparameters, fit_damm
from lfd_torch.gmm.em import check_em_hyperparameters, fit_em, fit_em_bic
from lfd_torch.gmm.model import GMM
from lfd_torch.gmm.pcgmm import check_pcgmm_hyperparameters, fit_pcgmm
from lfd_torch.utils import check_generator

__all__ = ["PCGMMFitter", "DAMMFitter", "EMFitter", "EMBICFitter"]


def _hyperparameters(fitter: object) -> dict[str, object]:
    """The dataclass fields of a fitter as keyword arguments of its fit function (one source of truth)."""
    return {f.name: getattr(fitter, f.name) for f in fields(fitter)}  # type: ignore[arg-type]


def _check_generator(generator: object, fitter: str) -> None:
    check_generator(generator, where=fitter)


@dataclass(frozen=True)
class PCGMMFitter:
    """PC-GMM (:func:`~lfd_torch.gmm.pcgmm.fit_pcgmm`); the fields are its hyperparameters."""

    length_scale: float | None = None
    alpha: float = 1.0
    kappa0: float = 1.0
    nu0_offset: float = 2.0
    psi_scale: float = 1.0
    n_iter: int = 20
    min_cluster_size: int | None = None
    max_points: int | None = 500
    reg_covar: float = 1e-3
    uses_velocities = True

    def __post_init__(self) -> None:
        check_pcgmm_hyperparameters(**_hyperparameters(self))

    def __call__(self, x: Tensor, x_dot: Tensor | None = None, *, generator: torch.Generator) -> GMM:
        """Fit to positions x (N, d) and velocities x_dot (N, d) (required)."""
        if x_dot is None:
            raise InvalidArgumentError("PC-GMM needs velocities x_dot (N, d), got None")
        _check_generator(generator, "PCGMMFitter")
        return fit_pcgmm(x, x_dot, generator=generator, **_hyperparameters(self))


@dataclass(frozen=True)
class DAMMFitter:
    """DAMM-like mixture (:func:`~lfd_torch.gmm.damm.fit_damm`); the fields are its hyperparameters."""

    alpha: float = 1.0
    kappa: float = 5.0
    kappa0: float = 1.0
    nu0_offset: float = 10.0
    psi_scale: float = 1.0
    n_iter: int = 20
    min_cluster_size: int | None = None
    reg_covar: float = 1e-3
    uses_velocities = True

    def __post_init__(self) -> None:
        check_damm_hyperparameters(**_hyperparameters(self))

    def __call__(self, x: Tensor, x_dot: Tensor | None = None, *, generator: torch.Generator) -> GMM:
        """Fit to positions x (N, d) and velocities x_dot (N, d) (required)."""
        if x_dot is None:
            raise InvalidArgumentError("DAMM needs velocities x_dot (N, d), got None")
        _check_generator(generator, "DAMMFitter")
        return fit_damm(x, x_dot, generator=generator, **_hyperparameters(self))


@dataclass(frozen=True)
class EMFitter:
    """EM with a fixed number of components (:func:`~lfd_torch.gmm.em.fit_em`)."""

    n_components: int = 5
    n_init: int = 1
    max_iter: int = 100
    tol: float = 1e-6
    reg_covar: float = 1e-6
    kmeans_iter: int = 10
    uses_velocities = False

    def __post_init__(self) -> None:
        check_em_hyperparameters(**_hyperparameters(self))

    def __call__(self, x: Tensor, x_dot: Tensor | None = None, *, generator: torch.Generator) -> GMM:
        """Fit to positions x (N, d); ``x_dot`` is ignored."""
        _check_generator(generator, "EMFitter")
        return fit_em(x, generator=generator, **_hyperparameters(self))


@dataclass(frozen=True)
class EMBICFitter:
    """EM for every K in ``k_range``, lowest BIC kept (:func:`~lfd_torch.gmm.em.fit_em_bic`)."""

    k_range: Sequence[int] = field(default=tuple(range(1, 11)))
    n_init: int = 1
    max_iter: int = 100
    tol: float = 1e-6
    reg_covar: float = 1e-6
    kmeans_iter: int = 10
    uses_velocities = False

    def __post_init__(self) -> None:
        if isinstance(self.k_range, (str, bytes)) or not isinstance(self.k_range, Iterable):
            raise InvalidArgumentError(f"k_range must be a sequence of integers >= 1, got {self.k_range!r}")
        object.__setattr__(self, "k_range", tuple(self.k_range))
        check_em_hyperparameters(**_hyperparameters(self))

    def __call__(self, x: Tensor, x_dot: Tensor | None = None, *, generator: torch.Generator) -> GMM:
        """Fit to positions x (N, d); ``x_dot`` is ignored."""
        _check_generator(generator, "EMBICFitter")
        return fit_em_bic(x, generator=generator, **_hyperparameters(self))
