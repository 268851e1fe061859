"""Physically-consistent Bayesian non-parametric GMM (PC-GMM; Figueroa & Billard, CoRL 2018).

Model. Every sample i picks a *customer link* c_i in {1..M} under a distance-dependent CRP prior
(Blei & Frazier 2011)

    p(c_i = j) ∝ alpha      if j = i,
                 S_ij       otherwise,   S_ij = exp(-||x_i - x_j|| / length_scale) (1 + cos(x_dot_i, x_dot_j)),

so points link to nearby points that move in the same direction (S_ij = 0 for opposite velocities). In
the paper's notation S_ij = exp(-l ||x_i - x_j||)(...) with l = 1 / length_scale. Tables (clusters) are
the connected components of the link graph. Each table's positions are Gaussian with a Normal-inverse-
Wishart (NIW) base measure that is integrated out; the number of components K is inferred.

Inference: collapsed Gibbs sampling over the links (exact for the model above; the test suite checks the
chain's partition frequencies against full enumeration on a small problem). Removing c_i splits i's table
iff i was not on the table's cycle (found by a search over reverse links). The conditional of c_i = j is
S_ij times, when j sits in another table T, the ratio p(T_i ∪ T) / (p(T_i) p(T)) of NIW marginal
likelihoods. Tables keep their sufficient statistics (count, sum, sum of outer products), so each ratio is
an O(d^3) closed form evaluated once per live table (not per point), and c_i is drawn over all points in
one vectorised step. The sequential sampler runs in float64 numpy on the CPU; all random numbers come
from ``generator``. The state with the highest joint log posterior over ``n_iter`` sweeps (MAP sample) is
kept; clusters with fewer than ``min_cluster_size`` samples are then merged into the cluster with the
nearest mean, and the returned GMM is the maximum-likelihood fit of that partition (plus a small relative
diagonal loading ``reg_covar``).

Defaults and approximations (documented choices of this implementation):
    * length_scale (data units) defaults to ``LENGTH_SCALE_FACTOR`` = 0.25 x the RMS distance of the samples to
      their mean (:func:`default_length_scale`), i.e. a quarter of the data's radius. Figueroa & Billard's
      implementation also derives it from the data (from the mode of the pairwise distances); the RMS radius is
      used here because the mode of the distance histogram of a few curves is erratic (on LASA it ranges from
      0.4x to 2x the RMS radius). The factor was selected by leave-one-demonstration-out cross-validation of
      LPV-DS (P-QLF) on the *training* demonstrations (0-3, every 2nd sample) of all 30 LASA shapes, from
      {2, 1, 0.5, 0.25, 0.125} (with ``nu0_offset`` = 2): the number of shapes whose held-out RMSE and mean
      |1 - cos| were both no worse than SEDS's rose from 16 of 30 at 2 to 20 at 1, 22-23 at 0.5 and 25-26 at 0.25
      (two seeds), then levelled off (25 at 0.125; the former defaults, 2 with ``nu0_offset`` = 10: 12 of 30).
      The largest scale on that plateau (fewer components: K about 7 on LASA against 9 at 0.125) is the default.
      Longer scales tie whole stretches of the trajectories together and the direction term alone must separate
      the regimes, which merges curved stretches into one linear system; they suit data that fill a region
      uniformly (the three-regime field of the tests recovers its regimes at 2 x the RMS radius).
    * NIW prior in standardised coordinates (data centred and divided by its overall RMS standard
      deviation): mu0 = 0, kappa0 = ``kappa0``, nu0 = d + ``nu0_offset``, Psi0 = (nu0 - d - 1)
      ``psi_scale``^2 I, i.e. a prior mean cluster covariance of (``psi_scale`` x data std)^2 I with the
      weight of ``nu0_offset`` pseudo-observations. The default ``nu0_offset`` = 2 is the weakest prior whose
      mean covariance exists (Psi0 = I, the data variance, as Figueroa & Billard's Lambda_0; they use nu0 = d).
      A strong prior (e.g. ``nu0_offset`` = 10) pulls every cluster towards the size of the whole data set and
      merges regimes (selected with the length scale by the cross-validation above).
    * Coarsening (the only approximation): with ``max_points`` set and N above it, the sampler runs on every
      ceil(N / max_points)-th sample (in the given order, i.e. along the trajectories), and every other
      sample takes the cluster of its most similar (largest S_ij) retained sample. ``max_points=None``
      runs on every sample (O(N^2) memory for the prior weights; about 2x slower per doubling of N).
    * Initial links are drawn from the prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from torch import Tensor

from lfd_torch.errors import ShapeMismatchError
from lfd_torch.gmm.model import NOT_GIVEN, GMM, InvalidGMMError, _gmm_from_dense_labels, check_samples
from lfd_torch.gmm.niw import NIWPrior, niw_log_marginal_likelihood, niw_log_marginal_normalizer
from lfd_torch.gmm.postprocess import merge_small_components
from lfd_torch.utils import check_cost, check_float, check_generator, check_int

__all__ = [
    "fit_pcgmm", "pcgmm_labels", "PCGMMResult", "prior_weights", "default_length_scale", "MIN_SAMPLES_PCGMM",
    "LENGTH_SCALE_FACTOR",
]

MIN_SAMPLES_PCGMM = 3

#: Bounds that keep the sampler's cost finite: Gibbs sweeps, and samples it keeps (M^2 similarities).
MAX_SWEEPS = 10_000
MAX_SAMPLER_POINTS = 10_000

#: Default similarity length scale as a multiple of the RMS distance of the samples to their mean (module docstring).
LENGTH_SCALE_FACTOR = 0.25


@dataclass(frozen=True)
class PCGMMResult:
    """Outcome of the sampler on the (possibly coarsened) samples.

    Attributes:
        labels: (N,) int64 cluster of every input sample (after merging small clusters), 0..K-1.
        log_posterior: (n_iter,) float64 joint log posterior (up to a constant) after every sweep.
        n_tables: (n_iter,) number of tables after every sweep.
        length_scale: the length scale used (data units).
        sample_index: (M,) indices of the samples the sampler ran on.
    """

    labels: Tensor
    log_posterior: Tensor
    n_tables: Tensor
    length_scale: float
    sample_index: Tensor


def _in_tree(root: int, children: list[list[int]]) -> list[int]:
    """Nodes whose link path reaches ``root`` (root included), by breadth-first search over reverse links."""
    out = [root]
    k = 0
    while k < len(out):
        out.extend(children[out[k]])
        k += 1
    return out


def _flat_features(y: np.ndarray) -> np.ndarray:
    """Per-point sufficient statistics [1, y (d), upper triangle of y y^T (row-major)], shape (M, p)."""
    M, d = y.shape
    iu = np.triu_indices(d)
    outer = (y[:, :, None] * y[:, None, :])[:, iu[0], iu[1]]
    return np.concatenate([np.ones((M, 1)), y, outer], axis=1)


def _unflatten(F: np.ndarray, d: int) -> tuple[Tensor, Tensor, Tensor]:
    """Statistics rows F (m, p) of :func:`_flat_features` as tensors: counts (m,), sums (m, d), outer (m, d, d)."""
    Ft = torch.as_tensor(F, dtype=torch.float64)
    iu = torch.triu_indices(d, d, device=Ft.device)
    outer = torch.zeros(F.shape[0], d, d, dtype=torch.float64, device=Ft.device)
    outer[:, iu[0], iu[1]] = Ft[:, 1 + d :]
    outer[:, iu[1], iu[0]] = Ft[:, 1 + d :]
    return Ft[:, 0], Ft[:, 1 : 1 + d], outer


class _LogMarginal:
    """NIW log marginal likelihood (:func:`~lfd_torch.gmm.niw.niw_log_marginal_likelihood`) of flat statistics
    rows [n, s, triu(Q)] under a prior with mean 0 and scale Psi0 = c I.

    The sampler scores every live table for every point, and one tensor call costs more than a whole update, so
    the per-candidate path splits the marginal as c(n) - nu_n / 2 log|Psi_n| (:mod:`lfd_torch.gmm.niw`): c(n) is
    tabulated once by :func:`~lfd_torch.gmm.niw.niw_log_marginal_normalizer`, and only the determinant of
    Psi_n = c I + Q - s s^T / kappa_n is written out, in Python floats, for d <= 3. Larger d and batches call the
    tensor kernel.
    """

    def __init__(self, prior: NIWPrior, n_max: int):
        self.prior = prior
        self.d = prior.dim
        self.c = float(prior.scale[0, 0])
        self.kappa0 = float(prior.kappa)
        self.nu0 = float(prior.dof)
        counts = torch.arange(n_max + 1, dtype=torch.float64, device=prior.mean.device)
        self.const = niw_log_marginal_normalizer(prior, counts).tolist()

    def batch(self, F: np.ndarray) -> np.ndarray:
        """Log marginals (m,) of statistics rows F (m, p), through the tensor kernel."""
        return niw_log_marginal_likelihood(self.prior, *_unflatten(F, self.d)).numpy()

    def merged(self, a: list[float], b: list[float]) -> float:
        """Log marginal of the union of two tables with statistics rows ``a`` and ``b``."""
        if self.d != 2:
            return self([p + q for p, q in zip(a, b)])
        c = self.c
        n = a[0] + b[0]
        kn = self.kappa0 + n
        s0 = a[1] + b[1]
        s1 = a[2] + b[2]
        p00 = c + a[3] + b[3] - s0 * s0 / kn
        p01 = a[4] + b[4] - s0 * s1 / kn
        p11 = c + a[5] + b[5] - s1 * s1 / kn
        return self.const[int(n)] - (self.nu0 + n) / 2 * math.log(p00 * p11 - p01 * p01)

    def __call__(self, f: list[float]) -> float:
        d, c = self.d, self.c
        n = f[0]
        kn = self.kappa0 + n
        if d == 1:
            det = c + f[2] - f[1] * f[1] / kn
        elif d == 2:
            s0, s1 = f[1], f[2]
            p00 = c + f[3] - s0 * s0 / kn
            p01 = f[4] - s0 * s1 / kn
            p11 = c + f[5] - s1 * s1 / kn
            det = p00 * p11 - p01 * p01
        elif d == 3:
            s0, s1, s2 = f[1], f[2], f[3]
            a = c + f[4] - s0 * s0 / kn
            b = f[5] - s0 * s1 / kn
            e = f[6] - s0 * s2 / kn
            g = c + f[7] - s1 * s1 / kn
            h = f[8] - s1 * s2 / kn
            k = c + f[9] - s2 * s2 / kn
            det = a * (g * k - h * h) - b * (b * k - h * e) + e * (b * h - g * e)
        else:
            return float(self.batch(np.asarray([f]))[0])
        return self.const[int(n)] - (self.nu0 + n) / 2 * math.log(det)


def _ddcrp_gibbs(
    y: np.ndarray,
    weights: np.ndarray,
    prior: NIWPrior,
    n_iter: int,
    generator: torch.Generator,
    trace: list[np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Collapsed Gibbs sampler over customer links with a dense ddCRP prior.

    Each update removes c_i (splitting i's table when i was not on its cycle), evaluates the NIW ratio
    p(T_i ∪ T) / (p(T_i) p(T)) once per live table T (1 for i's own table), and draws the new target j over
    all points with probability ∝ S_ij x ratio(table of j) in one vectorised step (exact Gibbs conditional).

    Args:
        y: (M, d) standardised positions.
        weights: (M, M) prior link weights, weights[i, j] = S_ij (j != i) and weights[i, i] = alpha.
        prior: NIW prior in the coordinates of y (mu0 = 0, isotropic Psi0).
        n_iter: number of sweeps.
        generator: source of the random numbers (link initialisation, visiting orders, uniforms).
        trace: if given, the table labels after every sweep are appended to it (for tests).

    Returns:
        (MAP table labels (M,), log posterior per sweep (n_iter,), tables per sweep (n_iter,)).
    """
    M, d = y.shape
    lm = _LogMarginal(prior, M)
    feats = _flat_features(y)
    with np.errstate(divide="ignore"):
        log_w = np.log(weights)
    # initial links drawn from the prior
    u0 = torch.rand(M, dtype=torch.float64, generator=generator, device=generator.device).cpu().numpy()
    cdf = np.cumsum(weights, 1)
    links = np.minimum((cdf <= (u0 * cdf[:, -1])[:, None]).sum(1), M - 1)
    links = np.where(weights[np.arange(M), links] > 0, links, np.arange(M)).tolist()
    children: list[list[int]] = [[] for _ in range(M)]
    for i in range(M):
        if links[i] != i:
            children[links[i]].append(i)
    # tables = connected components of the undirected link graph
    graph = coo_matrix((np.ones(M), (np.arange(M), np.asarray(links))), shape=(M, M))
    _, table = connected_components(graph, directed=False)
    table = table.astype(np.int64)
    F = np.zeros((M, feats.shape[1]))
    np.add.at(F, table, feats)
    logml_arr = np.zeros(M)
    live0 = F[:, 0] > 0
    logml_arr[live0] = lm.batch(F[live0])
    Fl = F.tolist()  # Python mirror of F: the per-update scoring runs on floats, not small arrays
    logml = logml_arr.tolist()
    live = sorted(set(table.tolist()))
    free = [t for t in range(M - 1, -1, -1) if t not in set(live)]
    buf = np.zeros(M)  # per-table factor exp(ratio - max), indexed by table id

    lp_hist = np.empty(n_iter)
    nt_hist = np.empty(n_iter, dtype=np.int64)
    best_lp = -math.inf
    best_table = table.copy()
    exp = math.exp
    dev = generator.device
    for sweep in range(n_iter):
        order = torch.randperm(M, generator=generator, device=dev).tolist()
        uni = torch.rand(M, dtype=torch.float64, generator=generator, device=dev).tolist()
        for step in range(M):
            i = order[step]
            old = links[i]
            t = int(table[i])
            if old != i:
                children[old].remove(i)
                sub = _in_tree(i, children)
                if len(sub) < Fl[t][0]:  # i was not on the table's cycle: the table splits
                    tn = free.pop()
                    sub_idx = np.asarray(sub)
                    table[sub_idx] = tn
                    fs = feats[sub_idx].sum(0)
                    F[tn] = fs
                    F[t] -= fs
                    Fl[tn] = F[tn].tolist()
                    Fl[t] = F[t].tolist()
                    logml[tn] = lm(Fl[tn])
                    logml[t] = lm(Fl[t])
                    live.append(tn)
                    t = tn
            # P(c_i = j) ∝ S_ij * ratio(table of j): one draw over all points, with the NIW ratio
            # p(T_i ∪ T) / (p(T_i) p(T)) evaluated once per live table T (1 for i's own table)
            ft = Fl[t]
            lt = logml[t]
            rs = []
            for T in live:
                if T == t:
                    rs.append(0.0)
                else:
                    rs.append(lm.merged(Fl[T], ft) - logml[T] - lt)
            rmax = max(rs)
            buf[live] = [exp(r - rmax) for r in rs]
            w_i = weights[i]
            cum = (w_i * buf[table]).cumsum()
            j = min(int(cum.searchsorted(uni[step] * cum[-1], side="right")), M - 1)
            if w_i[j] <= 0:  # guard against rounding at a zero-weight boundary
                j = int(np.argmax(w_i * buf[table]))
            T = int(table[j])
            links[i] = j
            if j != i:
                children[j].append(i)
            if T != t:  # merge table t into T
                table[table == t] = T
                F[T] += F[t]
                F[t] = 0.0
                Fl[T] = F[T].tolist()
                Fl[t] = F[t].tolist()
                logml[T] = lm(Fl[T])
                live.remove(t)
                free.append(t)
        lp = float(log_w[np.arange(M), links].sum()) + sum(logml[T] for T in live)
        lp_hist[sweep] = lp
        nt_hist[sweep] = len(live)
        if trace is not None:
            trace.append(table.copy())
        if lp > best_lp:
            best_lp = lp
            best_table = table.copy()
    return best_table, lp_hist, nt_hist


