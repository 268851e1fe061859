"""Results tables: one row per (experiment, shape, method, fold, seed, trajectory), metric columns beside.

Every row also carries its provenance (``config_hash``, ``seed``, ``package_version``, ``git_sha``; see
:func:`lfd_torch.store.run_manifest`). Tables are Parquet files written atomically (pyarrow); the file's
schema metadata keeps the full run manifest (key ``lfd_torch.manifest``) and the write time in nanoseconds
since the epoch (key ``lfd_torch.written_at_ns``), which :func:`lfd_torch.store.collect` uses to resolve rows
written twice.

Columns:
    experiment (str), shape (str), method (str), fold (int), seed (int), trajectory (int or str)
        -- :data:`KEY_COLUMNS`; no nulls, unique together.
    config_hash, package_version, git_sha (str) -- provenance; no nulls.
    anything else -- metrics (float, in the data's units, e.g. mm) and labels (e.g. ``split``: train/test).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from lfd_torch.errors import StoreError
from lfd_torch.utils import check_path
from lfd_torch.store.atomic import atomic_path

__all__ = [
    "KEY_COLUMNS",
    "PROVENANCE_COLUMNS",
    "REQUIRED_COLUMNS",
    "as_frame",
    "validate_table",
    "write_table",
    "read_table",
    "read_manifest",
]

#: Columns that identify a row; unique together in a valid table.
KEY_COLUMNS: tuple[str, ...] = ("experiment", "shape", "method", "fold", "seed", "trajectory")
#: Columns every row carries to say what produced it (``seed`` is also a key).
PROVENANCE_COLUMNS: tuple[str, ...] = ("config_hash", "seed", "package_version", "git_sha")
#: Key columns followed by the provenance columns that are not keys.
REQUIRED_COLUMNS: tuple[str, ...] = KEY_COLUMNS + tuple(c for c in PROVENANCE_COLUMNS if c not in KEY_COLUMNS)

MANIFEST_METADATA_KEY = b"lfd_torch.manifest"
WRITTEN_AT_METADATA_KEY = b"lfd_torch.written_at_ns"

# What pyarrow and pandas raise on a damaged file: a truncated or corrupt Parquet file (OSError, ArrowException),
# or damaged ``pandas`` schema metadata, which ``Table.to_pandas`` parses (broken JSON or bytes that are not UTF-8:
# ValueError; a missing field: KeyError; an unknown dtype name or a field of the wrong kind: TypeError,
# AttributeError, IndexError).
_READ_ERRORS: tuple[type[BaseException], ...] = (
    OSError, pa.ArrowException, ValueError, KeyError, IndexError, TypeError, AttributeError,
)


def as_frame(rows: pd.DataFrame | Sequence[Mapping[str, Any]]) -> pd.DataFrame:
    """Rows as a DataFrame with a default index (a copy; the input is never modified).

    A DataFrame's named index levels become columns (e.g. after ``groupby``); an unnamed index is dropped.

    Args:
        rows: a DataFrame, or a sequence of row dicts (column name -> value).

    Raises:
        StoreError: ``rows`` is neither.
    """
    if isinstance(rows, pd.DataFrame):
        frame = rows.copy()
        if any(name is not None for name in frame.index.names):
            frame = frame.reset_index()
        return frame.reset_index(drop=True)
    if isinstance(rows, Sequence) and not isinstance(rows, (str, bytes)):
        if not all(isinstance(row, Mapping) for row in rows):
            raise StoreError("rows must be a DataFrame or a sequence of mappings (one dict per row)")
        return pd.DataFrame.from_records([dict(row) for row in rows])
    raise StoreError(f"rows must be a DataFrame or a sequence of mappings, not {type(rows).__name__}")


def validate_table(frame: pd.DataFrame, *, where: str = "table") -> None:
    """Check that a results table has the required columns, no null keys and no duplicated keys.

    Args:
        frame: the table.
        where: name used in error messages (e.g. a file path).

    Raises:
        StoreError: ``frame`` is not a DataFrame, or naming the missing columns, the columns holding nulls, or a few
            duplicated keys.
    """
    if not isinstance(frame, pd.DataFrame):
        raise StoreError(f"{where}: a results table must be a pandas DataFrame, got {type(frame).__name__} (build "
                         "one from row dicts with as_frame)")  # fmt: skip
    missing = [c for c in REQUIRED_COLUMNS if c not in frame.columns]
    if missing:
        raise StoreError(f"{where}: missing required column(s) {missing}; required: {list(REQUIRED_COLUMNS)}")
    if frame.columns.duplicated().any():
        dup = sorted(set(frame.columns[frame.columns.duplicated()]))
        raise StoreError(f"{where}: duplicated column name(s) {dup}")
    with_nulls = [c for c in REQUIRED_COLUMNS if frame[c].isna().any()]
    if with_nulls:
        raise StoreError(f"{where}: null values in required column(s) {with_nulls}")
    try:
        duplicated = frame.duplicated(subset=list(KEY_COLUMNS), keep=False)
    except TypeError as exc:  # a key cell that is not a scalar (a list, an array) cannot be compared
        bad = [c for c in KEY_COLUMNS if not frame[c].map(pd.api.types.is_scalar).all()]
        raise StoreError(f"{where}: key column(s) {bad} hold values that are not scalars ({exc})") from exc
    if duplicated.any():
        examples = frame.loc[duplicated, list(KEY_COLUMNS)].drop_duplicates().head(3).to_dict("records")
        raise StoreError(
            f"{where}: {int(duplicated.sum())} rows share their key {list(KEY_COLUMNS)}, e.g. {examples}"
        )


def _apply_manifest(frame: pd.DataFrame, manifest: Mapping[str, Any]) -> pd.DataFrame:
    missing = [c for c in PROVENANCE_COLUMNS if c not in manifest]
    if missing:
        raise StoreError(f"manifest lacks field(s) {missing}; build it with run_manifest(cfg, seed)")
    for column in PROVENANCE_COLUMNS:
        value = manifest[column]
        if column not in frame.columns:
            frame[column] = value
        elif len(frame) and not (frame[column] == value).all():
            seen = sorted({str(v) for v in frame[column].unique()})[:3]
            raise StoreError(f"column {column!r} holds {seen} but the manifest says {value!r}")
    return frame


def _to_arrow(frame: pd.DataFrame, metadata: Mapping[bytes, bytes], where: str) -> pa.Table:
    try:
        table = pa.Table.from_pandas(frame, preserve_index=False)
    except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError) as exc:
        raise StoreError(f"{where}: a column cannot be stored in Parquet: {exc}") from exc
    return table.replace_schema_metadata({**(table.schema.metadata or {}), **metadata})


def write_parquet_atomic(
    frame: pd.DataFrame, path: str | os.PathLike[str], metadata: Mapping[bytes, bytes] | None = None
) -> Path:
    """Write a validated results table to Parquet atomically (temp file, fsync, rename).

    Args:
        frame: a table that passes :func:`validate_table`.
        path: destination file.
        metadata: extra schema metadata; the write time is added under ``lfd_torch.written_at_ns``.

    Returns:
        The destination path.

    Raises:
        StoreError: invalid table, a column pyarrow cannot store, or an I/O failure. The destination then
            keeps its previous content.
    """
    path = Path(path)
    validate_table(frame, where=str(path))
    meta = dict(metadata or {})
    meta[WRITTEN_AT_METADATA_KEY] = str(time.time_ns()).encode()
    table = _to_arrow(frame, meta, str(path))
    try:
        with atomic_path(path) as tmp:
            pq.write_table(table, tmp)
    except (OSError, pa.ArrowException) as exc:
        raise StoreError(f"cannot write {path}: {exc}") from exc
    return path


def write_table(
    rows: pd.DataFrame | Sequence[Mapping[str, Any]],
    path: str | os.PathLike[str],
    manifest: Mapping[str, Any] | None = None,
) -> Path:
    """Write result rows to a Parquet file, atomically.

    Args:
        rows: a DataFrame or a list of row dicts, one row per (experiment, shape, method, fold, seed,
            trajectory) with metric columns beside (see the module docstring).
        path: destination ``.parquet`` file (another extension is refused: the file is always Parquet),
            conventionally ``results.parquet`` in the job's output directory. Missing parent directories are
            created; an existing file is replaced only once the new one is complete.
        manifest: the run's :func:`run_manifest`. Provenance columns the rows lack are filled from it; the
            ones they have must agree with it. The whole manifest is also kept in the file's metadata.
            Without a manifest the rows must already carry the provenance columns.

    Returns:
        The destination path.

    Raises:
        StoreError: ``path`` not a ``.parquet`` file path, missing required columns, null or duplicated keys, a
            disagreement with the manifest, a column that Parquet cannot hold, or an I/O failure (the destination is
            then left unchanged).
    """
    path = check_path(path, "path", error=StoreError)
    if path.suffix.lower() != ".parquet":
        raise StoreError(f"path {str(path)!r} must end in .parquet: write_table writes Parquet (for a CSV copy use "
                         "collect(..., save_to='....csv') or DataFrame.to_csv)")  # fmt: skip
    frame = as_frame(rows)
    metadata: dict[bytes, bytes] = {}
    if manifest is not None and not isinstance(manifest, Mapping):
        raise StoreError(f"manifest must be a mapping from run_manifest(cfg, seed), got {type(manifest).__name__}")
    if manifest is not None:
        frame = _apply_manifest(frame, manifest)
        try:
            metadata[MANIFEST_METADATA_KEY] = json.dumps(dict(manifest), sort_keys=True).encode()
        except (TypeError, ValueError) as exc:
            raise StoreError(f"manifest is not JSON-serialisable: {exc}") from exc
    return write_parquet_atomic(frame, path, metadata)


def read_table(path: str | os.PathLike[str], *, validate: bool = True) -> pd.DataFrame:
    """Read a results table written by :func:`write_table`.

    Args:
        path: a Parquet file.
        validate: check the table with :func:`validate_table`.

    Returns:
        The rows, in the order they were written, with a default index.

    Raises:
        StoreError: the file is missing or unreadable (damaged Parquet data or pandas metadata included), or (with
            ``validate``) not a valid results table.
    """
    path = check_path(path, "path", error=StoreError)
    frame, _ = _read_rows(path)
    if validate:
        validate_table(frame, where=str(path))
    return frame


def _read_rows(path: Path) -> tuple[pd.DataFrame, dict[bytes, bytes]]:
    """The rows of a Parquet file (not validated) and its schema metadata.

    Raises:
        StoreError: naming the file, when it is missing or damaged (the file itself, or the
            ``pandas`` metadata that :meth:`pyarrow.Table.to_pandas` reads).
    """
    try:
        table = pq.read_table(path)
        return table.to_pandas(), dict(table.schema.metadata or {})
    except _READ_ERRORS as exc:
        raise StoreError(f"cannot read results table {path}: {type(exc).__name__}: {exc}") from exc


def _schema_metadata(path: str | os.PathLike[str]) -> dict[bytes, bytes]:
    try:
        return dict(pq.read_schema(path).metadata or {})
    except _READ_ERRORS as exc:
        raise StoreError(f"cannot read the schema of {path}: {exc}") from exc


def read_manifest(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The run manifest stored with a results table, or None if it was written without one.

    Raises:
        StoreError: ``path`` is not a file path, the file is missing or unreadable, or its manifest is not a JSON
            object.
    """
    path = check_path(path, "path", error=StoreError)
    return _manifest_from_metadata(_schema_metadata(path), path)


