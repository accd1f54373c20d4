"""Poses refined by the boxes, when objects the refinement did not see say that it helps.

On a trajectory without a bound on each pose the boxes do not move the poses by default
(docs/drift.md): a real detector's boxes err alike over hundreds of frames, and thousands of
them pull each pose where the model, not the world, wants it. Boxes whose errors are
independent (each box its own noise) do take the drift out. Which of the two a recording has
is measured here, not assumed, by a cross-validation between objects
(``validate_refinement``):

1. the labels split into two halves A and B of about as many boxes (``label_halves``): a
   detector's bias belongs to an object and a viewpoint, the drift to the camera, so the
   halves share the drift and not the biases;
2. the poses refined by A's boxes alone (the joint optimisation from the current poses,
   each pose within the odometry's walk, ``check_trajectory``);
3. B's objects mapped with the poses held at the current trajectory, and held at A's
   refined one: B's box cost per box (``box_cost_per_box``) on each, their ratio;
4. the same with A and B swapped.

The refinement is accepted when both ratios are at most ``REFINE_MAX_RATIO``: each half's
boxes fit the poses the other half refined clearly better than the poses it was given, a
correction they took no part in. The run then optimises the poses with every box, from the
current poses, its trajectory checked against the odometry's walk from the input; and tries
again from the refined poses, up to ``REFINE_MAX_ROUNDS`` rounds, until the halves refuse (a
joint optimisation from far away stops short of the truth; from nearer it goes further).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

__all__ = ["REFINE_MAX_RATIO", "REFINE_MAX_ROUNDS", "Refinement", "box_cost_per_box", "label_halves",
           "validate_refinement"]

#: The largest ratio of a half's box cost per box on the poses the other half refined to its
#: cost on the poses given, for the refinement to be accepted (module docstring).
REFINE_MAX_RATIO = 0.8
#: The most rounds of the refinement, each from the poses the last one refined.
REFINE_MAX_ROUNDS = 4


def label_halves(labels) -> tuple[frozenset, frozenset] | None:
    """The labels of ``labels`` (one per box) split into two halves of about as many boxes
    each (the most frequent label first, each to the half with fewer boxes so far; ties by
    name); None with fewer than two labels."""
    counts = Counter(str(x) for x in labels)
    if len(counts) < 2:
        return None
    halves: tuple[set, set] = (set(), set())
    sizes = [0, 0]
    for label, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])):
        k = 0 if sizes[0] <= sizes[1] else 1
        halves[k].add(label)
        sizes[k] += n
    return frozenset(halves[0]), frozenset(halves[1])


def box_cost_per_box(result) -> float:
    """A mapping result's box cost (the factor kinds ``*_box`` of ``MapResult.costs``) over
    the boxes its objects were estimated from (``MapObject.observed_by``); NaN without any."""
    boxes = sum(int(n) for o in result.objects for _, n in (o.observed_by or ()))
    cost = sum(float(v) for k, v in result.costs.items() if k.endswith("_box"))
    return cost / boxes if boxes else float("nan")


@dataclass(frozen=True)
class Refinement:
    """The cross-validation's answer (module docstring): the two halves' labels, each
    half's ratio (its boxes on the other half's refined poses over the poses given, those
    reached), whether the refinement is accepted, why not, and its round (1 from the input
    or the loops' poses)."""

    halves: tuple = ()
    ratios: tuple = ()
    accepted: bool = False
    reason: str = ""
    details: list = field(default_factory=list)
    round: int = 1

    def note(self) -> str:
        if self.accepted:
            return (f"poses refined by the boxes, round {self.round}: each half of the labels' boxes fits the "
                    f"poses the other half refined at {' and '.join(f'{100 * r:.0f} %' for r in self.ratios)} of "
                    f"its cost on the poses given (the limit {100 * REFINE_MAX_RATIO:.0f} %)")
        return f"poses not refined by the boxes, round {self.round}: {self.reason}"

    def as_dict(self) -> dict:
        return {"round": self.round, "halves": [sorted(h) for h in self.halves],
                "ratios": [float(r) for r in self.ratios], "accepted": self.accepted, "reason": self.reason,
                "limit": REFINE_MAX_RATIO, "details": list(self.details)}


def validate_refinement(labels, refine: Callable, held_cost: Callable) -> Refinement:
    """The cross-validation of the module docstring over the boxes' ``labels``:
    ``refine(half) -> poses | str`` the poses the boxes of the labels ``half`` refine from the
    current ones (or why they did not move them), ``held_cost(half, poses) -> float`` the
    box cost per box of the labels ``half`` with the poses held at ``poses`` (None: the
    current ones; NaN when they could not be mapped)."""
    halves = label_halves(labels)
    if halves is None:
        return Refinement(reason="one label only: no half of the objects to check the other with")
    ratios: list = []
    details: list = []
    for train, test in (halves, halves[::-1]):
        poses = refine(train)
        name = ", ".join(sorted(train))
        if isinstance(poses, str):
            return Refinement(halves, tuple(ratios), reason=f"the boxes of {name} did not move the poses "
                                                            f"({poses})", details=details)
        given, moved = held_cost(test, None), held_cost(test, poses)
        details.append({"refined_by": sorted(train), "checked_by": sorted(test), "cost_per_box_given": given,
                        "cost_per_box_refined": moved})
        if not (np.isfinite(given) and np.isfinite(moved) and given > 0):
            return Refinement(halves, tuple(ratios), details=details,
                              reason=f"the objects of {', '.join(sorted(test))} were not mapped on both the poses "
                                     f"given and those {name} refined: nothing to judge them by")
        ratio = moved / given
        ratios.append(ratio)
        if not ratio <= REFINE_MAX_RATIO:
            return Refinement(halves, tuple(ratios), details=details,
                              reason=f"the boxes of {', '.join(sorted(test))} fit the poses {name} refined at "
                                     f"{100 * ratio:.0f} % of their cost on the poses given (the limit "
                                     f"{100 * REFINE_MAX_RATIO:.0f} %)")
    return Refinement(halves, tuple(ratios), accepted=True, details=details)
