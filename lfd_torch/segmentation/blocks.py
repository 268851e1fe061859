"""Block emission: the states' motion scored on block means of the positions (an option of the collapsed score).

Notation:
    B  labellings scored at once, N sequences, T padded grid length, M = T - 1 increments, K states, d dimension,
    p = d + 1
    xbar  (N, T, d)  standardised mean of the samples nearest each grid point (block j: the samples closer to grid
                     point j than to its neighbours, m_j of them)
    sbar  (N, T)     their mean path length (standardised units), ds_j = sbar_(j+1) - sbar_j
    var   (N, T)     the noise variance of a block mean per axis, sigma^2 / m_j

Why. The direction emission (:mod:`.field`) sees local least-squares slopes, one per grid point, as independent
observations. A straight leg's direction is then known to about sigma_dir / sqrt(n) from its n grid points, while
a line through the leg's samples knows it about n / 3 times better: the lever arm of the leg's length. On the
constant-speed benchmark families a known-count oracle that fits lines to the positions finds every switch where
the sampler misses mild corners between short legs and the scoop's hook (``experiments/oracle_switches.py``,
``experiments/segmentation_studies.md``, "A known-count oracle"). This module scores the same states on the block
means, where that lever arm is kept.

Model (per axis, the axes independent and alike). The increment Delta_j = xbar_(j+1) - xbar_j of two grid points
of one run of state k is the state's motion over ds_j plus the difference of the two blocks' noises:

    straight state   Delta_j = ds_j (b_k + b_ik) + e_(j+1) - e_j,   b_k ~ N(0, 1 / d), b_ik ~ N(0, omega^2)
    curved state     Delta_j = ds_j (B_k zbar_j + o_ik) + ds_j eta_j + e_(j+1) - e_j,   eta_j ~ N(0, sigma_u^2)

with e_j ~ N(0, var_j) the blocks' noise, b_ik and o_ik each demonstration's own small turn of the direction or
offset of the field, N(0, omega^2) per axis (its corners are its own; omega = ``spread``), B_k the affine field on
the midpoint regressors zbar_j = (z_j + z_(j+1)) / 2 under the field prior's scales (slope entries N(0, s^2), offset
N(0, 1); s may differ per state, as the sampler's profile over two scales sets it) and eta_j the direction
tolerance sigma_u of the curved states (a random walk of the position along the
run). A straight state has no tolerance: it is a line. An increment across a switch belongs to neither state: the
corner lies somewhere between the two grid points, so that increment is a free displacement, N(0, ds_j^2) per axis.
Which of the two a state is, is an argument here; the sampler starts from the direction emission's spike-and-slab
choice and switches one state at a time while the evidence rises (:meth:`~.sampler._Run._block_evidence`), a
profile over the components rather than the sum over the 2^K combinations. With the coefficients Gaussian, the
increments of all sequences are one Gaussian, y ~ N(0, Omega + X Lambda X^T), Omega block-diagonal per sequence and
tridiagonal (the shared block noise of consecutive increments), so the evidence is

    log p = -1/2 sum_a (y_a^T Omega^-1 y_a - c_a^T A^-1 c_a) - d / 2 (log|Omega| + log|Lambda| + log|A| + M log 2 pi),
    A = Lambda^-1 + X^T Omega^-1 X,   c_a = X^T Omega^-1 y_a.

The first block of every sequence (its start) is the same for every labelling and left out. Padded increments
(beyond a sequence's end) are unit-variance zeros, a constant.

Computation. Each demonstration's own coefficients (turns, offsets) appear in its rows alone, so they are integrated
out per sequence (a Schur complement of A), which leaves each sequence's share of the shared block of A and of c
(:class:`BlockTerms`, :func:`block_sequence_terms`); the shares of a labelling's sequences are summed and the shared
coefficients integrated out last (:func:`combine_block_terms`). A move of the map search that changes one sequence
recomputes that sequence's share alone. Omega's Cholesky factor is bidiagonal, so the whitening L^-1 [X, y] is a
recurrence along the increments, O(M) per column, and a sequence's columns are those of the states it uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError
from lfd_torch.segmentation.states import used_states

__all__ = ["BlockMeans", "BlockTerms", "block_means", "block_sequence_terms", "combine_block_terms",
           "block_log_evidence", "check_block_variances", "state_slots", "DEMO_SPREAD"]

#: omega, the prior scale (rad) of each demonstration's own turn of a straight state's direction: demonstrations put
#: their corners a few percent of a leg apart, which turns a leg by a few degrees (the benchmark's jitter, 2 % of the
#: shorter leg, turns it by up to about 3 degrees); without it one line for all demonstrations pays for every such
#: turn at the block noise's scale.
DEMO_SPREAD = 0.05


@dataclass(frozen=True, eq=False)
class BlockMeans:
    """Block means of N sequences on their grids, in the units of the positions.

    Attributes:
        means: N tensors (n_i, d), the mean of the samples nearest each grid point.
        lengths: N tensors (n_i,), their mean path length.
        counts: N tensors (n_i,), the number of samples in each block.
        noise: the position noise's standard deviation per axis (unit of the positions).
    """

    means: list[Tensor]
    lengths: list[Tensor]
    counts: list[Tensor]
    noise: float


def block_means(positions: Tensor, grid: Tensor, path_length: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Means (n, d), mean path lengths (n,) and sample counts (n,) of the blocks around the grid samples.

    Args:
        positions: (T, d) one sequence at full rate; grid: (n,) increasing sample indices; path_length: (T,)
            the path length at every sample.
    """
    T = positions.shape[0]
    if grid.ndim != 1 or path_length.shape != (T,):
        raise ShapeMismatchError(f"grid {tuple(grid.shape)} and path_length {tuple(path_length.shape)} do not fit "
                                 f"positions {tuple(positions.shape)}")
    edges = torch.cat([grid.new_zeros(1), torch.div(grid[1:] + grid[:-1] + 1, 2, rounding_mode="floor"),
                       grid.new_full((1,), T)])
    block = torch.bucketize(torch.arange(T, device=grid.device), edges[1:-1], right=True)  # (T,) block of a sample
    n = grid.shape[0]
    counts = torch.bincount(block, minlength=n).to(positions.dtype)
    means = positions.new_zeros(n, positions.shape[1]).index_add_(0, block, positions) / counts.unsqueeze(-1)
    lengths = path_length.new_zeros(n).index_add_(0, block, path_length) / counts
    return means, lengths, counts


