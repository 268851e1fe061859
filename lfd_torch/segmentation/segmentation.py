"""From BP-GM-HMM state sequences to ordered steps, attractors and subtask spaces (paper Sec. III-A/B, Table I).

Notation:
    N  demonstrations (sequences), T_i samples each, d state dimension
    S  HMM states (features) of the returned sample, M ordered steps m = 1..M (0-based in code)
    labels      N tensors (T_i,) long, step index of every sample
    boundaries  (N, M + 1) long, first sample of each step and T_i at the end
    attractors  (M, d) g_m, mean over sequences of the last sample of step m
    subtask space A_m: mixture of the emission Gaussians of the states step m visits, weighted by how many of the
        step's samples each state explains; log p(x | A_m) in :meth:`Segmentation.log_density`.

Steps are runs of HMM states (NOTES.md sec. 2); the line model only decides which adjacent runs are merged.
A Gaussian emission fits a long straight or gently curved leg better with several states than with one (the
density of a uniform line piece doubles when it is halved), and a minimum-jerk leg's dwell near a corner forms a
state that straddles the corner. So:
    1. runs shorter than ``min_length`` are absorbed by the neighbour whose state explains them best; the starts
       of the remaining runs are the HMM's state switches (``info["hmm_switches"]``, full resolution), the only
       candidate step boundaries;
    2. merging criterion: adjacent runs are merged greedily while the Bayesian information criterion prefers one
       line to two (the union is one straight leg), the perpendicular residuals of a line being Gaussian with a
       variance floored at (tolerance x data spread)^2. A merge removes a switch; it never adds one;
    3. all sequences get the same number of steps (the most frequent count, ties to the larger): extra steps
       are merged (same criterion), missing steps are split at the remaining HMM switch that lowers the two-line
       residual most (at the best change point only for a step that contains no switch). Steps are matched
       across sequences by their order only, so a demonstration that skips a step has one of its steps split in
       two to reach the consensus count; this is reported (:class:`SegmentationWarning`,
       ``info["forced_to_consensus"]``), as is the last-resort equal cut of a sequence too short to split
       (``info["equal_cut_fallback"]``);
    4. local refinement: each boundary is moved towards the posterior median of the change point between its
       two steps under the two-line model (a corner), but by at most ``info["refine_radius"]`` = max(min_length,
       subsampling stride) samples from its HMM switch (the switch is only known to the stride). The one
       exception is a corner state, a run next to the boundary whose samples both adjacent lines explain (mean
       squared perpendicular distance to the other step's line <= 4 floor variances, e.g. the state that
       straddles a minimum-jerk corner): the boundary may move anywhere inside that run. The line model never
       places a boundary away from the HMM's switches otherwise.

The line stages need d >= 2 (a 1-D path is a line everywhere): :func:`segment` raises
:class:`~lfd_torch.errors.InvalidArgumentError` for 1-D data; :class:`FixedSegmenter` and :class:`NoSegmenter`
accept it.

Resolution. The HMM and the BIC merge of stage 2 run on the subsampled sequences (at most ``max_samples``
points), so ``max_samples`` is a resolution parameter, not only a speed knob: more points make the evidence for a
bend stronger (the BIC penalty grows like log n, the misfit of one line for a curved piece like n), and a curved
path can then be cut into more steps. Keep it fixed when comparing step counts across runs.
"""

from __future__ import annotations

import math
import warnings
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError, ShapeMismatchError, StoreError, TooFewSamplesError
from lfd_torch.segmentation.emissions import gaussian_log_density
from lfd_torch.segmentation.sampler import BetaProcessHMMSampler, SamplerResult

__all__ = [
    "Segmentation",
    "segment",
    "BPGMHMMSegmenter",
    "FixedSegmenter",
    "NoSegmenter",
    "runs",
    "resolve_min_length",
    "SegmentationWarning",
    "SCHEMA_VERSION",
]


class SegmentationWarning(UserWarning):
    """The step extraction had to force a result (a sequence cut to the consensus step count, or cut evenly)."""


SCHEMA_VERSION = 1


