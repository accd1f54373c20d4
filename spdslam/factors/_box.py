"""Box factors: a detected box against a landmark seen from a camera pose, for any landmark
parameterisation (SPD, RTS or Full).

Notation: landmark (P, t) with Q* = [[P − ttᵀ, −t], [−tᵀ, −1]]; camera pose T_wc
(camera-to-world); box b = [u_min, v_min, u_max, v_max] in pixels; planes π = [n; d] with
‖n‖ = 1, so π·[x; 1] is a signed distance. For such a plane

    πᵀ Q* π = nᵀPn − (n·t + d)²,

the squared support distance minus the squared centre distance: zero iff π is tangent.

Box-like objects are boxed by the silhouette of the circumscribed cuboid (axes R, half-extents
s): the cuboid box factors use its 8 projected corners, or its support function
h(n) = n·t + Σᵢ sᵢ|n·Rᵢ| for the edge planes.

Truncation: every box factor takes a (4,) 0/1 mask ``keep`` of the edges that bound the
object (``geometry.truncation_mask``: edges farther than ``truncation_margin`` px from the
image border); the residual of a dropped edge is 0. The factors carry ``keep`` as
measurement data only when a margin is given, so factors built alike batch together.
"""

from __future__ import annotations

from typing import Any, Callable, ClassVar

import jax.numpy as jnp
import jaxlie
import numpy as np

from ..geometry import (
    Camera,
    box_planes,
    cuboid_half_axes,
    cuboid_in_front,
    dual_quadric,
    frame_pose,
    in_front,
    interpolated_frame,
    project_box,
    project_cuboid_box,
    truncation_mask,
)
from ._base import Factor, FactorBatch, RobustKernel, Sigma, diagonal_sqrt_information

__all__ = [
    "DEFAULT_TRUNCATION_MARGIN",
    "InverseBoxFactor",
    "SemiInverseBoxFactor",
    "InverseCuboidBoxFactor",
    "SemiInverseCuboidBoxFactor",
    "FrameBoxFactor",
    "DriftBoxFactor",
    "inverse_box_residual",
    "frame_box_residual",
    "drift_box_residual",
    "semi_inverse_box_residual",
    "inverse_cuboid_box_residual",
    "semi_inverse_cuboid_box_residual",
    "box_visible",
    "cuboid_box_visible",
]

#: A detected box edge within this many pixels of the image border is taken as truncated.
DEFAULT_TRUNCATION_MARGIN = 5.0


def _masked(r, keep):
    """r ∘ keep (keep None: every edge)."""
    return r if keep is None else r * keep


def inverse_box_residual(T_wc, landmark, box, camera: Camera, keep=None):
    """Inverse model: (the closed-form box of C* = M Q* Mᵀ minus the detected box) ∘ keep
    (px, 4)."""
    return _masked(project_box(landmark, T_wc, camera) - box, keep)


def semi_inverse_box_residual(T_wc, landmark, box, camera: Camera, keep=None):
    """Semi-inverse model: πᵢᵀ Q* πᵢ · keepᵢ for the 4 edge planes πᵢ = Mᵀ lᵢ, each with
    unit normal.

    One residual per edge (m²): the paper's single sum Σᵢ πᵢᵀQ*πᵢ lets edges that are too
    tight cancel edges that are too loose.
    """
    planes = box_planes(box, T_wc, camera)
    Q = dual_quadric(landmark)
    return _masked(jnp.einsum("ki,ij,kj->k", planes, Q, planes), keep)


def frame_box_residual(frame, landmark, T_wc, box, camera: Camera, keep=None):
    """Inverse model with the camera in another frame: the box of the landmark seen from
    ``geometry.frame_pose(frame, T_wc)`` minus the detected box, ∘ keep (px, 4). ``frame``
    (``jaxlie.SE3`` or ``geometry.Sim3``) moves the recording's frame, where the camera pose
    T_wc was given, into the landmark's."""
    return inverse_box_residual(frame_pose(frame, T_wc), landmark, box, camera, keep)


def frame_box_visible(frame, landmark, T_wc, box, camera: Camera, keep=None, min_depth: float = 1e-3):
    """Validity of a frame box factor: the ellipsoid in front of the moved camera."""
    return in_front(landmark, frame_pose(frame, T_wc), min_depth)


