"""Metrics and the results store against independent references: per-sample Python loops, numpy,
shapely, closed forms and file-system properties (boundaries, dtype promotion, gapped masks, weights, atomicity)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lfd_torch.errors import InvalidArgumentError, InvalidDemoError, NonFiniteError, ShapeMismatchError
from lfd_torch.metrics import (
    aggregate,
    cosine_dissimilarity,
    dtw_distance,
    swept_area,
    triangle_areas,
    velocity_error,
)
from lfd_torch.utils import safe_magnitude

from pathlib import Path

F64 = torch.float64


# ----------------------------------------------------------------------------------------- naive references
def _loop_mean_norm(pred, ref):
    terms = [math.sqrt(sum((r - p) ** 2 for p, r in zip(ps, rs))) for ps, rs in zip(pred, ref)]
    return sum(terms) / len(terms)


def _loop_cosine(pred, ref, eps):
    total = 0.0
    for p, r in zip(pred, ref):
        n_p = math.sqrt(sum(c * c for c in p))
        n_r = math.sqrt(sum(c * c for c in r))
        if n_p <= eps and n_r <= eps:
            term = 0.0
        elif n_p <= eps or n_r <= eps:
            term = 1.0
        else:
            term = 1.0 - max(-1.0, min(1.0, sum(a * b for a, b in zip(p, r)) / (n_p * n_r)))
        total += term
    return total / len(pred)


# ----------------------------------------------------------------------------------------- E1 / E2 / E3
def test_masks_with_gaps_and_an_invalid_first_sample_match_loops():
    """E1 and E2 average over exactly the True entries of a general mask (gaps, first sample invalid); E3 sums the
    quadrilaterals of consecutive valid pairs only (shapely areas as reference)."""
    import shapely

    rng = np.random.default_rng(11)
    B, T, d = 6, 12, 2
    pred = torch.from_numpy(rng.normal(size=(B, T, d)))
    ref = torch.from_numpy(rng.normal(size=(B, T, d)))
    mask = torch.from_numpy(rng.random((B, T)) < 0.6)
    mask[:, 0] = False  # every row starts with an invalid sample
    mask[:, 4:7] = True  # and holds a run of consecutive valid samples
    pred_pad = pred.clone()
    pred_pad[~mask] = float("nan")
    e1 = velocity_error(pred_pad, ref, mask)
    e2 = cosine_dissimilarity(pred_pad, ref, mask)
    e3 = swept_area(pred_pad, ref, mask, reduction="sum")
    for b in range(B):
        idx = [t for t in range(T) if mask[b, t]]
        p, r = pred[b, idx].tolist(), ref[b, idx].tolist()
        assert float(e1[b]) == pytest.approx(_loop_mean_norm(p, r), rel=1e-12)
        assert float(e2[b]) == pytest.approx(_loop_cosine(p, r, 1e-9), rel=1e-12)
        pairs = [t for t in range(T - 1) if mask[b, t] and mask[b, t + 1]]
        quads = np.stack([ref[b, pairs], ref[b, [t + 1 for t in pairs]], pred[b, [t + 1 for t in pairs]],
                          pred[b, pairs]], 1)  # fmt: skip
        want = float(shapely.area(shapely.make_valid(shapely.polygons(quads))).sum())
        assert float(e3[b]) == pytest.approx(want, rel=1e-9)


def test_cosine_zero_threshold_is_inclusive_for_either_velocity():
    """A velocity whose norm equals eps exactly counts as zero (<= eps), for the prediction and for the
    reference; with eps = 0 an exactly zero velocity is zero and still gives a finite term."""
    v = torch.tensor([[[0.5, 0.0]]], dtype=F64)  # norm exactly 0.5
    parallel = torch.tensor([[[2.0, 0.0]]], dtype=F64)
    # one of the two counts as zero: orthogonal convention, term 1 (and not the parallel cosine's 0)
    assert float(cosine_dissimilarity(parallel, v, eps=0.5)) == 1.0
    assert float(cosine_dissimilarity(v, parallel, eps=0.5)) == 1.0
    assert float(cosine_dissimilarity(v, v, eps=0.5)) == 0.0  # both zero: full agreement
    zero = torch.zeros(1, 1, 2, dtype=F64)
    assert float(cosine_dissimilarity(parallel, zero, eps=0.0)) == 1.0
    assert float(cosine_dissimilarity(zero, parallel, eps=0.0)) == 1.0
    assert float(cosine_dissimilarity(zero, zero, eps=0.0)) == 0.0


def test_cosine_terms_never_leave_zero_to_two_for_parallel_and_antiparallel_pairs():
    """Each E2 term lies in [0, 2] even when the normalised dot product rounds past +-1 (clipping)."""
    g = torch.Generator().manual_seed(7)
    n = 4000
    p = torch.randn(n, 1, 3, generator=g, dtype=F64) * torch.exp(3 * torch.randn(n, 1, 1, generator=g, dtype=F64))
    scale = torch.rand(n, 1, 1, generator=g, dtype=F64) + 0.1
    anti = cosine_dissimilarity(p, -scale * p)
    same = cosine_dissimilarity(p, scale * p)
    assert (anti <= 2.0).all() and (anti >= 2.0 - 1e-15).all()
    assert (same >= 0.0).all() and (same <= 1e-15).all()


def test_mixed_float32_float64_inputs_promote_to_float64():
    """Inputs of different floating dtypes are promoted (float32 + float64 -> float64) before computing: the
    result equals the all-float64 result of the same numbers."""
    g = torch.Generator().manual_seed(3)
    a32 = torch.randn(3, 9, 2, generator=g).cumsum(1)
    b64 = torch.randn(3, 9, 2, generator=g, dtype=F64).cumsum(1)
    calls = [velocity_error, cosine_dissimilarity, swept_area, dtw_distance]
    for f in calls:
        for x, y in ((a32, b64), (b64, a32)):
            got = f(x, y)
            assert got.dtype == F64, f.__name__
            want = f(x.double(), y.double())
            torch.testing.assert_close(got, want, rtol=1e-13, atol=1e-13)


def test_magnitude_limit_is_inclusive():
    """A coordinate of magnitude exactly safe_magnitude(dtype) is accepted; the next float above is rejected."""
    limit = safe_magnitude(F64)  # a Python float: exactly representable in float64
    at = torch.full((1, 3, 2), limit, dtype=F64)
    assert float(velocity_error(at, at)) == 0.0
    assert float(velocity_error(-at, -at, kind="rms")) == 0.0
    above = torch.nextafter(at, torch.tensor(math.inf, dtype=F64))
    with pytest.raises(NonFiniteError):
        velocity_error(above, at)


def test_lengths_must_be_integer_tensors():
    """Floating or bool valid-sample counts are refused, not truncated to integers."""
    x = torch.zeros(2, 5, 2, dtype=F64)
    for bad in (torch.tensor([3.0, 5.0]), torch.tensor([True, True])):
        with pytest.raises(InvalidArgumentError):
            velocity_error(x, x, lengths=bad)
        with pytest.raises(InvalidArgumentError):
            dtw_distance(x, x, bad)


def test_triangle_areas_match_half_root_gram_determinant():
    """triangle_areas(u, v) = 0.5 sqrt(det [[u.u, u.v], [u.v, v.v]]) in d = 2, 3, 5 (numpy determinant)."""
    rng = np.random.default_rng(5)
    for d in (2, 3, 5):
        u = rng.normal(size=(200, d))
        v = rng.normal(size=(200, d))
        gram = np.stack([np.stack([(u * u).sum(1), (u * v).sum(1)], -1), np.stack([(u * v).sum(1), (v * v).sum(1)], -1)], -2)
        want = 0.5 * np.sqrt(np.linalg.det(gram))
        got = triangle_areas(torch.from_numpy(u), torch.from_numpy(v)).numpy()
        assert got.shape == (200,)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


# ----------------------------------------------------------------------------------------- aggregate
def test_aggregate_ignores_non_finite_values_of_zero_weight():
    """A NaN/Inf value whose count is 0 is left out of the pooled mean and RMS (closed forms)."""
    values = torch.tensor([2.0, math.nan, 4.0, math.inf], dtype=F64)
    counts = torch.tensor([1, 0, 3, 0])
    assert float(aggregate(values, counts)) == pytest.approx((2.0 + 12.0) / 4.0, rel=1e-15)
    assert float(aggregate(values, counts, kind="rms")) == pytest.approx(math.sqrt((4.0 + 48.0) / 4.0), rel=1e-15)
    with pytest.raises(NonFiniteError):
        aggregate(values, torch.tensor([1, 1, 3, 0]))


def test_aggregate_rejects_negative_infinite_and_bool_counts():
    """Counts must be non-negative, finite and numeric (not bool), even when their sum is positive."""
    values = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    with pytest.raises(InvalidDemoError) as err:
        aggregate(values, torch.tensor([2.0, -1.0, 3.0], dtype=F64))
    assert type(err.value) is InvalidDemoError and err.value.demo_index == 1
    with pytest.raises(NonFiniteError):
        aggregate(values, torch.tensor([1.0, math.inf, 1.0], dtype=F64))
    with pytest.raises(ShapeMismatchError):
        aggregate(values, torch.tensor([True, False, True]))


# ----------------------------------------------------------------------------------------- store: atomic writes
def _dead_pid() -> int:
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(done.stdout)


def test_stale_temporaries_of_names_with_glob_metacharacters_are_removed(tmp_path):
    """A destination named with glob metacharacters ([, ], *) still has its dead writers' temporaries removed,
    and a look-alike temporary of another destination is kept."""
    from lfd_torch.store import atomic_write

    target = tmp_path / "t[1]*.parquet"
    pid = _dead_pid()
    stale = tmp_path / f".t[1]*.parquet.{pid}.00ff.tmp"
    stale.write_bytes(b"half")
    lookalike = tmp_path / f".t1x.parquet.{pid}.00ff.tmp"  # what the unescaped pattern t[1]*.parquet would match
    lookalike.write_bytes(b"other")
    atomic_write(target, lambda p: p.write_bytes(b"new"))
    assert target.read_bytes() == b"new"
    assert not stale.exists() and lookalike.exists()


def test_temporaries_with_a_foreign_name_or_an_unkillable_owner_are_kept(tmp_path, monkeypatch):
    """A temporary whose pid field is not a number is left alone (no crash); one whose process exists but belongs to
    another user (kill(pid, 0) -> PermissionError) is a live writer and is kept."""
    import os

    from lfd_torch.store import atomic_write

    target = tmp_path / "out.bin"
    odd = tmp_path / ".out.bin.notapid.1234.tmp"
    odd.write_bytes(b"x")
    foreign = tmp_path / ".out.bin.999999.abcd.tmp"
    foreign.write_bytes(b"y")
    real_kill = os.kill

    def kill(pid, sig):
        if pid == 999999:
            raise PermissionError(1, "Operation not permitted")
        return real_kill(pid, sig)

    monkeypatch.setattr(os, "kill", kill)
    atomic_write(target, lambda p: p.write_bytes(b"new"))
    assert target.read_bytes() == b"new" and odd.exists() and foreign.exists()


def test_atomic_path_refuses_directory_like_names(tmp_path):
    """'..' as the last component is not a file path: StoreError before any write, nothing created or replaced."""
    from lfd_torch.errors import StoreError
    from lfd_torch.store import atomic_write

    (tmp_path / "sub").mkdir()
    calls = []
    with pytest.raises(StoreError, match="not a file path"):
        atomic_write(tmp_path / "sub" / "..", lambda p: calls.append(p) or p.write_bytes(b"x"))
    assert calls == [] and sorted(p.name for p in tmp_path.rglob("*")) == ["sub"]


def test_hidden_files_and_folders_are_not_sweep_parts(tmp_path):
    """Hidden names (a leading '.') are temporary, in the file name and in any folder above it: a valid table under
    a hidden staging folder or in a hidden file is never collected."""
    from lfd_torch.store import collect, find_parts, is_temp_file, write_table

    assert is_temp_file(tmp_path / ".hidden.parquet") and is_temp_file("x.tmp") and not is_temp_file("x.parquet")
    write_table([_row()], tmp_path / "0" / "results.parquet")
    write_table([_row(trajectory=1)], tmp_path / ".staging-7" / "0" / "results.parquet")
    write_table([_row(trajectory=2)], tmp_path / "1" / ".results.parquet")
    assert find_parts(tmp_path) == [tmp_path / "0" / "results.parquet"]
    assert collect(tmp_path)["trajectory"].tolist() == [0]


# ----------------------------------------------------------------------------------------- store: checksums
def test_digest_separates_structures_that_share_a_byte_stream():
    """Length prefixes and type tags keep apart values a naive concatenation would merge: nested list boundaries,
    nested mapping boundaries, string boundaries, True vs 1, and floats that differ in the last bit."""
    from lfd_torch.store.checksum import payload_digest

    pairs = [
        ({"x": [[1], 2]}, {"x": [[1, 2]]}),
        ({"a": {"b": 1}, "c": 2}, {"a": {"b": 1, "c": 2}}),
        ({"x": ["aS:b", "c"]}, {"x": ["a", "bS:c"]}),
        ({"x": ["ab", "c"]}, {"x": ["a", "bc"]}),
        ({"x": True}, {"x": 1}),
        ({"x": False}, {"x": 0}),
        ({"x": 0.1}, {"x": math.nextafter(0.1, 1.0)}),
        ({"x": 1.0 + 2.0**-40}, {"x": 1.0}),
    ]
    for a, b in pairs:
        assert payload_digest(a) != payload_digest(b), (a, b)
    # and equal content gives equal digests, whatever the key order
    assert payload_digest({"a": [1, "s", None, 2.5], "b": True}) == payload_digest({"b": True, "a": (1, "s", None, 2.5)})


def test_digest_mismatch_in_any_hex_digit_is_detected():
    """verify_digest compares the whole digest: changing the last hex digit of a stored digest is caught."""
    from lfd_torch.errors import StoreError
    from lfd_torch.store.checksum import DIGEST_KEY, payload_digest, verify_digest

    state = {"w": torch.arange(4, dtype=F64), "n": 3}
    state[DIGEST_KEY] = payload_digest(state)
    verify_digest(state, "ok")
    for k in (0, 31, 63):
        digit = state[DIGEST_KEY][k]
        tampered = dict(state)
        tampered[DIGEST_KEY] = state[DIGEST_KEY][:k] + ("0" if digit != "0" else "1") + state[DIGEST_KEY][k + 1 :]
        with pytest.raises(StoreError, match="checksum"):
            verify_digest(tampered, "damaged")


def test_compact_cpu_storage_holds_exactly_the_view():
    """compact_cpu of a view (slice, transpose, offset) owns a storage of exactly numel * element_size bytes that
    holds the view's values; a compact tensor is returned as is."""
    from lfd_torch.store.checksum import compact_cpu

    base = torch.arange(24, dtype=F64).reshape(4, 6)
    for view in (base[:2], base[1:3, 2:], base.t(), base[:, 0]):
        c = compact_cpu(view)
        assert torch.equal(c, view)
        assert c.untyped_storage().nbytes() == view.numel() * view.element_size()
        assert c.is_contiguous() and c.storage_offset() == 0
    assert compact_cpu(base).data_ptr() == base.data_ptr()  # already compact: no copy


