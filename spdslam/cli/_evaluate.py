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
    out: Path = typer.Argument(..., help="A saved map: the output folder of spdslam run (or its map.json), or "
                               "another system's map (an Osmap .yaml of GOReloc or VOOM, docs/map-reuse.md)."),
    sequence: Path = typer.Argument(..., help="The sequence folder with ground truth."),
    trajectory: Path | None = typer.Option(None, "--trajectory", help="A TUM file of the map's camera poses "
                                           "(T_wc) to align it to the ground truth by (default: the map's own: "
                                           "trajectory.txt, or the keyframes of another system's map)."),
    to: Path | None = typer.Option(None, "--out", help="Where to write metrics.json and report.md (default: the "
                                   "run folder; required for another system's map)."),
) -> None:
    """Evaluate a map against a sequence's ground truth; prints and writes
    metrics.json and report.md (in the run folder, or --out)."""

    import numpy as np

    from ..evaluation import evaluate_run, report_markdown, shown
    from ..io import MapFormatError, SequenceFormatError, dumps_strict, load_map, read_tum, write_file_atomically

    try:
        saved = load_map(out)
    except MapFormatError as e:
        fail(str(e))
    if to is None and not saved.is_spdslam:
        fail(f"{out}: another system's map ({saved.format}): give --out DIR for its metrics.json and report.md")
    seq = load_sequence(sequence)
    m, objects = saved.document, saved.objects
    folder = to if to is not None else saved.path.parent
    poses = saved.trajectory
    if trajectory is not None:
        try:
            poses = read_tum(trajectory, str(trajectory))
        except SequenceFormatError as e:
            fail(str(e))
    if not seq.objects_gt and seq.groundtruth_tum is None:
        fail(f"{sequence}: expected ground truth (objects_gt.txt or groundtruth.txt), got neither")
    if poses is None and saved.is_spdslam:
        poses = np.column_stack([seq.timestamps, seq.poses_tum])
    try:
        metrics = evaluate_run(m, objects, None, poses, seq)
        texts = {"metrics.json": dumps_strict(metrics) + "\n",
                 "report.md": report_markdown(metrics, m)}
    except (TypeError, ValueError, KeyError) as e:
        fail(f"{saved.path}: expected a map written by spdslam run, got {type(e).__name__}: {e}")
    name = "the folder"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for name, text in texts.items():
            write_file_atomically(folder / name, lambda tmp, text=text: tmp.write_text(text, encoding="utf-8"))
    except OSError as e:
        fail(f"{folder}: cannot write {name}: {e.strerror or e}")
    for r in metrics.get("objects", []):
        console.print(f"object {r['id']} ({r['label']}): IoU {shown(r['iou'])}, "
                      f"orientation {shown(r['orientation_deg'], '.2f', '°')}")
    print_metrics(metrics)
    console.print(f"wrote {folder / 'metrics.json'} and {folder / 'report.md'}")