def drift_box_residual(knot_a, knot_b, landmark, T_wc, weight, box, camera: Camera, keep=None):
    """Inverse model with a drifting odometry: the box of the landmark seen from the pose
    K(t) T_wc, where T_wc is the odometry's pose at time t and K(t) =
    ``geometry.interpolated_frame(knot_a, knot_b, weight)`` its drift correction between the
    knots around t, minus the detected box, ∘ keep (px, 4)."""
    return inverse_box_residual(interpolated_frame(knot_a, knot_b, weight) @ T_wc, landmark, box, camera, keep)


def drift_box_visible(knot_a, knot_b, landmark, T_wc, weight, box, camera: Camera, keep=None,
                      min_depth: float = 1e-3):
    """Validity of a drift box factor: the ellipsoid in front of the corrected camera."""
    return in_front(landmark, interpolated_frame(knot_a, knot_b, weight) @ T_wc, min_depth)


def box_visible(T_wc, landmark, box, camera: Camera, keep=None, min_depth: float = 1e-3):
    """Validity of a box factor: the whole ellipsoid is in front of the camera
    (which also rules out the camera being inside it)."""
    return in_front(landmark, T_wc, min_depth)


def inverse_cuboid_box_residual(T_wc, landmark, box, camera: Camera, keep=None):
    """Inverse cuboid model: (the box of the 8 projected corners t + Σᵢ ±sᵢRᵢ of the
    circumscribed cuboid minus the detected box) ∘ keep (px, 4)."""
    return _masked(project_cuboid_box(landmark, T_wc, camera) - box, keep)


def semi_inverse_cuboid_box_residual(T_wc, landmark, box, camera: Camera, keep=None):
    """Semi-inverse cuboid model, per edge plane π = [n; d] (unit n), in m:

        rᵢ = (Σⱼ sⱼ|n·Rⱼ| − |n·t + d|) · keepᵢ,

    the cuboid's half-width along n (its support function minus n·t) minus the centre's
    distance to the plane: zero iff the plane touches the cuboid with the cuboid on one
    side, > 0 where it cuts it (box too tight), < 0 where it misses it (box too loose).
    """
    planes = box_planes(box, T_wc, camera)
    H, t = cuboid_half_axes(landmark)
    half_width = jnp.sum(jnp.abs(planes[:, :3] @ H), axis=1)
    return _masked(half_width - jnp.abs(planes[:, :3] @ t + planes[:, 3]), keep)


def cuboid_box_visible(T_wc, landmark, box, camera: Camera, keep=None, min_depth: float = 1e-3):
    """Validity of a cuboid box factor: all 8 corners of the circumscribed cuboid are in
    front of the camera (depth > ``min_depth``)."""
    return cuboid_in_front(landmark, T_wc, min_depth)


def _check_boxes(boxes: np.ndarray, camera: Camera) -> None:
    """``_box_data``'s checks of n boxes (n, 4) at once (``many``)."""
    bad = ~(np.all(np.isfinite(boxes), axis=1) & (boxes[:, 2] >= boxes[:, 0]) & (boxes[:, 3] >= boxes[:, 1]))
    if bad.any():
        b = boxes[int(np.flatnonzero(bad)[0])]
        raise ValueError(f"box must be finite [u_min, v_min, u_max, v_max], got {b.tolist()}")
    if not isinstance(camera, Camera):
        raise TypeError("camera must be a spdslam Camera")


def _box_data(box, camera: Camera, truncation_margin: float | None) -> tuple:
    """A box factor's data, checked: (box, camera) and, with a ``truncation_margin`` (px), the
    box's truncation mask."""
    box = np.asarray(box, dtype=float)
    if box.shape != (4,) or not np.all(np.isfinite(box)) or box[2] < box[0] or box[3] < box[1]:
        raise ValueError(f"box must be finite [u_min, v_min, u_max, v_max], got {box.tolist()}")
    if not isinstance(camera, Camera):
        raise TypeError("camera must be a spdslam Camera")
    if truncation_margin is None:
        return (box, camera)
    if not (np.isfinite(truncation_margin) and truncation_margin >= 0):
        raise ValueError(f"truncation_margin must be finite and ≥ 0 px, got {truncation_margin!r}")
    return (box, camera, np.asarray(truncation_mask(box, camera, float(truncation_margin))))