# ----------------------------------------------------------------------------------------- store: staging
def test_staged_outputs_publish_tables_last_and_manifests_after_their_files(tmp_path, monkeypatch):
    """On success the staged files are moved in this order: everything outside tables/ first, a folder's
    manifest.json after its other files, tables/ last (a reader of a table sees the figures and libraries it
    describes)."""
    import os

    from lfd_torch.store import staged_outputs

    moved = []
    real_replace = os.replace

    def record(src, dst):
        moved.append(Path(dst).relative_to(tmp_path).as_posix())
        return real_replace(src, dst)

    with staged_outputs(tmp_path) as staging:
        monkeypatch.setattr(os, "replace", record)
        for rel in ("tables/a.parquet", "libraries/lib/manifest.json", "libraries/lib/z.pt", "figures/f.png",
                    "libraries/lib/a.pt", "zz/x.txt"):  # fmt: skip
            (staging / rel).parent.mkdir(parents=True, exist_ok=True)
            (staging / rel).write_text(rel)
    assert moved[-1] == "tables/a.parquet"
    lib = [m for m in moved if m.startswith("libraries/lib/")]
    assert lib[-1] == "libraries/lib/manifest.json" and len(lib) == 3
    assert sorted(moved) == sorted(["tables/a.parquet", "libraries/lib/manifest.json", "libraries/lib/z.pt",
                                    "figures/f.png", "libraries/lib/a.pt", "zz/x.txt"])  # fmt: skip


