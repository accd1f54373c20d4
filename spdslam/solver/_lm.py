"""The Levenberg-Marquardt / Gauss-Newton step-and-stop rule, written once.

Cost F(x) = Σᵢ ½ ρᵢ(‖Wᵢ rᵢ(x)‖²). At x the solver linearises (IRLS for robust kernels),
H = JᵀJ, g = Jᵀr, and solves the damped normal equations

    (H + λ D) δ = −g,

with the damping matrix D (``damping``):

- "isotropic": D = μ_b I on each tangent block b of each variable, the blocks in which
  its manifold's metric is isotropic (``manifold.register(blocks=…)``: SPD(3) and R³ of an
  ellipsoid, ω and v of a pose), with μ_b = max diag H_bb the block's largest curvature
  (clipped to [min_diagonal, max_diagonal]). In orthonormal tangent bases (the
  affine-invariant basis of SPD(3)) λD is λμ_b times the metric on each block, so
  the damped step minimises the model in a ball of the metric: it cannot run far along a
  direction the residuals barely see, such as a vanishing radius, whose diagonal vanishes
  with it (docs/core.md, "The damping");
- "marquardt": D = clip(diag H, min_diagonal, max_diagonal), Marquardt's scaling as in
  Ceres: invariant to the units of each coordinate, but a coordinate with a vanishing
  diagonal is left undamped;
- "identity": D = I (gtsam's default), λ in the units of H.

The candidate is x' = regularize(x ⊞ δ).

LM (Nielsen's rule, ``lambda_schedule="nielsen"``, the default). The gain ratio
ρ = (F(x) − F(x')) / L, with the model decrease L = −gᵀδ − ½δᵀHδ = ½ δᵀ(λDδ − g) > 0. The step
is accepted iff F(x') < F(x), F(x') is finite, its Jacobian is finite, and no factor that
is valid at x is invalid at x'. On acceptance λ ← max(λ_min, λ·max(1/3, 1 − (2ρ − 1)³)),
ν ← 2; on rejection λ ← λν, ν ← 2ν. ``lambda_schedule="fixed"`` is gtsam's default rule
instead: λ ← max(λ_min, λ/f) on acceptance, λ ← λf on rejection (f = ``lambda_factor``, 10).

Dogleg (``DoglegParams``, Powell's method as in GTSAM's DoglegOptimizer and Ceres): the
Gauss-Newton step solves (H + ε clip(diag H))δ = −g (ε = ``ridge``, so that Cholesky
survives gauge and scale directions), the Cauchy point d_sd = −(gᵀg / gᵀHg) g, and the step
is the dogleg path's point in the trust region ‖δ‖₂ ≤ Δ (``dogleg_step``): the GN step
itself whenever it fits, so no damping slows a run down a long valley, and never longer
than Δ in the metric. ρ against L = −gᵀδ − ½δᵀHδ; acceptance as for LM; Δ ← ‖δ‖/4 when
ρ < 1/4 (and on rejection), Δ ← min(2Δ, Δ_max) when ρ > 3/4 and the step reached the
boundary. The records' ``damping`` holds Δ (with ``radius`` True).

GN: λ is a fixed tiny ridge (``ridge``, relative to D) so that Cholesky survives singular
directions. Every step that lowers the cost is taken; the first that does not (cost increase,
invalid factor, non-finite cost) ends the run, keeping the values before it: reason
"relative" when the change was within the relative tolerance, else "cost_increase".

An iteration is one solve of the damped system and one trial step (accepted or not), as in
Ceres. Stopping reasons (``OptimizationResult.reason``, ``BatchedResult.reason``):

- "absolute":       F(x) ≤ absolute_tolerance;
- "relative":       an accepted step lowered F by ≤ relative_tolerance·F, or a rejected step
                    changed F and had a model decrease both ≤ relative_tolerance·F;
- "gradient":       ‖g‖∞ ≤ gradient_tolerance;
- "step":           ‖δ‖₂ ≤ step_tolerance;
- "max_iterations": the iteration budget ran out;
- "lambda_max":     LM: λ grew beyond lambda_max without an acceptable step;
- "cost_increase":  GN: a step raised the cost (see above);
- "linear_solver":  GN: the ridged system could not be factorised;
- "callback":       the callback returned True.

``converged`` is True for the first four.

The rule is pure and array-generic (``decide``): the sparse host loop (``_optimizers``)
calls it on NumPy scalars once per iteration, the batched driver (``_batched_loop``) on JAX
arrays of all lanes at once, so both take the same decisions.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, cast

import numpy as np

from ._linear import DENSE_THRESHOLD, check_cholmod_options

__all__ = [
    "OptimizerParams",
    "LevenbergMarquardtParams",
    "DoglegParams",
    "GaussNewtonParams",
    "IterationRecord",
    "REASONS",
    "CONVERGED_REASONS",
    "DAMPINGS",
    "StepRule",
    "resolve_params",
    "damping",
    "predicted_decrease",
    "dogleg_step",
    "model_decrease",
    "initial_reason",
    "decide",
]

#: Reason codes (index → reason string); 0: not stopped.
REASONS = (
    "",
    "absolute",
    "relative",
    "gradient",
    "step",
    "max_iterations",
    "lambda_max",
    "cost_increase",
    "linear_solver",
    "callback",
)
ABSOLUTE, RELATIVE, GRADIENT, STEP, MAX_ITERATIONS, LAMBDA_MAX, COST_INCREASE, LINEAR_SOLVER, \
    CALLBACK = range(1, 10)
CONVERGED_REASONS = ("absolute", "relative", "gradient", "step")
#: The damping matrices of LM (see the module docstring).
DAMPINGS = ("isotropic", "marquardt", "identity")


@dataclass
class OptimizerParams:
    """Stopping rules and linear solver, shared by LM and GN.

    max_iterations:     budget of iterations (damped solves + trial steps).
    relative_tolerance: stop when an accepted step lowers F by ≤ this·F.
    absolute_tolerance: stop when F ≤ this.
    gradient_tolerance: stop when ‖Jᵀr‖∞ ≤ this.
    step_tolerance:     stop when ‖δ‖₂ ≤ this.
    min_diagonal, max_diagonal: clip of diag H in the damping matrix D.
    linear_solver:      "auto" (dense below ``dense_threshold`` tangent dims, else CHOLMOD
                        through scikit-sparse, else through cvxopt, else scipy), "cholmod",
                        "cvxopt", "scipy", "dense" (the batched solver is always dense).
    cholmod_mode, cholmod_ordering: CHOLMOD's factorisation ("supernodal", "simplicial",
                        "auto") and fill-reducing ordering ("default", "amd", "metis", …;
                        cvxopt: "default", "amd", "natural"); see ``_linear``.
    cholmod_openmp, cholmod_blas_threads: threads of CHOLMOD's OpenMP regions (False: one)
                        and of its OpenBLAS (None: unchanged) during factorisations and
                        solves; see ``_linear.cholmod_threads``.
    verbose:            print one line per iteration (batched: per iteration of each problem).
    callback:           ``callback(record)`` after each iteration (an ``IterationRecord``);
                        returning True stops (batched: stops that record's problem).
    """

    max_iterations: int = 100
    relative_tolerance: float = 1e-6
    absolute_tolerance: float = 1e-12
    gradient_tolerance: float = 1e-10
    step_tolerance: float = 1e-10
    min_diagonal: float = 1e-6
    max_diagonal: float = 1e32
    linear_solver: str = "auto"
    dense_threshold: int = DENSE_THRESHOLD
    cholmod_mode: str = "supernodal"
    cholmod_ordering: str = "default"
    cholmod_openmp: bool = False
    cholmod_blas_threads: int | None = 1
    verbose: bool = False
    callback: Callable[["IterationRecord"], Any] | None = None


@dataclass
class LevenbergMarquardtParams(OptimizerParams):
    """LM damping: λ starts at ``lambda_initial``, stays ≥ ``lambda_min``, and the run stops
    (reason "lambda_max") when rejections push it above ``lambda_max``. ``lambda_schedule``:
    "nielsen" (gain-ratio rule) or "fixed" (÷/× ``lambda_factor``, gtsam's default);
    ``damping``: "isotropic" (μᵥI per variable, the default), "marquardt" (clip(diag H)) or
    "identity" (I, gtsam's default); see the module docstring."""

    lambda_initial: float = 1e-4
    lambda_min: float = 1e-10
    lambda_max: float = 1e10
    lambda_schedule: str = "nielsen"
    lambda_factor: float = 10.0
    damping: str = "isotropic"


@dataclass
class DoglegParams(OptimizerParams):
    """Powell's dogleg in a trust region ‖δ‖₂ ≤ Δ of the tangent coordinates (the metric in
    orthonormal bases): Δ starts at ``trust_radius_initial`` and stays ≤
    ``trust_radius_max``; the Gauss-Newton step solves (H + ``ridge``·clip(diag H))δ = −g."""

    trust_radius_initial: float = 1.0
    trust_radius_max: float = 1e4
    ridge: float = 1e-9


@dataclass
class GaussNewtonParams(OptimizerParams):
    """GN: ``ridge`` is the fixed relative damping λ in (H + λD)δ = −g."""

    ridge: float = 1e-9


@dataclass
class IterationRecord:
    """One iteration: the trial at ``damping`` with step norm ‖δ‖₂.

    cost:       F after the iteration (the trial's cost if accepted, else unchanged);
    trial_cost: F at the trial point (inf if the system could not be solved);
    damping:    λ of LM, or the dogleg's trust-region radius Δ (``radius`` True);
    gain_ratio: ρ = actual / predicted decrease (−inf for an unusable trial);
    time:       wall-clock seconds of this iteration (incl. relinearisation if accepted;
                batched: of the loop step, shared by the problems in flight);
    problem:    the problem's index in a batched solve (None for a single solve);
    radius:     True when ``damping`` is the dogleg's Δ.
    """

    iteration: int
    cost: float
    trial_cost: float
    step_norm: float
    damping: float
    gain_ratio: float
    accepted: bool
    time: float
    problem: int | None = None
    radius: bool = False

    def line(self) -> str:
        """The line ``verbose`` prints."""
        who = "" if self.problem is None else f"problem {self.problem:5d}  "
        return (
            f"{who}iter {self.iteration:4d}  cost {self.cost:.10e}  trial {self.trial_cost:.4e}  "
            f"|step| {self.step_norm:.3e}  {'radius' if self.radius else 'lambda'} {self.damping:.2e}  "
            f"rho {self.gain_ratio:.3g}  {'accept' if self.accepted else 'reject'}  {1e3 * self.time:.1f} ms"
        )


@dataclass(frozen=True)
class StepRule:
    """The static part of the rule (what changes the code, not the numbers): Gauss-Newton
    or LM, the λ schedule, the damping matrix (GN: Marquardt's, for its ridge)."""

    gn: bool = False
    schedule: str = "nielsen"
    damping: str = "marquardt"
    dogleg: bool = False

    @classmethod
    def of(cls, params: OptimizerParams) -> "StepRule":
        if isinstance(params, GaussNewtonParams):
            return cls(gn=True)
        if isinstance(params, DoglegParams):
            return cls(dogleg=True)
        lm = cast(LevenbergMarquardtParams, params)  # the remaining kind
        return cls(False, lm.lambda_schedule, lm.damping)


#: The numbers of the rule, in the order of ``hyper`` (the batched solver passes them as
#: one array, so changing them compiles nothing).
HYPER = ("relative_tolerance", "absolute_tolerance", "gradient_tolerance", "step_tolerance",
         "min_diagonal", "max_diagonal", "lambda_initial", "lambda_min", "lambda_max",
         "lambda_factor", "ridge")


def hyper(params: OptimizerParams) -> dict[str, float]:
    """The numbers of the rule: tolerances, clip of D, and λ₀, λ_min, λ_max, f (GN: the
    ridge, held fixed; dogleg: Δ₀, 0, Δ_max, 1), and the ridge of the GN step (LM: 0)."""
    out = {k: float(getattr(params, k)) for k in HYPER[:6]}
    if isinstance(params, GaussNewtonParams):
        out.update(lambda_initial=params.ridge, lambda_min=params.ridge, lambda_max=np.inf,
                   lambda_factor=1.0, ridge=params.ridge)
    elif isinstance(params, DoglegParams):
        out.update(lambda_initial=params.trust_radius_initial, lambda_min=0.0,
                   lambda_max=params.trust_radius_max, lambda_factor=1.0, ridge=params.ridge)
    else:
        lm = cast(LevenbergMarquardtParams, params)
        out.update(lambda_initial=lm.lambda_initial, lambda_min=lm.lambda_min,
                   lambda_max=lm.lambda_max, lambda_factor=lm.lambda_factor, ridge=0.0)
    return {k: float(v) for k, v in out.items()}


def resolve_params(cls_params: type, params: OptimizerParams | None, overrides: dict
                   ) -> OptimizerParams:
    """``params`` as a ``cls_params`` (default ``cls_params()``; params of the other method
    keep their shared fields), with keyword ``overrides`` of its fields, checked."""
    if params is None:
        params = cls_params()
    elif not isinstance(params, cls_params):
        shared = {f.name: getattr(params, f.name) for f in dataclasses.fields(OptimizerParams)}
        params = cls_params(**shared)
    if overrides:
        params = dataclasses.replace(params, **overrides)
    if isinstance(params, DoglegParams):
        if not 0 < params.trust_radius_initial <= params.trust_radius_max:
            raise ValueError("need 0 < trust_radius_initial ≤ trust_radius_max, got "
                             f"{params.trust_radius_initial!r}, {params.trust_radius_max!r}")
    elif not isinstance(params, GaussNewtonParams):
        lm = cast(LevenbergMarquardtParams, params)
        if lm.lambda_schedule not in ("nielsen", "fixed"):
            raise ValueError(
                f"lambda_schedule must be 'nielsen' or 'fixed', got {lm.lambda_schedule!r}"
            )
        if lm.damping not in DAMPINGS:
            raise ValueError(
                f"damping must be one of {', '.join(map(repr, DAMPINGS))}, got {lm.damping!r}"
            )
        if not lm.lambda_factor > 1:
            raise ValueError(f"lambda_factor must be > 1, got {lm.lambda_factor!r}")
    check_cholmod_options(params.cholmod_mode, params.cholmod_ordering)
    return params


def damping(diag_h, rule: StepRule, h: dict, xp, blocks=None):
    """D of ``rule.damping`` from diag H (n,). ``blocks``: the tangent layout, a sequence of
    (number of variables, block dims of one variable) in order (the drivers lay variables
    of one type out contiguously); "isotropic" takes μ over each block of each variable
    (None: one block)."""
    if rule.damping == "identity":
        return xp.ones_like(diag_h)
    if rule.damping == "marquardt":
        return xp.clip(diag_h, h["min_diagonal"], h["max_diagonal"])
    if blocks is None:
        blocks = ((1, (diag_h.shape[-1],)),)
    flat, o = [], 0
    for count, dims in blocks:
        dim = sum(dims)
        if not count:
            continue
        seg = xp.reshape(diag_h[o : o + count * dim], (count, dim))
        pieces, b = [], 0
        for d in dims:
            mu = xp.max(seg[:, b : b + d], axis=1, keepdims=True)
            pieces.append(xp.broadcast_to(mu, (count, d)))
            b += d
        flat.append(xp.reshape(xp.concatenate(pieces, axis=1), (-1,)))
        o += count * dim
    D = xp.concatenate(flat) if len(flat) > 1 else flat[0]
    return xp.clip(D, h["min_diagonal"], h["max_diagonal"])


def predicted_decrease(delta, D, g, lam, xp):
    """L = ½ δᵀ(λDδ − g), the decrease the damped model predicts (over the last axis)."""
    return 0.5 * xp.sum(delta * (xp.asarray(lam)[..., None] * D * delta - g), axis=-1)


def dogleg_step(d_gn, g, Hg, radius, xp):
    """Powell's dogleg in ‖δ‖₂ ≤ Δ (1-D arrays): the Gauss-Newton step d_gn if it fits,
    else the steepest-descent step to the boundary if the Cauchy point d_sd = −(gᵀg/gᵀHg) g
    lies outside, else the point of the segment d_sd → d_gn on the boundary."""
    gg = xp.sum(g * g)
    gHg = xp.sum(g * Hg)
    alpha = xp.where(gHg > 0, gg / xp.where(gHg > 0, gHg, 1.0), np.inf)
    gnorm = xp.sqrt(gg)
    n_gn = xp.sqrt(xp.sum(d_gn * d_gn))
    to_boundary = radius / xp.where(gnorm > 0, gnorm, 1.0)
    d_sd = -xp.minimum(alpha, to_boundary) * g
    n_sd = xp.minimum(alpha, to_boundary) * gnorm
    d = d_gn - d_sd
    a = xp.sum(d * d)
    b = 2.0 * xp.sum(d_sd * d)
    c = n_sd**2 - radius**2
    tau = (-b + xp.sqrt(xp.maximum(b * b - 4.0 * a * c, 0.0))) / (2.0 * xp.where(a > 0, a, 1.0))
    blend = d_sd + xp.clip(tau, 0.0, 1.0) * d
    return xp.where(n_gn <= radius, d_gn, xp.where(alpha >= to_boundary, d_sd, blend))


def model_decrease(delta, g, Hdelta, xp):
    """L = −gᵀδ − ½δᵀHδ, the decrease the quadratic model predicts (over the last axis)."""
    return -xp.sum(g * delta, axis=-1) - 0.5 * xp.sum(delta * Hdelta, axis=-1)


def initial_reason(cost, gmax, h: dict, xp):
    """The reason to stop at the initial linearisation (0: none), for a finite cost and
    gradient (the drivers check finiteness first)."""
    return xp.where(cost <= h["absolute_tolerance"], ABSOLUTE,
                    xp.where(gmax <= h["gradient_tolerance"], GRADIENT, 0))


def decide(rule: StepRule, h: dict, cost, trial_cost, usable, solved, pred, step_norm,
           gmax_trial, lam, nu, xp):
    """One iteration's decision, elementwise over lanes (NumPy scalars or JAX arrays).

    ``usable``: the system was solved and the trial is finite (cost and Jacobian) and
    violates no validity; ``solved``: the damped system was factorised; ``pred`` the model
    decrease; ``gmax_trial`` ‖g‖∞ at the trial point (used if it is accepted).
    Returns (accepted, gain ratio, λ, ν, reason code).
    """
    gain = xp.where(usable & (pred > 0), (cost - trial_cost) / xp.where(pred > 0, pred, 1.0),
                    -np.inf)
    accepted = usable & (trial_cost < cost)
    if rule.gn:
        lam_acc, lam_rej, nu_acc, nu_rej = lam, lam, nu, nu
        fail = xp.where(solved, COST_INCREASE, LINEAR_SOLVER)
    elif rule.dogleg:  # λ is the trust radius Δ
        grow = (gain > 0.75) & (step_norm >= 0.99 * lam)
        shrunk = 0.25 * xp.where(xp.isfinite(step_norm), xp.minimum(step_norm, lam), lam)
        lam_acc = xp.where(gain < 0.25, shrunk,
                           xp.where(grow, xp.minimum(2.0 * lam, h["lambda_max"]), lam))
        lam_rej, nu_acc, nu_rej = shrunk, nu, nu
        fail = xp.where(solved, 0, LINEAR_SOLVER)
    else:
        if rule.schedule == "fixed":
            lam_acc = xp.maximum(h["lambda_min"], lam / h["lambda_factor"])
            lam_rej, nu_acc, nu_rej = lam * h["lambda_factor"], nu, nu
        else:
            with np.errstate(over="ignore"):  # a gain beyond 1e102 (the model's decrease ~0): 1/3, silently
                shrink = xp.maximum(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            lam_acc = xp.maximum(h["lambda_min"], lam * shrink)
            lam_rej, nu_acc, nu_rej = lam * nu, 2.0, 2.0 * nu
        fail = xp.where(lam_rej > h["lambda_max"], LAMBDA_MAX, 0)
    rel = h["relative_tolerance"]
    on_accept = xp.where(
        trial_cost <= h["absolute_tolerance"], ABSOLUTE,
        xp.where(cost - trial_cost <= rel * cost, RELATIVE,
                 xp.where(gmax_trial <= h["gradient_tolerance"], GRADIENT,
                          xp.where(step_norm <= h["step_tolerance"], STEP, 0))))
    small = usable & (xp.abs(cost - trial_cost) <= rel * cost) & (pred <= rel * cost)
    on_reject = xp.where(solved & (step_norm <= h["step_tolerance"]), STEP,
                         xp.where(small, RELATIVE, fail))
    return (accepted, gain, xp.where(accepted, lam_acc, lam_rej),
            xp.where(accepted, nu_acc, nu_rej), xp.where(accepted, on_accept, on_reject))
