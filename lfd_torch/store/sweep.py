"""Merge the per-job results tables of a sweep into one table.

A Hydra multirun leaves one ``results.parquet`` per job (``multirun/<date>/<time>/<job>/results.parquet``).
:func:`collect` finds them, skips what is not a finished table, and merges the rest:

* temporary files (names starting with ``.`` or ending with ``.tmp``: atomic writes in progress) are
  ignored silently;
* files that cannot be read (truncated, corrupt, damaged pandas metadata) or are not valid results tables are
  skipped with a :class:`PartialSweepWarning`, so a half-finished sweep can be inspected;
* a part inside a Hydra job folder (one holding ``.hydra/config.yaml``) whose run manifest has another
  ``config_hash`` or ``seed`` than that ``config.yaml`` (rows an earlier sweep into the same folder left there) is
  skipped with a :class:`PartialSweepWarning`; the job counts as unfinished (:func:`unfinished_jobs`). Parts written
  without a run manifest, or in a job folder whose ``config.yaml`` cannot be hashed, are not checked;
* job folders numbered at or beyond the job count of the sweep's ``multirun.yaml`` (left by an earlier, larger sweep
  into the same folder) are ignored, with a :class:`PartialSweepWarning`;
* rows that appear identically in several parts are kept once;
* rows whose key (:data:`~lfd_torch.store.KEY_COLUMNS`) appears in several parts with different values are
  resolved by keeping the **most recent write**: the part with the latest ``lfd_torch.written_at_ns``
  metadata (the file's mtime for tables written by other tools), ties broken by the later path in sorted
  order. A warning says how many keys were resolved this way. This applies to re-runs of one configuration
  (same ``config_hash``); a key written by parts with *different* configurations means a swept setting is
  missing from the key, and raises :class:`~lfd_torch.errors.StoreError` instead of silently dropping a run;
* the result is sorted by the key columns, columns in order: keys, then every other column in order of
  first appearance over the parts in sorted path order. The same files give the same table.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from lfd_torch.errors import StoreError
from lfd_torch.utils import check_path
from lfd_torch.store.atomic import atomic_path, is_temp_file
from lfd_torch.store.manifest import config_hash, same_run
from lfd_torch.store.table import (
    KEY_COLUMNS,
    REQUIRED_COLUMNS,
    WRITTEN_AT_METADATA_KEY,
    _to_arrow,
    _manifest_from_metadata,
    read_manifest,
    _read_rows,
    read_table,
    validate_table,
    written_at_ns,
)

__all__ = ["collect", "expected_jobs", "find_parts", "finished_part", "job_config", "jobs_beyond_count", "sweep_files",
           "unfinished_jobs", "PartialSweepWarning", "main"]

_SUFFIXES = (".parquet", ".csv")
_ORDER_COLUMNS = ("__written_at_ns", "__part")


class PartialSweepWarning(UserWarning):
    """A sweep part was skipped (unreadable or not a results table) or rows were resolved by recency."""


def find_parts(root: str | os.PathLike[str], pattern: str = "**/*.parquet") -> list[Path]:
    """Result files of a sweep, in sorted order, temporary files excluded.

    Args:
        root: a sweep directory, or one table file (returned alone).
        pattern: glob pattern relative to ``root``.

    Raises:
        StoreError: ``root`` does not exist, or ``pattern`` is not a non-empty relative glob.
    """
    root = check_path(root, "path_or_dir", error=StoreError)
    check_pattern(pattern)
    if root.is_file():
        return [root]
    if not root.is_dir():
        raise StoreError(f"no such file or directory: {root}")
    parts = []
    for path in root.glob(pattern):
        relative = path.relative_to(root)
        if not path.is_file() or any(is_temp_file(part) for part in relative.parts):
            continue
        parts.append(path)
    return sorted(parts)


def check_pattern(pattern: object) -> str:
    """``pattern`` if it is a glob that :meth:`pathlib.Path.glob` accepts: a non-empty relative pattern.

    Raises:
        StoreError: naming ``pattern`` and what is wrong.
    """
    if not isinstance(pattern, str) or not pattern.strip():
        raise StoreError(f"pattern must be a non-empty glob relative to the sweep folder (e.g. '**/*.parquet'), got "
                         f"{pattern!r}")  # fmt: skip
    if os.path.isabs(pattern) or Path(pattern).anchor:
        raise StoreError(f"pattern must be relative to the sweep folder (e.g. '**/*.parquet'), got the absolute "
                         f"{pattern!r}")  # fmt: skip
    return pattern


def _output_paths(save_to: object) -> list[Path]:
    """The ``save_to`` files of :func:`collect`, checked before anything is read or written: file paths with a
    supported suffix, whose folder exists (or can be created) and is writable."""
    if save_to is None:
        return []
    if isinstance(save_to, (str, os.PathLike)):
        items: list[object] = [save_to]
    elif isinstance(save_to, Iterable) and not isinstance(save_to, bytes):
        items = list(save_to)
    else:
        raise StoreError(f"save_to must be a file path or a sequence of file paths, got {save_to!r} "
                         f"({type(save_to).__name__})")  # fmt: skip
    outputs = [check_path(p, "save_to", error=StoreError) for p in items]
    bad = [p for p in outputs if p.suffix.lower() not in _SUFFIXES]
    if bad:
        raise StoreError(f"cannot save to {[str(p) for p in bad]}: supported suffixes are {list(_SUFFIXES)}")
    for path in outputs:
        if path.is_dir():
            raise StoreError(f"cannot save to {path}: it is a directory")
        folder = path.parent
        while not folder.exists() and folder != folder.parent:  # the nearest folder that exists
            folder = folder.parent
        if not folder.is_dir():
            raise StoreError(f"cannot save to {path}: {folder} is a file, not a folder")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise StoreError(f"cannot save to {path}: no permission to write in {folder}")
    return outputs


def _job_folder(part: Path, root: Path) -> Path | None:
    """The Hydra job folder (holding ``.hydra/config.yaml``) that ``part`` lies in: the nearest one from the part's
    folder up to ``root``; None outside any."""
    for folder in part.parents:
        if (folder / ".hydra" / "config.yaml").is_file():
            return folder
        if folder == root or folder == folder.parent:
            return None
    return None


def job_config(job: str | os.PathLike[str]) -> tuple[str, int | None] | None:
    """``(config_hash, seed)`` of a Hydra job folder, from its ``.hydra/config.yaml``: what
    :func:`~lfd_torch.store.prepare_job` puts in the run manifest of the job's rows (:func:`config_hash` of the job's
    configuration; seed None when the file has no integer seed). None when the file cannot be read or hashed (e.g.
    an interpolation that resolves only inside Hydra): the job's configuration is then unknown."""
    try:
        from omegaconf import DictConfig, OmegaConf

        cfg = OmegaConf.load(Path(job) / ".hydra" / "config.yaml")
        if not isinstance(cfg, DictConfig):
            return None
        seed = cfg.get("seed")
        return config_hash(cfg), (seed if isinstance(seed, int) and not isinstance(seed, bool) else None)
    except Exception:  # noqa: BLE001 - an unreadable or unresolvable config: the job's configuration is unknown
        return None