# ----------------------------------------------------------------------------------------- store: tables, collect
def _row(**change):
    row = {"experiment": "e", "shape": "s", "method": "m", "fold": 0, "seed": 0, "trajectory": 0, "config_hash": "h",
           "package_version": "v", "git_sha": "g", "x": 1.0}  # fmt: skip
    row.update(change)
    return row


def test_tables_reject_null_provenance_duplicated_columns_and_partial_manifest_agreement(tmp_path):
    """Provenance columns may not hold nulls, a column name may not repeat, and every row (not just one) must agree
    with the manifest; the previous file stays in place."""
    import pandas as pd

    from lfd_torch.errors import StoreError
    from lfd_torch.store import write_table

    path = tmp_path / "t.parquet"
    write_table([_row()], path)
    before = path.read_bytes()
    for column in ("config_hash", "package_version", "git_sha"):
        with pytest.raises(StoreError, match="null"):
            write_table([_row(trajectory=1), _row(**{column: None})], path)
    frame = pd.DataFrame([list(_row().values()) + [2.0]], columns=[*_row().keys(), "x"])
    with pytest.raises(StoreError, match="duplicated column"):
        write_table(frame, path)
    manifest = {"config_hash": "h", "seed": 0, "package_version": "v", "git_sha": "g"}
    with pytest.raises(StoreError, match="manifest says"):
        write_table([_row(), _row(trajectory=1, config_hash="other")], path, manifest=manifest)
    assert path.read_bytes() == before


