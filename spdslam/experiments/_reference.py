"""An independent reference for the simulation study: the same trials and the same residuals,
solved by SciPy's trust-region reflective least squares (``scipy.optimize.least_squares``,
``method="trf"``) instead of our LM.

Each parameterisation is solved over a global chart at its initial value x₀, in which
``least_squares`` works in plain Rⁿ:

- O (SPD):  P = P₀^½ Exp(Σ ξₖEₖ) P₀^½, t = t₀ + δt, (ξ, δt) ∈ R⁶ × R³; ξ ↦ P is a
            diffeomorphism of R⁶ onto SPD(3), so no step can leave the manifold;
- S (RTS):  R = R₀ Exp(ω), t = t₀ + δt, s = s₀ + δs, (ω, δt, δs) ∈ R⁹, P = R diag(s²) Rᵀ;
- F (Full): the 10 upper-triangle entries q of Q*, the residuals on Q*/(−Q*₃₃); the
            result is regularised as the solver regularises every step (``EllipsoidFull``).

The residuals are the box factors' (``factors.inverse_box_residual``,
``semi_inverse_box_residual``) evaluated through ``geometry``'s NumPy path, divided by the
study's σ, with no validity gating (a negative discriminant of the box formula gives the
clamped box, as everywhere); the Jacobian is central differences, all 2n perturbed points
in one vectorised evaluation. Cost ½‖r‖², the study's cost. Nothing here shares code with
``solver``.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..geometry import (
    Camera,
    EllipsoidFull,
    box_planes,
    conic_box,
    dual_quadric_of,
    project_dual_quadric,
)

__all__ = ["ReferenceResult", "reference_solve", "REFERENCE_PARAMS", "compare_with_reference",
           "reference_table"]

REFERENCE_PARAMS = ("F", "S", "O")
_SQ = 2.0**-0.5
#: Relative step of the central differences (of max(1, |x|)).
_FD_STEP = 1e-6


def _sym_from_vec(c):
    """(…, 6) → (…, 3, 3): Σ cₖ Eₖ in the Frobenius-orthonormal basis of ``geometry.spd``."""
    a, b, d, e, f, g = np.moveaxis(c, -1, 0)
    return np.stack([np.stack([a, _SQ * e, _SQ * f], -1),
                     np.stack([_SQ * e, b, _SQ * g], -1),
                     np.stack([_SQ * f, _SQ * g, d], -1)], -2)


def _sym_fun(S, fun):
    w, V = np.linalg.eigh(S)
    return (V * fun(w)[..., None, :]) @ np.swapaxes(V, -1, -2)


class _Chart:
    """x ∈ Rⁿ ↦ dual quadrics Q* (…, 4, 4) around a start landmark given as (P₀, t₀)."""

    def __init__(self, param: str, P0, t0):
        self.param, self.t0 = param, np.asarray(t0, float)
        P0 = np.asarray(P0, float)
        if param == "O":
            self.P0h = _sym_fun(P0, np.sqrt)
            self.x0 = np.concatenate([np.zeros(6), self.t0])
        elif param == "S":
            w, V = np.linalg.eigh(P0)
            if np.linalg.det(V) < 0:
                V[:, 0] = -V[:, 0]
            self.R0 = V
            self.x0 = np.concatenate([np.zeros(3), self.t0, np.sqrt(np.maximum(w, 0.0))])
        elif param == "F":
            self.x0 = np.asarray(dual_quadric_of(P0, self.t0))[np.triu_indices(4)]
        else:
            raise ValueError(f"unknown parameterisation {param!r}: expected F, S or O")

    def quadrics(self, X):
        X = np.atleast_2d(X)
        if self.param == "O":
            P = self.P0h @ _sym_fun(_sym_from_vec(X[:, :6]), np.exp) @ self.P0h
            return dual_quadric_of(0.5 * (P + np.swapaxes(P, -1, -2)), X[:, 6:])
        if self.param == "S":
            R = self.R0 @ Rotation.from_rotvec(X[:, :3]).as_matrix()
            P = np.einsum("kij,kj,klj->kil", R, X[:, 6:] ** 2, R)
            return dual_quadric_of(P, X[:, 3:6])
        Q = np.zeros((len(X), 4, 4))
        Q[:, np.triu_indices(4)[0], np.triu_indices(4)[1]] = X
        Q = Q + np.swapaxes(np.triu(Q, 1), -1, -2)
        return Q / -Q[:, 3:4, 3:4]

    def ellipsoid(self, x):
        """(P, t) of the landmark at x (F: regularised, as the solver regularises)."""
        if self.param == "F":
            e = EllipsoidFull(np.asarray(x, float)).regularized().to_ellipsoid()
            return np.asarray(e.P), np.asarray(e.center)
        Q = self.quadrics(x)[0]
        t = -Q[:3, 3]
        return Q[:3, :3] + np.outer(t, t), t


def _residuals(model: str, Q, pose, boxes, planes, camera: Camera, sigma: float):
    """Whitened box residuals (k, 4V) of k dual quadrics against V boxes."""
    if model == "inv":
        C = project_dual_quadric(Q[:, None], pose, camera)  # (k, V, 3, 3)
        r = conic_box(C) - boxes
    else:
        r = np.einsum("vei,kij,vej->kve", planes, Q, planes)
    return r.reshape(len(Q), -1) / sigma


@dataclass
class ReferenceResult:
    """Per trial: the landmark found (P (B, 3, 3), t (B, 3)), its cost ½‖r‖², the cost at
    the start, ``least_squares``' function and Jacobian evaluations and its status."""

    P: np.ndarray
    center: np.ndarray
    cost: np.ndarray
    initial_cost: np.ndarray
    nfev: np.ndarray
    njev: np.ndarray
    status: np.ndarray


