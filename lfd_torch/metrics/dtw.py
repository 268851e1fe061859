"""Dynamic time warping distance (DTWD) between pairs of trajectories, batched on an anti-diagonal wavefront.

Notation:
    B       number of trajectory pairs
    Ta, Tb  padded numbers of samples of the first and second trajectory of each pair
    d       state dimension (>= 1)
    a, b    (B, Ta, d), (B, Tb, d) positions, data units (LASA: mm)
    c(i, j) local cost between a_i and b_j: ||a_i - b_j|| (default) or ||a_i - b_j||^2 (``squared_cost``)
    D(i, j) accumulated cost, D(i, j) = c(i, j) + min(D(i-1, j), D(i, j-1), D(i-1, j-1)), D(0, 0) = c(0, 0)

Cells with equal i + j (an anti-diagonal) depend only on the two previous anti-diagonals, so the whole batch
advances one anti-diagonal per step: Ta + Tb - 1 steps of vectorised work, with only three anti-diagonals of
D (and one of c) in memory. Anti-diagonal k holds cells i = max(0, k-Tb+1) .. min(k, Ta-1), j = k - i; it is
stored in a buffer indexed by i + 1, whose first and last entries stay +inf (the borders i = -1 and i = Ta).
"""

from __future__ import annotations

import torch
from torch import Tensor

from lfd_torch.errors import ShapeMismatchError, TooFewSamplesError
from lfd_torch.metrics._checks import check_finite, check_lengths
from lfd_torch.utils import check_tensor

__all__ = ["dtw_distance"]

# On CPU the batch is cut into chunks of about this many cells per anti-diagonal, so that the working set
# (five rows of that size) stays in cache; measured best around 1e5 cells of float64.
_CPU_CELLS_PER_DIAGONAL = 1 << 17


