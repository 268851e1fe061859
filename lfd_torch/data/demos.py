"""Ragged sets of demonstrations as padded tensors.

Notation:
    B  number of demonstrations
    T  padded number of samples (max over the set)
    d  state dimension
    positions  (B, T, d)   x, in data units (LASA: mm); padding repeats the last valid sample
    velocities (B, T, d)   x_dot, in data units per second; zero on padding
    times      (B, T)      seconds, strictly increasing over the valid part; padding repeats the last time
    lengths    (B,)        valid samples per demonstration (int64, >= 3)
    attractor  (d,)        the common goal g of the set
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from lfd_torch.data.finite_difference import finite_difference_unchecked
from lfd_torch.utils import check_float, float_dtype, resolve_device, resolve_dtype
from lfd_torch.errors import (
    InvalidArgumentError,
    InvalidIndexError,
    NonFiniteError,
    NonIncreasingTimeError,
    ShapeMismatchError,
    TooFewSamplesError,
)

__all__ = ["Demos", "MIN_SAMPLES"]

MIN_SAMPLES = 3

Index = int | slice | Sequence[int] | Tensor | np.ndarray


def _as_tensor(value: Any, dtype: torch.dtype | None, device: torch.device | str | None, name: str = "value",
               index: int | None = None) -> Tensor:  # fmt: skip
    """A real-valued tensor from a tensor or an array-like (int and bool are cast to ``dtype``; complex, strings
    and objects are rejected)."""
    if not isinstance(value, Tensor):
        try:
            arr = np.asarray(value)
        except (TypeError, ValueError) as exc:  # ragged nested lists
            raise ShapeMismatchError(f"{name} is not a rectangular array: {exc}", index) from exc
        if arr.dtype.kind not in "fiub":
            raise ShapeMismatchError(f"{name} must hold real numbers, got an array of {arr.dtype}", index)
        value = torch.tensor(arr)
    if value.is_complex() or not (value.is_floating_point() or value.dtype in _INT_DTYPES):
        raise ShapeMismatchError(f"{name} must hold real numbers, got {value.dtype}", index)
    return value.to(dtype=dtype or value.dtype, device=device or value.device)


_INT_DTYPES = (torch.bool, torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64)


def _pad_edge(rows: list[Tensor], T: int) -> Tensor:
    """Stack (T_i, ...) tensors into (B, T, ...), repeating each row's last entry."""
    out = []
    for r in rows:
        if r.shape[0] < T:
            r = torch.cat([r, r[-1:].expand(T - r.shape[0], *r.shape[1:])], dim=0)
        out.append(r)
    return torch.stack(out)


