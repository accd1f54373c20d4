"""Summaries of a study: per cell success rates (Wilson), IoU and iterations (bootstrap),
collapsed estimates, paired iterations O vs S (Wilcoxon); the Markdown table beside the
paper's."""

from __future__ import annotations

import platform
from dataclasses import asdict

import jax
import numpy as np

from .._version import __version__
from ..evaluation import bootstrap, paired_comparison, wilson
from ._paper import PAPER_IOU_H, PAPER_SUCCESS, PAPER_SUCCESS_IOU
from ._study import CSV_COLUMNS, StudyResult

__all__ = ["COLLAPSED_RATIO", "CSV_COLUMNS", "pooled_success_iou", "summarize", "table_markdown"]

#: An estimate whose smallest radius is below this fraction of its largest has collapsed.
COLLAPSED_RATIO = 1e-3

def _mask(C: dict, **kw) -> np.ndarray:
    """The entries of the columns ``C`` whose fields equal ``kw``."""
    m = np.ones(len(C["trial"]), bool)
    for k, v in kw.items():
        m &= C[k] == v
    return m


def _columns_of(data) -> dict:
    """Columns from a ``StudyResult``, a columns dict or a list of row dicts."""
    if hasattr(data, "columns"):
        return data.columns
    if isinstance(data, dict):
        return data
    rows = list(data)
    C = {k: np.array([r[k] for r in rows], dtype=object) for k in CSV_COLUMNS}
    C["success"] = C["success"].astype(bool)
    for k in ("angle", "trial", "iterations"):
        C[k] = C[k].astype(np.int64)
    C["iterations_to_tol"] = np.array([-1 if v == "" else v for v in C["iterations_to_tol"]], np.int64)
    for k in ("final_cost", "iou", "orientation_error_deg", "seconds", "truth_cost", "initial_cost",
              "min_radius_ratio"):
        C[k] = C[k].astype(float)
    return C


def pooled_success_iou(data, cells, models) -> list[dict]:
    """The paper's "Average Success IoU": per (range, noise, model) the mean IoU of the
    successful trials of every parameterisation pooled (bootstrap interval), beside the
    paper's figure and the difference. ``data``: a ``StudyResult``, its columns or rows."""
    C = _columns_of(data)
    out = []
    for a, n in cells:
        for m in models:
            ious = C["iou"][_mask(C, angle=int(a), noise=n, model=m) & C["success"]]
            paper = PAPER_SUCCESS_IOU.get((n, m, int(a)))
            est = bootstrap(ious).as_dict()
            out.append({"angle": int(a), "noise": n, "model": m, "successes": len(ious), "iou": est,
                        "paper": paper,
                        "difference": None if paper is None or not np.isfinite(est["estimate"])
                        else est["estimate"] - paper})
    return out


def summarize(result: StudyResult) -> dict:
    cfg, C = result.config, result.columns
    collapsed = ~(C["min_radius_ratio"] >= COLLAPSED_RATIO)
    cells = []
    for a, n in cfg.cells:
        for m in cfg.models:
            for p in cfg.params:
                sel = _mask(C, angle=int(a), noise=n, model=m, param=p)
                succ = sel & C["success"]
                cells.append(
                    {
                        "angle": int(a), "noise": n, "model": m, "param": p,
                        "trials": int(sel.sum()), "successes": int(succ.sum()),
                        "failures_collapsed": int((collapsed & sel & ~C["success"]).sum()),
                        "successes_collapsed": int((collapsed & succ).sum()),
                        "success_rate": wilson(int(succ.sum()), int(sel.sum())).as_dict(),
                        "iou_all": bootstrap(C["iou"][sel]).as_dict(),
                        "iou_success": bootstrap(C["iou"][succ]).as_dict(),
                        "iterations_to_tol": bootstrap(C["iterations_to_tol"][succ].astype(float)).as_dict(),
                        "orientation_error_deg_success": bootstrap(
                            C["orientation_error_deg"][succ]).as_dict(),
                    }
                )  # fmt: skip
    paired = {}
    if "O" in cfg.params and "S" in cfg.params:
        for m in cfg.models:
            for scope, filt in [("all", {}), *[(f"noise {n}", {"noise": n}) for n in cfg.noise]]:
                o = np.flatnonzero(_mask(C, model=m, param="O", **filt))
                s = np.flatnonzero(_mask(C, model=m, param="S", **filt))
                # every structure's entries are in the same (angle, noise, trial) order
                for k in ("angle", "noise", "trial"):
                    if not np.array_equal(C[k][o], C[k][s]):
                        raise ValueError("the O and S trials are not paired")
                both = C["success"][o] & C["success"][s]
                paired[f"{m} {scope}"] = paired_comparison(
                    C["iterations_to_tol"][o][both].tolist(), C["iterations_to_tol"][s][both].tolist()).as_dict()
    return {
        "config": asdict(result.config),
        "cells": cells,
        "paired_iterations_O_vs_S": paired,
        "pooled_success_iou": pooled_success_iou(C, cfg.cells, cfg.models),
        "timings": result.timings,
        "versions": {"spdslam": __version__, "jax": jax.__version__, "python": platform.python_version()},
        "machine": {"platform": platform.platform(), "processor": platform.processor()},
    }


