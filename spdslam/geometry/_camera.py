"""Pinhole camera, projection of dual quadrics and cuboids, boxes and their back-projected planes.

Convention (used everywhere in spdslam): a pose ``T_wc`` maps camera coordinates to world
coordinates (camera-to-world, as in TUM trajectory files). The projection matrix is

    M = K [R_cw | t_cw],   T_cw = T_wc⁻¹,

a dual quadric projects to the dual conic C* = M Q* Mᵀ, and a line l of the image
back-projects to the plane π = Mᵀ l.

The untruncated box of C* (the tangent lines u = const, v = const) is

    u = (C*₁₃ ± √(C*₁₃² − C*₁₁ C*₃₃)) / C*₃₃,   v = (C*₂₃ ± √(C*₂₃² − C*₂₂ C*₃₃)) / C*₃₃

(1-based indices; the paper's formula omits the division by C*₃₃, which is only right for
C*₃₃ = 1 and wrong for a homogeneous C*).

Box-like objects are boxed by the silhouette of their circumscribed cuboid, the corners
t + Σᵢ ±sᵢRᵢ for P = R diag(s²) Rᵀ: its box is the min/max of the 8 projected corners
(``project_cuboid_box``), meaningful when all 8 lie in front of the camera
(``cuboid_in_front``). A box edge within a margin of the image border is the image's
edge, not the object's: ``truncation_mask`` marks the edges that carry a bound.

Written once for NumPy and JAX (``_arrays``): a pose is a ``jaxlie.SE3`` (JAX) or a pair
(R_wc, c) of arrays (``se3.camera_axes``), a landmark any parameterisation (or an
``Ellipsoid`` of NumPy arrays), a cuboid a landmark or a pair (H, t) of half-edge vectors
and centre; every function broadcasts over leading axes. NumPy in, NumPy out: the front
end and the scene generators call these per frame on small batches, where a JAX dispatch
would cost more than the arithmetic.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from ._arrays import array_namespace
from ._ellipsoid import as_ellipsoid, cuboid_corners, cuboid_half_axes, dual_quadric
from .se3 import as_pose, camera_axes, world_to_camera

__all__ = [
    "Camera",
    "Equidistant",
    "projection_matrix",
    "project_dual_quadric",
    "conic_box",
    "project_box",
    "box_lines",
    "box_planes",
    "normalize_plane",
    "depth_range",
    "in_front",
    "camera_inside",
    "look_at",
    "project_points",
    "project_cuboid_box",
    "cuboid_depth_range",
    "cuboid_in_front",
    "truncation_mask",
    "undistort_points",
    "distort_points",
    "undistort_boxes",
]


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics: focal lengths and principal point in pixels, image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: float
    height: float

    def __post_init__(self):
        vals = (self.fx, self.fy, self.cx, self.cy, self.width, self.height)
        if not all(isinstance(v, (int, float, np.number)) for v in vals):
            return  # arrays or traced values (batched intrinsics, inside jit): not checked
        if not (all(np.isfinite(vals)) and min(self.fx, self.fy, self.width, self.height) > 0):
            raise ValueError(
                "Camera needs finite values and positive fx, fy, width, height; got "
                f"fx={self.fx}, fy={self.fy}, cx={self.cx}, cy={self.cy}, "
                f"width={self.width}, height={self.height}"
            )

    @property
    def K(self):
        """The 3×3 intrinsic matrix (NumPy for plain numbers, JAX for JAX values)."""
        xp = array_namespace(self.fx, self.fy, self.cx, self.cy)
        z = xp.zeros_like(xp.asarray(self.fx, dtype=float))
        return xp.array(
            [[self.fx, z, self.cx], [z, self.fy, self.cy], [z, z, z + 1.0]], dtype=float
        )

    def as_array(self) -> jax.Array:
        return jnp.array([self.fx, self.fy, self.cx, self.cy, self.width, self.height], dtype=float)

    @classmethod
    def from_array(cls, a) -> "Camera":
        return cls(*(a[..., i] for i in range(6)))


jax.tree_util.register_dataclass(
    Camera, data_fields=["fx", "fy", "cx", "cy", "width", "height"], meta_fields=[]
)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> jaxlie.SE3:
    """Camera-to-world pose at ``eye`` whose optical axis (+z) points at ``target``.

    Image x (+u) points right and image y (+v) down, with ``up`` appearing upwards.
    Broadcasts over leading axes of ``eye`` and ``target``.
    """
    eye = jnp.asarray(eye, dtype=float)
    z = jnp.asarray(target, dtype=float) - eye
    z = z / jnp.linalg.norm(z, axis=-1, keepdims=True)
    x = jnp.cross(z, jnp.broadcast_to(jnp.asarray(up, dtype=float), z.shape))
    x = x / jnp.linalg.norm(x, axis=-1, keepdims=True)
    y = jnp.cross(z, x)
    R = jnp.stack([x, y, z], axis=-1)
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_matrix(R), eye)


def _pose(T_wc):
    """A ``jaxlie.SE3`` or a pair (R_wc, c) as given; a 4×4 matrix → SE3."""
    return T_wc if isinstance(T_wc, tuple) else as_pose(T_wc)


def projection_matrix(T_wc, camera: Camera):
    """M = K [R_cw | t_cw] (…, 3, 4) of camera-to-world poses."""
    Rt = world_to_camera(_pose(T_wc))
    return array_namespace(Rt, camera).asarray(camera.K) @ Rt


def project_dual_quadric(Q, T_wc, camera: Camera):
    """C* = M Q* Mᵀ (…, 3, 3)."""
    M = projection_matrix(T_wc, camera)
    xp = array_namespace(M, Q)
    return M @ Q @ xp.swapaxes(M, -1, -2)


def _safe_sqrt(x):
    """√max(x, 0) with a finite derivative everywhere (0 where x ≤ 0)."""
    xp = array_namespace(x)
    pos = x > 0
    return xp.where(pos, xp.sqrt(xp.where(pos, x, 1.0)), 0.0)


def conic_box(C):
    """[u_min, v_min, u_max, v_max] (…, 4) of dual conics C* (…, 3, 3), any scale."""
    xp = array_namespace(C)
    C = xp.asarray(C)
    c11, c22, c33 = C[..., 0, 0], C[..., 1, 1], C[..., 2, 2]
    c13, c23 = C[..., 0, 2], C[..., 1, 2]
    du = _safe_sqrt(c13**2 - c11 * c33)
    dv = _safe_sqrt(c23**2 - c22 * c33)
    u1, u2 = (c13 - du) / c33, (c13 + du) / c33
    v1, v2 = (c23 - dv) / c33, (c23 + dv) / c33
    return xp.stack(
        [xp.minimum(u1, u2), xp.minimum(v1, v2), xp.maximum(u1, u2), xp.maximum(v1, v2)],
        axis=-1,
    )


def project_box(ellipsoid, T_wc, camera: Camera):
    """Untruncated box [u_min, v_min, u_max, v_max] of a landmark seen from T_wc.

    Only meaningful when ``in_front(ellipsoid, T_wc)``; elsewhere the result is finite but
    not a box of the object.
    """
    return conic_box(project_dual_quadric(dual_quadric(ellipsoid), T_wc, camera))


def box_lines(box):
    """The 4 image lines (…, 4, 3) u = u_min, v = v_min, u = u_max, v = v_max."""
    xp = array_namespace(box)
    b = xp.asarray(box, dtype=float)
    one, zero = xp.ones_like(b[..., 0]), xp.zeros_like(b[..., 0])
    return xp.stack(
        [
            xp.stack([one, zero, -b[..., 0]], axis=-1),
            xp.stack([zero, one, -b[..., 1]], axis=-1),
            xp.stack([one, zero, -b[..., 2]], axis=-1),
            xp.stack([zero, one, -b[..., 3]], axis=-1),
        ],
        axis=-2,
    )


def normalize_plane(pi):
    """π / ‖π[:3]‖: unit normal n, so π·[x; 1] = n·x + d is a signed distance."""
    xp = array_namespace(pi)
    pi = xp.asarray(pi)
    return pi / xp.linalg.norm(pi[..., :3], axis=-1, keepdims=True)


def box_planes(box, T_wc, camera: Camera):
    """World planes (…, 4, 4), unit normals, through the camera centre and each box edge:
    π = Mᵀ l."""
    M = projection_matrix(T_wc, camera)
    return normalize_plane(box_lines(box) @ M)


def _dot(a, b):
    """a · b over the last axis (…)."""
    return array_namespace(a, b).einsum("...i,...i->...", a, b)


def depth_range(ellipsoid, T_wc):
    """(…, 2) (z_min, z_max): the extent of the ellipsoid along the optical axis, in the
    camera frame."""
    e = as_ellipsoid(ellipsoid)
    xp = array_namespace(e.P, e.center)
    R_wc, c = camera_axes(_pose(T_wc))
    axis = R_wc[..., :, 2]
    zc = _dot(axis, e.center - c)
    half = _safe_sqrt(_dot(xp.einsum("...i,...ij->...j", axis, e.P), axis))
    return xp.stack([zc - half, zc + half], axis=-1)


def in_front(ellipsoid, T_wc, min_depth: float = 0.0):
    """True when the whole ellipsoid lies in front of the camera (every point has z_c > min_depth).

    Then the principal plane does not cut it and its projection is a bounded ellipse.
    """
    return depth_range(ellipsoid, T_wc)[..., 0] > min_depth


def camera_inside(ellipsoid, T_wc):
    """True when the camera centre lies inside the ellipsoid."""
    return as_ellipsoid(ellipsoid).contains(camera_axes(_pose(T_wc))[1])


# --- points and circumscribed cuboids --------------------------------------------------------


def project_points(X, T_wc, camera: Camera):
    """Pixels (…, n, 2) of world points X (…, n, 3): [u, v] = (M[X; 1])₁,₂ / (M[X; 1])₃."""
    M = projection_matrix(T_wc, camera)
    xp = array_namespace(M, X)
    p = X @ xp.swapaxes(M[..., :3], -1, -2) + M[..., None, :, 3]
    z = p[..., 2:]
    return p[..., :2] / xp.where(xp.abs(z) > 1e-12, z, 1e-12)  # z ≈ 0: finite, not a pixel


def project_cuboid_box(cuboid, T_wc, camera: Camera):
    """Untruncated box [u_min, v_min, u_max, v_max] of a circumscribed cuboid (a landmark, or
    half-edge vectors and centre (H, t)): the extremes of its 8 projected corners. Only
    meaningful when ``cuboid_in_front``."""
    uv = project_points(cuboid_corners(cuboid), T_wc, camera)
    xp = array_namespace(uv)
    return xp.concatenate([xp.min(uv, axis=-2), xp.max(uv, axis=-2)], axis=-1)


def cuboid_depth_range(cuboid, T_wc):
    """(…, 2) (z_min, z_max) of the cuboid along the optical axis a: a·(t − c) ∓ Σᵢ |a·Hᵢ|."""
    H, t = cuboid_half_axes(cuboid)
    xp = array_namespace(H, t)
    R_wc, c = camera_axes(_pose(T_wc))
    axis = R_wc[..., :, 2]
    zc = _dot(axis, t - c)
    half = xp.sum(xp.abs(xp.einsum("...i,...ij->...j", axis, H)), axis=-1)
    return xp.stack([zc - half, zc + half], axis=-1)


def cuboid_in_front(cuboid, T_wc, min_depth: float = 0.0):
    """True when all 8 corners of the cuboid have depth z_c > min_depth."""
    return cuboid_depth_range(cuboid, T_wc)[..., 0] > min_depth


def truncation_mask(box, camera: Camera, margin):
    """(…, 4) 0/1 mask of the box edges that bound the object: 1 where the edge lies more
    than ``margin`` px inside the image [0, width] × [0, height], 0 where it may be the
    image border (a truncated detection). ``margin=None`` keeps every edge."""
    xp = array_namespace(box)
    b = xp.asarray(box, dtype=float)
    if margin is None:
        return xp.ones_like(b)
    keep = xp.stack(
        [
            b[..., 0] > margin,
            b[..., 1] > margin,
            b[..., 2] < camera.width - margin,
            b[..., 3] < camera.height - margin,
        ],
        axis=-1,
    )
    return keep.astype(b.dtype)


# --- lens distortion ---------------------------------------------------------------------


class Equidistant(NamedTuple):
    """The equidistant (fisheye, Kannala–Brandt) lens of OpenCV's ``fisheye`` module, Kalibr's
    ``equidistant`` and ROS's ``equidistant``: a ray at angle θ from the optical axis is
    imaged at normalised radius θ_d = θ (1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸), in the ray's
    direction. Given where a distortion is (``undistort_points``, ``distort_points``,
    ``undistort_boxes``) in place of the radial-tangential (k1, k2, p1, p2, k3)."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0


