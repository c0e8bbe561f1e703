"""A store bounded by bytes, not by entries: what a viewer keeps of past frames must not grow with the run."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from typing import Generic, TypeVar

ValueT = TypeVar("ValueT")


class ByteBoundedStore(Generic[ValueT]):
    """Values by stamp; once their sizes add up to more than ``max_bytes`` the oldest added go first.

    A value larger than the whole budget is not kept (it would evict everything and still not fit).
    """

    def __init__(self, max_bytes: int, size_of: Callable[[ValueT], int]) -> None:
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be > 0, got {max_bytes}")
        self.max_bytes = max_bytes
        self._size_of = size_of
        self._values: OrderedDict[int, tuple[ValueT, int]] = OrderedDict()
        self.nbytes = 0

    def __len__(self) -> int:
        return len(self._values)

    def __contains__(self, stamp_ns: object) -> bool:
        return stamp_ns in self._values

    def add(self, stamp_ns: int, value: ValueT) -> bool:
        """Keep ``value`` (replacing one of the same stamp); False when it alone exceeds the budget."""
        size = self._size_of(value)
        if size > self.max_bytes:
            return False
        self.pop(stamp_ns)
        self._values[stamp_ns] = (value, size)
        self.nbytes += size
        while self.nbytes > self.max_bytes:
            _, (_, evicted) = self._values.popitem(last=False)
            self.nbytes -= evicted
        return True

    def get(self, stamp_ns: int) -> ValueT | None:
        entry = self._values.get(stamp_ns)
        return None if entry is None else entry[0]

    def pop(self, stamp_ns: int) -> ValueT | None:
        entry = self._values.pop(stamp_ns, None)
        if entry is None:
            return None
        self.nbytes -= entry[1]
        return entry[0]
