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
"""

from __future__ import annotations

import json
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from . import __version__
from .ellipsoid import Ellipsoid, EllipsoidFull, EllipsoidRTS
from .ellipsoid import _sorted_axes
from .evaluation import cuboid_iou_arrays, orientation_errors_deg
from .factors import InverseBoxFactor, SemiInverseBoxFactor
from .simulation import NOISE_LEVELS, Scenes, make_scenes
from .solver import BatchedProblem, NonlinearFactorGraph, Values
from .stats import bootstrap, paired_comparison, wilson

__all__ = [
    "StudyConfig",
    "StudyResult",
    "run_study",
    "write_outputs",
    "PAPER_SUCCESS",
    "PAPER_IOU_H",
    "PARAM_NAMES",
    "MODEL_NAMES",
]

PARAM_NAMES = {"F": "Full (regularised)", "S": "Rot-Trans-Scale", "O": "SPD(3)"}
MODEL_NAMES = {"inv": "inverse box", "semi": "semi-inverse box"}
_PARAM_TYPES = {"F": EllipsoidFull, "S": EllipsoidRTS, "O": Ellipsoid}
_MODEL_FACTORS = {"inv": InverseBoxFactor, "semi": SemiInverseBoxFactor}

#: The paper's Table II: successes (F, S, O) out of 24, per noise and (model, range).
PAPER_SUCCESS = {
    ("L", "inv", 60): (24, 24, 24), ("L", "semi", 60): (24, 24, 24),
    ("L", "inv", 120): (24, 24, 24), ("L", "semi", 120): (24, 24, 24),
    ("M", "inv", 60): (15, 23, 23), ("M", "semi", 60): (20, 24, 24),
    ("M", "inv", 120): (20, 24, 24), ("M", "semi", 120): (21, 24, 24),
    ("H", "inv", 60): (1, 13, 12), ("H", "semi", 60): (17, 24, 24),
    ("H", "inv", 120): (3, 19, 21), ("H", "semi", 120): (7, 24, 24),
}  # fmt: skip
#: The paper's average IoU (F, S, O) over all trials at noise H.
PAPER_IOU_H = {
    ("inv", 60): (0.15, 0.39, 0.37), ("semi", 60): (0.43, 0.56, 0.57),
    ("inv", 120): (0.21, 0.69, 0.76), ("semi", 120): (0.30, 0.76, 0.76),
}  # fmt: skip


@dataclass(frozen=True)
class StudyConfig:
    trials: int = 24
    seed: int = 0
    params: tuple[str, ...] = ("F", "S", "O")
    models: tuple[str, ...] = ("inv", "semi")
    angles: tuple[float, ...] = (60.0, 120.0)
    noise: tuple[str, ...] = ("L", "M", "H")
    max_iters: int = 100
    n_views: int = 10
    #: LM initial damping, relative to diag(H) (see docs/simulation.md).
    lambda_initial: float = 1.0
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
    #: True gives 2-3x faster LM loops for ~0.8 s more compile per structure
    #: (``benchmarks/simulation.py --optimize yes``).
    optimize: bool | None = None

    def __post_init__(self):
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
        if self.trials < 1 or self.max_iters < 1 or self.n_views < 3:
            raise ValueError("need trials ≥ 1, max_iters ≥ 1 and n_views ≥ 3")

    @property
    def cells(self) -> list[tuple[float, str]]:
        return [(a, n) for a in self.angles for n in self.noise]


@dataclass
class StudyResult:
    config: StudyConfig
    #: One record per (trial, model, param): the columns of trials.csv.
    rows: list[dict]
    #: (model, param) → relative cost history (B, max_iters + 1), cost / initial cost,
    #: forward-filled after the run stopped; B = cells × trials in config.cells order.
    histories: dict[tuple[str, str], np.ndarray]
    timings: dict[str, float] = field(default_factory=dict)


# --- scenes and problems -----------------------------------------------------------------
def _all_scenes(cfg: StudyConfig) -> tuple[Scenes, np.ndarray, np.ndarray]:
    """Scenes of every cell, concatenated along the batch axis, with their cell labels."""
    parts, angle, noise = [], [], []
    for ia, a in enumerate(cfg.angles):
        for n in cfg.noise:
            s = make_scenes(
                (cfg.seed, ia, "LMH".index(n)), cfg.trials, n, a, n_views=cfg.n_views
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


def _box_sigma(model: str, cfg: StudyConfig) -> float:
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
    for i in range(cfg.n_views):
        values[("x", i)] = jaxlie.SE3(scenes.poses.wxyz_xyz[0, i])
        graph.add(
            factor(
                ("x", i), "object", scenes.boxes[0, i], scenes.camera,
                sigma=_box_sigma(model, cfg),
            )
        )  # fmt: skip
    values["object"] = landmark0
    return graph, values


def _batched_args(scenes: Scenes, cfg: StudyConfig):
    """Per-factor batched args (box, camera) for the template's factors."""
    B = len(scenes)
    cam = jax.tree.map(lambda x: jnp.full((B,), x), scenes.camera)
    return {i: (jnp.asarray(scenes.boxes[:, i]), cam) for i in range(cfg.n_views)}


