"""The nonlinear factor graph: a list of ``Factor`` objects."""

from __future__ import annotations

from typing import Any, Hashable, Iterable, Iterator

from ..factors import Factor

__all__ = ["NonlinearFactorGraph"]


class NonlinearFactorGraph:
    """A list of factors. Its cost is F(x) = Σᵢ ½ ρᵢ(‖Wᵢ rᵢ(x)‖²), gtsam's ``graph.error``."""

    def __init__(self, factors: Iterable[Factor] = ()):
        self._factors: list[Factor] = []
        self.extend(factors)

    def add(self, factor: Factor) -> None:
        if not isinstance(factor, Factor):
            raise TypeError(f"expected a Factor, got {type(factor).__name__}")
        self._factors.append(factor)

    def extend(self, factors: Iterable[Factor]) -> None:
        for f in factors:
            self.add(f)

    def __len__(self) -> int:
        return len(self._factors)

    def __iter__(self) -> Iterator[Factor]:
        return iter(self._factors)

    def __getitem__(self, i):
        return self._factors[i]

    @property
    def factors(self) -> list[Factor]:
        return self._factors

    def keys(self) -> list[Hashable]:
        """The keys the factors touch, in order of first appearance."""
        seen: dict[Hashable, None] = {}
        for f in self._factors:
            for k in f.keys:
                seen.setdefault(k, None)
        return list(seen)

    def error(self, values: Any) -> float:
        """F(x) = Σ ½ ρ(‖W r‖²) at ``values`` (vectorised per factor type)."""
        from ._problem import Problem

        if not self._factors:
            return 0.0
        return Problem(self, values, check_free=False).cost()

    def __repr__(self) -> str:
        kinds: dict[str, int] = {}
        for f in self._factors:
            kinds[f.kind] = kinds.get(f.kind, 0) + 1
        desc = ", ".join(f"{n} {k}" for k, n in kinds.items())
        return f"NonlinearFactorGraph({len(self)} factors: {desc})"
