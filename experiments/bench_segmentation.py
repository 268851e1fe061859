"""Benchmark and accuracy study of the BP-GM-HMM segmentation (default settings of conf/segmentation/bp_gm_hmm.yaml).

Three parts (single-threaded torch; OMP_NUM_THREADS=1 recommended):

  lasa       wall-clock of ``segment`` on all 7 LASA demonstrations x 1000 samples (2-D) of several shapes: total
             seconds, sampler seconds, milliseconds per sweep (all chains batched), steps found.
  scaling    milliseconds per sweep against the subsampled length T (``max_samples``) and the number of
             sequences N, on one shape.
  synthetic  accuracy on the benchmark families of :mod:`lfd_torch.segmentation.synthetic` (``FAMILIES``: straight
             and curved legs, out-and-back, revisit, scoop; dwelling and constant-speed timing; 2-D and 3-D), with
             1 and 4 demonstrations per case and ``--seeds`` random cases per family, for ``segment`` (default
             settings) and two off-the-shelf baselines (below). Per case: exact step count (every demonstration's),
             every switch found (each true switch matched one-to-one to a detected switch within 3 % of its
             demonstration's length, no extra switch), median boundary error (% of the length, over the true
             switches, distance to the nearest detected switch; 100 % when none is detected), wall seconds.

  membership subtask spaces (paper Sec. IV test p(x | A_m) >= p(x | A_m-)) on the families (``--seeds`` cases,
             1 and 4 demonstrations) and on LASA Multi_Models_1..4 (all 7 demonstrations): per set the smallest
             share, over steps, of a step's own samples inside its A_m (``own_min``; issue 7 asks >= 0.98) and the
             largest share of the other steps' samples inside an A_m (``other_max``: how far the spaces overlap).

Detected switches of a demonstration are the samples t > 0 whose step label differs from that of t - 1 (from the
per-sample labels, whatever the method); the truth is ``SyntheticSteps.switch_times`` (the corner samples).

Baselines (both on features = positions and their Savitzky-Golay velocities, window 25 samples = 0.25 s, cubic;
each feature z-scored; the finite-difference velocities of the data are mostly noise at 1 % position noise):

  ruptures     PELT (ruptures' defaults min_size = 2, jump = 5) per demonstration, ``rbf`` cost (median-heuristic
               bandwidth; ``ruptures_l2``: ``l2`` cost). Penalty = c * log(T) * D, D = 2 d features, with c = 1,
               fixed once for every family: the BIC penalty of a new segment (log T per parameter, D means) for a
               Gaussian piecewise-constant model of unit noise variance. Unit variance is the largest the features
               can have (z-scored, resp. the rbf feature map has k(x, x) = 1), so this is the most conservative BIC
               and the only choice that needs no noise estimate.
  hmmlearn     ``GaussianHMM`` (full covariances, 100 EM iterations, kmeans initialisation, random_state = seed)
               fitted jointly to all demonstrations of a case (features z-scored over the case), the number of
               states chosen by BIC over 1..8; steps = maximal runs of the Viterbi state (a state visited again
               later starts a new step).

    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py
    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts synthetic --seeds 10
    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts synthetic --method ruptures hmmlearn
    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts lasa scaling --json out.json
    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts membership --seeds 2

``--noise-correlation RHO`` replaces each case's white noise by AR(1) noise of lag-one correlation RHO and the same
level (:func:`lfd_torch.segmentation.synthetic.with_correlated_noise`): the same paths under noise that is not
white at the sampling rate (a filtered sensor, a tremor), a check the families were not tuned on. With
``--segment-option noise_model=white`` the segmentation assumes white noise (the earlier default):

    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts synthetic --method segment \
        --noise-correlation 0.5 --n-demos 1 --jobs 2 --json results/tables/bench_segmentation_ar1.json

``--n-steps M`` draws the straight and curved families with M legs instead of 3-5 (same corner angles, length
ratio, timing and noise), a path with more corners than the benchmark's:

    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts synthetic --method segment \
        --families straight_dwell_2d straight_const_2d curved_dwell_2d curved_const_2d --n-steps 7 --jobs 2

``--families rounded_const_2d rounded_const_3d rounded_vary_2d rounded_vary_3d`` runs the held-out families
(:data:`lfd_torch.segmentation.synthetic.HELD_OUT_FAMILIES`, :func:`~lfd_torch.segmentation.synthetic.rounded_steps`):
corners rounded by circular arcs (the switch at the arc's midpoint) and a speed that varies along the whole
demonstration regardless of the corners, drawn by a generator that shares no rendering code with the families and
was added after every default was set:

    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts synthetic --jobs 2 \
        --families rounded_const_2d rounded_const_3d rounded_vary_2d rounded_vary_3d \
        --json results/tables/bench_segmentation_held_out.json

A second held-out set (:data:`lfd_torch.segmentation.synthetic.SLOWING_FAMILIES`, added later and used to choose
no setting either) draws the benchmark's shapes with a motion that slows at every corner to 20-70 % of the leg's
mean speed without stopping, between the families' rest and constant speed (the defaults and both baselines):

    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts synthetic --jobs 2 \
        --families straight_slow_2d straight_slow_3d curved_slow_2d curved_slow_3d out_and_back_slow_2d \
        revisit_slow_2d scoop_slow_3d --json results/tables/bench_segmentation_held_out_slowing.json

``--noise-scale S`` gives every case new white position noise of S times its level (the same paths; with
``--noise-correlation``, AR(1) noise of that level): at S = 0.1 a sensor ten times better, which tells a miss that
the data's noise makes from one that the model makes on any data:

    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts synthetic --method segment \
        --families straight_const_3d curved_const_2d curved_const_3d scoop_const_3d --noise-scale 0.1 --jobs 2 \
        --json results/tables/bench_segmentation_noise_scale01.json

``--rate HZ`` records every case at HZ instead of 100 Hz (:func:`lfd_torch.segmentation.synthetic.with_sampling_rate`:
the same motions and durations, new white noise of the same level per sample), a sensor slower or faster than the
one the families were drawn for: at 10 Hz a demonstration has 35-120 samples, at 500 Hz 1746-5971. The baselines
keep their 25-sample velocity window, so only ``--method segment`` is meaningful there:

    OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_segmentation.py --parts synthetic --method segment \
        --rate 25 --jobs 2 --json results/tables/bench_segmentation_rate25.json
"""

