"""The paper's simulation study (Sec. IV-A, Table II, Fig. 12), batched.

Grid: viewing range (60°, 120°) × noise level (L, M, H) × box model (inv, semi) ×
parameterisation (F Full-regularised, S Rot-Trans-Scale, O SPD(3)), ``trials`` scenes per
(range, noise) cell; the six (model, parameterisation) structures see the same scenes, so
methods are compared on paired trials. Each structure is one vmapped LM solve over all
cells × trials (no Python loop over trials); each structure compiles once.

Success rule (same for every method): with C̄ the cost at the ground-truth landmark,

    success  ⇔  final cost ≤ (1 + rtol)·C̄ + atol,

so a run stuck in a wrong basin fails whatever its parameterisation, and a run that reached
the basin of the truth succeeds even with noisy boxes (its optimum lies below C̄).
``iterations_to_tol`` is the first iteration whose cost satisfies the same inequality.
Summaries, tables and figures: ``_summary``, ``_outputs``; the paper's numbers: ``_paper``.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Callable, cast

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from ..evaluation import cuboid_iou_arrays, orientation_errors_deg
from ..factors import InverseBoxFactor, SemiInverseBoxFactor
from ..geometry import Ellipsoid, EllipsoidFull, EllipsoidRTS, sorted_axes
from ..solver import Dogleg, L, LevenbergMarquardt, NonlinearFactorGraph, Values, X
from ..synthetic import NOISE_LEVELS, Protocol, Scenes, get_protocol, make_scenes

__all__ = ["CSV_COLUMNS", "HISTORY_TRIALS", "STUDY_CHUNK", "StudyConfig", "StudyResult", "all_scenes", "box_sigma",
           "history_labels", "run_study"]

_PARAM_TYPES = {"F": EllipsoidFull, "S": EllipsoidRTS, "O": Ellipsoid}
_MODEL_FACTORS = {"inv": InverseBoxFactor, "semi": SemiInverseBoxFactor}
#: The landmark's key in every trial's graph.
OBJECT = L(0)


@dataclass(frozen=True)
class StudyConfig:
    trials: int = 24
    seed: int = 0
    params: tuple[str, ...] = ("F", "S", "O")
    models: tuple[str, ...] = ("inv", "semi")
    angles: tuple[float, ...] = (60.0, 120.0)
    noise: tuple[str, ...] = ("L", "M", "H")
    #: LM budget: at H a third of the optima have a collapsed axis, which the SPD chart
    #: approaches geometrically (docs/simulation.md, "Budget").
    max_iters: int = 200
    #: The scenes' free choices (``synthetic.Protocol`` or a name of ``synthetic.PROTOCOLS``):
    #: "paper", calibrated to the paper's method-independent figures; "v1", the study
    #: until issue 16 (docs/simulation.md).
    protocol: Protocol | str = "paper"
    #: Views per scene; None: the protocol's (10, as in the paper).
    n_views: int | None = None
    #: The solver: "lm" (Levenberg-Marquardt) or "dogleg" (Powell's dogleg, trust region).
    optimizer: str = "lm"
    #: LM initial damping, relative to the damping matrix (see docs/simulation.md).
    lambda_initial: float = 1.0
    #: Dogleg's initial trust radius, in the tangent metric.
    trust_radius_initial: float = 1.0
    #: Success: final cost ≤ (1 + success_rtol)·C̄ + success_atol (whitened cost units).
    success_rtol: float = 0.01
    success_atol: float = 1e-6
    #: Box-factor standard deviations: inverse in px per edge, semi-inverse in m² per edge
    #: plane. One σ per model for every noise level: with one factor type per problem the
    #: estimate does not depend on it, only the cost's units do.
    inverse_sigma: float = 1.0
    semi_sigma: float = 0.01
    #: Compile the batched solver with XLA's optimisations: None chooses by the work
    #: (``BatchedProblem``'s rule: off for this grid's size, where compile time dominates);
    #: True: faster LM loops for a longer compile (docs/performance.md,
    #: ``benchmarks/simulation.py --optimize yes``).
    optimize: bool | None = None

    def __post_init__(self):
        pr = get_protocol(self.protocol).replace(n_views=self.n_views)
        object.__setattr__(self, "protocol", pr)
        object.__setattr__(self, "n_views", pr.n_views)
        for p in self.params:
            if p not in _PARAM_TYPES:
                raise ValueError(f"unknown parameterisation {p!r}: expected F, S or O")
        for m in self.models:
            if m not in _MODEL_FACTORS:
                raise ValueError(f"unknown model {m!r}: expected inv or semi")
        for n in self.noise:
            if n not in NOISE_LEVELS:
                raise ValueError(f"unknown noise level {n!r}: expected L, M or H")
        for a in self.angles:
            if not 0 < a <= 360:
                raise ValueError(f"viewing range must be in (0, 360] degrees, got {a}")
        if self.optimizer not in ("lm", "dogleg"):
            raise ValueError(f"unknown optimizer {self.optimizer!r}: expected lm or dogleg")
        if self.trials < 1 or self.max_iters < 1 or self.n_views < 3:
            raise ValueError("need trials ≥ 1, max_iters ≥ 1 and n_views ≥ 3")

    @property
    def cells(self) -> list[tuple[float, str]]:
        return [(a, n) for a in self.angles for n in self.noise]


#: trials.csv's columns, in order.
CSV_COLUMNS = [
    "angle", "noise", "model", "param", "trial", "success", "iterations_to_tol", "final_cost",
    "iou", "orientation_error_deg", "seconds", "truth_cost", "initial_cost", "iterations", "reason",
    "min_radius_ratio",
]  # fmt: skip
#: Problems solved at a time by ``run_study`` without an engine: the memory a study holds
#: beyond its columns (scenes of a chunk, cost histories, compiled buffers) is bounded by
#: this, whatever the number of trials.
STUDY_CHUNK = 8192
#: Cost histories kept per (cell, model, param): those of the first this many trials, which
#: convergence.png summarises (every trial's history would be 1.6 kB per solve).
HISTORY_TRIALS = 1000


@dataclass
class StudyResult:
    config: StudyConfig
    #: trials.csv's columns (``CSV_COLUMNS``), one entry per (trial, model, param): NumPy
    #: arrays; ``iterations_to_tol`` is −1 where the trial failed (an empty field).
    columns: dict[str, np.ndarray]
    #: (model, param) → relative cost history (B', max_iters + 1), cost / initial cost,
    #: forward-filled after the run stopped, of the first ``HISTORY_TRIALS`` trials of each
    #: cell (B' = cells × min(trials, HISTORY_TRIALS), in config.cells order).
    histories: dict[tuple[str, str], np.ndarray]
    timings: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.columns["trial"])

    @property
    def rows(self) -> list[dict]:
        """The records as dicts (built on each call: for small studies)."""
        c = self.columns
        out = []
        for b in range(len(self)):
            success = bool(c["success"][b])
            out.append({
                "angle": int(c["angle"][b]), "noise": str(c["noise"][b]), "model": str(c["model"][b]),
                "param": str(c["param"][b]), "trial": int(c["trial"][b]), "success": success,
                "iterations_to_tol": int(c["iterations_to_tol"][b]) if success else "",
                **{k: float(c[k][b]) for k in ("final_cost", "iou", "orientation_error_deg", "seconds",
                                               "truth_cost", "initial_cost")},
                "iterations": int(c["iterations"][b]), "reason": str(c["reason"][b]),
                "min_radius_ratio": float(c["min_radius_ratio"][b]),
            })  # fmt: skip
        return out


def history_labels(cfg: StudyConfig) -> tuple[np.ndarray, np.ndarray]:
    """(angle, noise) of each row of ``StudyResult.histories``."""
    k = min(cfg.trials, HISTORY_TRIALS)
    return (np.repeat([a for a, _ in cfg.cells], k), np.repeat([n for _, n in cfg.cells], k))


# --- scenes and problems -----------------------------------------------------------------
def all_scenes(cfg: StudyConfig) -> tuple[Scenes, np.ndarray, np.ndarray]:
    """Scenes of every cell, concatenated along the batch axis, with their cell labels."""
    parts, angle, noise = [], [], []
    for ia, a in enumerate(cfg.angles):
        for n in cfg.noise:
            s = make_scenes(
                (cfg.seed, ia, "LMH".index(n)), cfg.trials, n, a, protocol=cfg.protocol
            )
            parts.append(s)
            angle += [a] * cfg.trials
            noise += [n] * cfg.trials
    cat = lambda *xs: jnp.concatenate(xs)  # noqa: E731
    scenes = Scenes(
        jax.tree.map(cat, *[p.truth for p in parts]),
        jax.tree.map(cat, *[p.initial for p in parts]),
        jax.tree.map(cat, *[p.poses for p in parts]),
        np.concatenate([p.boxes for p in parts]),
        parts[0].camera,
    )
    return scenes, np.array(angle), np.array(noise)


def box_sigma(model: str, cfg: StudyConfig) -> float:
    """The σ of ``model``'s box factors in the study: ``semi_sigma`` (m² per edge plane) for
    the semi-inverse model, else ``inverse_sigma`` (px per edge)."""
    return cfg.semi_sigma if model == "semi" else cfg.inverse_sigma


_FROM_ELLIPSOID = {
    "F": jax.jit(jax.vmap(EllipsoidFull.from_ellipsoid)),
    "S": jax.jit(jax.vmap(EllipsoidRTS.from_ellipsoid)),
}
_TO_ELLIPSOID = jax.jit(jax.vmap(lambda y: y.to_ellipsoid()))


def _convert(param: str, e: Ellipsoid):
    """Batched Ellipsoid → batched landmark of the parameterisation."""
    return e if param == "O" else _FROM_ELLIPSOID[param](e)


def _to_ellipsoid(x) -> Ellipsoid:
    return x if isinstance(x, Ellipsoid) else _TO_ELLIPSOID(x)


def _template(model: str, scenes: Scenes, cfg: StudyConfig, landmark0):
    factor = _MODEL_FACTORS[model]
    graph, values = NonlinearFactorGraph(), Values()
    for i in range(cast(int, cfg.n_views)):  # (resolved by StudyConfig)
        values[X(i)] = jaxlie.SE3(scenes.poses.wxyz_xyz[0, i])
        graph.add(factor(X(i), OBJECT, scenes.boxes[0, i], scenes.camera,
                         sigma=box_sigma(model, cfg)))
    values[OBJECT] = landmark0
    return graph, values


def _batched_args(scenes: Scenes, cfg: StudyConfig):
    """Per-factor batched args (box, camera) for the template's factors."""
    B = len(scenes)
    cam = jax.tree.map(lambda x: jnp.full((B,), x), scenes.camera)
    return {i: (jnp.asarray(scenes.boxes[:, i]), cam) for i in range(cast(int, cfg.n_views))}


