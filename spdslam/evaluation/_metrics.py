"""Evaluation of estimated objects against ground truth: oriented cuboids, 3D IoU, errors.

A cuboid is C = {c + R q : |q_k| ≤ h_k}, centre c, axes the columns of R, half-extents h > 0.
A landmark's circumscribed cuboid has c = t, R and h = s from ``Ellipsoid.axes()``.

- ``cuboid_iou``: exact |A ∩ B| / |A ∪ B| of two oriented cuboids. A ∩ B is a convex
  polytope whose vertices are the corners of each cuboid inside the other and the points
  where an edge of one crosses a face plane of the other; its volume is that of their
  convex hull (``scipy.spatial.ConvexHull``).
- ``orientation_error_deg``: the angle of the rotation aligning the estimate's axes with the
  ground truth's, whatever the order and signs of the axes (min over the octahedral group).
- ``translation_error``: ‖c_est − c_gt‖.

Pure numpy/scipy; every input is validated and degenerate ones raise ``ValueError``.
"""

from __future__ import annotations

import itertools
from typing import Sequence

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from ..geometry import CORNER_SIGNS, CUBOID_EDGES, Cuboid, align_rigid, as_cuboid
from ..geometry import checked_rotation as _orthonormal
from ..geometry import checked_vector as _vector

__all__ = [
    "cuboid_iou",
    "cuboid_iou_batch",
    "trajectory_alignment",
    "orientation_error_deg",
    "translation_error",
    "signed_permutations",
    "MAX_ORIENTATION_ERROR_DEG",
]


def _signed_permutations() -> np.ndarray:
    """All 48 signed permutation matrices (48×3×3), the 24 with det +1 first."""
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            G = np.zeros((3, 3))
            G[list(perm), range(3)] = signs
            mats.append(G)
    stack = np.array(mats)
    return stack[np.argsort(-np.round(np.linalg.det(stack)), kind="stable")]


_SIGNED_PERMS = _signed_permutations()


def signed_permutations(proper: bool = True) -> np.ndarray:
    """The 24 signed permutation matrices with det +1 (the octahedral group), or det −1."""
    return (_SIGNED_PERMS[:24] if proper else _SIGNED_PERMS[24:]).copy()


#: sup over R ∈ SO(3) of min_G angle(R G): the covering radius of the octahedral group,
#: 2 atan √(23 − 16√2) ≈ 62.7994°, attained at the rotation about (1, 1, √2 − 1).
MAX_ORIENTATION_ERROR_DEG = float(np.degrees(2.0 * np.arctan(np.sqrt(23.0 - 16.0 * np.sqrt(2)))))


# --- IoU ----------------------------------------------------------------------------------


def _stack(cuboids: Sequence[Cuboid]):
    c = np.stack([q.center for q in cuboids])
    R = np.stack([q.rotation for q in cuboids])
    h = np.stack([q.half_extents for q in cuboids])
    return c, R, h


def _edge_crossings(corners, c, R, h):
    """Points where the 12 edges of one cuboid (corners n×8×3) cross the 6 face planes
    q_k = ±h_k of another (c, R, h): n×72×3, and a mask of the crossings within the edge."""
    q = (corners - c[:, None, :]) @ R  # local coordinates, n×8×3
    q0, q1 = q[:, CUBOID_EDGES[:, 0]], q[:, CUBOID_EDGES[:, 1]]  # n×12×3
    p0 = corners[:, CUBOID_EDGES[:, 0]]
    d = corners[:, CUBOID_EDGES[:, 1]] - p0
    target = np.stack([-h, h], axis=-1)[:, None, :, :]  # n×1×3×2
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (target - q0[..., None]) / (q1 - q0)[..., None]  # n×12×3×2
    ok = np.isfinite(u) & (u >= -1e-12) & (u <= 1.0 + 1e-12)
    u = np.clip(np.where(ok, u, 0.0), 0.0, 1.0)
    pts = p0[:, :, None, None, :] + u[..., None] * d[:, :, None, None, :]  # n×12×3×2×3
    n = corners.shape[0]
    return pts.reshape(n, 72, 3), ok.reshape(n, 72)