def _load_part(path: Path, job: Path | None, configs: dict[Path, Any]) -> tuple[pd.DataFrame | None, str]:
    """The rows of a part with the order columns, or None and why it is not a finished part of its job: it cannot
    be read, is not a results table, or (in a Hydra job folder ``job``) its run manifest has another config_hash or
    seed than the job's ``.hydra/config.yaml``. ``configs`` caches :func:`job_config` per job folder."""
    try:
        frame, metadata = _read_rows(path)
        validate_table(frame, where=str(path))
        written = written_at_ns(path, metadata)
        if job is not None:
            if job not in configs:
                configs[job] = job_config(job)
            expected = configs[job]
            manifest = _manifest_from_metadata(metadata, path) if expected is not None else None
            if manifest is not None:
                want_hash, want_seed = expected
                keys = ("config_hash",) if want_seed is None else ("config_hash", "seed")  # None: no integer seed
                if not same_run(manifest, {"config_hash": want_hash, "seed": want_seed}, keys):
                    got_hash, got_seed = manifest.get("config_hash"), manifest.get("seed")
                    return None, (f"its rows come from another configuration (config_hash {got_hash!r}, seed "
                                  f"{got_seed!r}) than its job's {job / '.hydra' / 'config.yaml'} (config_hash "
                                  f"{want_hash!r}, seed {want_seed!r}): left there by an earlier sweep into the same "
                                  "folder; re-run the sweep")  # fmt: skip
    except (OSError, StoreError) as exc:
        return None, str(exc)
    frame["__written_at_ns"] = written
    frame["__part"] = str(path)
    return frame, ""


