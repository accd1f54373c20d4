"""The files of a study: trials.csv, table.md, convergence.png and summary.json."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..evaluation import dumps_strict
from ..io import write_file_atomically
from ._study import StudyResult, history_labels
from ._summary import CSV_COLUMNS, summarize, table_markdown

__all__ = ["plot_convergence", "write_outputs"]


def plot_convergence(result: StudyResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = result.config
    angle_lab, noise_lab = history_labels(cfg)
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
    title = "Cost vs iteration: median and interquartile band (F Full, S RTS, O SPD; - inv, -- semi)"
    rows, cols = len(cfg.angles), len(cfg.noise)
    if cols < 3:  # a narrow figure: the title on three lines
        title = title.replace(": ", ":\n").replace(" (", "\n(")
    fig.suptitle(title, fontsize=10 if cols < 3 else 12)
    # fixed margins: tight_layout draws the log axes once more only to measure them (1.2 s)
    fig.subplots_adjust(left=0.21 / cols, right=0.99, bottom=0.12 / rows,
                        top=1 - (0.2 if cols >= 3 else 0.33) / rows, wspace=0.22, hspace=0.28)
    fig.savefig(path, dpi=110, format="png")
    plt.close(fig)


def write_outputs(result: StudyResult, out: Path) -> dict:
    """trials.csv, table.md, convergence.png and summary.json under ``out``; each file is
    written to a temporary name first, so nothing is left half-written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(result)

    def atomic(name: str, write):
        write_file_atomically(out / name, write)

    def csv(path):
        with open(path, "w") as f:
            f.write(",".join(CSV_COLUMNS) + "\n")
            C, n = result.columns, len(result)
            for lo in range(0, n, _CSV_BLOCK):  # formatted a block of rows at a time
                cols = [_format_column(C[c][lo:lo + _CSV_BLOCK], C["success"][lo:lo + _CSV_BLOCK], c)
                        for c in CSV_COLUMNS]
                f.writelines(",".join(fields) + "\n" for fields in zip(*cols))

    atomic("trials.csv", csv)
    atomic("table.md", lambda p: p.write_text(table_markdown(summary)))
    atomic("convergence.png", lambda p: plot_convergence(result, p))
    atomic("summary.json", lambda p: p.write_text(dumps_strict(summary)))
    return summary


_CSV_BLOCK = 65536


def _format_column(values: np.ndarray, success: np.ndarray, name: str) -> list[str]:
    """One column of trials.csv as text (``_fmt`` of each value; a failed trial's
    ``iterations_to_tol`` is empty)."""
    if name == "success":
        return ["1" if v else "0" for v in values]
    if name == "iterations_to_tol":
        return [str(int(v)) if ok else "" for v, ok in zip(values, success)]
    if values.dtype.kind == "f":
        return [_fmt(float(v)) for v in values]
    if values.dtype.kind in "iu":
        return [str(int(v)) for v in values]
    return [str(v) for v in values]


def _fmt(v) -> str:
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return "" if not np.isfinite(v) else f"{v:.10g}"  # an empty field: not computed
    return str(v)