class _BoxFactor(Factor):
    """A detected box [u_min, v_min, u_max, v_max] (px) of a landmark seen from a pose.

    ``truncation_margin`` (px, e.g. ``DEFAULT_TRUNCATION_MARGIN``): edges within it of the
    image border carry no bound; None (default) keeps every edge and the data (box, camera).
    """

    variables = ("pose", "landmark")
    dim = 4
    group = "box"
    valid: ClassVar[Callable[..., Any] | None] = staticmethod(box_visible)

    def __init__(self, pose_key, landmark_key, box, camera: Camera, *,
                 truncation_margin: float | None = None, **noise):
        super().__init__((pose_key, landmark_key), _box_data(box, camera, truncation_margin), **noise)

    @classmethod
    def many(cls, pose_keys, landmark_keys, boxes, camera: Camera, *, sigma: Any = None,
             robust: RobustKernel | None = None, truncation_margin: float | None = None) -> FactorBatch:
        """The factors ``cls(pose_keys[i], landmark_keys[i], boxes[i], camera, sigma=sigma[i],
        …)`` of n boxes (n, 4) as one ``FactorBatch``, checked and built as arrays: the same
        factors as one by one (``sigma``: a scalar, 4 values or (n, 4); None: the type's
        default). ``landmark_keys``: a list, or one key for all."""
        boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
        n = len(boxes)
        pose_keys = list(pose_keys)
        landmark_keys = list(landmark_keys) if isinstance(landmark_keys, (list, np.ndarray)) \
            else [landmark_keys] * n
        if len(pose_keys) != n or len(landmark_keys) != n:
            raise ValueError(f"{cls.__name__}.many: {n} boxes, {len(pose_keys)} pose keys and "
                             f"{len(landmark_keys)} landmark keys")
        _check_boxes(boxes, camera)
        W = diagonal_sqrt_information(cls.default_sigma() if sigma is None else sigma, n, 4)
        # the solver's layout of the first factor's arguments (Factor.flat_args): box,
        # camera (the same for all), truncation mask
        first = cls(None, None, boxes[0] if n else np.array([0.0, 0.0, 1.0, 1.0]), camera,
                    sqrt_info=W[0] if n else None, robust=robust, truncation_margin=truncation_margin)
        leaves, treedef, shapes = first.flat_args()
        stacked = [boxes] + [np.broadcast_to(a, (n,) + a.shape) for a in leaves[1:]]
        if truncation_margin is not None:
            stacked[-1] = np.asarray(truncation_mask(boxes, camera, float(truncation_margin)))
        return FactorBatch(cls, (pose_keys, landmark_keys), stacked, treedef, shapes, W, robust)


class InverseBoxFactor(_BoxFactor):
    """Inverse box model: detected box vs the closed-form box of the projected ellipsoid."""

    kind = "inverse_box"
    residual = staticmethod(inverse_box_residual)
    sigmas = (Sigma(2.0, "px per box edge"),)


class SemiInverseBoxFactor(_BoxFactor):
    """Semi-inverse box model: tangency of the 4 back-projected box-edge planes.

    Not gated on ``box_visible``: πᵀQ*π is a polynomial in the landmark, defined and smooth
    wherever the ellipsoid is, so a step may carry the landmark through poses where it
    cuts a camera's principal plane (gating it there blocked the path to the optimum in
    most of the simulation's failures; docs/core.md, "Validity")."""

    kind = "semi_inverse_box"
    residual = staticmethod(semi_inverse_box_residual)
    valid = None
    sigmas = (Sigma(0.01, "m² per edge plane (≈ 2 px for a 0.3 m object at 3 m, f = 500)"),)


class InverseCuboidBoxFactor(_BoxFactor):
    """Inverse cuboid model: detected box vs the box of the projected circumscribed cuboid."""

    kind = "inverse_cuboid_box"
    residual = staticmethod(inverse_cuboid_box_residual)
    valid = staticmethod(cuboid_box_visible)
    sigmas = (Sigma(2.0, "px per box edge"),)


