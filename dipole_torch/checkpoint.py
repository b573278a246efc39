"""Outputs that survive a crash, and checkpoints that are verified and load without running
code.

* ``atomic_write_bytes``, ``atomic_write_text`` and ``atomic_save`` write a file
  under a temporary name in the same directory, flush it to disk (``fsync``) and move it into
  place with ``os.replace``: a reader (or a run killed at any moment, ``kill -9`` included)
  sees either the previous complete file or the new complete one, never a partial file.
* ``atomic_save`` stores a SHA-256 of what it writes, and ``load_checkpoint``
  verifies it before unpickling anything: a file changed after it was written (a flipped bit,
  a truncated or extended copy, pieces of two files spliced together) is refused, never
  loaded with other contents. The digest detects damage, not forgery: anyone who can write
  the file can write a matching digest, which is why loading is also safe (next point).
* ``load_checkpoint`` unpickles with ``torch.load(weights_only=True)``: tensors, dicts,
  lists, tuples, strings and numbers only. A file naming any other Python object (a pickle
  can name any callable, ``os.system`` included) is refused as unsafe and nothing in it is
  run; a file that is not a torch archive is never unpickled at all. Every failure to read a
  file is a ``CheckpointError`` that names the file and says what is wrong with it:
  missing, a directory, unreadable, empty, not a torch file, truncated or corrupt, failing
  its integrity check, unsafe, or another kind of file (not a dict, or lacking keys).

The file format of ``atomic_save``: the zip archive that ``torch.save`` writes, with its
archive comment set to a 56-byte integrity trailer::

    archive   the bytes of torch.save, except the comment length of the end-of-central-
              directory record (the archive's last 2 bytes), set to 56
    trailer   8 bytes   length of the archive above, unsigned little-endian
              32 bytes  SHA-256 of the archive above
              16 bytes  the marker b"\\x89DIPOLE-SHA256\\r\\n"

The whole file is a valid zip archive, so ``torch.load`` (and any zip reader) still reads it
directly. ``load_checkpoint`` takes a file ending with the marker to be of this format and
requires the length to be the file's size less 56 and the digest to match: every byte of the
file is then checked.

Files written before the trailer existed (plain ``torch.save``) still load. Such a *legacy*
file is recognised by its end, exactly as ``torch.save`` writes it: the last 22 bytes are the
end-of-central-directory record with an empty comment, and the central directory ends right
before that record. A damaged file of the new format cannot pass for legacy: its comment is
never empty, so a truncated one ends before the 56 bytes its record promises, and only
writing a whole new end record over the trailer (on purpose, as a forger would) makes it look
like one. A legacy file has no digest; the CRC-32 of each of its records is checked
(``torch.load`` itself checks none), which catches a flipped bit in any of their contents.
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import pickletools
import re
import struct
import tempfile
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, Any

import torch

__all__ = [
    "CheckpointError",
    "atomic_save",
    "atomic_write_bytes",
    "atomic_write_text",
    "load_checkpoint",
]

MARKER = b"\x89DIPOLE-SHA256\r\n"
_TRAILER = struct.Struct("<Q32s16s")  # archive length, SHA-256 of the archive, MARKER
TRAILER_SIZE = _TRAILER.size  # 56
_ZIP_START = b"PK\x03\x04"  # a local file header: the first bytes of every torch archive
_ZIP_END = struct.Struct("<4sHHHHIIH")  # the end-of-central-directory record (22 bytes)
_ZIP_END_SIGNATURE = b"PK\x05\x06"
_COMMENT_LENGTH = struct.pack("<H", TRAILER_SIZE)  # the last 2 bytes of the archive
_ZIP64 = 0xFFFFFFFF  # a field of the end record that the zip64 end record replaces
_ZIP64_LOCATOR = struct.Struct("<4sIQI")  # the zip64 end-of-central-directory locator
_ZIP64_END = struct.Struct("<4sQHHIIQQQQ")  # the zip64 end-of-central-directory record
_TORCH_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C  # the first pickle of torch < 1.6 files


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used: missing, truncated, corrupt, unsafe or of
    another kind."""


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
    """``torch.save(obj, path)`` atomically, with an integrity trailer: ``path`` holds the old
    file or the new one, and ``load_checkpoint`` refuses it if any byte changes later.

    The file is the zip archive of ``torch.save`` whose archive comment is the trailer (see
    the module docstring), so ``torch.load(path)`` also reads it.
    """

    def write(handle: IO[bytes]) -> None:
        buffer = io.BytesIO()
        torch.save(obj, buffer)
        archive, trailer = _with_integrity_trailer(buffer.getvalue())
        handle.write(archive)
        handle.write(trailer)

    _atomic_write(path, write)


