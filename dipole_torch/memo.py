"""A memo of values computed from tensors, kept while those tensors stay unchanged.

An iteration asks for the same per-policy quantities several times (each policy's best
return, the factors of its exploration covariance) from tensors that did not change in
between. The object that owns the tensors keeps a ``Memo``: a value is recomputed only
when one of its source tensors was replaced (identity) or written into (its version
counter), or when the value itself was written into, so a hit returns exactly what a fresh
computation would.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from operator import is_
from typing import Any

from torch import Tensor

__all__ = ["Memo"]


class Memo:
    """Values keyed by name, each valid while its source tensors are the same unmodified
    objects. A value is a tensor, a tuple of tensors, or an immutable host value (a tuple of
    numbers). Inference tensors have no version counter: their values are not memoised."""

    def __init__(self):
        # key -> (sources, the tensors watched: sources and the value's, their versions, value)
        self._entries: dict[Hashable, tuple[tuple[Tensor, ...], tuple, list[int], Any]] = {}

    def get(self, key: Hashable, sources: tuple[Tensor, ...], compute: Callable[[], Any]) -> Any:
        """``compute()``, or its memoised value while ``sources`` are unchanged. Not to be
        written into (a write only costs a recomputation)."""
        hit = self._entries.get(key)
        if hit is not None:
            old, watched, versions, value = hit
            # (A hit costs a few attribute reads: it is asked for several times an iteration.)
            if all(map(is_, old, sources)) and [t._version for t in watched] == versions:
                return value
        value = compute()
        watched = (*sources, *_tensors(value))
        try:
            versions = [t._version for t in watched]
        except RuntimeError:  # an inference tensor
            self._entries.pop(key, None)
            return value
        self._entries[key] = (sources, watched, versions, value)
        return value


def _tensors(value: Any) -> tuple[Tensor, ...]:
    """The tensors of ``value`` (a tensor, or a tuple) whose writes the memo watches."""
    if isinstance(value, Tensor):
        return (value,)
    if isinstance(value, tuple):
        return tuple(item for item in value if isinstance(item, Tensor))
    return ()