def _build_structure(model, param, scenes, cfg):
    """The batched problem of every trial of every cell for one (model, param), with its
    inputs: (problem, factor args, initial values, values at the truth)."""
    init = _convert(param, scenes.initial)
    truth = _convert(param, scenes.truth)
    first = jax.tree.map(lambda a: a[0], init)
    graph, values = _template(model, scenes, cfg, first)
    if cfg.optimizer == "dogleg":
        optimizer = Dogleg(max_iterations=cfg.max_iters,
                           trust_radius_initial=cfg.trust_radius_initial)
    else:
        optimizer = LevenbergMarquardt(max_iterations=cfg.max_iters,
                                       lambda_initial=cfg.lambda_initial)
    problem = optimizer.batched(graph, values, fixed=[X(i) for i in range(cfg.n_views)],
                                optimize=cfg.optimize)
    args = _batched_args(scenes, cfg)
    pose_values = {
        X(i): jax.tree.map(lambda a, i=i: a[:, i], scenes.poses) for i in range(cfg.n_views)
    }
    return problem, args, {**pose_values, OBJECT: init}, {**pose_values, OBJECT: truth}


def _solve_structure(built, compiled: dict | None = None):
    """One vmapped solve of a built structure (``_build_structure``); ``compiled``: the
    trace/compile seconds when it was compiled ahead (``BatchedProblem.compile``)."""
    problem, args, init, truth = built
    t0 = time.perf_counter()
    result = problem.solve(factor_args=args, values=init)
    t1 = time.perf_counter()
    truth_cost = problem.cost(factor_args=args, values=truth)
    timings = dict(result.timings)
    if compiled:
        timings.update(compiled)
    return {
        "estimate": _to_ellipsoid(result.values_batched[OBJECT]),
        "initial_cost": np.asarray(result.initial_cost),
        "final_cost": np.asarray(result.final_cost),
        "truth_cost": np.asarray(truth_cost),
        "cost_history": np.asarray(result.cost_history),
        "iterations": np.asarray(result.iterations),
        "reason": list(result.reason),
        "seconds": t1 - t0,
        "timings": timings,
    }


