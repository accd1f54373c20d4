"""Landmark initialisation from boxes.

Quadric-SVD. Every box edge back-projects to a plane π = Mᵀl that must be tangent to the
object: πᵀQ*π = 0 is linear in the 10 independent entries q of Q*,

    Σᵢ πᵢ² qᵢᵢ + Σᵢ<ⱼ 2πᵢπⱼ qᵢⱼ = 0,

so k ≥ 3 views (4k ≥ 12 planes for 9 degrees of freedom) give a homogeneous system A q = 0,
solved by the right singular vector of the smallest singular value; Q* is then projected to
the nearest ellipsoid (``EllipsoidFull.regularized``). For conditioning the planes are
expressed in a frame centred on the mean camera centre and scaled by the mean camera
distance from it: x = s x' + c, so π' = Tᵀπ and Q* = T Q*' Tᵀ with T = [[sI, c], [0, 1]].

Truncated detections: with a ``truncation_margin`` (px), box edges within it of the image
border (``geometry.truncation_mask``) are the image's edge, not the object's, and are left
out of both fits.

Without an up direction the multi-constraint fit has no frame; ``unoriented_initialize``
starts from Quadric-SVD where it fits the boxes, else from a sphere on the boxes' rays
(``sphere_initialize``): on real boxes the algebraic fit is often flat (a radius below 1 mm)
or metres long, starts the back end takes many iterations to leave, when it leaves them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import (
    OBJECT_SHAPES,
    Camera,
    Ellipsoid,
    EllipsoidFull,
    box_iou,
    box_planes,
    in_front,
    project_box,
    truncation_mask,
)
from ..geometry.se3 import as_pose, quat_to_matrix
from ..solver import stored_jit
from ._multi_fit import MultiProblem, fit_multi

__all__ = [
    "MultiFit",
    "TILT_SIGMA",
    "InitializationError",
    "multi_initialize",
    "multi_initialize_batch",
    "sphere_initialize",
    "svd_initialize",
    "triangulate_rays",
    "unoriented_initialize",
]

_TRIU = np.triu_indices(4)
_OFF = (_TRIU[0] != _TRIU[1]).astype(float)


class InitializationError(ValueError):
    """The boxes do not determine an ellipsoid (too few views, degenerate geometry)."""


def _views(boxes, poses, min_views: int):
    """(boxes (k, 4), poses as SE3) with k ≥ ``min_views``, else InitializationError."""
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
    poses = [as_pose(T) for T in poses]
    if len(poses) != len(boxes):
        raise ValueError(f"{len(boxes)} boxes but {len(poses)} poses")
    if len(boxes) < min_views:
        raise InitializationError(f"needs at least {min_views} views, got {len(boxes)}")
    return boxes, poses


def _keep(boxes, camera, truncation_margin):
    """(k, 4) bool: the box edges that bound the object."""
    return np.asarray(truncation_mask(boxes, camera, truncation_margin)) > 0


def svd_initialize(
    boxes, poses, camera: Camera, min_views: int = 3, truncation_margin: float | None = None
) -> Ellipsoid:
    """Quadric-SVD initial ellipsoid from ``boxes`` (k, 4) seen from camera-to-world ``poses``.

    With ``truncation_margin`` (px) the planes of edges within it of the image border are
    dropped. Raises ``InitializationError`` with the reason when it cannot: fewer than
    ``min_views`` boxes or 9 untruncated edges, a null space that is not one-dimensional, or
    a solution that is not an ellipsoid in front of the cameras.
    """
    boxes, poses = _views(boxes, poses, max(min_views, 3))
    keep = _keep(boxes, camera, truncation_margin).ravel()
    if keep.sum() < 9:
        raise InitializationError(
            f"only {int(keep.sum())} untruncated box edges, Quadric-SVD needs at least 9"
        )
    # every view's planes at once, in NumPy: the poses read on the host once
    rows = np.stack([np.asarray(T.wxyz_xyz, dtype=float) for T in poses])
    centres = rows[:, 4:]
    planes = np.asarray(box_planes(boxes, (quat_to_matrix(rows[:, [1, 2, 3, 0]]), centres), camera)).reshape(-1, 4)
    planes = planes[keep]
    c = centres.mean(axis=0)
    s = max(float(np.mean(np.linalg.norm(centres - c, axis=1))), 1e-6)
    T = np.eye(4)
    T[:3, :3] *= s
    T[:3, 3] = c
    p = planes @ T  # π' = Tᵀπ, one per row
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    A = p[:, _TRIU[0]] * p[:, _TRIU[1]] * (1.0 + _OFF)
    # Vt 10×10 (its last row the null vector): thin when A has 10 rows or more (no 4k × 4k U)
    _, sv, Vt = np.linalg.svd(A, full_matrices=len(A) < 10)
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
    P, center = (np.asarray(a) for a in _ELLIPSOID_OF_QUADRIC(Q))
    if not np.all(np.isfinite(P)) or not np.all(np.isfinite(center)):
        raise InitializationError("the fitted quadric is not finite")
    return Ellipsoid(jnp.asarray(P), jnp.asarray(center))


def _ellipsoid_of_quadric(Q):
    """(P, centre) of the ellipsoid nearest the dual quadric Q (``EllipsoidFull.regularized``)."""
    e = EllipsoidFull.from_dual_quadric(Q).regularized().to_ellipsoid()
    return e.P, e.center


#: ``_ellipsoid_of_quadric`` as one stored program (a few dozen operations: one call, not one
#: dispatch each)
_ELLIPSOID_OF_QUADRIC = stored_jit(_ellipsoid_of_quadric, "frontend.ellipsoid_of_quadric")


def sphere_initialize(boxes, poses, camera: Camera, min_views: int = 3,
                      truncation_margin: float | None = None) -> Ellipsoid:
    """A sphere from the boxes alone: its centre the point nearest the rays through the box
    centres, its radius the mean of the boxes' median half-width and half-height at that
    depth (``_ray_centre``, as the multi-constraint fit's starts). Raises
    ``InitializationError`` when the rays are (nearly) parallel or meet behind the cameras."""
    boxes, poses = _views(boxes, poses, max(min_views, 2))
    rows = np.stack([np.asarray(T.wxyz_xyz, dtype=float) for T in poses])
    c, half_w, half_h = _ray_centre(boxes, rows, camera, _keep(boxes, camera, truncation_margin))
    return Ellipsoid(np.eye(3) * (0.5 * (half_w + half_h)) ** 2, c)


def _box_fit(e: Ellipsoid, boxes, poses, camera: Camera) -> float:
    """The median over views of the IoU of the ellipsoid's box (``project_box``, clipped to
    the image) with the detected box; a view with the ellipsoid not wholly in front counts 0."""
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
    rows = np.stack([np.asarray(as_pose(T).wxyz_xyz, dtype=float) for T in poses])
    pose = (quat_to_matrix(rows[:, [1, 2, 3, 0]]), rows[:, 4:])
    e = Ellipsoid(np.asarray(e.P, dtype=float), np.asarray(e.center, dtype=float))
    with np.errstate(invalid="ignore", divide="ignore"):
        predicted = np.asarray(project_box(e, pose, camera))
    predicted = np.clip(predicted, 0.0, [camera.width, camera.height, camera.width, camera.height])
    iou = np.asarray(box_iou(predicted, boxes), dtype=float)
    iou = np.where(np.asarray(in_front(e, pose, 1e-3)) & np.isfinite(iou), iou, 0.0)
    return float(np.median(iou))


def unoriented_initialize(boxes, poses, camera: Camera, min_views: int = 3,
                          truncation_margin: float | None = None,
                          min_ratio: float = 0.0) -> tuple[Ellipsoid, str]:
    """The initial ellipsoid without an up direction, and which start it is ("svd" or
    "sphere"): Quadric-SVD (``svd_initialize``) unless it fails, is flat (smallest radius
    below ``min_ratio`` of the largest) or fits the boxes worse than the sphere on their rays
    (``sphere_initialize``; ``_box_fit``, the median IoU); then the sphere. Raises
    ``InitializationError`` when neither can be made."""
    svd, why = None, ""
    try:
        svd = svd_initialize(boxes, poses, camera, min_views, truncation_margin)
    except InitializationError as err:
        why = str(err)
    if svd is not None:
        r = np.sqrt(np.clip(np.linalg.eigvalsh(np.asarray(svd.P, dtype=float)), 0.0, None))
        if r[0] < min_ratio * r[2]:
            svd, why = None, f"Quadric-SVD is flat (radii {r[2]:.3g}, {r[1]:.3g}, {r[0]:.3g} m)"
    try:
        sphere = sphere_initialize(boxes, poses, camera, min_views, truncation_margin)
    except InitializationError as err:
        if svd is None:
            raise InitializationError(f"{why}; no sphere either: {err}") from None
        return svd, "svd"
    if svd is not None and _box_fit(svd, boxes, poses, camera) >= _box_fit(sphere, boxes, poses, camera):
        return svd, "svd"
    return sphere, "sphere"


# --- multi-constraint initialisation ---------------------------------------------------------

#: Starting yaws (rad) of the multi-constraint fit; with a ≠ b, [0, π) covers every
#: horizontal orientation, and each start is refined by LM.
_YAW_STARTS = np.arange(6) * np.pi / 6
_START_ASPECT = 1.4  # a/b of each start: a start with a = b has zero yaw gradient
#: σ (rad) of the prior that holds the multi-constraint start's tilt near upright
#: (``multi_initialize``): of the order of the error of an up direction
#: estimated from the cameras (docs/sequences.md gives the measurement and the choice).
TILT_SIGMA = 0.02
#: The multi-constraint fit uses at most this many views, evenly spread over the track, and
#: pads fewer to it: one compiled program per object shape whatever the track's length (the
#: start only has to be near the optimum; the back end refines it with every box).
MULTI_FIT_VIEWS = 64


def _plane_frame(up, plane):
    """(e1, e2, n, w0): an orthonormal frame with n the support normal (or up) and the
    support plane at height w0 along n (0 without a plane)."""
    if plane is not None:
        p = np.asarray(plane, dtype=float)
        k = np.linalg.norm(p[:3])
        n, w0 = p[:3] / k, -p[3] / k
        if up is not None and n @ np.asarray(up, dtype=float) < 0:
            n, w0 = -n, -w0
    else:
        n, w0 = np.asarray(up, dtype=float) / np.linalg.norm(up), 0.0
    a = np.eye(3)[np.argmin(np.abs(n))]
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1), n, w0


def triangulate_rays(origins, directions) -> np.ndarray:
    """The point nearest (least squares) to the lines xᵢ + λ dᵢ."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    M = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = M.sum(axis=0)
    b = np.einsum("kij,kj->i", M, origins)
    if np.linalg.cond(A) > 1e8:
        raise InitializationError("the views are (nearly) parallel: cannot locate the object")
    return np.linalg.solve(A, b)