def prior_weights(x: Tensor, x_dot: Tensor, length_scale: float, alpha: float) -> Tensor:
    """Dense ddCRP link weights (M, M): S_ij = exp(-||x_i - x_j|| / length_scale) (1 + cos(x_dot_i, x_dot_j))
    off the diagonal, alpha on it. Velocities with zero norm get cos = 0 (neutral)."""
    speed = torch.linalg.vector_norm(x_dot, dim=-1, keepdim=True)
    unit = torch.where(speed > 0, x_dot / speed.clamp_min(torch.finfo(x.dtype).tiny), torch.zeros_like(x_dot))
    cos = (unit @ unit.T).clamp(-1.0, 1.0)
    S = torch.exp(-torch.cdist(x, x) / length_scale) * (1.0 + cos)
    S.fill_diagonal_(float(alpha))
    return S


def default_length_scale(x: Tensor) -> float:
    """Data-driven similarity length scale: ``LENGTH_SCALE_FACTOR`` (0.25) times the RMS distance of the samples
    to their mean (data units); 1 when the samples coincide.

    Args:
        x: (N, d) positions (data units).

    Returns:
        The length scale (data units). See the module docstring for how the factor was chosen."""
    rms = float(((x - x.mean(0)) ** 2).sum(-1).mean().sqrt())
    return LENGTH_SCALE_FACTOR * rms if rms > 0 else 1.0


