"""SIGTERM and SIGINT in a training run: finish the iteration, checkpoint, say how to resume."""

from __future__ import annotations

import os
import signal
import sys

__all__ = ["StopRequest"]


class StopRequest:
    """A context in which SIGTERM / SIGINT ask the loop to stop after this iteration (the loop
    then writes a checkpoint and exits with status 128 + the signal number: 143, 130).

    A second signal stops at once, with the same status and no traceback: every file on disk
    is then the last complete one, since every write is atomic.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    def __bool__(self) -> bool:
        """Whether a stop was asked."""
        return self.signum is not None

    @property
    def name(self) -> str:
        """The signal's name (``SIGTERM``), once one came."""
        return signal.Signals(self.signum).name if self.signum is not None else ""

    def __call__(self, signum: int, frame) -> None:
        # os.write, not print: the handler may interrupt a print (the progress bar's) to the
        # same stream.
        name = signal.Signals(signum).name
        if self.signum is not None:
            os.write(sys.stderr.fileno(), f"\nsecond {name}: stopping now\n".encode())
            sys.stdout.flush()
            os._exit(128 + signum)
        self.signum = signum
        message = (
            f"\n{name} received: finishing this iteration, then writing a checkpoint (send it "
            "again to stop at once)\n"
        )
        os.write(sys.stderr.fileno(), message.encode())

    def __enter__(self) -> StopRequest:
        for signum in (signal.SIGTERM, signal.SIGINT):
            try:
                self._previous[signum] = signal.signal(signum, self)
            except ValueError:  # not the main thread (e.g. a threaded Hydra launcher)
                pass
        return self

    def __exit__(self, *exc) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