def test_collect_recency_follows_the_write_time_metadata_not_the_mtime(tmp_path):
    """Two writes of the same key by the same configuration: the later write wins even when the files' mtimes say
    the opposite (a copy or a touch changes the mtime, not the recorded write time)."""
    import os
    import time
    import warnings

    from lfd_torch.store import collect, write_table

    first = write_table([_row(x=1.0)], tmp_path / "b" / "results.parquet")
    time.sleep(0.01)
    second = write_table([_row(x=2.0)], tmp_path / "a" / "results.parquet")  # sorts first, written last
    now = time.time()
    os.utime(first, (now + 100, now + 100))  # the older write gets the newer mtime
    os.utime(second, (now - 100, now - 100))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        merged = collect(tmp_path)
    assert merged["x"].tolist() == [2.0]


def test_collect_never_reads_back_its_own_output_inside_the_sweep(tmp_path):
    """A merged table saved inside the sweep is not a part of the next collect: after a part is removed, the
    next merge no longer holds its rows."""
    from lfd_torch.store import collect, write_table

    sweep = tmp_path / "sweep"
    write_table([_row()], sweep / "0" / "results.parquet")
    write_table([_row(trajectory=1)], sweep / "1" / "results.parquet")
    out = sweep / "merged.parquet"
    assert len(collect(sweep, save_to=out)) == 2
    (sweep / "1" / "results.parquet").unlink()
    assert collect(sweep, save_to=out)["trajectory"].tolist() == [0]