def check_pcgmm_hyperparameters(
    *, length_scale: object, alpha: object, kappa0: object, nu0_offset: object, psi_scale: object, n_iter: object,
    min_cluster_size: object, max_points: object, reg_covar: object = NOT_GIVEN,
) -> None:  # fmt: skip
    """The checks of :func:`pcgmm_labels` / :func:`fit_pcgmm` on their hyperparameters, without the data (also run
    by :class:`~lfd_torch.gmm.PCGMMFitter` at construction); ``reg_covar`` is checked when given.

    Raises:
        InvalidGMMError: naming the first hyperparameter of the wrong type or out of range.
    """
    if reg_covar is not NOT_GIVEN:
        check_float(reg_covar, "reg_covar", low=0.0, error=InvalidGMMError)
    for name, v in (("alpha", alpha), ("kappa0", kappa0), ("psi_scale", psi_scale), ("nu0_offset", nu0_offset)):
        check_float(v, name, low=0.0, low_open=True, error=InvalidGMMError)
    check_int(n_iter, "n_iter", low=1, high=MAX_SWEEPS, error=InvalidGMMError)
    check_int(max_points, "max_points", low=MIN_SAMPLES_PCGMM, high=MAX_SAMPLER_POINTS, allow_none=True,
              error=InvalidGMMError)  # fmt: skip
    check_int(min_cluster_size, "min_cluster_size", low=1, allow_none=True, error=InvalidGMMError)
    check_float(length_scale, "length_scale", low=0.0, low_open=True, allow_none=True, error=InvalidGMMError)