def _inside(points, c, R, h, tol):
    """n×m mask of points (n×m×3) inside the cuboids (c, R, h), n of them, up to tol (n,)."""
    q = (points - c[:, None, :]) @ R
    return np.all(np.abs(q) <= h[:, None, :] + tol[:, None, None], axis=-1)


def _hull_volume(pts: np.ndarray, tol: float) -> float:
    """Volume of the convex hull of pts (m×3); 0 when fewer than 4 or (nearly) coplanar."""
    if len(pts) < 4:
        return 0.0
    pts = pts[np.unique(np.round(pts / tol), axis=0, return_index=True)[1]]
    if len(pts) < 4:
        return 0.0
    centred = pts - pts.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
    if np.max(np.abs(centred @ normal)) <= tol:
        return 0.0
    for options in (None, "QJ"):
        try:
            return float(ConvexHull(pts, qhull_options=options).volume)
        except QhullError:
            continue
    return 0.0


def _iou_arrays(ca, Ra, ha, cb, Rb, hb) -> np.ndarray:
    n = ca.shape[0]
    ca, cb = np.zeros_like(ca), cb - ca  # IoU is translation invariant: work about c_a
    tol = 1e-11 * np.maximum(ha.max(axis=1), hb.max(axis=1)) + 1e-13 * np.abs(cb).max(axis=1)
    corners_a = ca[:, None, :] + (CORNER_SIGNS * ha[:, None, :]) @ Ra.transpose(0, 2, 1)
    corners_b = cb[:, None, :] + (CORNER_SIGNS * hb[:, None, :]) @ Rb.transpose(0, 2, 1)
    cross_ab, ok_ab = _edge_crossings(corners_a, cb, Rb, hb)  # edges of A, faces of B
    cross_ba, ok_ba = _edge_crossings(corners_b, ca, Ra, ha)  # edges of B, faces of A
    cand = np.concatenate([corners_a, corners_b, cross_ab, cross_ba], axis=1)  # n×160×3
    ok = np.concatenate([np.ones((n, 16), bool), ok_ab, ok_ba], axis=1)
    ok &= _inside(cand, ca, Ra, ha, tol) & _inside(cand, cb, Rb, hb, tol)
    va, vb = 8.0 * ha.prod(axis=1), 8.0 * hb.prod(axis=1)
    # Bounding spheres apart ⇒ disjoint (the inside test would already leave nothing).
    reach = np.linalg.norm(ha, axis=1) + np.linalg.norm(hb, axis=1)
    near = np.linalg.norm(cb, axis=1) <= reach
    inter = np.zeros(n)
    for i in np.flatnonzero(near & (ok.sum(axis=1) >= 4)):
        inter[i] = _hull_volume(cand[i][ok[i]], tol[i])
    inter = np.minimum(inter, np.minimum(va, vb))
    return inter / (va + vb - inter)


def cuboid_iou(a, b) -> float:
    """|A ∩ B| / |A ∪ B| ∈ [0, 1], exact up to rounding; cuboids or landmarks.

    A candidate vertex is inside a cuboid within 10⁻¹¹ max h (+ 10⁻¹³ ‖c_b − c_a‖_∞);
    touching cuboids (shared face, edge or corner) give 0.
    """
    a, b = as_cuboid(a), as_cuboid(b)
    return float(_iou_arrays(*_stack([a]), *_stack([b]))[0])


def cuboid_iou_batch(list_a, list_b) -> np.ndarray:
    """IoU of the pairs (a_i, b_i) (n,), candidate vertices computed for all pairs at once."""
    list_a, list_b = [as_cuboid(a) for a in list_a], [as_cuboid(b) for b in list_b]
    if len(list_a) != len(list_b):
        raise ValueError(f"need as many cuboids in each list, got {len(list_a)} and {len(list_b)}")
    if not list_a:
        return np.zeros(0)
    return _iou_arrays(*_stack(list_a), *_stack(list_b))


# --- errors -------------------------------------------------------------------------------


def _rotation_of(x, name: str) -> np.ndarray:
    if isinstance(x, Cuboid):
        return x.rotation
    if hasattr(x, "axes"):
        x = x.axes()[0]
    elif hasattr(x, "as_matrix"):  # jaxlie.SO3
        x = x.as_matrix()
    return _orthonormal(np.asarray(x, dtype=float), name)


