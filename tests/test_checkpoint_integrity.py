"""Checkpoint integrity: a digest that atomic_save stores and load_checkpoint verifies, a
clear CheckpointError for every bad file (nothing else raised, nothing in it run), legacy
files that still load, and the lock that keeps a second process out of a run directory.

The fuzz test damages a realistic checkpoint (truncations, bit flips, splices of two
checkpoints, bytes cut out, repeated or appended, malicious pickles) and requires every file
either to be refused with a CheckpointError or to load exactly the contents written.
"""

from __future__ import annotations

import hashlib
import io
import math
import os
import pickle
import random
import re
import shlex
import signal
import struct
import subprocess
import sys
import zipfile
from collections import Counter
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import dipole_torch.training.run_directory as run_directory  # noqa: E402
from dipole_torch.checkpoint import CheckpointError, atomic_save, load_checkpoint  # noqa: E402

TRAILER_SIZE = 56  # the documented format: length (8), SHA-256 (32), marker (16)
MARKER = b"\x89DIPOLE-SHA256\r\n"
CONFIG = """\
task:
  _target_: dipole_torch.tasks.multimodal.MultimodalTask
  name: multimodal
  dimension: 2
  n0: 10
algo:
  name: dipole
  optimizer:
    alpha: 1.0
    pair_points: true
    max_sampled: null
seed: 3
trials: 40
checkpoint_every: 1
resume: null
"""


