"""Post-processing of fitted mixtures: component ordering and covariance regularisation.

Notation: K components in d dimensions; g (d,) the attractor of the dynamical system.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError
from lfd_torch.gmm.model import GMM, InvalidGMMError, check_samples
from lfd_torch.utils import check_float, check_int, real_array

__all__ = ["order_by_attractor", "regularize_covariances", "merge_small_components"]


def order_by_attractor(gmm: GMM, attractor: Tensor) -> GMM:
    """Reorder the components by increasing Euclidean distance ||mu_k - g|| of their means to the attractor.

    The density is unchanged; ties keep the original order (stable sort).

    Args:
        gmm: mixture with K components.
        attractor: (d,) goal g, same dtype/device as the mixture.

    Returns:
        A new :class:`GMM` whose component 0 is the closest to g.

    Raises:
        InvalidArgumentError: ``gmm`` is not a GMM. ShapeMismatchError: ``attractor`` is not a real (d,) vector.
        NonFiniteError: ``attractor`` holds NaN or Inf.
    """
    _check_gmm(gmm)
    if not isinstance(attractor, Tensor):
        attractor = real_array(attractor, "attractor")
    elif attractor.is_complex():
        raise ShapeMismatchError(f"attractor must hold real numbers, got {attractor.dtype}")
    g = torch.as_tensor(attractor, dtype=gmm.dtype, device=gmm.device)
    if g.shape != (gmm.dim,):
        raise ShapeMismatchError(f"attractor must have shape ({gmm.dim},), got {tuple(g.shape)}")
    if not torch.isfinite(g).all():
        raise NonFiniteError("attractor is not finite")
    dist = torch.linalg.vector_norm(gmm.means - g, dim=-1)
    order = torch.sort(dist, stable=True).indices
    return GMM(gmm.weights[order], gmm.means[order], gmm.covariances[order])


def _check_gmm(gmm: object) -> None:
    if not isinstance(gmm, GMM):
        raise InvalidArgumentError(f"gmm must be a GMM, got {type(gmm).__name__}")


def regularize_covariances(gmm: GMM, min_eig_ratio: float = 1e-2, *, min_eig: float = 0.0) -> GMM:
    """Floor the eigenvalues of thin covariances.

    For each component, eigenvalues below ``max(min_eig_ratio * lambda_max, min_eig)`` are raised to that
    floor, where lambda_max is the component's largest eigenvalue; eigenvectors (orientations), means and
    weights are unchanged. Thin (nearly degenerate) clusters otherwise give near-singular covariances, whose
    posteriors gamma_k(x) switch abruptly across them, which makes the LPV-DS scheduling stiff.

    Args:
        gmm: mixture.
        min_eig_ratio: relative floor in [0, 1] (condition numbers are capped at 1 / min_eig_ratio).
        min_eig: absolute floor in data units squared (>= 0).

    Returns:
        A new :class:`GMM`.

    Raises:
        InvalidGMMError: ``min_eig_ratio`` outside [0, 1], ``min_eig`` negative or not finite (naming it).
        InvalidArgumentError: ``gmm`` is not a GMM.
    """
    _check_gmm(gmm)
    min_eig_ratio = check_float(min_eig_ratio, "min_eig_ratio", low=0.0, high=1.0, error=InvalidGMMError)
    min_eig = check_float(min_eig, "min_eig", low=0.0, error=InvalidGMMError)
    evals, evecs = torch.linalg.eigh(gmm.covariances)
    floor = torch.clamp_min(min_eig_ratio * evals[..., -1:], float(min_eig))
    evals = torch.maximum(evals, floor)
    cov = (evecs * evals.unsqueeze(-2)) @ evecs.transpose(-2, -1)
    return GMM(gmm.weights, gmm.means, 0.5 * (cov + cov.transpose(-2, -1)))


def merge_small_components(x: Tensor, labels: Tensor, min_size: int) -> Tensor:
    """Reassign the points of clusters with fewer than ``min_size`` points to the nearest remaining cluster.

    "Nearest" is measured from each point of a small cluster to the means of the kept clusters (Euclidean).
    If no cluster reaches ``min_size``, the largest one is kept.

    Args:
        x: (N, d) samples.
        labels: (N,) int64 labels in 0..K-1.
        min_size: smallest cluster size kept (>= 1).

    Returns:
        (N,) int64 labels, densely renumbered 0..K'-1 in increasing order of the kept clusters' labels.

    Raises:
        ShapeMismatchError, TooFewSamplesError, NonFiniteError: ``x`` is not a finite (N, d) tensor with N >= 1, or
            ``labels`` is not an integer (N,) tensor on x's device.
        InvalidArgumentError: a negative label, or ``min_size`` not an integer >= 1.
    """
    check_samples(x, min_samples=1)
    if not isinstance(labels, Tensor) or labels.is_floating_point() or labels.is_complex() \
            or labels.dtype == torch.bool:
        what = labels.dtype if isinstance(labels, Tensor) else type(labels).__name__
        raise ShapeMismatchError(f"labels must be an integer tensor of shape ({x.shape[0]},), got {what}")
    if labels.shape != (x.shape[0],) or labels.device != x.device:
        raise ShapeMismatchError(f"labels must have shape ({x.shape[0]},) on {x.device} (one per row of x), got "
                                 f"{tuple(labels.shape)} on {labels.device}")  # fmt: skip
    if bool((labels < 0).any()):
        raise InvalidArgumentError(f"labels must be >= 0, got {int(labels.min())}")
    check_int(min_size, "min_size", low=1)
    labels = labels.long()
    K = int(labels.max()) + 1
    counts = torch.bincount(labels, minlength=K)
    keep = counts >= min_size
    if not keep.any():
        keep = counts == counts.max()
        keep &= torch.cumsum(keep.long(), 0) == 1
    kept = torch.nonzero(keep).reshape(-1)
    sums = torch.zeros(K, x.shape[1], dtype=x.dtype, device=x.device).index_add_(0, labels, x)
    means = sums[kept] / counts[kept, None].to(x.dtype)
    out = labels.clone()
    small = ~keep[labels]
    if small.any():
        out[small] = kept[torch.cdist(x[small], means).argmin(-1)]
    _, dense = torch.unique(out, return_inverse=True)
    return dense
