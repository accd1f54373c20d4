"""What every stage of a run reads of a sequence, computed once: the trajectory as SE(3),
the up direction and support planes, the class priors and each class's silhouette model."""

from __future__ import annotations

from dataclasses import dataclass

import jaxlie
import numpy as np

from ..geometry.se3 import from_tum
from ..io import Sequence, class_prior
from ._methods import Method

__all__ = ["SequenceContext", "as_context", "object_shape"]


@dataclass(frozen=True, eq=False)
class SequenceContext:
    """A sequence prepared for mapping.

    ``wxyz_xyz`` (F, 7): the trajectory T_wc as jaxlie's SE(3) parameters, converted once from
    the TUM rows; ``poses``: one ``jaxlie.SE3`` per frame (views of those rows); ``up`` (unit,
    or None) and ``planes`` (support planes with unit normals facing up, or None): the
    priors' one rule (``Priors.up_and_planes``).
    """

    seq: Sequence
    wxyz_xyz: np.ndarray
    poses: list
    up: np.ndarray | None
    planes: np.ndarray | None

    @classmethod
    def of(cls, seq: Sequence) -> "SequenceContext":
        rows = np.asarray(from_tum(np.asarray(seq.poses_tum)).wxyz_xyz)
        up, planes = (None, None) if seq.priors is None else seq.priors.up_and_planes()
        return cls(seq, rows, [jaxlie.SE3(r) for r in rows], up, planes)

    @property
    def camera(self):
        return self.seq.camera

    @property
    def priors(self):
        return self.seq.priors

    def trajectory(self, frames=None) -> jaxlie.SE3:
        """The poses of ``frames`` (default all) as one batched ``jaxlie.SE3``."""
        return jaxlie.SE3(self.wxyz_xyz if frames is None else self.wxyz_xyz[frames])

    def class_prior(self, label):
        """The ``ClassPrior`` of a label, or None."""
        return class_prior(self.priors, label)

    def support_planes(self) -> list:
        """The priors' support planes as given (rows [a, b, c, d]); [] without priors."""
        return [] if self.priors is None else list(self.priors.support_planes)


def as_context(seq) -> SequenceContext:
    """A ``SequenceContext`` as it is, or one made from a ``Sequence``."""
    return seq if isinstance(seq, SequenceContext) else SequenceContext.of(seq)


def object_shape(method: Method, priors, label) -> str:
    """The silhouette model of an object of class ``label``: the method's, or with
    ``object_shape="priors"`` its class prior's shape ("ellipsoid" without a prior)."""
    if method.object_shape != "priors":
        return method.object_shape
    cp = class_prior(priors, label)
    return "ellipsoid" if cp is None else getattr(cp, "shape", "ellipsoid")
