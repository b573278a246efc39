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
from typing import Any

from torch import Tensor

__all__ = ["Memo"]


class Memo:
    """Values keyed by name, each valid while its source tensors are the same unmodified
    objects. A value is a tensor, a tuple of tensors, or an immutable host value (a tuple of
    numbers). Inference tensors have no version counter: their values are not memoised."""

    def __init__(self):
        # key -> (sources, their versions, value, the versions of its tensors)
        self._entries: dict[Hashable, tuple[tuple[Tensor, ...], tuple[int, ...], Any, tuple]] = {}

    def get(self, key: Hashable, sources: tuple[Tensor, ...], compute: Callable[[], Any]) -> Any:
        """``compute()``, or its memoised value while ``sources`` are unchanged. Not to be
        written into (a write only costs a recomputation)."""
        try:
            versions = tuple(source._version for source in sources)
        except RuntimeError:  # an inference tensor
            return compute()
        hit = self._entries.get(key)
        if (
            hit is not None
            and hit[1] == versions
            and all(old is new for old, new in zip(hit[0], sources, strict=True))
            and _versions(hit[2]) == hit[3]
        ):
            return hit[2]
        value = compute()
        try:
            self._entries[key] = (sources, versions, value, _versions(value))
        except RuntimeError:  # computed under inference mode
            self._entries.pop(key, None)
        return value


def _versions(value: Any) -> tuple[int, ...]:
    """The version counters of the tensors in ``value`` (a tensor or a tuple)."""
    if isinstance(value, Tensor):
        return (value._version,)
    if isinstance(value, tuple):
        return tuple(item._version for item in value if isinstance(item, Tensor))
    return ()