from __future__ import annotations

import argparse
import functools
import inspect
import json
import logging
import math
import statistics
import time
import warnings
import zlib
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np
import torch

from lfd_torch.data import load_lasa
from lfd_torch.segmentation import segment
from lfd_torch.segmentation.synthetic import (
    FAMILIES,
    HELD_OUT_FAMILIES,
    SLOWING_FAMILIES,
    SyntheticSteps,
    with_correlated_noise,
    with_sampling_rate,
)

LASA_SHAPES = ("Multi_Models_1", "Multi_Models_2", "Multi_Models_3", "Multi_Models_4", "Angle", "Sshape")
METHODS = ("segment", "segment_joint", "segment_collapsed", "segment_modal", "segment_map", "ruptures", "ruptures_l2",
           "hmmlearn")
TOLERANCE = 0.03  # a switch is found when a detected one lies within 3 % of the demonstration's length
SAVGOL_WINDOW = 25  # samples (0.25 s at dt = 0.01 s)
PENALTY_C = 1.0  # PELT penalty = PENALTY_C * log(T) * n_features
HMM_STATES = range(1, 9)
ALL_FAMILIES = {**FAMILIES, **HELD_OUT_FAMILIES, **SLOWING_FAMILIES}


def _timed(demos, seed: int, **kw: Any) -> tuple[float, Any]:
    g = torch.Generator().manual_seed(seed)
    t0 = time.perf_counter()
    seg = segment(demos, generator=g, **kw)
    return time.perf_counter() - t0, seg