def test_collect_with_only_unreadable_parts_keeps_the_published_table(tmp_path):
    """Parts exist but none is readable: collect(save_to=...) raises and the published file is unchanged."""
    import warnings

    from lfd_torch.errors import StoreError
    from lfd_torch.store import collect, write_table

    published = write_table([_row()], tmp_path / "published.parquet")
    before = published.read_bytes()
    sweep = tmp_path / "sweep"
    (sweep / "0").mkdir(parents=True)
    (sweep / "0" / "results.parquet").write_bytes(before[: len(before) // 2])  # truncated
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(StoreError, match="nothing written"):
            collect(sweep, save_to=published)
    assert published.read_bytes() == before


def test_finished_part_without_a_manifest_is_not_finished(tmp_path):
    """A valid table written without a manifest cannot prove its configuration: it is not resumed."""
    from lfd_torch.store import finished_part, write_table

    path = write_table([_row()], tmp_path / "results.parquet")
    assert finished_part(path, {"config_hash": "h", "seed": 0, "git_sha": "g"}) is None


def test_unfinished_jobs_does_not_confuse_job_1_with_job_10(tmp_path):
    """Job folders whose names are prefixes of one another (1 and 10): a table in 10 does not finish 1."""
    from lfd_torch.store import unfinished_jobs, write_table

    for job in ("1", "10"):
        (tmp_path / job / ".hydra").mkdir(parents=True)
        (tmp_path / job / ".hydra" / "config.yaml").write_text("seed: 0\n")
    write_table([_row()], tmp_path / "10" / "results.parquet")
    assert unfinished_jobs(tmp_path) == [tmp_path / "1"]


def _sweep_yaml(folder, task, params):
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["hydra:", "  sweep:", "    subdir: ${hydra.job.num}", "  sweeper:",
             "    _target_: hydra._internal.core_plugins.basic_sweeper.BasicSweeper", "    params:"]  # fmt: skip
    lines += [f"      {k}: {v}" for k, v in params.items()] + ["  overrides:", "    task:"]
    lines += [f"    - {t}" for t in task]
    (folder / "multirun.yaml").write_text("\n".join(lines) + "\n")
    return folder / "multirun.yaml"


def test_expected_jobs_is_the_product_of_the_sweep_sizes(tmp_path):
    """The job count of a basic sweep is the product (not the sum) of its sweeps' sizes, counting a preset's
    param only where the command line does not set the key, with or without a '+' prefix."""
    from lfd_torch.store.sweep import expected_jobs

    assert expected_jobs(_sweep_yaml(tmp_path / "a", ["fold=0,1", "budget_s=5"], {"shape": "a,b"})) == 4
    assert expected_jobs(_sweep_yaml(tmp_path / "b", ["fold=0,1,2", "seed=1,2,3"], {"shape": "x,y,z,w"})) == 36
    assert expected_jobs(_sweep_yaml(tmp_path / "c", ["fold=0,1", "+shape=a"], {"shape": "a,b"})) == 2


# ----------------------------------------------------------------------------------------- store: config hash
def test_config_hash_is_the_sha256_of_the_documented_canonical_json():
    """config_hash = sha256 of compact JSON with sorted keys, non-ASCII kept as UTF-8, tuples as lists, the
    top-level run-location keys left out; True/1, inf/None, and the order a set was built in are told apart
    or not as JSON would."""
    import enum
    import hashlib

    from lfd_torch.store import config_hash

    class Mode(enum.Enum):
        FAST = "fast"

    cfg = {"b": (1, 2.5, "é"), "a": {"y": None, "x": True}, "m": Mode.FAST}
    text = '{"a":{"x":true,"y":null},"b":[1,2.5,"é"],"m":"fast"}'
    assert config_hash(cfg) == hashlib.sha256(text.encode("utf-8")).hexdigest()[:12]
    assert config_hash(cfg, length=64) == hashlib.sha256(text.encode("utf-8")).hexdigest()
    located = dict(cfg, seed=4, hydra={"run": "x"}, paths={"results": "/r"}, out_dir="/o", publish=True, resume=True,
                   progress=False)  # fmt: skip
    assert config_hash(located) == config_hash(cfg)
    assert config_hash({"v": True}) != config_hash({"v": 1})
    values = [math.inf, -math.inf, math.nan, None, 0.0]
    assert len({config_hash({"v": v}) for v in values}) == len(values)
    assert config_hash({"s": set([9, 1])}) == config_hash({"s": set([1, 9])}) == config_hash({"s": [1, 9]})