def _check_pair(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    for name, x in (("a", a), ("b", b)):  # float32 / float64 (FLOAT_DTYPES); finiteness on valid samples later
        check_tensor(x, name, ndim=3, finite=False, shape_hint="(B, T, d)")
    if a.shape[0] != b.shape[0]:
        raise ShapeMismatchError(f"a holds {a.shape[0]} trajectories, b holds {b.shape[0]}")
    if a.shape[2] != b.shape[2]:
        raise ShapeMismatchError(f"a has state dimension {a.shape[2]}, b has {b.shape[2]}")
    if a.shape[2] < 1:
        raise ShapeMismatchError("state dimension must be at least 1")
    if a.device != b.device:
        raise ShapeMismatchError(f"a is on {a.device}, b on {b.device}")
    dtype = torch.promote_types(a.dtype, b.dtype)
    return a.to(dtype), b.to(dtype)


def dtw_distance(
    a: Tensor,
    b: Tensor,
    lengths_a: Tensor | None = None,
    lengths_b: Tensor | None = None,
    *,
    squared_cost: bool = False,
) -> Tensor:
    """Dynamic time warping distance of each pair (a[k], b[k]).

    Default (``squared_cost=False``): the DTWD of the LPV-DS literature, the sum of the Euclidean local costs
    ||a_i - b_j|| along the optimal warping path, with steps (i-1, j), (i, j-1), (i-1, j-1), both end points
    matched, no window and no normalisation by path length. ``squared_cost=True``: squared Euclidean local cost,
    summed along the optimal path, then the square root of the total; this is what
    ``dtaidistance.dtw_ndim.distance`` (and ``dtaidistance.dtw.distance`` for d = 1) computes with default
    options. Both are symmetric, >= 0, and zero for identical trajectories.

    Work is O(B Ta Tb) in Ta + Tb - 1 vectorised steps (no Python loop over pairs); memory is O(B (Ta + Tb) d).
    Padded samples (beyond ``lengths_a`` / ``lengths_b``) may hold any value, even NaN. The result is not
    differentiable (computed under ``torch.no_grad``).

    Args:
        a: (B, Ta, d) first trajectories, data units.
        b: (B, Tb, d) second trajectories, same units and d.
        lengths_a: optional (B,) valid samples of each ``a`` row (1..Ta); None: all Ta.
        lengths_b: optional (B,) valid samples of each ``b`` row (1..Tb); None: all Tb.
        squared_cost: use the squared local cost and return the root of the accumulated sum.

    Returns:
        (B,) distances in data units, dtype of the (promoted) inputs, on their device.

    Raises:
        ShapeMismatchError: inputs not 3-D or not float32 / float64 (float16 and bfloat16 overflow the squared
            costs), different B or d, lengths of the wrong shape or above the padding.
        NonFiniteError: NaN or Inf at a valid sample.
        TooFewSamplesError: a trajectory with no valid sample.
    """
    a, b = _check_pair(a, b)
    B, Ta, _ = a.shape
    Tb = b.shape[1]
    device = a.device
    la = check_lengths(lengths_a, B, Ta, device, name="lengths_a")
    lb = check_lengths(lengths_b, B, Tb, device, name="lengths_b")
    if B == 0:
        return a.new_zeros(0)
    for name, n in (("a", la), ("b", lb)):
        if (n < 1).any():
            raise TooFewSamplesError(f"{name} has no valid sample (lengths_{name} = 0)", int(torch.nonzero(n < 1)[0]))
    mask_a = torch.arange(Ta, device=device).unsqueeze(0) < la.unsqueeze(1)
    mask_b = torch.arange(Tb, device=device).unsqueeze(0) < lb.unsqueeze(1)
    check_finite("a", a, mask_a)
    check_finite("b", b, mask_b)
    if Ta > Tb:  # DTW is symmetric: let the wavefront buffers run over the shorter axis
        a, b, la, lb, mask_a, mask_b, Ta, Tb = b, a, lb, la, mask_b, mask_a, Tb, Ta
    la_list = la.tolist()
    lb_list = lb.tolist()
    with torch.no_grad():
        zero = torch.zeros((), dtype=a.dtype, device=device)
        a = torch.where(mask_a.unsqueeze(-1), a, zero)
        b = torch.where(mask_b.unsqueeze(-1), b, zero)
        # On CPU, chunks of pairs keep the working set in cache (one chunk on other devices).
        size = max(8, _CPU_CELLS_PER_DIAGONAL // max(1, min(Ta, Tb))) if device.type == "cpu" else B
        if size >= B:
            chunks = [list(range(B))]
        else:
            # Pairs of similar size share a chunk, so that trimming each chunk to its longest pair wastes little.
            order = sorted(range(B), key=lambda k: (la_list[k] + lb_list[k], la_list[k]))
            chunks = [order[s : s + size] for s in range(0, B, size)]
        out = torch.empty(B, dtype=a.dtype, device=device)
        for rows in chunks:
            na = [la_list[k] for k in rows]
            nb = [lb_list[k] for k in rows]
            ta, tb = max(na), max(nb)
            if len(rows) == B:
                aa, bb = a[:, :ta], b[:, :tb]
            else:
                idx = torch.tensor(rows, device=device)
                aa, bb = a[idx, :ta], b[idx, :tb]
            value = _wavefront(aa, bb, na, nb, squared_cost)
            if len(rows) == B:
                out.copy_(value)
            else:
                out[idx] = value
        return out.sqrt_() if squared_cost else out


def _wavefront(a: Tensor, b: Tensor, la: list[int], lb: list[int], squared_cost: bool) -> Tensor:
    """Accumulated DTW cost D(la-1, lb-1) of each pair (sum of local costs, no final root).

    Args:
        a: (B, Ta, d) first trajectories, finite everywhere (padding already sanitised).
        b: (B, Tb, d) second trajectories, finite everywhere.
        la: B valid lengths of ``a`` (1..Ta).
        lb: B valid lengths of ``b`` (1..Tb).
        squared_cost: squared Euclidean local cost instead of Euclidean.

    Returns:
        (B,) accumulated costs.
    """
    B, Ta, d = a.shape
    Tb = b.shape[1]
    dtype, device = a.dtype, a.device
    # Planar layout (B, d, T): each coordinate of an anti-diagonal is a contiguous row slice. b is reversed
    # so that b_j for j = k - i, i = lo..hi, is the increasing slice rb[Tb-1-k+lo : Tb-k+hi].
    pa = a.permute(0, 2, 1).contiguous()
    rb = b.flip(1).permute(0, 2, 1).contiguous()
    a_rows = [pa[:, c] for c in range(d)]
    b_rows = [rb[:, c] for c in range(d)]
    inf = float("inf")
    buffers = [torch.full((B, Ta + 2), inf, dtype=dtype, device=device) for _ in range(3)]
    cost_buf = torch.empty(B, Ta, dtype=dtype, device=device)
    tmp_buf = torch.empty(B, Ta, dtype=dtype, device=device)
    out = torch.empty(B, dtype=dtype, device=device)
    # Pairs whose last cell (la-1, lb-1) lies on anti-diagonal k are read when the wavefront reaches k.
    ends: dict[int, list[int]] = {}
    for r in range(B):
        ends.setdefault(la[r] + lb[r] - 2, []).append(r)
    reads = {}
    for k, rs in ends.items():
        rows = torch.tensor(rs, device=device)
        cols = torch.tensor([la[r] for r in rs], device=device)  # buffer index (la - 1) + 1
        reads[k] = (rows, cols)
    sub, minimum, add = torch.sub, torch.minimum, torch.add
    for k in range(Ta + Tb - 1):
        lo = k - Tb + 1 if k >= Tb else 0
        hi = k if k < Ta else Ta - 1
        n = hi - lo + 1
        s = Tb - 1 - k + lo
        c = cost_buf[:, :n]
        t = tmp_buf[:, :n]
        sub(a_rows[0][:, lo : hi + 1], b_rows[0][:, s : s + n], out=c)
        c.mul_(c)
        for ci in range(1, d):
            sub(a_rows[ci][:, lo : hi + 1], b_rows[ci][:, s : s + n], out=t)
            c.addcmul_(t, t)
        if not squared_cost:
            c.sqrt_()
        d0 = buffers[k % 3]
        dst = d0[:, lo + 1 : hi + 2]
        if k == 0:
            dst.copy_(c)
        else:
            d1 = buffers[(k - 1) % 3]
            d2 = buffers[(k - 2) % 3]
            # D(i, j) = c(i, j) + min(D(i-1, j), D(i, j-1), D(i-1, j-1)); buffer index = i + 1.
            minimum(d1[:, lo : hi + 1], d1[:, lo + 1 : hi + 2], out=t)
            minimum(t, d2[:, lo : hi + 1], out=t)
            add(c, t, out=dst)
        hit = reads.get(k)
        if hit is not None:
            out[hit[0]] = d0[hit[0], hit[1]]
    return out
