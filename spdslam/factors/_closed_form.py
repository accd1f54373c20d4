"""Closed-form linearisations: a factor type's residual, its Jacobian in tangent coordinates
and its validity, in NumPy over stacked rows, for the factor types that dominate a run.

The solver linearises a group whose residual function has one here without JAX: no
tracing, no compiled program, nothing to load in a new process (docs/performance.md, "The
hot path without a compiler"). Every other factor type, and the batched solver, keep the
general path (forward-mode JAX through the residual); the tests check each closed form
against it and against central differences.

Conventions: poses are ``jaxlie.SE3`` T_wc (camera-to-world) retracted on the right,
T ⊞ δ = T · exp(δ), δ = (ρ, ω): to first order R ← R (I + [ω]×), c ← c + R ρ. A landmark's
tangent directions are its type's pushforward ∂(x ⊞ δ)/∂δ|₀, handed in by the solver (for
an ``Ellipsoid`` the images (dP, dt) of its 9 tangent basis vectors).

Inverse box model (``inverse_box_residual``). With A = R_wcᵀ, the landmark's centre in the
camera frame m = A (t − c) and its shape there S = A P Aᵀ, the dual conic is
C* = K G Kᵀ with G = S − m mᵀ, and with a = G₀₀, b = G₀₂, g = G₂₂, Δ = b² − a g,

    u = c_x + f_x (b ± √Δ) / g,

the sign giving u_min or u_max by the sign of g (v alike with G₁₁, G₁₂, f_y, c_y). Under
the pose's δ: dG = G[ω]× − [ω]×G + ρ mᵀ + m ρᵀ; under the landmark's (dP, dt):
dG = A dP Aᵀ − dm mᵀ − m dmᵀ with dm = A dt.

Object priors on an ``Ellipsoid`` (``orientation_residual``, ``shape_residual``,
``size_residual``, ``radius_floor_residual``). With P = V diag(w) Vᵀ (w ascending) the
landmark's SPD directions are dPₖ = P^½ Eₖ P^½ (its chart's, ``geometry.spd``), so that
Vᵀ dPₖ V = (√w √wᵀ) ∘ (Vᵀ Eₖ V); its centre directions change none of them. Then
dwᵢ = (Vᵀ dPₖ V)ᵢᵢ, averaged over the eigenvalues tied with wᵢ (``matfun.eigh``'s rule);
d log det P = tr Eₖ; and d log P = V (F ∘ Vᵀ dPₖ V) Vᵀ with Fᵢⱼ = (log wᵢ − log wⱼ)/(wᵢ − wⱼ),
1/((wᵢ + wⱼ)/2) at ties (``matfun.spectral``'s Daleckii–Krein rule).

Pose prior and between factors (``pose_prior_residual``, ``pose_between_residual``). With
E = T̄⁻¹ T (prior) or E = T̄₁₂⁻¹ D, D = T₁⁻¹ T₂ (between), r = Log(E), and

    ∂r/∂δ = J_r⁻¹(r),   ∂r/∂δ₂ = J_r⁻¹(r),   ∂r/∂δ₁ = −J_r⁻¹(r) Ad(D⁻¹),

the last from T̄₁₂⁻¹ Exp(−δ₁) D = E Exp(−Ad(D⁻¹) δ₁) (``geometry.se3.right_jacobian_inverse``).
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Callable

import jaxlie
import numpy as np

from ..geometry import Ellipsoid, native, spd
from ..geometry.matfun import TIE_RTOL
from ..geometry.se3 import (
    adjoint_params,
    compose_params,
    inverse_params,
    log_params,
    quat_to_matrix,
    right_jacobian_inverse,
)
from ._box import box_visible, inverse_box_residual
from ._object import orientation_residual, radius_floor_residual, shape_residual, size_residual
from ._pose import pose_between_residual, pose_prior_residual

__all__ = ["ClosedForm", "closed_form", "eigenvalue_steps", "ellipsoid_boxes", "inverse_box_linearization",
           "pose_prior_linearization", "pose_between_linearization", "orientation_linearization", "shape_linearization",
           "size_linearization", "radius_floor_linearization"]


@dataclass(frozen=True)
class ClosedForm:
    """A residual function's NumPy linearisation (``closed_form``).

    ``linearize(xs, Ts, args, jacobian)`` takes the stacked variables of n factors (``xs``,
    one pytree with NumPy leaves per variable), their pushforwards (``Ts``: per variable a
    pair (rows, index), the pushforwards of every variable of that type, stacked, and the
    row of each of the n factors' in them, (n,); not gathered per factor, since a landmark's
    is shared by its many factors) and the stacked data (``args``) and returns (r (n, m),
    J (n, m, D) in tangent coordinates or None without ``jacobian``, validity (n,) or None).
    It stands for ``residual`` with the validity rule ``valid`` when the variables are of
    ``types``. ``pushforwards``: for each variable, whether ``linearize`` reads its
    pushforward (the solver computes only those; an entry of ``Ts`` it does not read may be
    None)."""

    residual: Callable
    valid: Callable | None
    types: tuple[type, ...]
    linearize: Callable
    pushforwards: tuple[bool, ...] = ()


_CLOSED: dict[Callable, ClosedForm] = {}


def closed_form(residual: Callable, valid: Callable | None = None,
                types: tuple[type, ...] = ()) -> ClosedForm | None:
    """The closed form of ``residual`` for that validity rule and variable types, or None."""
    cf = _CLOSED.get(residual)
    if cf is None or cf.valid is not valid or tuple(types) != cf.types:
        return None
    return cf


def _register(cf: ClosedForm) -> None:
    _CLOSED[cf.residual] = cf


#: The entries (I[e], J[e]) of G the box edges read: (a, b, g) = (G₀₀, G₀₂, G₂₂) for u,
#: (G₁₁, G₁₂, G₂₂) for v.
_I, _J = np.array([0, 1, 2, 0, 1]), np.array([0, 1, 2, 2, 2])


def _box_jacobian(dr, G, m, A, T_landmark):
    """∂r/∂(ρ, ω, landmark) (n, 4, 6 + 9) = dr ∂G_e/∂(…) from dr = ∂r/∂G_e (n, 4, 5), for
    the entries e = (i, j) of ``_I``, ``_J``:

        ρ ↦ e_i m_j + m_i e_j,   ω ↦ e_j × g_i + e_i × g_j   (g_i: row i of G),
        (dP, dt) ↦ a_iᵀ dP a_j − (m_j a_i + m_i a_j)·dt   (a_i: row i of A),

    the pose's written out entry by entry (most are 0), the landmark's as dr times the
    coefficients of (dP, dt) (n, 4, 12), then times the landmark's directions: its
    pushforward ``T_landmark`` = (rows, index) (``ClosedForm``), as (12, 9) per landmark."""
    n = len(G)
    dG = np.zeros((n, 5, 6))
    g00, g11, g22, g01, g02, g12 = G[:, 0, 0], G[:, 1, 1], G[:, 2, 2], G[:, 0, 1], G[:, 0, 2], G[:, 1, 2]
    m0, m1, m2 = m[:, 0], m[:, 1], m[:, 2]
    # ρ
    dG[:, 0, 0], dG[:, 1, 1], dG[:, 2, 2] = 2.0 * m0, 2.0 * m1, 2.0 * m2
    dG[:, 3, 0], dG[:, 3, 2] = m2, m0
    dG[:, 4, 1], dG[:, 4, 2] = m2, m1
    # ω
    dG[:, 0, 4], dG[:, 0, 5] = -2.0 * g02, 2.0 * g01
    dG[:, 1, 3], dG[:, 1, 5] = 2.0 * g12, -2.0 * g01
    dG[:, 2, 3], dG[:, 2, 4] = -2.0 * g12, 2.0 * g02
    dG[:, 3, 3], dG[:, 3, 4], dG[:, 3, 5] = -g01, g00 - g22, g12
    dG[:, 4, 3], dG[:, 4, 4], dG[:, 4, 5] = g22 - g11, g01, -g02
    rows, index = T_landmark
    T = _directions(np.asarray(rows.P), np.asarray(rows.center))[index]
    return np.concatenate([dr @ dG, (dr @ _coefficients(A[:, None], m[:, None])[:, 0]) @ T], axis=2)


def _coefficients(A, m):
    """The coefficients (B, K, 5, 12) of a landmark's (dP, dt) (9 + 3, row-major) in ∂G_e for
    the entries e of ``_I``, ``_J`` seen from B × K cameras (A (B, K, 3, 3), m (B, K, 3)):
    a_iᵀ dP a_j − (m_j a_i + m_i a_j)·dt."""
    B, K = m.shape[:2]
    AI, AJ = A[:, :, _I], A[:, :, _J]
    dGP = np.einsum("bkei,bkej->bkeij", AI, AJ).reshape(B, K, 5, 9)
    dGt = -(m[:, :, _J, None] * AI + m[:, :, _I, None] * AJ)
    return np.concatenate([dGP, dGt], axis=3)


def _directions(TP, Tt):
    """B landmarks' Q directions (dP (B, Q, 3, 3), dt (B, Q, 3)) as columns (B, 12, Q),
    contiguous (matmul's fast path takes both operands so)."""
    B, Q = Tt.shape[:2]
    T = np.empty((B, 12, Q))
    T[:, :9] = np.swapaxes(TP.reshape(B, Q, 9), 1, 2)
    T[:, 9:] = np.swapaxes(Tt, 1, 2)
    return T


def _edges(a, b, g, f, c0, jacobian: bool):
    """(lower, upper) image coordinates c0 + f (b ± √Δ)/g, Δ = b² − a g (√ of Δ ≤ 0 taken
    as 0, with derivative 0, as ``geometry.conic_box``), and with ``jacobian`` their
    derivatives (n, 3) by (a, b, g)."""
    delta = b * b - a * g
    pos = delta > 0
    s = np.where(pos, np.sqrt(np.where(pos, delta, 1.0)), 0.0)
    sign_lo = np.where(g < 0, 1.0, -1.0)  # (b + σ s)/g is the smaller with σ = sign_lo
    if jacobian:
        inv_2s = np.where(pos, 0.5 / np.where(pos, s, 1.0), 0.0)
        ds = (-g * inv_2s, 2.0 * b * inv_2s, -a * inv_2s)  # ∂√Δ/∂(a, b, g)
    out: list[tuple[np.ndarray, np.ndarray | None]] = []
    for sigma in (sign_lo, -sign_lo):
        value = c0 + f * (b + sigma * s) / g
        d = None
        if jacobian:
            d = np.stack([f * sigma * ds[0] / g,
                          f * (1.0 + sigma * ds[1]) / g,
                          f * sigma * ds[2] / g - f * (b + sigma * s) / (g * g)], axis=-1)
        out.append((value, d))
    return out


def _box_of_entries(g, cam, jacobian: bool):
    """The box [u_min, v_min, u_max, v_max] (…, 4) of G's entries g (…, 5) = (G₀₀, G₁₁, G₂₂,
    G₀₂, G₁₂) (module docstring) and with ``jacobian`` its derivative (…, 4, 5) by them."""
    fx, fy, cx, cy = (np.asarray(v, dtype=float) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
    (u0, du0), (u1, du1) = _edges(g[..., 0], g[..., 3], g[..., 2], fx, cx, jacobian)
    (v0, dv0), (v1, dv1) = _edges(g[..., 1], g[..., 4], g[..., 2], fy, cy, jacobian)
    box = np.stack([u0, v0, u1, v1], axis=-1)
    if not jacobian:
        return box, None
    dr = np.zeros(box.shape + (5,))
    for row, d, (ia, ib) in ((0, du0, (0, 3)), (2, du1, (0, 3)), (1, dv0, (1, 4)), (3, dv1, (1, 4))):
        dr[..., row, ia] = d[..., 0]
        dr[..., row, ib] = d[..., 1]
        dr[..., row, 2] = d[..., 2]
    return box, dr


def ellipsoid_boxes(A, c, P, t, camera, directions=None):
    """The boxes [u_min, v_min, u_max, v_max] (B, K, 4) of B ellipsoids (P (B, 3, 3), centres
    t (B, 3)), each seen from K cameras (A = R_wcᵀ (B, K, 3, 3), centres c (B, K, 3)), by
    the inverse box model's closed form (module docstring); with ``directions`` = (dP (B, Q,
    3, 3), dt (B, Q, 3)) also their derivatives (B, K, 4, Q) along each ellipsoid's Q
    directions, shared by its K views. Only meaningful in front of each camera."""
    A, P, t = (np.asarray(x, dtype=float) for x in (A, P, t))
    B, K = A.shape[:2]
    Af = A.reshape(B, K * 3, 3)
    m = (Af @ t[:, :, None]).reshape(B, K, 3) - np.einsum("bkij,bkj->bki", A, c)
    S = (Af @ P).reshape(B, K, 3, 3) @ np.ascontiguousarray(np.swapaxes(A, 2, 3))  # A P Aᵀ
    g = S.reshape(B, K, 9)[:, :, _I * 3 + _J] - m[:, :, _I] * m[:, :, _J]
    box, dbox = _box_of_entries(g, camera, directions is not None)
    if directions is None:
        return box, None
    T = _directions(np.asarray(directions[0]), np.asarray(directions[1]))
    return box, ((dbox @ _coefficients(A, m)).reshape(B, K * 4, 12) @ T).reshape(B, K, 4, T.shape[2])


def inverse_box_linearization(xs, Ts, args, jacobian: bool = True):
    """``inverse_box_residual`` of n stacked (pose, Ellipsoid) pairs: (r (n, 4), J (n, 4, 15)
    or None, ``box_visible`` (n,)). See the module docstring for the derivation."""
    pose, lm = xs
    box_obs, cam = args[0], args[1]
    keep = args[2] if len(args) > 2 else None
    lib = native.native_kernels()
    if lib is not None:  # the same, per row in C (geometry.native)
        directions = index = None
        if jacobian:
            rows, index = Ts[1]
            directions = _directions(np.asarray(rows.P), np.asarray(rows.center))
        return native.box_linearize(lib, np.asarray(pose.wxyz_xyz), np.asarray(lm.P), np.asarray(lm.center),
                                    np.asarray(box_obs), (cam.fx, cam.fy, cam.cx, cam.cy),
                                    None if keep is None else np.asarray(keep), directions, index, _MIN_DEPTH)
    q = np.asarray(pose.wxyz_xyz)
    ok = np.all(np.isfinite(q), axis=1) & np.any(q[:, :4] != 0, axis=1)  # a pose a step sent astray: NaN out
    R = quat_to_matrix(np.where(ok[:, None], q[:, [1, 2, 3, 0]], [0.0, 0.0, 0.0, 1.0]))  # jaxlie's wxyz as xyzw
    R = np.where(ok[:, None, None], R, np.nan)
    A = np.swapaxes(R, 1, 2)
    P, t = np.asarray(lm.P), np.asarray(lm.center)
    m = np.einsum("nij,nj->ni", A, t - q[:, 4:])
    G = A @ P @ R - m[:, :, None] * m[:, None, :]
    box, dbox = _box_of_entries(G[:, _I, _J], cam, jacobian)
    r = box - np.asarray(box_obs)
    valid = _in_front(A, P, m)
    if keep is not None:
        r = r * keep
    if not jacobian:
        return r, None, valid
    dr = dbox if keep is None else dbox * keep[:, :, None]
    return r, _box_jacobian(dr, G, m, A, Ts[1]), valid


#: ``box_visible``'s depth margin, read from its signature (one place for the number).
_MIN_DEPTH = inspect.signature(box_visible).parameters["min_depth"].default


def _in_front(A, P, m, min_depth: float = _MIN_DEPTH):
    """``geometry.in_front`` from the camera-frame centre: z_c − √(a₂ᵀ P a₂) > min_depth."""
    a2 = A[:, 2]
    half2 = np.einsum("ni,nij,nj->n", a2, P, a2)
    half = np.where(half2 > 0, np.sqrt(np.where(half2 > 0, half2, 1.0)), 0.0)
    return m[:, 2] - half > min_depth


def pose_prior_linearization(xs, Ts, args, jacobian: bool = True):
    """``pose_prior_residual`` of n stacked poses: (r (n, 6), J (n, 6, 6) or None, None)."""
    (T,), (T_prior,) = xs, args
    lib = native.native_kernels()
    if lib is not None:  # the same, per row in C (geometry.native)
        return (*native.pose_prior(lib, np.asarray(T.wxyz_xyz), np.asarray(T_prior.wxyz_xyz), jacobian), None)
    r = log_params(compose_params(inverse_params(np.asarray(T_prior.wxyz_xyz)), np.asarray(T.wxyz_xyz)))
    return r, (right_jacobian_inverse(r) if jacobian else None), None


def pose_between_linearization(xs, Ts, args, jacobian: bool = True):
    """``pose_between_residual`` of n stacked pose pairs: (r (n, 6), J (n, 6, 12) or None,
    None)."""
    (T1, T2), (T12,) = xs, args
    lib = native.native_kernels()
    if lib is not None:  # the same, per row in C (geometry.native)
        return (*native.pose_between(lib, np.asarray(T1.wxyz_xyz), np.asarray(T2.wxyz_xyz),
                                     np.asarray(T12.wxyz_xyz), jacobian), None)
    D = compose_params(inverse_params(np.asarray(T1.wxyz_xyz)), np.asarray(T2.wxyz_xyz))
    r = log_params(compose_params(inverse_params(np.asarray(T12.wxyz_xyz)), D))
    if not jacobian:
        return r, None, None
    Jr = right_jacobian_inverse(r)
    return r, np.concatenate([-Jr @ adjoint_params(inverse_params(D)), Jr], axis=2), None


def _spectrum(landmark):
    """(w (n, 3) ascending, V (n, 3, 3), Vᵀ dPₖ V (n, 6, 3, 3), the tie mask (n, 3, 3)) of
    stacked Ellipsoids' P (symmetrised, as ``matfun.eigh`` takes it)."""
    w, V = spd.host_eigh(landmark.P)  # a step gone astray: NaN out, as the program's
    M = np.einsum("nai,kab,nbj->nkij", V, spd.BASIS, V)
    rw = np.sqrt(np.maximum(w, 0.0))
    dE = (rw[:, :, None] * rw[:, None, :])[:, None] * M
    scale = np.maximum(np.abs(w).max(axis=1), 1e-300)
    tie = np.abs(w[:, :, None] - w[:, None, :]) <= TIE_RTOL * scale[:, None, None]
    return w, V, dE, tie


def _eigenvalue_steps(dE, tie):
    """dwᵢ (n, 6, 3) per SPD direction: the diagonal of Vᵀ dPₖ V averaged over ties."""
    t = tie.astype(float)
    return np.einsum("nij,nkj->nki", t, np.diagonal(dE, axis1=2, axis2=3)) / t.sum(axis=2)[:, None, :]


def eigenvalue_steps(landmark):
    """(w (n, 3) ascending, dw (n, 6, 3)): the eigenvalues of stacked Ellipsoids' P and
    their derivatives along the six SPD chart directions dPₖ = P^½ Eₖ P^½ (``matfun.eigh``'s
    rule at tied eigenvalues: the mean of the tied ones' changes)."""
    w, _, dE, tie = _spectrum(landmark)
    return w, _eigenvalue_steps(dE, tie)


def _landmark_jacobian(J6):
    """(n, m, 6) SPD columns → (n, m, 9): the centre's three columns are zero."""
    return np.concatenate([J6, np.zeros(J6.shape[:2] + (3,))], axis=2)


def orientation_linearization(xs, Ts, args, jacobian: bool = True):
    """``orientation_residual`` of n stacked Ellipsoids: r = (Log(P) m) × m (n, 3), J (n, 3, 9)."""
    (lm,), (m,) = xs, args
    m = np.asarray(m, float)
    m = m / np.linalg.norm(m, axis=1, keepdims=True)
    w, V, dE, tie = _spectrum(lm)
    lw = np.log(np.maximum(w, 1e-300))
    L = (V * lw[:, None, :]) @ np.swapaxes(V, 1, 2)
    r = np.cross(np.einsum("nij,nj->ni", L, m), m)
    if not jacobian:
        return r, None, None
    wi, wj = w[:, :, None], w[:, None, :]
    F = np.where(tie, 1.0 / np.maximum(0.5 * (wi + wj), 1e-300),
                 (lw[:, :, None] - lw[:, None, :]) / np.where(tie, 1.0, wi - wj))
    dL = V[:, None] @ (F[:, None] * dE) @ np.swapaxes(V, 1, 2)[:, None]  # (n, 6, 3, 3)
    dr = np.cross(np.einsum("nkij,nj->nki", dL, m), m[:, None, :])  # (n, 6, 3)
    return r, _landmark_jacobian(np.swapaxes(dr, 1, 2)), None


def shape_linearization(xs, Ts, args, jacobian: bool = True):
    """``shape_residual`` of n stacked Ellipsoids: [s₁/s₃, s₂/s₃] − prior (n, 2), J (n, 2, 9)."""
    (lm,), (prior,) = xs, args
    w, _, dE, tie = _spectrum(lm)
    s = np.sqrt(np.maximum(w[:, ::-1], 1e-300))  # s₁ ≥ s₂ ≥ s₃
    r = s[:, :2] / s[:, 2:3] - np.asarray(prior, float)
    if not jacobian:
        return r, None, None
    ds = _eigenvalue_steps(dE, tie)[:, :, ::-1] / (2.0 * s[:, None, :])  # (n, 6, 3)
    J = ds[:, :, :2] / s[:, None, 2:3] - (s[:, :2] / s[:, 2:3] ** 2)[:, None, :] * ds[:, :, 2:3]
    return r, _landmark_jacobian(np.swapaxes(J, 1, 2)), None


def size_linearization(xs, Ts, args, jacobian: bool = True):
    """``size_residual`` of n stacked Ellipsoids: (½ log det P − log abc)/3 (n, 1); its
    derivative along dPₖ is tr Eₖ / 6, the same at every P."""
    (lm,), (log_volume,) = xs, args
    logdet = np.linalg.slogdet(np.asarray(lm.P, float))[1]
    r = ((0.5 * logdet - np.asarray(log_volume, float)) / 3.0)[:, None]
    if not jacobian:
        return r, None, None
    J6 = np.broadcast_to(np.trace(spd.BASIS, axis1=1, axis2=2) / 6.0, (len(r), 1, 6))
    return r, _landmark_jacobian(np.ascontiguousarray(J6)), None


def radius_floor_linearization(xs, Ts, args, jacobian: bool = True):
    """``radius_floor_residual`` of n stacked Ellipsoids: max(0, log ρ − ½ log w₀) (n, 1);
    its derivative −½ dw₀/w₀ where positive (half of it at 0, as JAX's max)."""
    (lm,), (log_floor,) = xs, args
    w, _, dE, tie = _spectrum(lm)
    x = np.asarray(log_floor, float) - 0.5 * np.log(np.maximum(w[:, 0], 1e-300))
    r = np.maximum(0.0, x)[:, None]
    if not jacobian:
        return r, None, None
    share = np.where(x > 0, 1.0, np.where(x == 0, 0.5, 0.0))
    J6 = (share / np.maximum(w[:, 0], 1e-300))[:, None] * -0.5 * _eigenvalue_steps(dE, tie)[:, :, 0]
    return r, _landmark_jacobian(J6[:, None, :]), None


_register(ClosedForm(inverse_box_residual, box_visible, (jaxlie.SE3, Ellipsoid), inverse_box_linearization,
                     (False, True)))
_register(ClosedForm(pose_prior_residual, None, (jaxlie.SE3,), pose_prior_linearization, (False,)))
_register(ClosedForm(pose_between_residual, None, (jaxlie.SE3, jaxlie.SE3), pose_between_linearization,
                     (False, False)))
for _residual, _linearize in ((orientation_residual, orientation_linearization), (shape_residual, shape_linearization),
                              (size_residual, size_linearization), (radius_floor_residual, radius_floor_linearization)):
    _register(ClosedForm(_residual, None, (Ellipsoid,), _linearize, (False,)))