def _solve_structure(model, param, scenes, cfg):
    """One vmapped solve of every trial of every cell for one (model, param)."""
    init = _convert(param, scenes.initial)
    truth = _convert(param, scenes.truth)
    first = jax.tree.map(lambda a: a[0], init)
    graph, values = _template(model, scenes, cfg, first)
    problem = BatchedProblem(
        graph, values, fixed=[("x", i) for i in range(cfg.n_views)],
        max_iterations=cfg.max_iters, lambda_initial=cfg.lambda_initial,
        optimize=cfg.optimize,
    )  # fmt: skip
    args = _batched_args(scenes, cfg)
    pose_values = {
        ("x", i): jax.tree.map(lambda a, i=i: a[:, i], scenes.poses) for i in range(cfg.n_views)
    }
    t0 = time.perf_counter()
    result = problem.solve(factor_args=args, values={**pose_values, "object": init})
    t1 = time.perf_counter()
    truth_cost = problem.cost(factor_args=args, values={**pose_values, "object": truth})
    return {
        "estimate": _to_ellipsoid(result.values_batched["object"]),
        "initial_cost": np.asarray(result.initial_cost),
        "final_cost": np.asarray(result.final_cost),
        "truth_cost": np.asarray(truth_cost),
        "cost_history": np.asarray(result.cost_history),
        "iterations": np.asarray(result.iterations),
        "reason": list(result.reason),
        "seconds": t1 - t0,
        "timings": dict(result.timings),
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
    return jax.vmap(_sorted_axes)(P)


def _ious_and_orientation(est: Ellipsoid, truth: Ellipsoid):
    """IoU of the circumscribed cuboids, orientation error (deg) and s₃/s₁ of the estimate,
    for a batch of estimates.

    A collapsed estimate (smallest radius < 1 nm, or non-finite) has no cuboid: IoU 0,
    orientation error NaN.
    """
    Re, se = (np.asarray(a) for a in _axes_batch(est.P))
    Rt, st = (np.asarray(a) for a in _axes_batch(truth.P))
    ce, ct = np.asarray(est.center), np.asarray(truth.center)
    ok = np.all(np.isfinite(Re), axis=(1, 2)) & np.all(np.isfinite(se), axis=1)
    ok &= np.all(np.isfinite(ce), axis=1) & (np.min(np.where(np.isfinite(se), se, 0), axis=1) > 1e-9)
    iou = np.zeros(len(ok))
    if ok.any():
        iou[ok] = cuboid_iou_arrays(ce[ok], Re[ok], se[ok], ct[ok], Rt[ok], st[ok])
    orient = orientation_errors_deg(np.where(ok[:, None, None], Re, np.nan), Rt)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(np.all(np.isfinite(se), axis=1), se[:, 2] / se[:, 0], np.nan)
    return iou, orient, ratio


def run_study(
    cfg: StudyConfig = StudyConfig(),
    progress: Callable[[str, int, int], None] | None = None,
) -> StudyResult:
    """Run the grid; ``progress(stage, done, total)`` is called as structures finish."""
    t_start = time.perf_counter()
    structures = [(m, p) for m in cfg.models for p in cfg.params]
    total = len(structures) + 1
    scenes, angle_lab, noise_lab = _all_scenes(cfg)
    trial_lab = np.tile(np.arange(cfg.trials), len(cfg.cells))
    if progress:
        progress("scenes", 1, total)
    rows: list[dict] = []
    histories: dict = {}
    timings = {"scenes": time.perf_counter() - t_start, "solve": 0.0, "evaluate": 0.0}
    B = len(scenes)
    for k, (model, param) in enumerate(structures):
        out = _solve_structure(model, param, scenes, cfg)
        t_eval = time.perf_counter()
        thr = (1 + cfg.success_rtol) * out["truth_cost"] + cfg.success_atol
        hist = _forward_fill(out["cost_history"], out["initial_cost"])
        below = hist <= thr[:, None]
        reached = below.any(axis=1)
        first = np.where(reached, below.argmax(axis=1), -1)
        success = out["final_cost"] <= thr
        iou, orient, ratio = _ious_and_orientation(out["estimate"], scenes.truth)
        histories[(model, param)] = hist / np.maximum(out["initial_cost"][:, None], 1e-300)
        per_trial_s = out["seconds"] / B
        for b in range(B):
            rows.append(
                {
                    "angle": int(angle_lab[b]),
                    "noise": str(noise_lab[b]),
                    "model": model,
                    "param": param,
                    "trial": int(trial_lab[b]),
                    "success": bool(success[b]),
                    "iterations_to_tol": int(first[b]) if success[b] else "",
                    "final_cost": float(out["final_cost"][b]),
                    "iou": float(iou[b]),
                    "orientation_error_deg": float(orient[b]),
                    "seconds": per_trial_s,
                    "truth_cost": float(out["truth_cost"][b]),
                    "initial_cost": float(out["initial_cost"][b]),
                    "iterations": int(out["iterations"][b]),
                    "reason": out["reason"][b],
                    "min_radius_ratio": float(ratio[b]),
                }
            )
        timings["solve"] += out["seconds"]
        timings.setdefault("structures", {})[f"{model}-{param}"] = {
            "seconds": out["seconds"], **{k2: float(v) for k2, v in out["timings"].items() if np.isscalar(v)}
        }
        timings["evaluate"] += time.perf_counter() - t_eval
        if progress:
            progress(f"{model}-{param}", k + 2, total)
    timings["wall"] = time.perf_counter() - t_start
    iters = sum(r["iterations"] for r in rows)
    st = timings.get("structures", {}).values()
    timings["compile"] = sum(v.get("trace", 0.0) + v.get("compile", 0.0) for v in st)
    timings["solve_loops"] = sum(v.get("solve", 0.0) for v in st)
    timings["problem_iterations"] = iters
    # the batched LM loops alone (compile excluded), per iteration of each problem
    timings["us_per_problem_iteration"] = 1e6 * timings["solve_loops"] / max(iters, 1)
    return StudyResult(cfg, rows, histories, timings)


# --- summaries and files -----------------------------------------------------------------
#: An estimate whose smallest radius is below this fraction of its largest has collapsed.
COLLAPSED_RATIO = 1e-3

CSV_COLUMNS = [
    "angle", "noise", "model", "param", "trial", "success", "iterations_to_tol", "final_cost",
    "iou", "orientation_error_deg", "seconds", "truth_cost", "initial_cost", "iterations", "reason",
    "min_radius_ratio",
]  # fmt: skip


def _select(rows, **kw):
    return [r for r in rows if all(r[k] == v for k, v in kw.items())]


def summarize(result: StudyResult) -> dict:
    cfg, rows = result.config, result.rows
    cells = []
    for a, n in cfg.cells:
        for m in cfg.models:
            for p in cfg.params:
                rs = _select(rows, angle=int(a), noise=n, model=m, param=p)
                succ = [r for r in rs if r["success"]]
                collapsed = [not r["min_radius_ratio"] >= COLLAPSED_RATIO for r in rs]
                its = [r["iterations_to_tol"] for r in succ]
                cells.append(
                    {
                        "angle": int(a), "noise": n, "model": m, "param": p,
                        "trials": len(rs), "successes": len(succ),
                        "failures_collapsed": sum(c and not r["success"] for c, r in zip(collapsed, rs)),
                        "successes_collapsed": sum(c and r["success"] for c, r in zip(collapsed, rs)),
                        "success_rate": wilson(len(succ), len(rs)).as_dict(),
                        "iou_all": bootstrap([r["iou"] for r in rs]).as_dict(),
                        "iou_success": bootstrap([r["iou"] for r in succ]).as_dict(),
                        "iterations_to_tol": bootstrap(np.array(its, dtype=float)).as_dict(),
                        "orientation_error_deg_success": bootstrap(
                            [r["orientation_error_deg"] for r in succ]).as_dict(),
                    }
                )  # fmt: skip
    paired = {}
    if "O" in cfg.params and "S" in cfg.params:
        for m in cfg.models:
            for scope, filt in [("all", {}), *[(f"noise {n}", {"noise": n}) for n in cfg.noise]]:
                o = _select(rows, model=m, param="O", **filt)
                s = _select(rows, model=m, param="S", **filt)
                key = lambda r: (r["angle"], r["noise"], r["trial"])  # noqa: E731
                s_by = {key(r): r for r in s}
                a_it, b_it = [], []
                for r in o:
                    q = s_by[key(r)]
                    if r["success"] and q["success"]:
                        a_it.append(r["iterations_to_tol"])
                        b_it.append(q["iterations_to_tol"])
                paired[f"{m} {scope}"] = paired_comparison(a_it, b_it).as_dict()
    return {
        "config": asdict(result.config),
        "cells": cells,
        "paired_iterations_O_vs_S": paired,
        "timings": result.timings,
        "versions": {"spdslam": __version__, "jax": jax.__version__, "python": platform.python_version()},
        "machine": {"platform": platform.platform(), "processor": platform.processor()},
    }


def _cell(summary, a, n, m, p):
    for c in summary["cells"]:
        if (c["angle"], c["noise"], c["model"], c["param"]) == (int(a), n, m, p):
            return c
    raise KeyError((a, n, m, p))


def table_markdown(summary: dict) -> str:
    cfg = summary["config"]
    params, models, angles = cfg["params"], cfg["models"], [int(a) for a in cfg["angles"]]
    cols = [(m, a) for a in angles for m in models]
    N = cfg["trials"]
    lines = [
        f"# Table II: successes {'+'.join(params)} out of {N} (paper: out of 24)",
        "",
        f"Success: final cost ≤ (1 + {cfg['success_rtol']})·C̄ + {cfg['success_atol']}, C̄ = cost at the ground truth.",
        "",
        "| noise | " + " | ".join(f"{m}-{a}" for m, a in cols) + " |",
        "| --- | " + " | ".join("---" for _ in cols) + " |",
    ]
    for n in cfg["noise"]:
        cells = []
        for m, a in cols:
            ours = "+".join(str(_cell(summary, a, n, m, p)["successes"]) for p in params)
            paper = PAPER_SUCCESS.get((n, m, a))
            ref = "+".join(str(paper["FSO".index(p)]) for p in params) if paper else "–"
            cells.append(f"{ours} (paper {ref})")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines += ["", f"## Average IoU {'/'.join(params)} over all trials (paper at H)", ""]
    lines += ["| noise | " + " | ".join(f"{m}-{a}" for m, a in cols) + " |"]
    lines += ["| --- | " + " | ".join("---" for _ in cols) + " |"]
    for n in cfg["noise"]:
        cells = []
        for m, a in cols:
            ours = "/".join(f"{_cell(summary, a, n, m, p)['iou_all']['estimate']:.2f}" for p in params)
            paper = PAPER_IOU_H.get((m, a)) if n == "H" else None
            ref = " (paper " + "/".join(f"{paper['FSO'.index(p)]:.2f}" for p in params) + ")" if paper else ""
            cells.append(ours + ref)
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines += ["", "## 95 % confidence intervals", ""]
    lines += [f"Collapsed: the estimate's smallest radius is below {COLLAPSED_RATIO:g} of its largest (a flat disc or a needle)."]
    lines += [""]
    lines += ["| range | noise | model | param | success rate (Wilson) | IoU all (bootstrap) | IoU successful | iterations to tol | failed (collapsed) |"]
    lines += ["| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for c in summary["cells"]:
        sr, ia, isu, it = c["success_rate"], c["iou_all"], c["iou_success"], c["iterations_to_tol"]
        f = lambda d, k=".2f": f"{d['estimate']:{k}} [{d['low']:{k}}, {d['high']:{k}}]"  # noqa: E731
        lines.append(
            f"| {c['angle']} | {c['noise']} | {c['model']} | {c['param']} | {f(sr)} | {f(ia)} | {f(isu)} | "
            f"{f(it, '.1f')} | {c['trials'] - c['successes']} ({c['failures_collapsed']}) |"
        )
    if summary["paired_iterations_O_vs_S"]:
        lines += ["", "## Iterations to tolerance, SPD (O) vs RTS (S), paired on trials where both succeed", ""]
        lines += ["| model, trials | pairs | mean O | mean S | O/S ratio of means [95 % CI] | Wilcoxon p | O faster in |"]
        lines += ["| --- | --- | --- | --- | --- | --- | --- |"]
        for k, c in summary["paired_iterations_O_vs_S"].items():
            r = c["ratio_of_means"]
            lines.append(
                f"| {k} | {c['n']} | {c['mean_a']:.2f} | {c['mean_b']:.2f} | "
                f"{r['estimate']:.3f} [{r['low']:.3f}, {r['high']:.3f}] | {c['wilcoxon_p']:.2g} | "
                f"{100 * c['fraction_a_less']:.0f} % |"
            )
    t = summary["timings"]
    lines += [
        "",
        f"Wall time {t['wall']:.2f} s: scenes {t['scenes']:.2f} s, solves {t['solve']:.2f} s "
        f"(of which tracing + XLA compilation {t['compile']:.2f} s, LM loops {t['solve_loops']:.2f} s), "
        f"evaluation {t['evaluate']:.2f} s; {t['us_per_problem_iteration']:.1f} µs per problem-iteration "
        f"(LM loops / {t['problem_iterations']} problem-iterations).",
    ]
    return "\n".join(lines) + "\n"


def plot_convergence(result: StudyResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = result.config
    angle_lab = np.repeat([a for a, _ in cfg.cells], cfg.trials)
    noise_lab = np.repeat([n for _, n in cfg.cells], cfg.trials)
    fig, axes = plt.subplots(
        len(cfg.angles), len(cfg.noise), figsize=(4.2 * len(cfg.noise), 3.4 * len(cfg.angles)),
        squeeze=False, sharex=True,
    )  # fmt: skip
    colors = {"F": "tab:red", "S": "tab:blue", "O": "tab:green"}
    styles = {"inv": "-", "semi": "--"}
    for i, a in enumerate(cfg.angles):
        for j, n in enumerate(cfg.noise):
            ax = axes[i, j]
            sel = (angle_lab == a) & (noise_lab == n)
            for (m, p), h in result.histories.items():
                y = np.maximum(h[sel], 1e-16)
                it = np.arange(y.shape[1])
                med = np.median(y, axis=0)
                q1, q3 = np.quantile(y, [0.25, 0.75], axis=0)
                ax.plot(it, med, styles[m], color=colors[p], lw=1.4, label=f"{p}-{m}")
                ax.fill_between(it, q1, q3, color=colors[p], alpha=0.10)
            ax.set_yscale("log")
            ax.set_title(f"{int(a)}°, noise {n}")
            if i == len(cfg.angles) - 1:
                ax.set_xlabel("iteration")
            if j == 0:
                ax.set_ylabel("cost / initial cost")
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, ncol=2)
    fig.suptitle("Cost vs iteration: median and interquartile band (F Full, S RTS, O SPD; - inv, -- semi)")
    fig.tight_layout()
    fig.savefig(path, dpi=110, format="png")
    plt.close(fig)


def write_outputs(result: StudyResult, out: Path) -> dict:
    """trials.csv, table.md, convergence.png and summary.json under ``out``; each file is
    written to a temporary name first, so nothing is left half-written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(result)

    def atomic(name: str, write):
        tmp = out / f".{name}.tmp"
        write(tmp)
        tmp.replace(out / name)

    def csv(path):
        with open(path, "w") as f:
            f.write(",".join(CSV_COLUMNS) + "\n")
            for r in result.rows:
                f.write(",".join(_fmt(r[c]) for c in CSV_COLUMNS) + "\n")

    atomic("trials.csv", csv)
    atomic("table.md", lambda p: p.write_text(table_markdown(summary)))
    atomic("convergence.png", lambda p: plot_convergence(result, p))
    atomic("summary.json", lambda p: p.write_text(json.dumps(summary, indent=1, default=_json_default)))
    return summary


def _fmt(v) -> str:
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return "nan" if not np.isfinite(v) else f"{v:.10g}"
    return str(v)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)
