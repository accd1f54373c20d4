"""Pinhole camera, projection of dual quadrics, boxes and their back-projected planes.

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
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .ellipsoid import EllipsoidRTS, as_ellipsoid, dual_quadric
from .matfun import eigh
from .se3 import as_pose

__all__ = [
    "Camera",
    "as_pose",
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
    "cuboid_half_axes",
    "cuboid_corners",
    "project_points",
    "project_cuboid_box",
    "cuboid_depth_range",
    "cuboid_in_front",
    "truncation_mask",
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
    def K(self) -> jax.Array:
        z = jnp.zeros_like(jnp.asarray(self.fx, dtype=float))
        return jnp.array(
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


def projection_matrix(T_wc, camera: Camera) -> jax.Array:
    """M = K [R_cw | t_cw] (3×4) for a camera-to-world pose."""
    T_cw = as_pose(T_wc).inverse()
    return camera.K @ T_cw.as_matrix()[:3, :]


def project_dual_quadric(Q, T_wc, camera: Camera) -> jax.Array:
    """C* = M Q* Mᵀ."""
    M = projection_matrix(T_wc, camera)
    return M @ Q @ M.T


def _safe_sqrt(x):
    """√max(x, 0) with a finite derivative everywhere (0 where x ≤ 0)."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def conic_box(C) -> jax.Array:
    """[u_min, v_min, u_max, v_max] of the dual conic C* (any scale; leading axes broadcast)."""
    C = jnp.asarray(C)
    c11, c22, c33 = C[..., 0, 0], C[..., 1, 1], C[..., 2, 2]
    c13, c23 = C[..., 0, 2], C[..., 1, 2]
    du = _safe_sqrt(c13**2 - c11 * c33)
    dv = _safe_sqrt(c23**2 - c22 * c33)
    u1, u2 = (c13 - du) / c33, (c13 + du) / c33
    v1, v2 = (c23 - dv) / c33, (c23 + dv) / c33
    return jnp.stack(
        [jnp.minimum(u1, u2), jnp.minimum(v1, v2), jnp.maximum(u1, u2), jnp.maximum(v1, v2)],
        axis=-1,
    )


def project_box(ellipsoid, T_wc, camera: Camera) -> jax.Array:
    """Untruncated box [u_min, v_min, u_max, v_max] of a landmark seen from T_wc.

    Only meaningful when ``in_front(ellipsoid, T_wc)``; elsewhere the result is finite but
    not a box of the object.
    """
    return conic_box(project_dual_quadric(dual_quadric(ellipsoid), T_wc, camera))


def box_lines(box) -> jax.Array:
    """The 4 image lines (4×3) u = u_min, v = v_min, u = u_max, v = v_max."""
    b = jnp.asarray(box, dtype=float)
    one, zero = jnp.ones_like(b[0]), jnp.zeros_like(b[0])
    return jnp.stack(
        [
            jnp.stack([one, zero, -b[0]]),
            jnp.stack([zero, one, -b[1]]),
            jnp.stack([one, zero, -b[2]]),
            jnp.stack([zero, one, -b[3]]),
        ]
    )


def normalize_plane(pi) -> jax.Array:
    """π / ‖π[:3]‖: unit normal n, so π·[x; 1] = n·x + d is a signed distance."""
    pi = jnp.asarray(pi)
    return pi / jnp.linalg.norm(pi[..., :3], axis=-1, keepdims=True)


def box_planes(box, T_wc, camera: Camera) -> jax.Array:
    """World planes (4×4, unit normals) through the camera centre and each box edge: π = Mᵀ l."""
    M = projection_matrix(T_wc, camera)
    return normalize_plane(box_lines(box) @ M)


def depth_range(ellipsoid, T_wc) -> jax.Array:
    """(z_min, z_max): the extent of the ellipsoid along the optical axis, in the camera frame."""
    e = as_ellipsoid(ellipsoid)
    T = as_pose(T_wc)
    R_wc = T.rotation().as_matrix()
    axis = R_wc[:, 2]
    zc = axis @ (e.center - T.translation())
    half = _safe_sqrt(axis @ e.P @ axis)
    return jnp.stack([zc - half, zc + half])