@dataclass(frozen=True, eq=False)
class BlockTerms:
    """Sequences' shares of the block evidence (leading dims, e.g. (B, N); summed over a labelling's sequences they
    give its evidence, :func:`combine_block_terms`), each on the R states its sequence uses.

    Attributes:
        gram: (..., Qr, Qr) X_s^T Omega^-1 X_s less what the sequence's own columns explain (its Schur complement),
            Qr = R (1 + p) columns, per state [direction, p field coefficients].
        proj: (..., Qr, d) the same for X_s^T Omega^-1 y.
        const: (...) the sequence's own terms: -1/2 (y^T Omega^-1 y - c_l^T D^-1 c_l) summed over the axes,
            -d/2 (log|Omega| + log|D| + log|Lambda_l| + M log 2 pi).
        at: (..., Qr) long, the column of each among the K (1 + p) shared columns (distinct within a sequence).
        columns: K (1 + p).
    """

    gram: Tensor
    proj: Tensor
    const: Tensor
    at: Tensor
    columns: int

    def __getitem__(self, index) -> BlockTerms:
        """The shares at ``index`` of the leading dims."""
        return BlockTerms(self.gram[index], self.proj[index], self.const[index], self.at[index], self.columns)

    def add_to(self, gram: Tensor, proj: Tensor, const: Tensor, rows: Tensor, sign: float = 1.0) -> None:
        """Add (sign = -1: subtract) each share, one leading dim (E,), to the totals gram (P, Qk, Qk), proj (P, Qk,
        d), const (P,) at ``rows`` (E,), in place (contiguous totals). One ``index_add_`` on the flattened totals
        per tensor: about 3x faster on the CPU than ``index_put_`` with ``accumulate=True``."""
        at = self.at
        Qk, d = gram.shape[-1], proj.shape[-1]
        cell = (rows.view(-1, 1, 1) * Qk + at.unsqueeze(-1)) * Qk + at.unsqueeze(-2)  # (E, Qr, Qr)
        gram.view(-1).index_add_(0, cell.reshape(-1), self.gram.reshape(-1), alpha=sign)
        cell = (rows.view(-1, 1, 1) * Qk + at.unsqueeze(-1)) * d + torch.arange(d, device=at.device)  # (E, Qr, d)
        proj.view(-1).index_add_(0, cell.reshape(-1), self.proj.reshape(-1), alpha=sign)
        const.index_add_(0, rows, self.const, alpha=sign)

    def totals(self) -> tuple[Tensor, Tensor, Tensor]:
        """The (B, Qk, Qk), (B, Qk, d), (B,) sums over the second leading dim (the sequences of each labelling)."""
        B, N = self.const.shape
        Qk, d = self.columns, self.proj.shape[-1]
        out = (self.gram.new_zeros(B, Qk, Qk), self.proj.new_zeros(B, Qk, d), self.const.new_zeros(B))
        rows = torch.arange(B, device=self.const.device).repeat_interleave(N)
        BlockTerms(self.gram.flatten(0, 1), self.proj.flatten(0, 1), self.const.flatten(0, 1),
                   self.at.flatten(0, 1), Qk).add_to(*out, rows)
        return out


