"""Atomic file writes: a run that fails or is killed never leaves a half-written file.

Every writer in :mod:`railtraj.io` writes to a hidden temporary file in the target's folder and
renames it over the target only once the data is complete and flushed to disk. ``os.replace`` is
atomic on POSIX and Windows when source and target are on the same file system, which is why the
temporary file lives in the same folder. A killed process may leave a hidden ``.*.part`` file
behind, but never a truncated file under the real name.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import IO


def _temp_name(target: Path, suffix: str) -> Path:
    """Create (and close) a unique empty temporary file next to ``target`` and return its path.

    Unlike :func:`tempfile.mkstemp` (mode 0600) the file gets the usual 0666-minus-umask
    permissions, so the renamed result is readable by the same people as any other output.
    """
    target.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = target.parent / f".{target.name}.{secrets.token_hex(4)}{suffix}"
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return tmp
        except FileExistsError:
            continue


def _fsync_dir(folder: Path) -> None:
    """Flush a folder's entry table so the rename survives a power cut (best effort, POSIX only)."""
    with contextlib.suppress(OSError, AttributeError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _fsync_file(path: Path) -> None:
    """Flush a file written by someone else (a library writing by path) to disk."""
    with open(path, "rb+") as f:
        os.fsync(f.fileno())


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", newline: str | None = "",
                 encoding: str | None = "utf-8") -> Iterator[IO]:
    """Open a temporary file next to ``path`` for writing; on success it replaces ``path``.

    ``mode`` is ``"w"`` (text, UTF-8, ``newline`` as for :func:`open`) or ``"wb"`` (binary). The
    temporary file is ``.<name>.<random>.part`` in the same folder (parent folders are created).
    On a clean exit the file is flushed, fsynced and renamed over ``path``; if the block raises,
    the temporary file is removed and ``path`` is left as it was.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write mode must be 'w' or 'wb', got {mode!r}")
    target = Path(path)
    tmp = _temp_name(target, ".part")
    binary = mode == "wb"
    try:
        with open(tmp, mode, newline=None if binary else newline,
                  encoding=None if binary else encoding) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(target.parent)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` for libraries that write by file name.

    The temporary name keeps the target's suffix (``.x.laz`` -> ``.x.<random>.tmp.laz``) because
    some libraries (laspy) choose the format from it. On a clean exit the file is fsynced and
    renamed over ``path``; if the block raises, it is deleted and ``path`` is left as it was.
    """
    target = Path(path)
    tmp = _temp_name(target, ".tmp" + target.suffix)
    try:
        yield tmp
        _fsync_file(tmp)
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(target.parent)
