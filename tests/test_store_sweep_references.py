"""Results store checked against independent references (mutation review of store/sweep, table, manifest).

References: pandas frames built by hand, hashlib/json computed by hand, files damaged by hand (truncated, byte
flipped), crashes simulated with monkeypatch, and Hydra sweep folders laid out by hand.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import os
import re
import time
import warnings
from pathlib import Path, PureWindowsPath

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from lfd_torch.errors import StoreError
from lfd_torch.store import (
    KEY_COLUMNS,
    canonical_json,
    collect,
    config_hash,
    find_parts,
    finished_part,
    read_manifest,
    read_table,
    unfinished_jobs,
    write_table,
)
from lfd_torch.store import manifest as manifest_module
from lfd_torch.store.table import WRITTEN_AT_METADATA_KEY, MANIFEST_METADATA_KEY


def _row(**change):
    row = {"experiment": "e", "shape": "s", "method": "m", "fold": 0, "seed": 0, "trajectory": 0, "config_hash": "h",
           "package_version": "v", "git_sha": "g", "x": 1.0}  # fmt: skip
    row.update(change)
    return row


MANIFEST = {"config_hash": "h", "seed": 0, "package_version": "v", "git_sha": "g"}


def _truncate(path: Path) -> None:
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])


def _flip_footer_magic(path: Path) -> None:
    raw = bytearray(path.read_bytes())
    raw[-1] ^= 0xFF  # the trailing b"PAR1" magic: pyarrow refuses the file
    path.write_bytes(bytes(raw))


# ------------------------------------------------------------------------------------------ damaged files
@pytest.mark.parametrize("damage", [_truncate, _flip_footer_magic])
def test_damaged_tables_raise_store_error_on_read(tmp_path, damage):
    """read_table and read_manifest of a truncated or byte-flipped Parquet file raise StoreError naming the file,
    never a raw pyarrow exception (documented: 'the file is missing or unreadable')."""
    path = write_table([_row()], tmp_path / "results.parquet", manifest=MANIFEST)
    damage(path)
    with pytest.raises(pa.ArrowException):  # the reference: pyarrow itself refuses the damaged file
        pq.read_table(path)
    for reader in (read_table, read_manifest):
        with pytest.raises(StoreError, match="results.parquet"):
            reader(path)


@pytest.mark.parametrize("damage", [_truncate, _flip_footer_magic])
def test_a_damaged_part_is_not_finished_and_does_not_raise(tmp_path, damage):
    """finished_part of a damaged results file (truncated, byte flipped) is None: the job runs again (documented:
    'A missing, damaged or foreign file ... is not finished')."""
    path = write_table([_row()], tmp_path / "results.parquet", manifest=MANIFEST)
    assert finished_part(path, MANIFEST) is not None
    damage(path)
    assert finished_part(path, MANIFEST) is None


def test_finished_part_rejects_an_invalid_table_with_a_matching_manifest(tmp_path):
    """A file whose manifest matches but whose rows are not a valid results table (duplicated keys, written by
    another tool) is not finished."""
    frame = pd.DataFrame([_row(), _row(x=2.0)])  # the same key twice
    table = pa.Table.from_pandas(frame, preserve_index=False)
    table = table.replace_schema_metadata({**table.schema.metadata, MANIFEST_METADATA_KEY: json.dumps(MANIFEST).encode()})
    path = tmp_path / "results.parquet"
    pq.write_table(table, path)
    assert read_manifest(path) == MANIFEST
    assert finished_part(path, MANIFEST) is None


def test_read_table_validates_only_when_asked(tmp_path):
    """read_table(validate=True) (the default) raises StoreError on duplicated keys; validate=False returns the rows
    exactly as pandas reads them back."""
    frame = pd.DataFrame([_row(), _row(x=2.0)])
    path = tmp_path / "dup.parquet"
    pq.write_table(pa.Table.from_pandas(frame, preserve_index=False), path)
    with pytest.raises(StoreError, match="share their key"):
        read_table(path)
    pd.testing.assert_frame_equal(read_table(path, validate=False), pd.read_parquet(path))


# ------------------------------------------------------------------------------------------ crash during write
def test_an_arrow_error_midway_through_a_write_keeps_the_old_table(tmp_path, monkeypatch):
    """A pyarrow error (not an OSError) raised after half the file was written: StoreError, the published table's
    bytes unchanged, no temporary file left."""
    path = write_table([_row()], tmp_path / "results.parquet")
    before = path.read_bytes()
    real = pq.write_table

    def half_then_arrow_error(table, where, **kwargs):
        real(table, where, **kwargs)
        with open(where, "r+b") as handle:
            handle.truncate(os.path.getsize(where) // 2)
        raise pa.ArrowInvalid("simulated encoder failure")

    monkeypatch.setattr(pq, "write_table", half_then_arrow_error)
    with pytest.raises(StoreError, match="simulated encoder failure"):
        write_table([_row(x=2.0)], path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.parquet"]


def test_nullable_and_string_dtypes_round_trip_exactly(tmp_path):
    """write_table then read_table gives back the same frame, pandas extension dtypes included (nullable Int64 with
    a missing value, a string column with a missing value)."""
    frame = pd.DataFrame([_row(), _row(trajectory=1)])
    frame["n"] = pd.array([1, None], dtype="Int64")
    frame["label"] = pd.array(["a", None], dtype="string")
    got = read_table(write_table(frame, tmp_path / "t.parquet"))
    pd.testing.assert_frame_equal(got, frame)
    assert got["n"].dtype == pd.Int64Dtype()


# ------------------------------------------------------------------------------------------ collect
def test_find_parts_is_sorted_and_column_order_follows_sorted_parts(tmp_path):
    """find_parts returns the parts in sorted path order; collect orders the non-key columns by first appearance over
    the parts in that order (reference: the column lists written, concatenated by hand)."""
    names = ["2", "0", "1"]
    extra = {"0": "A", "1": "B", "2": "C"}
    for i, name in enumerate(names):
        write_table([_row(trajectory=i, **{extra[name]: float(i)})], tmp_path / name / "results.parquet")
    parts = find_parts(tmp_path)
    assert parts == sorted(tmp_path / n / "results.parquet" for n in names)
    merged = collect(tmp_path)
    rest = [c for c in _row() if c not in KEY_COLUMNS]
    assert list(merged.columns) == list(KEY_COLUMNS) + rest + ["A", "B", "C"]
    expected = pd.DataFrame([_row(trajectory=i, **{extra[n]: float(i)}) for i, n in enumerate(names)])
    expected = expected.sort_values(list(KEY_COLUMNS)).reset_index(drop=True)[list(merged.columns)]
    pd.testing.assert_frame_equal(merged, expected, check_dtype=False)


def test_collect_with_array_cells_raises_store_error(tmp_path):
    """Parts holding array-valued cells cannot be merged: a typed StoreError, not a raw TypeError."""
    write_table([_row(arr=[1.0, 2.0])], tmp_path / "0" / "results.parquet")
    write_table([_row(trajectory=1, arr=[3.0])], tmp_path / "1" / "results.parquet")
    with pytest.raises(StoreError, match="non-scalar"):
        collect(tmp_path)


def test_collect_saves_to_an_upper_case_suffix(tmp_path):
    """The save_to suffix is case-insensitive: 'ALL.PARQUET' is written as Parquet and reads back as the merged
    table."""
    write_table([_row()], tmp_path / "sweep" / "0" / "results.parquet")
    out = tmp_path / "ALL.PARQUET"
    merged = collect(tmp_path / "sweep", save_to=out)
    pd.testing.assert_frame_equal(pd.read_parquet(out), merged, check_dtype=False)


def test_recency_falls_back_to_the_mtime_when_the_write_time_is_unreadable(tmp_path):
    """Parts whose lfd_torch.written_at_ns metadata is not an integer are ordered by their mtime: the part with the
    newer mtime wins even when its path sorts first."""
    for name, x, age in (("a", 2.0, 0), ("b", 1.0, 1000)):  # 'a' sorts first but is the newer file
        table = pa.Table.from_pandas(pd.DataFrame([_row(x=x)]), preserve_index=False)
        table = table.replace_schema_metadata({**table.schema.metadata, WRITTEN_AT_METADATA_KEY: b"not-a-number"})
        path = tmp_path / name / "results.parquet"
        path.parent.mkdir()
        pq.write_table(table, path)
        stamp = time.time() - age
        os.utime(path, (stamp, stamp))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        merged = collect(tmp_path)
    assert merged["x"].tolist() == [2.0]


# ------------------------------------------------------------------------------------------ unfinished sweeps
def test_job_0_that_never_started_keeps_the_sweep_unfinished(tmp_path):
    """A basic sweep of 2 jobs in which job 0 never made its folder (job 1 finished): unfinished_jobs names job 0,
    counting from 0 as Hydra's ${hydra.job.num} does."""
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "multirun.yaml").write_text(
        "hydra:\n  sweep:\n    subdir: ${hydra.job.num}\n  sweeper:\n"
        "    _target_: hydra._internal.core_plugins.basic_sweeper.BasicSweeper\n"
        "  overrides:\n    task:\n    - fold=0,1\n")
    (sweep / "1" / ".hydra").mkdir(parents=True)
    (sweep / "1" / ".hydra" / "config.yaml").write_text("seed: 0\n")
    write_table([_row()], sweep / "1" / "results.parquet")
    assert unfinished_jobs(sweep) == [sweep / "0"]