def _theta_d(theta, k):
    t2 = theta * theta
    return theta * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))


def _undistort_equidistant(flat, camera: Camera, k, iterations: int):
    """Normalised pinhole (x, y) of distorted pixels (n, 2): θ from θ_d by Newton's method
    (from θ = θ_d), then r = tan θ. Rays at 90° or more (a fisheye sees them; a pinhole
    image cannot hold them) come out not finite."""
    xd = (flat[:, 0] - camera.cx) / camera.fx
    yd = (flat[:, 1] - camera.cy) / camera.fy
    rd = np.hypot(xd, yd)
    theta = rd.copy()
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for _ in range(iterations):
            t2 = theta * theta
            f = _theta_d(theta, k) - rd
            df = 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])))
            theta = theta - f / df
        ok = (theta >= 0) & (theta < np.pi / 2) & np.isfinite(theta)
        scale = np.where(rd > 1e-15, np.tan(np.where(ok, theta, np.nan)) / np.where(rd > 1e-15, rd, 1.0), 1.0)
    return xd * scale, yd * scale


def undistort_points(uv, camera: Camera, distortion, iterations: int = 20):
    """Pinhole pixels (…, 2) of pixels ``uv`` measured through a lens. ``distortion`` =
    (k1, k2, p1, p2, k3): OpenCV's radial-tangential model, x_d = x·(1 + k1r² + k2r⁴ + k3r⁶)
    + (2p1xy + p2(r² + 2x²), p1(r² + 2y²) + 2p2xy) on normalised coordinates, inverted by
    fixed-point iteration (as OpenCV's ``undistortPoints``); or an ``Equidistant`` fisheye
    lens, inverted by Newton's method on θ. Where the iteration diverges (far outside the
    image, extreme coefficients, a fisheye ray at 90° or more) the result is not finite,
    silently: the callers refuse such boxes with their line. NumPy."""
    uv = np.asarray(uv, dtype=float)
    if isinstance(distortion, Equidistant):
        flat = uv.reshape(-1, 2)
        x, y = _undistort_equidistant(flat, camera, [float(v) for v in distortion], iterations)
        return np.stack([camera.fx * x + camera.cx, camera.fy * y + camera.cy], axis=-1).reshape(uv.shape)
    k1, k2, p1, p2, k3 = (float(v) for v in distortion)
    flat = uv.reshape(-1, 2)
    out = np.empty_like(flat)
    # in chunks that stay in cache across the iterations (the same arithmetic per point)
    for a in range(0, len(flat), _UNDISTORT_CHUNK):
        part = flat[a : a + _UNDISTORT_CHUNK]
        xd = (part[:, 0] - camera.cx) / camera.fx
        yd = (part[:, 1] - camera.cy) / camera.fy
        x, y = xd.copy(), yd.copy()
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            _fixed_point(x, y, xd, yd, (k1, k2, p1, p2, k3), iterations)
        out[a : a + _UNDISTORT_CHUNK, 0] = camera.fx * x + camera.cx
        out[a : a + _UNDISTORT_CHUNK, 1] = camera.fy * y + camera.cy
    return out.reshape(uv.shape)


