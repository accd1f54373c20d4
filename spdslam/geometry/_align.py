"""Rigid alignment of two point sets (Horn / Umeyama), for the evaluation's trajectory
metrics and the importers that bring a ground truth into a trajectory's frame."""

from __future__ import annotations

import numpy as np

__all__ = ["align_rigid", "align_rigid_many"]

#: Relative singular-value threshold below which a point set counts as collinear.
_RANK_TOL = 1e-9


def _points(x, name: str) -> np.ndarray:
    p = np.asarray(x, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be finite")
    return p


def align_rigid(src, dst, with_scale: bool = False, weights=None):
    """(R, t, s) minimising Σᵢ wᵢ ‖dstᵢ − (s R srcᵢ + t)‖², R ∈ SO(3) (Horn / Umeyama 1991).

    With weighted means μ, X = src − μ_src, Y = dst − μ_dst (centred, N×3), W = Σ wᵢ and the
    cross-covariance Σ = Σᵢ wᵢ yᵢ xᵢᵀ / W = U D Vᵀ (SVD): R = U S Vᵀ, S = diag(1, 1,
    sign det(U Vᵀ)) (a proper rotation even for reflected data); s = tr(D S) / σ²_src,
    σ²_src = Σᵢ wᵢ ‖xᵢ‖² / W (s = 1 unless ``with_scale``); t = μ_dst − s R μ_src.
    ``weights``: N non-negative numbers, not all zero (default all 1).

    ``src``, ``dst``: N×3, N ≥ 3. Raises ``ValueError`` for fewer than 3 points, non-finite
    input, or a degenerate configuration (either set collinear or coincident, or Σ of rank
    < 2), for which the rotation is not unique.
    """
    X, Y = _points(src, "src"), _points(dst, "dst")
    if X.shape != Y.shape:
        raise ValueError(f"src and dst must have the same shape, got {X.shape} and {Y.shape}")
    n = X.shape[0]
    if n < 3:
        raise ValueError(f"rigid alignment needs at least 3 point pairs, got {n}")
    if weights is None:
        mu_x, mu_y = X.mean(axis=0), Y.mean(axis=0)
        X, Y = X - mu_x, Y - mu_y
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
            raise ValueError(f"weights must be {n} finite non-negative numbers, not all zero")
        w = w / w.sum()
        mu_x, mu_y = w @ X, w @ Y
        root = np.sqrt(w * n)[:, None]  # Σ and σ² below divide by n
        X, Y = (X - mu_x) * root, (Y - mu_y) * root
    scale = max(np.abs(X).max(), np.abs(Y).max(), np.abs(mu_x).max(), np.abs(mu_y).max(), 1e-300)
    for name, Z in (("src", X), ("dst", Y)):
        sv = np.linalg.svd(Z, compute_uv=False)
        if not sv[1] > _RANK_TOL * max(sv[0], scale):
            raise ValueError(
                f"degenerate {name}: the points are collinear or coincide "
                f"(singular values {sv[0]:.3g}, {sv[1]:.3g}), the rotation is not unique"
            )
    U, D, Vt = np.linalg.svd(Y.T @ X / n)
    if not D[1] > _RANK_TOL * D[0]:
        raise ValueError(
            f"degenerate cross-covariance (singular values {D.tolist()}): the rotation is not unique"
        )
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    R = (U * S) @ Vt
    s = float(D @ S / (np.sum(X * X) / n)) if with_scale else 1.0
    t = mu_y - s * R @ mu_x
    return R, t, s


def align_rigid_many(src, dst, with_scale: bool = False):
    """``align_rigid`` of h point sets at once, unweighted: ``src``, ``dst`` (h, N, 3), N ≥ 3,
    finite. Returns (R (h, 3, 3), t (h, 3), s (h,), ok (h,)): ok is False where
    ``align_rigid`` raises for a degenerate configuration (R, t, s there are not used)."""
    X, Y = np.asarray(src, dtype=float), np.asarray(dst, dtype=float)
    if X.ndim != 3 or X.shape != Y.shape or X.shape[1] < 3 or X.shape[2] != 3:
        raise ValueError(f"src and dst must be (h, N ≥ 3, 3) of one shape, got {X.shape} and {Y.shape}")
    n = X.shape[1]
    mu_x, mu_y = X.mean(axis=1), Y.mean(axis=1)
    X, Y = X - mu_x[:, None], Y - mu_y[:, None]
    scale = np.maximum.reduce([np.abs(X).max(axis=(1, 2)), np.abs(Y).max(axis=(1, 2)),
                               np.abs(mu_x).max(axis=1), np.abs(mu_y).max(axis=1), np.full(len(X), 1e-300)])
    ok = np.ones(len(X), bool)
    for Z in (X, Y):
        sv = np.linalg.svd(Z, compute_uv=False)
        ok &= sv[:, 1] > _RANK_TOL * np.maximum(sv[:, 0], scale)
    U, D, Vt = np.linalg.svd(np.einsum("hni,hnj->hij", Y, X) / n)
    ok &= D[:, 1] > _RANK_TOL * D[:, 0]
    S = np.ones((len(X), 3))
    S[np.linalg.det(U) * np.linalg.det(Vt) < 0, 2] = -1.0
    R = np.einsum("hij,hj,hjk->hik", U, S, Vt)
    var = np.sum(X * X, axis=(1, 2)) / n  # 0 only where the source coincides (not ok)
    s = np.einsum("hi,hi->h", D, S) / np.where(var > 0, var, 1.0) if with_scale else np.ones(len(X))
    t = mu_y - s[:, None] * np.einsum("hij,hj->hi", R, mu_x)
    return R, t, s, ok