# ------------------------------------------------------------------------------------------ manifest
def test_git_sha_is_dirty_when_the_status_cannot_be_read(monkeypatch):
    """If `git status` fails after `git rev-parse` succeeded, the tree is not claimed clean: '<sha>-dirty'."""
    sha = "a" * 40

    def fake_git(args, cwd):
        return sha if args[0] == "rev-parse" else None

    monkeypatch.setattr(manifest_module, "_run_git", fake_git)
    assert manifest_module._git_sha_uncached("/nowhere") == f"{sha}-dirty"
    monkeypatch.setattr(manifest_module, "_run_git", lambda args, cwd: sha if args[0] == "rev-parse" else "")
    assert manifest_module._git_sha_uncached("/nowhere") == sha


def test_run_manifest_timestamp_is_utc_to_the_second():
    """run_manifest's timestamp is UTC ISO 8601 with seconds resolution (no fraction)."""
    stamp = manifest_module.run_manifest(None, 0)["timestamp"]
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\+00:00", stamp), stamp


def test_canonical_json_of_keys_paths_enums_and_dataclasses():
    """Reference JSON written by hand: non-string keys become their JSON text (true, null, 1.5), a Windows path is
    POSIX, an enum is its value, a dataclass is the mapping of its fields; config_hash is the sha256 of that text."""

    class Level(enum.Enum):
        LOW = 3

    @dataclasses.dataclass
    class Opt:
        lr: float
        name: str

    cfg = {"k": {True: 1, None: 2, 1.5: 3}, "p": PureWindowsPath(r"data\lasa\x.mat"), "e": Level.LOW,
           "o": Opt(0.5, "adam")}  # fmt: skip
    text = '{"e":3,"k":{"1.5":3,"null":2,"true":1},"o":{"lr":0.5,"name":"adam"},"p":"data/lasa/x.mat"}'
    assert canonical_json(cfg) == text
    assert config_hash(cfg, length=64) == hashlib.sha256(text.encode("utf-8")).hexdigest()
    with pytest.raises(StoreError, match="collide"):  # True and "true" have the same JSON key
        canonical_json({"k": {True: 1, "true": 2}})