def bench_lasa(shapes: tuple[str, ...] = LASA_SHAPES, seed: int = 0, **options: Any) -> list[dict[str, Any]]:
    """One row per shape: seconds for all 7 demonstrations with the default settings (or ``options``, the
    ``--segment-option`` keywords of ``segment``)."""
    rows = []
    for shape in shapes:
        demos = load_lasa(shape)
        seconds, seg = _timed(demos, seed, **options)
        n_iter = seg.sampler.trace.shape[1]
        rows.append({
            "part": "lasa", "shape": shape, "n_demos": demos.n_demos, "T_full": demos.max_length,
            "seconds": seconds, "sampler_seconds": seg.info["sampler_seconds"],
            "ms_per_sweep": 1e3 * seg.info["sampler_seconds"] / n_iter, "n_steps": seg.n_steps,
            "n_features": seg.sampler.n_features,
        })  # fmt: skip
    return rows


def bench_scaling(shape: str = "Angle", seed: int = 0, n_iterations: int = 10) -> list[dict[str, Any]]:
    """ms per sweep against T (max_samples) with N = 7, and against N with T = 60 (the default)."""
    demos = load_lasa(shape)
    rows = []
    for T in (50, 100, 200, 400):
        _, seg = _timed(demos, seed, max_samples=T, n_iterations=n_iterations)
        rows.append({"part": "scaling_T", "shape": shape, "T": T, "N": demos.n_demos,
                     "ms_per_sweep": 1e3 * seg.info["sampler_seconds"] / n_iterations})  # fmt: skip
    for N in (1, 2, 4, 7):
        _, seg = _timed(demos[list(range(N))], seed, max_samples=60, n_iterations=n_iterations)
        rows.append({"part": "scaling_N", "shape": shape, "T": 60, "N": N,
                     "ms_per_sweep": 1e3 * seg.info["sampler_seconds"] / n_iterations})  # fmt: skip
    return rows


def membership_shares(seg: Any, demos: Any) -> tuple[float, float]:
    """(own_min, other_max) of one segmentation (module docstring, part ``membership``)."""
    x = torch.cat(demos.sequences())
    lab = torch.cat(list(seg.labels))
    inside = seg.membership(x.to(seg.space_mean))
    own = [float(inside[lab == m, m].double().mean()) for m in range(seg.n_steps) if bool((lab == m).any())]
    other = [float(inside[lab != m, m].double().mean()) for m in range(seg.n_steps) if bool((lab != m).any())]
    return min(own), max(other, default=0.0)


def bench_membership(seeds: int, families: tuple[str, ...], n_demos: tuple[int, ...],
                     shapes: tuple[str, ...] = LASA_SHAPES[:4]) -> list[dict[str, Any]]:
    """One row per data set: the subtask-space shares of ``segment`` with its default settings."""
    from lfd_torch.segmentation import SegmentationWarning

    rows = []
    sets: list[tuple[str, int, int, Any]] = [(shape, 7, 0, None) for shape in shapes]
    sets += [(f, n, seed, None) for f in families for n in n_demos for seed in range(seeds)]
    for name, n, seed, _ in sets:
        demos = load_lasa(name) if name in shapes else ALL_FAMILIES[name](
            torch.Generator().manual_seed(data_seed(name, seed)), n).demos
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SegmentationWarning)
            seg = segment(demos, generator=torch.Generator().manual_seed(seed))
        own, other = membership_shares(seg, demos)
        rows.append({"part": "membership", "set": name, "n_demos": n, "seed": seed, "n_steps": seg.n_steps,
                     "own_min": own, "other_max": other})  # fmt: skip
        print(f"membership {name:>22} N={n} seed={seed}: own_min={own:.3f} other_max={other:.3f}", flush=True)
    return rows


