"""``evaluate``: a run's map and trajectory against the ground truth."""

from __future__ import annotations

from pathlib import Path

import typer

from ._app import app, console, fail
from ._common import (
    load_sequence,
    print_metrics,
)

__all__ = ["evaluate"]


@app.command()
def evaluate(
    out: Path = typer.Argument(..., help="Output folder of spdslam run (or its map.json)."),
    sequence: Path = typer.Argument(..., help="The sequence folder with ground truth."),
) -> None:
    """Evaluate a map against a sequence's ground truth; prints and writes
    OUT/metrics.json and OUT/report.md."""

    import numpy as np

    from ..evaluation import evaluate_run, report_markdown, shown
    from ..io import MapFormatError, SequenceFormatError, dumps_strict, read_map, read_tum, write_file_atomically

    seq = load_sequence(sequence)
    try:
        m, objects = read_map(out)
    except MapFormatError as e:
        fail(str(e))
    folder = out if out.is_dir() else out.parent
    traj = folder / "trajectory.txt"
    poses = None
    if traj.is_file():
        try:
            poses = read_tum(traj, str(traj))
        except SequenceFormatError as e:
            fail(str(e))
    if not seq.objects_gt and seq.groundtruth_tum is None:
        fail(f"{sequence}: expected ground truth (objects_gt.txt or groundtruth.txt), got neither")
    if poses is None:
        poses = np.column_stack([seq.timestamps, seq.poses_tum])
    try:
        metrics = evaluate_run(m, objects, None, poses, seq)
        texts = {"metrics.json": dumps_strict(metrics) + "\n",
                 "report.md": report_markdown(metrics, m)}
    except (TypeError, ValueError, KeyError) as e:
        fail(f"{folder / 'map.json'}: expected a map written by spdslam run, got {type(e).__name__}: {e}")
    try:
        for name, text in texts.items():
            write_file_atomically(folder / name, lambda tmp, text=text: tmp.write_text(text, encoding="utf-8"))
    except OSError as e:
        fail(f"{folder}: cannot write {name}: {e.strerror or e}")
    for r in metrics.get("objects", []):
        console.print(f"object {r['id']} ({r['label']}): IoU {shown(r['iou'])}, "
                      f"orientation {shown(r['orientation_deg'], '.2f', '°')}")
    print_metrics(metrics)
    console.print(f"wrote {folder / 'metrics.json'} and {folder / 'report.md'}")