class SemiInverseCuboidBoxFactor(_BoxFactor):
    """Semi-inverse cuboid model: the back-projected box-edge planes touch the
    circumscribed cuboid."""

    kind = "semi_inverse_cuboid_box"
    residual = staticmethod(semi_inverse_cuboid_box_residual)
    valid = staticmethod(cuboid_box_visible)
    sigmas = (Sigma(0.01, "m per edge plane (≈ 2 px at 2.5 m, f = 500)"),)


class FrameBoxFactor(Factor):
    """A detected box of a recording whose frame is unknown: the camera pose T_wc is data
    (the recording's odometry), the variables are the frame (``jaxlie.SE3``, or
    ``geometry.Sim3`` when the recording's scale is unknown) that moves the recording into
    the map, and a landmark of the map (``frame_box_residual``: the inverse box model).
    ``spdslam.mapping.refine_localization`` fits the frame to a recording's boxes with it."""

    kind = "frame_box"
    residual = staticmethod(frame_box_residual)
    valid: ClassVar[Callable[..., Any] | None] = staticmethod(frame_box_visible)
    variables = ("frame", "landmark")
    dim = 4
    group = "box"
    # the inverse box model's noise, under its name: one σ for one measurement model
    sigmas = (Sigma(2.0, "px per box edge", name="inverse_box"),)

    def __init__(self, frame_key, landmark_key, T_wc, box, camera: Camera, *,
                 truncation_margin: float | None = None, **noise):
        pose = np.asarray(T_wc.wxyz_xyz if hasattr(T_wc, "wxyz_xyz") else T_wc, dtype=float)
        if pose.shape != (7,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"T_wc must be a jaxlie.SE3 (or its 7 numbers wxyz_xyz), got shape {pose.shape}")
        pose_leaf = jaxlie.SE3(pose)  # type: ignore[arg-type]  # numpy leaf
        super().__init__((frame_key, landmark_key), (pose_leaf, *_box_data(box, camera, truncation_margin)),
                         **noise)

    @classmethod
    def many(cls, frame_key, landmark_keys, poses_wxyz_xyz, boxes, camera: Camera, *,
             sigma: Any = None, robust: RobustKernel | None = None,
             truncation_margin: float | None = None) -> FactorBatch:
        """n boxes (n, 4) seen from the recording's poses (n, 7, jaxlie's wxyz_xyz) against
        the landmarks ``landmark_keys`` (a list, or one key), all with one frame variable, as
        one ``FactorBatch`` (the same factors as one by one)."""
        boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
        poses = np.asarray(poses_wxyz_xyz, dtype=float).reshape(-1, 7)
        n = len(boxes)
        landmark_keys = list(landmark_keys) if isinstance(landmark_keys, (list, np.ndarray)) \
            else [landmark_keys] * n
        if len(poses) != n or len(landmark_keys) != n or n == 0:
            raise ValueError(f"{cls.__name__}.many: {n} boxes, {len(poses)} poses and "
                             f"{len(landmark_keys)} landmark keys (at least one of each)")
        _check_boxes(boxes, camera)
        if not np.all(np.isfinite(poses)):
            raise ValueError("the poses must be finite")
        W = diagonal_sqrt_information(cls.default_sigma() if sigma is None else sigma, n, 4)
        first = cls(None, None, poses[0], boxes[0], camera, sqrt_info=W[0], robust=robust,
                    truncation_margin=truncation_margin)
        leaves, treedef, shapes = first.flat_args()
        # the layout of the arguments' leaves: the pose (7,), the box, the camera's, the mask
        stacked = [poses, boxes] + [np.broadcast_to(a, (n,) + a.shape) for a in leaves[2:]]
        if truncation_margin is not None:
            stacked[-1] = np.asarray(truncation_mask(boxes, camera, float(truncation_margin)))
        return FactorBatch(cls, ([frame_key] * n, landmark_keys), stacked, treedef, shapes, W, robust)