def _read_part(path: Path, job: Path | None, configs: dict[Path, Any]) -> pd.DataFrame | None:
    frame, problem = _load_part(path, job, configs)
    if frame is None:
        warnings.warn(f"skipping sweep part {path}: {problem}", PartialSweepWarning, stacklevel=3)
    return frame


def _save_all(frame: pd.DataFrame, paths: Sequence[Path]) -> None:
    """Write ``frame`` to every file of ``paths`` (.parquet or .csv), all or none: each goes to a temporary file
    first, and the files are renamed into place only once every one of them is complete. A failure leaves every
    destination as it was.

    Raises:
        StoreError: naming the file that could not be written.
    """
    import time

    table = None
    if any(p.suffix.lower() == ".parquet" for p in paths):
        validate_table(frame, where=str(paths[0]))
        table = _to_arrow(frame, {WRITTEN_AT_METADATA_KEY: str(time.time_ns()).encode()}, str(paths[0]))
    with contextlib.ExitStack() as stack:  # renames on a clean exit, in reverse order; removes every temp on error
        for path in paths:
            try:
                tmp = stack.enter_context(atomic_path(path))
                if path.suffix.lower() == ".parquet":
                    pq.write_table(table, tmp)
                elif path.suffix.lower() == ".csv":
                    frame.to_csv(tmp, index=False)
                else:
                    raise StoreError(f"cannot save to {path}: supported suffixes are {list(_SUFFIXES)}")
            except (OSError, pa.ArrowException) as exc:
                raise StoreError(f"cannot write {path}: {exc}") from exc


def sweep_files(root: str | os.PathLike[str]) -> list[Path]:
    """The ``multirun.yaml`` files under ``root``: one per Hydra sweep (a folder that holds several sweeps, e.g.
    ``multirun/lasa_benchmark`` with one timestamped sweep per run, has several)."""
    if isinstance(root, bytes) or not isinstance(root, (str, os.PathLike)):
        return []
    base = Path(root)
    return sorted(base.glob("**/multirun.yaml")) if base.is_dir() else []


def expected_jobs(sweep_file: str | os.PathLike[str]) -> int | None:
    """The number of jobs a Hydra sweep launches, from its ``multirun.yaml``: the product of the numbers of
    values of its sweep overrides (command line, and ``hydra.sweeper.params`` where the command line does not set
    the key), as Hydra's basic sweeper expands them. None when that cannot be read: another sweeper, or job
    folders not named by their number (``hydra.sweep.subdir`` other than ``${hydra.job.num}``)."""
    try:
        import yaml
        from hydra.core.override_parser.overrides_parser import OverridesParser

        cfg = yaml.safe_load(Path(sweep_file).read_text())
        hydra = cfg["hydra"]
        if not str(hydra["sweeper"]["_target_"]).endswith("BasicSweeper") or \
                str(hydra["sweep"]["subdir"]) != "${hydra.job.num}":
            return None
        task = [str(o) for o in hydra["overrides"]["task"]]
        keys = {o.split("=", 1)[0].lstrip("+~") for o in task}
        params = hydra["sweeper"].get("params") or {}
        task += [f"{k}={v}" for k, v in params.items() if k not in keys]
        n = 1
        for override in OverridesParser.create().parse_overrides(task):
            if override.is_sweep_override():
                n *= len(list(override.sweep_string_iterator()))
        return n
    except Exception:  # noqa: BLE001 - an unreadable or unusual sweep file: the count is unknown, not an error
        return None


