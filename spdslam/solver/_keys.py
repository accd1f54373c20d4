"""Key symbols: a letter and an index, as gtsam's ``symbol_shorthand``.

``X(i)`` is the key of pose i, ``L(j)`` of landmark j. A symbol is a named tuple, so it is
equal to (and hashes as) the plain tuple ``("x", i)``; any hashable is a valid key.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["Symbol", "X", "L"]


class Symbol(NamedTuple):
    """A key: ``chr`` (one letter) and ``index``; printed as ``x3``."""

    chr: str
    index: int  # type: ignore[assignment]  # shadows tuple.index (public field name)

    def __repr__(self) -> str:
        return f"{self.chr}{self.index}"


def X(i: int) -> Symbol:
    """The key of pose ``i``."""
    return Symbol("x", int(i))


def L(j: int) -> Symbol:
    """The key of landmark ``j``."""
    return Symbol("l", int(j))