class DriftBoxFactor(Factor):
    """A detected box seen from a drifting odometry: the camera pose T_wc at time t is data,
    its correction K(t) is interpolated between two knot variables (``jaxlie.SE3``) with
    the weight w = (t − t_a)/(t_b − t_a) (data), and the landmark is the third variable
    (``drift_box_residual``: the inverse box model). The mapping's drift correction (``mapping._drift``) fits
    the knots of a recording's drift to its boxes with it."""

    kind = "drift_box"
    residual = staticmethod(drift_box_residual)
    valid: ClassVar[Callable[..., Any] | None] = staticmethod(drift_box_visible)
    variables = ("knot", "knot", "landmark")
    dim = 4
    group = "box"
    # the inverse box model's noise, under its name: one σ for one measurement model
    sigmas = (Sigma(2.0, "px per box edge", name="inverse_box"),)

    def __init__(self, knot_a, knot_b, landmark_key, T_wc, weight: float, box, camera: Camera, *,
                 truncation_margin: float | None = None, **noise):
        pose = np.asarray(T_wc.wxyz_xyz if hasattr(T_wc, "wxyz_xyz") else T_wc, dtype=float)
        if pose.shape != (7,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"T_wc must be a jaxlie.SE3 (or its 7 numbers wxyz_xyz), got shape {pose.shape}")
        w = float(weight)
        if not 0.0 <= w <= 1.0:
            raise ValueError(f"weight must be in [0, 1], got {weight!r}")
        pose_leaf = jaxlie.SE3(pose)  # type: ignore[arg-type]  # numpy leaf
        super().__init__((knot_a, knot_b, landmark_key),
                         (pose_leaf, np.float64(w), *_box_data(box, camera, truncation_margin)), **noise)

    @classmethod
    def many(cls, knot_a_keys, knot_b_keys, landmark_keys, poses_wxyz_xyz, weights, boxes, camera: Camera, *,
             sigma: Any = None, robust: RobustKernel | None = None,
             truncation_margin: float | None = None) -> FactorBatch:
        """n boxes (n, 4) seen from the odometry's poses (n, 7, jaxlie's wxyz_xyz) between the
        knots ``knot_a_keys`` and ``knot_b_keys`` with the weights (n,), against the landmarks
        ``landmark_keys`` (a list, or one key), as one ``FactorBatch`` (the same factors as
        one by one)."""
        boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
        poses = np.asarray(poses_wxyz_xyz, dtype=float).reshape(-1, 7)
        weights = np.asarray(weights, dtype=float).reshape(-1)
        n = len(boxes)
        landmark_keys = list(landmark_keys) if isinstance(landmark_keys, (list, np.ndarray)) \
            else [landmark_keys] * n
        knot_a_keys, knot_b_keys = list(knot_a_keys), list(knot_b_keys)
        if n == 0 or {len(poses), len(weights), len(landmark_keys), len(knot_a_keys), len(knot_b_keys)} != {n}:
            raise ValueError(f"{cls.__name__}.many: {n} boxes, {len(poses)} poses, {len(weights)} weights, "
                             f"{len(knot_a_keys)} and {len(knot_b_keys)} knot keys and {len(landmark_keys)} "
                             "landmark keys (the same number, at least one)")
        _check_boxes(boxes, camera)
        if not np.all(np.isfinite(poses)):
            raise ValueError("the poses must be finite")
        if not np.all((weights >= 0.0) & (weights <= 1.0)):
            raise ValueError("the weights must be in [0, 1]")
        W = diagonal_sqrt_information(cls.default_sigma() if sigma is None else sigma, n, 4)
        first = cls(None, None, None, poses[0], weights[0], boxes[0], camera, sqrt_info=W[0], robust=robust,
                    truncation_margin=truncation_margin)
        leaves, treedef, shapes = first.flat_args()
        # the layout of the arguments' leaves: the pose (7,), the weight, the box, the camera's, the mask
        stacked = [poses, weights, boxes] + [np.broadcast_to(a, (n,) + a.shape) for a in leaves[3:]]
        if truncation_margin is not None:
            stacked[-1] = np.asarray(truncation_mask(boxes, camera, float(truncation_margin)))
        return FactorBatch(cls, (knot_a_keys, knot_b_keys, landmark_keys), stacked, treedef, shapes, W, robust)