def _cell(summary, a, n, m, p):
    for c in summary["cells"]:
        if (c["angle"], c["noise"], c["model"], c["param"]) == (int(a), n, m, p):
            return c
    raise KeyError((a, n, m, p))


def protocol_line(pr: dict) -> str:
    """One line naming the scenes' protocol (``synthetic.Protocol`` as a dict)."""
    lo, hi = pr["distance"]
    return (f"Protocol {pr['name']}: f = {pr['focal']:g} px, cameras {lo:g}–{hi:g} m from the centre, "
            f"{pr['pattern']} of views (elevation ±{pr['elevation_deg']:g}°), {pr['n_views']} views.")


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
        *([protocol_line(cfg["protocol"]), ""] if isinstance(cfg.get("protocol"), dict) else []),
    ]

    def grid(title: str, text) -> list[str]:
        """A noise × (model, range) table whose cells are ``text(noise, model, range)``."""
        out = ["", title, ""] if title else []
        out += ["| noise | " + " | ".join(f"{m}-{a}" for m, a in cols) + " |",
                "| --- | " + " | ".join("---" for _ in cols) + " |"]
        return out + [f"| {n} | " + " | ".join(text(n, m, a) for m, a in cols) + " |" for n in cfg["noise"]]

    def successes(n, m, a):
        ours = "+".join(str(_cell(summary, a, n, m, p)["successes"]) for p in params)
        paper = PAPER_SUCCESS.get((n, m, a))
        return f"{ours} (paper {'+'.join(str(paper['FSO'.index(p)]) for p in params) if paper else '–'})"

    def iou_all(n, m, a):
        ours = "/".join(f"{_cell(summary, a, n, m, p)['iou_all']['estimate']:.2f}" for p in params)
        paper = PAPER_IOU_H.get((m, a)) if n == "H" else None
        return ours + (" (paper " + "/".join(f"{paper['FSO'.index(p)]:.2f}" for p in params) + ")" if paper else "")

    pooled = {(c["angle"], c["noise"], c["model"]): c for c in summary.get("pooled_success_iou", [])}

    def pooled_iou(n, m, a):
        c = pooled[(a, n, m)]
        est = c["iou"]["estimate"]
        return (f"{est:.2f}" if np.isfinite(est) else "– (none)") + \
            (f" (paper {c['paper']:.2f})" if c["paper"] is not None else "")

    lines += grid("", successes)
    lines += grid(f"## Average IoU {'/'.join(params)} over all trials (paper at H)", iou_all)
    if pooled:
        lines += grid(f"## Average success IoU, {'+'.join(params)} pooled (paper's row, all three pooled)",
                      pooled_iou)
    lines += ["", "## 95 % confidence intervals", ""]
    lines += [f"Collapsed: the estimate's smallest radius is below {COLLAPSED_RATIO:g} of its largest "
              "(a flat disc or a needle)."]
    lines += [""]
    lines += ["| range | noise | model | param | success rate (Wilson) | IoU all (bootstrap) | IoU successful "
              "| iterations to tol | failed (collapsed) |"]
    lines += ["| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for c in summary["cells"]:
        sr, ia, isu, it = c["success_rate"], c["iou_all"], c["iou_success"], c["iterations_to_tol"]
        f = lambda d, k=".2f": (f"{d['estimate']:{k}} [{d['low']:{k}}, {d['high']:{k}}]"  # noqa: E731
                                if np.isfinite(d["estimate"]) else "– (none)")
        lines.append(
            f"| {c['angle']} | {c['noise']} | {c['model']} | {c['param']} | {f(sr)} | {f(ia)} | {f(isu)} | "
            f"{f(it, '.1f')} | {c['trials'] - c['successes']} ({c['failures_collapsed']}) |"
        )
    if summary["paired_iterations_O_vs_S"]:
        lines += ["", "## Iterations to tolerance, SPD (O) vs RTS (S), paired on trials where both succeed", ""]
        lines += ["| model, trials | pairs | mean O | mean S | O/S ratio of means [95 % CI] | Wilcoxon p "
                  "| O faster in |"]
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
        f"(LM loops / {t['problem_iterations']} problem-iterations)."
        + (f" Solves, compilation and evaluation are sums over the {t['tasks']} tasks "
           f"({t['trials_per_task']} problems each) on {t['workers']} {t['engine']} workers."
           if "tasks" in t else ""),
    ]
    return "\n".join(lines) + "\n"