def _with_integrity_trailer(archive: bytes) -> tuple[bytes, bytes]:
    """``(archive with a 56-byte comment declared, the trailer that is that comment)`` for the
    bytes of ``torch.save``; their concatenation is what ``atomic_save`` writes.

    Raises:
        ValueError: ``archive`` does not end with an end-of-central-directory record with an
            empty comment (``torch.save`` always writes one).
    """
    end = archive[-_ZIP_END.size :]
    if not end.startswith(_ZIP_END_SIGNATURE) or end[-2:] != b"\0\0":
        raise ValueError(
            "not the output of torch.save: it does not end with a zip end-of-central-directory "
            "record with an empty comment"
        )
    archive = archive[:-2] + _COMMENT_LENGTH
    return archive, _TRAILER.pack(len(archive), hashlib.sha256(archive).digest(), MARKER)


def load_checkpoint(
    path: str | os.PathLike,
    required: Iterable[str] = (),
    kind: str = "checkpoint",
    hint: str = "",
) -> dict:
    """Load a dict saved by ``atomic_save``, after checking its integrity, with
    ``torch.load(weights_only=True)``.

    A file of ``atomic_save``'s format must match its SHA-256; a legacy file (plain
    ``torch.save``, no trailer) must be a complete zip archive whose records match their
    CRC-32 (see the module docstring). Only then is the file unpickled, from the bytes that
    were checked.

    Args:
        path: the file.
        required: keys the dict must hold (a missing one means another kind of file).
        kind: what the file should be, for the messages (e.g. ``"train.py checkpoint"``).
        hint: a sentence appended to the message about missing keys.

    Returns:
        The dict, its tensors on the CPU.

    Raises:
        CheckpointError: the file is missing, is a directory, cannot be read, is empty, is
            not a torch file, is truncated or corrupt, fails its integrity check, holds
            objects other than tensors and plain containers (refused as unsafe, never
            executed), is not a dict, or lacks a required key. The message names the file
            and says which of these it is. Nothing else is raised for any file content.
    """
    path = Path(path)
    name = str(path)
    if not path.exists():
        raise CheckpointError(f"{kind} {name!r} does not exist")
    if path.is_dir():
        raise CheckpointError(
            f"{kind} {name!r} is a directory; give the file, e.g. {str(path / 'checkpoint.pt')!r}"
        )
    try:
        data = path.read_bytes()
    except OSError as error:
        raise CheckpointError(
            f"{kind} {name!r} cannot be read ({type(error).__name__}: {_first_line(error)})"
        ) from None
    if not data:
        raise CheckpointError(f"{kind} {name!r} is empty (0 bytes): it was never completed")
    verified = _check_bytes(data, kind, name)
    try:
        loaded = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as error:  # any failure of the unpickler is a failure of the file
        refused = _refused_global(error)
        if refused is not None:
            raise CheckpointError(_unsafe(kind, name, "its pickle", [refused])) from None
        if verified:  # intact since atomic_save wrote it, yet unreadable to this torch
            raise CheckpointError(
                f"{kind} {name!r} ({len(data)} bytes) passes its integrity check, but "
                f"torch.load cannot read it ({_described(error)})"
            ) from None
        raise CheckpointError(_corrupt(kind, name, len(data), _described(error))) from None
    if not isinstance(loaded, dict):
        raise CheckpointError(
            f"{name!r} is not a {kind}: it holds a {type(loaded).__name__}, not a dict"
        )
    missing = [key for key in required if key not in loaded]
    if missing:
        raise CheckpointError(
            f"{name!r} is not a {kind}: it lacks {missing} and holds the keys "
            f"{sorted(map(str, loaded))}. {hint}".rstrip()
        )
    return loaded


