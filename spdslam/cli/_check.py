"""The ``check`` command: the consistency of a sequence's inputs before mapping
(``spdslam.evaluation.check_sequence``)."""

from __future__ import annotations

import math
import os
from pathlib import Path

import typer

from ._app import app, check_output, console, err_console, fail

__all__ = ["check"]


def _cell(v, spec=".3f"):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, (list, tuple)):
        return " / ".join(format(x, spec) for x in v)
    return format(v, spec)


def _print_report(report: dict) -> None:
    head = (f"{'id':>4}  {'label':<14} {'pairs':>6} {'IoU':>6} {'cuboid':>6} "
            f"{'offset u/v px':>13} {'size w/h':>11} {'detected':>8}")
    for s in report["sources"]:
        console.print(f"{report['sequence']}: detections against the {report['objects']}, "
                      f"{s['reference']} (box IoU; IoU of the circumscribed cuboid's silhouette; "
                      "centre offset and size ratio, detected / projected; frames seen whole "
                      "with a detection)", highlight=False)
        console.print(head, highlight=False)
        for r in s["objects"] + [{"id": "all", "label": "", **s["overall"], "detection_rate": None}]:
            rate = r.get("detection_rate")
            console.print(
                f"{str(r['id']):>4}  {r['label'][:14]:<14} {r['pairs']:>6} {_cell(r['iou']):>6} "
                f"{_cell(r.get('cuboid_iou')):>6} {_cell(r['center_offset_px'], '+.1f'):>13} "
                f"{_cell(r['size_ratio'], '.2f'):>11} "
                f"{'–' if rate is None else f'{100 * rate:.0f}%':>8}", highlight=False)
        console.print("")
    console.print("Findings:")
    for line in report["findings"]:
        console.print(f"- {line}", highlight=False, soft_wrap=True)


@app.command()
def check(
    sequence: Path = typer.Argument(..., help="A sequence folder (any layout spdslam run reads)."),
    map_: Path | None = typer.Option(
        None, "--map", help="Check against the objects of this run (its folder or map.json; the run's "
                            "trajectory.txt when present) instead of the ground-truth objects."),
    json_path: Path | None = typer.Option(None, "--json", help="Also write the report as JSON to this file."),
    min_iou: float = typer.Option(
        0.3, help="A detection pairs with a projected object of its label above this box IoU."),
) -> None:
    """Check that the detection boxes agree with objects projected with the poses and the
    camera: per object and overall IoU, centre offset and size ratio, the time offset
    between detections and poses, the box convention, the lens distortion. Against the
    ground-truth objects when the sequence has them; else against a map (--map, or the
    map spdslam run makes with its defaults, made first)."""
    from ..evaluation import check_sequence
    from ..io import (
        MapFormatError,
        SequenceFormatError,
        check_sequence_path,
        dumps_strict,
        load_map,
        read_measured_boxes,
        read_sequence,
    )

    if not (math.isfinite(min_iou) and 0 < min_iou < 1):
        fail(f"--min-iou: expected a number in (0, 1), got {min_iou}")
    if json_path is not None:
        if json_path.exists() and json_path.is_dir():
            fail(f"--json: {json_path} is a folder: expected a file path")
        try:
            check_sequence_path(sequence)
        except SequenceFormatError as e:
            fail(str(e))
        check_output(json_path, (sequence,) + ((map_,) if map_ is not None else ()), "--json")
    try:
        seq = read_sequence(sequence)
        measured = read_measured_boxes(sequence)
    except SequenceFormatError as e:
        fail(str(e))
    raw, dist = measured if measured is not None else (None, None)
    objects = poses = None
    if map_ is not None:
        try:
            saved = load_map(map_)
        except MapFormatError as e:
            fail(str(e))
        if not saved.is_spdslam:  # its frame is not the sequence's: the boxes would not fall on it
            fail(f"--map: {map_} is another system's map ({saved.format}): check projects a map made from "
                 "this sequence (spdslam run); spdslam localize --map puts the sequence into its frame")
        objects, poses = saved.objects, saved.trajectory
        if not objects:
            fail(f"--map: {map_} has no mapped objects to project")
    elif not seq.objects_gt:
        from ..mapping import run_sequence

        err_console.print("[dim]no ground-truth objects: mapping with spdslam run's defaults "
                          "first (multi-spd), to check against the map[/dim]")
        result = run_sequence(seq, "multi-spd")
        objects, poses = result.objects, result.poses_tum
        if not objects:
            fail(f"{sequence}: no ground-truth objects and the mapping maps none: nothing to project")
    if not seq.detections:
        fail(f"{sequence}: expected detections to check, got none")
    report = check_sequence(seq, objects, poses, raw=raw, distortion=dist, min_iou=min_iou)
    _print_report(report)
    if json_path is not None:
        tmp = json_path.with_name(f".{json_path.name}.tmp")
        try:
            tmp.write_text(dumps_strict(report) + "\n", encoding="utf-8")
            os.replace(tmp, json_path)
        except OSError as e:
            fail(f"--json: cannot write {json_path}: {e.strerror or e}")
        console.print(f"wrote {json_path}")