def jobs_beyond_count(root: str | os.PathLike[str]) -> dict[Path, tuple[Path, int]]:
    """Job folders (holding ``.hydra/``) numbered at or beyond the job count of their sweep's ``multirun.yaml``
    (:func:`expected_jobs`): left by an earlier, larger sweep into the same ``hydra.sweep.dir``, not jobs of this one.
    Maps each to its ``multirun.yaml`` and that sweep's job count."""
    beyond: dict[Path, tuple[Path, int]] = {}
    for sweep in sweep_files(root):
        n = expected_jobs(sweep)
        if n is None:
            continue
        for folder in sweep.parent.iterdir():
            name = folder.name
            if name.isdecimal() and name == str(int(name)) and int(name) >= n and (folder / ".hydra").is_dir():
                beyond[folder] = (sweep, n)
    return dict(sorted(beyond.items()))


def _beyond(path: Path, beyond: Mapping[Path, Any]) -> Path | None:
    return next((folder for folder in path.parents if folder in beyond), None)


def unfinished_jobs(root: str | os.PathLike[str], pattern: str = "**/*.parquet") -> list[Path]:
    """Jobs of a Hydra sweep without a finished results table: job folders (holding ``.hydra/``) in which none was
    written (killed, failed, or still running), or whose only parts cannot be read, are not valid results tables, or
    come from another configuration than the job's ``.hydra/config.yaml`` (an earlier sweep into the same folder; the
    rules of :func:`collect`), and, when the sweep's ``multirun.yaml`` tells how many jobs it launches and its job
    folders are numbered (``hydra.sweep.subdir: ${hydra.job.num}``), the folders of jobs that never started
    (:func:`expected_jobs`). Job folders beyond that count (:func:`jobs_beyond_count`) are not jobs of the sweep."""
    base = Path(root)
    beyond = jobs_beyond_count(base)
    jobs = sorted({p.parent.parent for p in base.glob("**/.hydra/config.yaml")} - set(beyond))
    done: set[Path] = set()
    configs: dict[Path, Any] = {}
    for part in find_parts(base, pattern) if jobs else []:
        job = _job_folder(part, base)
        if job is not None and job not in done and _load_part(part, job, configs)[0] is not None:
            done.add(job)
    missing = [j for j in jobs if j not in done]
    for sweep in sweep_files(base):
        n = expected_jobs(sweep)
        if n is not None:
            missing += [sweep.parent / str(k) for k in range(n) if not (sweep.parent / str(k)).is_dir()]
    return sorted(set(missing))


def finished_part(path: str | os.PathLike[str], manifest: Mapping[str, Any]) -> pd.DataFrame | None:
    """The rows of a job that already ran with the same configuration, for resuming a sweep; else None.

    Raises:
        StoreError: ``path`` is not a file path or ``manifest`` is not a mapping (arguments, not the file's state).

    A job's part counts as finished when ``path`` is a valid results table (it is written atomically, as the
    job's last act) whose manifest has the same ``config_hash``, ``seed`` and ``git_sha`` as ``manifest`` (from
    :func:`~lfd_torch.store.run_manifest` of the job about to run). A missing, damaged or foreign file, or one from
    another configuration or commit, is not finished: the job runs and replaces it (a sweep resumed after a code
    change does not mix two versions of the code; a ``-dirty`` tree edited in between is not told apart).
    """
    p = check_path(path, "path", error=StoreError)
    if not isinstance(manifest, Mapping):
        raise StoreError(f"manifest must be a mapping from run_manifest(cfg, seed), got {type(manifest).__name__}")
    if not p.is_file():
        return None
    try:
        old = read_manifest(p)
        frame = read_table(p)
    except StoreError:
        return None
    if not same_run(old, manifest, ("config_hash", "seed", "git_sha")):
        return None
    return frame