def _check_bytes(data: bytes, kind: str, name: str) -> bool:
    """Raise a ``CheckpointError`` unless ``data`` is a file of ``atomic_save``'s
    format that matches its digest (return True), or a complete legacy archive whose
    CRC-32s match (return False)."""
    size = len(data)
    if data.endswith(MARKER):
        if size < TRAILER_SIZE:
            raise CheckpointError(
                _failed_integrity(kind, name, size, "it is shorter than its trailer")
            )
        length, digest, _ = _TRAILER.unpack(data[-TRAILER_SIZE:])
        if length != size - TRAILER_SIZE:
            raise CheckpointError(
                _failed_integrity(
                    kind,
                    name,
                    size,
                    f"its trailer records an archive of {length} bytes, but "
                    f"{size - TRAILER_SIZE} bytes precede it (bytes were cut out, added or "
                    "changed)",
                )
            )
        if hashlib.sha256(memoryview(data)[:length]).digest() != digest:
            raise CheckpointError(
                _failed_integrity(
                    kind,
                    name,
                    size,
                    "the SHA-256 of its contents differs from the one stored when it was "
                    "written (a changed byte, or pieces of two files)",
                )
            )
        return True
    if _ZIP_START.startswith(data):
        raise CheckpointError(_corrupt(kind, name, size, "it ends within its first 4 bytes"))
    if not data.startswith(_ZIP_START):
        if data[-_ZIP_END.size :].startswith(_ZIP_END_SIGNATURE):
            raise CheckpointError(
                _corrupt(kind, name, size, "it ends like a zip archive but does not start like one")
            )
        raise CheckpointError(_not_torch(data, kind, name))
    end = data[-_ZIP_END.size :]
    if not end.startswith(_ZIP_END_SIGNATURE) or end[-2:] != b"\0\0":
        # A file of the new format whose marker changed still has its end record, declaring
        # the 56-byte comment, right before the trailer.
        before = data[-TRAILER_SIZE - _ZIP_END.size : -TRAILER_SIZE]
        if before.startswith(_ZIP_END_SIGNATURE) and before[-2:] == _COMMENT_LENGTH:
            raise CheckpointError(
                _failed_integrity(kind, name, size, "its integrity trailer is damaged")
            )
        raise CheckpointError(
            _corrupt(
                kind,
                name,
                size,
                "it does not end like a complete checkpoint: neither with the integrity "
                "trailer that atomic_save writes nor with the end record of a zip archive",
            )
        )
    problem = _legacy_problem(data)
    if problem is not None:
        raise CheckpointError(_corrupt(kind, name, size, problem))
    return False


def _legacy_problem(data: bytes) -> str | None:
    """Why ``data`` (ending with an end-of-central-directory record with an empty comment)
    is no complete, undamaged legacy file; ``None`` if it is one."""
    *_, cd_size, cd_offset, _ = _ZIP_END.unpack(data[-_ZIP_END.size :])
    cd_end = len(data) - _ZIP_END.size  # where the central directory must end
    locator = data[cd_end - _ZIP64_LOCATOR.size : cd_end]
    if locator.startswith(b"PK\x06\x07"):  # torch.save writes one even for a small archive
        _, _, record_offset, _ = _ZIP64_LOCATOR.unpack(locator)
        record = data[record_offset : record_offset + _ZIP64_END.size]
        if len(record) < _ZIP64_END.size or not record.startswith(b"PK\x06\x06"):
            return "its zip64 end record is missing"
        _, remaining, *_, cd_size, cd_offset = _ZIP64_END.unpack(record)
        if record_offset + 12 + remaining != cd_end - _ZIP64_LOCATOR.size:
            return "its zip64 end record does not end where its locator starts"
        cd_end = record_offset
    elif _ZIP64 in (cd_size, cd_offset):
        return "its zip64 end record is missing"
    if cd_offset + cd_size != cd_end:
        return (
            "its zip central directory does not end where its end record starts (bytes were "
            "cut out, added or changed)"
        )
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            infos = archive.infolist()
            if not infos or min(info.header_offset for info in infos) != 0:
                return "its zip archive does not start at the file's first byte"
            names = [info.filename for info in infos]
            if len(set(names)) != len(names):
                return "its zip archive holds two records of the same name"
            for info in infos:  # reading a record to its end checks its CRC-32
                with archive.open(info) as stream:
                    while stream.read(1 << 20):
                        pass
    except Exception as error:  # zipfile raises many kinds for damaged archives
        return (
            f"a legacy checkpoint (written without an integrity trailer) whose zip archive "
            f"is damaged ({_described(error)})"
        )
    return None


