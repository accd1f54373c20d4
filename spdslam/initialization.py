"""Landmark initialisation from boxes.

Quadric-SVD. Every box edge back-projects to a plane π = Mᵀl that must be tangent to the
object: πᵀQ*π = 0 is linear in the 10 independent entries q of Q*,

    Σᵢ πᵢ² qᵢᵢ + Σᵢ<ⱼ 2πᵢπⱼ qᵢⱼ = 0,

so k ≥ 3 views (4k ≥ 12 planes for 9 degrees of freedom) give a homogeneous system A q = 0,
solved by the right singular vector of the smallest singular value; Q* is then projected to
the nearest ellipsoid (``EllipsoidFull.regularized``). For conditioning the planes are
expressed in a frame centred on the mean camera centre and scaled by the mean camera
distance from it: x = s x' + c, so π' = Tᵀπ and Q* = T Q*' Tᵀ with T = [[sI, c], [0, 1]].
"""

from __future__ import annotations

import numpy as np

from .camera import Camera, box_planes
from .ellipsoid import Ellipsoid, EllipsoidFull
from .se3 import as_pose

__all__ = ["InitializationError", "svd_initialize"]

_TRIU = np.triu_indices(4)
_OFF = (_TRIU[0] != _TRIU[1]).astype(float)


class InitializationError(ValueError):
    """The boxes do not determine an ellipsoid (too few views, degenerate geometry)."""


def svd_initialize(boxes, poses, camera: Camera, min_views: int = 3) -> Ellipsoid:
    """Quadric-SVD initial ellipsoid from ``boxes`` (k, 4) seen from camera-to-world ``poses``.

    Raises ``InitializationError`` with the reason when it cannot: fewer than ``min_views``
    boxes, a null space that is not one-dimensional, or a solution that is not an ellipsoid
    in front of the cameras.
    """
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
    poses = [as_pose(T) for T in poses]
    if len(poses) != len(boxes):
        raise ValueError(f"{len(boxes)} boxes but {len(poses)} poses")
    if len(boxes) < max(min_views, 3):
        raise InitializationError(f"needs at least {max(min_views, 3)} views, got {len(boxes)}")
    planes = np.concatenate([np.asarray(box_planes(b, T, camera)) for b, T in zip(boxes, poses)])
    centres = np.array([np.asarray(T.translation()) for T in poses])
    c = centres.mean(axis=0)
    s = max(float(np.mean(np.linalg.norm(centres - c, axis=1))), 1e-6)
    T = np.eye(4)
    T[:3, :3] *= s
    T[:3, 3] = c
    p = planes @ T  # π' = Tᵀπ, one per row
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    A = p[:, _TRIU[0]] * p[:, _TRIU[1]] * (1.0 + _OFF)
    _, sv, Vt = np.linalg.svd(A)
    if sv[-2] <= 1e-9 * sv[0]:
        raise InitializationError(
            "the box planes do not determine the quadric (null space of dimension > 1): "
            "views too similar or too few"
        )
    Q_local = np.zeros((4, 4))
    Q_local[_TRIU] = Vt[-1]
    Q_local = Q_local + np.triu(Q_local, 1).T
    Q = T @ Q_local @ T.T
    if abs(Q[3, 3]) <= 1e-12 * np.max(np.abs(Q)):
        raise InitializationError("the fitted quadric has no finite centre (Q*₃₃ ≈ 0)")
    Q = Q / -Q[3, 3]
    e = EllipsoidFull.from_dual_quadric(Q).regularized().to_ellipsoid()
    if not np.all(np.isfinite(np.asarray(e.P))) or not np.all(np.isfinite(np.asarray(e.center))):
        raise InitializationError("the fitted quadric is not finite")
    return e
