"""Malformed-input audit of the public API (issue 11): every call gives a typed error or a correct result.

    python experiments/audit_inputs.py [--publish] [--out DIR] [--only GROUP[,GROUP]] [--timeout 20] [--flips -1]

Builds a corpus of calls "of the same kinds" as issue 11 (NaN/Inf, empty, single sample, wrong rank, ragged,
mismatched dimensions, zero velocities, huge magnitudes, int/float16/bool dtypes, wrong types, bad
hyperparameters, damaged files) into every public entry point, on tiny data (three 2-D demonstrations of 50
samples, K <= 3, few iterations). Each call runs under ``signal.alarm`` (``--timeout`` s) and is classified:

    typed          an lfd_torch error (:class:`~lfd_torch.errors.LfdError`) whose message names the argument
    correct        the call returned and the result passed its check (finite; equal to the result on the
                   equivalent float64 input for casts, lists and arrays; a model for valid hyperparameters)
    typed_unnamed  an lfd_torch error whose message does not name the argument (or the file)
    builtin        a builtin exception raised by lfd_torch code itself
    crash          an exception raised from inside torch / numpy / cvxpy / pathlib / ... (not lfd_torch)
    silent         returned although the input was invalid, or returned NaN / garbage
    hang           still running after ``--timeout`` s

A second section flips single bytes of saved files -- every byte of the metadata pickle and every byte (or, with
``--flips N``, a seeded sample of N bytes) of the tensor payload of two saved primitives (LPV-DS, SEDS), a saved
segmentation and every file of a saved skill library -- and counts the flips detected on load (StoreError naming
the file); a flip whose load returns content identical to the saved one (SHA-256 of the loaded state) is counted
as harmless, anything else as missed.

Writes ``audit_inputs.md`` (counts by outcome and group, then every call that failed) into ``--out`` (default
``outputs/audit_inputs``) and, with ``--publish``, into ``results/tables/audit_inputs.md`` of the project root.
Exits 1 if any call is neither typed nor correct or any flip was missed. About 1-2 minutes on one core.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import dataclasses
import math
import signal
import sys
import tempfile
import time
import traceback
import warnings
import zipfile
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

import lfd_torch
from lfd_torch.errors import LfdError, StoreError

PACKAGE_DIR = Path(lfd_torch.__file__).resolve().parent
PASS = ("typed", "correct")
OUTCOMES = ("typed", "correct", "typed_unnamed", "builtin", "crash", "silent", "hang")
F64 = torch.float64


class Hang(BaseException):
    """Raised by the alarm handler; a BaseException so that ``except Exception`` in the library cannot eat it."""


def _on_alarm(signum: int, frame: Any) -> None:
    raise Hang()


@dataclasses.dataclass
class Case:
    """One call of the corpus.

    expect: "error" (the input is invalid: a typed error is required), "either" (a typed error or a result passing
    ``check``), "result" (a result passing ``check`` is required).
    names: strings of which one must appear in a typed error's message (the argument, or the file name).
    """

    group: str
    kind: str
    label: str
    fn: Callable[[], Any]
    expect: str
    names: tuple[str, ...]
    check: Callable[[Any], str | None] | None = None


@dataclasses.dataclass
class Outcome:
    case: Case
    outcome: str
    detail: str
    seconds: float


# ---------------------------------------------------------------------------------------------- result checks
def _leaves(out: Any, depth: int = 0) -> list[Any]:
    """Tensors, arrays and floats inside a result (tuples, lists, dicts, dataclasses), in a stable order."""
    if depth > 4:
        return []
    if isinstance(out, Tensor):
        return [out]
    if isinstance(out, np.ndarray):
        return [torch.from_numpy(np.array(out, dtype=np.float64))] if out.dtype.kind in "fiub" else []
    if isinstance(out, float):
        return [torch.tensor(out, dtype=F64)]
    if isinstance(out, (tuple, list)):
        return [t for o in out for t in _leaves(o, depth + 1)]
    if isinstance(out, dict):  # "info" holds timings, which differ between identical calls
        return [t for k in sorted(out, key=str) if k != "info" for t in _leaves(out[k], depth + 1)]
    if dataclasses.is_dataclass(out) and not isinstance(out, type):
        return [t for f in dataclasses.fields(out) if f.name != "info" for t in _leaves(getattr(out, f.name), depth + 1)]
    return []


def finite(out: Any) -> str | None:
    """None if every floating tensor in ``out`` is finite, else what is wrong."""
    for t in _leaves(out):
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            return f"non-finite values in a {tuple(t.shape)} result"
    return None


def same_as(reference: Callable[[], Any], rtol: float = 1e-6) -> Callable[[Any], str | None]:
    """A check: finite, and equal (rtol) to ``reference()`` -- the call on the equivalent valid input."""

    def check(out: Any) -> str | None:
        bad = finite(out)
        if bad:
            return bad
        ref = _leaves(reference())
        got = _leaves(out)
        if len(ref) != len(got):
            return f"{len(got)} result tensors, the float64 call gives {len(ref)}"
        for a, b in zip(got, ref):
            if a.shape != b.shape:
                return f"result shape {tuple(a.shape)}, the float64 call gives {tuple(b.shape)}"
            a64, b64 = a.detach().cpu().to(F64), b.detach().cpu().to(F64)
            if not torch.allclose(a64, b64, rtol=rtol, atol=rtol * (1.0 + float(b64.abs().max()) if b64.numel() else 1)):
                return "result differs from the call on the equivalent float64 input"
        return None

    return check


def all_of(*checks: Callable[[Any], str | None]) -> Callable[[Any], str | None]:
    def check(out: Any) -> str | None:
        for c in checks:
            bad = c(out)
            if bad:
                return bad
        return None

    return check


# ---------------------------------------------------------------------------------------------- running
def _innermost_frame(exc: BaseException) -> str:
    tb = exc.__traceback__
    last = None
    while tb is not None:
        last = tb
        tb = tb.tb_next
    return last.tb_frame.f_code.co_filename if last is not None else ""


def run_case(case: Case, timeout: int) -> Outcome:
    t0 = time.perf_counter()
    signal.alarm(timeout)
    try:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                out = case.fn()
                bad = None
                if case.expect != "error":
                    bad = (case.check or finite)(out)
        finally:
            signal.alarm(0)
    except Hang:
        return Outcome(case, "hang", f"still running after {timeout} s", time.perf_counter() - t0)
    except LfdError as exc:
        msg = str(exc)
        dt = time.perf_counter() - t0
        if case.expect == "result":
            return Outcome(case, "silent", f"a valid input was rejected: {type(exc).__name__}: {msg}", dt)
        named = any(n.lower() in msg.lower() for n in case.names)
        return Outcome(case, "typed" if named else "typed_unnamed", f"{type(exc).__name__}: {msg}", dt)
    except Exception as exc:  # noqa: BLE001 -- classifying every failure is the point
        where = _innermost_frame(exc)
        inside = Path(where).resolve().is_relative_to(PACKAGE_DIR) if where else False
        kind = "builtin" if inside else "crash"
        return Outcome(case, kind, f"{type(exc).__name__}: {exc} [{Path(where).name}]", time.perf_counter() - t0)
    dt = time.perf_counter() - t0
    if case.expect == "error":
        return Outcome(case, "silent", "returned although the input is invalid", dt)
    if bad:
        return Outcome(case, "silent", bad, dt)
    return Outcome(case, "correct", "", dt)


# ---------------------------------------------------------------------------------------------- corpus helpers
def _with(t: Tensor, index: tuple, value: float) -> Tensor:
    t = t.clone()
    t[index] = value
    return t


def tensor_cases(
    group: str,
    arg: str,
    call: Callable[[Any], Any],
    good: Tensor,
    *,
    names: Sequence[str] = (),
    rows: bool = True,
    batched: bool = False,
    single_ok: bool = False,
    empty_ok: bool = False,
    mismatch_ok: bool = False,
    optional: bool = False,
    check: Callable[[Any], str | None] | None = None,
) -> list[Case]:
    """The standard malformed variants of one tensor argument ``arg`` (good value ``good``, float64).

    rows: the argument has a sample axis (-2) that can be emptied or cut to one sample.
    batched: extra leading dimensions are valid (the result must then be finite).
    single_ok / empty_ok: one sample / zero samples are valid inputs (then the result must be finite).
    """
    names = (arg, *names)
    first = (0,) * good.dim()
    out: list[Case] = []

    def add(kind: str, label: str, value: Any, expect: str, chk: Callable[[Any], str | None] | None = None) -> None:
        out.append(Case(group, kind, f"{arg}: {label}", lambda v=value: call(v), expect, names, chk or check))

    add("nan", "NaN entry", _with(good, first, math.nan), "error")
    add("inf", "+Inf entry", _with(good, first, math.inf), "error")
    add("inf", "-Inf entry", _with(good, tuple(i - 1 for i in good.shape), -math.inf), "error")
    if rows and good.dim() >= 2:
        add("empty", "zero samples", good[..., :0, :], "either" if empty_ok else "error")
        add("single", "one sample", good[..., :1, :], "either" if single_ok else "error")
    else:
        add("empty", "empty tensor", good.reshape(-1)[:0], "error")
    if good.dim() >= 1:
        add("rank", "last axis dropped", good[..., 0], "error")
        add("mismatch", "one extra coordinate", torch.cat([good, good[..., :1]], -1),
            "either" if mismatch_ok else "error")
    add("rank", "0-d tensor", torch.tensor(1.0, dtype=F64), "error")
    add("rank", "two extra leading axes", good[None, None], "either" if batched else "error")
    add("huge", "magnitude 1e200", good * 1e200, "either")
    as_int = good.round().to(torch.int64)
    add("dtype", "int64", as_int, "either", same_as(lambda: call(as_int.to(F64))))
    as_half = good.to(torch.float16)
    add("dtype", "float16", as_half, "either", same_as(lambda: call(as_half.to(F64)), rtol=1e-2))
    add("dtype", "bool", good != 0, "either", same_as(lambda: call((good != 0).to(F64))))
    add("dtype", "complex128", good.to(torch.complex128), "error")
    add("type", "nested list", good.tolist(), "either", same_as(lambda: call(good)))
    add("type", "numpy array", good.numpy(), "either", same_as(lambda: call(good)))
    add("type", "a string", "abc", "error")
    if not optional:
        add("type", "None", None, "error")
    return out


def value_cases(
    group: str,
    arg: str,
    call: Callable[[Any], Any],
    bad: Iterable[Any],
    good: Iterable[Any] = (),
    *,
    kind: str = "hyper",
    names: Sequence[str] = (),
    check: Callable[[Any], str | None] | None = None,
) -> list[Case]:
    """Calls with ``arg`` set to each bad value (a typed error required) and each good one (a result required)."""
    names = (arg, *names)
    out = [Case(group, kind, f"{arg}={v!r}"[:80], lambda v=v: call(v), "error", names) for v in bad]
    out += [Case(group, kind, f"{arg}={v!r} (valid)"[:80], lambda v=v: call(v), "result", names, check) for v in good]
    return out


COUNT_BAD = (0, -1, 2.5, "3", None, True, math.nan)
POSITIVE_BAD = (0.0, -1.0, math.nan, math.inf, "1", None)
NONNEG_BAD = (-1.0, math.nan, math.inf, "1")
PROB_BAD = (-0.1, 1.5, math.nan, "0.5")


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ---------------------------------------------------------------------------------------------- fixtures
@dataclasses.dataclass
class Fixtures:
    demos: Any
    x: Tensor
    x_dot: Tensor
    lpvds: Any
    seds: Any
    multi: Any
    segmentation: Any
    library: Any
    tmp: Path


def build_fixtures(tmp: Path) -> Fixtures:
    from lfd_torch.data import Demos
    from lfd_torch.ds import fit_lpvds, fit_seds
    from lfd_torch.gmm import EMFitter
    from lfd_torch.segmentation import FixedSegmenter
    from lfd_torch.segmentation.synthetic import multi_step_demos
    from lfd_torch.skills import SkillLibrary

    t = torch.linspace(0, 3, 50, dtype=F64)
    seqs = []
    for a, b in [(1.0, 0.5), (0.8, 0.9), (1.2, 0.2)]:
        th, r = 1.5 * torch.exp(-t), torch.exp(-1.2 * t)
        seqs.append(torch.stack([10 * a * r * torch.cos(th), 10 * b * r * torch.sin(th) + 5 * r], -1))
    demos = Demos.from_sequences(seqs, dt=3 / 49)
    x, x_dot, _ = demos.samples()
    lpvds = fit_lpvds(demos, gmm=EMFitter(n_components=2, max_iter=20), generator=gen(0))
    seds = fit_seds(demos, n_components=2, max_iter=30, generator=gen(0))
    corners = torch.tensor([[-1.0, 1.0], [-1.0, 0.0], [0.0, 0.0]], dtype=F64)
    multi = multi_step_demos(gen(0), n_demos=2, waypoints=corners, samples_per_step=25, timing_jitter=0.0).demos
    segmentation = FixedSegmenter([0.5])(multi)
    library = SkillLibrary.learn(multi, segmentation, generator=gen(1), check=False)
    return Fixtures(demos, x, x_dot, lpvds, seds, multi, segmentation, library, tmp)


# ---------------------------------------------------------------------------------------------- corpus: data
def corpus_demos(fx: Fixtures) -> list[Case]:
    from lfd_torch.data import Demos

    seq = fx.demos.sequences()[0]
    g = "Demos"
    cases = tensor_cases(g, "positions", lambda v: Demos.from_sequences([v], dt=0.1), seq,
                         names=("demonstration",), mismatch_ok=True, check=finite)  # fmt: skip
    cases += tensor_cases(g, "positions[1]", lambda v: Demos.from_sequences([seq, v], dt=0.1), seq,
                          names=("positions", "demonstration", "dimension"), check=finite)  # fmt: skip
    ragged = [seq, seq[:, :1]]
    cases += [
        Case(g, "ragged", "positions: dimensions differ", lambda: Demos.from_sequences(ragged, dt=0.1), "error",
             ("dimension",)),
        Case(g, "empty", "positions: empty list", lambda: Demos.from_sequences([], dt=0.1), "error",
             ("demonstration",)),
        Case(g, "ragged", "positions: ragged nested list (rows of 2 and 3 numbers)",
             lambda: Demos.from_sequences([[[0.0, 1.0], [0.0, 1.0, 2.0], [1.0, 1.0]]], dt=0.1), "error",
             ("positions",)),
        Case(g, "ragged", "positions: sequences of different lengths (valid)",
             lambda: Demos.from_sequences([seq, seq[:20]], dt=0.1), "result", ("positions",),
             lambda d: None if d.lengths.tolist() == [50, 20] and not finite(d.positions) else "wrong lengths"),
        Case(g, "ragged", "times: ragged list of stamps",
             lambda: Demos.from_sequences([seq], times=[[0.0, [1.0]] + [2.0] * 48]), "error", ("times",)),
        Case(g, "ragged", "velocities: one row short",
             lambda: Demos.from_sequences([seq], dt=0.1, velocities=[seq[:-1]]), "error", ("velocit",)),
        Case(g, "mismatch", "times: fewer stamps than samples",
             lambda: Demos.from_sequences([seq], times=[torch.arange(10, dtype=F64)]), "error", ("time",)),
        Case(g, "hyper", "times: decreasing",
             lambda: Demos.from_sequences([seq], times=[-torch.arange(50, dtype=F64)]), "error", ("time",)),
        Case(g, "hyper", "times: repeated stamp",
             lambda: Demos.from_sequences([seq], times=[torch.zeros(50, dtype=F64)]), "error", ("time",)),
        Case(g, "zero_velocity", "positions: one repeated point (zero velocities)",
             lambda: Demos.from_sequences([seq[:1].expand(50, 2).clone()], dt=0.1), "either", ("positions",),
             finite),
        Case(g, "mismatch", "velocities: wrong shape",
             lambda: Demos.from_sequences([seq], dt=0.1, velocities=[seq[:, :1]]), "error", ("velocit",)),
        Case(g, "mismatch", "attractor: wrong dimension",
             lambda: Demos.from_sequences([seq], dt=0.1, attractor=torch.zeros(3, dtype=F64)), "error",
             ("attractor",)),
        Case(g, "nan", "attractor: NaN",
             lambda: Demos.from_sequences([seq], dt=0.1, attractor=torch.tensor([math.nan, 0.0], dtype=F64)),
             "error", ("attractor",)),
        Case(g, "type", "names: wrong count",
             lambda: Demos.from_sequences([seq], dt=0.1, names=["a", "b"]), "error", ("names",)),
        Case(g, "type", "velocity_scheme: unknown",
             lambda: Demos.from_sequences([seq], dt=0.1, velocity_scheme="bogus"), "error", ("scheme",)),
        Case(g, "dtype", "dtype: int64",
             lambda: Demos.from_sequences([seq], dt=0.1, dtype=torch.int64), "error", ("dtype",)),
        Case(g, "dtype", "dtype: float16",
             lambda: Demos.from_sequences([seq], dt=0.1, dtype=torch.float16), "error", ("dtype",)),
        Case(g, "type", "positions: a string", lambda: Demos.from_sequences("abc", dt=0.1), "error",
             ("positions", "demonstration")),
        Case(g, "type", "positions: a tensor, not a list", lambda: Demos.from_sequences(seq, dt=0.1), "error",
             ("positions", "demonstration")),
    ]  # fmt: skip
    cases += value_cases(g, "dt", lambda v: Demos.from_sequences([seq], dt=v), (0.0, -0.1, math.nan, math.inf, "x"),
                         (0.05,))  # fmt: skip
    P, V, T, L, A = (fx.demos.positions, fx.demos.velocities, fx.demos.times, fx.demos.lengths, fx.demos.attractor)
    cases += tensor_cases(g, "Demos.positions", lambda v: Demos(v, V, T, L, A), P, rows=False,
                          names=("positions",), check=finite)  # fmt: skip
    cases += value_cases(g, "lengths", lambda v: Demos(P, V, T, v, A),
                         (torch.tensor([2, 50, 50]), torch.tensor([51, 50, 50]), torch.tensor([50, 50]),
                          torch.tensor([50.5, 50, 50]), [50, 50, 50], None),
                         kind="mismatch")  # fmt: skip
    cases += value_cases(g, "index", lambda v: fx.demos[v], (5, -9, [0, 7], "a", 1.5, slice(None, None, 0),
                                                             slice(None, None, -1), slice("a", None)),
                         (0, [0, 2], slice(0, 3, 2)), kind="type", names=("demonstration",))  # fmt: skip
    cases += [
        Case(g, "mismatch", "times: a (2, 25) array for 50 samples",
             lambda: Demos.from_sequences([seq], times=[torch.arange(50, dtype=F64).reshape(2, 25)]), "error",
             ("times",)),
        Case(g, "dtype", "concat: float64 and float32 parts",
             lambda: Demos.concat([fx.demos, fx.demos.to(dtype=torch.float32)]), "error", ("float32", "dtype")),
    ]  # fmt: skip
    bad_devices = ("bogus", 3) + (() if torch.cuda.is_available() else ("cuda",))
    cases += value_cases(g, "device", lambda v: fx.demos.to(device=v), bad_devices, ("cpu",), kind="type",
                         check=lambda d: finite(d.positions))  # fmt: skip
    return cases


def corpus_preprocess(fx: Fixtures) -> list[Case]:
    from lfd_torch import preprocess as pp

    d = fx.demos
    g = "preprocess"

    def pre(**kw: Any) -> Any:
        return pp.Preprocess(**kw)(d)

    cases: list[Case] = []
    cases += value_cases(g, "window", lambda v: pre(window=v), (0, -3, 2.5, "5", None, 4, 10**6), (7,))
    cases += value_cases(g, "polyorder", lambda v: pre(window=7, polyorder=v), (-1, 7, 2.5, "2", None), (2,))
    cases += value_cases(g, "n_samples", lambda v: pre(n_samples=v), (0, 1, -5, 2.5, "40", 10**9), (40, None))
    cases += value_cases(g, "subsample_step", lambda v: pre(subsample_step=v), (0, -2, 1.5, "2", None), (2,))
    cases += value_cases(g, "screen_threshold", lambda v: pre(screen_threshold=v), (-0.1, 1.5, math.nan, "0.1"),
                         (0.01,))  # fmt: skip
    cases += value_cases(g, "smoothing", lambda v: pre(smoothing=v), ("bogus", 3, None), ("none", "moving_average"))
    cases += value_cases(g, "resample_mode", lambda v: pre(n_samples=30, resample_mode=v), ("bogus", 1), ("arc_length",))
    cases += value_cases(g, "velocity_scheme", lambda v: pre(velocity_scheme=v), ("bogus", None), ("forward",))
    cases += value_cases(g, "trim_position_tol", lambda v: pre(trim_position_tol=v, trim_velocity_tol=0.1),
                         (-1.0, math.nan, "x"), (0.01,))  # fmt: skip
    cases += value_cases(g, "demos", lambda v: pp.Preprocess()(v), (None, fx.x, [fx.x], "abc"), kind="type")
    for fn, arg, bad in [
        (lambda v: pp.resample(d, v), "n_samples", (0, 1, 2.5, -3, None, 10**9)),
        (lambda v: pp.subsample(d, v), "step", (0, -1, 2.5, None)),
        (lambda v: pp.moving_average(d, v), "window", (0, -1, 2.5, 10**6, None)),
        (lambda v: pp.savitzky_golay(d, v), "window", (0, 4, 2.5, 10**6, None)),
        (lambda v: pp.smooth(d, 7, method=v), "method", ("bogus", None)),
        (lambda v: pp.estimate_velocities(d, v), "scheme", ("bogus", None)),
        (lambda v: pp.trim_still_tail(d, v, 0.1), "position_tol", (-1.0, math.nan, None)),
        (lambda v: pp.screen_dimensions(d, v), "threshold", (-1.0, 2.0, math.nan, None)),
        (lambda v: pp.dimension_shares(v), "demos", (None, fx.x, "abc")),
    ]:
        cases += value_cases(g, arg, fn, bad)
    return cases


def corpus_loaders(fx: Fixtures) -> list[Case]:
    from lfd_torch.data import load_lasa, load_mnist, mnist_demos, read_idx

    g = "loaders"
    tmp = fx.tmp / "idx"
    tmp.mkdir()
    good = tmp / "good.idx"
    good.write_bytes(bytes([0, 0, 8, 2]) + (2).to_bytes(4, "big") + (3).to_bytes(4, "big") + bytes(range(6)))
    files = {
        "missing": tmp / "missing.idx",
        "empty": tmp / "empty.idx",
        "random": tmp / "random.idx",
        "truncated": tmp / "truncated.idx",
        "bad_type": tmp / "badtype.idx",
        "too_long": tmp / "long.idx",
        "bad_gzip": tmp / "bad.idx.gz",
        "directory": tmp / "dir.idx",
    }
    files["empty"].write_bytes(b"")
    files["random"].write_bytes(np.random.default_rng(0).bytes(64))
    files["truncated"].write_bytes(good.read_bytes()[:-2])
    files["bad_type"].write_bytes(bytes([0, 0, 7, 2]) + good.read_bytes()[4:])
    files["too_long"].write_bytes(good.read_bytes() + b"\0\0")
    files["bad_gzip"].write_bytes(b"\x1f\x8b\x08\x00garbage")
    files["directory"].mkdir()
    cases = [Case(g, "file", f"read_idx: {k} file", lambda p=p: read_idx(p), "error", (p.name,))
             for k, p in files.items()]  # fmt: skip
    cases.append(Case(g, "file", "read_idx: valid file", lambda: read_idx(good), "result", ("path",),
                      lambda a: None if a.shape == (2, 3) and a.tolist() == [[0, 1, 2], [3, 4, 5]] else "wrong"))
    cases += value_cases(g, "read_idx path", read_idx, (None, 3), kind="type", names=("path",))
    cases += value_cases(g, "shape", lambda v: load_lasa(v), ("NotAShape", "", None, 3, "angle"), kind="type",
                         names=("LASA",))  # fmt: skip
    cases += value_cases(g, "dtype", lambda v: load_lasa("Angle", dtype=v), ("int64", torch.int64, "float16", "x"),
                         ("float32",), names=("LASA",))  # fmt: skip
    cases += value_cases(g, "split", lambda v: load_mnist(v, directory=tmp), ("bogus", None, 3), kind="type")
    cases += value_cases(g, "directory", lambda v: load_mnist("test", directory=v),
                         (tmp / "nowhere", files["random"], 3), kind="file", names=("mnist", "MNIST", "director"))  # fmt: skip
    from lfd_torch.data import extract_stroke

    digit = torch.zeros(28, 28, dtype=F64)
    digit[6:22, 12:16] = 255.0  # a stroke of a "1" (grey levels 0..255)
    cases += value_cases(g, "image", extract_stroke, (torch.zeros(28), digit * math.nan, "abc", None, digit[:1],
                                                      torch.zeros(28, 28)),
                         (digit,), kind="type", names=("image", "ink"),
                         check=lambda st: None if st.path.shape[-1] == 2 and np.isfinite(st.path).all() else "bad")
    cases += value_cases(g, "upsample", lambda u: extract_stroke(digit, upsample=u), (0, 2.5, 10**6, "4"))
    cases += value_cases(g, "threshold", lambda u: extract_stroke(digit, threshold=u), (0.0, 1.0, math.nan, "x"))
    cases += value_cases(g, "digit", lambda v: mnist_demos(v, directory=tmp), (-1, 10, 2.5, "3", None))
    cases += value_cases(g, "n_demos", lambda v: mnist_demos(3, v, directory=tmp), (0, -1, 2.5, 10**9))
    cases += value_cases(g, "n_points", lambda v: mnist_demos(3, 2, n_points=v, directory=tmp), (0, 2, 2.5, 10**9))
    cases += value_cases(g, "cusp_angle", lambda v: mnist_demos(3, 2, cusp_angle=v, directory=tmp), (0.0, "x"))
    from lfd_torch.data import stroke_trajectory

    pen = np.stack([np.r_[np.linspace(0, 10, 41), np.linspace(10, 4, 25)[1:]], np.zeros(65)], 1)  # out and back
    rests = lambda r: None if np.linalg.norm(r[2], axis=1)[len(r[1]) // 2 - 40: len(r[1]) // 2 + 40].min() < 0.05 \
        else "no rest at the cusp"  # noqa: E731
    cases += value_cases(g, "cusp_angle", lambda v: stroke_trajectory(pen, cusp_angle=v),
                         (0.0, 180.0, -30.0, math.nan, "120"), (120.0, 90.0), check=rests)
    cases += value_cases(g, "cusp_window", lambda v: stroke_trajectory(pen, cusp_window=v),
                         (0.0, -1.0, math.nan, math.inf, "1", None), (1.0, 0.5), check=rests)
    return cases


# ---------------------------------------------------------------------------------------------- corpus: gmm
def corpus_gmm(fx: Fixtures) -> list[Case]:
    from lfd_torch import gmm as G

    x, v = fx.x, fx.x_dot
    cases: list[Case] = []
    fitters = {
        "EM": (lambda a, b, **kw: G.fit_em(a, 2, generator=gen(), max_iter=10, **kw)),
        "PC-GMM": (lambda a, b, **kw: G.fit_pcgmm(a, b, generator=gen(), n_iter=3, **kw)),
        "DAMM": (lambda a, b, **kw: G.fit_damm(a, b, generator=gen(), n_iter=3, **kw)),
    }
    for name, fit in fitters.items():
        g = f"gmm {name}"
        cases += tensor_cases(g, "x", lambda a, fit=fit: fit(a, v), x, mismatch_ok=name == "EM")
        if name != "EM":
            cases += tensor_cases(g, "x_dot", lambda b, fit=fit: fit(x, b), v)
            cases.append(Case(g, "zero_velocity", "x_dot: all zero", lambda fit=fit: fit(x, torch.zeros_like(v)),
                              "either", ("x_dot", "velocit")))  # fmt: skip
        cases.append(Case(g, "zero_velocity", "x: one repeated point",
                          lambda fit=fit: fit(x[:1].expand_as(x).clone(), v), "either", ("x",)))  # fmt: skip
    g = "gmm EM"
    cases += value_cases(g, "n_components", lambda k: G.fit_em(x, k, generator=gen(), max_iter=5),
                         COUNT_BAD + (10**6, 1000), (1, 3))  # fmt: skip
    cases += value_cases(g, "max_iter", lambda k: G.fit_em(x, 2, generator=gen(), max_iter=k),
                         (-1, 2.5, "3", None, True, math.nan, 10**12), (0, 1))  # fmt: skip
    cases += value_cases(g, "n_init", lambda k: G.fit_em(x, 2, generator=gen(), n_init=k, max_iter=5),
                         COUNT_BAD + (10**9,))  # fmt: skip
    cases += value_cases(g, "tol", lambda t: G.fit_em(x, 2, generator=gen(), tol=t, max_iter=5), NONNEG_BAD)
    cases += value_cases(g, "reg_covar", lambda t: G.fit_em(x, 2, generator=gen(), reg_covar=t, max_iter=5),
                         NONNEG_BAD)  # fmt: skip
    cases += value_cases(g, "generator", lambda r: G.fit_em(x, 2, generator=r, max_iter=5), (None, 0, "seed"))
    cases += value_cases(g, "k_range", lambda r: G.fit_em_bic(x, k_range=r, generator=gen(), max_iter=5),
                         ([], [0, 1], [2.5], "abc", None, range(1, 10**7)), ([1, 2],))  # fmt: skip
    g = "gmm PC-GMM"
    for arg, bad in [("alpha", POSITIVE_BAD), ("length_scale", (0.0, -1.0, math.nan, "1")),
                     ("n_iter", COUNT_BAD + (10**9,)), ("max_points", (0, -1, 2.5, "5", 10**9)),
                     ("min_cluster_size", (0, -1, 2.5, "5")), ("reg_covar", NONNEG_BAD)]:  # fmt: skip
        cases += value_cases(g, arg, lambda val, arg=arg: G.fit_pcgmm(x, v, generator=gen(), **{"n_iter": 3, arg: val}),
                             bad)  # fmt: skip
    cases += value_cases(g, "generator", lambda r: G.PCGMMFitter(n_iter=3)(x, v, generator=r), (None, 1))
    g = "gmm DAMM"
    for arg, bad in [("alpha", POSITIVE_BAD), ("kappa", POSITIVE_BAD), ("n_iter", COUNT_BAD + (10**9,)),
                     ("nu0_offset", (-5.0, math.nan)), ("reg_covar", NONNEG_BAD)]:  # fmt: skip
        cases += value_cases(g, arg, lambda val, arg=arg: G.fit_damm(x, v, generator=gen(), **{"n_iter": 3, arg: val}),
                             bad)  # fmt: skip
    cases += value_cases(g, "generator", lambda r: G.DAMMFitter(n_iter=3)(x, v, generator=r), (None, 1))
    g = "gmm fitters"
    cases += value_cases(g, "x_dot", lambda b: G.PCGMMFitter(n_iter=3)(x, b, generator=gen()), (None,))
    cases += value_cases(g, "EMFitter n_components", lambda k: G.EMFitter(n_components=k)(x, generator=gen()),
                         (0, -1, 2.5, "2", None), names=("n_components",))  # fmt: skip
    cases += value_cases(g, "EMBICFitter k_range", lambda k: G.EMBICFitter(k_range=k)(x, generator=gen()),
                         ((), (0,), "ab", None), names=("k_range",))  # fmt: skip
    gm = fx.lpvds.gmm
    cases += tensor_cases("gmm GMM", "x", lambda a: gm.log_prob(a), x, single_ok=True, empty_ok=True, batched=True)
    cases += value_cases("gmm GMM", "weights", lambda w: G.GMM(w, gm.means, gm.covariances),
                         (torch.tensor([0.5, 0.6], dtype=F64), torch.tensor([-0.5, 1.5], dtype=F64),
                          torch.tensor([math.nan, 1.0], dtype=F64), torch.tensor([1.0], dtype=F64), None),
                         names=("weight",))  # fmt: skip
    cases += value_cases("gmm GMM", "covariances", lambda c: G.GMM(gm.weights, gm.means, c),
                         (-gm.covariances, gm.covariances[:, :1], gm.covariances * math.nan, None),
                         names=("covariance",))  # fmt: skip
    return cases


# ---------------------------------------------------------------------------------------------- corpus: ds
def corpus_ds(fx: Fixtures) -> list[Case]:
    from lfd_torch.data import Demos
    from lfd_torch.ds import fit_lpvds, fit_seds, load_primitive
    from lfd_torch.gmm import EMFitter

    d = fx.demos
    em = EMFitter(n_components=2, max_iter=10)
    cases: list[Case] = []

    def lpv(**kw: Any) -> Any:
        return fit_lpvds(kw.pop("demos", d), gmm=kw.pop("gmm", em), generator=kw.pop("generator", gen()), **kw)

    def sed(**kw: Any) -> Any:
        kw.setdefault("n_components", 2)
        kw.setdefault("max_iter", 10)
        return fit_seds(kw.pop("demos", d), generator=kw.pop("generator", gen()), **kw)

    def certified(model: Any) -> str | None:
        return finite(model) or (None if model.stability_certificate().certified else "not certified")

    seq = d.sequences()
    still = Demos.from_sequences([s[:1].expand(50, 2).clone() for s in seq], dt=0.1)
    for g, fit in (("fit_lpvds", lpv), ("fit_seds", sed)):
        cases += value_cases(g, "demos", lambda v, fit=fit: fit(demos=v), (None, fx.x, seq, "abc", 3), kind="type")
        cases += tensor_cases(g, "attractor", lambda a, fit=fit: fit(attractor=a), d.attractor, rows=False,
                              optional=True, check=certified)  # fmt: skip
        cases.append(Case(g, "zero_velocity", "demos: every sample at rest (one repeated point)",
                          lambda fit=fit: fit(demos=still), "either", ("demos", "rest", "samples"), certified))
        cases.append(Case(g, "huge", "demos: magnitude 1e150",
                          lambda fit=fit: fit(demos=Demos.from_sequences([s * 1e150 for s in seq], dt=0.1)), "either",
                          ("demos", "positions"), certified))  # fmt: skip
        cases.append(Case(g, "dtype", "demos: float32 (valid)",
                          lambda fit=fit: fit(demos=d.to(torch.float32)), "result", ("demos",), certified))
        cases += value_cases(g, "eps", lambda e, fit=fit: fit(eps=e), POSITIVE_BAD)
        cases += value_cases(g, "generator", lambda r, fit=fit: fit(generator=r), (0, "seed"))
    g = "fit_lpvds"
    cases += value_cases(g, "gmm", lambda m: lpv(gmm=m), (3, "bogus", fx.seds.gmm.replace(
        means=fx.seds.gmm.means[:, :1], covariances=fx.seds.gmm.covariances[:, :1, :1])), (None,),
                         check=certified)  # fmt: skip  (None: PC-GMM with its defaults)
    cases += value_cases(g, "lyapunov", lambda m: lpv(lyapunov=m),
                         ("sos", 3, torch.eye(3, dtype=F64), -torch.eye(2, dtype=F64),
                          torch.full((2, 2), math.nan, dtype=F64)), ("qlf",), check=certified)  # fmt: skip
    cases += value_cases(g, "ridge", lambda r: lpv(ridge=r), NONNEG_BAD)
    cases += value_cases(g, "p_margin", lambda r: lpv(p_margin=r), NONNEG_BAD)
    cases += value_cases(g, "p_min_eigenvalue", lambda r: lpv(p_min_eigenvalue=r), POSITIVE_BAD)
    cases += value_cases(g, "solvers", lambda s: lpv(solvers=s), (["NOT_A_SOLVER"], [], 3, None))
    cases += value_cases(g, "solver_options", lambda o: lpv(solver_options=o, solvers=["CLARABEL"]),
                         ({"CLARABEL": {"bogus_option": 1}}, {"CLARABEL": 3}, "abc", {"CLARABEL": {"max_iter": -1}}),
                         names=("solver", "option"))  # fmt: skip
    g = "fit_seds"
    cases += value_cases(g, "n_components", lambda k: sed(n_components=k), (0, -1, 2.5, "2", True, 10**6), (1, 3),
                         check=certified)  # fmt: skip
    cases += value_cases(g, "max_iter", lambda k: sed(max_iter=k), (0, -1, 2.5, "5", None, 10**12), (1,),
                         check=certified)  # fmt: skip
    cases += value_cases(g, "max_restarts", lambda k: sed(max_restarts=k), (-1, 2.5, "1", None, 10**9))
    cases += value_cases(g, "em_n_init", lambda k: sed(em_n_init=k), (0, -1, 2.5, None, 10**9))
    cases += value_cases(g, "reg", lambda r: sed(reg=r), POSITIVE_BAD)
    cases += value_cases(g, "gain_prior", lambda r: sed(gain_prior=r), (0.0, -1.0, math.nan, "1"), (None,),
                         check=certified)  # fmt: skip
    cases += value_cases(g, "tolerance_grad", lambda r: sed(tolerance_grad=r), NONNEG_BAD)
    cases += value_cases(g, "tolerance_change", lambda r: sed(tolerance_change=r), NONNEG_BAD)
    cases += value_cases(g, "objective", lambda o: sed(objective=o), ("bogus", None, 1), ("mse",), check=certified)
    cases += value_cases(g, "k_selection", lambda o: sed(n_components=None, k_selection=o), ("bogus", None))
    cases += value_cases(g, "k_range", lambda r: sed(n_components=None, k_selection="bic", k_range=r),
                         ([], [0], [2.5], "ab", None, range(2, 10**7)))  # fmt: skip
    for name, model in (("LPVDS", fx.lpvds), ("SEDS", fx.seds)):
        g = f"primitive {name}"
        x = fx.x[:7]
        for method in ("__call__", "lyapunov", "lyapunov_derivative"):
            fn = model if method == "__call__" else getattr(model, method)
            cases += tensor_cases(g, "x", lambda a, fn=fn: fn(a), x, names=(method,), single_ok=True,
                                  empty_ok=True, batched=True)  # fmt: skip
        cases += value_cases(g, "dtype", lambda t, m=model: m.to(dtype=t)(x.to(t)),
                             (torch.int64, torch.float16, "float16"), (torch.float32,))  # fmt: skip
        saved = model.save(fx.tmp / f"{name}_args.pt")
        cases += value_cases(g, "load_primitive dtype", lambda t, f=saved: load_primitive(f, dtype=t),
                             (torch.int64, torch.float16, "bogus", 3), ("float32",), names=("dtype",),
                             check=lambda m: finite(m(x.to(m.dtype))))  # fmt: skip
        cases += value_cases(g, "load_primitive device", lambda v, f=saved: load_primitive(f, device=v),
                             ("bogus", 3) + (() if torch.cuda.is_available() else ("cuda",)), ("cpu",),
                             names=("device",), check=lambda m: finite(m(x)))  # fmt: skip
    return cases


# ---------------------------------------------------------------------------------------------- corpus: segmentation
def corpus_segmentation(fx: Fixtures) -> list[Case]:
    from lfd_torch.segmentation import FixedSegmenter, Segmentation, segment

    d = fx.multi
    g = "segment"

    def seg(**kw: Any) -> Any:
        kw.setdefault("n_chains", 1)
        kw.setdefault("n_iterations", 4)
        return segment(kw.pop("demos", d), generator=kw.pop("generator", gen()), **kw)

    from lfd_torch.data import Demos

    still = Demos.from_sequences([s[:1].expand(40, 2).clone() for s in d.sequences()], dt=0.1)
    cases = value_cases(g, "demos", lambda v: seg(demos=v), (None, "abc", 3, [], [torch.zeros(5, 2, dtype=F64)],
                                                             [torch.full((40, 2), math.nan, dtype=F64)]),
                        kind="type")  # fmt: skip
    cases.append(Case(g, "zero_velocity", "demos: one repeated point", lambda: seg(demos=still), "either",
                      ("demos", "demonstration", "rest", "samples")))  # fmt: skip
    cases += value_cases(g, "generator", lambda r: seg(generator=r), (None, 0))
    from lfd_torch.segmentation import BPGMHMMSegmenter
    from lfd_torch.segmentation.synthetic import multi_step_demos

    clean = multi_step_demos(gen(0), n_demos=1, n_steps=3, profile="constant", noise=0.0).demos
    cases.append(Case(g, "zero_noise", "demos: a generated path without noise (valid)", lambda: seg(demos=clean),
                      "result", ("demos",), lambda r: None if r.n_steps >= 1 else "no step"))
    cases += value_cases("BPGMHMMSegmenter", "hyperparameters", lambda kw: BPGMHMMSegmenter(**kw),
                         ({"stickines": 25.0}, {"foo": 1}), names=("stickines", "foo"))  # fmt: skip
    for arg, bad in [("n_chains", COUNT_BAD + (10**6,)), ("n_iterations", COUNT_BAD + (10**9,)),
                     ("n_initial_features", COUNT_BAD + (1000,)), ("max_samples", COUNT_BAD + (10**9,)),
                     ("min_length", (-0.1, 1.5, math.nan)), ("burn_in", (-0.1, 1.0, math.nan)),
                     ("stickiness", (-1.0, math.nan)), ("direction_noise", (0.0, -1.0, math.nan)),
                     ("feature_mass", (0.0, -1.0, math.nan))]:  # fmt: skip
        cases += value_cases(g, arg, lambda val, arg=arg: seg(**{arg: val}), bad)
    g = "FixedSegmenter"
    cases += value_cases(g, "boundaries", lambda b: FixedSegmenter(b)(d), ([1.5], [-0.1], [0.6, 0.4], ["a"], [math.nan]))
    cases.append(Case(g, "hyper", "split of a 2-sample fixed step", lambda: FixedSegmenter([0.02, 0.5])(d).split(d),
                      "error", ("step 0",)))
    g = "Segmentation"
    cases += value_cases(g, "i", lambda i: fx.segmentation.step_sequence(i), (-1, 5, 0.0, True, "0"), (0, 1),
                         kind="type", check=lambda r: None if r == [0, 1] else "wrong steps")  # fmt: skip
    cases.append(Case(g, "type", "split: a list of tensors", lambda: fx.segmentation.split(list(d.sequences())),
                      "error", ("demos",)))
    cases.append(Case(g, "mismatch", "split: the segmented demonstrations in another order",
                      lambda: fx.segmentation.split(d[[1, 0]]), "error", ("demonstrations",)))
    g = "Segmentation"
    s = fx.segmentation
    cases += tensor_cases(g, "x", lambda a: s.log_density(a), d.positions[0, :5], single_ok=True, empty_ok=True,
                          batched=True)  # fmt: skip
    cases += file_cases(g, "Segmentation.load", Segmentation.load, fx.segmentation.save(fx.tmp / "seg.pt"),
                        other=fx.lpvds.save(fx.tmp / "seg_other.pt"), tmp=fx.tmp / "segfiles")  # fmt: skip
    return cases


# ---------------------------------------------------------------------------------------------- corpus: files
def file_cases(group: str, label: str, load: Callable[[Any], Any], good: Path, *, other: Path, tmp: Path,
               directory: bool = False) -> list[Case]:  # fmt: skip
    """Damaged copies of the saved ``good`` file (or directory): missing, empty, random, truncated, foreign ..."""
    import shutil

    tmp.mkdir(parents=True, exist_ok=True)
    cases: list[Case] = []

    def variant(name: str, make: Callable[[Path], None]) -> None:
        path = tmp / name
        if directory:
            shutil.copytree(good, path)
            target = path / "manifest.json" if (path / "manifest.json").exists() else sorted(path.iterdir())[0]
        else:
            shutil.copy(good, path)
            target = path
        make(target)
        cases.append(Case(group, "file", f"{label}: {name.replace('_', ' ')}", lambda: load(path), "error",
                          (path.name, target.name)))  # fmt: skip

    raw = good.read_bytes() if not directory else None
    rng = np.random.default_rng(0)
    variant("empty", lambda p: p.write_bytes(b""))
    variant("random_bytes", lambda p: p.write_bytes(rng.bytes(max(64, p.stat().st_size))))
    variant("truncated_half", lambda p: p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]))
    variant("truncated_tail", lambda p: p.write_bytes(p.read_bytes()[:-1]))
    variant("text", lambda p: p.write_text("not a model\n"))
    if not directory:
        variant("foreign_torch_file", lambda p: torch.save({"a": torch.zeros(2)}, p))
        variant("other_kind", lambda p: p.write_bytes(other.read_bytes()))
        variant("foreign_list", lambda p: torch.save([1, 2, 3], p))
        variant("zip_of_nothing", lambda p: zipfile.ZipFile(p, "w").close())
    missing = tmp / "does_not_exist"
    cases.append(Case(group, "file", f"{label}: missing", lambda: load(missing), "error", (missing.name,)))
    cases.append(Case(group, "file", f"{label}: a directory" if not directory else f"{label}: a file",
                      lambda: load(tmp if not directory else good.parent / "seg.pt"), "error",
                      (tmp.name, "seg.pt", "manifest.json")))  # fmt: skip
    cases.append(Case(group, "type", f"{label}: None", lambda: load(None), "error", ("path", "director", "None")))
    cases.append(Case(group, "type", f"{label}: an int", lambda: load(3), "error", ("path", "director", "3")))
    del raw
    return cases


def corpus_store(fx: Fixtures) -> list[Case]:
    from lfd_torch.ds import load_primitive
    from lfd_torch.store import collect, config_hash, read_table, run_manifest, write_table

    g = "store"
    tmp = fx.tmp / "store"
    tmp.mkdir()
    prim = fx.lpvds.save(tmp / "prim.pt")
    cases = file_cases(g, "load_primitive", load_primitive, prim, other=fx.segmentation.save(tmp / "other.pt"),
                       tmp=tmp / "prim")  # fmt: skip
    cases += value_cases(g, "path", lambda p: fx.lpvds.save(p), (tmp / "prim" / "empty" / "x.pt", None, 3, tmp),
                         kind="file", names=("path", "empty", "prim", "director", "None", "3"))  # fmt: skip
    manifest = run_manifest({"seed": 0}, seed=0)
    row = {"experiment": "e", "shape": "s", "method": "m", "fold": 0, "seed": 0, "trajectory": 0, "E1": 1.0}
    tbl = write_table([row], tmp / "t.parquet", manifest=manifest)
    cases += value_cases(g, "rows", lambda r: write_table(r, tmp / "u.parquet", manifest=manifest),
                         (None, 3, "abc", [{"E1": 1.0}], [row, row], [dict(row, method=None)]),
                         names=("rows", "column", "key"))  # fmt: skip
    cases += value_cases(g, "manifest", lambda m: write_table([row], tmp / "v.parquet", manifest=m),
                         ({}, {"seed": 1}, 3), names=("manifest",))  # fmt: skip
    cases += value_cases(g, "path", lambda p: write_table([row], p, manifest=manifest), (None, 3, ""),
                         kind="file", names=("path", "None", "3", "bogus", "suffix"))  # fmt: skip
    bad_tbl = tmp / "bad.parquet"
    bad_tbl.write_bytes(b"PAR1garbage")
    cases += value_cases(g, "read_table path", read_table, (bad_tbl, tmp / "none.parquet", tmp, None),
                         kind="file", names=("bad.parquet", "none.parquet", "store", "path", "None"))  # fmt: skip
    cases.append(Case(g, "file", "read_table: valid", lambda: read_table(tbl), "result", ("path",),
                      lambda t: None if len(t) == 1 and float(t["E1"].iloc[0]) == 1.0 else "wrong"))
    cases += value_cases(g, "seed", lambda s: run_manifest({"seed": 0}, seed=s), (None, 1.5, "0", 1))
    cases += value_cases(g, "cfg", lambda c: run_manifest(c, seed=0), (3, "abc", {"a": object()}), names=("config",))
    cases += value_cases(g, "length", lambda n: config_hash({"a": 1}, length=n), (0, 65, 2.5, "8"))
    cases += value_cases(g, "path_or_dir", lambda p: collect(p), (tmp / "nowhere", None, 3),
                         kind="file", names=("nowhere", "path", "None", "3", "director"))  # fmt: skip
    return cases


# ---------------------------------------------------------------------------------------------- corpus: metrics
def corpus_metrics(fx: Fixtures) -> list[Case]:
    from lfd_torch.metrics import aggregate, cosine_dissimilarity, dtw_distance, swept_area, velocity_error

    P, V = fx.demos.positions[:, :20], fx.demos.velocities[:, :20]
    cases: list[Case] = []
    for name, fn, ref in (("E1", velocity_error, V), ("E2", cosine_dissimilarity, V), ("E3", swept_area, P),
                          ("DTW", dtw_distance, P)):  # fmt: skip
        g = f"metrics {name}"
        pred = ref + 0.1
        first, second = fn.__code__.co_varnames[:2]
        cases += tensor_cases(g, first, lambda a, fn=fn, r=ref: fn(a, r), pred, rows=False)
        cases += tensor_cases(g, second, lambda b, fn=fn, p=pred: fn(p, b), ref, rows=False)
        cases.append(Case(g, "empty", "zero samples", lambda fn=fn, p=pred, r=ref: fn(p[:, :0], r[:, :0]), "either",
                          (first, "sample")))  # fmt: skip
        cases.append(Case(g, "mismatch", "different batch sizes", lambda fn=fn, p=pred, r=ref: fn(p[:2], r), "error",
                          (first, second, "batch", "shape")))  # fmt: skip
        if name != "DTW":
            cases += value_cases(g, "mask", lambda m, fn=fn, p=pred, r=ref: fn(p, r, m),
                                 (torch.ones(3, 5, dtype=torch.bool), torch.zeros(3, 20, dtype=torch.bool),
                                  torch.ones(3, 20), "abc"), (torch.ones(3, 20, dtype=torch.bool),))  # fmt: skip
            cases += value_cases(g, "lengths", lambda n, fn=fn, p=pred, r=ref: fn(p, r, lengths=n),
                                 (torch.tensor([0, 5, 5]), torch.tensor([21, 5, 5]), torch.tensor([5, 5]),
                                  torch.tensor([2.5, 5, 5]), "abc"), (torch.tensor([20, 5, 2]),))  # fmt: skip
        else:
            cases += value_cases(g, "lengths_a", lambda n, p=pred, r=ref: dtw_distance(p, r, n),
                                 (torch.tensor([0, 5, 5]), torch.tensor([21, 5, 5]), torch.tensor([5, 5]), "abc"),
                                 (torch.tensor([20, 5, 1]),))  # fmt: skip
    cases += value_cases("metrics E1", "kind", lambda k: velocity_error(V + 1, V, kind=k), ("bogus", None))
    cases += value_cases("metrics E3", "reduction", lambda k: swept_area(P + 1, P, reduction=k), ("bogus", None))
    cases += tensor_cases("metrics aggregate", "values", lambda a: aggregate(a), torch.tensor([1.0, 2.0], dtype=F64),
                          rows=False, mismatch_ok=True)  # fmt: skip
    cases += value_cases("metrics aggregate", "counts", lambda c: aggregate(torch.tensor([1.0, 2.0], dtype=F64), c),
                         (torch.tensor([1, -1]), torch.tensor([1]), torch.tensor([0, 0]), "abc"))  # fmt: skip
    return cases


# ---------------------------------------------------------------------------------------------- corpus: rollout
def corpus_rollout(fx: Fixtures) -> list[Case]:
    from lfd_torch.rollout import Disturbance, rollout

    g = "rollout"
    x0 = fx.demos.start_points

    def field(x: Tensor) -> Tensor:
        return -x

    def conv(out: Any) -> str | None:
        return finite(out.positions)

    cases = tensor_cases(g, "x0", lambda a: rollout(field, a, 0.05, 20), x0, single_ok=True, mismatch_ok=True,
                         check=lambda r: finite(r.positions))  # fmt: skip
    cases += value_cases(g, "dt", lambda v: rollout(field, x0, v, 20), POSITIVE_BAD + (torch.tensor([0.1, 0.2]),),
                         (0.01,), check=conv)  # fmt: skip
    cases += value_cases(g, "n_steps", lambda n: rollout(field, x0, 0.05, n), (0, -1, 2.5, "5", None, True, 10**12),
                         (1, 7), check=conv)  # fmt: skip
    cases += value_cases(g, "method", lambda m: rollout(field, x0, 0.05, 5, method=m), ("bogus", 3, None),
                         ("rk4",), check=conv)  # fmt: skip
    cases += value_cases(g, "field", lambda f: rollout(f, x0, 0.05, 5),
                         (None, 3, lambda x: x[..., :1], lambda x: x * math.nan, lambda x: torch.zeros(5)),
                         names=("field",))  # fmt: skip
    cases += value_cases(g, "attractor", lambda a: rollout(field, x0, 0.05, 5, attractor=a),
                         (torch.zeros(3, dtype=F64), torch.tensor([math.nan, 0.0], dtype=F64), "abc"))  # fmt: skip
    cases += value_cases(g, "position_tol", lambda t: rollout(field, x0, 0.05, 5, position_tol=t), NONNEG_BAD)
    cases += value_cases(g, "velocity_tol", lambda t: rollout(field, x0, 0.05, 5, velocity_tol=t), NONNEG_BAD)
    goal = torch.zeros(2, dtype=F64)
    for arg in ("position_tol", "velocity_tol"):
        cases += value_cases(g, f"{arg} (with an attractor)",
                             lambda t, arg=arg: rollout(field, x0, 0.05, 5, attractor=goal, **{arg: t}),
                             (-1.0, math.nan, "1", "a"), (0.0, math.inf), names=(arg,),
                             check=conv)  # fmt: skip
    cases += value_cases(g, "positions_at times", lambda t: rollout(field, x0, 0.05, 5).positions_at(t),
                         ("a", [-1.0], [math.nan]), ([0.0, 0.1],), names=("times",), check=finite)  # fmt: skip
    cases += value_cases(g, "check_every", lambda c: rollout(field, x0, 0.05, 5, check_every=c), (0, -1, 2.5, "3"))
    cases += value_cases(g, "compact_below", lambda c: rollout(field, x0, 0.05, 5, compact_below=c),
                         (-0.1, 1.5, math.nan, "a"))  # fmt: skip
    cases += value_cases(g, "hook_until", lambda c: rollout(field, x0, 0.05, 5, hook_until=c), (-1, 2.5, "3"))
    cases += value_cases(g, "disturbances", lambda dd: rollout(field, x0, 0.05, 10, disturbances=dd),
                         (3, "abc", [3]), names=("disturbance",))  # fmt: skip
    cases += value_cases(g, "Disturbance", lambda kw: rollout(field, x0, 0.05, 10, disturbances=Disturbance(**kw)),
                         ({"steps": -1, "value": 1.0}, {"steps": 2.5, "value": 1.0}, {"steps": 2, "value": math.nan},
                          {"steps": 2, "value": 1.0, "kind": "bogus"}, {"steps": 2, "value": "abc"}),
                         names=("steps", "value", "kind", "disturbance"))  # fmt: skip
    cases += value_cases(g, "disturbance value", lambda v: rollout(field, x0, 0.05, 10, disturbances=Disturbance(2, v)),
                         (torch.zeros(3, dtype=F64), torch.zeros(5, 2, dtype=F64)),
                         names=("value", "disturbance", "shape"))  # fmt: skip
    return cases


# ---------------------------------------------------------------------------------------------- corpus: viz
def corpus_viz(fx: Fixtures) -> list[Case]:
    import pandas as pd
    from matplotlib.figure import Figure

    from lfd_torch.viz import save_figure, violin, violin_grid

    g = "viz"
    table = pd.DataFrame({"method": ["a", "a", "b", "b"], "split": ["train", "test"] * 2, "E1": [1.0, 2.0, 3.0, 4.0]})
    nan_table = table.assign(E1=[math.nan] * 4)
    cases = value_cases(g, "table", lambda t: violin(t, "E1"),
                        (None, 3, fx.tmp / "none.csv", table.iloc[:0], nan_table, table.drop(columns="method")),
                        names=("table", "none.csv", "method", "E1", "empty"))  # fmt: skip
    cases += value_cases(g, "metric", lambda m: violin(table, m), ("bogus", None, "method", 3), names=("metric",))
    cases += value_cases(g, "by", lambda b: violin(table, "E1", by=b), ("bogus", None, 3), names=("by", "column"))
    cases += value_cases(g, "hue", lambda h: violin(table, "E1", hue=h), ("bogus", 3), names=("hue", "column"))
    cases += value_cases(g, "path", lambda p: save_figure(Figure(), p), (fx.tmp / "fig.bogus", None, 3),
                         kind="file", names=("path", "bogus", "format", "None", "3", "extension"))  # fmt: skip
    cases += value_cases(g, "metrics", lambda ms: violin_grid(table, ms), ([], ["bogus"], None, "E1"),
                         names=("metric",))  # fmt: skip
    return cases


# ---------------------------------------------------------------------------------------------- corpus: skills
def corpus_skills(fx: Fixtures) -> list[Case]:
    from lfd_torch.skills import SkillEngine, SkillLibrary, check_stability, random_pushes

    lib, d, seg = fx.library, fx.multi, fx.segmentation
    cases: list[Case] = []
    g = "SkillLibrary"
    cases += value_cases(g, "demos", lambda v: SkillLibrary.learn(v, seg, generator=gen(), check=False),
                         (None, fx.x, "abc", fx.demos), kind="type", names=("demos", "dimension", "demonstration"))
    cases += value_cases(g, "segmentation", lambda s: SkillLibrary.learn(d, s, generator=gen(), check=False),
                         (None, 3, "abc"), kind="type")  # fmt: skip
    cases += value_cases(g, "generator", lambda r: SkillLibrary.learn(d, seg, generator=r, check=False), (None, 0))
    cases += value_cases(g, "entropy_quantile",
                         lambda q: SkillLibrary.learn(d, seg, generator=gen(), entropy_quantile=q, check=False),
                         PROB_BAD)  # fmt: skip
    cases += value_cases(g, "entropy_reference",
                         lambda q: SkillLibrary.learn(d, seg, generator=gen(), entropy_reference=q, check=False),
                         ("bogus", None, 3))  # fmt: skip
    cases += value_cases(g, "check", lambda c: SkillLibrary.learn(d, seg, generator=gen(), check=c),
                         ("abc", 3, {"bogus_option": 1}), names=("check", "bogus_option"))  # fmt: skip
    cases += value_cases(g, "m", lambda m: lib.with_step(m, lib.skills[0].primitive), (-1, 5, 1.5, "0", None, True))
    cases += value_cases(g, "primitive", lambda p: lib.with_step(0, p), (None, 3, fx.lpvds), names=("primitive",
                                                                                                   "attractor"))
    lib_dir = fx.tmp / "library"
    lib.save(lib_dir)
    cases += file_cases(g, "SkillLibrary.load", SkillLibrary.load, lib_dir, other=lib_dir, tmp=fx.tmp / "libs",
                        directory=True)  # fmt: skip
    import json

    def edited(change: dict[str, Any]) -> Any:
        root = fx.tmp / f"lib_edit_{len(list(fx.tmp.glob('lib_edit_*')))}"
        lib.save(root)
        man = json.loads((root / "manifest.json").read_text())
        man.update(change)
        (root / "manifest.json").write_text(json.dumps(man))
        return SkillLibrary.load(root)

    cases += value_cases(g, "manifest edit", edited, ({"span": 1e-3}, {"entropy_quantile": 7},
                                                      {"stability": {"passed": True}}, {"span": "abc"}),
                         kind="file", names=("manifest.json",))  # fmt: skip
    cases += value_cases(g, "load dtype", lambda t: SkillLibrary.load(lib_dir, dtype=t),
                         (torch.float16, "bogus", torch.int64), ("float32",), names=("dtype",),
                         check=lambda lb: None if lb.dtype == torch.float32 else "not float32")  # fmt: skip
    cases += value_cases(g, "load device", lambda v: SkillLibrary.load(lib_dir, device=v),
                         ("bogus",) + (() if torch.cuda.is_available() else ("cuda",)), ("cpu",), names=("device",),
                         check=lambda lb: None)  # fmt: skip
    cases += value_cases(g, "directory", lambda p: lib.save(p), (None, 3, lib_dir / "manifest.json"), kind="file",
                         names=("director", "path", "None", "3", "manifest.json"))  # fmt: skip
    g = "SkillEngine"
    eng = SkillEngine(lib, "full")
    x = d.start_points
    cases += value_cases(g, "modulation", lambda m: SkillEngine(lib, m), ("bogus", 3, None))
    cases += value_cases(g, "library", lambda m: SkillEngine(m, "full"), (None, 3, fx.lpvds))
    cases += tensor_cases(g, "x", lambda a: eng.tick(a).velocity, x[0], rows=False,
                          check=finite)  # fmt: skip
    cases += value_cases(g, "step", lambda s: eng.tick(x[0], step=s), (-1, 5, 1.5, "a", True), (0, 1),
                         check=lambda r: finite(r.velocity))  # fmt: skip
    cases += value_cases(g, "route", lambda s: eng.tick(x[0], route=s), (-1, 5, 1.5, "a"))
    cases += tensor_cases(g, "x", lambda a: eng.step_batch(a)[0], x, single_ok=True)
    cases += value_cases(g, "route", lambda r: eng.step_batch(x, route=r),
                         (torch.tensor([5, 0]), torch.tensor([0]), torch.tensor([0.5, 0.0]), "abc"))  # fmt: skip
    cases += value_cases(g, "index", lambda i: eng.step_batch(x, route=torch.zeros(2, dtype=torch.long), index=i),
                         (torch.tensor([-1, 0]), torch.tensor([9, 0]), torch.tensor([0]), "abc"))  # fmt: skip
    done_route = torch.zeros(x.shape[0], dtype=torch.long)
    done_index = torch.full_like(done_route, len(lib.routes[0]))  # a finished row, as Decision.index returns it
    cases += value_cases(g, "index (progress fed back)", lambda i: eng.step_batch(x, done_route, i)[0],
                         (done_index + 1, -done_index), (done_index,), names=("index",), check=finite)  # fmt: skip
    cases += tensor_cases(g, "x0", lambda a: eng.rollout(a, dt=0.01, n_steps=5).result.positions, x, single_ok=True)
    cases += value_cases(g, "dt", lambda v: eng.rollout(x, dt=v, n_steps=5), POSITIVE_BAD)
    cases += value_cases(g, "n_steps", lambda n: eng.rollout(x, dt=0.01, n_steps=n), (-1, 2.5, "5", None, 10**12))
    cases += value_cases(g, "method", lambda m: eng.rollout(x, dt=0.01, n_steps=5, method=m), ("bogus", None))
    cases += value_cases(g, "pushes", lambda p: eng.rollout(x, dt=0.01, n_steps=5, pushes=p), (3, "abc"))
    g = "disturbances"
    base = dict(generator=gen(), window=(1, 4), magnitude=(0.1, 0.2))
    for arg, bad in [("n_rows", (0, -1, 2.5, "2", None, 10**12)), ("n_pushes", (-1, 2.5, "1", 10**9)),
                     ("window", ((4, 1), (-1, 3), (1.5, 3), "ab", None)),
                     ("magnitude", ((0.2, 0.1), (-1.0, 1.0), (math.nan, 1.0), "ab", None)),
                     ("kinds", ("bogus", 3, ())), ("away", (-1.0, math.nan, "x")),
                     ("n_candidates", (0, -1, 2.5, 10**9)), ("generator", (None, 0))]:  # fmt: skip
        cases += value_cases(g, arg, lambda v, arg=arg: random_pushes(**{"n_rows": 2, **base, arg: v}), bad)
    g = "check_stability"
    cases += value_cases(g, "modes", lambda v: check_stability(lib, modes=v, n_box=20, n_near=5, n_far=5),
                         ("bogus", ["bogus"], (), 3), names=("mode",))  # fmt: skip
    for arg, bad in [("seed", (None, 1.5, "0")),
                     ("lambda_limit", (0.5, -1.0, math.nan, "2")), ("radial_floor", (-0.1, math.nan, "x")),
                     ("n_box", (-1, 2.5, 10**12)), ("near_radius", (-1.0, math.nan)), ("bogus_kwarg", (1,))]:  # fmt: skip
        cases += value_cases(g, arg, lambda v, arg=arg: check_stability(lib, **{"n_box": 20, "n_near": 5, "n_far": 5,
                                                                                 arg: v}), bad)  # fmt: skip
    cases += value_cases(g, "library", lambda v: check_stability(v), (None, 3, fx.lpvds))
    return cases


# ---------------------------------------------------------------------------------------------- corpus: modulation
def corpus_modulation(fx: Fixtures) -> list[Case]:
    from lfd_torch.modulation import (Modulation, goal_direction, large_scale_factor, modulated_velocity,
                                      reference_entropy, renyi_entropy, small_scale_factor)  # fmt: skip

    prim = fx.lpvds
    x = fx.x[:6]
    f = prim(x).detach()
    gl = prim.attractor
    g = "modulation"

    def mv(**kw: Any) -> Any:
        base = dict(x=x, f=f, attractor=gl, log_p_own=0.0, log_p_other=-1.0, h2=1.0, h2_ref=0.5, mode="full")
        base.update(kw)
        return modulated_velocity(base.pop("x"), base.pop("f"), base.pop("attractor"), **base).velocity

    cases = tensor_cases(g, "x", lambda a: mv(x=a), x, single_ok=True, batched=False)
    cases += tensor_cases(g, "f", lambda a: mv(f=a), f, single_ok=True, batched=False)
    cases += tensor_cases(g, "attractor", lambda a: mv(attractor=a), gl, rows=False)
    cases += value_cases(g, "mode", lambda m: mv(mode=m), ("bogus", None, 3), ("none", "large", "small"))
    cases += value_cases(g, "lambda_limit", lambda v: mv(lambda_limit=v), (0.5, -1.0, math.nan, math.inf, "3"))
    cases += value_cases(g, "radial_floor", lambda v: mv(radial_floor=v), (-0.1, math.nan, "x"))
    cases += value_cases(g, "h2_ref", lambda v: mv(h2_ref=v), (math.nan, "x", torch.zeros(4, dtype=F64)))
    cases += value_cases(g, "log_p_own", lambda v: mv(log_p_own=v), (math.nan, "x", torch.zeros(4, dtype=F64)))
    cases += value_cases(g, "Modulation mode", lambda m: Modulation(mode=m), ("bogus", 3), names=("mode",))
    cases += value_cases(g, "Modulation lambda_limit", lambda v: Modulation(lambda_limit=v), (0.5, math.nan, "3"),
                         names=("lambda_limit",))  # fmt: skip
    cases += value_cases(g, "Modulation entropy_quantile", lambda v: Modulation(entropy_quantile=v), PROB_BAD,
                         names=("entropy_quantile", "quantile"))  # fmt: skip
    mod = Modulation("full")
    cases += tensor_cases(g, "Modulation x", lambda a: mod(prim, a, log_p_own=0.0, log_p_other=-1.0, h2_ref=0.5)
                          .velocity, x, names=("x",), single_ok=True, empty_ok=True, batched=True)  # fmt: skip
    cases += value_cases(g, "primitive", lambda p: mod(p, x, log_p_own=0.0, log_p_other=-1.0, h2_ref=0.5),
                         (None, 3, "abc"))  # fmt: skip
    cases += tensor_cases(g, "renyi_entropy x", lambda a: renyi_entropy(prim, a), x, names=("x",), single_ok=True,
                          empty_ok=True, batched=True)  # fmt: skip
    cases += value_cases(g, "quantile", lambda q: reference_entropy(prim, x, q), PROB_BAD)
    cases += tensor_cases(g, "goal_direction x", lambda a: goal_direction(a, gl).unit, x, names=("x",),
                          single_ok=True, empty_ok=True, batched=True)  # fmt: skip
    cases += value_cases(g, "large_scale lambda_limit",
                         lambda v: large_scale_factor(torch.zeros(3), torch.zeros(3), torch.ones(3), v),
                         (0.5, math.nan, "2"), names=("lambda_limit",))  # fmt: skip
    cases += value_cases(g, "small_scale h2_ref", lambda v: small_scale_factor(torch.zeros(3), v),
                         (math.nan, "x", None), names=("h2_ref",))  # fmt: skip
    return cases


# ---------------------------------------------------------------------------------------------- corpus: robot
def corpus_robot(fx: Fixtures) -> list[Case]:
    from lfd_torch.robot import BaxterArm, BaxterPlant, DLSVelocityMap, ImpedanceController, build_robot

    g = "robot"
    arm = BaxterArm()
    q = arm.neutral().unsqueeze(0).expand(2, 7).clone()
    cases = tensor_cases(g, "q", lambda a: arm.forward_kinematics(a), q, rows=False, batched=True,
                         names=("forward_kinematics",))  # fmt: skip
    cases += tensor_cases(g, "q", lambda a: arm.jacobian(a), q, rows=False, batched=True, names=("jacobian",))
    cases += value_cases(g, "frame", lambda fr: arm.forward_kinematics(q, fr), ("bogus", None, 3))
    cases += value_cases(g, "tool_offset", lambda t: BaxterArm(t), (-0.1, math.nan, "x", None, 100.0))
    dls = DLSVelocityMap(arm)
    v = torch.zeros(2, 3, dtype=F64)
    cases += tensor_cases(g, "v", lambda a: dls(q, a), v, rows=False, names=("DLS", "q"))
    cases += tensor_cases(g, "q", lambda a: dls(a, v), q, rows=False, names=("DLS", "v"))
    cases += value_cases(g, "dt", lambda t: dls(q, v, dt=t), POSITIVE_BAD)
    for arg, bad in [("damping", (-0.1, math.nan, "x")), ("iterations", (0, -1, 2.5, 10**9)),
                     ("limit_margin", (-0.1, math.nan)), ("null_gain", (-1.0, math.nan))]:  # fmt: skip
        cases += value_cases(g, f"DLSVelocityMap {arg}", lambda val, arg=arg: DLSVelocityMap(arm, **{arg: val}), bad,
                             names=(arg,))  # fmt: skip
    imp = ImpedanceController()
    z = torch.zeros(2, 7, dtype=F64)
    cases += tensor_cases(g, "q", lambda a: imp.torque(a, z, q, z), q, rows=False, batched=True, names=("torque",))
    cases += tensor_cases(g, "qd", lambda a: imp.torque(q, a, q, z), z, rows=False, batched=True, names=("torque",))
    cases += value_cases(g, "max_lag", lambda m: ImpedanceController(max_lag=m), (-1.0, math.nan, "x"))
    cases += value_cases(g, "stiffness", lambda s: ImpedanceController(stiffness=s), ([1.0] * 3, [-1.0] * 7,
                                                                                     [math.nan] * 7, "abc"))
    plant = BaxterPlant()
    q7 = arm.neutral()
    cases += tensor_cases(g, "q", lambda a: plant.reset(a), q7, rows=False, optional=True, names=("reset",))
    cases += tensor_cases(g, "q_d", lambda a: plant.set_command(a, torch.zeros(7, dtype=F64)), q7, rows=False,
                          names=("set_command",))  # fmt: skip
    cases += value_cases(g, "force", lambda fo: plant.apply_force("left_hand", fo),
                         ([math.nan, 0, 0], [1.0, 2.0], "abc", None, [1e300, 0, 0]))  # fmt: skip
    cases += value_cases(g, "body", lambda b: plant.apply_force(b, [0.0, 0.0, 1.0]), ("bogus", None, 3))
    cases += value_cases(g, "n_substeps", lambda n: plant.step(n), (0, -1, 2.5, "3", 10**9))
    from lfd_torch.robot.demonstration import load_demonstration

    tmp = fx.tmp / "demo_files"
    tmp.mkdir(exist_ok=True)
    arrays = {"q_of_width_3": {"t": np.arange(3.0), "q": np.zeros((3, 3))},
              "complex_tip": {"t": np.arange(3.0), "tip": np.zeros((3, 3)) + 1j},
              "t_2d": {"t": np.arange(6.0).reshape(2, 3), "tip": np.zeros((6, 3))},
              "q_and_tip": {"t": np.arange(3.0), "tip": np.zeros((3, 3)), "q": np.zeros((3, 7))}}
    for label, content in arrays.items():
        np.savez(tmp / f"{label}.npz", **content)
        cases.append(Case(g, "file", f"load_demonstration: {label}.npz",
                          lambda f=tmp / f"{label}.npz": load_demonstration(f), "error", (f"{label}.npz",)))
    np.savez(tmp / "good.npz", t=np.arange(3.0) * 0.01, tip=np.zeros((3, 3)))
    cases += value_cases(g, "load_demonstration dtype", lambda t: load_demonstration(tmp / "good.npz", dtype=t),
                         (torch.int64, torch.float16, None, "bogus"), ("float32",), names=("dtype",),
                         check=lambda dm: finite(dm.tip))  # fmt: skip
    for arg, bad in [("timestep", (0.0, -1e-3, math.nan, "x", 1.0)), ("control_period", (0.0, -0.01, math.nan)),
                     ("stiffness", ([1.0] * 3, [-1.0] * 7)), ("max_lag", (-1.0, math.nan)),
                     ("velocity_map", ({"bogus": 1}, 3)), ("scene", ({"bogus": 1}, 3))]:  # fmt: skip
        cases += value_cases(g, f"build_robot {arg}", lambda val, arg=arg: build_robot(**{arg: val}), bad,
                             names=(arg,))  # fmt: skip
    return cases


# ---------------------------------------------------------------------------------------------- byte flips
def payload_ranges(path: Path) -> dict[str, list[tuple[int, int]]]:
    """Byte ranges of a torch zip file: ``payload`` (tensor storages) and ``header`` (the metadata pickle)."""
    from lfd_torch.store.checksum import zip_member_spans

    out: dict[str, list[tuple[int, int]]] = {"payload": [], "header": []}
    for name, span in zip_member_spans(path).items():
        if "/data/" in name:
            out["payload"].append(span)
        elif name.endswith("data.pkl"):
            out["header"].append(span)
    return out


def flip_positions(path: Path, n_payload: int, generator: np.random.Generator) -> list[tuple[str, int]]:
    """Every metadata byte, and a seeded sample of ``n_payload`` payload bytes (all of them when fewer)."""
    ranges = payload_ranges(path)
    header = [p for a, b in ranges["header"] for p in range(a, b)]
    payload = np.array([p for a, b in ranges["payload"] for p in range(a, b)], dtype=np.int64)
    if 0 <= n_payload < len(payload):
        payload = np.sort(generator.choice(payload, size=n_payload, replace=False))
    return [("header", int(p)) for p in header] + [("payload", int(p)) for p in payload]


def _content(obj: Any) -> str:
    """SHA-256 of the loaded content (state dicts; for a library every part), to tell a harmless flip from a miss."""
    from lfd_torch.skills import SkillLibrary
    from lfd_torch.store.checksum import payload_digest

    if isinstance(obj, SkillLibrary):
        state = {"segmentation": obj.segmentation.state_dict(),
                 "skills": [{"primitive": s.primitive.state_dict(), "h2_ref": s.h2_ref, "x": s.train_positions,
                             "speed": s.speed, "duration": s.duration} for s in obj.skills],
                 "span": obj.span, "entropy_quantile": obj.entropy_quantile}  # fmt: skip
    else:
        state = obj.state_dict()
    return payload_digest(state)


def byte_flip_audit(fx: Fixtures, n_payload: int, timeout: int) -> list[dict[str, Any]]:
    """Flip each selected byte (XOR a seeded non-zero value) of each saved file, load, restore; count the outcomes.

    detected: StoreError naming the file. harmless: the load returned content identical to the saved one (e.g. a
    flip of the pickle protocol byte or of a memo index). missed: anything else (changed content loaded, another
    error, a hang).
    """
    from lfd_torch.ds import load_primitive
    from lfd_torch.segmentation import Segmentation
    from lfd_torch.skills import SkillLibrary

    rng = np.random.default_rng(20241101)
    root = fx.tmp / "flips"
    lib_dir = root / "library"
    fx.library.save(lib_dir)
    targets: list[tuple[str, Path, Callable[[], Any], Any]] = [
        ("primitive (LPV-DS)", fx.lpvds.save(root / "lpvds.pt"), lambda: load_primitive(root / "lpvds.pt"), fx.lpvds),
        ("primitive (SEDS)", fx.seds.save(root / "seds.pt"), lambda: load_primitive(root / "seds.pt"), fx.seds),
        ("segmentation", fx.segmentation.save(root / "segmentation.pt"),
         lambda: Segmentation.load(root / "segmentation.pt"), fx.segmentation),
    ]  # fmt: skip
    for p in sorted(lib_dir.glob("*.pt")):
        targets.append((f"skill library: {p.name}", p, lambda: SkillLibrary.load(lib_dir), fx.library))
    rows = []
    for what, path, load, original in targets:
        raw = path.read_bytes()
        reference = _content(load())
        counts: Counter[tuple[str, str]] = Counter()
        missed: list[str] = []
        for part, pos in flip_positions(path, n_payload, rng):
            mutated = bytearray(raw)
            mutated[pos] ^= int(rng.integers(1, 256))
            path.write_bytes(bytes(mutated))
            signal.alarm(timeout)
            try:
                result = "harmless" if _content(load()) == reference else "missed: changed content loaded"
            except Hang:
                result = "missed: hang"
            except StoreError as exc:
                result = "detected" if path.name in str(exc) or path.parent.name in str(exc) else "missed: unnamed"
            except Exception as exc:  # noqa: BLE001
                result = f"missed: {type(exc).__name__}"
            finally:
                signal.alarm(0)
            counts[(part, result)] += 1
            if result.startswith("missed") and len(missed) < 5:
                missed.append(f"{part} byte {pos}: {result}")
        path.write_bytes(raw)
        del original
        for part in ("header", "payload"):
            n = sum(c for (p, _), c in counts.items() if p == part)
            rows.append({"file": what, "part": part, "flips": n, "detected": counts[(part, "detected")],
                         "harmless": counts[(part, "harmless")],
                         "missed": n - counts[(part, "detected")] - counts[(part, "harmless")],
                         "examples": "; ".join(m for m in missed if m.startswith(part))})  # fmt: skip
    return rows


# ---------------------------------------------------------------------------------------------- report
CORPORA = {
    "demos": corpus_demos,
    "preprocess": corpus_preprocess,
    "loaders": corpus_loaders,
    "gmm": corpus_gmm,
    "ds": corpus_ds,
    "segmentation": corpus_segmentation,
    "store": corpus_store,
    "metrics": corpus_metrics,
    "rollout": corpus_rollout,
    "viz": corpus_viz,
    "skills": corpus_skills,
    "modulation": corpus_modulation,
    "robot": corpus_robot,
}


def _md_table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        lines.append("| " + " | ".join(str(c).replace("|", "\\|").replace("\n", " ") for c in r) + " |")
    return "\n".join(lines)


def report(results: list[Outcome], flips: list[dict[str, Any]], seconds: float, command: str) -> str:
    total = Counter(r.outcome for r in results)
    by_group: dict[str, Counter[str]] = defaultdict(Counter)
    by_kind: dict[str, Counter[str]] = defaultdict(Counter)
    for r in results:
        by_group[r.case.group][r.outcome] += 1
        by_kind[r.case.kind][r.outcome] += 1
    n_pass = total["typed"] + total["correct"]
    parts = [
        "# Malformed-input audit (issue 11)",
        "",
        f"`{command}` -- {len(results)} calls in {seconds:.0f} s, torch {torch.__version__}.",
        "",
        f"**{n_pass} / {len(results)} calls ({100 * n_pass / max(1, len(results)):.1f} %) raised a typed lfd_torch "
        "error naming the argument or returned a correct result.**",
        "",
        _md_table(["outcome", "calls"], [(o, total[o]) for o in OUTCOMES]),
        "",
        "## By entry point",
        "",
        _md_table(["group", *OUTCOMES], [(g, *(c[o] for o in OUTCOMES)) for g, c in sorted(by_group.items())]),
        "",
        "## By kind of input",
        "",
        _md_table(["kind", *OUTCOMES], [(k, *(c[o] for o in OUTCOMES)) for k, c in sorted(by_kind.items())]),
        "",
    ]
    if flips:
        n = sum(r["flips"] for r in flips)
        det = sum(r["detected"] for r in flips)
        harmless = sum(r["harmless"] for r in flips)
        pay = [r for r in flips if r["part"] == "payload"]
        parts += [
            "## Single-byte flips of saved files",
            "",
            "One flip at a time (XOR with a seeded non-zero byte) of every byte of the metadata pickle (`data.pkl`, "
            "\"header\") and of a seeded sample of the tensor payload (`data/*`) of each file, then a load. "
            "*detected*: StoreError naming the file; *harmless*: the load returned content identical to the saved "
            "one (SHA-256 of the loaded state; e.g. the pickle protocol byte or a memo index); *missed*: anything else.",
            "",
            f"**Payload: {sum(r['detected'] for r in pay)} / {sum(r['flips'] for r in pay)} detected. All files: "
            f"{det} detected, {harmless} harmless, {n - det - harmless} missed of {n} flips.**",
            "",
            _md_table(["file", "part", "flips", "detected", "harmless", "missed", "missed (first few)"],
                      [(r["file"], r["part"], r["flips"], r["detected"], r["harmless"], r["missed"], r["examples"])
                       for r in flips]),  # fmt: skip
            "",
        ]
    failed = [r for r in results if r.outcome not in PASS]
    parts += ["## Calls that are neither typed nor correct", ""]
    if failed:
        parts.append(_md_table(["group", "kind", "call", "outcome", "detail"],
                               [(r.case.group, r.case.kind, r.case.label, r.outcome, r.detail[:200]) for r in failed]))
    else:
        parts.append("None.")
    slow = sorted(results, key=lambda r: -r.seconds)[:5]
    parts += ["", "## Slowest calls", "",
              _md_table(["group", "call", "s"], [(r.case.group, r.case.label, f"{r.seconds:.2f}") for r in slow]), ""]
    return "\n".join(parts)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="outputs/audit_inputs", help="folder of the report (audit_inputs.md)")
    parser.add_argument("--publish", action="store_true", help="also write results/tables/audit_inputs.md")
    parser.add_argument("--only", default="",
                        help=f"comma-separated groups of {list(CORPORA) + ['flips']} (default: all)")
    parser.add_argument("--timeout", type=int, default=20, help="seconds before a call counts as a hang")
    parser.add_argument("--flips", type=int, default=-1,
                        help="payload bytes flipped per file: -1 every byte (default), N a seeded sample, 0 none")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--verbose", action="store_true", help="print every failing call as it happens")
    parser.add_argument("--memory-gb", type=float, default=6.0,
                        help="address-space limit: an unbounded allocation fails (a crash) instead of exhausting RAM")
    args = parser.parse_args(argv)
    if args.memory_gb > 0:
        import resource

        limit = int(args.memory_gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    torch.set_num_threads(args.threads)
    signal.signal(signal.SIGALRM, _on_alarm)
    only = [s for s in args.only.split(",") if s]
    unknown = [s for s in only if s not in CORPORA and s != "flips"]
    if unknown:
        parser.error(f"unknown groups {unknown}; valid: {list(CORPORA)}")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="audit_inputs_") as tmp:
        fx = build_fixtures(Path(tmp))
        results: list[Outcome] = []
        for name, build in CORPORA.items():
            if only and name not in only:
                continue
            try:
                cases = build(fx)
            except Exception:  # noqa: BLE001 -- a corpus that cannot even be built is reported, not hidden
                traceback.print_exc()
                print(f"[audit] could not build the {name} corpus", file=sys.stderr)
                return 2
            for case in cases:
                r = run_case(case, args.timeout)
                results.append(r)
                if args.verbose and r.outcome not in PASS:
                    print(f"[{r.outcome}] {case.group} | {case.label} | {r.detail[:160]}", flush=True)
            print(f"[audit] {name}: {len(cases)} calls, "
                  f"{sum(r.outcome in PASS for r in results[-len(cases):])} pass", flush=True)  # fmt: skip
        run_flips = args.flips != 0 and (not only or "flips" in only)
        flips = byte_flip_audit(fx, args.flips, args.timeout) if run_flips else []
    seconds = time.perf_counter() - t0
    command = "python experiments/audit_inputs.py" + (" " + " ".join(argv if argv is not None else sys.argv[1:]))
    text = report(results, flips, seconds, command.strip())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "audit_inputs.md").write_text(text)
    print(text.split("## By entry point")[0])
    if args.publish:
        from lfd_torch.store.atomic import atomic_path
        from lfd_torch.store.paths import project_root

        dest = Path(project_root()) / "results" / "tables" / "audit_inputs.md"
        with atomic_path(dest) as tmp_path:
            tmp_path.write_text(text)
        print(f"[audit] published {dest}")
    n_fail = sum(r.outcome not in PASS for r in results)
    n_missed = sum(r["missed"] for r in flips)
    print(f"[audit] {n_fail} calls neither typed nor correct; {n_missed} byte flips missed; {seconds:.0f} s")
    return 1 if n_fail or n_missed else 0


if __name__ == "__main__":
    sys.exit(main())