# ============================================================================================ synthetic benchmark
def switches_from_labels(labels: torch.Tensor | np.ndarray) -> list[int]:
    """Samples t > 0 whose label differs from that of t - 1, for one demonstration's (T,) step labels."""
    lab = torch.as_tensor(np.asarray(labels)).reshape(-1)
    return (torch.nonzero(lab[1:] != lab[:-1]).reshape(-1) + 1).tolist()


def _features(positions: np.ndarray) -> np.ndarray:
    """(T, d) positions -> (T, 2 d) positions and Savitzky-Golay velocities (not yet standardized)."""
    from scipy.signal import savgol_filter

    window = min(SAVGOL_WINDOW, positions.shape[0] - (1 - positions.shape[0] % 2))
    vel = savgol_filter(positions, window, 3, deriv=1, delta=0.01, axis=0)
    return np.hstack([positions, vel])


def _zscore(x: np.ndarray) -> np.ndarray:
    return (x - x.mean(0)) / np.maximum(x.std(0), 1e-12)


def _sequences(syn: SyntheticSteps) -> list[np.ndarray]:
    return [syn.demos.positions[i, : int(n)].cpu().numpy() for i, n in enumerate(syn.demos.lengths)]


def detect_segment(syn: SyntheticSteps, seed: int, selection: str | None = None,
                   **options: Any) -> tuple[list[list[int]], dict[str, Any]]:  # fmt: skip
    """``lfd_torch.segmentation.segment`` with its default settings (``segment_collapsed`` / ``segment_modal`` /
    ``segment_map`` / ``segment_joint``: the returned sample chosen with ``selection="collapsed"`` / ``"modal"`` /
    ``"map"`` / ``"joint"``; None: the default's), or others given by ``--segment-option``."""
    from lfd_torch.segmentation import SegmentationWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SegmentationWarning)
        if selection is not None:
            options = {**options, "selection": selection}
        seg = segment(syn.demos, generator=torch.Generator().manual_seed(seed), **options)
    return [switches_from_labels(lab) for lab in seg.labels], {"n_steps": seg.n_steps}


def segment_settings(options: dict[str, Any]) -> dict[str, Any]:
    """Every keyword of :func:`segment` (but ``generator``) as a call with ``options`` sets it: the signature's
    defaults of this checkout overlaid by ``options``. Stored with a table, it says what the table measured even
    after a default changes (``options`` alone are relative to the defaults of the day)."""
    params = inspect.signature(segment).parameters
    unknown = sorted(set(options) - set(params))
    if unknown:
        raise SystemExit(f"--segment-option: segment() has no keyword {', '.join(unknown)}")
    out = {k: p.default for k, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY and k != "generator"}
    return {**out, **options}


def segment_options(pairs: list[str]) -> dict[str, Any]:
    """``["extra_dof=2", "robust_dof=None", "dwell_cue=True", "noise_model=white"]`` -> {"extra_dof": 2.0,
    "robust_dof": None, "dwell_cue": True, "noise_model": "white"} (ints stay ints, anything else not a number
    stays a string)."""
    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise SystemExit(f"--segment-option expects KEY=VALUE, got {pair!r}")
        if value in ("None", "True", "False"):
            out[key] = None if value == "None" else value == "True"
        elif value.lstrip("-").isdigit():
            out[key] = int(value)
        else:
            try:
                out[key] = float(value)
            except ValueError:
                out[key] = value
    return out


def _pelt(model: str) -> Callable[[SyntheticSteps, int], tuple[list[list[int]], dict[str, Any]]]:
    def detect(syn: SyntheticSteps, seed: int) -> tuple[list[list[int]], dict[str, Any]]:
        import ruptures

        out, pens = [], []
        for pos in _sequences(syn):
            x = _zscore(_features(pos))
            pen = PENALTY_C * math.log(x.shape[0]) * x.shape[1]
            bkps = ruptures.Pelt(model=model).fit(x).predict(pen=pen)
            out.append([int(b) for b in bkps[:-1]])  # a breakpoint b ends a segment: b starts the next one
            pens.append(pen)
        return out, {"penalty": pens}

    return detect


