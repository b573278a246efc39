"""``argparse`` types for the benchmarks' options, so that a bad value is an argparse error
naming the option (``argument --seeds: must be a positive integer, got '0'``) rather than an
empty report written over a figure's JSON, or a traceback from deep inside a run."""

from __future__ import annotations

import argparse
from pathlib import Path


def positive_int(text: str) -> int:
    """An integer ≥ 1: a count of seeds, runs, trials, dimensions, repeats."""
    return _int_at_least(text, 1, "a positive integer")


def at_least(low: int):
    """An integer ≥ ``low``: ``at_least(2)`` for a count of points a covariance is taken of."""

    def parse(text: str) -> int:
        return _int_at_least(text, low, f"an integer >= {low}")

    parse.__name__ = f"at_least_{low}"
    return parse


def positive_even_int(text: str) -> int:
    """An even integer ≥ 2: ``--ks``, the landscapes' optima (half bumps, half sharp peaks)."""
    value = _int_at_least(text, 2, "an even integer >= 2")
    if value % 2:
        raise argparse.ArgumentTypeError(f"must be an even integer >= 2, got {text!r}")
    return value


def nonnegative_int(text: str) -> int:
    """An integer ≥ 0: ``--workers``, where 0 means this process."""
    return _int_at_least(text, 0, "an integer >= 0")


def positive_float(text: str) -> float:
    """A finite float > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}") from None
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return value


def _int_at_least(text: str, low: int, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return value


def nonnegative_float(text: str) -> float:
    """A finite float ≥ 0 (a noise level, where 0 is none)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text!r}") from None
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text!r}")
    return value


def device(text: str) -> str:
    """A torch device this machine has (``cpu``, ``cuda``, ``cuda:1``), kept as written."""
    import torch

    try:
        kind = torch.device(text).type
    except RuntimeError:
        raise argparse.ArgumentTypeError(f"not a torch device: {text!r}") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise argparse.ArgumentTypeError(f"{text!r}: torch {torch.__version__} sees no CUDA device")
    if kind == "mps" and not torch.backends.mps.is_available():
        raise argparse.ArgumentTypeError(f"{text!r}: torch sees no MPS device")
    return text


def report_path(text: str) -> Path:
    """A file to write a JSON report to: not a directory, and no file on its way (its missing
    directories are made when it is written), so that a run does not end failing to write."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a directory, not a file")
    for parent in path.parents:
        if parent.exists() and not parent.is_dir():
            raise argparse.ArgumentTypeError(f"{text!r}: {str(parent)!r} is not a directory")
    return path


def output_dir(text: str) -> Path:
    """A directory to write figures and JSON to (made if missing): not an existing file, and
    no file on its way."""
    path = Path(text)
    for at in (path, *path.parents):
        if at.exists() and not at.is_dir():
            raise argparse.ArgumentTypeError(f"{text!r}: {str(at)!r} is not a directory")
    return path


class Distinct(argparse.Action):
    """A ``nargs="+"`` option's values, each once in the order given: ``--dims 2 2`` ran every
    case twice and counted both (``8/8`` runs of one seed)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, list(dict.fromkeys(values)))