#: Points ``undistort_points`` iterates on together.
_UNDISTORT_CHUNK = 16384

#: Steps after which ``_fixed_point`` sets aside the points that no longer move.
_UNDISTORT_PRUNE = (8, 12)


def _fixed_point(x, y, xd, yd, coefficients, iterations: int) -> None:
    """``iterations`` steps x ← (x_d − Δx(x, y)) / radial(x, y) (y alike) in place. A point
    that a step leaves exactly where it was is at the map's fixed point and stays there, so
    after the steps in ``_UNDISTORT_PRUNE`` only the points that still move are iterated:
    the same result, to the bit, as every step on every point."""
    k1, k2, p1, p2, k3 = coefficients
    idx = None  # the points still iterated (None: all)
    xs, ys, xds, yds = x, y, xd, yd
    for it in range(iterations):
        r2 = xs * xs + ys * ys
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * xs * ys + p2 * (r2 + 2.0 * xs * xs)
        dy = p1 * (r2 + 2.0 * ys * ys) + 2.0 * p2 * xs * ys
        xn, yn = (xds - dx) / radial, (yds - dy) / radial
        if it in _UNDISTORT_PRUNE and it < iterations - 1:
            moving = ~((xn == xs) & (yn == ys))
            if idx is None:
                x[:], y[:] = xn, yn
                idx = np.flatnonzero(moving)
            else:
                x[idx], y[idx] = xn, yn
                idx = idx[moving]
            xs, ys, xds, yds = x[idx], y[idx], xd[idx], yd[idx]
            continue
        xs, ys = xn, yn
    if idx is None:
        x[:], y[:] = xs, ys
    else:
        x[idx], y[idx] = xs, ys


