"""Outputs that survive a crash, and checkpoints that load without running code.

* :func:`atomic_write_bytes`, :func:`atomic_write_text` and :func:`atomic_save` write a file
  under a temporary name in the same directory, flush it to disk (``fsync``) and move it into
  place with ``os.replace``: a reader (or a run killed at any moment, ``kill -9`` included)
  sees either the previous complete file or the new complete one, never a partial file.
* :func:`load_checkpoint` reads a file written by :func:`atomic_save` with
  ``torch.load(weights_only=True)``: tensors, dicts, lists, tuples, strings and numbers only.
  A file holding any other Python object is refused, so loading a data file never runs code
  (a pickle can name any callable). Every failure is a :class:`CheckpointError` that names
  the file and says what is wrong with it.
* :func:`config_differences` lists the dotted keys in which two nested dicts differ.

Nothing here imports Hydra: configs are plain dicts (``OmegaConf.to_container``).
"""

from __future__ import annotations

import os
import pickle
import tempfile
import zipfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import IO, Any

import torch

__all__ = [
    "CheckpointError",
    "atomic_save",
    "atomic_write_bytes",
    "atomic_write_text",
    "config_differences",
    "flatten",
    "load_checkpoint",
    "remove_stale_temporaries",
]


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used: missing, truncated, unsafe or of another kind."""


def _atomic_write(path: str | os.PathLike, write: Callable[[IO[bytes]], None]) -> None:
    path = Path(path)
    directory = path.parent
    fd, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        # mkstemp makes the file private (0600); give it the mode a plain open() would.
        os.chmod(temporary, _file_mode(path))
        with os.fdopen(fd, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        # Any failure (a full disk, an exception in ``write``, Ctrl-C) leaves the previous
        # file untouched and no temporary behind.
        try:
            os.unlink(temporary)
        except FileNotFoundError:
            pass
        raise
    # The rename itself survives a power cut only once the directory entry is on disk.
    try:
        dir_fd = os.open(directory, os.O_RDONLY)
    except OSError:  # platforms without directory handles (Windows)
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)


def _file_mode(path: Path) -> int:
    """The replaced file's permissions, or the default ones under the current umask."""
    try:
        return path.stat().st_mode & 0o7777
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file, ``fsync``, ``os.replace``)."""
    _atomic_write(path, lambda handle: handle.write(data))


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_save(obj: Any, path: str | os.PathLike) -> None:
    """``torch.save(obj, path)`` atomically: ``path`` holds the old file or the new one."""
    _atomic_write(path, lambda handle: torch.save(obj, handle))


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


def load_checkpoint(
    path: str | os.PathLike,
    required: Iterable[str] = (),
    kind: str = "checkpoint",
    hint: str = "",
) -> dict:
    """Load a dict saved by :func:`atomic_save` with ``torch.load(weights_only=True)``.

    Args:
        path: the file.
        required: keys the dict must hold (a missing one means another kind of file).
        kind: what the file should be, for the messages (e.g. ``"train.py checkpoint"``).
        hint: a sentence appended to the message about missing keys.

    Returns:
        The dict, its tensors on the CPU.

    Raises:
        CheckpointError: the file is missing, is a directory, is empty or truncated, holds
            objects other than tensors and plain containers (refused, never executed), is
            not a dict, or lacks a required key. The message names the file.
    """
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{kind} {str(path)!r} does not exist")
    if path.is_dir():
        raise CheckpointError(
            f"{kind} {str(path)!r} is a directory; give the file, "
            f"e.g. {str(path / 'checkpoint.pt')!r}"
        )
    size = path.stat().st_size
    if size == 0:
        raise CheckpointError(f"{kind} {str(path)!r} is empty (0 bytes): it was never completed")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        if "global" not in str(error).lower():  # e.g. "Unsupported operand": garbage bytes
            raise CheckpointError(_corrupt(kind, path, size, error)) from None
        # The weights-only unpickler met a global it does not allow: code could run.
        raise CheckpointError(
            f"refusing to load {kind} {str(path)!r}: it holds Python objects other than "
            "tensors, dicts, lists, strings and numbers, and loading it could run code "
            f"({_unsafe_detail(error)})"
        ) from None
    except (RuntimeError, OSError, EOFError, zipfile.BadZipFile, ValueError) as error:
        raise CheckpointError(_corrupt(kind, path, size, error)) from None
    if not isinstance(data, dict):
        raise CheckpointError(
            f"{str(path)!r} is not a {kind}: it holds a {type(data).__name__}, not a dict"
        )
    missing = [key for key in required if key not in data]
    if missing:
        raise CheckpointError(
            f"{str(path)!r} is not a {kind}: it lacks {missing} and holds the keys "
            f"{sorted(map(str, data))}. {hint}".rstrip()
        )
    return data


def _corrupt(kind: str, path: Path, size: int, error: BaseException) -> str:
    return (
        f"{kind} {str(path)!r} ({size} bytes) is truncated or corrupt and cannot be read "
        f"({type(error).__name__}: {_first_line(error)})"
    )


def _unsafe_detail(error: BaseException) -> str:
    """The line of the weights-only unpickler's message that names the refused object."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    named = [line for line in lines if "GLOBAL" in line or "global" in line.lower()]
    return named[0] if named else "the weights-only unpickler refused it"


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def flatten(tree: Mapping, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` → ``{"a.b": 1}``; lists are leaves."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(flatten(value, f"{name}."))
        else:
            flat[name] = value
    return flat


def config_differences(
    saved: Mapping, current: Mapping, ignore: Iterable[str] = ()
) -> list[tuple[str, Any, Any]]:
    """``[(key, saved value, current value)]`` for every dotted key whose values differ
    (a key present in only one side has ``<missing>`` on the other), except keys in
    ``ignore`` and keys under an ignored prefix (``"hydra"`` ignores ``"hydra.run.dir"``)."""
    ignore = tuple(ignore)
    a, b = flatten(saved), flatten(current)
    differences = []
    for key in sorted(set(a) | set(b)):
        if any(key == skip or key.startswith(f"{skip}.") for skip in ignore):
            continue
        left, right = a.get(key, "<missing>"), b.get(key, "<missing>")
        if left != right:
            differences.append((key, left, right))
    return differences
