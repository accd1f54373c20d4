"""SE(3) poses (through jaxlie) and the one convention spdslam uses.

A pose ``T_wc`` maps camera coordinates to world coordinates (camera-to-world): its
translation is the camera centre in the world, its rotation's columns are the camera axes
(x right, y down, z forward along the optical axis) in the world. TUM trajectory lines
``timestamp tx ty tz qx qy qz qw`` store exactly this pose. Tangent vectors are jaxlie's
(v, ω), translation first, with the right perturbation T ⊞ δ = T · Exp(δ).
``interpolate_tum`` reads a TUM trajectory between its samples.
"""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie
import numpy as np
from scipy.spatial.transform import Rotation

from ._arrays import array_namespace

__all__ = [
    "as_pose",
    "from_tum",
    "to_tum",
    "from_matrix",
    "to_matrix",
    "stack",
    "camera_axes",
    "world_to_camera",
    "quat_to_matrix",
    "matrix_to_quat",
    "interpolate_tum",
]


def as_pose(T) -> jaxlie.SE3:
    """A jaxlie.SE3 from an SE3 or a 4×4 homogeneous matrix (a concrete matrix is checked)."""
    if isinstance(T, jaxlie.SE3):
        return T
    if isinstance(T, (np.ndarray, list, tuple)):
        M = np.asarray(T, dtype=float)
        if M.shape[-2:] != (4, 4):
            raise ValueError(f"a pose must be a jaxlie.SE3 or a 4x4 matrix, got shape {M.shape}")
        if not np.all(np.isfinite(M)):
            raise ValueError("pose matrix has non-finite entries")
    return jaxlie.SE3.from_matrix(jnp.asarray(T, dtype=float))


def from_matrix(T) -> jaxlie.SE3:
    return jaxlie.SE3.from_matrix(jnp.asarray(T, dtype=float))


def to_matrix(T) -> np.ndarray:
    return np.asarray(as_pose(T).as_matrix())


def from_tum(values) -> jaxlie.SE3:
    """Pose(s) from TUM fields ``tx ty tz qx qy qz qw`` (shape (..., 7)); quaternions are normalised."""
    v = jnp.asarray(values, dtype=float)
    q_xyzw = v[..., 3:7]
    q = q_xyzw / jnp.linalg.norm(q_xyzw, axis=-1, keepdims=True)
    wxyz = jnp.concatenate([q[..., 3:4], q[..., :3]], axis=-1)
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3(wxyz), v[..., :3])


def to_tum(T) -> np.ndarray:
    """TUM fields ``tx ty tz qx qy qz qw`` (…, 7) of pose(s), with qw ≥ 0."""
    T = as_pose(T)
    wxyz = np.asarray(T.rotation().wxyz)
    wxyz = np.where(wxyz[..., :1] < 0, -wxyz, wxyz)
    return np.concatenate([np.asarray(T.translation()), wxyz[..., 1:], wxyz[..., :1]], axis=-1)


def stack(poses) -> jaxlie.SE3:
    """A batched SE3 from a sequence of poses."""
    return jaxlie.SE3(jnp.stack([as_pose(T).wxyz_xyz for T in poses]))


def camera_axes(T_wc):
    """(R_wc, c): the camera axes (columns) and centre in the world. ``T_wc`` is a
    ``jaxlie.SE3`` or already such a pair of arrays ((…, 3, 3), (…, 3): NumPy stays NumPy)."""
    if isinstance(T_wc, jaxlie.SE3):
        return T_wc.rotation().as_matrix(), T_wc.translation()
    R_wc, c = T_wc
    return R_wc, c


def world_to_camera(T_wc):
    """[R_cw | t_cw] (…, 3, 4), the world-to-camera map x_c = R_cw x + t_cw: the top rows of
    T_wc⁻¹ for a ``jaxlie.SE3``; R_cw = R_wcᵀ, t_cw = −R_wcᵀ c for a pair (R_wc, c) of arrays."""
    if isinstance(T_wc, jaxlie.SE3):
        return T_wc.inverse().as_matrix()[..., :3, :]
    R_wc, c = T_wc
    xp = array_namespace(R_wc, c)
    R_cw = xp.swapaxes(R_wc, -1, -2)
    return xp.concatenate([R_cw, -(R_cw @ c[..., None])], axis=-1)


def quat_to_matrix(q_xyzw) -> np.ndarray:
    """Rotation matrix of a quaternion ``qx qy qz qw`` (normalised here), NumPy."""
    return Rotation.from_quat(np.asarray(q_xyzw, dtype=float)).as_matrix()


def matrix_to_quat(R) -> np.ndarray:
    """Unit quaternion ``qx qy qz qw`` with qw ≥ 0 of a rotation matrix, NumPy."""
    q = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    return np.where(q[..., 3:] < 0, -q, q)


def interpolate_tum(rows, times) -> np.ndarray:
    """Poses (n, 7) ``tx ty tz qx qy qz qw`` of the trajectory ``rows`` (N, 8) TUM rows
    ``t tx ty tz qx qy qz qw`` (sorted here by time, stably) at ``times`` (n,), NumPy.

    Between the samples k and k + 1 around t (t_k ≤ t < t_k+1, k the last of equal times),
    with a = (t − t_k) / (t_k+1 − t_k): the centre c_k + a (c_k+1 − c_k) and the rotation
    R_k Exp(a Log(R_k⁻¹ R_k+1)) (slerp). A sample's time gives the sample itself; a time
    outside [t_0, t_N−1] gives the end pose (no extrapolation: the caller decides whether
    such a time is usable)."""
    P = np.asarray(rows, dtype=float)
    t = np.asarray(times, dtype=float)
    P = P[np.argsort(P[:, 0], kind="stable")]
    ts = P[:, 0]
    k = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 1)
    k1 = np.minimum(k + 1, len(ts) - 1)
    span = ts[k1] - ts[k]
    a = np.where(span > 0, (t - ts[k]) / np.where(span > 0, span, 1.0), 0.0)
    a = np.clip(a, 0.0, 1.0)
    c = P[k, 1:4] + a[:, None] * (P[k1, 1:4] - P[k, 1:4])
    r0, r1 = Rotation.from_quat(P[k, 4:8]), Rotation.from_quat(P[k1, 4:8])
    r = r0 * Rotation.from_rotvec((r0.inv() * r1).as_rotvec() * a[:, None])
    return np.c_[c, r.as_quat()]