def detect_hmmlearn(syn: SyntheticSteps, seed: int) -> tuple[list[list[int]], dict[str, Any]]:
    """Joint full-covariance GaussianHMM, states by BIC over 1..8, steps = maximal Viterbi runs."""
    from hmmlearn.hmm import GaussianHMM

    logging.getLogger("hmmlearn").setLevel(logging.ERROR)
    feats = [_features(p) for p in _sequences(syn)]
    lengths = [f.shape[0] for f in feats]
    x = _zscore(np.vstack(feats))
    best, best_bic, bics = None, math.inf, {}
    for k in HMM_STATES:
        model = GaussianHMM(n_components=k, covariance_type="full", n_iter=100, random_state=seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                model.fit(x, lengths)
                bic = float(model.bic(x, lengths))
            except (ValueError, np.linalg.LinAlgError):
                continue
        bics[k] = bic
        if bic < best_bic:
            best, best_bic = model, bic
    states = best.predict(x, lengths)
    out, start = [], 0
    for n in lengths:
        out.append(switches_from_labels(states[start : start + n]))
        start += n
    return out, {"n_states": best.n_components, "bic": bics}


DETECTORS: dict[str, Callable[[SyntheticSteps, int], tuple[list[list[int]], dict[str, Any]]]] = {
    "segment": detect_segment,
    "segment_joint": lambda syn, seed: detect_segment(syn, seed, "joint"),
    "segment_collapsed": lambda syn, seed: detect_segment(syn, seed, "collapsed"),
    "segment_modal": lambda syn, seed: detect_segment(syn, seed, "modal"),
    "segment_map": lambda syn, seed: detect_segment(syn, seed, "map"),
    "ruptures": _pelt("rbf"),
    "ruptures_l2": _pelt("l2"),
    "hmmlearn": detect_hmmlearn,
}


def score_case(truth: torch.Tensor, lengths: torch.Tensor, found: list[list[int]]) -> dict[str, Any]:
    """Metrics of one case.

    Args:
        truth: (B, M - 1) true switches.
        lengths: (B,) demonstration lengths.
        found: B lists of detected switches.

    Returns:
        exact_steps, all_switches (bools), median_error_pct, found_steps (B,), true_steps.
    """
    errs, exact, matched = [], True, True
    M = truth.shape[1] + 1
    for i, det in enumerate(found):
        T = float(lengths[i])
        true = sorted(truth[i].tolist())
        det = sorted(det)
        exact &= len(det) + 1 == M
        # on a line, a one-to-one matching within tol exists iff the sorted pairing is within tol
        matched &= len(det) == len(true) and all(abs(a - b) <= TOLERANCE * T for a, b in zip(det, true))
        for t in true:
            errs.append(100.0 * min(abs(t - s) for s in det) / T if det else 100.0)
    return {
        "true_steps": M, "found_steps": [len(d) + 1 for d in found], "exact_steps": bool(exact),
        "all_switches": bool(matched), "median_error_pct": statistics.median(errs) if errs else 0.0,
    }  # fmt: skip


def data_seed(family: str, seed: int) -> int:
    """Seed of the data of case ``seed`` of a family (independent of the registry's order and of n_demos)."""
    return (zlib.crc32(family.encode()) + 7919 * seed) % (2**31)


def map_cases(fn: Callable[[Any], Any], tasks: list[Any], jobs: int = 1):
    """fn over tasks, in order: in the calling process (jobs = 1) or in ``jobs`` worker processes. Yields results."""
    if jobs <= 1:
        yield from map(fn, tasks)
        return
    with ProcessPoolExecutor(jobs) as pool:
        yield from pool.map(fn, tasks)


def case_data(family: str, seed: int, n: int, *, n_steps: int | None = None, rate: float | None = None,
              rho: float | None = None, noise_scale: float | None = None):
    """The SyntheticSteps of case ``seed`` of a family with n demonstrations: recorded at ``rate`` Hz instead of 100
    when rate is not None (:func:`with_sampling_rate`, new white noise seeded data seed + 2); AR(1) noise of lag-one
    correlation rho instead of the white noise when rho is not None (:func:`with_correlated_noise`, seeded data
    seed + 1); that noise, white unless rho is given, at noise_scale times the level when noise_scale is not None;
    M legs instead of the drawn number when n_steps is not None."""
    overrides = {} if n_steps is None else {"n_steps": n_steps}
    syn = ALL_FAMILIES[family](torch.Generator().manual_seed(data_seed(family, seed)), n, **overrides)
    if rate is not None:
        syn = with_sampling_rate(syn, rate, torch.Generator().manual_seed(data_seed(family, seed) + 2))
    if rho is not None or noise_scale is not None:
        syn = with_correlated_noise(syn, 0.0 if rho is None else rho,
                                    torch.Generator().manual_seed(data_seed(family, seed) + 1),
                                    1.0 if noise_scale is None else noise_scale)
    return syn


def _synthetic_case(task: tuple[str, int, int, tuple[str, ...], float | None, int | None, float | None,
                                float | None]) -> list[dict[str, Any]]:  # fmt: skip
    """The rows of one (family, n_demos, seed) case, one per method, on :func:`case_data`."""
    family, n, seed, methods, rho, n_steps, rate, noise_scale = task
    torch.set_num_threads(1)
    syn = case_data(family, seed, n, n_steps=n_steps, rate=rate, rho=rho, noise_scale=noise_scale)
    rows = []
    for method in methods:
        t0 = time.perf_counter()
        error = None
        try:
            found, extra = DETECTORS[method](syn, seed)
        except Exception as exc:  # a failing method detects nothing; recorded
            found, extra, error = [[] for _ in range(n)], {}, f"{type(exc).__name__}: {exc}"
        seconds = time.perf_counter() - t0
        rows.append({"part": "synthetic", "method": method, "family": family, "n_demos": n, "seed": seed,
                     **score_case(syn.switch_times, syn.demos.lengths, found), "seconds": seconds,
                     "true_switches": syn.switch_times.tolist(), "found_switches": found,
                     "lengths": syn.demos.lengths.tolist(), "noise_fraction": syn.noise / syn.span,
                     "error": error, **extra})  # fmt: skip
    return rows


def synthetic_study(
    seeds: int = 10,
    methods: tuple[str, ...] = ("segment", "ruptures", "hmmlearn"),
    families: tuple[str, ...] | None = None,
    n_demos: tuple[int, ...] = (1, 4),
    jobs: int = 1,
    noise_correlation: float | None = None,
    n_steps: int | None = None,
    rate: float | None = None,
    noise_scale: float | None = None,
) -> list[dict[str, Any]]:
    """One row per (method, family, n_demos, seed); the data of a (family, seed) share the nominal path. ``jobs``
    worker processes (one thread each) share the cases; the rows, in the same order, do not depend on it (the wall
    times do: with two workers on two cores each case runs as it would alone). ``noise_correlation``: AR(1) noise
    of that lag-one correlation, same marginal level, instead of each family's white noise. ``n_steps``: that many
    legs instead of 3-5 (straight and curved families only). ``rate``: the demonstrations recorded at that many Hz
    instead of 100, same noise per sample. ``noise_scale``: new noise at that multiple of each case's level."""
    families = tuple(FAMILIES) if families is None else families
    if n_steps is not None and not all(f.startswith(("straight_", "curved_")) for f in families):
        raise SystemExit("--n-steps applies to the straight_* and curved_* families only (--families)")
    if noise_scale is not None and not (math.isfinite(noise_scale) and noise_scale > 0):
        raise SystemExit(f"--noise-scale must be a positive number, got {noise_scale}")
    tasks = [(family, n, seed, methods, noise_correlation, n_steps, rate, noise_scale)
             for family in families for n in n_demos for seed in range(seeds)]
    rows = []
    for case_rows in map_cases(_synthetic_case, tasks, jobs):
        for row in case_rows:
            rows.append(row)
            print(f"{row['method']:>11} {row['family']:>22} N={row['n_demos']} seed={row['seed']}: steps "
                  f"{row['true_steps']} -> {row['found_steps']}  exact={int(row['exact_steps'])} "
                  f"all={int(row['all_switches'])} med_err={row['median_error_pct']:.1f}% {row['seconds']:.2f}s"
                  + (f"  [{row['error']}]" if row["error"] else ""), flush=True)  # fmt: skip
    return rows


def _summary_row(rs: list[dict[str, Any]], **keys: Any) -> dict[str, Any]:
    n = len(rs)
    ratio = [statistics.mean(f / r["true_steps"] for f in r["found_steps"]) for r in rs]
    return {
        **keys, "cases": n,
        "exact_steps": sum(r["exact_steps"] for r in rs) / n,
        "all_switches": sum(r["all_switches"] for r in rs) / n,
        "median_error_pct": statistics.median(r["median_error_pct"] for r in rs),
        "found/true_steps": statistics.mean(ratio),
        "median_seconds": statistics.median(r["seconds"] for r in rs),
        "failures": sum(r["error"] is not None for r in rs),
    }  # fmt: skip


def summarize_synthetic(rows: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Per (method, family, n_demos) and totals over families per (method, n_demos) and per method.

    Rates are fractions of cases; ``median_error_pct`` is the median over cases of each case's median boundary
    error; ``found/true_steps`` the mean over cases and demonstrations of found / true step counts.
    """
    methods = list(dict.fromkeys(r["method"] for r in rows))
    families = list(dict.fromkeys(r["family"] for r in rows))
    ns = sorted({r["n_demos"] for r in rows})
    per_family, totals = [], []
    for method in methods:
        for family in families:
            for n in ns:
                rs = [r for r in rows if (r["method"], r["family"], r["n_demos"]) == (method, family, n)]
                if rs:
                    per_family.append(_summary_row(rs, method=method, family=family, n_demos=n))
        for n in ns:
            rs = [r for r in rows if (r["method"], r["n_demos"]) == (method, n)]
            if rs:
                totals.append(_summary_row(rs, method=method, family="ALL", n_demos=n))
        totals.append(_summary_row([r for r in rows if r["method"] == method], method=method, family="ALL",
                                   n_demos="all"))  # fmt: skip
    return {"per_family": per_family, "totals": totals}


def _print(rows: list[dict[str, Any]]) -> None:
    if not rows:
        return
    keys = list(rows[0])
    print(" | ".join(keys))
    for r in rows:
        print(" | ".join(f"{r[k]:.4g}" if isinstance(r[k], float) else str(r[k]) for k in keys))
    print()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", nargs="+", default=["lasa", "scaling", "synthetic"],
                        choices=["lasa", "scaling", "synthetic", "membership"])  # fmt: skip
    parser.add_argument("--shapes", nargs="+", default=list(LASA_SHAPES))
    parser.add_argument("--lasa-seed", type=int, default=0,
                        help="sampler seed of the lasa part (each shape is segmented once, in this process, in order: "
                             "the first pays the process's one-off costs)")  # fmt: skip
    parser.add_argument("--seeds", type=int, default=10, help="synthetic cases per family and number of demos")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes for the synthetic part (one thread each)")
    parser.add_argument("--method", nargs="+", default=["segment", "ruptures", "hmmlearn"], choices=METHODS,
                        help="methods of the synthetic part")  # fmt: skip
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=list(ALL_FAMILIES),
                        help="synthetic part: families of FAMILIES (the default, all of them), HELD_OUT_FAMILIES or "
                             "SLOWING_FAMILIES")
    parser.add_argument("--n-demos", nargs="+", type=int, default=[1, 4])
    parser.add_argument("--noise-correlation", type=float, default=None, metavar="RHO",
                        help="synthetic part: AR(1) position noise of this lag-one correlation (same level) instead "
                             "of the families' white noise")  # fmt: skip
    parser.add_argument("--n-steps", type=int, default=None, metavar="M",
                        help="synthetic part, straight_* and curved_* families: M legs instead of 3-5")
    parser.add_argument("--rate", type=float, default=None, metavar="HZ",
                        help="synthetic part: the demonstrations recorded at HZ instead of 100 Hz (same durations, "
                             "white noise of the same level per sample)")
    parser.add_argument("--noise-scale", type=float, default=None, metavar="S",
                        help="synthetic part: new position noise at S times each case's level (same paths)")
    parser.add_argument("--json", type=str, default=None, help="write all rows to this JSON file")
    parser.add_argument("--segment-option", nargs="+", default=[], metavar="KEY=VALUE",
                        help="segment() keyword arguments of the segment methods (numbers, or None), e.g. extra_dof=2")
    args = parser.parse_args()
    options = segment_options(args.segment_option)
    if options:
        DETECTORS["segment"] = functools.partial(detect_segment, **options)
        DETECTORS["segment_joint"] = functools.partial(detect_segment, selection="joint", **options)
        DETECTORS["segment_collapsed"] = functools.partial(detect_segment, selection="collapsed", **options)
        DETECTORS["segment_modal"] = functools.partial(detect_segment, selection="modal", **options)
        DETECTORS["segment_map"] = functools.partial(detect_segment, selection="map", **options)
    torch.set_num_threads(1)
    result: dict[str, Any] = {}
    if "lasa" in args.parts:
        result["lasa"] = bench_lasa(tuple(args.shapes), seed=args.lasa_seed, **options)
        _print(result["lasa"])
    if "scaling" in args.parts:
        result["scaling"] = bench_scaling()
        _print(result["scaling"])
    if "membership" in args.parts:
        result["membership"] = bench_membership(args.seeds, tuple(args.families), tuple(args.n_demos))
        rows_m = result["membership"]
        print(f"membership: own_min over all sets {min(r['own_min'] for r in rows_m):.3f}, "
              f"other_max median {statistics.median(r['other_max'] for r in rows_m):.3f}, "
              f"max {max(r['other_max'] for r in rows_m):.3f}")  # fmt: skip
    if "synthetic" in args.parts:
        rows = synthetic_study(args.seeds, tuple(args.method), tuple(args.families), tuple(args.n_demos), args.jobs,
                               args.noise_correlation, args.n_steps, args.rate, args.noise_scale)
        summary = summarize_synthetic(rows)
        result["synthetic"] = rows
        result["synthetic_summary"] = summary
        result["synthetic_settings"] = {
            "tolerance": TOLERANCE, "savgol_window": SAVGOL_WINDOW, "penalty_c": PENALTY_C,
            "hmm_states": list(HMM_STATES), "seeds": args.seeds, "n_demos": args.n_demos,
            "noise_correlation": args.noise_correlation, "n_steps": args.n_steps, "rate": args.rate,
            "noise_scale": args.noise_scale,
        }  # fmt: skip
        print()
        _print(summary["per_family"])
        _print(summary["totals"])
    if args.json:
        from lfd_torch.store import atomic_write, git_sha

        result["provenance"] = {"git_sha": git_sha(), "methods": list(args.method), "segment_options": options,
                                "segment_settings": segment_settings(options)}
        atomic_write(args.json, lambda p: p.write_text(json.dumps(result, indent=2)))


if __name__ == "__main__":
    main()
