"""What every stage of a run reads of a sequence, computed once: the trajectory as SE(3),
the up direction and support planes, the class priors and each class's silhouette model."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import jaxlie
import numpy as np

from ..geometry.se3 import from_tum, quat_to_matrix
from ..io import Sequence, class_prior
from ._methods import Method

__all__ = ["SequenceContext", "as_context", "camera_axes_of", "object_shape"]


@dataclass(frozen=True, eq=False)
class SequenceContext:
    """A sequence prepared for mapping.

    ``wxyz_xyz`` (F, 7): the trajectory T_wc as jaxlie's SE(3) parameters, converted once from
    the TUM rows; ``poses``: one ``jaxlie.SE3`` per frame (views of those rows); ``up`` (unit,
    or None) and ``planes`` (support planes with unit normals facing up, or None): the
    priors' one rule (``Priors.up_and_planes``); ``box_factors``: the store of the box
    factors built on this context.
    """

    seq: Sequence
    wxyz_xyz: np.ndarray
    poses: list
    up: np.ndarray | None
    planes: np.ndarray | None
    #: the box factors made of each track in this context (``build_graph``), so that the
    #: builds of one run make a track's once
    box_factors: dict = field(default_factory=dict, repr=False)

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

    @cached_property
    def camera_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_wc (F, 3, 3), camera centres (F, 3)) of the trajectory, NumPy, computed once."""
        return camera_axes_of(self.wxyz_xyz)

    def trajectory(self, frames=None) -> jaxlie.SE3:
        """The poses of ``frames`` (default all) as one batched ``jaxlie.SE3``."""
        return jaxlie.SE3(self.wxyz_xyz if frames is None else self.wxyz_xyz[frames])  # type: ignore[arg-type]

    def class_prior(self, label):
        """The ``ClassPrior`` of a label, or None."""
        return class_prior(self.priors, label)

    def support_planes(self) -> list:
        """The priors' support planes as given (rows [a, b, c, d]); [] without priors."""
        return [] if self.priors is None else list(self.priors.support_planes)


def camera_axes_of(wxyz_xyz) -> tuple[np.ndarray, np.ndarray]:
    """(R_wc (n, 3, 3), centres (n, 3)) of jaxlie SE(3) rows [qw qx qy qz x y z] (NumPy)."""
    rows = np.asarray(wxyz_xyz, dtype=float).reshape(-1, 7)
    return quat_to_matrix(rows[:, [1, 2, 3, 0]]).reshape(-1, 3, 3), rows[:, 4:]


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
