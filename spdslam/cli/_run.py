"""``run``, ``localize`` and ``merge``: a map made from a sequence, a sequence put into a
saved map's frame, and recordings merged into one map."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from ._app import app, check_output, collector_paused, console, fail
from ._common import (
    METHOD_HELP,
    ROBUST_HELP,
    SEQUENCE_HELP,
    SIGMA_HELP,
    check_out,
    check_recording,
    default_of,
    format_options,
    help_of,
    load_sequence,
    parse_sigmas,
    print_metrics,
    print_result,
    progress,
    run_and_write,
    run_settings,
    sequence_path,
    write_recording_file,
    write_run_folder,
)

__all__ = ["run", "localize", "merge"]


@app.command()
def run(
    sequence: Path = typer.Argument(..., help=SEQUENCE_HELP),
    method: str = typer.Option("multi-spd", help=METHOD_HELP),
    out: Path = typer.Option(Path("out"), "--out", help="Output folder."),
    option: list[str] | None = typer.Option(None, "--option", help="An option of the sequence format's reader, "
        "NAME=VALUE, repeatable (e.g. min_score=0.3 for an OA-SLAM folder; docs/formats.md)."),
    parameterization: str | None = typer.Option(None, help=help_of("parameterization")),
    box_model: str | None = typer.Option(None, help=help_of("box_model")),
    associate: str | None = typer.Option(None, help=help_of("associate")),
    object_shape: str | None = typer.Option(None, help=help_of("object_shape")),
    truncation_margin: float | None = typer.Option(None, help=help_of("truncation_margin")),
    robust: list[str] | None = typer.Option(None, help=ROBUST_HELP),
    robust_k: float | None = typer.Option(None, help=help_of("robust_k")),
    sigma: list[str] | None = typer.Option(None, help=SIGMA_HELP),
    max_iterations: int = typer.Option(default_of("max_iterations"), help=help_of("max_iterations")),
    keyframes: str = typer.Option(default_of("keyframes"), help=help_of("keyframes")),
    support_planes: str = typer.Option(default_of("support_planes"), help=help_of("support_planes")),
    tolerance: float = typer.Option(default_of("tolerance"), help=help_of("tolerance")),
    min_views: int = typer.Option(default_of("min_views"), help=help_of("min_views")),
    hold_trajectory: bool = typer.Option(default_of("hold_trajectory"), "--hold-trajectory/--free-trajectory",
                                         help=help_of("hold_trajectory")),
    drift_interval: float = typer.Option(default_of("drift_interval"), help=help_of("drift_interval")),
    initial_poses: str = typer.Option(default_of("initial_poses"), help=help_of("initial_poses")),
    screen: bool = typer.Option(default_of("screen"), "--screen/--no-screen", help=help_of("screen")),
    class_table: bool = typer.Option(default_of("class_table"), "--class-table/--no-class-table",
                                     help=help_of("class_table")),
    overlay: bool = typer.Option(True, help="Write overlay/ frames when the sequence has images."),
    overwrite: bool = typer.Option(False, help="Replace a non-empty OUT."),
    rerun: Path | None = typer.Option(None, "--rerun", help="Also write a rerun recording of the run to this .rrd "
        "file (needs rerun-sdk, the viewer extra; open it with: rerun FILE)."),
    online: bool = typer.Option(False, "--online", help="Replay the sequence frame by frame through the online mapper "
        "(a fixed-lag smoother) instead of one batch optimisation; also writes OUT/latency.csv and OUT/latency.png."),
    window: int = typer.Option(default_of("online.window"), help=help_of("online.window", "--online")),
    every: int = typer.Option(default_of("online.every"), help=help_of("online.every", "--online")),
    online_iterations: int = typer.Option(default_of("online.iterations"),
                                          help=help_of("online.iterations", "--online")),
    warmup_first: bool = typer.Option(default_of("online.warmup"), "--warmup",
                                      help=help_of("online.warmup", "--online")),
    final_batch: bool = typer.Option(default_of("online.final_batch"), "--final-batch/--no-final-batch",
                                     help=help_of("online.final_batch", "--online")),
    background: bool = typer.Option(default_of("online.background"), "--background",
                                    help=help_of("online.background", "--online")),
    realtime: bool = typer.Option(default_of("online.realtime"), "--realtime",
                                  help=help_of("online.realtime", "--online")),
) -> None:
    """Map a sequence: initialise every object, optimise poses and objects jointly.

    Writes OUT/map.json, OUT/trajectory.txt, OUT/map_top.png, and with ground truth
    OUT/report.md and OUT/metrics.json, and with images OUT/overlay/; with --rerun FILE
    also a rerun recording (as the view command writes). With --online the frames are
    mapped one at a time (docs/online.md), and OUT/latency.csv and OUT/latency.png say how
    long each took.
    """
    on = {"window": window, "every": every, "iterations": online_iterations,
          "final_batch": final_batch, "warmup": warmup_first, "background": background,
          "realtime": realtime} if online else None
    settings = run_settings(
        method, sigma=parse_sigmas(sigma), robust=robust, robust_k=robust_k,
        parameterization=parameterization, box_model=box_model, associate=associate,
        object_shape=object_shape, truncation_margin=truncation_margin,
        max_iterations=max_iterations, keyframes=keyframes, support_planes=support_planes,
        class_table=class_table, tolerance=tolerance, min_views=min_views,
        hold_trajectory=hold_trajectory, drift_interval=drift_interval, initial_poses=initial_poses,
        screen=screen, online=on)
    options = format_options(option)
    sequence_path(sequence)
    check_output(out, [sequence])
    if rerun is not None:
        check_recording(rerun, "--rerun")
    with collector_paused():  # the sequence lives as long as the process: out of the collector's
        seq = load_sequence(sequence, options)  # full passes, which would pause a frame (docs/online.md)
    result, metrics = run_and_write(seq, settings, out, overwrite, overlay, source=sequence)
    if rerun is not None:
        write_recording_file(rerun, "--rerun", result.objects, result.poses_tum, seq,
                         metrics.get("to_groundtruth"))


@app.command()
def localize(
    sequence: Path = typer.Argument(..., help=SEQUENCE_HELP),
    map_path: Path = typer.Option(..., "--map", help="A saved map: the output folder of spdslam run "
                                  "(or its map.json), or another system's (an Osmap .yaml of GOReloc or VOOM)."),
    out: Path = typer.Option(Path("out"), "--out", help="Output folder."),
    sim3: bool = typer.Option(False, "--sim3", help="Also estimate a scale (the recording's odometry has none of "
        "its own, as from a monocular front end)."),
    match_tolerance: float = typer.Option(0.15, help="Metres within which a matched object's centre must land "
        "in the map."),
    refine: bool = typer.Option(True, help="Refine the transform found from the objects with the recording's "
        "boxes against the map's objects."),
    method: str = typer.Option("multi-spd", help=METHOD_HELP),
    option: list[str] | None = typer.Option(None, "--option", help="An option of the sequence format's reader, "
        "NAME=VALUE, repeatable (docs/formats.md)."),
    overlay: bool = typer.Option(True, help="Write overlay/ frames when the sequence has images."),
    overwrite: bool = typer.Option(False, help="Replace a non-empty OUT."),
) -> None:
    """Put a new recording into a saved map's frame, from the objects alone.

    Maps the recording in its own frame (as spdslam run does), matches its objects to the
    map's by label, size and layout, refines the transform with the recording's boxes against
    the map's objects, and writes the run moved into the map's frame (OUT/map.json,
    OUT/trajectory.txt, ...) with OUT/localization.json: T_map_sequence, scale, covariance,
    matches and the agreement of the boxes with the map's projected objects. Refuses, in one
    line and writing nothing, when fewer than three objects match or two transforms fit
    about equally (docs/map-reuse.md).
    """
    import numpy as np

    from ..experiments import localize_sequence
    from ..io import MapFormatError, dumps_strict, load_map
    from ..mapping import LocalizationError

    if not (math.isfinite(match_tolerance) and match_tolerance > 0):
        fail(f"--match-tolerance: expected a positive number of metres, got {match_tolerance}")
    settings = run_settings(method)
    options = format_options(option)
    sequence_path(sequence)
    check_output(out, [sequence, map_path])
    check_out(out, overwrite)
    try:
        map_objects = load_map(map_path).objects
    except MapFormatError as e:
        fail(str(e))
    except OSError as e:
        fail(f"--map: cannot read {map_path}: {e.strerror or e}")
    seq = load_sequence(sequence, options)
    try:
        moved, loc, doc = localize_sequence(seq, map_objects, settings, sim3=sim3, tolerance=match_tolerance,
                                            refine=refine, progress=progress)
    except LocalizationError as e:
        fail(f"{seq.name}: cannot localise against {map_path}: {e}")
    except ValueError as e:
        fail(f"{seq.name}: {e}")
    up = None if seq.priors is None or seq.priors.up is None else \
        loc.T_map_sequence[:3, :3] @ np.asarray(seq.priors.up, float)
    metrics = write_run_folder(out, seq, moved, overlay=overlay, overwrite=overwrite, source=sequence, up=up,
                         extra={"localization.json": dumps_strict(doc) + "\n"})
    print_result(moved)
    R = loc.T_map_sequence[:3, :3]
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    console.print(f"localised: {len(loc.matches)} objects matched (the best rival transform matches "
                  f"{loc.runner_up}), centre rms {loc.rms:.3f} m, rotation {angle:.1f}°, translation "
                  f"{np.linalg.norm(loc.T_map_sequence[:3, 3]):.3f} m" + (f", scale {loc.scale:.4f}" if sim3 else ""))
    agreement = doc.get("agreement", {})
    if "iou" in agreement:
        console.print(f"the map's objects from the localised poses: median IoU {agreement['iou']:.3f} "
                      f"over {agreement['pairs']} box pairs")
    print_metrics(metrics)
    console.print(f"wrote {out}")


def _recorded_sequence(run: Path, doc: dict, given: Path | None, option: str) -> Path:
    """The sequence of a run: ``given``, else the one its map.json records."""
    if given is not None:
        return given
    path = doc.get("sequence")
    if not isinstance(path, str):
        fail(f"{run}: the map records no sequence: give {option} (the recording it was made from)")
    return Path(path)


def _in_map_frame(seq, saved, option: str):
    """``seq`` as it is for a run of spdslam (its poses are its map's frame); for another
    system's map, moved into the map's frame: its trajectory aligned to the map's keyframes
    over their common times (the recording the map was made from)."""
    if saved.is_spdslam:
        return seq
    import numpy as np

    from ..evaluation import trajectory_alignment
    from ..mapping import moved_sequence

    if saved.trajectory is None:
        fail(f"{option}: {saved.path} has no keyframes: its recording cannot be put into its frame")
    try:
        T = trajectory_alignment(np.c_[seq.timestamps, seq.poses_tum], saved.trajectory)
    except ValueError as e:
        fail(f"{option}: {seq.name} against {saved.path}'s keyframes: {e}")
    return moved_sequence(seq, T)


@app.command()
def merge(
    run_a: Path = typer.Argument(..., help="A run's output folder (spdslam run), or another system's saved map "
                                 "with --sequence-a: the result is in its frame."),
    run_b: Path = typer.Argument(..., help="A second run's output folder (or another system's map with "
                                 "--sequence-b), of the same place."),
    out: Path = typer.Option(Path("out"), "--out", help="Output folder."),
    sequence_a: Path | None = typer.Option(None, help="RUN_A's sequence (default: the one its map.json records; "
                                           "another system's map: the recording it was made from, put into its "
                                           "frame by its keyframes' times)."),
    sequence_b: Path | None = typer.Option(None, help="RUN_B's sequence (default: the one its map.json records; "
                                           "another system's map as for --sequence-a)."),
    sim3: bool = typer.Option(False, "--sim3", help="Also estimate B's scale against A's."),
    match_tolerance: float = typer.Option(0.15, help="Metres within which a matched object's centre must land."),
    refine: bool = typer.Option(True, help="Refine B's transform with B's boxes against A's objects."),
    method: str = typer.Option("multi-spd", help=METHOD_HELP),
    overlay: bool = typer.Option(True, help="Write overlay/ frames when the sequences have images."),
    overwrite: bool = typer.Option(False, help="Replace a non-empty OUT."),
) -> None:
    """One map of two recordings of the same place.

    Localises RUN_B's objects against RUN_A's (as localize does), moves B's sequence into A's
    frame, appends it to A's and maps the two as one sequence: an object seen in both becomes
    one, estimated from both recordings' boxes. Writes the usual run outputs and
    OUT/merge.json: for each object, the object of A and of B it continues, and the counts of
    objects in both, only in A, only in B (docs/map-reuse.md).
    """
    from ..experiments import merge_recordings
    from ..io import MapFormatError, dumps_strict, load_map
    from ..mapping import LocalizationError

    if not (math.isfinite(match_tolerance) and match_tolerance > 0):
        fail(f"--match-tolerance: expected a positive number of metres, got {match_tolerance}")
    settings = run_settings(method)
    maps = []
    for run, option in ((run_a, "RUN_A"), (run_b, "RUN_B")):
        try:
            saved = load_map(run)
        except MapFormatError as e:
            fail(str(e))
        except OSError as e:
            fail(f"{option}: cannot read {run}: {e.strerror or e}")
        maps.append(saved)
    saved_a, saved_b = maps
    doc_a, objects_a, doc_b, objects_b = saved_a.document, saved_a.objects, saved_b.document, saved_b.objects
    path_a = _recorded_sequence(run_a, doc_a, sequence_a, "--sequence-a")
    path_b = _recorded_sequence(run_b, doc_b, sequence_b, "--sequence-b")
    for p in (path_a, path_b):
        sequence_path(p)
    check_output(out, [run_a, run_b, path_a, path_b])
    check_out(out, overwrite)
    seq_a = _in_map_frame(load_sequence(path_a), saved_a, "--sequence-a")
    seq_b = _in_map_frame(load_sequence(path_b), saved_b, "--sequence-b")
    try:
        result, joined, loc, doc = merge_recordings(seq_a, objects_a, seq_b, objects_b, settings, sim3=sim3,
                                                    tolerance=match_tolerance, refine=refine, progress=progress)
    except LocalizationError as e:
        fail(f"cannot merge {run_b} into {run_a}: {e}")
    except ValueError as e:
        fail(f"{seq_a.name}+{seq_b.name}: {e}")
    metrics = write_run_folder(out, joined, result, overlay=overlay, overwrite=overwrite,
                         extra={"merge.json": dumps_strict(doc) + "\n"})
    print_result(result)
    console.print(f"merged: {len(result.objects)} objects: {doc['in_both']} in both recordings, {doc['only_a']} "
                  f"only in A, {doc['only_b']} only in B, {doc['new']} in neither map before "
                  f"(B localised from {len(loc.matches)} objects, centre rms {loc.rms:.3f} m)")
    print_metrics(metrics)
    console.print(f"wrote {out}")