def _center_of(x, name: str) -> np.ndarray:
    if hasattr(x, "center"):
        x = x.center
    return _vector(np.asarray(x, dtype=float), name)


def orientation_error_deg(R_est, R_gt) -> float:
    """min over signed permutations G (det R_gtᵀR_est G = +1) of angle(R_gtᵀ R_est G), degrees.

    The axes are compared as unsigned lines in any order. Arguments: 3×3 orthonormal
    matrices (columns = axes), ``Cuboid``s, landmarks, or anything with ``.axes()``.
    The angle is atan2(‖vee(M − Mᵀ)‖/2, (tr M − 1)/2), accurate also near 0. Range
    [0°, ``MAX_ORIENTATION_ERROR_DEG``] = [0°, 2 atan √(23 − 16√2)] ≈ [0°, 62.7994°].
    """
    Re, Rg = _rotation_of(R_est, "R_est"), _rotation_of(R_gt, "R_gt")
    return float(orientation_errors_deg(Re[None], Rg[None])[0])


def orientation_errors_deg(R_est, R_gt) -> np.ndarray:
    """``orientation_error_deg`` for stacks of rotation matrices (n, 3, 3) → (n,).

    Rows with non-finite entries give NaN.
    """
    Re, Rg = np.asarray(R_est, dtype=float), np.asarray(R_gt, dtype=float)
    if Re.shape != Rg.shape or Re.shape[-2:] != (3, 3) or Re.ndim != 3:
        raise ValueError(f"need two (n, 3, 3) stacks, got {Re.shape} and {Rg.shape}")
    M = np.einsum("nji,njk->nik", Rg, Re)
    ok = np.all(np.isfinite(M), axis=(1, 2))
    M = np.where(ok[:, None, None], M, np.eye(3))
    proper = np.linalg.det(M) > 0
    G = np.where(proper[:, None, None, None], _SIGNED_PERMS[None, :24], _SIGNED_PERMS[None, 24:])
    MG = np.einsum("nij,ngjk->ngik", M, G)  # n×24×3×3
    cos = 0.5 * (np.trace(MG, axis1=2, axis2=3) - 1.0)
    skew = MG - np.swapaxes(MG, 2, 3)
    sin = 0.5 * np.linalg.norm(skew[:, :, [2, 0, 1], [1, 2, 0]], axis=-1)
    out = np.degrees(np.min(np.arctan2(sin, cos), axis=1))
    return np.where(ok, out, np.nan)


def cuboid_iou_arrays(center_a, rotation_a, half_a, center_b, rotation_b, half_b) -> np.ndarray:
    """IoU of n cuboid pairs given as arrays: centres (n,3), rotations (n,3,3) with
    orthonormal columns, half-extents (n,3) > 0 (not re-validated: the fast path of
    ``cuboid_iou_batch``)."""
    ca, Ra, ha, cb, Rb, hb = (np.asarray(x, dtype=float) for x in
                              (center_a, rotation_a, half_a, center_b, rotation_b, half_b))
    Ra, Rb = Ra.copy(), Rb.copy()
    for R in (Ra, Rb):  # reflections describe the same solids
        flip = np.linalg.det(R) < 0
        R[flip, :, 2] *= -1
    return _iou_arrays(ca, Ra, ha, cb, Rb, hb)


def translation_error(a, b) -> float:
    """‖c_a − c_b‖; centres (3,), ``Cuboid``s or landmarks."""
    return float(np.linalg.norm(_center_of(a, "a") - _center_of(b, "b")))


# --- trajectories -------------------------------------------------------------------------

__all__ += ["absolute_trajectory_error", "align_rigid", "associate_timestamps"]