def pcgmm_labels(
    x: Tensor,
    x_dot: Tensor,
    *,
    generator: torch.Generator,
    length_scale: float | None = None,
    alpha: float = 1.0,
    kappa0: float = 1.0,
    nu0_offset: float = 2.0,
    psi_scale: float = 1.0,
    n_iter: int = 20,
    min_cluster_size: int | None = None,
    max_points: int | None = 500,
) -> PCGMMResult:
    """Cluster labels of PC-GMM (see the module docstring for the model and every hyperparameter).

    Args:
        x: (N, d) positions (data units).
        x_dot: (N, d) velocities (data units / s).
        generator: torch generator (any device; its draws are moved to the CPU sampler).
        length_scale: similarity length scale in data units (None: :func:`default_length_scale`).
        alpha: ddCRP self-link weight (> 0); larger values give more clusters.
        kappa0, nu0_offset, psi_scale: NIW prior (standardised coordinates).
        n_iter: Gibbs sweeps, in [1, 10000]; each costs O(M^2) for the M <= max_points retained samples.
        min_cluster_size: clusters smaller than this are merged into the nearest one
            (None: max(3, 1 % of N)).
        max_points: coarsen to at most this many samples for the sampler, in [3, 10000] (None: no coarsening; N
            must then be <= 10000, since the similarities take M^2 floats).

    Returns:
        :class:`PCGMMResult`.

    Raises:
        ShapeMismatchError, NonFiniteError, TooFewSamplesError: malformed ``x`` or ``x_dot``.
        InvalidArgumentError: a hyperparameter of the wrong type or out of range, or no generator.
    """
    if x_dot is None:
        raise ShapeMismatchError("x_dot (N, d) velocities are required, got None")
    check_samples(x, x_dot, min_samples=MIN_SAMPLES_PCGMM)
    check_generator(generator, where="PC-GMM")
    check_pcgmm_hyperparameters(length_scale=length_scale, alpha=alpha, kappa0=kappa0, nu0_offset=nu0_offset,
                                psi_scale=psi_scale, n_iter=n_iter, min_cluster_size=min_cluster_size,
                                max_points=max_points)  # fmt: skip
    n_kept = x.shape[0] if max_points is None else min(x.shape[0], max_points)
    check_cost("max_points", float(n_kept) ** 2, float(MAX_SAMPLER_POINTS) ** 2, "pairwise similarities")
    N, d = x.shape
    xc = x.detach().to(device="cpu", dtype=torch.float64)
    vc = x_dot.detach().to(device="cpu", dtype=torch.float64)
    stride = 1 if max_points is None else max(1, math.ceil(N / int(max_points)))
    keep = torch.arange(0, N, stride)
    xs, vs = xc[keep], vc[keep]
    ls = default_length_scale(xs) if length_scale is None else float(length_scale)
    W = prior_weights(xs, vs, ls, float(alpha))
    center = xs.mean(0)
    scale = float(xs.std(0, unbiased=False).pow(2).mean().sqrt())
    scale = scale if scale > 0 else 1.0
    y = ((xs - center) / scale).numpy()
    nu0 = d + float(nu0_offset)
    f64 = dict(dtype=torch.float64, device=xc.device)
    prior = NIWPrior(
        mean=torch.zeros(d, **f64), kappa=torch.tensor(float(kappa0), **f64), dof=torch.tensor(nu0, **f64),
        scale=torch.eye(d, **f64) * max(nu0 - d - 1.0, 1e-3) * float(psi_scale) ** 2,
    )  # fmt: skip
    table, lp_hist, nt_hist = _ddcrp_gibbs(y, W.numpy(), prior, int(n_iter), generator)
    _, z = np.unique(table, return_inverse=True)
    z_t = torch.as_tensor(z, dtype=torch.long)
    if stride > 1:  # every sample takes the cluster of its most similar retained sample
        speed_all = torch.linalg.vector_norm(vc, dim=-1, keepdim=True)
        speed_s = torch.linalg.vector_norm(vs, dim=-1, keepdim=True)
        ua = torch.where(speed_all > 0, vc / speed_all.clamp_min(1e-300), torch.zeros_like(vc))
        us = torch.where(speed_s > 0, vs / speed_s.clamp_min(1e-300), torch.zeros_like(vs))
        best = []
        for a in range(0, N, 2048):
            logS = -torch.cdist(xc[a : a + 2048], xs) / ls + torch.log1p((ua[a : a + 2048] @ us.T).clamp(-1, 1))
            best.append(logS.argmax(1))
        z_all = z_t[torch.cat(best)]
        z_all[keep] = z_t
    else:
        z_all = z_t
    min_size = max(3, math.ceil(0.01 * N)) if min_cluster_size is None else int(min_cluster_size)
    z_all = merge_small_components(xc, z_all, max(1, min_size))
    return PCGMMResult(
        labels=z_all.to(x.device),
        log_posterior=torch.as_tensor(lp_hist),
        n_tables=torch.as_tensor(nt_hist),
        length_scale=ls,
        sample_index=keep,
    )