def state_slots(uses: Tensor) -> tuple[Tensor, Tensor]:
    """The slots of the states each row uses (``uses`` (..., K) bool): ``order`` (..., R), the used states first,
    by index (R the most any row uses, at least 1; a row using fewer is padded with unused states), and ``rank``
    (..., K) long, each used state's slot (an unused state's entry is meaningless: 0 or a padding slot)."""
    R = max(int(uses.sum(-1).max()), 1) if uses.numel() else 1
    order = torch.argsort((~uses).to(torch.uint8), dim=-1, stable=True)[..., :R]
    rank = torch.zeros(uses.shape, dtype=torch.long, device=uses.device)
    rank.scatter_(-1, order, torch.arange(R, device=uses.device).expand(*uses.shape[:-1], R))
    return order, rank


def block_sequence_terms(xbar: Tensor, sbar: Tensor, var: Tensor, zmid: Tensor, valid: Tensor, labels: Tensor,
                         straight: Tensor, *, tolerance: float, spread: float, slope_scale: float | Tensor) -> BlockTerms:
    """Each sequence's share of :func:`block_log_evidence` (same arguments; the data may also carry a leading
    batch dimension (B, N, ...), e.g. one sequence of a different demonstration per labelling). ``slope_scale``
    belongs to the shared coefficients' prior, applied by :func:`combine_block_terms`; it is accepted here so that
    both take the same options."""
    B, N, T = labels.shape
    K = straight.shape[-1]
    d = xbar.shape[-1]
    p = d + 1
    M = T - 1
    if xbar.ndim == 3:
        xbar, sbar, var, zmid, valid = (t.unsqueeze(0) for t in (xbar, sbar, var, zmid, valid))
    inc = valid[..., 1:] & valid[..., :-1]  # (1 or B, N, M)
    ds = (sbar[..., 1:] - sbar[..., :-1]).clamp_min(0.0) * inc
    y = (xbar[..., 1:, :] - xbar[..., :-1, :]) * inc.unsqueeze(-1)  # (1 or B, N, M, d)
    same = (labels[..., 1:] == labels[..., :-1]) & inc  # (B, N, M)
    switch = inc & ~same
    own = labels[..., 1:]
    is_straight = torch.gather(straight, 1, own.reshape(B, -1)).reshape(B, N, M) & same
    is_curved = same & ~is_straight
    # Omega: tridiagonal per sequence, the padded increments unit-variance
    diag = torch.where(inc, var[..., 1:] + var[..., :-1], torch.ones_like(ds)).expand(B, N, M)
    diag = diag + is_curved * (ds * tolerance) ** 2 + switch * ds**2
    # masked by where, not by a product: a padded block's variance is never read (NaN * 0 is NaN)
    both = inc[..., 1:] & inc[..., :-1]
    off = -torch.where(both, var[..., 1:-1], torch.zeros_like(var[..., 1:-1])).expand(B, N, M - 1)
    # X per sequence, only its nonzero columns, per state [direction, p field coefficients, the sequence's own turn,
    # its own offset]: each increment's row written into its own state's slot. The own columns of different
    # sequences never meet, so they are eliminated per sequence (a Schur complement) before the shared ones.
    # Only the R states a sequence uses get slots (R the most any sequence of the batch uses), in the order of
    # ``order`` (B, N, R); the shares are scattered back to the K states' columns at the end. The own turn's column
    # is the direction's (ds on the state's straight increments) and, when the last regressor is the constant 1 (the
    # sampler's [x~, 1]), the own offset's is the field offset's: only the u distinct columns of a slot are whitened
    # and multiplied (p + 1 of them, else p + 2), which halves the Gram's work on the plane (d = 2: 4 of 6).
    ones = bool((zmid[..., -1] == 1).all())
    u = p + 1 if ones else p + 2
    order, rank = state_slots(used_states(labels, valid, K))  # (B, N, R), (B, N, K)
    R = order.shape[-1]
    slot = torch.gather(rank, -1, own)  # (B, N, M) each increment's slot
    st, cu = is_straight * ds, is_curved * ds  # (B, N, M)
    row = torch.cat([st.unsqueeze(-1), cu.unsqueeze(-1) * zmid] + ([] if ones else [cu.unsqueeze(-1)]), -1)
    Q = R * u
    # [X, y] laid out along the increments first (M, B, N, Q + d), as the whitening recurrence steps through them
    Z = row.new_zeros(M, B, N, Q + d)
    Z[..., :Q].unflatten(-1, (R, u)).scatter_(3, slot.movedim(-1, 0).reshape(M, B, N, 1, 1).expand(M, B, N, 1, u),
                                              row.movedim(-2, 0).unsqueeze(3))
    Z[..., Q:] = y.movedim(-2, 0)
    logdet_omega = _tridiagonal_whiten(diag.movedim(-1, 0), off.movedim(-1, 0), Z)
    Zb = Z.view(M, B * N, Q + d).permute(1, 2, 0)  # (B N, Q + d, M)
    full_gram = (Zb @ Zb.transpose(-1, -2)).view(B, N, Q + d, Q + d)  # [W, v]^T [W, v]
    G, c = full_gram[..., :Q, :Q], full_gram[..., :Q, Q:]  # (B, N, Q, Q), (B, N, Q, d)
    vv = torch.diagonal(full_gram[..., Q:, Q:], dim1=-2, dim2=-1).sum(-1)  # (B, N)
    first = torch.arange(R, device=xbar.device).unsqueeze(-1) * u  # (R, 1) each slot's first column
    shared = (first + torch.arange(p + 1, device=xbar.device)).view(-1)  # direction, field
    local = (first + torch.tensor([0, u - 1], device=xbar.device)).view(-1)  # own turn, own offset
    Ql = local.numel()
    prior_l = xbar.new_full((Ql,), spread**2)
    Gl = G[..., local[:, None], local]
    chol_d = torch.linalg.cholesky(Gl + torch.diag(1.0 / prior_l))  # (B, N, Ql, Ql)
    C = G[..., shared[:, None], local]  # (B, N, Qs, Ql)
    cl = c[..., local, :]
    # W = L_D^-1 [C^T, c_l] (one triangular solve, 2-4x faster than cholesky_solve's two on these sizes): then
    # W^T W holds C D^-1 C^T, C D^-1 c_l and c_l^T D^-1 c_l
    W = torch.linalg.solve_triangular(chol_d, torch.cat([C.transpose(-1, -2), cl], -1), upper=False)
    WW = W.transpose(-1, -2) @ W  # (B, N, Qs + d, Qs + d)
    Qs = shared.numel()
    logdet = logdet_omega + 2.0 * torch.log(torch.diagonal(chol_d, dim1=-2, dim2=-1)).sum(-1)  # (B, N)
    const = (-0.5 * (vv - torch.diagonal(WW[..., Qs:, Qs:], dim1=-2, dim2=-1).sum(-1))
             - 0.5 * d * (logdet + torch.log(prior_l).sum() + M * math.log(2.0 * math.pi)))
    if not ones:  # the direction's and field's columns alone (with the ones, they are all of them)
        G, c = G[..., shared[:, None], shared], c[..., shared, :]
    gram = G - WW[..., :Qs, :Qs]  # (B, N, R (1 + p), R (1 + p))
    proj = c - WW[..., :Qs, Qs:]
    at = (order.unsqueeze(-1) * (1 + p) + torch.arange(1 + p, device=xbar.device)).view(B, N, Qs)
    return BlockTerms(gram=gram, proj=proj, const=const, at=at, columns=K * (1 + p))


