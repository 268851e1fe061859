"""Bad input to the BP-GM-HMM segmentation and its stored state: short demonstrations under the dwell cue, malformed
segmentation state dicts and files, and a non-bool ``end_at_attractor`` (issue: confirmed bad-input defects).

Every test seeds its generators; the file runs in a few seconds (small data, ``FixedSegmenter`` for the states).
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import pytest
import torch

from lfd_torch.data import Demos
from lfd_torch.errors import InvalidArgumentError, StoreError
from lfd_torch.segmentation import FixedSegmenter, Segmentation, segment
from lfd_torch.segmentation.dwell import dwell_log_likelihood, dwell_log_prob, dwell_prior, dwell_start

F64 = torch.float64
ROOT = Path(__file__).resolve().parents[1]


def _curve(T: int, seed: int = 0) -> torch.Tensor:
    """(T, 2) a smooth curve with small noise (one demonstration that moves)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0.0, 1.0, T, dtype=F64)
    return torch.stack([torch.cos(2 * t), torch.sin(3 * t)], -1) + 1e-3 * torch.randn(T, 2, generator=g, dtype=F64)


def _two_demos() -> Demos:
    t = torch.linspace(0.0, 1.0, 40, dtype=F64)[:, None]
    return Demos.from_sequences([t * torch.tensor([1.0, 0.5], dtype=F64), t * torch.tensor([0.8, -0.3], dtype=F64)])


# ---------------------------------------------------------------------------------------------- 1. dwell cue
@pytest.mark.parametrize("T, kw", [(6, {}), (7, {}), (86, {"min_length": 0.5, "n_iterations": 4, "n_chains": 1}),
                                   (86, {"min_length": 43, "n_iterations": 4, "n_chains": 1})])
def test_short_demonstrations_segment_with_the_dwell_cue(T: int, kw: dict) -> None:
    """Property: a demonstration that passes the documented length checks (T >= 2 * min_length) segments with the
    default ``dwell_cue=True`` even when fewer than 2 grid points can start a run (the dwell term's start variance is
    undefined there): one step covering every sample, finite scores and dwell summary, no torch warning."""
    x = _curve(T)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seg = segment([x], generator=torch.Generator().manual_seed(0), **kw)
    assert seg.n_steps == 1 and seg.labels[0].shape == (T,) and seg.pieces[0].tolist() == [[0, 0, T]]
    assert all(torch.isfinite(torch.tensor(v)) for v in seg.info["dwell"].values()) and seg.info["dwell"]
    assert torch.isfinite(torch.tensor(seg.info["collapsed_log_prob"]))
    assert not [w for w in caught if "degrees of freedom" in str(w.message)], [str(w.message) for w in caught]


@pytest.mark.parametrize("n_seen", [0, 1, 2, 5])
def test_dwell_start_is_finite_for_fewer_than_two_values(n_seen: int) -> None:
    """Property (dwell.dwell_start docstring): the chains' start is (mean of c, 0) and the variance of c floored at
    1e-6 (torch's own mean and var, bit for bit) with 2 or more values; with fewer, where those are undefined, mu -> 0
    (with none) or the one value, and sigma^2 -> the prior's E[sigma^2] = 0.1, so the dwell term is finite."""
    seen = torch.tensor([0.3, -0.2, 0.1, 0.25, -0.05], dtype=F64)[:n_seen]
    beta, noise = dwell_start(seen)
    assert beta.shape == (2,) and noise.shape == () and beta.dtype == noise.dtype == F64
    if n_seen >= 2:
        assert torch.equal(beta, torch.stack([seen.mean(), torch.zeros((), dtype=F64)]))
        assert torch.equal(noise, seen.var().clamp_min(1e-6))
    else:
        assert beta.tolist() == [seen.sum().item(), 0.0] and noise.item() == 0.1
    c = torch.tensor([[0.0, 0.3, -0.2, 0.1]], dtype=F64)
    mask = torch.zeros(1, 4, dtype=torch.bool)
    mask[0, 1 : 1 + min(n_seen, 3)] = True
    ll = dwell_log_likelihood(c, mask, beta.expand(2, 2), noise.expand(2))
    assert ll.shape == (2, 1, 4, 2) and bool(torch.isfinite(ll).all()) and bool((ll[:, :, ~mask[0]] == 0).all())
    phase = torch.ones(2, 1, 4, dtype=torch.long)
    assert bool(torch.isfinite(dwell_log_prob(dwell_prior(), c, mask, phase, beta.expand(2, 2), noise.expand(2))).all())


# ---------------------------------------------------------------------------------------------- 2. stored state
@pytest.fixture(scope="module")
def seg() -> Segmentation:
    return FixedSegmenter([0.5])(_two_demos())  # M = 2 steps, N = 2 demonstrations, d = 2


def _cov_not_pd(state: dict) -> torch.Tensor:
    cov = state["space_covariance"].clone()
    cov[0] = -cov[0]
    return cov


def _labels_off(state: dict) -> list[torch.Tensor]:
    first = state["labels"][0].clone()
    first[0] = 1  # sample 0 lies in a piece of step 0
    return [first, state["labels"][1]]


