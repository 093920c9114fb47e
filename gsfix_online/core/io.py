"""Atomic file writes: readers see either the old file or the whole new one, never a part.

Every file the project writes for others to read (maps, images, metrics, configs, checkpoints)
goes through :func:`atomic_path`: the data is written to a temporary file beside the target,
synced, given the mode a plain ``open()`` would have given it (the process umask applied to
0666, so 0644 under the usual umask 022 and an output folder can be shared), renamed over the
target, and the folder is synced so that the rename itself survives a power failure.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0)  # the only portable way to read it: set and restore at once
    os.umask(mask)
    return mask


def _fsync_dir(folder: Path) -> None:
    """Sync a folder's entries (a rename in it) to disk; a no-op where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:  # e.g. Windows: folders cannot be opened for syncing
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems do not support syncing a folder
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix, so tools that pick the format from
    it still work); when the block succeeds it replaces ``path`` in one rename, so readers see
    either the old or the whole new file. The temporary file is synced to disk and given the
    umask's mode before the rename, and the folder is synced after it, so a crash never leaves
    a renamed file with missing data or a lost rename. On error the temporary file is removed;
    an OSError (a full disk, a read-only folder) is raised again as one line naming ``path``:
    ``cannot write PATH: No space left on device``."""
    p = Path(path)
    tmp = None
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{p.stem}.", suffix=p.suffix, dir=p.parent)
        os.close(fd)
        yield Path(tmp)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600 whatever the umask
        os.replace(tmp, p)
        _fsync_dir(p.parent)
    except BaseException as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.errno is not None:
            # the failing call named the temporary file, or nothing (a write's ENOSPC)
            raise type(exc)(exc.errno, f"cannot write {p}: {exc.strerror}") from exc
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`), synced to disk."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` to ``path`` so that readers see either the old or the whole new file."""
    atomic_write_bytes(path, text.encode())