# --- evaluation --------------------------------------------------------------------------
def _forward_fill(h: np.ndarray, initial: np.ndarray) -> np.ndarray:
    """Cost after each iteration with the initial cost in column 0; NaN padding → last value."""
    full = np.concatenate([initial[:, None], h], axis=1)
    mask = np.isfinite(full)
    idx = np.where(mask, np.arange(full.shape[1])[None, :], 0)
    np.maximum.accumulate(idx, axis=1, out=idx)
    return full[np.arange(full.shape[0])[:, None], idx]


@jax.jit
def _axes_batch(P):
    return jax.vmap(sorted_axes)(P)


def _ious_and_orientation(est: Ellipsoid, truth: Ellipsoid):
    """IoU of the circumscribed cuboids, orientation error (deg) and s₃/s₁ of the estimate,
    for a batch of estimates.

    A collapsed estimate (smallest radius < 1 nm) has no cuboid: IoU 0; its axes, and so
    its orientation error, still exist (the collapse is in s₃/s₁). Only a non-finite
    estimate has neither: orientation error NaN (an empty field in trials.csv).
    """
    Re, se = (np.asarray(a) for a in _axes_batch(est.P))
    Rt, st = (np.asarray(a) for a in _axes_batch(truth.P))
    ce, ct = np.asarray(est.center), np.asarray(truth.center)
    ok = np.all(np.isfinite(Re), axis=(1, 2)) & np.all(np.isfinite(se), axis=1)
    ok &= np.all(np.isfinite(ce), axis=1) & (np.min(np.where(np.isfinite(se), se, 0), axis=1) > 1e-9)
    iou = np.zeros(len(ok))
    if ok.any():
        iou[ok] = cuboid_iou_arrays(ce[ok], Re[ok], se[ok], ct[ok], Rt[ok], st[ok])
    axes = np.all(np.isfinite(Re), axis=(1, 2))
    orient = orientation_errors_deg(np.where(axes[:, None, None], Re, np.nan), Rt)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(np.all(np.isfinite(se), axis=1), se[:, 2] / se[:, 0], np.nan)
    return iou, orient, ratio