#: (what is wrong, the key the error must name, the malformed entries of a state dict of M = 2, N = 2, d = 2)
BAD_STATES = [
    ("M=3 attractors", "attractors", lambda s: {"attractors": torch.zeros(3, 2, dtype=F64)}),
    ("list attractors", "attractors", lambda s: {"attractors": s["attractors"].tolist()}),
    ("long attractors", "attractors", lambda s: {"attractors": s["attractors"].long()}),
    ("int routes", "routes", lambda s: {"routes": 5}),
    ("step 9 in routes", "routes", lambda s: {"routes": [[0, 9]]}),
    ("step 1 in no route", "routes", lambda s: {"routes": [[0]]}),
    ("bool in routes", "routes", lambda s: {"routes": [[0, True]]}),
    ("int states", "states", lambda s: {"states": 5}),
    ("short states", "states", lambda s: {"states": [t[:-1] for t in s["states"]]}),
    ("1-D pieces", "pieces", lambda s: {"pieces": [p.reshape(-1) for p in s["pieces"]]}),
    ("float pieces", "pieces", lambda s: {"pieces": [p.float() for p in s["pieces"]]}),
    ("pieces not covering", "pieces", lambda s: {"pieces": [s["pieces"][0][:1], s["pieces"][1]]}),
    ("labels against pieces", "labels", lambda s: {"labels": _labels_off(s)}),
    ("N=1 labels", "labels", lambda s: {"labels": s["labels"][:1]}),
    ("route_of out of range", "route_of", lambda s: {"route_of": torch.tensor([0, 1])}),
    ("short step_state", "step_state", lambda s: {"step_state": torch.tensor([0])}),
    ("d=3 endpoints", "endpoints", lambda s: {"endpoints": torch.zeros(2, 2, 3, dtype=F64)}),
    ("negative space_weights", "space_weights", lambda s: {"space_weights": -s["space_weights"]}),
    ("narrow space_weights", "space_weights", lambda s: {"space_weights": s["space_weights"][:, :-1]}),
    ("zero space_weights", "space_weights", lambda s: {"space_weights": torch.zeros_like(s["space_weights"])}),
    ("d=1 space_mean", "space_mean", lambda s: {"space_mean": s["space_mean"][:, :1]}),
    ("float32 space_mean", "space_mean", lambda s: {"space_mean": s["space_mean"].float()}),
    ("space_covariance not PD", "space_covariance", lambda s: {"space_covariance": _cov_not_pd(s)}),
    ("J-1 space_covariance", "space_covariance", lambda s: {"space_covariance": s["space_covariance"][:-1]}),
    ("extra key", "stray", lambda s: {"stray": 1}),
]


@pytest.mark.parametrize("what, key, change", BAD_STATES, ids=[c[0] for c in BAD_STATES])
def test_malformed_state_dicts_are_store_errors_naming_the_key(seg: Segmentation, what: str, key: str,
                                                               change) -> None:
    """Property (Segmentation.from_state_dict docstring): a wrong type, shape or dtype, an out-of-range or
    inconsistent entry (M, J, N, d) or an unknown key is a StoreError whose message names the key, never a builtin
    error inside torch later (TypeError, StopIteration, RuntimeError) nor a silent acceptance."""
    state = seg.state_dict()
    with pytest.raises(StoreError, match=key):
        Segmentation.from_state_dict(state | change(state))


def test_a_missing_key_is_named(seg: Segmentation) -> None:
    """Property: a state without ``labels`` (or any other key) says which key is missing, not that ``endpoints``
    is malformed."""
    state = seg.state_dict()
    for key in ("labels", "routes", "space_weights"):
        with pytest.raises(StoreError, match=key) as info:
            Segmentation.from_state_dict({k: v for k, v in state.items() if k != key})
        assert "lacks" in str(info.value) and "endpoints" not in str(info.value)


def test_a_saved_inconsistent_segmentation_does_not_load_but_published_ones_do(seg: Segmentation,
                                                                                  tmp_path: Path) -> None:
    """Property (Segmentation.load): a file whose content is consistent with its digest but not with itself
    (attractors of M = 3 rows for 2 steps) raises StoreError naming the file and the key; files the current code
    saves, those saved before the end points were kept, and the published ones under results/ load."""
    bad = dataclasses.replace(seg, attractors=torch.zeros(3, 2, dtype=F64))
    with pytest.raises(StoreError, match="bad.pt.*attractors"):
        Segmentation.load(bad.save(tmp_path / "bad.pt"))
    back = Segmentation.load(seg.save(tmp_path / "seg.pt"))
    assert torch.equal(back.attractors, seg.attractors) and back.routes == seg.routes
    legacy = {k: v for k, v in seg.state_dict().items() if k != "endpoints"}
    assert Segmentation.from_state_dict(legacy).endpoints is None
    for path in sorted((ROOT / "results").rglob("segmentation.pt")):  # none in a copy without results/
        loaded = Segmentation.load(path)
        assert len(loaded.table()) == loaded.n_steps


# ---------------------------------------------------------------------------------------------- 3. split
def test_split_requires_a_bool_end_at_attractor(seg: Segmentation) -> None:
    """Property (Segmentation.split docstring): ``end_at_attractor`` other than a bool ("no", 1, None) is an
    InvalidArgumentError naming it, not read as its truth value; True and False keep working."""
    demos = _two_demos()
    for bad in ("no", 1, None, 0.0):
        with pytest.raises(InvalidArgumentError, match="end_at_attractor"):
            seg.split(demos, end_at_attractor=bad)
    plain, closed = seg.split(demos, end_at_attractor=False), seg.split(demos, end_at_attractor=True)
    assert [int(p.lengths[0]) + 1 for p in plain] == [int(p.lengths[0]) for p in closed]