def fit_pcgmm(
    x: Tensor,
    x_dot: Tensor,
    *,
    generator: torch.Generator,
    length_scale: float | None = None,
    alpha: float = 1.0,
    kappa0: float = 1.0,
    nu0_offset: float = 2.0,
    psi_scale: float = 1.0,
    n_iter: int = 20,
    min_cluster_size: int | None = None,
    max_points: int | None = 500,
    reg_covar: float = 1e-3,
) -> GMM:
    """Fit a PC-GMM to positions ``x`` with velocities ``x_dot``; K is inferred.

    Args:
        x: (N, d) positions (data units), N >= 3.
        x_dot: (N, d) velocities.
        generator: torch generator (any device); the only source of randomness.
        length_scale, alpha, kappa0, nu0_offset, psi_scale, n_iter, min_cluster_size, max_points:
            see :func:`pcgmm_labels` and the module docstring.
        reg_covar: relative diagonal loading of the final covariances (times the mean data variance).

    Returns:
        :class:`GMM` (same dtype/device as ``x``) fitted by maximum likelihood to the MAP partition.

    Raises:
        ShapeMismatchError, NonFiniteError, TooFewSamplesError: malformed input.
        InvalidGMMError: invalid hyperparameters.
    """
    check_float(reg_covar, "reg_covar", low=0.0, error=InvalidGMMError)
    res = pcgmm_labels(
        x, x_dot, generator=generator, length_scale=length_scale, alpha=alpha, kappa0=kappa0,
        nu0_offset=nu0_offset, psi_scale=psi_scale, n_iter=n_iter, min_cluster_size=min_cluster_size,
        max_points=max_points,
    )  # fmt: skip
    return _gmm_from_dense_labels(x, res.labels, reg_covar)