def _evaluate(out: dict, truth: Ellipsoid, cfg: StudyConfig) -> dict:
    """Per-trial arrays of one solved batch (``_solve_structure``'s ``out``): success,
    first iteration within tolerance, relative cost history, IoU, orientation error, s₃/s₁."""
    thr = (1 + cfg.success_rtol) * out["truth_cost"] + cfg.success_atol
    hist = _forward_fill(out["cost_history"], out["initial_cost"])
    below = hist <= thr[:, None]
    reached = below.any(axis=1)
    iou, orient, ratio = _ious_and_orientation(out["estimate"], truth)
    return {
        "success": out["final_cost"] <= thr,
        "first": np.where(reached, below.argmax(axis=1), -1),
        "history": hist / np.maximum(out["initial_cost"][:, None], 1e-300),
        "iou": iou, "orientation": orient, "ratio": ratio,
        "final_cost": out["final_cost"], "truth_cost": out["truth_cost"],
        "initial_cost": out["initial_cost"], "iterations": out["iterations"],
        "reason": np.asarray(out["reason"], dtype=object),
    }  # fmt: skip


_INTERNED: dict[str, str] = {}


def _interned(values) -> np.ndarray:
    """An object array of the strings ``values``, each distinct string stored once."""
    return np.array([_INTERNED.setdefault(str(v), str(v)) for v in values], dtype=object)