def _box_rays(boxes, rows, camera):
    """Camera centres and world directions through the box centres; ``rows`` (k, 7): the
    poses' jaxlie parameters (NumPy)."""
    K = np.asarray(camera.K)
    uv1 = np.c_[(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2, np.ones(len(boxes))]
    rays_c = uv1 @ np.linalg.inv(K).T
    Rs = quat_to_matrix(rows[:, [1, 2, 3, 0]])
    return rows[:, 4:], np.einsum("kij,kj->ki", Rs, rays_c), Rs


@dataclass(frozen=True)
class MultiFit:
    """What the Quadric-Multi fit (``multi_initialize``) assumes beyond the boxes: the class
    size prior ``prior_radii`` (semi-axes, any order; the sorted log radii with σ
    ``prior_sigma``), the silhouette ``shape`` (``OBJECT_SHAPES``), ``truncation_margin``
    (px: box edges within it of the image border are ignored) and ``tilt_sigma`` (rad,
    the prior towards upright; None holds the axes upright)."""

    prior_radii: Any = None
    prior_sigma: float = 0.2
    shape: str = "ellipsoid"
    truncation_margin: float | None = None
    tilt_sigma: float | None = TILT_SIGMA

    def __post_init__(self):
        if self.shape not in OBJECT_SHAPES:
            raise ValueError(f"shape must be one of {', '.join(OBJECT_SHAPES)}, got {self.shape!r}")
        t = self.tilt_sigma
        if t is not None and not (np.isfinite(t) and t > 0):
            raise ValueError(f"tilt_sigma must be a positive angle (rad) or None, got {t!r}")


def multi_initialize(boxes, poses, camera: Camera, up, support_plane=None, fit: MultiFit = MultiFit(),
                     min_views: int = 2) -> Ellipsoid:
    """Multi-constraint ("Quadric-Multi") initial ellipsoid: one axis along ``up``, resting on
    ``support_plane`` (a·x + b·y + c·z + d = 0) when one is given, with the class size prior
    of ``fit`` (``MultiFit``) when it has one.

    Unknowns: the centre on the plane (2, or 3 without a plane), the yaw about ``up`` and the
    three radii (the centre sits one vertical radius above the plane). They are fitted to the
    boxes (inverse box model, 2 px) by LM from several yaws; the centre and radii start from
    the rays through the box centres and the box sizes. Needs ``min_views`` ≥ 2 views;
    of more than :data:`MULTI_FIT_VIEWS`, that many evenly spread over the track are used.
    ``fit.shape="cuboid"`` fits the box of the circumscribed cuboid (box-like objects)
    instead of the ellipsoid's; the result is the cuboid's inscribed ellipsoid (radii =
    half-extents). With ``fit.truncation_margin`` (px) box edges within it of the image
    border are ignored.

    Each start is upright (one axis along ``up``); with ``fit.tilt_sigma`` (rad, default
    ``TILT_SIGMA``) the tilt is free under a prior of that σ towards upright, so that the
    axes end where the boxes put them rather than snapped to ``up``; None holds them upright.
    ``multi_initialize_batch`` fits many objects at once.
    """
    got = multi_initialize_batch([(boxes, poses, support_plane, fit)], camera, up, min_views)[0]
    if isinstance(got, Exception):
        raise got
    return got


def multi_initialize_batch(objects, camera: Camera, up, min_views: int = 2) -> list:
    """``multi_initialize`` of each of ``objects`` (boxes, poses, support_plane, fit), every
    start of every object in one batch (``_multi_fit``): per object its Ellipsoid, or the
    ``InitializationError`` (or other object error) that it alone raised."""
    if up is None:
        raise ValueError("multi-constraint initialisation needs the up direction")
    out: list = [None] * len(objects)
    problems, where = [], []
    for i, (boxes, poses, plane, fit) in enumerate(objects):
        try:
            problems.append(_multi_problem(boxes, poses, camera, up, plane, fit, min_views))
            where.append(i)
        except (ValueError, ArithmeticError) as e:  # this object only (InitializationError among them)
            out[i] = e
    try:
        fits: list = fit_multi(problems, camera)
    except (ValueError, ArithmeticError):  # each alone, so that an object's error stays its own
        fits = []
        for p in problems:
            try:
                fits.append(fit_multi([p], camera)[0])
            except (ValueError, ArithmeticError) as e:
                fits.append(e)
    for i, fitted in zip(where, fits):
        if isinstance(fitted, Exception):
            out[i] = fitted
            continue
        costs, Ps, centers = fitted
        if not np.any(np.isfinite(costs)):
            out[i] = InitializationError("the constrained fit diverged from every start")
            continue
        best = int(np.nanargmin(np.where(np.isfinite(costs), costs, np.nan)))
        out[i] = Ellipsoid(jax.device_put(Ps[best]), jax.device_put(centers[best]))  # no program to run
    return out


def _multi_problem(boxes, poses, camera: Camera, up, support_plane, fit: MultiFit, min_views: int) -> MultiProblem:
    """One object's fit (``MultiProblem``): its views (at most ``MULTI_FIT_VIEWS``), the
    edges kept, the frame of its plane, its starts and priors."""
    boxes, poses = _views(boxes, poses, max(min_views, 2))
    if len(boxes) > MULTI_FIT_VIEWS:
        pick = np.unique(np.linspace(0, len(boxes) - 1, MULTI_FIT_VIEWS).round().astype(int))
        boxes, poses = boxes[pick], [poses[i] for i in pick]
    keep = _keep(boxes, camera, fit.truncation_margin)
    if not keep.any():
        raise InitializationError("every box edge is truncated by the image border")
    frame = _plane_frame(up, support_plane)
    rows = np.stack([np.asarray(T.wxyz_xyz, dtype=float) for T in poses])  # on the host once
    starts = _multi_starts(boxes, rows, camera, keep, frame, support_plane is not None)
    if fit.prior_radii is None:
        prior_log, prior_w = np.zeros(3), 0.0
    else:
        prior_log, prior_w = np.sort(np.log(np.asarray(fit.prior_radii, dtype=float))), 1.0 / fit.prior_sigma
    tilt_w = 0.0 if fit.tilt_sigma is None else 1.0 / float(fit.tilt_sigma)
    return MultiProblem(np.asarray(starts, dtype=float), tuple(np.asarray(f, dtype=float) for f in frame),
                        support_plane is not None, rows, boxes, keep.astype(float), prior_log, prior_w, tilt_w,
                        fit.shape)


def _ray_centre(boxes, rows, camera: Camera, keep) -> tuple[np.ndarray, float, float]:
    """(centre, half-width, half-height) of an object from its boxes: the point nearest the
    rays through the box centres, and the boxes' median half-sizes at its depth (whole boxes
    when there are two, a truncated box's centre and size are biased; ``keep`` the edges
    kept, ``rows`` the poses' jaxlie parameters)."""
    whole = keep.all(axis=1)
    start = whole if whole.sum() >= 2 else np.ones(len(boxes), bool)
    origins, dirs, Rs = _box_rays(boxes[start], rows[start], camera)
    c0 = triangulate_rays(origins, dirs)
    depth = np.einsum("ki,ki->k", c0 - origins, Rs[:, :, 2])
    if np.median(depth) <= 0:
        raise InitializationError("the triangulated centre is behind the cameras")
    depth = np.maximum(depth, 1e-3)
    half_w = np.median((boxes[start, 2] - boxes[start, 0]) * depth / (2 * camera.fx))
    half_h = np.median((boxes[start, 3] - boxes[start, 1]) * depth / (2 * camera.fy))
    return c0, float(half_w), float(half_h)


def _multi_starts(boxes, rows, camera: Camera, keep, frame, on_plane: bool) -> list:
    """The fit's starts θ = (centre in the plane's frame, log radii, yaw, tilt), one per
    yaw of ``_YAW_STARTS``: the centre from the rays through the box centres, the radii from
    the box sizes at that depth (whole boxes when there are two, a truncated box's centre
    and size are biased), resting on the plane when ``on_plane``."""
    e1, e2, n, w0 = frame
    c0, half_w, half_h = _ray_centre(boxes, rows, camera, keep)
    r_h = max(half_w, 1e-3)
    r_v = max(half_h, 1e-3)
    w = c0 @ n
    if on_plane:
        r_v = max(0.5 * (r_v + max(w - w0, 1e-3)), 1e-3)
    return [[c0 @ e1, c0 @ e2, w, np.log(r_h * np.sqrt(_START_ASPECT)), np.log(r_h / np.sqrt(_START_ASPECT)),
             np.log(r_v), psi, 0.0, 0.0] for psi in _YAW_STARTS]
