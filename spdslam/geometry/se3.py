"""SE(3) poses (through jaxlie) and the one convention spdslam uses.

A pose ``T_wc`` maps camera coordinates to world coordinates (camera-to-world): its
translation is the camera centre in the world, its rotation's columns are the camera axes
(x right, y down, z forward along the optical axis) in the world. TUM trajectory lines
``timestamp tx ty tz qx qy qz qw`` store exactly this pose. Tangent vectors are jaxlie's
(v, ω), translation first, with the right perturbation T ⊞ δ = T · Exp(δ).
``interpolate_tum`` reads a TUM trajectory between its samples.

The ``*_params`` functions and ``right_jacobian_inverse`` are the group's operations in
NumPy on stacked jaxlie parameters (…, 7) ``qw qx qy qz tx ty tz`` (``SE3.wxyz_xyz``), for
host code that must not trace or compile (``factors.closed_form``); each equals jaxlie's
operation to round-off (tests/test_se3.py).
"""

from __future__ import annotations

import jax
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
    "compose_params",
    "inverse_params",
    "log_params",
    "exp_params",
    "adjoint_params",
    "right_jacobian_inverse",
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
    if isinstance(values, jax.core.Tracer):  # inside a traced function
        v = jnp.asarray(values, dtype=float)
        q_xyzw = v[..., 3:7]
        q = q_xyzw / jnp.linalg.norm(q_xyzw, axis=-1, keepdims=True)
        wxyz = jnp.concatenate([q[..., 3:4], q[..., :3]], axis=-1)
        return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3(wxyz), v[..., :3])
    # the slicing and concatenation (exact) on the host; the norm and the division in XLA,
    # whose rounding the results so far carry (NumPy's differs in the last bit)
    rows = np.asarray(values, dtype=float)
    q_dev = jax.device_put(np.ascontiguousarray(rows[..., 3:7]))
    q = np.asarray(q_dev / jnp.linalg.norm(q_dev, axis=-1, keepdims=True))
    return jaxlie.SE3(jax.device_put(np.concatenate([q[..., 3:4], q[..., :3], rows[..., :3]], axis=-1)))


def to_tum(T) -> np.ndarray:
    """TUM fields ``tx ty tz qx qy qz qw`` (…, 7) of pose(s), with qw ≥ 0."""
    p = np.asarray(as_pose(T).wxyz_xyz)  # read on the host: nothing to compile
    wxyz = np.where(p[..., :1] < 0, -p[..., :4], p[..., :4])
    return np.concatenate([p[..., 4:], wxyz[..., 1:], wxyz[..., :1]], axis=-1)


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


# ------------------------------------------------------------------------------------------
# The group's operations in NumPy on jaxlie parameters (…, 7) qw qx qy qz tx ty tz
# ------------------------------------------------------------------------------------------

#: jaxlie's float64 threshold on ‖q_xyz‖² and θ² below which it takes Taylor expansions.
_JAXLIE_EPS = 1e-10
#: θ below which the coefficients of ``right_jacobian_inverse``'s Q take their series (the
#: closed forms lose digits to cancellation as θ → 0).
_Q_SERIES = 1e-2


def _hat(w) -> np.ndarray:
    """[w]× (…, 3, 3)."""
    w = np.asarray(w, dtype=float)
    o = np.zeros(w.shape[:-1])
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    return np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2)


def _quat_mul(a, b) -> np.ndarray:
    """Hamilton product of (…, 4) wxyz quaternions."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def _rotation(T) -> np.ndarray:
    q = np.asarray(T, dtype=float)[..., :4]
    return quat_to_matrix(q.reshape(-1, 4)[:, [1, 2, 3, 0]]).reshape(q.shape[:-1] + (3, 3))


def compose_params(a, b) -> np.ndarray:
    """a · b: (q_a q_b, R_a t_b + t_a)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    t = np.einsum("...ij,...j->...i", _rotation(a), b[..., 4:]) + a[..., 4:]
    return np.concatenate([_quat_mul(a[..., :4], b[..., :4]), t], axis=-1)


def inverse_params(a) -> np.ndarray:
    """a⁻¹: (q̄, −Rᵀ t) (unit quaternions)."""
    a = np.asarray(a, dtype=float)
    q = a[..., :4] * np.array([1.0, -1.0, -1.0, -1.0])
    t = -np.einsum("...ji,...j->...i", _rotation(a), a[..., 4:])
    return np.concatenate([q, t], axis=-1)


def _so3_left_jacobian_inverse(w) -> np.ndarray:
    """J_l⁻¹(ω) = I − ½[ω]× + (1 − θ cos(θ/2) / (2 sin(θ/2)))/θ² [ω]×² (jaxlie's, with its
    Taylor expansion for θ² < 1e-10)."""
    th2 = np.sum(w * w, axis=-1)
    small = th2 < _JAXLIE_EPS
    th2s = np.where(small, 1.0, th2)
    th = np.sqrt(th2s)
    c = np.where(small, 1.0 / 12.0, (1.0 - th * np.cos(th / 2) / (2.0 * np.sin(th / 2))) / th2s)
    W = _hat(w)
    return np.eye(3) - 0.5 * W + c[..., None, None] * (W @ W)


