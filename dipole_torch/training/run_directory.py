"""A run's directory: one writer at a time, and no temporaries left by a killed one.

* ``lock_run_directory`` holds an exclusive, non-blocking ``fcntl.flock`` on a lock file
  in a run's directory while a process writes there; a second process (a resume started
  while the run still goes on) gets ``RunDirectoryLocked`` instead of writing the same
  files. The operating system drops the lock when its holder exits or dies (``kill -9``
  included), so a lock is never left stale.
* ``remove_stale_temporaries`` deletes what a writer killed mid-write left behind.
"""

from __future__ import annotations

import errno
import os
import socket
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from dipole_torch.checkpoint import CheckpointError, _first_line

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None
    import msvcrt

__all__ = ["RunDirectoryLocked", "lock_run_directory", "remove_stale_temporaries"]


class RunDirectoryLocked(CheckpointError):
    """Another process holds the lock of a run's directory (see ``lock_run_directory``)."""


def remove_stale_temporaries(directory: str | os.PathLike, names: Iterable[str]) -> list[Path]:
    """Delete the temporary files that a writer killed mid-write (``kill -9``, power cut)
    left next to ``directory/name`` for each name; return them. Call it only while no other
    process writes those files (e.g. when a run starts)."""
    removed = []
    for name in names:
        for temporary in Path(directory).glob(f".{name}.*.tmp"):
            temporary.unlink(missing_ok=True)
            removed.append(temporary)
    return removed


@contextmanager
def lock_run_directory(directory: str | os.PathLike, name: str = ".lock") -> Iterator[Path]:
    """Hold the exclusive lock of a run's directory for the body of a ``with`` block.

    The lock is a non-blocking ``fcntl.flock`` on ``directory/name`` (the directory and the
    file are created if missing), which also records the holder's pid and host for the
    message another process gets. The operating system releases it when the block ends or
    the process exits or dies in any way (``kill -9`` included), so no stale lock can block
    a later resume; the file itself stays and means nothing without the lock.

    A lock belongs to an open file, not to a process: a second ``lock_run_directory`` of the
    same directory fails in the same process too, and a child forked inside the block shares
    the lock, which the block's end releases for the child too (a child left running cannot
    keep the directory locked).

    Yields:
        The lock file's path.

    Raises:
        RunDirectoryLocked: another process (or another block of this one) holds the lock.
            The message names the directory and the holder's pid and host.
        CheckpointError: the lock file cannot be created or locked (e.g. a read-only
            directory, or a file system without locks).
    """
    directory = Path(directory)
    lock_path = directory / name
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as error:
        raise CheckpointError(
            f"cannot lock run directory {str(directory)!r}: cannot create {str(lock_path)!r} "
            f"({type(error).__name__}: {_first_line(error)})"
        ) from None
    try:
        try:
            _lock(fd)
        except OSError as error:
            if error.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise CheckpointError(
                    f"cannot lock run directory {str(directory)!r} with {str(lock_path)!r} "
                    f"({type(error).__name__}: {_first_line(error)})"
                ) from None
            holder = _holder(lock_path)
            if holder.startswith(f"pid {os.getpid()} on {socket.gethostname()}"):
                raise RunDirectoryLocked(
                    f"run directory {str(directory)!r} is locked: this process ({holder}) "
                    "already holds its lock and is writing it"
                ) from None
            raise RunDirectoryLocked(
                f"run directory {str(directory)!r} is locked: another process ({holder}) is "
                "writing it. Wait for that run to end, or stop it, before running in that "
                f"directory; the lock ({str(lock_path)!r}) ends with its process."
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode())
        try:
            yield lock_path
        finally:
            _unlock(fd)
    finally:
        os.close(fd)


def _lock(fd: int) -> None:
    if fcntl is not None:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    else:  # pragma: no cover - Windows
        os.lseek(fd, 0, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)


def _unlock(fd: int) -> None:
    if fcntl is not None:
        fcntl.flock(fd, fcntl.LOCK_UN)
    else:  # pragma: no cover - Windows
        os.lseek(fd, 0, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)


def _holder(lock_path: Path) -> str:
    """What the lock file says of its holder (``pid N on HOST``), or that it is unknown."""
    try:
        text = lock_path.read_text(errors="replace").strip()
    except OSError:
        text = ""
    return text[:200] if text else "holder unknown"
