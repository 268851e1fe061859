"""Atomic file writes: a reader sees the old file or the complete new one, never a half-written file.

The new content goes to a temporary file in the destination's directory (same file system, so the final
rename is atomic), named ``.{name}.{pid}.{uuid}.tmp`` so that concurrent writers never collide and sweep
collectors can recognise and skip it. Once the writer returns, the temporary file is flushed to disk
(``fsync``) and renamed over the destination with :func:`os.replace`; the directory entry is then fsynced
too. If the writer raises (or the process is interrupted with an exception), the temporary file is removed
and the destination is left untouched. A process killed mid-write leaves its temporary file; the next atomic write
to the same destination removes it (:func:`remove_stale_temps`: files whose writer process no longer exists).

A writer must not infer the file format from the temporary file's suffix (it ends in ``.tmp``): pass the
format explicitly (``savefig(..., format="png")``).
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

from lfd_torch.errors import InvalidArgumentError, StoreError
from lfd_torch.utils import check_path

__all__ = ["atomic_path", "atomic_save", "atomic_write", "is_temp_file", "remove_stale_temps", "TEMP_SUFFIX"]

TEMP_SUFFIX = ".tmp"


def _temp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex}{TEMP_SUFFIX}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def remove_stale_temps(path: str | os.PathLike[str]) -> list[Path]:
    """Delete temporary files that interrupted atomic writes of ``path`` left behind (their process is gone).

    A killed writer cannot clean up after itself; the next save to the same place does. Temporary files of live
    processes (a concurrent writer) are kept. Returns the files removed.
    """
    final = Path(path)
    removed = []
    prefix = f".{final.name}."
    try:
        candidates = list(final.parent.glob(f".{glob_escape(final.name)}.*{TEMP_SUFFIX}"))
    except OSError:
        return removed
    for tmp in candidates:
        middle = tmp.name[len(prefix) : -len(TEMP_SUFFIX)]
        pid_text = middle.split(".", 1)[0]
        if not pid_text.isdigit():
            continue
        pid = int(pid_text)
        if pid == os.getpid() or _pid_alive(pid):
            continue
        with contextlib.suppress(OSError):
            tmp.unlink()
            removed.append(tmp)
    return removed


def glob_escape(name: str) -> str:
    """``name`` with glob metacharacters escaped."""
    import glob

    return glob.escape(name)


def is_temp_file(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` looks like an in-progress atomic write (or any hidden/temporary file).

    Args:
        path: a file path.

    Returns:
        True for names that start with ``.`` or end with ``.tmp``.
    """
    name = Path(path).name
    return name.startswith(".") or name.endswith(TEMP_SUFFIX)


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as handle:
        os.fsync(handle.fileno())


def _fsync_dir(directory: Path) -> None:
    # Persists the rename. Not possible on every platform (Windows cannot open a directory): best effort.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], *, fsync: bool = True) -> Iterator[Path]:
    """Context manager yielding a temporary path that replaces ``path`` atomically on a clean exit.

    Example::

        with atomic_path("results/model.pt") as tmp:
            torch.save(state, tmp)

    Args:
        path: destination file. Missing parent directories are created.
        fsync: flush the file and its directory entry to disk before and after the rename.

    Yields:
        The temporary path, in the destination's directory. The body must create it.

    Raises:
        StoreError: ``path`` is not a file path, its folder cannot be created, the body returned without creating
            the temporary file, or the rename failed. Any exception raised by the body propagates unchanged; in every
            error case the temporary file is removed and the destination keeps its previous content (or stays absent).
    """
    final = check_path(path, "path", error=StoreError)
    if final.name in ("", ".", ".."):
        raise StoreError(f"not a file path: {str(path)!r}")
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StoreError(f"cannot create directory {final.parent}: {exc}") from exc
    remove_stale_temps(final)
    tmp = _temp_name(final)
    try:
        yield tmp
        if not tmp.is_file():
            raise StoreError(f"atomic write of {final}: the writer did not create {tmp.name}")
        if fsync:
            _fsync_file(tmp)
        try:
            os.replace(tmp, final)
        except OSError as exc:
            raise StoreError(f"cannot move {tmp} to {final}: {exc}") from exc
        if fsync:
            _fsync_dir(final.parent)
    finally:
        # Present only when the body or the rename failed.
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def atomic_write(
    path: str | os.PathLike[str], writer: Callable[[Path], object], *, fsync: bool = True
) -> Path:
    """Write a file atomically through ``writer(tmp_path)``; see :func:`atomic_path`.

    Args:
        path: destination file. Missing parent directories are created.
        writer: called once with the temporary path; it must create that file (its return value is ignored).
        fsync: flush to disk before and after the rename.

    Returns:
        The destination path.

    Raises:
        StoreError: ``path`` is not a file path, the writer did not create the file, or the rename failed. Exceptions
            raised by ``writer`` propagate unchanged; the destination is then left as it was.
        InvalidArgumentError: ``writer`` is not callable.
    """
    if not callable(writer):
        raise InvalidArgumentError(f"writer must be a callable writer(tmp_path), got {type(writer).__name__}")
    with atomic_path(path, fsync=fsync) as tmp:
        writer(tmp)
    return Path(path)


def atomic_save(path: str | os.PathLike[str], writer: Callable[[Path], object], *, what: str = "file") -> Path:
    """:func:`atomic_write` for the package's own files: an I/O failure of ``writer`` (an unwritable folder, a full
    disk; ``torch.save`` reports these as RuntimeError) is a StoreError naming the file ``what`` it was to be.

    Raises:
        StoreError: as :func:`atomic_write`, or the writer's OSError / RuntimeError. Other exceptions of ``writer``
            propagate unchanged. In every error case the destination keeps its previous content (or stays absent).
    """
    try:
        return atomic_write(path, writer)
    except StoreError:
        raise
    except (OSError, RuntimeError) as exc:
        raise StoreError(f"cannot write {what} {path}: {type(exc).__name__}: {exc}") from exc