def in_front(ellipsoid, T_wc, min_depth: float = 0.0) -> jax.Array:
    """True when the whole ellipsoid lies in front of the camera (every point has z_c > min_depth).

    Then the principal plane does not cut it and its projection is a bounded ellipse.
    """
    return depth_range(ellipsoid, T_wc)[0] > min_depth


def camera_inside(ellipsoid, T_wc) -> jax.Array:
    """True when the camera centre lies inside the ellipsoid."""
    return as_ellipsoid(ellipsoid).contains(as_pose(T_wc).translation())


# --- circumscribed cuboid --------------------------------------------------------------------
_SIGNS = np.array([[a, b, c] for a in (-1.0, 1.0) for b in (-1.0, 1.0) for c in (-1.0, 1.0)])


def cuboid_half_axes(landmark):
    """(H, t): the columns of H are the cuboid's half-edge vectors sᵢRᵢ, t its centre.

    RTS landmarks use their rotation and |radii| directly (smooth in their parameters); SPD
    and Full go through P = V diag(λ) Vᵀ with the tie-safe ``matfun.eigh``, sᵢ = √λᵢ. The
    cuboid is invariant to the order and signs of the axes, but at repeated radii its
    orientation is not determined by P: there the box is that of one valid choice of axes
    and its derivative is finite (the coupling inside the tie is dropped), not a limit.
    """
    if isinstance(landmark, EllipsoidRTS):
        return landmark.rotation.as_matrix() * jnp.abs(landmark.radii), landmark.center
    e = as_ellipsoid(landmark)
    w, V = eigh(e.P)
    return V * jnp.sqrt(jnp.maximum(w, 1e-300)), e.center


def cuboid_corners(landmark) -> jax.Array:
    """The 8 corners (8×3) t + H σ, σ ∈ {±1}³, of the circumscribed cuboid."""
    H, t = cuboid_half_axes(landmark)
    return t + jnp.asarray(_SIGNS) @ H.T


def project_points(X, T_wc, camera: Camera) -> jax.Array:
    """Pixels (n×2) of world points X (n×3): [u, v] = (M[X; 1])₁,₂ / (M[X; 1])₃."""
    M = projection_matrix(T_wc, camera)
    p = X @ M[:, :3].T + M[:, 3]
    z = p[:, 2:]
    return p[:, :2] / jnp.where(jnp.abs(z) > 1e-12, z, 1e-12)  # z ≈ 0: finite, not a pixel


def project_cuboid_box(landmark, T_wc, camera: Camera) -> jax.Array:
    """Untruncated box [u_min, v_min, u_max, v_max] of the landmark's circumscribed cuboid:
    the extremes of its 8 projected corners. Only meaningful when ``cuboid_in_front``."""
    uv = project_points(cuboid_corners(landmark), T_wc, camera)
    return jnp.concatenate([jnp.min(uv, axis=0), jnp.max(uv, axis=0)])


def cuboid_depth_range(landmark, T_wc) -> jax.Array:
    """(z_min, z_max) of the cuboid along the optical axis a: a·(t − c) ∓ Σᵢ |a·Hᵢ|."""
    H, t = cuboid_half_axes(landmark)
    T = as_pose(T_wc)
    axis = T.rotation().as_matrix()[:, 2]
    zc = axis @ (t - T.translation())
    half = jnp.sum(jnp.abs(axis @ H))
    return jnp.stack([zc - half, zc + half])


def cuboid_in_front(landmark, T_wc, min_depth: float = 0.0) -> jax.Array:
    """True when all 8 corners of the circumscribed cuboid have depth z_c > min_depth."""
    return cuboid_depth_range(landmark, T_wc)[0] > min_depth


def truncation_mask(box, camera: Camera, margin):
    """(…, 4) 0/1 mask of the box edges that bound the object: 1 where the edge lies more
    than ``margin`` px inside the image [0, width] × [0, height], 0 where it may be the
    image border (a truncated detection). ``margin=None`` keeps every edge. A JAX array in
    (traced or not) gives a JAX array, anything else a NumPy array (no device dispatch)."""
    xp = jnp if isinstance(box, jax.Array) else np
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