def _manifest_from_metadata(metadata: Mapping[bytes, bytes], path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The run manifest in a table's schema ``metadata`` (see :func:`read_manifest`; ``path`` names the file in
    errors), or None if it was written without one.

    Raises:
        StoreError: the manifest is not a JSON object.
    """
    raw = metadata.get(MANIFEST_METADATA_KEY)
    if raw is None:
        return None
    try:
        manifest = json.loads(raw)
    except ValueError as exc:  # JSONDecodeError and UnicodeDecodeError both derive from it
        raise StoreError(f"{os.fspath(path)}: its run manifest is not valid JSON ({exc})") from exc
    if not isinstance(manifest, dict):
        raise StoreError(f"{os.fspath(path)}: its run manifest is a {type(manifest).__name__}, not a JSON object")
    return manifest


def written_at_ns(path: str | os.PathLike[str], metadata: Mapping[bytes, bytes] | None = None) -> int:
    """When a table was written: its ``lfd_torch.written_at_ns`` metadata, else the file's mtime (ns)."""
    meta = _schema_metadata(path) if metadata is None else metadata
    raw = meta.get(WRITTEN_AT_METADATA_KEY)
    if raw is not None:
        try:
            return int(raw)
        except ValueError:
            pass
    return os.stat(path).st_mtime_ns