def _columns(model, param, ev: dict, seconds: np.ndarray, angle_lab, noise_lab, trial_lab) -> dict:
    """trials.csv's columns of one (model, param) from ``_evaluate``'s arrays."""
    n = len(ev["success"])
    success = np.asarray(ev["success"], bool)
    return {
        "angle": np.asarray(angle_lab, dtype=np.int64), "noise": _interned(noise_lab),
        "model": _interned([model] * n), "param": _interned([param] * n),
        "trial": np.asarray(trial_lab, dtype=np.int64), "success": success,
        "iterations_to_tol": np.where(success, np.asarray(ev["first"]), -1).astype(np.int64),
        "final_cost": np.asarray(ev["final_cost"], float), "iou": np.asarray(ev["iou"], float),
        "orientation_error_deg": np.asarray(ev["orientation"], float),
        "seconds": np.asarray(seconds, float), "truth_cost": np.asarray(ev["truth_cost"], float),
        "initial_cost": np.asarray(ev["initial_cost"], float),
        "iterations": np.asarray(ev["iterations"], dtype=np.int64), "reason": _interned(ev["reason"]),
        "min_radius_ratio": np.asarray(ev["ratio"], float),
    }  # fmt: skip


def _concat_columns(parts: list[dict]) -> dict:
    return {k: np.concatenate([q[k] for q in parts]) for k in CSV_COLUMNS}


def _finish_timings(timings: dict, columns: dict, t_start: float) -> None:
    timings["wall"] = time.perf_counter() - t_start
    iters = int(np.sum(columns["iterations"]))
    st = timings.get("structures", {}).values()
    timings["solve_loops"] = sum(v.get("solve", 0.0) for v in st)
    timings["problem_iterations"] = iters
    # the batched LM loops alone (compile excluded), per iteration of each problem
    timings["us_per_problem_iteration"] = 1e6 * timings["solve_loops"] / max(iters, 1)


def _labels(cfg: StudyConfig):
    """(angle, noise, trial) of every problem of the concatenated batch, in cells order."""
    return (np.repeat([a for a, _ in cfg.cells], cfg.trials),
            np.repeat([n for _, n in cfg.cells], cfg.trials),
            np.tile(np.arange(cfg.trials), len(cfg.cells)))