def _tridiagonal_whiten(diag: Tensor, off: Tensor, Z: Tensor) -> Tensor:
    """Overwrite Z (M, ..., Q) with L^-1 Z and return log|Omega| (...), for the tridiagonal Omega (M x M per
    batch element) of diagonal ``diag`` (M, ...) and off-diagonal ``off`` (M - 1, ...), L its Cholesky factor (lower
    bidiagonal: l_j on the diagonal, m_j = off_j / l_j below it). Two recurrences along the M increments, one
    fused op per step each: the pivots l_j^2 = diag_j - off_{j-1}^2 / l_{j-1}^2, then, on Z scaled by 1 / l_j,
    Z_j <- Z_j - (m_{j-1} / l_j) Z_{j-1}. O(M Q) where the dense factor and solve are O(M^3 + M^2 Q); with LASA's
    M = 76 the loop is 3x faster than ``torch.linalg.cholesky`` and ``solve_triangular`` on the dense Omega (one-off
    timing, 32 x 7 sequences, 60 columns), and it needs no M x M matrix. The steps are small ops, so their number
    is what costs: the fused form takes a third of the ops of the plain one."""
    M = diag.shape[0]
    piv = torch.empty_like(diag)
    piv[0] = diag[0]
    off2 = off * off
    for j in range(M - 1):
        torch.addcdiv(diag[j + 1], off2[j], piv[j], value=-1.0, out=piv[j + 1])
    l = piv.sqrt()
    inv = l.reciprocal()
    gain = (-off * inv[:-1] * inv[1:]).unsqueeze(-1)  # -m_j / l_{j+1}
    Z.mul_(inv.unsqueeze(-1))
    for j in range(M - 1):
        Z[j + 1].addcmul_(gain[j], Z[j])
    return torch.log(piv).sum(0)