def associate_timestamps(t_a, t_b, tolerance: float = 0.02):
    """One-to-one matches (ia, ib) with |t_a[ia] − t_b[ib]| ≤ ``tolerance``.

    Greedy by increasing time difference (as TUM's ``associate.py``): the closest pair is
    matched first and both stamps are then taken. Returns two int arrays sorted by ``ia``.
    """
    a = np.asarray(t_a, dtype=float).ravel()
    b = np.asarray(t_b, dtype=float).ravel()
    tolerance = float(tolerance)
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"tolerance must be finite and >= 0, got {tolerance}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("timestamps must be finite")
    empty = np.zeros(0, dtype=int)
    if a.size == 0 or b.size == 0:
        return empty, empty.copy()
    order = np.argsort(b, kind="stable")
    bs = b[order]
    lo = np.searchsorted(bs, a - tolerance, side="left")
    hi = np.searchsorted(bs, a + tolerance, side="right")
    counts = hi - lo
    ia = np.repeat(np.arange(a.size), counts)
    if ia.size == 0:
        return empty, empty.copy()
    offsets = np.arange(ia.size) - np.repeat(np.cumsum(counts) - counts, counts)
    jb = np.repeat(lo, counts) + offsets  # index into bs
    diff = np.abs(a[ia] - bs[jb])
    keep = diff <= tolerance
    ia, jb, diff = ia[keep], jb[keep], diff[keep]
    used_a = np.zeros(a.size, bool)
    used_b = np.zeros(b.size, bool)
    out_a, out_b = [], []
    for k in np.lexsort((jb, ia, diff)):  # by difference, ties by index
        i, j = ia[k], jb[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            out_a.append(i)
            out_b.append(order[j])
    pa = np.asarray(out_a, dtype=int)
    pb = np.asarray(out_b, dtype=int)
    s = np.argsort(pa, kind="stable")
    return pa[s], pb[s]


def _tum_array(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim != 2 or a.shape[1] != 8:
        raise ValueError(
            f"{name} must be TUM rows 'timestamp tx ty tz qx qy qz qw' of shape (N, 8), got {a.shape}"
        )
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite")
    return a


def _paired_centres(est_tum, gt_tum, tolerance: float, align: bool = True):
    """(estimated centres, ground-truth centres, 4×4 alignment of the first onto the
    second or the identity) over the timestamp pairs within ``tolerance``; ``ValueError``
    with fewer than 3 pairs or centres that do not fix the alignment."""
    est = _tum_array(est_tum, "est_tum")
    gt = _tum_array(gt_tum, "gt_tum")
    ia, ib = associate_timestamps(est[:, 0], gt[:, 0], tolerance)
    if ia.size < 3:
        raise ValueError(
            f"ATE needs at least 3 timestamp pairs within {tolerance} s, got {ia.size} "
            f"({len(est)} estimated and {len(gt)} ground-truth poses)"
        )
    p, g = est[ia, 1:4], gt[ib, 1:4]
    T = np.eye(4)
    if align:
        T[:3, :3], T[:3, 3], _ = align_rigid(p, g)
    return p, g, T


def trajectory_alignment(est_tum, gt_tum, tolerance: float = 0.02) -> np.ndarray:
    """The 4×4 rigid motion of ``absolute_trajectory_error``'s alignment: the estimated
    camera centres onto the ground truth's over timestamps within ``tolerance``."""
    return _paired_centres(est_tum, gt_tum, tolerance)[2]


def absolute_trajectory_error(est_tum, gt_tum, tolerance: float = 0.02, align: bool = True) -> dict:
    """Absolute trajectory error of camera centres (TUM RGB-D benchmark convention).

    Rows of ``est_tum`` and ``gt_tum`` ((N, 8) TUM arrays) are paired with
    ``associate_timestamps``; the estimated centres pᵢ are aligned onto the ground truth's
    gᵢ by the rigid motion (R, t) of ``align_rigid`` (SE(3), no scale; skipped when
    ``align`` is False) and eᵢ = ‖gᵢ − (R pᵢ + t)‖. Returns ``rmse`` = √(Σ eᵢ²/n), ``mean``,
    ``median``, ``max`` (metres) and ``pairs`` = n. Raises ``ValueError`` when fewer than
    3 pairs match.
    """
    p, g, T = _paired_centres(est_tum, gt_tum, tolerance, align)
    p = p @ T[:3, :3].T + T[:3, 3]
    e = np.linalg.norm(g - p, axis=1)
    return {
        "rmse": float(np.sqrt(np.mean(e * e))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "max": float(np.max(e)),
        "pairs": int(e.size),
    }