def run_study(
    cfg: StudyConfig = StudyConfig(),
    progress: Callable[[str, int, int], None] | None = None,
    engine=None,
    trials_per_task: int | None = None,
    chunk: int | None = None,
) -> StudyResult:
    """Run the grid; ``progress(stage, done, total)`` is called as structures (or tasks)
    finish.

    Without an engine the problems are solved ``chunk`` (default ``STUDY_CHUNK``) at a time,
    every structure on the same chunk, and each chunk is reduced to its trials.csv columns
    (and the first ``HISTORY_TRIALS`` cost histories per cell) before the next: the memory
    held grows with the columns only (about 130 bytes per solve). The results do not
    depend on ``chunk`` (each problem runs in a lane of its own, with the compile options
    the whole batch would get).

    ``engine`` (``LocalEngine``, ``RayEngine``): shard the grid into tasks of
    ``trials_per_task`` problems of one (model, param) (default: each structure in twice as
    many tasks as the engine has workers, at least 16 and at most ``MAX_TRIALS_PER_TASK``
    problems each), one batched solve per task; the trials, costs and estimates are those of the
    run without an engine (each problem runs in a lane of its own, with the compile options the
    whole batch would get).
    A task that fails every attempt raises ``RuntimeError`` naming it.
    """
    if engine is not None:
        return _run_sharded(cfg, progress, engine, trials_per_task)
    from ..solver import AUTO_OPTIMIZE_WORK

    t_start = time.perf_counter()
    structures = [(m, p) for m in cfg.models for p in cfg.params]
    scenes, _, _ = all_scenes(cfg)
    B = len(scenes)
    size = min(B, STUDY_CHUNK if chunk is None else int(chunk))
    if size < 1:
        raise ValueError(f"chunk must be ≥ 1, got {chunk}")
    # the compile options the whole batch would get, so that chunking changes no arithmetic
    opt = cfg.optimize if cfg.optimize is not None else B * cfg.max_iters > AUTO_OPTIMIZE_WORK
    run_cfg = dataclasses.replace(cfg, optimize=opt)
    labels = _labels(cfg)
    keep_history = labels[2] < HISTORY_TRIALS
    chunks = [(lo, min(lo + size, B)) for lo in range(0, B, size)]
    total = len(chunks) * len(structures) + 1
    if progress:
        progress("scenes", 1, total)
    parts: dict = {s_: [] for s_ in structures}
    hist: dict = {s_: [] for s_ in structures}
    timings: dict[str, Any] = {"scenes": time.perf_counter() - t_start, "solve": 0.0, "evaluate": 0.0,
                               "chunks": len(chunks), "chunk": size}
    done = 1
    for c, (lo, hi) in enumerate(chunks):
        n = hi - lo
        part = scenes if n == B else _scene_slice(scenes, np.minimum(np.arange(lo, lo + size), hi - 1))
        built = [_build_structure(m, p, part, run_cfg) for m, p in structures]
        compiled = [None] * len(built)
        if c == 0:
            # every structure compiled first, two at a time (XLA compiles in parallel
            # threads), then solved one after the other; later chunks reuse the programs
            t_compile = time.perf_counter()
            compiled = _compile_all(built)
            # wall time of tracing and compiling (in parallel: less than the structures' sum)
            timings["compile"] = time.perf_counter() - t_compile
            timings["solve"] += timings["compile"]
        for k, (model, param) in enumerate(structures):
            out = _solve_structure(built[k], compiled[k])
            t_eval = time.perf_counter()
            ev = {key: v[:n] for key, v in _evaluate(out, part.truth, run_cfg).items()}
            hist[(model, param)].append(ev["history"][keep_history[lo:hi]])
            parts[(model, param)].append(_columns(
                model, param, ev, np.full(n, out["seconds"] / len(part)),
                *(lab[lo:hi] for lab in labels)))
            timings["solve"] += out["seconds"]
            st = timings.setdefault("structures", {}).setdefault(f"{model}-{param}", {"seconds": 0.0})
            st["seconds"] += out["seconds"]
            for k2, v in out["timings"].items():
                if np.isscalar(v):
                    st[k2] = st.get(k2, 0.0) + float(v)  # type: ignore[arg-type]  # a number
            timings["evaluate"] += time.perf_counter() - t_eval
            done += 1
            if progress:
                progress(f"{model}-{param}" if len(chunks) == 1 else
                         f"{model}-{param}, problems {lo}-{hi - 1} of {B}", done, total)
        del built, part
    columns = _concat_columns([q for s_ in structures for q in parts.pop(s_)])
    histories = {s_: np.concatenate(h) for s_, h in hist.items()}
    _finish_timings(timings, columns, t_start)
    return StudyResult(cfg, columns, histories, timings)