# ---------------------------------------------------------------------------------------------- result
@dataclass(frozen=True, eq=False)
class Segmentation:
    """Ordered steps shared by a set of demonstrations (see the module docstring for notation).

    Attributes:
        labels: N tensors (T_i,) long, step of every sample (non-decreasing, 0..M-1).
        boundaries: (N, M + 1) long, first sample of each step, then T_i.
        attractors: (M, d) g_m: for m < M the mean over sequences of the last sample of step m; g_M is the
            demonstrations' attractor (``Demos.attractor``, by default the mean of their end points).
        state_mean: (S, d) emission means of the HMM states (or one Gaussian per step without an HMM).
        state_covariance: (S, d, d).
        step_weights: (M, S) mixture weights of the states in each subtask space (rows sum to 1).
        states: N tensors (T_i,) long HMM state of every sample (the step index when there is no HMM).
        sampler: the sampler's result (trace, acceptance), None without an HMM.
        info: free-form diagnostics (timings, subsampling strides, merge decisions).

    Index tensors (labels, boundaries, states) live on the device of the segmented data.
    """

    labels: tuple[Tensor, ...]
    boundaries: Tensor
    attractors: Tensor
    state_mean: Tensor
    state_covariance: Tensor
    step_weights: Tensor
    states: tuple[Tensor, ...]
    sampler: SamplerResult | None = None
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_steps(self) -> int:
        return self.attractors.shape[0]

    @property
    def n_sequences(self) -> int:
        return len(self.labels)

    @property
    def dim(self) -> int:
        return self.attractors.shape[1]

    def step_states(self) -> list[list[int]]:
        """HMM states of each step (a state may recur in several steps), ordered by weight."""
        out = []
        for w in self.step_weights:
            idx = torch.nonzero(w > 0).reshape(-1)
            out.append(idx[torch.argsort(w[idx], descending=True)].tolist())
        return out

    def log_density(self, x: Tensor) -> Tensor:
        """log p(x | A_m) for every step.

        Args:
            x: (..., d) states.

        Returns:
            (..., M) log densities.
        """
        if x.shape[-1] != self.dim:
            raise ShapeMismatchError(f"x has dimension {x.shape[-1]}, the segmentation {self.dim}")
        lead = x.shape[:-1]
        flat = x.reshape(-1, self.dim).to(self.state_mean)
        comp = gaussian_log_density(flat, self.state_mean, self.state_covariance)  # (n, S)
        logw = torch.log(self.step_weights.to(comp))  # (M, S), -inf where absent
        out = torch.logsumexp(comp.unsqueeze(1) + logw.unsqueeze(0), dim=-1)  # (n, M)
        return out.reshape(*lead, self.n_steps)

    def other_log_density(self, x: Tensor) -> Tensor:
        """log p(x | A_m-) = the largest log p(x | A_m') over the other steps m' != m (NOTES.md sec. 2).

        With a single step there is no other region: -inf.

        Args:
            x: (..., d).

        Returns:
            (..., M).
        """
        ld = self.log_density(x)
        M = self.n_steps
        if M == 1:
            return torch.full_like(ld, float("-inf"))
        eye = torch.eye(M, dtype=torch.bool, device=ld.device)
        masked = ld.unsqueeze(-2).masked_fill(eye, float("-inf"))  # (..., M, M): row m hides m
        return masked.amax(-1)

    def membership(self, x: Tensor) -> Tensor:
        """(..., M) bool: x lies in A_m, i.e. p(x | A_m) >= p(x | A_m-) (the test of paper Sec. IV)."""
        return self.log_density(x) >= self.other_log_density(x)

    def split(self, demos: Demos, *, end_at_attractor: bool = False) -> list[Demos]:
        """Cut every demonstration into its steps.

        A piece ends where its demonstration reaches the step boundary, not exactly at g_m: g_m is the mean of
        the pieces' end points (or the task attractor for the last step), so each piece's end differs from g_m by
        that demonstration's spread around the mean, and its last velocity is the demonstration's velocity there
        (not zero). Primitives fitted to the pieces must therefore tolerate ends that miss the attractor, or use
        ``end_at_attractor=True``.

        Args:
            demos: the demonstrations that were segmented (same number and lengths).
            end_at_attractor: append one sample at g_m with zero velocity to every piece of step m, one time step
                (the piece's last sampling interval) after its last sample, so that every piece ends at rest at
                its attractor.

        Returns:
            M ``Demos``; entry m holds the pieces of step m, with attractor g_m. Piece m of demonstration i is
            samples boundaries[i, m] .. boundaries[i, m + 1] - 1 (plus the appended sample with
            ``end_at_attractor``); velocities and times are the original ones.
        """
        if demos.n_demos != self.n_sequences:
            raise ShapeMismatchError(f"{demos.n_demos} demonstrations, the segmentation has {self.n_sequences}")
        if not torch.equal(demos.lengths.cpu(), self.boundaries[:, -1].cpu()):
            raise ShapeMismatchError("demonstration lengths differ from the segmented ones")
        out = []
        for m in range(self.n_steps):
            pos, vel, tms = [], [], []
            for i in range(self.n_sequences):
                a, b = int(self.boundaries[i, m]), int(self.boundaries[i, m + 1])
                p, v, t = demos.positions[i, a:b], demos.velocities[i, a:b], demos.times[i, a:b]
                if end_at_attractor:
                    dt = t[-1] - t[-2] if b - a > 1 else t.new_tensor(1.0)
                    p = torch.cat([p, self.attractors[m].to(p).unsqueeze(0)])
                    v = torch.cat([v, torch.zeros_like(v[:1])])
                    t = torch.cat([t, (t[-1] + dt).unsqueeze(0)])
                pos.append(p)
                vel.append(v)
                tms.append(t)
            out.append(
                Demos.from_sequences(
                    pos, times=tms, velocities=vel, attractor=self.attractors[m].to(demos.positions),
                    names=demos.names or None, dtype=demos.dtype, device=demos.device,
                )  # fmt: skip
            )
        return out

    # ------------------------------------------------------------------ persistence
    def state_dict(self) -> dict[str, Any]:
        """Plain dict of tensors and lists (no sampler result, no info), for ``torch.save``."""
        return {
            "schema_version": SCHEMA_VERSION,
            "labels": [t.cpu() for t in self.labels],
            "boundaries": self.boundaries.cpu(),
            "attractors": self.attractors.cpu(),
            "state_mean": self.state_mean.cpu(),
            "state_covariance": self.state_covariance.cpu(),
            "step_weights": self.step_weights.cpu(),
            "states": [t.cpu() for t in self.states],
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> Segmentation:
        """Inverse of :meth:`state_dict`."""
        if state.get("schema_version") != SCHEMA_VERSION:
            raise StoreError(f"segmentation schema {state.get('schema_version')!r}, expected {SCHEMA_VERSION}")
        return cls(
            labels=tuple(state["labels"]), boundaries=state["boundaries"], attractors=state["attractors"],
            state_mean=state["state_mean"], state_covariance=state["state_covariance"],
            step_weights=state["step_weights"], states=tuple(state["states"]),
        )  # fmt: skip

    def save(self, path: str | Path) -> Path:
        """Write :meth:`state_dict` atomically with ``torch.save``."""
        from lfd_torch.store import atomic_path

        with atomic_path(path) as tmp:
            torch.save(self.state_dict(), tmp)
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> Segmentation:
        """Read a file written by :meth:`save`."""
        return cls.from_state_dict(torch.load(path, weights_only=True))

    def table(self) -> list[dict[str, Any]]:
        """One row per step: index, attractor, HMM states, mean start/end sample and mean length fraction."""
        rows = []
        lengths = self.boundaries[:, -1].to(torch.float64)
        for m in range(self.n_steps):
            start = self.boundaries[:, m].to(torch.float64)
            end = self.boundaries[:, m + 1].to(torch.float64)
            row: dict[str, Any] = {"step": m + 1, "states": " ".join(str(s) for s in self.step_states()[m])}
            for j, v in enumerate(self.attractors[m].tolist()):
                row[f"g_{j}"] = v
            row["mean_start"] = float(start.mean())
            row["mean_end"] = float(end.mean())
            row["mean_fraction"] = float(((end - start) / lengths).mean())
            rows.append(row)
        return rows


# ---------------------------------------------------------------------------------------------- helpers
def runs(labels: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Maximal runs of equal labels.

    Args:
        labels: (T,) long.

    Returns:
        starts (R,), ends (R,) (exclusive) and values (R,).
    """
    change = torch.nonzero(labels[1:] != labels[:-1]).reshape(-1) + 1
    starts = torch.cat([change.new_zeros(1), change])
    ends = torch.cat([change, change.new_tensor([labels.shape[0]])])
    return starts, ends, labels[starts]


def resolve_min_length(min_length: float, length: int) -> int:
    """Minimum step length in samples: ``min_length`` samples if >= 1, else that fraction of ``length`` (>= 3)."""
    if not min_length > 0:
        raise ValueError(f"min_length must be positive, got {min_length!r}")
    n = int(min_length) if min_length >= 1 else int(math.ceil(min_length * length))
    return max(n, 3)


def _line_sse(x: Tensor) -> Tensor:
    """Sum of squared perpendicular residuals of the best line through x (n, d): trace(S) - lambda_max(S)."""
    c = x - x.mean(0)
    scatter = c.T @ c
    ev = torch.linalg.eigvalsh(scatter)
    return (ev[:-1]).sum().clamp_min(0.0)


def _line_log_lik(x: Tensor, floor_var: float) -> float:
    """Gaussian log likelihood of perpendicular residuals with variance max(MLE, floor)."""
    n, d = x.shape
    if n < 2:
        return 0.0
    dof = n * (d - 1)
    var = max(float(_line_sse(x)) / dof, floor_var)
    return -0.5 * dof * (math.log(2.0 * math.pi * var) + float(_line_sse(x)) / (dof * var))


def _prefix_line_sse(x: Tensor) -> tuple[Tensor, Tensor]:
    """Perpendicular SSE of the best line through x[:t] and x[t:] for every t = 0..n: two (n + 1,) tensors."""
    n, d = x.shape

    def prefix(y: Tensor) -> Tensor:
        ones = torch.ones(n, 1, dtype=y.dtype, device=y.device)
        cnt = torch.cat([ones.new_zeros(1, 1), ones.cumsum(0)]).squeeze(-1)  # (n+1,)
        s1 = torch.cat([y.new_zeros(1, d), y.cumsum(0)])  # (n+1, d)
        s2 = torch.cat([y.new_zeros(1, d, d), (y.unsqueeze(-1) * y.unsqueeze(-2)).cumsum(0)])
        safe = cnt.clamp_min(1.0)
        scatter = s2 - s1.unsqueeze(-1) * s1.unsqueeze(-2) / safe[:, None, None]
        scatter = 0.5 * (scatter + scatter.transpose(-1, -2))
        ev = torch.linalg.eigvalsh(scatter)
        return ev[:, :-1].sum(-1).clamp_min(0.0)

    center = x - x.mean(0)
    left = prefix(center)
    right = prefix(center.flip(0)).flip(0)
    return left, right


def _best_split(
    x: Tensor,
    min_len: int,
    *,
    posterior_median: bool = False,
    around: int | None = None,
    radius: int = 0,
    limits: tuple[int, int] | None = None,
) -> tuple[int, float]:
    """Change point t (min_len <= t <= n - min_len) of two lines fitted to x[:t] and x[t:], and its SSE.

    By default t minimises the summed perpendicular squared residuals. With ``posterior_median`` it is the median
    of the change-point posterior p(t) ∝ exp(-(SSE(t) - SSE_min) / (2 sigma^2)) under a flat prior, sigma^2 the
    residual variance at the optimum: where the two lines explain a stretch equally well (a minimum-jerk dwell at
    a corner, where samples pile up within noise of the corner) the estimate sits in the middle of that stretch
    instead of at an arbitrary noise-driven minimum.

    With ``around`` the estimate is clamped to ``around +- radius`` (a local refinement of a given boundary, e.g.
    an HMM state switch, which may move it by at most ``radius`` samples); ``limits`` (lo, hi), when given,
    replaces that interval.
    """
    n, d = x.shape
    left, right = _prefix_line_sse(x)
    total = left + right
    lo, hi = min_len, n - min_len
    if around is not None:
        t, _ = _best_split(x, min_len, posterior_median=posterior_median)
        a_lo, a_hi = limits if limits is not None else (around - radius, around + radius)
        t = max(min(max(t, a_lo), a_hi, n - 1), 1)
        return t, float(total[t])
    if hi < lo:
        return n // 2, float(total[n // 2])
    window = total[lo : hi + 1]
    t = lo + int(torch.argmin(window))
    if posterior_median:
        dof = max((n - 2 * d) * (d - 1), 1)
        var = (float(window.min()) / dof) + torch.finfo(x.dtype).tiny
        weights = torch.softmax(-(window - window.min()) / (2.0 * var), dim=0)
        half = torch.tensor([0.5], dtype=weights.dtype, device=weights.device)
        t = lo + int(torch.searchsorted(weights.cumsum(0), half).clamp_max(hi - lo))
    return t, float(total[t])


def _absorb_short(states: Tensor, min_len: int, log_emission: Tensor) -> Tensor:
    """Relabel runs shorter than ``min_len`` with the neighbour state that explains them best (repeat until none)."""
    states = states.clone()
    while True:
        starts, ends, values = runs(states)
        lengths = ends - starts
        short = torch.nonzero(lengths < min_len).reshape(-1)
        if short.numel() == 0 or starts.numel() == 1:
            return states
        r = int(short[torch.argmin(lengths[short])])
        a, b = int(starts[r]), int(ends[r])
        cands = []
        if r > 0:
            cands.append(int(values[r - 1]))
        if r < starts.numel() - 1:
            cands.append(int(values[r + 1]))
        scores = [float(log_emission[a:b, c].sum()) for c in cands]
        states[a:b] = cands[max(range(len(cands)), key=lambda j: scores[j])]


def _merge_steps(x: Tensor, bounds: list[int], floor_var: float, target: int | None = None) -> list[int]:
    """Greedy merging of adjacent steps of one sequence (bounds: step starts plus the end).

    Without ``target``: merge the best pair while the line BIC prefers one segment. With ``target``: merge the
    best pairs until ``target`` steps remain.
    """
    bounds = list(bounds)
    d = x.shape[1]
    n_params = 2 * d  # mean, direction, residual variance of a line
    while len(bounds) > 2:
        if target is not None and len(bounds) - 1 <= target:
            break
        best, best_gain = None, -math.inf
        for j in range(1, len(bounds) - 1):
            a, b, c = bounds[j - 1], bounds[j], bounds[j + 1]
            ll_split = _line_log_lik(x[a:b], floor_var) + _line_log_lik(x[b:c], floor_var)
            ll_union = _line_log_lik(x[a:c], floor_var)
            # gain of merging: BIC(split) - BIC(union), BIC = -2 LL + p log n
            gain = 2.0 * (ll_union - ll_split) + n_params * math.log(max(c - a, 2))
            if gain > best_gain:
                best, best_gain = j, gain
        if best is None or (target is None and best_gain <= 0):
            break
        del bounds[best]
    return bounds


def _split_steps(
    x: Tensor, bounds: list[int], target: int, min_len: int, candidates: Sequence[int] | None = None
) -> list[int]:
    """Split the step whose best change point lowers the line SSE most, until ``target`` steps.

    With ``candidates`` (the HMM state switches of the sequence) a step is split only at one of them (the one
    that lowers the two-line SSE most); a step without an admissible candidate falls back to its best change
    point.
    """
    bounds = list(bounds)
    while len(bounds) - 1 < target:
        best, best_gain, best_t = None, -math.inf, 0
        for j in range(len(bounds) - 1):
            a, b = bounds[j], bounds[j + 1]
            if b - a < 2 * min_len:
                continue
            inside = [c - a for c in (candidates or ()) if a + min_len <= c <= b - min_len]
            if inside:
                left, right = _prefix_line_sse(x[a:b])
                tot = left + right
                t = min(inside, key=lambda c: float(tot[c]))
                sse = float(tot[t])
            else:
                t, sse = _best_split(x[a:b], min_len)
            gain = float(_line_sse(x[a:b])) - sse
            if gain > best_gain:
                best, best_gain, best_t = j, gain, a + t
        if best is None:
            break
        bounds.insert(best + 1, best_t)
    return bounds


def _line_perp_sq(points: Tensor, line_of: Tensor) -> float:
    """Mean squared perpendicular distance of points (n, d) to the best line through line_of (m, d)."""
    mean = line_of.mean(0)
    c = line_of - mean
    direction = torch.linalg.eigh(c.T @ c)[1][:, -1]
    q = points - mean
    return float(((q * q).sum(-1) - (q @ direction) ** 2).mean())


def _refine(
    x: Tensor,
    bounds: list[int],
    min_len: int,
    radius: int | None = None,
    switches: Sequence[int] | None = None,
    floor_var: float = 0.0,
) -> list[int]:
    """Move every inner boundary to the two-line change point between its neighbours' outer ends (left to right).

    With ``radius`` a boundary moves by at most ``radius`` samples (it stays at the HMM state switch it came from,
    refined locally); None searches the whole span between the neighbours. With ``switches`` (the HMM state
    switches of the sequence) the boundary may also move across the whole HMM run next to it when that run is a
    corner state: its samples lie within twice the residual floor (mean squared perpendicular distance
    <= 4 floor_var) of the line of the step on the other side too, i.e. both steps explain it (a minimum-jerk dwell
    at a corner).
    """
    bounds = list(bounds)
    sw = sorted(set(switches or ()))
    for j in range(1, len(bounds) - 1):
        a, b, c = bounds[j - 1], bounds[j], bounds[j + 1]
        if c - a < 2 * min_len:
            continue
        if radius is None:
            t, _ = _best_split(x[a:c], min_len, posterior_median=True)
        else:
            lo, hi = b - radius, b + radius
            if sw:
                p = max([s for s in sw if s < b] + [a])  # HMM run [p, b) left of the boundary, inside step j - 1
                q = min([s for s in sw if s > b] + [c])  # HMM run [b, q) right of it, inside step j
                if b - p >= 2 and c - b >= 2 and _line_perp_sq(x[p:b], x[b:c]) <= 4.0 * floor_var:
                    lo = min(lo, p)
                if q - b >= 2 and b - a >= 2 and _line_perp_sq(x[b:q], x[a:b]) <= 4.0 * floor_var:
                    hi = max(hi, q)
            t, _ = _best_split(x[a:c], min_len, posterior_median=True, around=b - a, limits=(lo - a, hi - a))
        bounds[j] = a + t
    return bounds


def _consensus(
    seqs: list[Tensor],
    bounds_all: list[list[int]],
    floor_var: float,
    min_length: float,
    candidates: list[list[int]] | None = None,
    radius: list[int] | None = None,
) -> tuple[list[list[int]], dict[int, int], list[int]]:
    """Bring every sequence to the consensus step count M (the most frequent count, ties to the larger).

    Extra steps are merged (line BIC), missing ones split at their best change point; a sequence too short to
    split is cut evenly. Every sequence whose count was changed triggers a :class:`SegmentationWarning`.

    Args:
        seqs: N full-resolution sequences (T_i, d).
        bounds_all: N lists of step starts plus T_i.
        floor_var: residual variance floor of the line model.
        min_length: the ``min_length`` argument of :func:`segment`.
        candidates: per sequence, the HMM state switches (full resolution) at which a missing step may be split;
            None splits at the best change point anywhere.
        radius: per sequence, the most samples the final refinement may move a boundary (None: anywhere between
            its neighbours).

    Returns:
        The refined bounds (all with M + 1 entries), {sequence: its own count} for the sequences forced to M, and
        the sequences that were cut evenly.
    """
    counts = Counter(len(b) - 1 for b in bounds_all)
    top = max(counts.values())
    M = max(c for c, v in counts.items() if v == top)
    forced: dict[int, int] = {}
    equal_cut: list[int] = []
    out = []
    for i, xf in enumerate(seqs):
        min_len = resolve_min_length(min_length, xf.shape[0])
        b = bounds_all[i]
        if len(b) - 1 != M:
            forced[i] = len(b) - 1
        if len(b) - 1 > M:
            b = _merge_steps(xf, b, floor_var, target=M)
        elif len(b) - 1 < M:
            b = _split_steps(xf, b, M, min_len, None if candidates is None else candidates[i])
        if len(b) - 1 != M:  # too short to split further: keep a consistent count by equal cuts
            Ti = xf.shape[0]
            b = [round(j * Ti / M) for j in range(M)] + [Ti]
            equal_cut.append(i)
        out.append(
            _refine(
                xf, b, min_len, None if radius is None else radius[i],
                None if candidates is None else candidates[i], floor_var,
            )  # fmt: skip
        )
    if forced:
        warnings.warn(
            f"sequences {sorted(forced)} had {[forced[i] for i in sorted(forced)]} steps and were forced to the "
            f"consensus count {M} (steps are matched by order: a sequence that skips or adds a step is cut to fit)"
            + (f"; sequences {equal_cut} were too short to split and were cut evenly" if equal_cut else ""),
            SegmentationWarning,
            stacklevel=3,
        )
    return out, forced, equal_cut


def _gaussian_fit(x: Tensor, ridge: Tensor) -> tuple[Tensor, Tensor]:
    mean = x.mean(0)
    c = x - mean
    cov = c.T @ c / max(x.shape[0] - 1, 1) + ridge
    return mean, 0.5 * (cov + cov.T)


def _check_demos(demos: Demos | Sequence[Tensor], min_len_param: float) -> Demos:
    if not isinstance(demos, Demos):
        demos = Demos.from_sequences(list(demos))  # typed errors on shape / NaN / too short
    for i, n in enumerate(demos.lengths.tolist()):
        m = resolve_min_length(min_len_param, n)
        if n < 2 * m:
            raise TooFewSamplesError(f"has {n} samples; segmentation needs at least 2 * min_length = {2 * m}", i)
    return demos


def _assemble(
    demos: Demos,
    bounds: list[list[int]],
    states_full: list[Tensor],
    state_mean: Tensor,
    state_cov: Tensor,
    sampler: SamplerResult | None,
    info: dict[str, Any],
) -> Segmentation:
    M = len(bounds[0]) - 1
    S = state_mean.shape[0]
    boundaries = torch.tensor(bounds, dtype=torch.long, device=demos.device)
    labels = []
    weights = torch.zeros(M, S, dtype=torch.float64, device=demos.device)
    ends = torch.zeros(M, demos.dim, dtype=demos.dtype, device=demos.device)
    for i, b in enumerate(bounds):
        lab = torch.zeros(int(demos.lengths[i]), dtype=torch.long, device=demos.device)
        for m in range(M):
            lab[b[m] : b[m + 1]] = m
            st = states_full[i][b[m] : b[m + 1]]
            weights[m] += torch.bincount(st.to(demos.device), minlength=S).to(torch.float64)[:S]
            ends[m] += demos.positions[i, b[m + 1] - 1]
        labels.append(lab)
    weights = weights / weights.sum(-1, keepdim=True).clamp_min(1.0)
    attractors = ends / len(bounds)
    attractors[-1] = demos.attractor.to(attractors)  # the last step ends at the task's goal
    return Segmentation(
        labels=tuple(labels),
        boundaries=boundaries,
        attractors=attractors,
        state_mean=state_mean,
        state_covariance=state_cov,
        step_weights=weights.to(state_mean),
        states=tuple(s.to(demos.device) for s in states_full),
        sampler=sampler,
        info=info,
    )


def _steps_from_bounds(demos: Demos, bounds: list[list[int]], info: dict[str, Any]) -> Segmentation:
    """Segmentation with one Gaussian subtask space per step (no HMM): fixed boundaries or a single step."""
    M = len(bounds[0]) - 1
    x_all = demos.samples()[0]
    ridge = torch.diag(x_all.var(0) * 1e-4 + torch.finfo(demos.dtype).eps)
    means, covs, states = [], [], []
    for m in range(M):
        pts = torch.cat([demos.positions[i, b[m] : b[m + 1]] for i, b in enumerate(bounds)])
        mu, cov = _gaussian_fit(pts, ridge)
        means.append(mu)
        covs.append(cov)
    for i, b in enumerate(bounds):
        s = torch.zeros(int(demos.lengths[i]), dtype=torch.long, device=demos.device)
        for m in range(M):
            s[b[m] : b[m + 1]] = m
        states.append(s)
    return _assemble(demos, bounds, states, torch.stack(means), torch.stack(covs), None, info)


# ---------------------------------------------------------------------------------------------- entry points
def segment(
    demos: Demos | Sequence[Tensor],
    *,
    generator: torch.Generator,
    min_length: float = 0.04,
    max_samples: int = 60,
    straightness_tolerance: float = 0.1,
    feature_mass: float = 2.0,
    feature_concentration: float = 1.0,
    transition_concentration: float = 1.0,
    stickiness: float = 25.0,
    covariance_scale: float = 0.05,
    mean_pseudo_count: float = 0.01,
    extra_dof: float = 2.0,
    n_chains: int = 4,
    n_iterations: int = 40,
    burn_in: float = 0.5,
    n_initial_features: int = 4,
    birth_window: float = 0.1,
    birth_prior_mix: float = 0.1,
    resample_hyperparameters: bool = False,
    progress: bool = False,
) -> Segmentation:
    """Segment demonstrations into ordered steps with the BP-GM-HMM (no number of steps is given).

    Args:
        demos: N demonstrations (a ``Demos`` or a list of (T_i, d) tensors).
        generator: source of all randomness (CPU generator for CPU data).
        min_length: shortest step, samples (>= 1) or fraction of each sequence's length (< 1); every sequence
            needs at least 2 * min_length samples.
        max_samples: sequences are subsampled uniformly in time to at most this many points before sampling;
            labels are mapped back and boundaries refined at full resolution. It is also the resolution of the
            BIC merge of steps (see the module docstring): the number of steps of a curved path can change with
            it, so keep it fixed when step counts are compared.
        straightness_tolerance: residual floor of the segment-level line model, as a fraction of the RMS spread
            of the data (the spatial resolution of a step; see the module docstring).
        Remaining keyword arguments: see :class:`BetaProcessHMMSampler`.

    Returns:
        Segmentation. ``info["forced_to_consensus"]`` maps each sequence whose own step count differed from the
        consensus count M to that count; ``info["equal_cut_fallback"]`` lists the sequences that had to be cut
        evenly into M steps. Either case also emits a :class:`SegmentationWarning`. ``info["hmm_switches"]``
        lists, per sequence, the HMM state switches (full resolution, after absorbing short runs) from which the
        boundaries are taken, and ``info["refine_radius"]`` how far the local refinement may move a boundary from
        its switch (except across a corner state, see the module docstring).

    Raises:
        InvalidArgumentError: 1-D data (the segment-level line model needs d >= 2) or bad hyperparameters.
        TooFewSamplesError: a sequence shorter than 2 * min_length.
    """
    import time

    demos = _check_demos(demos, min_length)
    if demos.dim < 2:
        raise InvalidArgumentError(
            "BP-GM-HMM segmentation needs d >= 2: its step extraction fits lines to the path, and every 1-D path is "
            "a line; use FixedSegmenter or NoSegmenter for 1-D data"
        )
    if max_samples < 4:
        raise ValueError(f"max_samples must be >= 4, got {max_samples}")
    if not straightness_tolerance > 0:
        raise ValueError("straightness_tolerance must be positive")
    t0 = time.perf_counter()
    seqs_full = [s.to(torch.float64) for s in demos.sequences()]
    strides = [max(1, math.ceil(s.shape[0] / max_samples)) for s in seqs_full]
    seqs = [s[::k] for s, k in zip(seqs_full, strides)]
    sampler = BetaProcessHMMSampler(
        feature_mass=feature_mass, feature_concentration=feature_concentration,
        transition_concentration=transition_concentration, stickiness=stickiness,
        covariance_scale=covariance_scale, mean_pseudo_count=mean_pseudo_count, extra_dof=extra_dof,
        n_chains=n_chains, n_iterations=n_iterations, burn_in=burn_in, n_initial_features=n_initial_features,
        birth_window=birth_window, birth_prior_mix=birth_prior_mix,
        resample_hyperparameters=resample_hyperparameters, progress=progress,
    )  # fmt: skip
    result = sampler.run(seqs, generator)
    t1 = time.perf_counter()
    x_all = torch.cat(seqs_full)
    spread2 = float(x_all.var(0).sum())
    floor_var = (straightness_tolerance**2) * spread2
    state_mean, state_cov = result.mean, result.covariance
    bounds_all: list[list[int]] = []
    states_full: list[Tensor] = []
    switches: list[list[int]] = []  # HMM state switches (after absorbing short runs), full resolution
    radii: list[int] = []  # how far the local refinement may move a boundary from its switch
    for i, (xs, xf, k) in enumerate(zip(seqs, seqs_full, strides)):
        Ti = xf.shape[0]
        min_len = resolve_min_length(min_length, Ti)
        st = result.states[i, : xs.shape[0]]
        le = gaussian_log_density(xs, state_mean, state_cov)
        st = _absorb_short(st, max(1, math.ceil(min_len / k)), le)
        full = st.repeat_interleave(k)[:Ti]
        if full.shape[0] < Ti:
            full = torch.cat([full, full[-1:].expand(Ti - full.shape[0])])
        starts, _, _ = runs(full)
        switches.append(starts[1:].tolist())
        radii.append(max(min_len, k))
        bounds = starts.tolist() + [Ti]
        bounds = _merge_steps(xs, [min(b // k, xs.shape[0]) if b < Ti else xs.shape[0] for b in bounds], floor_var)
        bounds_all.append([b * k for b in bounds[:-1]] + [Ti])
        states_full.append(full)
    counts = Counter(len(b) - 1 for b in bounds_all)
    bounds_all, forced, equal_cut = _consensus(
        seqs_full, bounds_all, floor_var, min_length, candidates=switches, radius=radii
    )
    info = {
        "sampler_seconds": t1 - t0,
        "postprocess_seconds": time.perf_counter() - t1,
        "strides": strides,
        "step_counts_before_consensus": dict(counts),
        "forced_to_consensus": forced,
        "equal_cut_fallback": equal_cut,
        "straightness_floor_var": floor_var,
        "hmm_switches": switches,
        "refine_radius": radii,
    }
    return _assemble(
        demos, bounds_all, states_full, state_mean.to(demos.dtype), state_cov.to(demos.dtype), result, info
    )


class BPGMHMMSegmenter:
    """Config-friendly BP-GM-HMM segmenter: keyword arguments of :func:`segment` are fixed at construction.

    ``BPGMHMMSegmenter(**cfg)(demos, generator=g)`` equals ``segment(demos, generator=g, **cfg)``.
    """

    def __init__(self, **hyperparameters: Any) -> None:
        import inspect

        valid = set(inspect.signature(segment).parameters) - {"demos", "generator"}
        unknown = set(hyperparameters) - valid
        if unknown:
            raise TypeError(f"unknown hyperparameters {sorted(unknown)}; valid: {sorted(valid)}")
        self.hyperparameters = dict(hyperparameters)

    def __call__(self, demos: Demos | Sequence[Tensor], *, generator: torch.Generator) -> Segmentation:
        return segment(demos, generator=generator, **self.hyperparameters)


class FixedSegmenter:
    """Hand-given boundaries (ablations).

    Args:
        boundaries: inner boundaries as fractions of each demonstration's length in (0, 1), increasing; the same
            for every demonstration. ``[]`` gives one step.
    """

    def __init__(self, boundaries: Sequence[float] = ()) -> None:
        b = [float(v) for v in boundaries]
        if any(not 0 < v < 1 for v in b) or any(b2 <= b1 for b1, b2 in zip(b, b[1:])):
            raise ValueError(f"boundaries must be increasing fractions in (0, 1), got {b}")
        self.boundaries = b

    def __call__(self, demos: Demos | Sequence[Tensor], *, generator: torch.Generator | None = None) -> Segmentation:
        demos = _check_demos(demos, 3)
        bounds = []
        for i, n in enumerate(demos.lengths.tolist()):
            b = [0] + [int(round(f * n)) for f in self.boundaries] + [n]
            if any(b2 - b1 < 1 for b1, b2 in zip(b, b[1:])):
                raise TooFewSamplesError(f"a fixed step would be empty (length {n})", i)
            bounds.append(b)
        return _steps_from_bounds(demos, bounds, {"method": "fixed"})


class NoSegmenter:
    """One step per demonstration (the whole task is one primitive)."""

    def __call__(self, demos: Demos | Sequence[Tensor], *, generator: torch.Generator | None = None) -> Segmentation:
        demos = _check_demos(demos, 3)
        bounds = [[0, n] for n in demos.lengths.tolist()]
        return _steps_from_bounds(demos, bounds, {"method": "none"})
