"""Ellipses of the maps' figures and checks, pure NumPy: the top view of an ellipsoid along
``up`` and the ellipse of a dual conic C* = [[S − ccᵀ, −c], [−cᵀ, −1]] (C*₃₃ = −1), the
set {x : (x − c)ᵀ S⁻¹ (x − c) ≤ 1}; the figures themselves are ``experiments``'."""

from __future__ import annotations

import numpy as np

__all__ = [
    "camera_centers",
    "conic_ellipse",
    "conic_ellipses",
    "conic_outline",
    "ellipse_points",
    "ellipses_points",
    "plane_basis",
    "top_view_ellipse",
]


def plane_basis(up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """B (2×3): rows e₁, e₂, an orthonormal basis of the plane ⟂ ``up`` with (e₁, e₂, up)
    right-handed. e₁ is the world axis (x, else y) most orthogonal to up, projected onto
    the plane; for up = +z, B = [x; y]."""
    u = np.asarray(up, dtype=float).reshape(3)
    n = float(np.linalg.norm(u))
    if not (np.isfinite(n) and n > 0):
        raise ValueError(f"up must be a finite non-zero 3-vector, got {u.tolist()}")
    u = u / n
    a = np.eye(3)[0] if abs(u[0]) < 0.9 else np.eye(3)[1]
    e1 = a - (a @ u) * u
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    return np.stack([e1, e2])


def top_view_ellipse(P, center, basis) -> tuple[np.ndarray, np.ndarray]:
    """(c, S): the orthographic projection of the ellipsoid (P, t) onto the plane spanned by
    the rows of ``basis`` (2×3, orthonormal) is the ellipse c = B t, S = B P Bᵀ."""
    B = np.asarray(basis, dtype=float)
    P = np.asarray(P, dtype=float)
    t = np.asarray(center, dtype=float)
    S = B @ P @ B.T
    return B @ t, 0.5 * (S + S.T)


def ellipse_points(center, S, n: int = 100) -> np.ndarray:
    """n points (n×2) c + S^½ (cos θ, sin θ), θ = 2πk/n, on the ellipse
    {x : (x − c)ᵀ S⁻¹ (x − c) = 1}; the first point is repeated at the end (n+1 rows)."""
    S = np.asarray(S, dtype=float)
    w = np.linalg.eigvalsh(0.5 * (S + S.T))
    if not np.all(w > 0):
        raise ValueError(f"the ellipse's shape matrix must be positive definite, eigenvalues {w.tolist()}")
    return ellipses_points(center, S, n)


def ellipses_points(center, S, n: int = 100) -> np.ndarray:
    """Batched ``ellipse_points``: centres (…, 2), shapes (…, 2, 2) → (…, n+1, 2); a shape
    that is not positive definite is not checked (its negative eigenvalues count as 0)."""
    S = np.asarray(S, dtype=float)
    w, V = np.linalg.eigh(0.5 * (S + np.swapaxes(S, -1, -2)))
    theta = np.linspace(0.0, 2.0 * np.pi, int(n) + 1)
    unit = np.stack([np.cos(theta), np.sin(theta)], axis=-1)  # (n+1, 2)
    r = np.sqrt(np.maximum(w, 0.0))[..., None, :]
    return np.asarray(center, dtype=float)[..., None, :] + (unit * r) @ np.swapaxes(V, -1, -2)


def conic_ellipses(Cstar):
    """Batched ``conic_ellipse`` without raising: dual conics (…, 3, 3) → (c (…, 2),
    S (…, 2, 2), ok (…,)); where ``ok`` is False (not finite, C*₃₃ = 0, or S not positive
    definite) c = 0 and S = I stand in."""
    C = np.asarray(Cstar, dtype=float)
    C = 0.5 * (C + np.swapaxes(C, -1, -2))
    finite = np.all(np.isfinite(C), axis=(-1, -2))
    C = np.where(finite[..., None, None], C, 0.0)
    c33 = C[..., 2, 2]
    ok = finite & (np.abs(c33) > 1e-12 * np.abs(C).max(axis=(-1, -2)))
    C = C / np.where(ok, -c33, -1.0)[..., None, None]
    c = -C[..., :2, 2]
    S = C[..., :2, :2] + c[..., :, None] * c[..., None, :]
    ok &= (S[..., 0, 0] > 0) & (np.linalg.det(S) > 0)
    return (np.where(ok[..., None], c, 0.0), np.where(ok[..., None, None], S, np.eye(2)), ok)


def conic_ellipse(Cstar) -> tuple[np.ndarray, np.ndarray]:
    """(c, S) of the ellipse of a dual conic C* (any non-zero scale or sign).

    C*/(−C*₃₃) = [[S − ccᵀ, −c], [−cᵀ, −1]]: c = −C̃*[:2, 2], S = C̃*[:2, :2] + ccᵀ.
    Raises ``ValueError`` when C* is not a real ellipse (C*₃₃ = 0: a parabola; S not
    positive definite: a hyperbola or nothing), e.g. a landmark not wholly in front.
    """
    C = np.asarray(Cstar, dtype=float)
    if C.shape != (3, 3) or not np.all(np.isfinite(C)):
        raise ValueError(f"a dual conic must be a finite 3×3 matrix, got shape {C.shape}")
    c, S, ok = conic_ellipses(C)
    if not ok:
        C = 0.5 * (C + C.T)
        if not abs(C[2, 2]) > 1e-12 * np.abs(C).max():
            raise ValueError("not an ellipse: C*₃₃ = 0 (the conic is a parabola or degenerate)")
        raise ValueError("not an ellipse: the dual conic's shape is not positive definite")
    return c, S


def conic_outline(Cstar, n: int = 100) -> np.ndarray:
    """(n+1)×2 points of the ellipse of the dual conic C* (closed: first point repeated).

    Each x̄ = (u, v, 1) satisfies x̄ᵀ C x̄ = 0 with C = (C*)⁻¹; see ``conic_ellipse``.
    """
    c, S = conic_ellipse(Cstar)
    return ellipse_points(c, S, n)


def camera_centers(trajectory) -> np.ndarray:
    """Camera centres (N×3) of TUM rows: (N, 7) ``tx ty tz qx qy qz qw`` or (N, 8) with a
    leading timestamp."""
    a = np.asarray(trajectory, dtype=float)
    if a.ndim != 2 or a.shape[1] not in (7, 8):
        raise ValueError(f"a trajectory must be TUM rows of shape (N, 7) or (N, 8), got {a.shape}")
    return a[:, 1:4] if a.shape[1] == 8 else a[:, 0:3]
