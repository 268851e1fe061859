"""The Gaussian mixture on positions shared by every fitter of :mod:`lfd_torch.gmm`.

Notation:
    K  number of components
    d  state dimension
    N  number of samples
    weights      (K,)       mixing weights pi_k >= 0, summing to 1
    means        (K, d)     component means mu_k (data units, e.g. mm)
    covariances  (K, d, d)  symmetric positive-definite Sigma_k (data units squared)

Densities are evaluated through the Cholesky factor L_k of Sigma_k (cached at construction):
``log N(x; mu_k, Sigma_k) = -0.5 ||L_k^-1 (x - mu_k)||^2 - sum_i log L_k[i, i] - 0.5 d log(2 pi)``, the
normaliser from :func:`~lfd_torch.gmm.gaussian.gaussian_log_normalizer`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor

from lfd_torch.errors import (
    InvalidArgumentError,
    InvalidGMMError,
    NonFiniteError,
    ShapeMismatchError,
    StoreError,
    TooFewSamplesError,
)
from lfd_torch.gmm.gaussian import gaussian_log_normalizer
from lfd_torch.utils import check_float, check_generator, check_int, check_tensor, to_arguments

__all__ = ["GMM", "InvalidGMMError", "check_samples"]

#: Default of optional hyperparameter arguments of the check helpers: "not given, do not check".
NOT_GIVEN = object()

#: Relative tolerance on sum(weights) == 1 and on the symmetry of the covariances.
_WEIGHT_TOL = 1e-6


def check_samples(x: Tensor, x_dot: Tensor | None = None, *, min_samples: int = 1, name: str = "x") -> None:
    """Validate a sample matrix (and optional velocities) before fitting.

    Args:
        x: (N, d) positions.
        x_dot: optional (N, d) velocities paired row by row with ``x``.
        min_samples: smallest admissible N.
        name: name of ``x`` in error messages.

    Raises:
        ShapeMismatchError: ``x`` is not 2-D, ``x_dot`` differs in shape, dtype or device, or d == 0.
        TooFewSamplesError: N < ``min_samples``.
        NonFiniteError: NaN, Inf or an overflowing magnitude (:func:`lfd_torch.utils.safe_magnitude`) in ``x`` or
            ``x_dot``.
    """
    check_tensor(x, name, ndim=2, shape_hint="(N, d)")
    if x.shape[1] == 0:
        raise ShapeMismatchError(f"{name} must have shape (N, d) with d >= 1, got {tuple(x.shape)}")
    if x.shape[0] < min_samples:
        raise TooFewSamplesError(f"{name} has {x.shape[0]} samples, at least {min_samples} are needed")
    check_tensor(x, name)
    if x_dot is not None:
        if not isinstance(x_dot, Tensor) or x_dot.shape != x.shape:
            shape = tuple(x_dot.shape) if isinstance(x_dot, Tensor) else type(x_dot).__name__
            raise ShapeMismatchError(f"x_dot must have the shape of {name} {tuple(x.shape)}, got {shape}")
        check_tensor(x_dot, "x_dot", dtype=x.dtype, device=x.device)


@dataclass(frozen=True, eq=False)
class GMM:
    """A validated Gaussian mixture model on R^d (shapes in the module docstring).

    Immutable; ``to`` and the post-processing functions return new instances. Construction checks shapes,
    dtypes, devices, finiteness, ``weights >= 0``, ``sum(weights) == 1`` (relative tolerance 1e-6), symmetry
    of every covariance, and positive definiteness (a Cholesky factorisation, which is cached for
    evaluation).

    Raises:
        ShapeMismatchError: inconsistent shapes, dtypes or devices.
        NonFiniteError: NaN or Inf in a parameter.
        InvalidGMMError: invalid weights or a covariance that is not symmetric positive definite.
    """

    weights: Tensor
    means: Tensor
    covariances: Tensor
    _chol: Tensor = field(init=False, repr=False, compare=False)
    _chol_inv: Tensor = field(init=False, repr=False, compare=False)
    _log_norm: Tensor = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        w, mu, S = self.weights, self.means, self.covariances
        for name, t in (("weights", w), ("means", mu), ("covariances", S)):
            if not isinstance(t, Tensor):
                raise ShapeMismatchError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
            if not t.is_floating_point():
                raise ShapeMismatchError(f"{name} must be floating point, got {t.dtype}")
        if mu.ndim != 2 or mu.shape[0] == 0 or mu.shape[1] == 0:
            raise ShapeMismatchError(f"means must have shape (K, d) with K, d >= 1, got {tuple(mu.shape)}")
        K, d = mu.shape
        if w.shape != (K,):
            raise ShapeMismatchError(f"weights must have shape ({K},), got {tuple(w.shape)}")
        if S.shape != (K, d, d):
            raise ShapeMismatchError(f"covariances must have shape {(K, d, d)}, got {tuple(S.shape)}")
        for name, t in (("weights", w), ("covariances", S)):
            if t.dtype != mu.dtype or t.device != mu.device:
                raise ShapeMismatchError(f"{name} is {t.dtype} on {t.device}, means are {mu.dtype} on {mu.device}")
        for name, t in (("weights", w), ("means", mu), ("covariances", S)):
            if not torch.isfinite(t).all():
                raise NonFiniteError(f"GMM {name} contain NaN or Inf")
        if (w < 0).any():
            raise InvalidGMMError(f"weights must be non-negative, got {w.tolist()}")
        total = float(w.sum())
        if abs(total - 1.0) > _WEIGHT_TOL:
            raise InvalidGMMError(f"weights must sum to 1, they sum to {total!r}")
        scale = S.abs().amax(dim=(-2, -1), keepdim=True).clamp_min(torch.finfo(S.dtype).tiny)
        asym = ((S - S.transpose(-2, -1)).abs() / scale).amax()
        if float(asym) > _WEIGHT_TOL * 10:
            raise InvalidGMMError(f"covariances must be symmetric (relative asymmetry {float(asym):.3g})")
        L, info = torch.linalg.cholesky_ex(0.5 * (S + S.transpose(-2, -1)))
        if (info != 0).any():
            k = int(torch.nonzero(info != 0)[0])
            raise InvalidGMMError(f"covariance {k} is not positive definite")
        eye = torch.eye(d, dtype=S.dtype, device=S.device).expand(K, d, d)
        L_inv = torch.linalg.solve_triangular(L, eye, upper=False)
        log_norm = torch.log(w) + gaussian_log_normalizer(L)
        object.__setattr__(self, "_chol", L)
        object.__setattr__(self, "_chol_inv", L_inv)
        object.__setattr__(self, "_log_norm", log_norm)

    # ------------------------------------------------------------------ properties
    @property
    def n_components(self) -> int:
        """K."""
        return self.means.shape[0]

    @property
    def dim(self) -> int:
        """d."""
        return self.means.shape[1]

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def cholesky(self) -> Tensor:
        """(K, d, d) lower Cholesky factors L_k with L_k L_k^T = Sigma_k."""
        return self._chol

    @property
    def precisions(self) -> Tensor:
        """(K, d, d) inverse covariances Sigma_k^-1 = L_k^-T L_k^-1."""
        return self._chol_inv.transpose(-2, -1) @ self._chol_inv

    # ------------------------------------------------------------------ densities
    def _check_points(self, x: Tensor) -> None:
        """x (..., d) in the GMM's dtype and device, finite and below the overflow magnitude."""
        check_tensor(x, "x", min_ndim=1, last_dim=self.dim, dtype=self.dtype, device=self.device,
                     shape_hint=f"(..., {self.dim})")  # fmt: skip

    def mahalanobis_sq(self, x: Tensor) -> Tensor:
        """Squared Mahalanobis distances (x - mu_k)^T Sigma_k^-1 (x - mu_k).

        Args:
            x: (..., d) points.

        Returns:
            (..., K) tensor.
        """
        self._check_points(x)
        diff = x.unsqueeze(-2) - self.means  # (..., K, d)
        z = torch.einsum("kij,...kj->...ki", self._chol_inv, diff)
        return (z * z).sum(-1)

    def log_prob_components(self, x: Tensor) -> Tensor:
        """Joint log densities log pi_k + log N(x; mu_k, Sigma_k).

        Args:
            x: (..., d) points, same dtype and device as the GMM (NaN, Inf or overflowing entries raise).

        Returns:
            (..., K) tensor; -inf for components with zero weight.
        """
        return self._log_norm - 0.5 * self.mahalanobis_sq(x)

    def log_prob(self, x: Tensor) -> Tensor:
        """Mixture log density log sum_k pi_k N(x; mu_k, Sigma_k).

        Args:
            x: (..., d) points.

        Returns:
            (...) tensor.
        """
        return torch.logsumexp(self.log_prob_components(x), dim=-1)

    def posterior(self, x: Tensor) -> Tensor:
        """Responsibilities gamma_k(x) = pi_k N(x; mu_k, Sigma_k) / sum_j pi_j N(x; mu_j, Sigma_j).

        Computed as a softmax of :meth:`log_prob_components`, so it stays finite and normalised far from the
        data (where every density underflows).

        Args:
            x: (..., d) points.

        Returns:
            (..., K) tensor, non-negative, summing to 1 over the last dimension.
        """
        return torch.softmax(self.log_prob_components(x), dim=-1)

    def sample(self, n: int, *, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """Draw ``n`` samples.

        Args:
            n: number of samples, in [0, 10^8] (memory n d floats).
            generator: torch generator on the GMM's device.

        Returns:
            x (n, d) samples and their component labels (n,) int64.
        """
        check_int(n, "n", low=0, high=10**8)
        check_generator(generator)
        if n == 0:  # torch.multinomial refuses to draw no samples
            return self.means.new_zeros(0, self.dim), torch.zeros(0, dtype=torch.long, device=self.device)
        labels = torch.multinomial(self.weights, n, replacement=True, generator=generator)
        eps = torch.randn(n, self.dim, dtype=self.dtype, device=self.device, generator=generator)
        x = self.means[labels] + torch.einsum("nij,nj->ni", self._chol[labels], eps)
        return x, labels

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def from_labels(cls, x: Tensor, labels: Tensor, *, reg_covar: float = 1e-6) -> GMM:
        """Maximum-likelihood mixture of a hard partition: one component per distinct label.

        Component order follows the sorted label values. ``reg_covar`` times the mean per-dimension data
        variance (or times 1 when the data have zero spread) is added to every covariance diagonal, so
        singleton clusters are valid components.

        Args:
            x: (N, d) samples.
            labels: (N,) integer labels (any values; relabelled 0..K-1).
            reg_covar: relative diagonal loading of the covariances.

        Returns:
            A GMM with K = number of distinct labels.

        Raises:
            ShapeMismatchError, TooFewSamplesError, NonFiniteError: ``x`` is not a finite (N, d) tensor, or
                ``labels`` is not a real (N,) tensor (NaN labels included).
            InvalidGMMError: ``reg_covar`` is not a finite number >= 0.
        """
        check_samples(x, min_samples=1)
        if not isinstance(labels, Tensor) or labels.is_complex():
            what = labels.dtype if isinstance(labels, Tensor) else type(labels).__name__
            raise ShapeMismatchError(f"labels must be a torch.Tensor of shape ({x.shape[0]},), got {what}")
        if labels.shape != (x.shape[0],):
            raise ShapeMismatchError(f"labels must have shape ({x.shape[0]},), got {tuple(labels.shape)}")
        if labels.is_floating_point() and not bool(torch.isfinite(labels).all()):
            raise NonFiniteError("labels contain NaN or Inf")
        check_float(reg_covar, "reg_covar", low=0.0, error=InvalidGMMError)
        _, z = torch.unique(labels.to(x.device), return_inverse=True)
        return _gmm_from_dense_labels(x, z, reg_covar)

    # ------------------------------------------------------------------ conversion and persistence
    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> GMM:
        """A copy with parameters cast to ``dtype`` (float32 or float64, or its name) and moved to ``device``
        (``.to("cuda")``: a device as the only argument, as ``torch.Tensor.to``)."""
        dtype, device = to_arguments(dtype, device, error=ShapeMismatchError)
        f = dict(dtype=dtype or self.dtype, device=device or self.device)
        return GMM(self.weights.to(**f), self.means.to(**f), self.covariances.to(**f))

    def replace(self, **changes: Tensor) -> GMM:
        """A copy with some of ``weights``, ``means``, ``covariances`` replaced; validated again.

        Raises:
            InvalidArgumentError: a keyword that is not one of the three fields. Otherwise as the constructor.
        """
        unknown = sorted(set(changes) - {"weights", "means", "covariances"})
        if unknown:
            raise InvalidArgumentError(f"GMM.replace got unknown field(s) {unknown}; the fields are weights, means, "
                                       "covariances")  # fmt: skip
        return dataclasses.replace(self, **changes)

    def state_dict(self) -> dict[str, Tensor]:
        """Plain dict of the parameter tensors (``weights``, ``means``, ``covariances``)."""
        return {"weights": self.weights, "means": self.means, "covariances": self.covariances}

    @classmethod
    def from_state_dict(cls, state: dict[str, Tensor]) -> GMM:
        """Inverse of :meth:`state_dict` (extra keys are rejected).

        Raises:
            StoreError: ``state`` is not a mapping. ShapeMismatchError: other keys than the three fields. Otherwise
                as the constructor.
        """
        if not isinstance(state, Mapping):
            raise StoreError(f"a GMM state dict must be a mapping, got {type(state).__name__}")
        keys = {"weights", "means", "covariances"}
        if set(state) != keys:
            raise ShapeMismatchError(f"GMM state dict needs exactly the keys {sorted(keys)}, got {sorted(state)}")
        return cls(state["weights"], state["means"], state["covariances"])

    def __repr__(self) -> str:
        return f"GMM(n_components={self.n_components}, dim={self.dim}, dtype={self.dtype}, device={self.device})"


def _gmm_from_dense_labels(x: Tensor, z: Tensor, reg_covar: float) -> GMM:
    """ML mixture for labels z in 0..K-1, all used. x (N, d), z (N,) int64."""
    N, d = x.shape
    K = int(z.max()) + 1
    counts = torch.bincount(z, minlength=K).to(x.dtype)
    sums = torch.zeros(K, d, dtype=x.dtype, device=x.device).index_add_(0, z, x)
    means = sums / counts[:, None]
    diff = x - means[z]
    outer = diff.unsqueeze(-1) * diff.unsqueeze(-2)
    scatter = torch.zeros(K, d, d, dtype=x.dtype, device=x.device).index_add_(0, z, outer)
    cov = scatter / counts[:, None, None]
    var_scale = x.var(dim=0, unbiased=False).mean() if N > 1 else x.new_tensor(0.0)
    if not float(var_scale) > 0:
        var_scale = x.new_tensor(1.0)
    cov = 0.5 * (cov + cov.transpose(-2, -1)) + reg_covar * var_scale * torch.eye(d, dtype=x.dtype, device=x.device)
    return GMM(counts / N, means, cov)