def test_published_table_survives_a_failed_rename(tmp_path, monkeypatch):
    """collect(save_to=...) when the final os.replace fails: StoreError, the published table's bytes unchanged and
    still readable, no temporary file left beside it."""
    write_table([_row()], tmp_path / "sweep" / "0" / "results.parquet")
    published = write_table([_row(x=5.0)], tmp_path / "pub" / "table.parquet")
    before = published.read_bytes()

    def failing_replace(src, dst):
        raise OSError("simulated crash at rename")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(StoreError, match="simulated crash"):
        collect(tmp_path / "sweep", save_to=published)
    monkeypatch.undo()
    assert published.read_bytes() == before
    assert read_table(published)["x"].tolist() == [5.0]
    assert sorted(p.name for p in published.parent.iterdir()) == ["table.parquet"]
    np.testing.assert_array_equal(collect(tmp_path / "sweep", save_to=published)["x"].to_numpy(), [1.0])
    assert read_table(published)["x"].tolist() == [1.0]


def test_key_columns_holding_lists_are_a_store_error_everywhere(tmp_path):
    """A results table whose key column holds lists (unhashable, so no key can be compared) is refused with
    StoreError naming the column by ``write_table`` and ``read_table``, and ``collect`` skips such a part with a
    warning as it does any invalid part (it raised a bare TypeError from pandas before)."""
    frame = pd.DataFrame([_row(trajectory=[0, 1]), _row(seed=1, trajectory=[2])])
    with pytest.raises(StoreError, match="trajectory"):
        write_table(frame, tmp_path / "w.parquet")
    assert not (tmp_path / "w.parquet").exists()
    sweep = tmp_path / "sweep"
    (sweep / "0").mkdir(parents=True)
    (sweep / "1").mkdir()
    pq.write_table(pa.Table.from_pandas(frame, preserve_index=False), sweep / "0" / "results.parquet")
    with pytest.raises(StoreError, match="trajectory"):
        read_table(sweep / "0" / "results.parquet")
    write_table(pd.DataFrame([_row(seed=2)]), sweep / "1" / "results.parquet")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = collect(sweep)
    assert out["seed"].tolist() == [2]
    assert any("0" in str(w.message) for w in caught)


@pytest.mark.parametrize("raw", [b'{"config_hash": "h", ', b"\xff\xfe", b"[1, 2]"])
def test_a_manifest_that_is_not_a_json_object_is_a_store_error(tmp_path, raw):
    """A table whose stored run manifest is broken JSON, not UTF-8, or JSON but not an object: ``read_manifest``
    raises StoreError (its docstring's contract; json's own errors escaped before), and ``finished_part`` reads the
    file as not finished (None) instead of crashing the resumed sweep."""
    path = tmp_path / "results.parquet"
    table = pa.Table.from_pandas(pd.DataFrame([_row()]), preserve_index=False)
    table = table.replace_schema_metadata({**table.schema.metadata, MANIFEST_METADATA_KEY: raw})
    pq.write_table(table, path)
    with pytest.raises(StoreError, match="manifest"):
        read_manifest(path)
    assert finished_part(path, MANIFEST) is None