def log_params(T) -> np.ndarray:
    """Log(T) = (V⁻¹ t, ω) (…, 6), ω the rotation vector with |ω| ≤ π, V⁻¹ = J_l⁻¹(ω)
    (jaxlie's SE3.log)."""
    T = np.asarray(T, dtype=float)
    w, v = T[..., 0], T[..., 1:4]
    n2 = np.sum(v * v, axis=-1)
    small = n2 < _JAXLIE_EPS
    n = np.sqrt(np.where(small, 1.0, n2))
    ws = np.where(small, w, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(
            small, 2.0 / ws - 2.0 / 3.0 * n2 / ws**3,
            np.where(np.abs(w) < _JAXLIE_EPS, np.where(w > 0, 1.0, -1.0) * np.pi / n,
                     2.0 * np.arctan2(np.where(w < 0, -n, n), np.abs(w)) / n))
    omega = factor[..., None] * v
    rho = np.einsum("...ij,...j->...i", _so3_left_jacobian_inverse(omega), T[..., 4:])
    return np.concatenate([rho, omega], axis=-1)


def exp_params(xi) -> np.ndarray:
    """Exp(ξ) (…, 7) of ξ = (v, ω) (…, 6): q = (cos(θ/2), sin(θ/2) ω/θ), t = V(ω) v with
    V = I + (1 − cos θ)/θ² [ω]× + (θ − sin θ)/θ³ [ω]×² (jaxlie's SE3.exp, with its Taylor
    expansions for θ² < 1e-10: q to θ⁴, V = R)."""
    xi = np.asarray(xi, dtype=float)
    w = xi[..., 3:]
    th2 = np.sum(w * w, axis=-1)
    small = th2 < _JAXLIE_EPS
    th2s = np.where(small, 1.0, th2)
    th = np.sqrt(th2s)
    real = np.where(small, 1.0 - th2 / 8.0 + th2 * th2 / 384.0, np.cos(0.5 * th))
    imag = np.where(small, 0.5 - th2 / 48.0 + th2 * th2 / 3840.0, np.sin(0.5 * th) / th)
    q = np.concatenate([real[..., None], imag[..., None] * w], axis=-1)
    W = _hat(w)
    V = np.eye(3) + ((1.0 - np.cos(th)) / th2s)[..., None, None] * W + ((th - np.sin(th)) / (th2s * th))[
        ..., None, None] * (W @ W)
    V = np.where(small[..., None, None], _rotation(np.concatenate([q, np.zeros(q.shape[:-1] + (3,))], -1)), V)
    return np.concatenate([q, np.einsum("...ij,...j->...i", V, xi[..., :3])], axis=-1)


def adjoint_params(T) -> np.ndarray:
    """Ad(T) (…, 6, 6) in (v, ω) order: [[R, [t]× R], [0, R]], so that T Exp(δ) T⁻¹ =
    Exp(Ad(T) δ)."""
    T = np.asarray(T, dtype=float)
    R = _rotation(T)
    out = np.zeros(T.shape[:-1] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = _hat(T[..., 4:]) @ R
    return out


def right_jacobian_inverse(xi) -> np.ndarray:
    """J_r⁻¹(ξ) (…, 6, 6) of SE(3) in (v, ω) order: Log(Exp(ξ) Exp(δ)) = ξ + J_r⁻¹(ξ) δ + O(δ²).

    J_r⁻¹(ξ) = J_l⁻¹(−ξ) = [[A, −A Q A], [0, A]] with A = J_l⁻¹(−ω) of SO(3) and Q = Q(−ρ, −ω),
    Barfoot's (State Estimation for Robotics, eq. 7.86)

        Q(ρ, φ) = ½[ρ] + c₁([φ][ρ] + [ρ][φ] + [φ][ρ][φ]) + c₂([φ]²[ρ] + [ρ][φ]² − 3[φ][ρ][φ])
                  + c₃([φ][ρ][φ]² + [φ]²[ρ][φ]),
        c₁ = (θ − sin θ)/θ³,  c₂ = (θ² + 2 cos θ − 2)/(2θ⁴),  c₃ = (2θ − 3 sin θ + θ cos θ)/(2θ⁵)

    ([·] = [·]×), each cᵢ by its series to θ⁴ below θ = 10⁻²."""
    xi = -np.asarray(xi, dtype=float)
    rho, phi = xi[..., :3], xi[..., 3:]
    th2 = np.sum(phi * phi, axis=-1)
    small = th2 < _Q_SERIES**2
    th = np.sqrt(np.where(small, 1.0, th2))
    s, c = np.sin(th), np.cos(th)
    c1 = np.where(small, 1 / 6 - th2 / 120 + th2**2 / 5040, (th - s) / th**3)
    c2 = np.where(small, 1 / 24 - th2 / 720 + th2**2 / 40320, (th * th + 2 * c - 2) / (2 * th**4))
    c3 = np.where(small, 1 / 120 - th2 / 2520 + th2**2 / 120960, (2 * th - 3 * s + th * c) / (2 * th**5))
    P, Rh = _hat(phi), _hat(rho)
    PR, RP, PP = P @ Rh, Rh @ P, P @ P
    PRP = PR @ P
    Q = (0.5 * Rh + c1[..., None, None] * (PR + RP + PRP) + c2[..., None, None] * (PP @ Rh + RP @ P - 3 * PRP)
         + c3[..., None, None] * (PRP @ P + PP @ RP))
    A = _so3_left_jacobian_inverse(phi)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = A
    out[..., 3:, 3:] = A
    out[..., :3, 3:] = -A @ Q @ A
    return out