def _not_torch(data: bytes, kind: str, name: str) -> str:
    """The message for a file that is not a zip archive: unsafe if it is a pickle naming a
    callable (read with ``pickletools``, nothing run), else what it is."""
    callables, complete, first = _pickle_globals(data)
    if callables:
        return _unsafe(kind, name, "it is a bare pickle, not a torch archive, that", callables)
    start = f"{kind} {name!r} ({len(data)} bytes)"
    zip_archive = f"the zip archive that torch.save writes (which starts with {_ZIP_START!r})"
    if complete and first == _TORCH_LEGACY_MAGIC:
        return (
            f"{start} is in the serialization format of torch before 1.6, not {zip_archive}; "
            "atomic_save never wrote it"
        )
    if complete:
        return f"{start} is not a torch file: it is a bare pickle, not {zip_archive}"
    return f"{start} is not a torch file: it starts with {data[:16]!r}, not {zip_archive}"


def _pickle_globals(data: bytes) -> tuple[list[str], bool, Any]:
    """``(callables named, whether the opcodes parse up to a STOP, the first value pushed)``
    for ``data`` read as a pickle by ``pickletools.genops``, which runs nothing.

    The names of ``STACK_GLOBAL`` come from the strings pushed before it (directly or from
    the memo); one that cannot be told is ``"<unknown>"``.
    """
    names: list[str] = []
    strings: list[str | None] = []  # values pushed, as far as they are strings
    memo: dict[Any, str | None] = {}
    first: Any = None
    try:
        for opcode, arg, _ in pickletools.genops(data):
            op = opcode.name
            if op == "STOP":
                return names, True, first
            if op in ("GLOBAL", "INST"):
                names.append(".".join(str(arg).split(" ", 1)))
                strings.append(None)
            elif op == "STACK_GLOBAL":
                module, qualname = ([None, None] + strings)[-2:]
                known = isinstance(module, str) and isinstance(qualname, str)
                names.append(f"{module}.{qualname}" if known else "<unknown>")
                strings.append(None)
            elif op == "MEMOIZE":
                memo[len(memo)] = strings[-1] if strings else None
            elif op in ("PUT", "BINPUT", "LONG_BINPUT"):
                memo[arg] = strings[-1] if strings else None
            elif op in ("GET", "BINGET", "LONG_BINGET"):
                strings.append(memo.get(arg))
            elif op != "PROTO" and op != "FRAME":
                strings.append(arg if isinstance(arg, str) else None)
                if first is None and arg is not None:
                    first = arg
    except Exception:  # not (or no longer) a pickle: what was read so far tells
        pass
    return names, False, first


def _refused_global(error: BaseException) -> str | None:
    """The object that the weights-only unpickler refused, if that is why it failed."""
    if not isinstance(error, pickle.UnpicklingError):
        return None
    # ("GLOBAL posix.system was not an allowed global" in later torch releases, "Unsupported
    # class posix.system" in torch 2.2 and 2.3.)
    found = re.search(r"\bGLOBAL\s+(\S+)|\bUnsupported class\s+(\S+)", str(error))
    return next(name for name in found.groups() if name) if found else None


def _unsafe(kind: str, name: str, source: str, callables: list[str]) -> str:
    named = ", ".join(dict.fromkeys(callables))
    return (
        f"refusing to load {kind} {name!r}: it is unsafe: {source} names the callable "
        f"{named} (a checkpoint holds only tensors, dicts, lists, strings and numbers), and "
        "loading it could run code; nothing in it was run"
    )


def _failed_integrity(kind: str, name: str, size: int, why: str) -> str:
    return f"{kind} {name!r} ({size} bytes) is corrupt (integrity check failed): {why}"


def _corrupt(kind: str, name: str, size: int, why: str) -> str:
    return f"{kind} {name!r} ({size} bytes) is truncated or corrupt and cannot be read: {why}"


def _described(error: BaseException) -> str:
    """``"Type: first line"``; for the weights-only unpickler, the line saying what it met."""
    text = str(error)
    if "WeightsUnpickler error:" in text:
        text = text.split("WeightsUnpickler error:", 1)[1]
    return f"{type(error).__name__}: {_first_line(text) or type(error).__name__}"


def _first_line(error: BaseException | str) -> str:
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[0] if lines else type(error).__name__