#: Seconds the compilation of a study's structures may take before ``run_study`` gives up
#: with an error (``SPDSLAM_COMPILE_TIMEOUT`` overrides): a stalled XLA compilation would
#: otherwise hang the process without a word (docs/performance.md, "Compile stress").
COMPILE_TIMEOUT = 900.0


def _compile_all(built) -> list:
    """Compile every structure (``BatchedProblem.compile``), two at a time in daemon threads
    (XLA compiles in parallel; a daemon thread does not keep a stalled process alive), in
    at most ``COMPILE_TIMEOUT`` seconds, else ``RuntimeError`` naming what to change."""
    timeout = float(os.environ.get("SPDSLAM_COMPILE_TIMEOUT", COMPILE_TIMEOUT))
    futures: list[Future] = [Future() for _ in built]
    todo = list(enumerate(built))
    lock = threading.Lock()

    def worker():
        while True:
            with lock:
                if not todo:
                    return
                k, b = todo.pop(0)
            try:
                futures[k].set_result(b[0].compile(b[1], b[2]))
            except BaseException as e:  # noqa: BLE001 - handed to the caller
                futures[k].set_exception(e)

    for _ in range(max(1, min(2, os.cpu_count() or 1))):
        threading.Thread(target=worker, daemon=True, name="spdslam-compile").start()
    deadline = time.monotonic() + timeout
    out = []
    for f in futures:
        try:
            out.append(f.result(timeout=max(0.0, deadline - time.monotonic())))
        except TimeoutError:
            raise RuntimeError(
                f"compiling the batched solver did not finish in {timeout:g} s (XLA may have "
                "stalled): run again with optimize=True (`spdslam simulate --optimize yes`, XLA's "
                "default compile options), or raise SPDSLAM_COMPILE_TIMEOUT if this machine is "
                "that slow") from None
    return out


# --- the grid in tasks (an engine: local or Ray) -------------------------------------------
def _scene_slice(scenes: Scenes, idx: np.ndarray) -> Scenes:
    """The problems ``idx`` of a batch of scenes, as numpy arrays (cheap to send)."""
    take = lambda tree: jax.tree.map(lambda a: np.asarray(a)[idx], tree)  # noqa: E731
    return Scenes(take(scenes.truth), take(scenes.initial), take(scenes.poses),
                  np.asarray(scenes.boxes)[idx], scenes.camera)


def _solve_task(cfg: StudyConfig, model: str, param: str, scenes: Scenes, n: int) -> dict:
    """One task: the batched solve of one (model, param) over ``scenes`` (its first ``n``
    problems are real, the rest repeat the last to keep one shape per structure) and its
    per-trial evaluation. Runs in a worker; ``cfg.optimize`` is decided by the driver."""
    built = _build_structure(model, param, scenes, cfg)
    compiled = built[0].compile(built[1], built[2])
    out = _solve_structure(built, compiled)
    t_eval = time.perf_counter()
    ev = _evaluate(out, scenes.truth, cfg)
    ev = {k: v[:n] for k, v in ev.items()}
    ev["evaluate"] = time.perf_counter() - t_eval
    ev["timings"] = {k: float(v) for k, v in out["timings"].items()  # type: ignore[arg-type]  # numbers
                     if np.isscalar(v)}
    ev["seconds"] = out["seconds"]
    ev["B"] = len(scenes)
    return ev


#: The default task size's ceiling: a task's cost histories (problems × iterations × 6
#: floats) stay under ~100 MB at the default 200 iterations.
MAX_TRIALS_PER_TASK = 10_000