def _solve_one(job):
    model, param, P0, t0, R_wc, c, boxes, camera, sigma, max_nfev = job
    chart = _Chart(param, P0, t0)
    pose = (R_wc, c)
    planes = box_planes(boxes, pose, camera) if model == "semi" else None

    def res(X):
        return _residuals(model, chart.quadrics(X), pose, boxes, planes, camera, sigma)

    n = len(chart.x0)

    def fun(x):
        return res(x)[0]

    def jac(x):
        h = _FD_STEP * np.maximum(1.0, np.abs(x))
        E = np.diag(h)
        R = res(np.concatenate([x + E, x - E]))
        return ((R[:n] - R[n:]) / (2 * h[:, None])).T

    r0 = fun(chart.x0)
    if not np.all(np.isfinite(r0)):
        P, t = chart.ellipsoid(chart.x0)
        return P, t, np.inf, np.inf, 0, 0, -99
    sol = least_squares(fun, chart.x0, jac=jac, method="trf", max_nfev=max_nfev)
    P, t = chart.ellipsoid(sol.x)
    r = _residuals(model, dual_quadric_of(P, t)[None], pose, boxes, planes, camera, sigma)
    cost = 0.5 * float(np.sum(r**2))
    return P, t, cost, 0.5 * float(r0 @ r0), int(sol.nfev), int(sol.njev or 0), int(sol.status)