# ------------------------------------------------------------------ helpers
def realistic_checkpoint(seed: int) -> dict:
    """A dict shaped like train.py's checkpoint: an optimizer state of tensors with its
    generator's state, the task's generator state, a history of dicts, the config YAML."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    optimizer = {
        "trials": 37,
        "iteration": 4,
        "policies": {
            "theta": torch.randn(12, 2, generator=g, dtype=f64),
            "returns": torch.rand(12, generator=g, dtype=f64),
            "active": torch.rand(12, generator=g) < 0.5,
        },
        "mixture": {
            "labels": torch.randint(0, 3, (12,), generator=g),
            "means": torch.randn(3, 3, generator=g, dtype=f64),
            "covariances": torch.eye(3, dtype=f64).expand(3, 3, 3).clone(),
            "prior": {"kappa": 0.01, "nu": 5.0, "mean": torch.zeros(3, dtype=f64)},
        },
        "generator": g.get_state(),
    }
    task_generator = torch.Generator().manual_seed(seed + 100)
    torch.rand(seed + 1, generator=task_generator)
    history = [
        {
            "iteration": i,
            "trials": 10 + 9 * i,
            "best_return": 0.25 + 0.1 * i + 0.01 * seed,
            "components": 1 + i % 3,
        }
        for i in range(5)
    ]
    return {
        "optimizer": optimizer,
        "task_generator": task_generator.get_state(),
        "history": history,
        "config": CONFIG,
        "overrides": ["task=multimodal", "trials=40", f"seed={seed}"],
        "wall_time_s": 1.5 + seed,
    }


def same(a, b) -> bool:
    """Deep equality of nested dicts / lists / tensors / numbers (types and dtypes too)."""
    if isinstance(a, torch.Tensor):
        return (
            isinstance(b, torch.Tensor)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and torch.equal(a, b)
        )
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return type(a) is type(b) and len(a) == len(b) and all(map(same, a, b))
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return type(a) is type(b) and a == b


def saved_bytes(obj, directory: Path, name: str) -> bytes:
    path = directory / name
    atomic_save(obj, path)
    return path.read_bytes()


def torch_saved_bytes(obj) -> bytes:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()


def flip(data: bytes, position: int, bit: int) -> bytes:
    changed = bytearray(data)
    changed[position] ^= 1 << bit
    return bytes(changed)


class Marker:
    """Pickles as a call that creates ``path`` when unpickled by a loader that runs code."""

    def __init__(self, path: Path, how: str):
        self.path, self.how = path, how

    def __reduce__(self):
        if self.how == "open":
            return (open, (str(self.path), "w"))
        return (os.system, (f"touch {shlex.quote(str(self.path))}",))


# ------------------------------------------------------------------ the file format
def test_atomic_save_writes_the_documented_trailer_and_stays_a_torch_file(tmp_path):
    original = realistic_checkpoint(0)
    data = saved_bytes(original, tmp_path, "checkpoint.pt")
    length, digest, marker = struct.unpack("<Q32s16s", data[-TRAILER_SIZE:])
    assert marker == MARKER and length == len(data) - TRAILER_SIZE
    assert digest == hashlib.sha256(data[:length]).digest()
    # The trailer is the zip archive's comment: any zip reader and torch.load read the file.
    with zipfile.ZipFile(tmp_path / "checkpoint.pt") as archive:
        assert archive.comment == data[-TRAILER_SIZE:]
        assert archive.testzip() is None
    assert same(torch.load(tmp_path / "checkpoint.pt", weights_only=True), original)
    assert same(load_checkpoint(tmp_path / "checkpoint.pt"), original)
    # Apart from the declared comment, the archive is the one torch.save writes.
    legacy = torch_saved_bytes(original)
    assert len(legacy) == length and legacy[:-2] == data[: length - 2]


def test_a_legacy_checkpoint_still_loads(tmp_path):
    """Files written by plain torch.save (before the trailer existed) load unchanged: the
    archive of torch.save, and one rewritten by another zip writer (no zip64 records)."""
    original = realistic_checkpoint(1)
    legacy = tmp_path / "legacy.pt"
    torch.save(original, legacy)
    assert same(load_checkpoint(legacy, required=["optimizer", "config"]), original)
    # The same records written by Python's zipfile, whose small archives have no zip64 end.
    repacked = io.BytesIO()
    with zipfile.ZipFile(legacy) as source, zipfile.ZipFile(repacked, "w") as target:
        for info in source.infolist():
            target.writestr(info.filename, source.read(info.filename))
    assert b"PK\x06\x07" not in repacked.getvalue()[-60:]
    (tmp_path / "repacked.pt").write_bytes(repacked.getvalue())
    assert same(load_checkpoint(tmp_path / "repacked.pt"), original)


def test_a_new_checkpoint_cut_at_its_archive_end_is_not_taken_for_a_legacy_one(tmp_path):
    data = saved_bytes(realistic_checkpoint(0), tmp_path, "checkpoint.pt")
    cut = tmp_path / "cut.pt"
    cut.write_bytes(data[:-TRAILER_SIZE])  # the archive alone, declaring a missing comment
    with pytest.raises(CheckpointError, match=r"is truncated or corrupt"):
        load_checkpoint(cut)


# ------------------------------------------------------------------ every failure, its message
def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _bad_files(tmp_path: Path, monkeypatch) -> tuple[dict[str, Path], Path]:
    good = saved_bytes(realistic_checkpoint(0), tmp_path, "good.pt")
    legacy = torch_saved_bytes(realistic_checkpoint(0))
    marker = tmp_path / "ran"
    old_format = io.BytesIO()
    torch.save({"a": torch.ones(2)}, old_format, _use_new_zipfile_serialization=False)
    unreadable = _write(tmp_path / "unreadable.pt", good)
    real_read_bytes = Path.read_bytes

    def read_bytes(self):
        if self == unreadable:
            raise PermissionError(13, "Permission denied", str(self))
        return real_read_bytes(self)

    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    policies = tmp_path / "policies.pt"
    atomic_save({"policies": {"theta": torch.zeros(2, 2)}}, policies)
    a_list = tmp_path / "list.pt"
    atomic_save([torch.zeros(2)], a_list)
    return {
        "missing": tmp_path / "nothing.pt",
        "directory": tmp_path,
        "unreadable": unreadable,
        "empty": _write(tmp_path / "empty.pt", b""),
        "text": _write(tmp_path / "text.pt", b"hello\n"),
        "bare pickle": _write(tmp_path / "pickle.pt", pickle.dumps({"a": [1, 2.0]})),
        "torch < 1.6 format": _write(tmp_path / "old.pt", old_format.getvalue()),
        "unsafe bare pickle": _write(
            tmp_path / "raw.pt", pickle.dumps({"optimizer": Marker(marker, "system")})
        ),
        "unsafe torch archive": _write(
            tmp_path / "evil.pt", torch_saved_bytes({"optimizer": Marker(marker, "system")})
        ),
        "truncated": _write(tmp_path / "truncated.pt", good[:1000]),
        "truncated header": _write(tmp_path / "pk.pt", good[:3]),
        "digest mismatch": _write(tmp_path / "flipped.pt", flip(good, 200, 3)),
        "length mismatch": _write(tmp_path / "extended.pt", good[:100] + good[99:]),
        "damaged trailer": _write(tmp_path / "marker.pt", flip(good, len(good) - 5, 0)),
        "damaged legacy": _write(tmp_path / "legacy.pt", flip(legacy, 200, 3)),
        "bad legacy end": _write(tmp_path / "legacy_end.pt", legacy[:-30] + legacy[-29:]),
        "not a dict": a_list,
        "missing keys": policies,
    }, marker


MESSAGES = {
    "missing": r"^train.py checkpoint '.*nothing.pt' does not exist$",
    "directory": r"is a directory; give the file, e.g. '.*checkpoint.pt'",
    "unreadable": r"cannot be read \(PermissionError: .*Permission denied",
    "empty": r"is empty \(0 bytes\): it was never completed",
    "text": r"is not a torch file: it starts with b'hello\\n', not the zip archive",
    "bare pickle": r"is not a torch file: it is a bare pickle, not the zip archive",
    "torch < 1.6 format": r"is in the serialization format of torch before 1\.6, not the zip",
    "unsafe bare pickle": (
        r"^refusing to load .*: it is unsafe: it is a bare pickle, not a torch archive, that "
        r"names the callable (posix|nt)\.system .* could run code; nothing in it was run$"
    ),
    "unsafe torch archive": (
        r"^refusing to load .*: it is unsafe: its pickle names the callable (posix|nt)\.system"
        r" .* could run code; nothing in it was run$"
    ),
    "truncated": (
        r"\(1000 bytes\) is truncated or corrupt and cannot be read: it does not end like a "
        "complete checkpoint"
    ),
    "truncated header": r"\(3 bytes\) is truncated or corrupt .*: it ends within its first 4",
    "digest mismatch": r"is corrupt \(integrity check failed\): the SHA-256 of its contents",
    "length mismatch": r"is corrupt \(integrity check failed\): its trailer records an archive",
    "damaged trailer": r"is corrupt \(integrity check failed\): its integrity trailer is damaged",
    "damaged legacy": (
        r"is truncated or corrupt .*: a legacy checkpoint \(written without an integrity "
        r"trailer\) whose zip archive is damaged \(BadZipFile: Bad CRC-32"
    ),
    "bad legacy end": r"is truncated or corrupt .*: its zip central directory does not end where",
    "not a dict": r"is not a train.py checkpoint: it holds a list, not a dict",
    "missing keys": r"is not a train.py checkpoint: it lacks \['optimizer', 'task_generator'",
}


def test_each_kind_of_bad_file_gets_its_own_message_naming_the_file(tmp_path, monkeypatch):
    files, marker = _bad_files(tmp_path, monkeypatch)
    assert files.keys() == MESSAGES.keys()
    messages = {}
    for what, path in files.items():
        with pytest.raises(CheckpointError) as error:
            load_checkpoint(
                path, required=("optimizer", "task_generator"), kind="train.py checkpoint"
            )
        message = str(error.value)
        assert type(error.value) is CheckpointError, what
        assert re.search(MESSAGES[what], message), f"{what}: {message}"
        assert str(path) in message, what
        # The family (the words after the file's name) differs from every other kind's.
        messages[what] = re.sub(r"\(\d+ bytes\)", "", message.replace(str(path), "FILE"))
    assert len(set(messages.values())) == len(messages)
    assert not marker.exists()


# ------------------------------------------------------------------ the fuzz test
def _mutants(tmp_path: Path) -> tuple[dict, dict, list[tuple[str, str, bytes]]]:
    """``(originals, their files, [(kind, origin, bytes)])``: the damaged files, each with
    the name of the original it comes from (whose contents it may load, nothing else)."""
    rng = random.Random(20130101)
    originals = {"a": realistic_checkpoint(0), "b": realistic_checkpoint(1)}
    a = saved_bytes(originals["a"], tmp_path, "a.pt")
    b = saved_bytes(originals["b"], tmp_path, "b.pt")
    legacy = torch_saved_bytes(originals["a"])
    archive_end = len(a) - TRAILER_SIZE
    mutants: list[tuple[str, str, bytes]] = []

    # Truncations: every size near the start, the archive's end and the file's end, and a
    # spread of sizes between.
    sizes = {*range(0, 40), *range(archive_end - 30, len(a))}
    sizes |= set(rng.sample(range(40, archive_end - 30), 120))
    mutants += [("truncated", "a", a[:size]) for size in sorted(sizes)]
    mutants += [
        ("truncated legacy", "a", legacy[:size]) for size in rng.sample(range(len(legacy)), 40)
    ]

    # Single bit flips: random ones over the whole file, and every bit of the trailer and of
    # the zip end records before it.
    positions = [(rng.randrange(len(a)), rng.randrange(8)) for _ in range(300)]
    positions += [(p, bit) for p in range(archive_end - 98, len(a)) for bit in range(8)]
    mutants += [("bit flip", "a", flip(a, p, bit)) for p, bit in positions]
    legacy_flips = [(rng.randrange(len(legacy)), rng.randrange(8)) for _ in range(200)]
    mutants += [("bit flip legacy", "a", flip(legacy, p, bit)) for p, bit in legacy_flips]

    # Splices: the start of one checkpoint and the end of the other, bytes cut out or
    # repeated, two files end to end, one file's archive with the other's trailer, a legacy
    # archive with a trailer, extra bytes at the end.
    short = min(len(a), len(b))
    for cut in sorted(rng.sample(range(1, short), 60)):
        mutants.append(("spliced a|b", "a|b", a[:cut] + b[cut:]))
        mutants.append(("spliced b|a", "a|b", b[:cut] + a[cut:]))
    for _ in range(40):
        i = rng.randrange(len(a))
        j = min(len(a), i + rng.randrange(1, 200))
        mutants.append(("bytes cut out", "a", a[:i] + a[j:]))
        mutants.append(("bytes repeated", "a", a[:j] + a[i:j] + a[j:]))
    mutants += [
        ("two files", "a|b", a + b),
        ("two files", "a|b", b + a),
        ("two files", "a", legacy + a),
        ("trailer swapped", "a|b", a[:archive_end] + b[-TRAILER_SIZE:]),
        ("trailer swapped", "a|b", b[: len(b) - TRAILER_SIZE] + a[-TRAILER_SIZE:]),
        ("trailer swapped", "a", legacy + a[-TRAILER_SIZE:]),
        ("trailer swapped", "a", legacy[:-2] + struct.pack("<H", TRAILER_SIZE) + a[-56:]),
        ("bytes appended", "a", a + b"\0"),
        ("bytes appended", "a", a + b"\n" * 100),
        ("bytes appended", "a", legacy + b"\0"),
        ("bytes appended", "a", legacy + a[:200]),
        ("bytes prepended", "a", b"\0" + a),
        ("bytes prepended", "a", b"PK" + legacy),
    ]
    return originals, {"a": a, "b": b, "legacy": legacy}, mutants


def _malicious(tmp_path: Path, marker: Path) -> list[tuple[str, str, bytes]]:
    """Files whose unpickling would create ``marker``: bare pickles of every protocol, torch
    archives, and files of atomic_save's format with a valid digest (a forger's)."""
    files = []
    for how in ("open", "system"):
        obj = {"optimizer": Marker(marker, how), "task_generator": 0, "history": [], "config": ""}
        for protocol in range(pickle.HIGHEST_PROTOCOL + 1):
            files.append(("malicious", "", pickle.dumps(obj, protocol=protocol)))
        files.append(("malicious", "", torch_saved_bytes(obj)))
        files.append(("malicious", "", saved_bytes(obj, tmp_path, f"evil_{how}.pt")))
        nested = {"optimizer": {"history": [{"x": (1, Marker(marker, how))}]}}
        files.append(("malicious", "", saved_bytes(nested, tmp_path, f"nested_{how}.pt")))
        # A malicious pickle in place of a benign archive's data.pkl, with a valid trailer.
        files.append(("malicious", "", _forged(torch_saved_bytes({"x": 1}), obj)))
    return files


def _forged(archive: bytes, obj) -> bytes:
    """``archive`` with ``obj``'s pickle as its data.pkl, in atomic_save's format (a trailer
    with a correct digest, computed here from the documented format)."""
    source, target = zipfile.ZipFile(io.BytesIO(archive)), io.BytesIO()
    with zipfile.ZipFile(target, "w") as forged:
        for info in source.infolist():
            data = source.read(info)
            if info.filename.endswith("/data.pkl"):
                data = pickle.dumps(obj, protocol=2)
            forged.writestr(info.filename, data)
    body = target.getvalue()[:-2] + struct.pack("<H", TRAILER_SIZE)
    return body + struct.pack("<Q32s16s", len(body), hashlib.sha256(body).digest(), MARKER)


@pytest.mark.parametrize(
    "message",
    [
        # the weights-only unpickler of later torch releases (2.13 among them)
        "Weights only load failed. ... Unsupported global: GLOBAL posix.system was not an "
        "allowed global by default.",
        # torch 2.2's and 2.3's
        "Weights only load failed. ... Unsupported class posix.system",
    ],
)
def test_the_refused_callable_is_read_from_each_torch_versions_message(message):
    # CI runs one torch; the message of the others is held here (the file is refused as
    # corrupt instead of unsafe when its wording is not recognised).
    from dipole_torch.checkpoint import _refused_global

    assert _refused_global(pickle.UnpicklingError(message)) == "posix.system"
    assert _refused_global(pickle.UnpicklingError("invalid load key, 'x'.")) is None


def test_no_damaged_checkpoint_loads_other_contents_or_raises_anything_else(tmp_path):
    originals, sources, mutants = _mutants(tmp_path)
    marker = tmp_path / "ran"
    malicious = _malicious(tmp_path, marker)
    mutants += malicious
    assert len(mutants) >= 500
    untouched = {sources["a"], sources["b"], sources["legacy"]}
    target = tmp_path / "checkpoint.pt"
    outcomes: Counter = Counter()
    for index, (kind, origin, data) in enumerate(mutants):
        target.write_bytes(data)
        try:
            loaded = load_checkpoint(target, kind="train.py checkpoint")
        except CheckpointError as error:
            assert str(target) in str(error), (index, kind, str(error))
            if kind == "malicious":  # refused as unsafe, not as damaged
                assert "it is unsafe" in str(error), (index, str(error))
            outcomes[kind, "refused"] += 1
            continue
        except Exception as error:  # pragma: no cover - the failure this test looks for
            raise AssertionError(f"{kind} #{index} raised {error!r}") from error
        # A file that loads holds exactly the contents of one of its originals.
        assert any(same(loaded, originals[name]) for name in origin.split("|") if name), (
            f"{kind} #{index} loaded other contents"
        )
        outcome = "is an original, loaded" if data in untouched else "changed, loaded as written"
        outcomes[kind, outcome] += 1
    assert not marker.exists()
    print(dict(sorted(outcomes.items())))
    # The new format refuses every change; only a legacy file, which has no digest, loads
    # after a harmless flip (in bytes that its readers ignore).
    changed = {kind for kind, outcome in outcomes if outcome == "changed, loaded as written"}
    assert changed <= {"bit flip legacy"}, f"changed files that loaded: {sorted(changed)}"
    assert outcomes["malicious", "refused"] == len(malicious)
    # The originals themselves load (the checks above are not refusing everything).
    for name, original in (("a", "a"), ("b", "b"), ("legacy", "a")):
        target.write_bytes(sources[name])
        assert same(load_checkpoint(target), originals[original])


# ------------------------------------------------------------------ the run-directory lock
def test_a_locked_run_directory_refuses_a_second_writer_until_released(tmp_path):
    run = tmp_path / "run"
    with run_directory.lock_run_directory(run) as lock_file:
        assert lock_file.parent == run and lock_file.exists()
        with pytest.raises(run_directory.RunDirectoryLocked) as error:
            with run_directory.lock_run_directory(run):
                pass
        message = str(error.value)
        assert str(run) in message and f"this process (pid {os.getpid()} on" in message
        assert isinstance(error.value, CheckpointError)
    with run_directory.lock_run_directory(run):  # released at the end of the block
        pass
    with pytest.raises(RuntimeError), run_directory.lock_run_directory(run):
        raise RuntimeError("the run failed")
    with run_directory.lock_run_directory(run):  # released by an exception too
        pass


def test_the_end_of_the_block_releases_the_lock_for_a_child_forked_inside_it(tmp_path):
    # In an interpreter of its own (os.fork of this multi-threaded one may deadlock): the
    # child outlives the block, and the directory can be locked again at once.
    script = (
        "import os, sys, time\n"
        "from dipole_torch.training.run_directory import lock_run_directory\n"
        "with lock_run_directory(sys.argv[1]):\n"
        "    child = os.fork()\n"
        "    if child == 0:\n"
        "        time.sleep(5)\n"
        "        os._exit(0)\n"
        "with lock_run_directory(sys.argv[1]):\n"
        "    print('locked again', flush=True)\n"
        "os.kill(child, 9)\n"
        "os.waitpid(child, 0)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path / "run")], capture_output=True, text=True
    )
    assert done.stdout == "locked again\n", done.stderr[-500:]


def test_the_lock_file_records_its_holder_and_the_message_names_it(tmp_path, monkeypatch):
    import fcntl
    import socket

    run = tmp_path / "run"
    run.mkdir()
    (run / ".lock").write_text("pid 4000000000 on a-host-with-a-much-longer-name-than-this\n")
    with run_directory.lock_run_directory(run) as lock_file:  # a longer record is replaced
        assert lock_file.read_text() == f"pid {os.getpid()} on {socket.gethostname()}\n"
    # The same pid on another host (a run directory on a shared file system) is another process.
    monkeypatch.setattr(socket, "gethostname", lambda: "elsewhere")
    with run_directory.lock_run_directory(tmp_path / "shared"):
        monkeypatch.undo()
        with pytest.raises(run_directory.RunDirectoryLocked, match="another process"):
            with run_directory.lock_run_directory(tmp_path / "shared"):
                pass
    # A holder that has not written its record yet is unknown.
    fd = os.open(run / ".lock", os.O_RDWR | os.O_TRUNC)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(run_directory.RunDirectoryLocked, match=r"\(holder unknown\)"):
            with run_directory.lock_run_directory(run):
                pass
    finally:
        os.close(fd)


def test_a_run_directory_and_its_parents_are_created_for_the_lock(tmp_path):
    with run_directory.lock_run_directory(tmp_path / "new" / "run") as lock_file:
        assert lock_file == tmp_path / "new" / "run" / ".lock" and lock_file.exists()


def test_stale_temporaries_of_the_named_outputs_are_removed_and_nothing_else(tmp_path):
    stale = [tmp_path / ".checkpoint.pt.a1b2.tmp", tmp_path / ".results.json.c3.tmp"]
    kept = [tmp_path / "checkpoint.pt", tmp_path / ".other.json.d4.tmp", tmp_path / "x.tmp"]
    for path in stale + kept:
        path.write_text("x")
    removed = run_directory.remove_stale_temporaries(tmp_path, ["checkpoint.pt", "results.json"])
    assert sorted(removed) == sorted(stale)
    assert not any(path.exists() for path in stale) and all(path.exists() for path in kept)


def test_a_run_directory_lock_dies_with_its_process(tmp_path):
    """A process killed with SIGKILL while it holds the lock leaves no stale lock."""
    run = tmp_path / "run"
    # A child of its own interpreter (not os.fork of this multi-threaded one, which may
    # deadlock in the child): it takes the lock, says so, and waits to be killed.
    holder = (
        "import sys, time\n"
        "from dipole_torch.training.run_directory import lock_run_directory\n"
        "with lock_run_directory(sys.argv[1]):\n"
        "    print('locked', flush=True)\n"
        "    time.sleep(600)\n"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", holder, str(run)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout.readline().strip() == "locked"
        held = rf"another process \(pid {child.pid} on"
        with pytest.raises(run_directory.RunDirectoryLocked, match=held):
            with run_directory.lock_run_directory(run):
                pass
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
        child.stdout.close()
    assert (run / ".lock").exists()  # the file stays; without its holder it locks nothing
    with run_directory.lock_run_directory(run):
        pass


def test_a_run_directory_that_cannot_hold_a_lock_file_gives_a_clear_error(tmp_path):
    not_a_directory = tmp_path / "file"
    not_a_directory.write_text("x")
    with pytest.raises(CheckpointError, match=r"cannot lock run directory '.*file'"):
        with run_directory.lock_run_directory(not_a_directory):
            pass


def test_a_file_shorter_than_its_trailer_is_refused_as_such(tmp_path):
    from dipole_torch.checkpoint import MARKER

    short = tmp_path / "short.pt"
    short.write_bytes(b"PK\x03\x04" + MARKER)  # ends with the marker, too short to hold more
    with pytest.raises(CheckpointError, match="shorter than its trailer"):
        load_checkpoint(short)


def test_a_legacy_archive_with_two_records_of_one_name_is_refused(tmp_path):
    import warnings

    def saved(value):
        buffer = io.BytesIO()
        torch.save({"a": torch.tensor([value])}, buffer)
        return zipfile.ZipFile(io.BytesIO(buffer.getvalue()))

    first, second = saved(1.0), saved(2.0)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (zipfile warns of the duplicate name)
        for info in first.infolist():
            archive.writestr(info.filename, first.read(info.filename))
        name = next(i.filename for i in second.infolist() if i.filename.endswith("data/0"))
        archive.writestr(name, second.read(name))
    twice = tmp_path / "twice.pt"
    twice.write_bytes(out.getvalue())
    with pytest.raises(CheckpointError, match="two records of the same name"):
        load_checkpoint(twice)