def _run_sharded(cfg, progress, engine, trials_per_task) -> StudyResult:
    from ..solver import AUTO_OPTIMIZE_WORK, DEFAULT_LANES

    t_start = time.perf_counter()
    structures = [(m, p) for m in cfg.models for p in cfg.params]
    scenes, _, _ = all_scenes(cfg)
    B = len(scenes)
    if trials_per_task is None:
        trials_per_task = min(MAX_TRIALS_PER_TASK,
                              max(DEFAULT_LANES, -(-B // (2 * max(1, engine.workers)))))
    if trials_per_task < 1:
        raise ValueError(f"trials_per_task must be ≥ 1, got {trials_per_task}")
    size = min(trials_per_task, B)
    # the compile options the whole batch would get, so that each problem's arithmetic is
    # that of the run without an engine
    opt = cfg.optimize if cfg.optimize is not None else B * cfg.max_iters > AUTO_OPTIMIZE_WORK
    task_cfg = dataclasses.replace(cfg, optimize=opt)
    chunks = [(lo, min(lo + size, B)) for lo in range(0, B, size)]
    # each chunk's scenes sliced once, for every structure; the last chunk padded
    slices = [_scene_slice(scenes, np.minimum(np.arange(lo, lo + size), hi - 1)) for lo, hi in chunks]
    tasks, owners = [], []
    for m, p in structures:
        for (lo, hi), part in zip(chunks, slices):
            tasks.append((task_cfg, m, p, part, hi - lo))
            owners.append((m, p, lo, hi))
    timings = {"scenes": time.perf_counter() - t_start, "engine": engine.name,
               "workers": engine.workers, "tasks": len(tasks), "trials_per_task": size}
    if progress:
        progress("scenes", 1, len(tasks) + 1)

    def on_done(done, total):
        if progress:
            progress(f"{done} of {total} tasks", done + 1, total + 1)

    outcomes = engine.map(_solve_task, tasks, progress=on_done)
    failed = [(owners[o.index], o) for o in outcomes if not o.ok]
    if failed:
        (m, p, lo, hi), o = failed[0]
        raise RuntimeError(f"{len(failed)} of {len(tasks)} tasks failed; the first, {m}-{p} "
                           f"problems {lo}-{hi - 1}, after {o.attempts} attempts: {o.error}")
    labels = _labels(cfg)
    keep_history = labels[2] < HISTORY_TRIALS
    cols: list[dict] = []
    histories: dict = {}
    structures_t = timings.setdefault("structures", {})
    for m, p in structures:
        parts = [o.value for o, own in zip(outcomes, owners) if own[:2] == (m, p)]
        ev = {k: np.concatenate([q[k] for q in parts]) for k in parts[0] if k not in
              ("timings", "seconds", "B", "evaluate")}
        seconds = np.concatenate([np.full(len(q["success"]), q["seconds"] / q["B"]) for q in parts])
        histories[(m, p)] = ev["history"][keep_history]
        cols.append(_columns(m, p, ev, seconds, *labels))
        st = {"seconds": sum(q["seconds"] for q in parts)}
        for q in parts:
            for k, v in q["timings"].items():
                st[k] = st.get(k, 0.0) + v
        structures_t[f"{m}-{p}"] = st
    # sums over the tasks (worker seconds), not wall time
    timings["task_seconds"] = float(sum(o.seconds for o in outcomes))
    timings["compile"] = sum(v.get("trace", 0.0) + v.get("compile", 0.0) for v in structures_t.values())
    timings["solve"] = sum(v["seconds"] for v in structures_t.values()) + timings["compile"]
    timings["evaluate"] = float(sum(o.value["evaluate"] for o in outcomes))
    columns = _concat_columns(cols)
    _finish_timings(timings, columns, t_start)
    return StudyResult(cfg, columns, histories, timings)
