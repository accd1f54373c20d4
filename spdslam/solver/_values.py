"""Values: the assignment key → variable value that the solver reads and returns."""

from __future__ import annotations

from collections.abc import MutableMapping
from typing import Any, Hashable, Iterator

from ..geometry import manifold

__all__ = ["Values"]


def _check_type(key: Hashable, value: Any) -> None:
    if not manifold.is_registered(type(value)):
        try:
            manifold.ops(value)
        except TypeError as e:
            raise TypeError(f"value for key {key!r}: {e}") from None


class Values(MutableMapping):
    """A dict key → value; every value is an instance of a registered variable type
    (``jaxlie.SE3``, ``Ellipsoid``, ``EllipsoidRTS``, ``EllipsoidFull``, …, see
    ``spdslam.geometry.manifold``). Keys are any hashables, usually ``X(i)`` / ``L(j)``
    symbols. Insertion order is kept.
    """

    __slots__ = ("_data",)

    def __init__(self, items: Any = None, /, **kwargs: Any):
        self._data: dict[Hashable, Any] = {}
        if items is not None:
            self.update(items)
        if kwargs:
            self.update(kwargs)

    def __getitem__(self, key: Hashable) -> Any:
        try:
            return self._data[key]
        except KeyError:
            raise KeyError(f"no value for key {key!r}") from None

    def __setitem__(self, key: Hashable, value: Any) -> None:
        _check_type(key, value)
        self._data[key] = value

    def __delitem__(self, key: Hashable) -> None:
        del self._data[key]

    def __iter__(self) -> Iterator[Hashable]:
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def __contains__(self, key: object) -> bool:
        return key in self._data

    def insert(self, key: Hashable, value: Any) -> None:
        """Add a new key; raises ``KeyError`` if it already has a value (gtsam semantics)."""
        if key in self._data:
            raise KeyError(f"key {key!r} already has a value")
        self[key] = value

    def at(self, key: Hashable) -> Any:
        return self[key]

    def copy(self) -> "Values":
        out = Values()
        out._data = dict(self._data)
        return out

    def __repr__(self) -> str:
        kinds: dict[str, int] = {}
        for v in self._data.values():
            kinds[type(v).__name__] = kinds.get(type(v).__name__, 0) + 1
        desc = ", ".join(f"{n} {k}" for k, n in kinds.items())
        return f"Values({len(self)} values: {desc})"