def reference_solve(model: str, param: str, scenes, sigma: float, max_nfev: int = 100,
                    workers: int | None = None) -> ReferenceResult:
    """Solve every trial of ``scenes`` (``synthetic.Scenes``) with TRF for one (box model
    ``"inv"``/``"semi"``, parameterisation) structure, ``workers`` processes (None: one per
    core, at most 2)."""
    if model not in ("inv", "semi"):
        raise ValueError(f"unknown model {model!r}: expected inv or semi")
    if param not in REFERENCE_PARAMS:
        raise ValueError(f"unknown parameterisation {param!r}: expected F, S or O")
    wxyz_xyz = np.asarray(scenes.poses.wxyz_xyz)
    B, V = wxyz_xyz.shape[:2]
    R_wc = Rotation.from_quat(wxyz_xyz[..., [1, 2, 3, 0]].reshape(-1, 4)).as_matrix()
    R_wc = R_wc.reshape(B, V, 3, 3)
    P0, t0 = np.asarray(scenes.initial.P), np.asarray(scenes.initial.center)
    boxes = np.asarray(scenes.boxes, float)
    jobs = [(model, param, P0[b], t0[b], R_wc[b], wxyz_xyz[b, :, 4:], boxes[b], scenes.camera,
             float(sigma), int(max_nfev)) for b in range(B)]
    workers = min(2, os.cpu_count() or 1) if workers is None else int(workers)
    if workers > 1 and B > 8:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as ex:
            out = list(ex.map(_solve_one, jobs, chunksize=max(1, B // (8 * workers))))
    else:
        out = [_solve_one(j) for j in jobs]
    P, t, cost, cost0, nfev, njev, status = (np.asarray(v) for v in zip(*out))
    return ReferenceResult(P, t, cost.astype(float), cost0.astype(float), nfev, njev, status)


# --- ours beside the reference, trial by trial ------------------------------------------


def _radius_ratio(P):
    w = np.linalg.eigvalsh(np.asarray(P))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.maximum(w[:, 0], 0.0) / w[:, 2])


def compare_with_reference(cfg, max_nfev: int = 100, workers: int | None = None,
                           progress=None) -> dict:
    """Run the study ``cfg`` (``StudyConfig``) with our LM and every structure again with
    TRF on the same scenes; the same success rule for both. Returns per (cell, model,
    param): trials, successes of each, trials where only one succeeds, median iterations
    (ours) and function evaluations (TRF), and collapse rates (smallest radius below
    ``COLLAPSED_RATIO`` of the largest), plus the study itself under "result"."""
    from ._study import all_scenes, box_sigma, run_study
    from ._summary import COLLAPSED_RATIO

    result = run_study(cfg)
    scenes, angle_lab, noise_lab = all_scenes(cfg)
    cells = []
    for model in cfg.models:
        for param in cfg.params:
            rows = [r for r in result.rows if r["model"] == model and r["param"] == param]
            ref = reference_solve(model, param, scenes, box_sigma(model, cfg), max_nfev, workers)
            thr = np.array([(1 + cfg.success_rtol) * r["truth_cost"] + cfg.success_atol
                            for r in rows])
            ours = np.array([r["success"] for r in rows])
            theirs = ref.cost <= thr
            ours_collapsed = np.array([not r["min_radius_ratio"] >= COLLAPSED_RATIO for r in rows])
            ref_collapsed = ~(_radius_ratio(ref.P) >= COLLAPSED_RATIO)
            its = np.array([r["iterations"] for r in rows])
            for a, n in cfg.cells:
                sel = (angle_lab == a) & (noise_lab == n)
                cells.append({
                    "angle": int(a), "noise": n, "model": model, "param": param,
                    "trials": int(sel.sum()),
                    "ours": float(ours[sel].mean()), "reference": float(theirs[sel].mean()),
                    "only_ours": int((ours & ~theirs)[sel].sum()),
                    "only_reference": int((theirs & ~ours)[sel].sum()),
                    "median_iterations": float(np.median(its[sel])),
                    "median_reference_evaluations": float(np.median(ref.nfev[sel])),
                    "ours_collapsed": float(ours_collapsed[sel].mean()),
                    "reference_collapsed": float(ref_collapsed[sel].mean()),
                    "max_initial_cost_mismatch": float(np.max(np.abs(
                        ref.initial_cost[sel] / np.array([r["initial_cost"] for r in rows])[sel]
                        - 1.0))),
                })
            if progress:
                progress(f"{model}-{param}")
    return {"cells": cells, "result": result, "max_nfev": max_nfev}


def reference_table(cells: list[dict]) -> str:
    """Markdown: per cell, ours and the reference's success rates and the rest."""
    head = ("| range | noise | model | param | ours | TRF | only ours | only TRF | "
            "median iterations (ours) | median evaluations (TRF) | collapsed ours / TRF |")
    lines = [head, "|" + " --- |" * 11]
    for c in cells:
        lines.append(
            f"| {c['angle']} | {c['noise']} | {c['model']} | {c['param']} | {c['ours']:.3f} | "
            f"{c['reference']:.3f} | {c['only_ours']} | {c['only_reference']} | "
            f"{c['median_iterations']:.0f} | {c['median_reference_evaluations']:.0f} | "
            f"{c['ours_collapsed']:.3f} / {c['reference_collapsed']:.3f} |")
    return "\n".join(lines) + "\n"