def distort_points(uv, camera: Camera, distortion):
    """The forward model of ``undistort_points``: pixels (…, 2) of a pinhole camera →
    pixels measured through the radial-tangential distortion (k1, k2, p1, p2, k3), or
    through an ``Equidistant`` fisheye lens. NumPy."""
    uv = np.asarray(uv, dtype=float)
    if isinstance(distortion, Equidistant):
        x = (uv[..., 0] - camera.cx) / camera.fx
        y = (uv[..., 1] - camera.cy) / camera.fy
        r = np.hypot(x, y)
        theta = np.arctan(r)
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(r > 1e-15, _theta_d(theta, [float(v) for v in distortion]) / np.where(r > 1e-15, r, 1.0),
                             1.0)
        return np.stack([camera.fx * x * scale + camera.cx, camera.fy * y * scale + camera.cy], axis=-1)
    k1, k2, p1, p2, k3 = (float(v) for v in distortion)
    x = (uv[..., 0] - camera.cx) / camera.fx
    y = (uv[..., 1] - camera.cy) / camera.fy
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([camera.fx * xd + camera.cx, camera.fy * yd + camera.cy], axis=-1)


def undistort_boxes(boxes, camera: Camera, distortion, samples: int = 16):
    """The pinhole box (…, 4) of boxes measured on a distorted image: the extremes of the
    undistorted box outline (``samples`` points per edge). The object's outline lies inside
    the box in the distorted image, so its pinhole outline lies inside the undistorted
    outline, whose bounding box this is (exact where the object touches an edge at the
    edge's extreme after undistortion; larger by the edge's bow elsewhere). NumPy."""
    b = np.asarray(boxes, dtype=float)
    s = np.linspace(0.0, 1.0, samples)
    u0, v0, u1, v1 = (b[..., k, None] for k in range(4))
    us = u0 + s * (u1 - u0)
    vs = v0 + s * (v1 - v0)
    pts = np.concatenate([
        np.stack([us, np.broadcast_to(v0, us.shape)], -1),
        np.stack([us, np.broadcast_to(v1, us.shape)], -1),
        np.stack([np.broadcast_to(u0, vs.shape), vs], -1),
        np.stack([np.broadcast_to(u1, vs.shape), vs], -1),
    ], axis=-2)
    q = undistort_points(pts, camera, distortion)
    return np.concatenate([q.min(axis=-2), q.max(axis=-2)], axis=-1)
