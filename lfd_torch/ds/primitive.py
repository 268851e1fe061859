"""Common interface of the stable motion primitives: GMM-scheduled mixtures of linear dynamical systems.

Both :class:`~lfd_torch.ds.lpvds.LPVDS` and :class:`~lfd_torch.ds.seds.SEDS` evaluate (paper eq. 5)

    f(x) = sum_k gamma_k(x) (A_k x + b_k),   b_k = -A_k g,   i.e.   f(x) = sum_k gamma_k(x) A_k (x - g),

with gamma_k(x) the posterior of a GMM on positions, and carry a quadratic Lyapunov function
V(x) = (x - g)^T P (x - g) with A_k^T P + P A_k < 0 for every k (paper eq. 6). Since gamma_k >= 0 and
sum_k gamma_k = 1, dV/dt = sum_k gamma_k (x - g)^T (A_k^T P + P A_k) (x - g) < 0 for x != g: g is globally
asymptotically stable. SEDS is the special case P = I.

Notation:
    K  number of components, d state dimension
    A                      (K, d, d)  system matrices, 1/s
    attractor g            (d,)       data units (LASA: mm)
    P                      (d, d)     symmetric positive definite, largest eigenvalue 1 (dimensionless)
    velocity_covariances   (K, d, d)  per-component covariance of the velocity around A_k (x - g), (units/s)^2
    x                      (..., d)   query positions; f(x) has the same shape (units/s)

Persistence: :meth:`StablePrimitive.save` writes ``torch.save`` of a plain dict of tensors plus a JSON string of
metadata (``schema_version``, ``kind``, ``info``) through a temporary file and ``os.replace``; :func:`load_primitive`
reads it back with ``weights_only=True`` and re-checks the certificate.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import torch
from torch import Tensor

from lfd_torch.errors import (
    CertificationError,
    InvalidArgumentError,
    LfdError,
    NonFiniteError,
    ShapeMismatchError,
    StoreError,
    UnknownNameError,
)
from lfd_torch.gmm import GMM, GaussianBank, check_samples
from lfd_torch.store import atomic_save
from lfd_torch.store.checksum import DIGEST_KEY, compact_cpu, payload_digest, verify_digest
from lfd_torch.utils import check_float, check_path, check_tensor, float_dtype, resolve_device, to_arguments

__all__ = [
    "SCHEMA_VERSION",
    "StabilityCertificate",
    "StablePrimitive",
    "load_primitive",
    "quadratic_margins",
    "check_velocity_covariances",
    "residual_velocity_covariances",
]

#: Version of the on-disk format written by :meth:`StablePrimitive.save`.
SCHEMA_VERSION = 1


class StabilityCertificate(NamedTuple):
    """Result of :meth:`StablePrimitive.stability_certificate`.

    Attributes:
        margins: (K,) float64, lambda_max(A_k^T P + P A_k) in 1/s; all < 0 for a certified primitive.
        max_margin: the largest margin (the worst component).
        certified: ``max_margin < 0``.
    """

    margins: Tensor
    max_margin: float
    certified: bool


def quadratic_margins(A: Tensor, P: Tensor) -> Tensor:
    """Largest eigenvalue of A_k^T P + P A_k for each k, computed in float64.

    Args:
        A: (K, d, d) system matrices.
        P: (d, d) symmetric Lyapunov matrix.

    Returns:
        (K,) float64 tensor on the device of ``A``.

    Raises:
        ShapeMismatchError / NonFiniteError: A not a finite (K, d, d) tensor or P not a finite (d, d) one.
    """
    check_tensor(A, "A", ndim=3, bounded=False, shape_hint="(K, d, d)")
    d = A.shape[-1]
    check_tensor(P, "P", ndim=2, last_dim=d, bounded=False, shape_hint=f"({d}, {d})")
    if A.shape[-2] != d or P.shape[0] != d:
        raise ShapeMismatchError(f"A must be (K, d, d) and P (d, d), got {tuple(A.shape)} and {tuple(P.shape)}")
    A64 = A.to(torch.float64)
    P64 = P.to(dtype=torch.float64, device=A.device)
    Q = A64.transpose(-2, -1) @ P64 + P64 @ A64
    Q = 0.5 * (Q + Q.transpose(-2, -1))
    return torch.linalg.eigvalsh(Q)[..., -1]


def _to_json(info: Mapping[str, Any]) -> str:
    try:
        return json.dumps(dict(info), sort_keys=True)
    except TypeError as exc:
        raise StoreError(f"primitive info must be JSON-serialisable: {exc}") from exc


@dataclass(frozen=True, eq=False)
class StablePrimitive:
    """A certified GMM-scheduled mixture of linear systems (see the module docstring for shapes and units).

    Construction validates shapes, dtypes, devices and finiteness, and checks the stability certificate in
    float64: an instance is always certified. Subclasses only set :attr:`kind` and provide ``fit``.

    Attributes:
        gmm: mixture on positions whose posterior gives gamma_k(x).
        A: (K, d, d) system matrices.
        attractor: (d,) goal g.
        P: (d, d) Lyapunov matrix, symmetric positive definite.
        velocity_covariances: (K, d, d) covariance of the velocity residual of each component (used by the
            disturbance modulation's entropy); symmetric positive definite.
        info: JSON-serialisable fit metadata (hyperparameters, timings, solver); not used for evaluation.

    Raises:
        ShapeMismatchError: inconsistent shapes, dtypes or devices.
        NonFiniteError: NaN or Inf in a parameter.
        CertificationError: P is not positive definite, or some A_k^T P + P A_k is not negative definite.
    """

    kind: ClassVar[str] = "StablePrimitive"

    gmm: GMM
    A: Tensor
    attractor: Tensor
    P: Tensor
    velocity_covariances: Tensor
    info: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.gmm, GMM):
            raise ShapeMismatchError(f"gmm must be a GMM, got {type(self.gmm).__name__}")
        if not isinstance(self.info, Mapping):
            raise InvalidArgumentError(f"info must be a mapping (JSON-serialisable), got {type(self.info).__name__}")
        K, d = self.gmm.n_components, self.gmm.dim
        expected = {"A": (K, d, d), "attractor": (d,), "P": (d, d), "velocity_covariances": (K, d, d)}
        for name, shape in expected.items():
            t = getattr(self, name)
            if not isinstance(t, Tensor):
                raise ShapeMismatchError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
            if tuple(t.shape) != shape:
                raise ShapeMismatchError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
            if t.dtype != self.gmm.dtype or t.device != self.gmm.device:
                raise ShapeMismatchError(
                    f"{name} is {t.dtype} on {t.device}, the GMM is {self.gmm.dtype} on {self.gmm.device}"
                )
            if not torch.isfinite(t).all():
                raise NonFiniteError(f"{name} contains NaN or Inf")
        object.__setattr__(self, "info", dict(self.info))
        _to_json(self.info)
        P64 = self.P.to(torch.float64)
        if float((P64 - P64.T).abs().max()) > 1e-9 * float(P64.abs().max()):
            raise CertificationError("P is not symmetric")
        if float(torch.linalg.eigvalsh(P64)[0]) <= 0:
            raise CertificationError("P is not positive definite")
        cert = self.stability_certificate()
        if not cert.certified:
            raise CertificationError(
                f"{self.kind}: lambda_max(A_k^T P + P A_k) = {cert.margins.tolist()} (1/s); all must be < 0"
            )
        check_velocity_covariances(self.velocity_covariances)

    # ------------------------------------------------------------------ properties
    @property
    def n_components(self) -> int:
        """K."""
        return self.gmm.n_components

    @property
    def dim(self) -> int:
        """d."""
        return self.gmm.dim

    @property
    def dtype(self) -> torch.dtype:
        return self.gmm.dtype

    @property
    def device(self) -> torch.device:
        return self.gmm.device

    @property
    def b(self) -> Tensor:
        """(K, d) offsets b_k = -A_k g (units/s)."""
        return -(self.A @ self.attractor)

    # ------------------------------------------------------------------ evaluation
    def _check(self, x: Tensor) -> None:
        """x (..., d) positions in the primitive's dtype and device, finite and below the overflow magnitude."""
        check_tensor(x, "x (positions)", min_ndim=1, last_dim=self.dim, dtype=self.dtype, device=self.device,
                     shape_hint=f"(..., {self.dim})")  # fmt: skip

    def component_velocities(self, x: Tensor) -> Tensor:
        """Velocity of every linear component, A_k (x - g).

        Args:
            x: (..., d) positions.

        Returns:
            (..., K, d) velocities (units/s).
        """
        self._check(x)
        return torch.einsum("kij,...j->...ki", self.A, x - self.attractor)

    def __call__(self, x: Tensor) -> Tensor:
        """Velocity f(x) = sum_k gamma_k(x) A_k (x - g).

        Args:
            x: (..., d) positions (any leading batch shape), same dtype/device as the primitive.

        Returns:
            (..., d) velocities (units/s).

        Precision: x - g is formed first, so a float32 model of a goal far from the origin keeps its velocities near
        the goal (``tests/test_lpvds.py::test_float32_velocities_near_a_goal_far_from_the_origin``).
        """
        self._check(x)
        K, d = self.n_components, self.dim
        lead = x.shape[:-1]
        xt = x.reshape(-1, d).T  # (d, N); contiguous for the rollout engine's (N, d) views of (d, N) storage
        n = xt.shape[1]
        bank, log_pi, A_stack = self._feature_major
        # Feature-major evaluation, (K*d, N) intermediates: reductions over a trailing axis of size d are slow on
        # CPUs. Same numbers as sum_k softmax_k(log pi_k + log N(x; mu_k, Sigma_k)) A_k (x - g).
        logits = bank.log_density_fm(xt).add_(log_pi)  # (K, N)
        gamma = torch.softmax(logits, dim=0)
        y = torch.mm(A_stack, xt - self.attractor.unsqueeze(1)).view(K, d, n)  # A_k (x - g)
        out = (y * gamma.unsqueeze(1)).sum(0)  # (d, N)
        return out.T.reshape(*lead, d)

    @functools.cached_property
    def _feature_major(self) -> tuple[GaussianBank, Tensor, Tensor]:
        """Constants of :meth:`__call__`: the GMM's Gaussians as a bank, log pi (K, 1), A (K*d, d)."""
        K, d = self.n_components, self.dim
        bank = GaussianBank(self.gmm.means, self.gmm.covariances)
        return bank, self.gmm.weights.log().reshape(K, 1), self.A.reshape(K * d, d)

    def lyapunov(self, x: Tensor) -> Tensor:
        """V(x) = (x - g)^T P (x - g).

        Args:
            x: (..., d) positions.

        Returns:
            (...) values (units^2).
        """
        self._check(x)
        e = x - self.attractor
        return torch.einsum("...i,ij,...j->...", e, self.P, e)

    def lyapunov_derivative(self, x: Tensor) -> Tensor:
        """dV/dt along the flow, 2 (x - g)^T P f(x); negative for every x != g.

        Args:
            x: (..., d) positions.

        Returns:
            (...) values (units^2/s).
        """
        x_dot = self(x)  # validates x
        return 2.0 * torch.einsum("...i,ij,...j->...", x - self.attractor, self.P, x_dot)

    def stability_certificate(self) -> StabilityCertificate:
        """Per-component margins lambda_max(A_k^T P + P A_k) in float64 and whether all are negative."""
        margins = quadratic_margins(self.A, self.P)
        worst = float(margins.max())
        return StabilityCertificate(margins, worst, worst < 0.0)

    # ------------------------------------------------------------------ conversion and persistence
    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> StablePrimitive:
        """A copy with every tensor cast to ``dtype`` (float32 or float64, or its name) and moved to ``device``
        (``.to("cuda")``: a device as the only argument, as ``torch.Tensor.to``)."""
        dtype, device = to_arguments(dtype, device, error=ShapeMismatchError)
        f = dict(dtype=dtype or self.dtype, device=device or self.device)
        return dataclasses.replace(
            self,
            gmm=self.gmm.to(**f),
            A=self.A.to(**f),
            attractor=self.attractor.to(**f),
            P=self.P.to(**f),
            velocity_covariances=self.velocity_covariances.to(**f),
        )

    def state_dict(self) -> dict[str, Any]:
        """Plain dict: ``schema_version`` (int), ``kind`` (str), ``info`` (JSON str) and the tensors.

        Each tensor is a compact CPU copy (its storage holds exactly its elements): a view of a larger storage would
        save bytes that no checksum covers, and a flipped bit there would go unnoticed.
        """
        return {
            "schema_version": SCHEMA_VERSION,
            "kind": self.kind,
            "info": _to_json(self.info),
            "gmm": {k: compact_cpu(v) for k, v in self.gmm.state_dict().items()},
            "A": compact_cpu(self.A),
            "attractor": compact_cpu(self.attractor),
            "P": compact_cpu(self.P),
            "velocity_covariances": compact_cpu(self.velocity_covariances),
        }

    @classmethod
    def from_state_dict(
        cls, state: Mapping[str, Any], *, dtype: torch.dtype | None = None, device: torch.device | str | None = None
    ) -> StablePrimitive:
        """Inverse of :meth:`state_dict`; called on the base class it dispatches on ``kind``.

        Raises:
            StoreError: not a mapping, unknown ``schema_version``, missing keys or malformed entries, or a ``kind``
                that does not match ``cls``.
            CertificationError: the stored parameters are not certified.
        """
        if not isinstance(state, Mapping):
            raise StoreError(f"a primitive state dict must be a mapping, got {type(state).__name__}")
        version = state.get("schema_version")
        if version != SCHEMA_VERSION:
            raise StoreError(f"unsupported primitive schema_version {version!r}; this version reads {SCHEMA_VERSION}")
        missing = {"kind", "info", "gmm", "A", "attractor", "P", "velocity_covariances"} - set(state)
        if missing:
            raise StoreError(f"primitive state dict lacks {sorted(missing)}")
        kind = state["kind"]
        bad = [k for k in ("A", "attractor", "P", "velocity_covariances") if not isinstance(state[k], Tensor)]
        if not isinstance(kind, str) or not isinstance(state["info"], str) or not isinstance(state["gmm"], Mapping) \
                or bad:  # fmt: skip
            raise StoreError(f"primitive state dict: kind and info must be strings, gmm a mapping and the arrays "
                             f"tensors (bad: {bad or [k for k in ('kind', 'info', 'gmm')]})")  # fmt: skip
        try:
            info = json.loads(state["info"])
        except json.JSONDecodeError as exc:
            raise StoreError(f"primitive state dict: info is not JSON ({exc})") from exc
        target = _registry().get(kind)
        if target is None:
            raise UnknownNameError("primitive kind", str(kind), tuple(_registry()))
        if cls is not StablePrimitive and target is not cls:
            raise StoreError(f"the file holds a {kind}, not a {cls.kind}")
        gmm = GMM.from_state_dict(dict(state["gmm"]))
        f = dict(dtype=dtype or gmm.dtype, device=device or gmm.device)
        return target(
            gmm=gmm.to(**f),
            A=state["A"].to(**f),
            attractor=state["attractor"].to(**f),
            P=state["P"].to(**f),
            velocity_covariances=state["velocity_covariances"].to(**f),
            info=info,
        )

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write :meth:`state_dict` with ``torch.save``, atomically (:func:`lfd_torch.store.atomic_save`: temporary
        file in the same folder, then ``os.replace``).

        Returns:
            The path written.

        Raises:
            StoreError: ``path`` is not a file path, or the file cannot be written (a file already there is kept).
        """
        state = self.state_dict()
        state[DIGEST_KEY] = payload_digest(state)
        path = check_path(path, "path", error=StoreError)
        return atomic_save(path, lambda tmp: torch.save(state, tmp), what="primitive file")

    @classmethod
    def load(
        cls, path: str | os.PathLike[str], *, dtype: torch.dtype | None = None, device: torch.device | str | None = None
    ) -> StablePrimitive:
        """Read a file written by :meth:`save` (``weights_only=True``); see :meth:`from_state_dict`."""
        dtype, device = float_dtype(dtype), resolve_device(device)  # the arguments' faults are not the file's
        try:
            state = torch.load(Path(path), map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - a damaged file fails anywhere in torch's unpickler (IndexError, ...)
            raise StoreError(f"cannot read primitive file {path}: {type(exc).__name__}: {exc}") from exc
        if not isinstance(state, Mapping):
            raise StoreError(f"{path} does not hold a primitive state dict")
        verify_digest(state, f"primitive file {path}")
        try:
            return cls.from_state_dict(state, dtype=dtype, device=device)
        except CertificationError as exc:
            raise CertificationError(f"primitive file {path}: {exc}") from exc
        except (LfdError, KeyError, TypeError, ValueError, AttributeError, RuntimeError) as exc:
            raise StoreError(f"primitive file {path}: {type(exc).__name__}: {exc}") from exc

    def __repr__(self) -> str:
        cert = self.stability_certificate()
        return (
            f"{self.kind}(n_components={self.n_components}, dim={self.dim}, max_margin={cert.max_margin:.3g}, "
            f"dtype={self.dtype}, device={self.device})"
        )


def _registry() -> dict[str, type[StablePrimitive]]:
    """kind -> class, for every subclass defined so far."""
    out: dict[str, type[StablePrimitive]] = {}
    stack = list(StablePrimitive.__subclasses__())
    while stack:
        c = stack.pop()
        out[c.kind] = c
        stack.extend(c.__subclasses__())
    return out


def load_primitive(
    path: str | os.PathLike[str], *, dtype: torch.dtype | None = None, device: torch.device | str | None = None
) -> StablePrimitive:
    """Load any primitive saved with :meth:`StablePrimitive.save` (LPVDS or SEDS, chosen by the file's ``kind``)."""
    import lfd_torch.ds  # noqa: F401  (registers the subclasses)

    return StablePrimitive.load(path, dtype=dtype, device=device)


def check_velocity_covariances(S: Tensor, name: str = "velocity_covariances") -> None:
    """Raise ShapeMismatchError (naming ``name``) unless the finite (K, d, d) S is symmetric (to rtol 1e-6) and positive
    definite (the smallest eigenvalue of its symmetric part > 0, in float64)."""
    Sv = S.to(torch.float64)
    if not torch.allclose(Sv, Sv.transpose(-2, -1), rtol=1e-6, atol=0.0):
        raise ShapeMismatchError(f"{name} must be symmetric positive definite (each S_k equal to its transpose)")
    low = torch.linalg.eigvalsh(0.5 * (Sv + Sv.transpose(-2, -1)))[..., 0]
    if bool((low <= 0).any()):
        k = int(torch.nonzero(low <= 0)[0])
        raise ShapeMismatchError(f"{name} must be symmetric positive definite; S_{k} has the eigenvalue "
                                 f"{float(low[k]):.3g}")  # fmt: skip


def residual_velocity_covariances(
    gamma: Tensor, x: Tensor, x_dot: Tensor, A: Tensor, attractor: Tensor, *, prior_weight: float = 1.0
) -> Tensor:
    """Responsibility-weighted covariance of the velocity residual x_dot - A_k (x - g) of each component.

    Each covariance is shrunk towards the pooled residual covariance of the whole model with ``prior_weight``
    pseudo-samples (plus a 1e-9 relative diagonal load), so components with little mass stay positive definite.

    Args:
        gamma: (N, K) responsibilities.
        x: (N, d) positions.
        x_dot: (N, d) velocities.
        A: (K, d, d) system matrices.
        attractor: (d,) goal.
        prior_weight: pseudo-sample weight of the pooled covariance.

    Returns:
        (K, d, d) symmetric positive-definite covariances ((units/s)^2).

    Raises:
        ShapeMismatchError / NonFiniteError / TooFewSamplesError: inputs of the wrong shapes, not finite, or empty.
        InvalidArgumentError: ``gamma`` with negative entries, or ``prior_weight`` not a finite number > 0.
    """
    check_samples(x, x_dot, min_samples=1)
    N, d = x.shape
    check_tensor(gamma, "gamma", ndim=2, dtype=x.dtype, device=x.device, shape_hint="(N, K)")
    K = gamma.shape[1]
    if gamma.shape[0] != N or K == 0:
        raise ShapeMismatchError(f"gamma must have shape ({N}, K >= 1), got {tuple(gamma.shape)}")
    if bool((gamma < 0).any()):
        raise InvalidArgumentError("gamma: responsibilities must be >= 0")
    check_tensor(A, "A", dtype=x.dtype, device=x.device, shape_hint=f"({K}, {d}, {d})")
    if A.shape != (K, d, d):
        raise ShapeMismatchError(f"A must have shape ({K}, {d}, {d}) (K from gamma), got {tuple(A.shape)}")
    check_tensor(attractor, "attractor", ndim=1, last_dim=d, dtype=x.dtype, device=x.device, shape_hint=f"({d},)")
    check_float(prior_weight, "prior_weight", low=0.0, low_open=True)
    e = x - attractor
    r = x_dot.unsqueeze(-2) - torch.einsum("kij,nj->nki", A, e)  # (N, K, d)
    outer = r.unsqueeze(-1) * r.unsqueeze(-2)  # (N, K, d, d)
    weighted = torch.einsum("nk,nkij->kij", gamma, outer)
    f_res = (gamma.unsqueeze(-1) * r).sum(1)  # residual of the full model, (N, d)
    pooled = f_res.T @ f_res / x.shape[0]
    eye = torch.eye(d, dtype=x.dtype, device=x.device)
    scale = float((x_dot * x_dot).sum(-1).mean()) / d or 1.0
    pooled = pooled + 1e-9 * scale * eye
    cov = (weighted + prior_weight * pooled) / (gamma.sum(0) + prior_weight)[:, None, None]
    return 0.5 * (cov + cov.transpose(-2, -1))