def collect(
    path_or_dir: str | os.PathLike[str],
    pattern: str = "**/*.parquet",
    *,
    save_to: str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | None = None,
) -> pd.DataFrame:
    """Merge a sweep's per-job results tables into one (rules in the module docstring).

    Args:
        path_or_dir: the sweep directory (e.g. ``multirun/2024-05-21/10-00-00``), or a single table file.
        pattern: glob pattern of the parts, relative to the directory.
        save_to: optional file(s) to write the merged table to, atomically: ``.parquet`` and/or ``.csv``.
            A ``save_to`` file inside the sweep directory is never read back as a part.

    Returns:
        The merged table (default index). Empty, with the required columns, when no part is readable.
        Skipped parts (unreadable, invalid, of another configuration than their job) do not stop a ``save_to``:
        refuse a partial sweep first with :func:`unfinished_jobs`, as the command line does.

    Raises:
        StoreError: the directory does not exist, ``pattern`` is not a relative glob, or ``save_to`` is not a file
            path (or a sequence of them), has an unsupported suffix or cannot be written (checked for every file
            before anything is written; the files are then written all or none); with ``save_to``, also when no
            part is readable (a published table is never replaced by an
            empty one) or the directory holds several sweeps (several ``multirun.yaml``).

    Warns:
        PartialSweepWarning: for each part skipped, and once if rows were resolved by recency.
    """
    outputs = _output_paths(save_to)
    check_pattern(pattern)
    exclude = {p.resolve() for p in outputs}
    parts = [p for p in find_parts(path_or_dir, pattern) if p.resolve() not in exclude]  # checks path_or_dir
    sweeps = sweep_files(path_or_dir)
    if outputs and len(sweeps) > 1:  # e.g. multirun/lasa_benchmark, one timestamped sweep per run
        raise StoreError(f"{path_or_dir} holds {len(sweeps)} sweeps ({', '.join(str(p.parent) for p in sweeps[:3])}"
                         f"{' ...' if len(sweeps) > 3 else ''}); collect one sweep folder (hydra.sweep.dir)")
    if not parts:
        warnings.warn(f"no results tables match {pattern!r} under {path_or_dir}", PartialSweepWarning, stacklevel=2)
    beyond = jobs_beyond_count(path_or_dir)
    for folder in sorted({f for f in (_beyond(p, beyond) for p in parts) if f is not None}):
        sweep, n = beyond[folder]
        warnings.warn(f"ignoring {folder}: {sweep} launches {n} job(s) (0..{n - 1}), so this folder is left by an "
                      "earlier sweep into the same folder", PartialSweepWarning, stacklevel=2)  # fmt: skip
    parts = [p for p in parts if _beyond(p, beyond) is None]
    root = Path(path_or_dir)
    root = root.parent if root.is_file() else root
    configs: dict[Path, Any] = {}
    frames = [frame for frame in (_read_part(p, _job_folder(p, root), configs) for p in parts) if frame is not None]
    if outputs and not frames:  # a published table is never replaced by an empty one
        raise StoreError(f"no readable results table under {path_or_dir}: nothing written to "
                         f"{', '.join(str(p) for p in outputs)}")

    if frames:
        merged = pd.concat(frames, ignore_index=True, sort=False)
    else:
        merged = pd.DataFrame({c: pd.Series(dtype=object) for c in (*REQUIRED_COLUMNS, *_ORDER_COLUMNS)})
    data_columns = [c for c in merged.columns if c not in _ORDER_COLUMNS]
    columns = list(KEY_COLUMNS) + [c for c in data_columns if c not in KEY_COLUMNS]

    # Oldest first, so that "keep the last" keeps the most recent write.
    merged = merged.sort_values(list(_ORDER_COLUMNS), kind="mergesort")
    try:
        merged = merged.drop_duplicates(subset=data_columns, keep="last")
    except TypeError as exc:  # unhashable cells, e.g. arrays stored in a column
        raise StoreError(f"cannot merge tables with non-scalar cells: {exc}") from exc
    conflicts = merged.duplicated(subset=list(KEY_COLUMNS), keep="last")
    if conflicts.any() and "config_hash" in merged.columns:
        clashing = merged[merged.duplicated(subset=list(KEY_COLUMNS), keep=False)]
        n_configs = clashing.groupby(list(KEY_COLUMNS), dropna=False)["config_hash"].nunique()
        if (n_configs > 1).any():
            example = n_configs[n_configs > 1].index[0]
            raise StoreError(
                f"{int((n_configs > 1).sum())} key(s) come from parts with different configurations (config_hash), "
                f"e.g. {dict(zip(KEY_COLUMNS, example))}: a swept setting is missing from the key; put it in "
                "the method name (or another key column) so the runs stay distinct"
            )
    if conflicts.any():
        n_keys = merged.loc[conflicts, list(KEY_COLUMNS)].drop_duplicates().shape[0]
        warnings.warn(
            f"{n_keys} key(s) appear with different values in several parts; kept the most recent write",
            PartialSweepWarning,
            stacklevel=2,
        )
        merged = merged.loc[~conflicts]
    for column in KEY_COLUMNS:  # e.g. trajectory stored as int by one job and as str by another
        if merged[column].dtype == object and merged[column].map(type).nunique() > 1:
            kinds = sorted({type(v).__name__ for v in merged[column]})
            raise StoreError(f"key column {column!r} mixes types across parts: {kinds}")
    merged = merged.sort_values(list(KEY_COLUMNS), kind="mergesort")[columns].reset_index(drop=True)

    if outputs:
        _save_all(merged, outputs)
    return merged


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``python -m lfd_torch.store.collect SWEEP_DIR [--pattern GLOB] [--out FILE ...] [--force]``.

    Without ``--out`` the merged table is printed to stdout as CSV. Skipped parts are reported on stderr. With
    ``--out``, a sweep in which some job folder holds no results (killed, failed, still running) is refused unless
    ``--force``: a partial sweep never overwrites a published table.

    Returns:
        The exit status (0 on success, 2 on a StoreError). Invalid arguments (an empty or absolute ``--pattern``, an
        ``--out`` with another suffix than .parquet/.csv) are usage errors: argparse prints them and exits with 2.
    """
    import argparse
    import sys

    parser = argparse.ArgumentParser(
        prog="python -m lfd_torch.store.collect",
        description="Merge the per-job results tables of a sweep into one table.",
    )
    parser.add_argument("path", help="sweep directory (or one table file)")
    parser.add_argument("--pattern", default="**/*.parquet", help="glob of the parts (default: %(default)s)")
    parser.add_argument(
        "--out", action="append", default=None, help="output .parquet or .csv file (repeatable)"
    )
    parser.add_argument("--force", action="store_true", help="write --out even if some jobs of the sweep have no rows")
    args = parser.parse_args(argv)
    try:
        check_pattern(args.pattern)
    except StoreError as exc:
        parser.error(f"--pattern: {exc}")
    bad = [o for o in args.out or [] if Path(o).suffix.lower() not in _SUFFIXES]
    if bad:
        parser.error(f"--out: {', '.join(bad)}: supported suffixes are {', '.join(_SUFFIXES)}")
    if args.out and not args.force and Path(args.path).is_dir():
        missing = unfinished_jobs(args.path, args.pattern)
        if missing:  # a partial sweep must not overwrite a published table
            names = ", ".join(str(m) for m in missing[:5]) + (" ..." if len(missing) > 5 else "")
            print(f"error: {len(missing)} job(s) of the sweep have no finished results (none, unreadable, or of "
                  f"another configuration: {names}); re-run the sweep with the same hydra.sweep.dir (finished jobs "
                  "are skipped) or pass --force", file=sys.stderr)  # fmt: skip
            return 2
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", PartialSweepWarning)
            merged = collect(args.path, args.pattern, save_to=args.out)
    except StoreError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for warning in caught:
        print(f"warning: {warning.message}", file=sys.stderr)
    if args.out:
        print(f"{len(merged)} rows -> {', '.join(args.out)}", file=sys.stderr)
    else:
        merged.to_csv(sys.stdout, index=False)
    return 0