@dataclass(frozen=True, eq=False)
class Demos:
    """A validated, padded batch of demonstrations (see the module docstring for shapes and units).

    Build one with :meth:`from_sequences` from a list of ragged arrays, or directly from padded tensors.
    Instances are immutable; every transformation returns a new ``Demos``.
    """

    positions: Tensor
    velocities: Tensor
    times: Tensor
    lengths: Tensor
    attractor: Tensor
    names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in ("positions", "velocities", "times", "lengths", "attractor"):
            value = getattr(self, name)
            if not isinstance(value, Tensor):
                raise ShapeMismatchError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
        if self.lengths.is_floating_point() or self.lengths.is_complex() or self.lengths.dtype == torch.bool:
            raise ShapeMismatchError(f"lengths must be an integer tensor, got {self.lengths.dtype}")
        if isinstance(self.names, (str, bytes)) or not isinstance(self.names, Iterable):
            raise ShapeMismatchError(f"names must be a sequence of strings (() for none), got {self.names!r}")
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "lengths", self.lengths.to(dtype=torch.long, device=self.positions.device))
        self._validate()
        self._canonicalize_padding()

    def _canonicalize_padding(self) -> None:
        """Edge-pad positions and times, zero-pad velocities, whatever the caller put in the padding.

        Kernels rely on it: e.g. interpolation searches the padded time grid, which must be non-decreasing.
        """
        if bool((self.lengths == self.max_length).all()):
            return
        rows = torch.arange(self.n_demos, device=self.device)
        last = self.lengths - 1
        mask = self.mask
        object.__setattr__(self, "times", torch.where(mask, self.times, self.times[rows, last].unsqueeze(1)))
        m3 = mask.unsqueeze(-1)
        object.__setattr__(
            self, "positions", torch.where(m3, self.positions, self.positions[rows, last].unsqueeze(1))
        )
        object.__setattr__(self, "velocities", torch.where(m3, self.velocities, torch.zeros_like(self.velocities)))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_sequences(
        cls,
        positions: Sequence[Any],
        *,
        times: Sequence[Any] | None = None,
        dt: float | None = None,
        velocities: Sequence[Any] | None = None,
        attractor: Any | None = None,
        names: Sequence[str] | None = None,
        velocity_scheme: str = "central",
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> Demos:
        """Build from ragged sequences.

        Args:
            positions: B array-likes of shape (T_i, d).
            times: B array-likes of shape (T_i,), seconds; or None with ``dt`` for uniform sampling.
            dt: uniform time step in seconds when ``times`` is None (default 1.0).
            velocities: B array-likes (T_i, d); None estimates them by finite differences (``velocity_scheme``).
            attractor: (d,) goal; None takes the mean of the demonstrations' end points.
            names: optional B labels.
            device: a torch device or its name (``"auto"``: CUDA when present); None keeps the inputs' device.

        ``times`` and ``dt`` exclude each other: passing both raises InvalidArgumentError (a ``dt`` would otherwise be
        ignored silently).

        Raises:
            ShapeMismatchError, TooFewSamplesError, NonFiniteError, NonIncreasingTimeError: malformed sequences (the
                message names the argument and the demonstration).
            InvalidArgumentError: both ``times`` and ``dt``, or an unknown or unavailable ``device``.
        """
        if isinstance(positions, (str, bytes)) or not hasattr(positions, "__len__"):
            raise ShapeMismatchError(f"positions must be a list of (T_i, d) arrays, got {type(positions).__name__}")
        for name, value in (("times", times), ("velocities", velocities)):
            if value is not None and (isinstance(value, (str, bytes)) or not hasattr(value, "__len__")):
                raise ShapeMismatchError(f"{name} must be a list of one array per demonstration, got "
                                         f"{type(value).__name__} {value!r}")  # fmt: skip
        if times is not None and dt is not None:
            raise InvalidArgumentError(f"give times or dt, not both (dt={dt!r} would be ignored)")
        device = resolve_device(device)
        dtype = float_dtype(dtype, allow_none=False, error=ShapeMismatchError)
        if len(positions) == 0:
            raise TooFewSamplesError("positions is empty: a demonstration set needs at least one demonstration")
        pos = []
        for i, p in enumerate(positions):
            t = _as_tensor(p, dtype, device, "positions", i)
            if t.ndim != 2:
                raise ShapeMismatchError(f"positions must have shape (T, d), got {tuple(t.shape)}", i)
            pos.append(t)
        dims = {p.shape[1] for p in pos}
        if len(dims) != 1:
            raise ShapeMismatchError(f"state dimensions differ across demonstrations: {[p.shape[1] for p in pos]}")
        for i, p in enumerate(pos):
            if p.shape[0] < MIN_SAMPLES:
                raise TooFewSamplesError(f"has {p.shape[0]} samples, at least {MIN_SAMPLES} are needed", i)
        lengths = torch.tensor([p.shape[0] for p in pos], dtype=torch.long, device=pos[0].device)
        T = int(lengths.max())
        if times is None:
            step = 1.0 if dt is None else check_float(dt, "dt", low=0.0, low_open=True, error=NonIncreasingTimeError)
            tms = [torch.arange(p.shape[0], dtype=dtype, device=p.device) * step for p in pos]
        else:
            if len(times) != len(pos):
                raise ShapeMismatchError(f"{len(times)} time vectors for {len(pos)} demonstrations")
            tms = []
            for i, (t, p) in enumerate(zip(times, pos)):
                tt = _as_tensor(t, dtype, p.device, "times", i)
                if tt.ndim == 2 and tt.shape[1] == 1:  # a column vector
                    tt = tt[:, 0]
                if tt.ndim != 1:
                    raise ShapeMismatchError(f"times: a (T,) vector per demonstration, got shape {tuple(tt.shape)}", i)
                if tt.shape[0] != p.shape[0]:
                    raise ShapeMismatchError(f"times: {tt.shape[0]} time stamps for {p.shape[0]} samples", i)
                tms.append(tt)
        P = _pad_edge(pos, T)
        Tm = _pad_edge(tms, T)
        if velocities is None:
            cls._check_values(P, Tm, lengths)  # clear errors before differentiating
            V = finite_difference_unchecked(P, Tm, lengths, scheme=velocity_scheme)
        else:
            if len(velocities) != len(pos):
                raise ShapeMismatchError(f"{len(velocities)} velocity arrays for {len(pos)} demonstrations")
            vel = []
            for i, (v, p) in enumerate(zip(velocities, pos)):
                vv = _as_tensor(v, dtype, p.device, "velocities", i)
                if vv.shape != p.shape:
                    raise ShapeMismatchError(
                        f"velocities have shape {tuple(vv.shape)}, positions {tuple(p.shape)}", i
                    )
                vel.append(torch.cat([vv, vv.new_zeros(T - vv.shape[0], vv.shape[1])]))
            V = torch.stack(vel)
        if attractor is None:
            g = P[torch.arange(len(pos), device=P.device), lengths - 1].mean(0)
        else:
            g = _as_tensor(attractor, dtype, P.device, "attractor")
            if g.shape != (P.shape[-1],):
                raise ShapeMismatchError(f"attractor must have shape ({P.shape[-1]},), got {tuple(g.shape)}")
        return cls(P, V, Tm, lengths, g, tuple(names) if names is not None else ())

    # ------------------------------------------------------------------ validation
    @staticmethod
    def _check_values(positions: Tensor, times: Tensor, lengths: Tensor, velocities: Tensor | None = None) -> None:
        B, T = times.shape
        mask = torch.arange(T, device=times.device).unsqueeze(0) < lengths.unsqueeze(1)
        if (lengths < MIN_SAMPLES).any():
            i = int(torch.nonzero(lengths < MIN_SAMPLES)[0])
            raise TooFewSamplesError(f"has {int(lengths[i])} samples (lengths[{i}]), at least {MIN_SAMPLES} are needed",
                                     i)  # fmt: skip
        if (lengths > T).any():
            i = int(torch.nonzero(lengths > T)[0])
            raise ShapeMismatchError(f"lengths[{i}] = {int(lengths[i])} exceeds the padded length {T}", i)
        for name, value in (("positions", positions), ("velocities", velocities)):
            if value is None:
                continue
            bad = (~torch.isfinite(value)).any(-1) & mask
            if bad.any():
                i, t = (int(v) for v in torch.nonzero(bad)[0])
                what = "NaN" if torch.isnan(value[i, t]).any() else "Inf"
                raise NonFiniteError(f"{name} contain {what} at sample {t}", i)
        bad_t = (~torch.isfinite(times)) & mask
        if bad_t.any():
            i, t = (int(v) for v in torch.nonzero(bad_t)[0])
            raise NonFiniteError(f"times contain a non-finite value at sample {t}", i)
        step_mask = mask[:, 1:]
        bad_step = (times[:, 1:] <= times[:, :-1]) & step_mask
        if bad_step.any():
            i, t = (int(v) for v in torch.nonzero(bad_step)[0])
            raise NonIncreasingTimeError(
                f"time is not strictly increasing at sample {t + 1} "
                f"({float(times[i, t])} -> {float(times[i, t + 1])})",
                i,
            )

    def _validate(self) -> None:
        P, V, Tm, L, g = self.positions, self.velocities, self.times, self.lengths, self.attractor
        if P.ndim != 3:
            raise ShapeMismatchError(f"positions must be (B, T, d), got {tuple(P.shape)}")
        B, T, d = P.shape
        if B == 0:
            raise TooFewSamplesError("a demonstration set needs at least one demonstration")
        if d == 0:
            raise ShapeMismatchError("positions have dimension d = 0; a demonstration needs at least one coordinate")
        if P.dtype not in (torch.float32, torch.float64):
            raise ShapeMismatchError(
                f"positions have dtype {P.dtype}; demonstrations are float32 or float64 (convert with .to(), or pass "
                "dtype= to Demos.from_sequences): half precision cannot hold the Cholesky factors downstream"
            )
        if V.shape != P.shape:
            raise ShapeMismatchError(f"velocities {tuple(V.shape)} do not match positions {tuple(P.shape)}")
        if Tm.shape != (B, T):
            raise ShapeMismatchError(f"times must be (B, T) = {(B, T)}, got {tuple(Tm.shape)}")
        if L.shape != (B,):
            raise ShapeMismatchError(f"lengths must be (B,) = ({B},), got {tuple(L.shape)}")
        if g.shape != (d,):
            raise ShapeMismatchError(f"attractor must have shape ({d},), got {tuple(g.shape)}")
        if not torch.isfinite(g).all():
            raise NonFiniteError("attractor contains NaN or Inf")
        if self.names and len(self.names) != B:
            raise ShapeMismatchError(f"{len(self.names)} names for {B} demonstrations")
        for name, t in (("velocities", V), ("times", Tm), ("attractor", g)):
            if t.device != P.device:
                raise ShapeMismatchError(f"{name} on {t.device}, positions on {P.device}")
            if t.dtype != P.dtype:
                raise ShapeMismatchError(f"{name} has dtype {t.dtype}, positions {P.dtype}")
        self._check_values(P, Tm, L, V)

    # ------------------------------------------------------------------ properties
    @property
    def n_demos(self) -> int:
        return self.positions.shape[0]

    def __len__(self) -> int:
        return self.n_demos

    @property
    def dim(self) -> int:
        return self.positions.shape[-1]

    @property
    def max_length(self) -> int:
        return self.positions.shape[1]

    @property
    def dtype(self) -> torch.dtype:
        return self.positions.dtype

    @property
    def device(self) -> torch.device:
        return self.positions.device

    @property
    def mask(self) -> Tensor:
        """(B, T) bool, True on valid samples."""
        T = self.max_length
        return torch.arange(T, device=self.device).unsqueeze(0) < self.lengths.unsqueeze(1)

    @property
    def start_points(self) -> Tensor:
        """(B, d) first sample of each demonstration."""
        return self.positions[:, 0]

    @property
    def end_points(self) -> Tensor:
        """(B, d) last valid sample of each demonstration."""
        return self.positions[torch.arange(self.n_demos, device=self.device), self.lengths - 1]

    @property
    def durations(self) -> Tensor:
        """(B,) seconds from first to last valid sample."""
        rows = torch.arange(self.n_demos, device=self.device)
        return self.times[rows, self.lengths - 1] - self.times[:, 0]

    @property
    def dt(self) -> Tensor:
        """(B,) median time step of each demonstration, seconds."""
        steps = (self.times[:, 1:] - self.times[:, :-1]).masked_fill(~self.mask[:, 1:], float("nan"))
        return steps.nanmedian(dim=1).values

    # ------------------------------------------------------------------ views and conversions
    def replace(self, **changes: Any) -> Demos:
        """A copy with some fields replaced; validated again."""
        return dataclasses.replace(self, **changes)

    def to(self, dtype: torch.dtype | str | None = None, device: torch.device | str | None = None) -> Demos:
        """Cast floating tensors to ``dtype`` and move everything to ``device`` (names accepted)."""
        f = dict(dtype=resolve_dtype(dtype) or self.dtype, device=resolve_device(device) or self.device)
        return Demos(
            self.positions.to(**f),
            self.velocities.to(**f),
            self.times.to(**f),
            self.lengths.to(device=f["device"]),
            self.attractor.to(**f),
            self.names,
        )

    def _rows(self, index: Index) -> Tensor:
        if isinstance(index, bool) or isinstance(index, (float, str, bytes)) or index is None:
            raise InvalidIndexError(f"index must be an int, a slice, a sequence of ints or a bool mask, got {index!r}")
        if isinstance(index, (int, np.integer)):
            index = int(index)
            if not -self.n_demos <= index < self.n_demos:
                raise InvalidIndexError(f"demonstration index {index} out of range for {self.n_demos} demonstrations")
            return torch.tensor([index % self.n_demos], device=self.device)
        if isinstance(index, slice):
            if index.step == 0:
                raise InvalidIndexError("index: a slice step must not be 0")
            try:
                return torch.arange(self.n_demos, device=self.device)[index]
            except (TypeError, ValueError) as exc:  # a step < 0 (torch has no negative steps) or non-int bounds
                raise InvalidIndexError(f"index: {index!r} is not a slice of ints with a positive step") from exc
        try:
            idx = torch.as_tensor(np.asarray(index) if not isinstance(index, Tensor) else index, device=self.device)
        except (TypeError, ValueError) as exc:
            raise InvalidIndexError(f"index must be an int, a slice, a sequence of ints or a bool mask, got {index!r}") from exc
        if idx.numel() == 0 and idx.dtype != torch.bool:  # np.asarray([]) is float64: say what is wrong
            raise InvalidIndexError(f"index {index!r} selects no demonstration")
        if idx.dtype != torch.bool and (idx.is_floating_point() or idx.is_complex()):
            raise InvalidIndexError(f"index must hold integers or booleans, got {idx.dtype}")
        if idx.dtype == torch.bool:
            if idx.shape != (self.n_demos,):
                raise ShapeMismatchError(f"boolean index of shape {tuple(idx.shape)} for {self.n_demos} demos")
            return torch.nonzero(idx).reshape(-1)
        idx = idx.reshape(-1).long()
        if ((idx < -self.n_demos) | (idx >= self.n_demos)).any():
            raise InvalidIndexError(f"demonstration index out of range for {self.n_demos} demonstrations: {idx.tolist()}")
        return idx % self.n_demos

    def __getitem__(self, index: Index) -> Demos:
        """Select demonstrations (int, slice, index list, bool mask); the result is trimmed to its longest."""
        rows = self._rows(index)
        if rows.numel() == 0:
            raise TooFewSamplesError("selection contains no demonstration")
        L = self.lengths[rows]
        T = int(L.max())
        names = tuple(self.names[int(r)] for r in rows) if self.names else ()
        return Demos(
            self.positions[rows, :T],
            self.velocities[rows, :T],
            self.times[rows, :T],
            L,
            self.attractor,
            names,
        )

    def split(self, index: Index) -> tuple[Demos, Demos]:
        """(selected, rest): e.g. ``train, test = demos.split([0])`` trains on demo 0 and tests on the others."""
        rows = self._rows(index)
        keep = torch.zeros(self.n_demos, dtype=torch.bool, device=self.device)
        keep[rows] = True
        if keep.all():
            raise TooFewSamplesError("split leaves no demonstration in the second part")
        return self[keep], self[~keep]

    def sequences(self) -> list[Tensor]:
        """The B unpadded position sequences, each (T_i, d)."""
        return [self.positions[i, : int(n)] for i, n in enumerate(self.lengths)]

    def samples(self) -> tuple[Tensor, Tensor, Tensor]:
        """All valid samples stacked: positions (N, d), velocities (N, d), demonstration index (N,)."""
        m = self.mask
        demo = torch.arange(self.n_demos, device=self.device).unsqueeze(1).expand_as(m)
        return self.positions[m], self.velocities[m], demo[m]

    @staticmethod
    def concat(parts: Sequence[Demos]) -> Demos:
        """Stack several sets that share dimension, dtype, device and attractor.

        ``parts`` is a list or tuple (or any iterable other than a mapping) of ``Demos``.

        Raises:
            InvalidArgumentError: ``parts`` is a mapping or not iterable, or holds something other than ``Demos``.
            TooFewSamplesError: no part. ShapeMismatchError: parts that do not agree.
        """
        if isinstance(parts, (Mapping, str, bytes, Demos)) or not isinstance(parts, Iterable):
            raise InvalidArgumentError(f"parts must be a list of Demos, got {type(parts).__name__}")
        parts = list(parts)
        for k, p in enumerate(parts):
            if not isinstance(p, Demos):
                raise InvalidArgumentError(f"parts[{k}] must be a Demos, got {type(p).__name__}")
        if not parts:
            raise TooFewSamplesError("nothing to concatenate")
        first = parts[0]
        for k, p in enumerate(parts[1:], 1):
            if p.dim != first.dim:
                raise ShapeMismatchError(f"part {k} has dimension {p.dim}, part 0 has {first.dim}")
            if p.dtype != first.dtype or p.device != first.device:
                raise ShapeMismatchError(f"part {k} is {p.dtype} on {p.device}, part 0 {first.dtype} on {first.device}"
                                         " (convert with .to(dtype=..., device=...))")
            if not torch.equal(p.attractor.to(first.attractor), first.attractor):
                raise ShapeMismatchError(f"part {k} has a different attractor")
        T = max(p.max_length for p in parts)

        def pad(t: Tensor, mode: str) -> Tensor:
            extra = T - t.shape[1]
            if extra == 0:
                return t
            tail = t[:, -1:].expand(-1, extra, *t.shape[2:]) if mode == "edge" else t.new_zeros(
                t.shape[0], extra, *t.shape[2:]
            )
            return torch.cat([t, tail], dim=1)

        names = sum((p.names or tuple("" for _ in range(p.n_demos)) for p in parts), ())
        return Demos(
            torch.cat([pad(p.positions, "edge") for p in parts]),
            torch.cat([pad(p.velocities, "zero") for p in parts]),
            torch.cat([pad(p.times, "edge") for p in parts]),
            torch.cat([p.lengths for p in parts]),
            first.attractor,
            names if any(names) else (),
        )

    def __repr__(self) -> str:
        return (
            f"Demos(n_demos={self.n_demos}, max_length={self.max_length}, dim={self.dim}, "
            f"lengths={self.lengths.tolist() if self.n_demos <= 10 else '...'}, dtype={self.dtype}, "
            f"device={self.device})"
        )
