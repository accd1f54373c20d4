"""The multi-constraint fit's Levenberg–Marquardt in NumPy, batched over objects and starts.

No tracing and no compiled program (docs/performance.md, "The multi-constraint starts
without a compiler"): every start of every object is one member of one batch, its residual
and Jacobian in closed form.

The model (``multi_initialize``): θ = [u, v, w, log a, log b, log c, ψ, α, β] in a frame
(e1, e2, n, w0) with n the support normal (or up), and

    U = [cos ψ e1 + sin ψ e2, −sin ψ e1 + cos ψ e2, n],   R = Exp(φ) U,  φ = α e1 + β e2,
    P = R diag(r²) Rᵀ,  r = exp(θ₃..₅),   t = u e1 + v e2 + h n,

with h = w, or on a support plane h = w0 + √(nᵀPn) (the object's lowest point on it). Its
derivatives: ∂R/∂ψ = Exp(φ) [x₂, −x₁, 0]; ∂R/∂α = [J_l(φ) e1]× R (β alike with e2), J_l
SO(3)'s left Jacobian, since Exp(φ + δ) = Exp(J_l(φ) δ) Exp(φ) to first order; ∂P/∂log rᵢ
= 2 rᵢ² Rᵢ Rᵢᵀ; ∂h = nᵀ ∂P n / (2 √(nᵀPn)). The box of the ellipsoid and its derivative by
(∂P, ∂t) are the inverse box factor's closed form (``factors.ellipsoid_boxes``), the 9
directions being θ's, shared by an object's views; the cuboid's box is that of its 8 corners
t + R diag(r) σ, u = f_x x/z + c_x, the extremes' derivatives those of the corners that
attain them.

Residuals: each box edge /2 px times its mask (truncated or padding: 0), the class size
prior w (sort(log r) − prior), the tilt prior w_t (α, β). LM with the damping isotropic per
block of θ (centre, log radii; yaw and tilt by their own curvature), λ × 0.3 on a step that
lowers the cost, × 10 otherwise, ``MULTI_ITERS`` steps; a member stops early once its step
is below ``STEP_FLOOR`` (on fr2_desk each start within 2e-11 of 60 full steps,
``benchmarks/multi_fit.py``) or is not finite (its system then stays as it is: no step could
be accepted).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np

from ..factors import ellipsoid_boxes
from ..geometry.se3 import quat_to_matrix

#: LM steps of the multi-constraint fit.
MULTI_ITERS = 60
#: A member of the fit stops once its step is below this in every coordinate of θ (m, log
#: radius, rad): the steps left would move a well-posed fit by round-off only.
STEP_FLOOR = 1e-12
#: σ (px) of a box edge in the fit.
PX_SIGMA = 2.0


@dataclass(frozen=True)
class MultiProblem:
    """One object's fit: ``starts`` (S, 9) θ, ``frame`` (e1, e2, n, w0), ``has_plane``,
    the views' poses ``rows`` (k, 7, jaxlie's wxyz_xyz T_wc), ``boxes`` (k, 4), ``mask``
    (k, 4) weighting each edge, the sorted log radii ``prior_log`` (3,) with weight
    ``prior_w`` (0: none), ``tilt_w`` (1/σ of the tilt; 0 holds it upright), ``shape``
    ("ellipsoid" or "cuboid")."""

    starts: np.ndarray
    frame: tuple
    has_plane: bool
    rows: np.ndarray
    boxes: np.ndarray
    mask: np.ndarray
    prior_log: np.ndarray
    prior_w: float
    tilt_w: float
    shape: str


def _hat(w) -> np.ndarray:
    """[w]× (B, 3, 3) of w (B, 3)."""
    F = np.zeros(w.shape[:-1] + (3, 3))
    F[..., 0, 1], F[..., 0, 2], F[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    F[..., 1, 0], F[..., 2, 0], F[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return F


def _exp_and_left_jacobian(phi, jacobian: bool):
    """Exp(φ) and with ``jacobian`` J_l(φ) = I + (1 − cos θ)/θ² Φ + (θ − sin θ)/θ³ Φ², Φ =
    [φ]×, (B, 3, 3) each (series below θ = 1e-4)."""
    th2 = np.einsum("bi,bi->b", phi, phi)
    small = th2 < 1e-8
    th2s = np.where(small, 1.0, th2)
    th = np.sqrt(th2s)
    sin_th, cos_th = np.sin(th), np.cos(th)
    sin_t = np.where(small, 1.0 - th2 / 6.0, sin_th / th)  # sin θ / θ
    cos_t = np.where(small, 0.5 - th2 / 24.0, (1.0 - cos_th) / th2s)
    F = _hat(phi)
    F2 = F @ F
    eye = np.eye(3)
    tilt = eye + sin_t[:, None, None] * F + cos_t[:, None, None] * F2
    if not jacobian:
        return tilt, None
    cub_t = np.where(small, 1.0 / 6.0 - th2 / 120.0, (th - sin_th) / (th * th2s))
    return tilt, eye + cos_t[:, None, None] * F + cub_t[:, None, None] * F2


@dataclass
class _Batch:
    """The members (one per start of each problem) stacked: frames, plane flags, priors and
    views padded to the most views with mask 0."""

    e1: np.ndarray
    e2: np.ndarray
    n: np.ndarray
    w0: np.ndarray
    has_plane: np.ndarray
    prior_log: np.ndarray
    prior_w: np.ndarray
    tilt_w: np.ndarray
    rows: np.ndarray     # (B, K, 7)
    A: np.ndarray        # (B, K, 3, 3) R_wcᵀ
    boxes: np.ndarray    # (B, K, 4)
    mask: np.ndarray     # (B, K, 4), over PX_SIGMA
    cuboid: bool
    camera: SimpleNamespace  # fx, fy, cx, cy

    @classmethod
    def of(cls, problems: list, members: np.ndarray, cuboid: bool, camera) -> "_Batch":
        K = max(len(p.boxes) for p in problems)

        def padded(a, fill_first: bool):
            a = np.asarray(a, dtype=float)
            pad = np.repeat(a[:1], K - len(a), axis=0) if fill_first else np.zeros((K - len(a),) + a.shape[1:])
            return np.concatenate([a, pad])

        rows = np.stack([padded(p.rows, True) for p in problems])
        boxes = np.stack([padded(p.boxes, True) for p in problems])
        mask = np.stack([padded(np.asarray(p.mask, float), False) for p in problems]) / PX_SIGMA
        R = quat_to_matrix(rows.reshape(-1, 7)[:, [1, 2, 3, 0]]).reshape(len(problems), K, 3, 3)
        frame = [np.array([np.asarray(p.frame[i], float) for p in problems]) for i in range(4)]
        pick = members
        return cls(frame[0][pick], frame[1][pick], frame[2][pick], frame[3][pick],
                   np.array([bool(p.has_plane) for p in problems])[pick],
                   np.stack([np.asarray(p.prior_log, float) for p in problems])[pick],
                   np.array([float(p.prior_w) for p in problems])[pick],
                   np.array([float(p.tilt_w) for p in problems])[pick],
                   rows[pick], np.swapaxes(R, -1, -2)[pick], boxes[pick], mask[pick], cuboid,
                   SimpleNamespace(fx=float(camera.fx), fy=float(camera.fy), cx=float(camera.cx),
                                   cy=float(camera.cy)))

    def take(self, keep) -> "_Batch":
        """The members ``keep`` (indices or a mask)."""
        return replace(self, **{f: getattr(self, f)[keep] for f in _PER_MEMBER})


_PER_MEMBER = ("e1", "e2", "n", "w0", "has_plane", "prior_log", "prior_w", "tilt_w", "rows", "A", "boxes", "mask")


def _model(theta, b: _Batch, jacobian: bool):
    """(R, r, P, t) of each member's θ (module docstring), and with ``jacobian`` (∂P (B, 9,
    3, 3), ∂t (B, 9, 3), ∂R (B, 9, 3, 3), ∂r (B, 9, 3)) by θ."""
    B = len(theta)
    psi = theta[:, 6]
    c, s = np.cos(psi)[:, None], np.sin(psi)[:, None]
    x1, x2 = c * b.e1 + s * b.e2, -s * b.e1 + c * b.e2
    U = np.empty((B, 3, 3))
    U[:, :, 0], U[:, :, 1], U[:, :, 2] = x1, x2, b.n
    phi = theta[:, 7, None] * b.e1 + theta[:, 8, None] * b.e2
    tilt, Jl = _exp_and_left_jacobian(phi, jacobian)
    R = tilt @ U
    r = np.exp(theta[:, 3:6])
    P = (R * (r * r)[:, None, :]) @ np.swapaxes(R, 1, 2)
    half = np.sqrt(np.einsum("bi,bi->b", (P @ b.n[:, :, None])[:, :, 0], b.n))
    h = np.where(b.has_plane, b.w0 + half, theta[:, 2])
    t = theta[:, 0, None] * b.e1 + theta[:, 1, None] * b.e2 + h[:, None] * b.n
    if not jacobian:
        return R, r, P, t, None
    dR = np.zeros((B, 9, 3, 3))
    V = np.zeros((B, 3, 3))
    V[:, :, 0], V[:, :, 1] = x2, -x1
    dR[:, 6] = tilt @ V
    dR[:, 7] = _hat(np.einsum("bij,bj->bi", Jl, b.e1)) @ R
    dR[:, 8] = _hat(np.einsum("bij,bj->bi", Jl, b.e2)) @ R
    dr = np.zeros((B, 9, 3))
    dr[:, 3:6] = np.eye(3) * r[:, None, :]
    D = r**2
    RD = R[:, None] * D[:, None, None, :]
    sym = dR @ np.swapaxes(RD, -1, -2)
    dP = sym + np.swapaxes(sym, -1, -2)
    dP[:, 3:6] = 2.0 * D[:, :, None, None] * R.transpose(0, 2, 1)[:, :, :, None] * R.transpose(0, 2, 1)[:, :, None, :]
    dt = np.zeros((B, 9, 3))
    dt[:, 0], dt[:, 1] = b.e1, b.e2
    dh = np.einsum("bi,bkij,bj->bk", b.n, dP, b.n) / (2.0 * half[:, None])
    dt[:, 2] = np.where(b.has_plane[:, None], 0.0, b.n)
    dt[:, 3:] += np.where(b.has_plane[:, None, None], dh[:, 3:, None] * b.n[:, None, :], 0.0)
    return R, r, P, t, (dP, dt, dR, dr)


def _ellipsoid_boxes(b: _Batch, P, t, d):
    """The boxes (B, K, 4) minus the detected ones, and with ``d`` their derivatives (B, K, 4,
    9) by θ (``factors.ellipsoid_boxes``)."""
    box, dbox = ellipsoid_boxes(b.A, b.rows[..., 4:], P, t, b.camera, None if d is None else d[:2])
    return box - b.boxes, dbox


_SIGNS = np.array([[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0) for sz in (-1.0, 1.0)])


def _cuboid_boxes(b: _Batch, R, r, t, d):
    """As ``_ellipsoid_boxes`` for the circumscribed cuboid's box (its 8 corners')."""
    cam = b.camera
    H = R * r[:, None, :]
    X = t[:, None, :] + np.einsum("bij,cj->bci", H, _SIGNS)  # (B, 8, 3)
    p = np.einsum("bkij,bcj->bkci", b.A, X) - np.einsum("bkij,bkj->bki", b.A, b.rows[..., 4:])[:, :, None, :]
    z = p[..., 2]
    z = np.where(np.abs(z) > 1e-12, z, 1e-12)
    u, v = cam.fx * p[..., 0] / z + cam.cx, cam.fy * p[..., 1] / z + cam.cy
    iu0, iv0, iu1, iv1 = np.argmin(u, -1), np.argmin(v, -1), np.argmax(u, -1), np.argmax(v, -1)
    pick = lambda a, i: np.take_along_axis(a, i[..., None], -1)[..., 0]  # noqa: E731
    box = np.stack([pick(u, iu0), pick(v, iv0), pick(u, iu1), pick(v, iv1)], -1) - b.boxes
    if d is None:
        return box, None
    _, dt, dR, dr = d
    dH = dR * r[:, None, None, :] + R[:, None] * dr[:, :, None, :]
    dX = dt[:, :, None, :] + np.einsum("bqij,cj->bqci", dH, _SIGNS)  # (B, 9, 8, 3)
    dp = np.einsum("bkij,bqcj->bkcqi", b.A, dX)  # (B, K, 8, 9, 3)
    du = cam.fx * (dp[..., 0] - (p[..., 0] / z)[..., None] * dp[..., 2]) / z[..., None]
    dv = cam.fy * (dp[..., 1] - (p[..., 1] / z)[..., None] * dp[..., 2]) / z[..., None]
    take = lambda a, i: np.take_along_axis(a, i[..., None, None], 2)[:, :, 0]  # noqa: E731
    return box, np.stack([take(du, iu0), take(dv, iv0), take(du, iu1), take(dv, iv1)], axis=2)


def _residuals(theta, b: _Batch, jacobian: bool):
    """(r (B, M), J (B, M, 9) or None): the masked box edges, the size prior, the tilt prior."""
    R, r, P, t, d = _model(theta, b, jacobian)
    if b.cuboid:
        box, dbox = _cuboid_boxes(b, R, r, t, d)
    else:
        box, dbox = _ellipsoid_boxes(b, P, t, d)
    B = len(theta)
    order = np.argsort(theta[:, 3:6], axis=1)
    sorted_log = np.take_along_axis(theta[:, 3:6], order, axis=1)
    res = np.concatenate([(box * b.mask).reshape(B, -1), b.prior_w[:, None] * (sorted_log - b.prior_log),
                          b.tilt_w[:, None] * theta[:, 7:9]], axis=1)
    if not jacobian:
        return res, None
    J = np.zeros((B, res.shape[1], 9))
    nb = box.shape[1] * 4
    J[:, :nb] = (dbox * b.mask[..., None]).reshape(B, nb, 9)
    rows = np.arange(3)
    J[np.arange(B)[:, None], nb + rows[None, :], 3 + order] = b.prior_w[:, None]
    J[:, nb + 3, 7], J[:, nb + 4, 8] = b.tilt_w, b.tilt_w
    J[:, :, 2] = np.where(b.has_plane[:, None], 0.0, J[:, :, 2])
    J[:, :, 7:9] = np.where((b.tilt_w > 0)[:, None, None], J[:, :, 7:9], 0.0)
    return res, J


def _cost(res) -> np.ndarray:
    with np.errstate(invalid="ignore", over="ignore"):
        return np.sum(np.where(np.isfinite(res), res * res, np.inf), axis=1)


def _solve(H, g) -> np.ndarray:
    """−H⁻¹g per member; NaN for a member whose system is singular or not finite."""
    bad = ~np.all(np.isfinite(H), axis=(1, 2)) | ~np.all(np.isfinite(g), axis=1)
    Hs = np.where(bad[:, None, None], np.eye(9), H)
    gs = np.where(bad[:, None], 0.0, g)
    try:
        step = -np.linalg.solve(Hs, gs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        step = np.full_like(g, np.nan)
        for i in range(len(g)):
            try:
                step[i] = -np.linalg.solve(Hs[i], gs[i])
            except np.linalg.LinAlgError:
                pass
    step[bad] = np.nan
    return step


def _lm(theta, b: _Batch):
    """``MULTI_ITERS`` LM steps on every member: (θ, cost); a member stops early once its step
    is below ``STEP_FLOOR`` in every coordinate or not finite (module docstring)."""
    B = len(theta)
    lam = np.full(B, 1e-3)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        res, J = _residuals(theta, b, True)
    cost = _cost(res)
    H, g = np.swapaxes(J, 1, 2) @ J, np.einsum("bmi,bm->bi", J, res)
    live = np.arange(B)
    for _ in range(MULTI_ITERS):
        Hl, gl, lam_l = H[live], g[live], lam[live]
        d = np.diagonal(Hl, axis1=1, axis2=2)
        D = np.concatenate([np.repeat(d[:, :3].max(1, keepdims=True), 3, 1),
                            np.repeat(d[:, 3:6].max(1, keepdims=True), 3, 1), d[:, 6:]], axis=1)
        step = _solve(Hl + lam_l[:, None, None] * (np.eye(9) * (D + 1e-9)[:, None, :]), gl)
        moving = np.all(np.isfinite(step), axis=1) & (np.max(np.abs(step), axis=1, initial=0.0) >= STEP_FLOOR)
        live, step = live[moving], step[moving]
        if not len(live):
            break
        cand = theta[live] + step
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            cres, _ = _residuals(cand, b.take(live), False)
        cc = _cost(cres)
        ok = cc < cost[live]
        lam[live] = np.where(ok, lam[live] * 0.3, lam[live] * 10.0)
        if ok.any():
            took = live[ok]
            theta[took], cost[took] = cand[ok], cc[ok]
            with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
                r2, J2 = _residuals(theta[took], b.take(took), True)
            H[took] = np.swapaxes(J2, 1, 2) @ J2
            g[took] = np.einsum("bmi,bm->bi", J2, r2)
    return theta, cost


def fit_multi(problems: list, camera) -> list:
    """Each problem's (cost, P, centre) per start, (S,), (S, 3, 3), (S, 3): the LM of the
    module docstring run on every start of every problem at once (one batch per shape)."""
    out: list = [None] * len(problems)
    for cuboid in (False, True):
        idx = [i for i, p in enumerate(problems) if (p.shape == "cuboid") == cuboid]
        if not idx:
            continue
        group = [problems[i] for i in idx]
        members = np.concatenate([np.full(len(p.starts), k) for k, p in enumerate(group)])
        batch = _Batch.of(group, members, cuboid, camera)
        theta0 = np.concatenate([np.asarray(p.starts, float) for p in group])
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            theta, cost = _lm(theta0.copy(), batch)
            _, _, P, t, _ = _model(theta, batch, False)
        at = 0
        for k, i in enumerate(idx):
            S = len(group[k].starts)
            out[i] = (cost[at:at + S], P[at:at + S], t[at:at + S])
            at += S
    return out