def combine_block_terms(gram: Tensor, proj: Tensor, const: Tensor, *, slope_scale: float | Tensor) -> Tensor:
    """(B,) the block evidence from the sequences' shares summed over them, gram (B, Qs, Qs), proj (B, Qs, d),
    const (B,): the shared coefficients integrated out under their prior Lambda_s. ``slope_scale``: s for every
    state, or (B, K) one per labelling and state (a straight state's is unused: its field columns are empty)."""
    Qs, d = proj.shape[-2:]
    K = Qs // (d + 2)
    scale = torch.as_tensor(slope_scale, dtype=gram.dtype, device=gram.device).expand(gram.shape[0], K)
    prior_s = torch.cat([torch.full_like(scale, 1.0 / d).unsqueeze(-1), (scale**2).unsqueeze(-1).expand(-1, K, d),
                         torch.ones_like(scale).unsqueeze(-1)], -1).flatten(-2)  # (B, Qs)
    chol_s = torch.linalg.cholesky(gram + torch.diag_embed(1.0 / prior_s))
    quad = torch.linalg.solve_triangular(chol_s, proj, upper=False).square().sum((-2, -1))  # proj^T A^-1 proj
    logdet = 2.0 * torch.log(torch.diagonal(chol_s, dim1=-2, dim2=-1)).sum(-1) + torch.log(prior_s).sum(-1)
    return const + 0.5 * quad - 0.5 * d * logdet


def block_log_evidence(xbar: Tensor, sbar: Tensor, var: Tensor, zmid: Tensor, valid: Tensor, labels: Tensor,
                       straight: Tensor, *, tolerance: float, spread: float, slope_scale: float | Tensor) -> Tensor:
    """(B,) log p(increments of the block means | labelling) (module docstring).

    Args:
        xbar: (N, T, d), sbar: (N, T), var: (N, T) block means, path lengths and noise variances (standardised).
        zmid: (N, M, p) midpoint regressors of the increments; valid: (N, T) bool.
        labels: (B, N, T) long states in [0, K); straight: (B, K) bool, the states scored as straight.
        tolerance: sigma_u of the curved states; spread: omega; slope_scale: s, or (B, K) one per state.
    """
    check_block_variances(var, valid)
    terms = block_sequence_terms(xbar, sbar, var, zmid, valid, labels, straight, tolerance=tolerance, spread=spread,
                                 slope_scale=slope_scale)
    return combine_block_terms(*terms.totals(), slope_scale=slope_scale)


def check_block_variances(var: Tensor, valid: Tensor) -> None:
    """Raise InvalidArgumentError unless every valid block's noise variance ``var`` is finite and positive (Omega
    must be positive definite; the whitening recurrence would otherwise give NaN silently)."""
    bad = valid & ~(torch.isfinite(var) & (var > 0))
    if bool(bad.any()):
        raise InvalidArgumentError(f"var: the block noise variances must be finite and > 0 ({int(bad.sum())} are not; "
                                   "is the position noise estimate 0?)")
