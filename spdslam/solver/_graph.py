"""The nonlinear factor graph: factors (``Factor``) and batches of factors (``FactorBatch``)."""

from __future__ import annotations

from typing import Any, Hashable, Iterable, Iterator

from ..factors import Factor, FactorBatch

__all__ = ["NonlinearFactorGraph"]


class NonlinearFactorGraph:
    """Factors. Its cost is F(x) = Σᵢ ½ ρᵢ(‖Wᵢ rᵢ(x)‖²), gtsam's ``graph.error``.

    ``add`` takes one factor or a ``FactorBatch`` (n factors of one type as columns), which
    stays one entry (``entries``) for the solver to lay out as arrays; ``len``, iteration
    and indexing count and give the factors one by one either way.
    """

    def __init__(self, factors: Iterable[Factor | FactorBatch] = ()):
        self._entries: list[Factor | FactorBatch] = []
        self._len = 0
        self.extend(factors)

    def add(self, factor: Factor | FactorBatch) -> None:
        if not isinstance(factor, (Factor, FactorBatch)):
            raise TypeError(f"expected a Factor or FactorBatch, got {type(factor).__name__}")
        self._entries.append(factor)
        self._len += len(factor) if isinstance(factor, FactorBatch) else 1

    def extend(self, factors: Iterable[Factor | FactorBatch]) -> None:
        if isinstance(factors, NonlinearFactorGraph):
            factors = factors.entries()
        for f in factors:
            self.add(f)

    def entries(self) -> list[Factor | FactorBatch]:
        """The factors and batches as added."""
        return list(self._entries)

    def __len__(self) -> int:
        return self._len

    def __iter__(self) -> Iterator[Factor]:
        for e in self._entries:
            if isinstance(e, FactorBatch):
                yield from e
            else:
                yield e

    def __getitem__(self, i):
        return self.factors[i]

    @property
    def factors(self) -> list[Factor]:
        """The factors one by one (a batch's made on the way)."""
        return list(self)

    def keys(self) -> list[Hashable]:
        """The keys the factors touch, in order of first appearance."""
        seen: dict[Hashable, None] = {}
        for e in self._entries:
            if isinstance(e, FactorBatch):
                for row in zip(*e.key_columns):
                    for k in row:
                        seen.setdefault(k, None)
            else:
                for k in e.keys:
                    seen.setdefault(k, None)
        return list(seen)

    def error(self, values: Any) -> float:
        """F(x) = Σ ½ ρ(‖W r‖²) at ``values`` (vectorised per factor type)."""
        from ._problem import Problem

        if not self._len:
            return 0.0
        return Problem(self, values, check_free=False).cost()

    def __repr__(self) -> str:
        kinds: dict[str, int] = {}
        for e in self._entries:
            kinds[e.kind] = kinds.get(e.kind, 0) + (len(e) if isinstance(e, FactorBatch) else 1)
        desc = ", ".join(f"{n} {k}" for k, n in kinds.items())
        return f"NonlinearFactorGraph({len(self)} factors: {desc})"
