"""The sequence commands: ``run``, ``localize``, ``merge``, ``evaluate``, ``import``,
``compare``, ``batch``, ``demo``, ``view`` and ``warmup``.

Their choices and help come from the factor registry (robust-kernel groups), the mapping
(methods, models, the sigma table, the settings' defaults and help) and the format registry,
through their copy in ``_help.FACTS``, so that the help imports none of them (nor JAX); a new
factor type, method or format fails tests/test_cli.py until the copy is renewed.
"""

from __future__ import annotations

import math
from pathlib import Path

import typer

from ._app import (
    RAY_ADDRESS_HELP,
    RAY_HELP,
    RETRIES_HELP,
    WORKERS_HELP,
    app,
    check_output,
    console,
    err_console,
    fail,
    open_engine,
)
from ._help import FACTS, formats_help, setting
from ._simulate import split_option

__all__ = ["run", "localize", "merge", "evaluate", "import_", "compare", "batch", "demo", "view", "warmup",
           "DEMO_MARKER"]

_SIGMA_HELP = (
    "Override a sigma, NAME=VALUE, repeatable (e.g. inverse_box=3); NAME one of "
    f"{', '.join(FACTS['sigmas'])} (units in docs/sequences.md)."
)
_ROBUST_HELP = (
    f"Robust kernel, repeatable: KERNEL ({', '.join(FACTS['robust_choices'])}) on box and "
    f"measured-ellipsoid factors (default auto: {FACTS['auto_box_kernel'][0]} with threshold "
    f"{FACTS['auto_box_kernel'][1]:g} when the detections are associated automatically, none with "
    "instance ids), or TYPE=KERNEL[:K] for one factor type "
    f"({', '.join(FACTS['robust_groups'])}; KERNEL one of {', '.join(FACTS['robust_kernels'])})."
)
_METHOD_HELP = f"The back end: {', '.join(FACTS['methods'])}."


def _default(name: str):
    """The default of a settings field (``RunSettings``, or ``online.NAME``: ``OnlineSettings``),
    as a command-line default (``_help.FACTS``: read without importing ``mapping``)."""
    return setting(name)[0]


def _help(name: str, prefix: str = "") -> str:
    """An option's help from the run's settings (``mapping.SETTINGS.help``, or the method
    overrides' ``SETTINGS.overrides``, as ``_help.FACTS`` copies them), as a sentence."""
    text = setting(name)[1]
    return f"{prefix}: {text}." if prefix else f"{text[0].upper()}{text[1:]}."


#: The help of a SEQUENCE argument and of ``import``'s SOURCE: the registered formats, listed
#: once when the CLI is imported.
_SEQUENCE_HELP = f"The sequence, in a registered format (docs/formats.md): {formats_help()}."
_INPUT_HELP = f"The input, in a registered format (docs/formats.md): {formats_help()}."


def _format_options(items) -> dict:
    """``--option NAME=VALUE`` items as keyword options of a format's reader (VALUE read as
    a YAML scalar: 3, 0.5, true, odometry)."""
    import yaml

    out = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or not name.isidentifier():
            fail(f"--option: expected NAME=VALUE, got {item!r}")
        try:
            v = yaml.safe_load(value) if value.strip() else ""
        except yaml.YAMLError:
            v = value
        if isinstance(v, (list, dict)):
            v = value
        out[name] = v
    return out


def _sequence_path(path: Path) -> None:
    """Refuse, before anything is read or written, a sequence path that is not there or
    cannot be resolved (a symbolic-link loop): one line, exit 2."""
    from ..io import SequenceFormatError, check_sequence_path

    try:
        check_sequence_path(path)
    except SequenceFormatError as e:
        fail(str(e))


def _load_sequence(path: Path, options: dict | None = None):
    """The sequence at ``path`` in its registered format (``io.read_sequence``), with the
    format's keyword ``options``; errors as one line."""
    from ..io import SequenceFormatError, read_sequence

    try:
        seq = read_sequence(path, **(options or {}))
    except SequenceFormatError as e:
        fail(str(e))
    except ValueError as e:  # an option the format does not take, or a bad value
        fail(f"--option: {e}")
    return seq


def _parse_sigmas(items) -> dict:
    """``--sigma NAME=VALUE`` items as {NAME: number} (the values are checked by
    ``RunSettings``)."""
    from ..mapping import SETTINGS

    out = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep:
            fail(f"--sigma: expected NAME=VALUE with NAME one of {', '.join(sorted(SETTINGS.sigmas))}, got "
                f"{item!r}")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            fail(f"--sigma: {value!r} is not a number (in {item!r})")
    return out


#: The command-line option of a settings field whose option is not ``--<field>``.
_OPTION_OF = {"online.iterations": "--online-iterations", "online.warmup": "--warmup",
              "online": "--online"}


def _settings(method: str, **options):
    """``RunSettings.of(method, **options)``: the run's settings, checked before anything is
    read; a bad one ends the command in one line naming its option."""
    from ..mapping import RunSettings, SettingsError

    try:
        return RunSettings.of(method, **options)
    except SettingsError as e:
        option = _OPTION_OF.get(e.field, "--" + e.field.split(".")[-1].replace("_", "-"))
        fail(f"{option}: {e.reason}")


def _print_metrics(metrics: dict) -> None:
    from ..evaluation import ate_line, shown

    s = metrics.get("summary")
    if s:
        console.print(
            f"mean IoU {shown(s['mean_iou'])}, orientation error {shown(s['mean_orientation_deg'], '.2f', '°')}, "
            f"centre error {shown(s['mean_center_error'], '.3f', ' m')} ({s['matched']}/{s['ground_truth_objects']} "
                f"objects)"
        )
    if "ate" in metrics:
        console.print(ate_line(metrics["ate"]))


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        fail(f"--out: {out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not overwrite:
        fail(f"--out: {out} exists and is not empty (use --overwrite)")


def _progress(message: str) -> None:
    """The run's stages and LM iterations, on stderr (stdout keeps the results)."""
    err_console.print(f"[dim]{message}[/dim]", highlight=False)


def _print_latency(records, rate) -> None:
    import numpy as np

    ms = 1e3 * np.array([r.seconds for r in records])
    console.print(f"online: {len(records)} frames, time per frame median {np.median(ms):.3g} ms, "
                  f"99th percentile {np.percentile(ms, 99):.3g} ms, max {ms.max():.3g} ms"
                  + (f" (frame period {1e3 / rate:.3g} ms)" if rate else ""))


def _write_run(out, seq, result, **options) -> dict:
    """``experiments.write_run``, its errors as one line."""
    from ..experiments import write_run

    try:
        return write_run(out, seq, result, **options)
    except FileExistsError as e:
        fail(f"--out: {e}")
    except OSError as e:  # the folder became unwritable, the disk is full, …
        fail(f"--out: cannot write {out}: {e.strerror or e}")


def _run_and_write(seq, settings, out, overwrite, overlay, source=None):
    """Map ``seq`` with ``settings`` (``experiments.map_sequence``) and write the run's folder
    ``out`` (``experiments.write_outputs``); errors as one line."""
    from ..experiments import frame_rate, map_sequence

    _check_out(out, overwrite)
    try:
        result, records = map_sequence(seq, settings, progress=_progress)
    except ValueError as e:
        fail(f"{seq.name}: {e}")
    if records is not None:
        _print_latency(records, frame_rate(seq))
    metrics = _write_run(out, seq, result, records=records, overlay=overlay, overwrite=overwrite, source=source)
    _print_result(result)
    _print_metrics(metrics)
    console.print(f"wrote {out}")
    return result, metrics


def _print_result(result) -> None:
    console.print(
        f"{result.method.name}: {len(result.objects)} objects, {result.iterations} iterations "
        f"({result.reason}), cost {result.initial_cost:.6g} -> {result.final_cost:.6g}"
    )
    for k, why in result.failed.items():
        err_console.print(f"object {k} not mapped: {why}")
    a = result.association
    if a.get("mode") == "auto":
        scores = (f": precision {a['precision']:.3f}, recall {a['recall']:.3f} against the instance ids"
                  if "precision" in a else "")
        console.print(f"automatic data association, {len(result.objects) + len(result.failed)} tracks{scores}")


def _check_recording(path: Path, option: str) -> None:
    """Refuse, before anything is computed, a recording path that is a folder, and a
    missing rerun-sdk (the viewer extra)."""
    from ..experiments import RERUN_MISSING

    if path.is_dir():
        fail(f"{option}: {path} is a folder: expected the path of a .rrd file")
    try:
        import rerun  # noqa: F401
    except ImportError:
        fail(RERUN_MISSING)


def _write_recording(path: Path, option: str, objects, trajectory, seq, to_groundtruth=None,
                     images: bool = True) -> None:
    """``experiments.write_recording`` (atomic), its errors as one line."""
    from ..experiments import write_recording

    try:
        write_recording(path, objects, trajectory, seq, to_groundtruth=to_groundtruth,
                        images=images)
    except ImportError as e:
        fail(str(e))
    except ValueError as e:
        fail(f"cannot record {path}: {e}")
    except OSError as e:
        fail(f"{option}: cannot write {path}: {e.strerror or e}")
    console.print(f"wrote {path} (open it with: rerun {path})")


@app.command()
def run(
    sequence: Path = typer.Argument(..., help=_SEQUENCE_HELP),
    method: str = typer.Option("multi-spd", help=_METHOD_HELP),
    out: Path = typer.Option(Path("out"), "--out", help="Output folder."),
    option: list[str] | None = typer.Option(None, "--option", help="An option of the sequence format's reader, "
        "NAME=VALUE, repeatable (e.g. min_score=0.3 for an OA-SLAM folder; docs/formats.md)."),
    parameterization: str | None = typer.Option(None, help=_help("parameterization")),
    box_model: str | None = typer.Option(None, help=_help("box_model")),
    associate: str | None = typer.Option(None, help=_help("associate")),
    object_shape: str | None = typer.Option(None, help=_help("object_shape")),
    truncation_margin: float | None = typer.Option(None, help=_help("truncation_margin")),
    robust: list[str] | None = typer.Option(None, help=_ROBUST_HELP),
    robust_k: float | None = typer.Option(None, help=_help("robust_k")),
    sigma: list[str] | None = typer.Option(None, help=_SIGMA_HELP),
    max_iterations: int = typer.Option(_default("max_iterations"), help=_help("max_iterations")),
    keyframes: str = typer.Option(_default("keyframes"), help=_help("keyframes")),
    support_planes: str = typer.Option(_default("support_planes"), help=_help("support_planes")),
    tolerance: float = typer.Option(_default("tolerance"), help=_help("tolerance")),
    min_views: int = typer.Option(_default("min_views"), help=_help("min_views")),
    hold_trajectory: bool = typer.Option(_default("hold_trajectory"), "--hold-trajectory/--free-trajectory",
                                         help=_help("hold_trajectory")),
    drift_interval: float = typer.Option(_default("drift_interval"), help=_help("drift_interval")),
    initial_poses: str = typer.Option(_default("initial_poses"), help=_help("initial_poses")),
    screen: bool = typer.Option(_default("screen"), "--screen/--no-screen", help=_help("screen")),
    class_table: bool = typer.Option(_default("class_table"), "--class-table/--no-class-table",
                                     help=_help("class_table")),
    overlay: bool = typer.Option(True, help="Write overlay/ frames when the sequence has images."),
    overwrite: bool = typer.Option(False, help="Replace a non-empty OUT."),
    rerun: Path | None = typer.Option(None, "--rerun", help="Also write a rerun recording of the run to this .rrd "
        "file (needs rerun-sdk, the viewer extra; open it with: rerun FILE)."),
    online: bool = typer.Option(False, "--online", help="Replay the sequence frame by frame through the online mapper "
        "(a fixed-lag smoother) instead of one batch optimisation; also writes OUT/latency.csv and OUT/latency.png."),
    window: int = typer.Option(_default("online.window"), help=_help("online.window", "--online")),
    every: int = typer.Option(_default("online.every"), help=_help("online.every", "--online")),
    online_iterations: int = typer.Option(_default("online.iterations"), help=_help("online.iterations", "--online")),
    warmup_first: bool = typer.Option(_default("online.warmup"), "--warmup", help=_help("online.warmup", "--online")),
    final_batch: bool = typer.Option(_default("online.final_batch"), "--final-batch/--no-final-batch",
                                     help=_help("online.final_batch", "--online")),
    background: bool = typer.Option(_default("online.background"), "--background",
                                    help=_help("online.background", "--online")),
    realtime: bool = typer.Option(_default("online.realtime"), "--realtime", help=_help("online.realtime", "--online")),
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
    settings = _settings(
        method, sigma=_parse_sigmas(sigma), robust=robust, robust_k=robust_k,
        parameterization=parameterization, box_model=box_model, associate=associate,
        object_shape=object_shape, truncation_margin=truncation_margin,
        max_iterations=max_iterations, keyframes=keyframes, support_planes=support_planes,
        class_table=class_table, tolerance=tolerance, min_views=min_views,
        hold_trajectory=hold_trajectory, drift_interval=drift_interval, initial_poses=initial_poses,
        screen=screen, online=on)
    options = _format_options(option)
    _sequence_path(sequence)
    check_output(out, [sequence])
    if rerun is not None:
        _check_recording(rerun, "--rerun")
    seq = _load_sequence(sequence, options)
    result, metrics = _run_and_write(seq, settings, out, overwrite, overlay, source=sequence)
    if rerun is not None:
        _write_recording(rerun, "--rerun", result.objects, result.poses_tum, seq,
                         metrics.get("to_groundtruth"))


@app.command()
def localize(
    sequence: Path = typer.Argument(..., help=_SEQUENCE_HELP),
    map_path: Path = typer.Option(..., "--map", help="A saved map: the output folder of spdslam run "
                                  "(or its map.json)."),
    out: Path = typer.Option(Path("out"), "--out", help="Output folder."),
    sim3: bool = typer.Option(False, "--sim3", help="Also estimate a scale (the recording's odometry has none of "
        "its own, as from a monocular front end)."),
    match_tolerance: float = typer.Option(0.15, help="Metres within which a matched object's centre must land "
        "in the map."),
    refine: bool = typer.Option(True, help="Refine the transform found from the objects with the recording's "
        "boxes against the map's objects."),
    method: str = typer.Option("multi-spd", help=_METHOD_HELP),
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
    from ..io import MapFormatError, dumps_strict, read_map
    from ..mapping import LocalizationError

    if not (math.isfinite(match_tolerance) and match_tolerance > 0):
        fail(f"--match-tolerance: expected a positive number of metres, got {match_tolerance}")
    settings = _settings(method)
    options = _format_options(option)
    _sequence_path(sequence)
    check_output(out, [sequence, map_path])
    _check_out(out, overwrite)
    try:
        _, map_objects = read_map(map_path)
    except MapFormatError as e:
        fail(str(e))
    except OSError as e:
        fail(f"--map: cannot read {map_path}: {e.strerror or e}")
    seq = _load_sequence(sequence, options)
    try:
        moved, loc, doc = localize_sequence(seq, map_objects, settings, sim3=sim3, tolerance=match_tolerance,
                                            refine=refine, progress=_progress)
    except LocalizationError as e:
        fail(f"{seq.name}: cannot localise against {map_path}: {e}")
    except ValueError as e:
        fail(f"{seq.name}: {e}")
    up = None if seq.priors is None or seq.priors.up is None else \
        loc.T_map_sequence[:3, :3] @ np.asarray(seq.priors.up, float)
    metrics = _write_run(out, seq, moved, overlay=overlay, overwrite=overwrite, source=sequence, up=up,
                         extra={"localization.json": dumps_strict(doc) + "\n"})
    _print_result(moved)
    R = loc.T_map_sequence[:3, :3]
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    console.print(f"localised: {len(loc.matches)} objects matched (the best rival transform matches "
                  f"{loc.runner_up}), centre rms {loc.rms:.3f} m, rotation {angle:.1f}°, translation "
                  f"{np.linalg.norm(loc.T_map_sequence[:3, 3]):.3f} m" + (f", scale {loc.scale:.4f}" if sim3 else ""))
    agreement = doc.get("agreement", {})
    if "iou" in agreement:
        console.print(f"the map's objects from the localised poses: median IoU {agreement['iou']:.3f} "
                      f"over {agreement['pairs']} box pairs")
    _print_metrics(metrics)
    console.print(f"wrote {out}")


def _recorded_sequence(run: Path, doc: dict, given: Path | None, option: str) -> Path:
    """The sequence of a run: ``given``, else the one its map.json records."""
    if given is not None:
        return given
    path = doc.get("sequence")
    if not isinstance(path, str):
        fail(f"{run}: its map.json records no sequence: give {option}")
    return Path(path)


@app.command()
def merge(
    run_a: Path = typer.Argument(..., help="A run's output folder (spdslam run): the result is in its frame."),
    run_b: Path = typer.Argument(..., help="A second run's output folder, of the same place."),
    out: Path = typer.Option(Path("out"), "--out", help="Output folder."),
    sequence_a: Path | None = typer.Option(None, help="RUN_A's sequence (default: the one its map.json records)."),
    sequence_b: Path | None = typer.Option(None, help="RUN_B's sequence (default: the one its map.json records)."),
    sim3: bool = typer.Option(False, "--sim3", help="Also estimate B's scale against A's."),
    match_tolerance: float = typer.Option(0.15, help="Metres within which a matched object's centre must land."),
    refine: bool = typer.Option(True, help="Refine B's transform with B's boxes against A's objects."),
    method: str = typer.Option("multi-spd", help=_METHOD_HELP),
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
    from ..io import MapFormatError, dumps_strict, read_map
    from ..mapping import LocalizationError

    if not (math.isfinite(match_tolerance) and match_tolerance > 0):
        fail(f"--match-tolerance: expected a positive number of metres, got {match_tolerance}")
    settings = _settings(method)
    maps = []
    for run, option in ((run_a, "RUN_A"), (run_b, "RUN_B")):
        try:
            maps.append(read_map(run))
        except MapFormatError as e:
            fail(str(e))
        except OSError as e:
            fail(f"{option}: cannot read {run}: {e.strerror or e}")
    (doc_a, objects_a), (doc_b, objects_b) = maps
    path_a = _recorded_sequence(run_a, doc_a, sequence_a, "--sequence-a")
    path_b = _recorded_sequence(run_b, doc_b, sequence_b, "--sequence-b")
    for p in (path_a, path_b):
        _sequence_path(p)
    check_output(out, [run_a, run_b, path_a, path_b])
    _check_out(out, overwrite)
    seq_a, seq_b = _load_sequence(path_a), _load_sequence(path_b)
    try:
        result, joined, loc, doc = merge_recordings(seq_a, objects_a, seq_b, objects_b, settings, sim3=sim3,
                                                    tolerance=match_tolerance, refine=refine, progress=_progress)
    except LocalizationError as e:
        fail(f"cannot merge {run_b} into {run_a}: {e}")
    except ValueError as e:
        fail(f"{seq_a.name}+{seq_b.name}: {e}")
    metrics = _write_run(out, joined, result, overlay=overlay, overwrite=overwrite,
                         extra={"merge.json": dumps_strict(doc) + "\n"})
    _print_result(result)
    console.print(f"merged: {len(result.objects)} objects: {doc['in_both']} in both recordings, {doc['only_a']} "
                  f"only in A, {doc['only_b']} only in B, {doc['new']} in neither map before "
                  f"(B localised from {len(loc.matches)} objects, centre rms {loc.rms:.3f} m)")
    _print_metrics(metrics)
    console.print(f"wrote {out}")


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

    seq = _load_sequence(sequence)
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
    _print_metrics(metrics)
    console.print(f"wrote {folder / 'metrics.json'} and {folder / 'report.md'}")


#: ``spdslam import``'s reader options: option name → (keyword of the readers, default).
_IMPORT_OPTIONS = {
    "--trajectory": ("trajectory", "odometry"),
    "--min-score": ("min_score", 0.5),
    "--undistort": ("undistort", True),
    "--camera-info-topic": ("camera_info_topic", None),
    "--detections-topic": ("detections_topic", None),
    "--pose-topic": ("pose_topic", None),
    "--world-frame": ("world_frame", None),
    "--camera-frame": ("camera_frame", None),
}


@app.command("import")
def import_(
    source: Path = typer.Argument(..., help=_INPUT_HELP),
    dest: Path = typer.Argument(..., help="Destination folder (canonical format)."),
    overwrite: bool = typer.Option(False, help="Replace a non-empty DEST."),
    trajectory: str = typer.Option("odometry", help="OA-SLAM layout: the poses to map with, odometry (the visual "
        "SLAM's, as the paper) or groundtruth (a ROS 2 bag's poses come from --pose-topic)."),
    min_score: float = typer.Option(0.5, help="OA-SLAM layout and ROS 2 bags: leave out detections scored below this."),
    undistort: bool = typer.Option(True, help="OA-SLAM layout and ROS 2 bags: replace each box by the pinhole box of "
        "its undistorted outline (--no-undistort keeps the measured boxes)."),
    camera_info_topic: str | None = typer.Option(None, help="ROS 2 bags: the sensor_msgs/msg/CameraInfo topic "
        "(default: the bag's only one)."),
    detections_topic: str | None = typer.Option(None, help="ROS 2 bags: the vision_msgs/msg/Detection2DArray topic "
        "(default: the bag's only one)."),
    pose_topic: str | None = typer.Option(None, help="ROS 2 bags: the camera poses, a geometry_msgs/msg/PoseStamped, "
        "nav_msgs/msg/Odometry or tf2_msgs/msg/TFMessage (/tf) topic (default: the bag's only one)."),
    world_frame: str | None = typer.Option(None, help="ROS 2 bags: the world frame of the poses (tf: default the root "
        "of the camera's tf tree; PoseStamped, Odometry: checked against header.frame_id)."),
    camera_frame: str | None = typer.Option(None, help="ROS 2 bags: the camera's optical frame (tf: default "
        "CameraInfo's header.frame_id; Odometry: checked against child_frame_id)."),
    option: list[str] | None = typer.Option(None, "--option", help="Any other option of the format's reader, "
        "NAME=VALUE, repeatable (a format a package adds; docs/extending.md)."),
) -> None:
    """Convert a sequence in any registered format (an fr3_cabinet- or OA-SLAM-style
    folder, a ROS 2 bag: CameraInfo, vision_msgs Detection2DArray, and PoseStamped,
    Odometry or tf camera poses, needing the rosbags package, the 'ros' extra; or a format
    a package adds) to the canonical sequence format. An option the SOURCE's format does
    not take is refused, naming the formats that take it."""
    import dataclasses

    from ..io import FORMATS, SequenceFormatError, find_format

    given = {"--trajectory": trajectory, "--min-score": min_score, "--undistort": undistort,
             "--camera-info-topic": camera_info_topic, "--detections-topic": detections_topic,
             "--pose-topic": pose_topic, "--world-frame": world_frame, "--camera-frame": camera_frame}
    if trajectory not in ("odometry", "groundtruth"):
        fail(f"--trajectory: expected odometry or groundtruth, got {trajectory!r}")
    if not math.isfinite(min_score):
        fail(f"--min-score: expected a finite number, got {min_score!r}")
    options = {kw: given[opt] for opt, (kw, default) in _IMPORT_OPTIONS.items()
               if given[opt] != default}
    options.update(_format_options(option))
    _sequence_path(source)

    def refuse(kw, got):
        flag = next((o for o, (k, _) in _IMPORT_OPTIONS.items() if k == kw), f"--option {kw}")
        takers = [f.describe() for f in FORMATS.values() if kw in f.options]
        fail(f"{flag}: expected {' or '.join(takers) or 'a format that takes it'}, got {source}, {got}")

    try:
        fmt = find_format(source)
    except SequenceFormatError as e:
        if options:  # say first what the option needs
            refuse(next(iter(options)), "which no format claims")
        fail(str(e))
    for kw in options:
        if kw not in fmt.options:
            hint = fmt.hints.get(kw)
            refuse(kw, fmt.title + (f" ({hint})" if hint else ""))
    check_output(dest, [source], "DEST")
    try:
        seq = fmt.read(source, **options)
        seq = dataclasses.replace(seq, name=dest.name)
        FORMATS["canonical"].write(seq, dest, overwrite=overwrite)
    except SequenceFormatError as e:
        fail(str(e))
    except FileExistsError as e:
        fail(f"{dest}: {e}")
    except OSError as e:
        fail(f"DEST: cannot write {dest}: {e.strerror or e}")
    except ValueError as e:  # a ROS 2 bag's options that do not fit its topics
        fail(f"{source}: {e}")
    console.print(f"imported {len(seq)} poses, {len(seq.detections)} detections into {dest}")


def _say_job(report, done: int, total: int) -> None:
    """One line per finished job: stdout when done, stderr when failed."""
    from ..evaluation import shown

    j = report.job
    if report.status == "done":
        s = report.metrics.get("summary") or {}
        iou = f", mean IoU {shown(s['mean_iou'])}" if s else ""
        console.print(f"[{done}/{total}] {j.name}: {report.objects} objects{iou} "
                      f"({report.seconds:.1f} s{', ' + report.where if report.where != 'local' else ''})",
                      highlight=False, markup=False)
    else:
        tries = f", {report.attempts} attempts" if report.attempts > 1 else ""
        # plain, so that the error stays on one line whatever the terminal's width
        typer.echo(f"[{done}/{total}] {j.name} failed ({report.stage}{tries}): {report.error}", err=True)


def _run_jobs(jobs, out, ray, ray_address, workers, retries, overwrite):
    """The jobs run (``experiments.run_batch``) with a line per job, batch.csv and
    batch.json written: the reports."""
    from ..experiments import run_batch, write_batch_report

    for job in jobs:
        _check_out(out / job.name, overwrite)
    engine = open_engine(ray, ray_address, workers, retries)
    console.print(f"{len(jobs)} jobs on {engine.name}"
                  + (f" ({engine.workers} CPUs)" if engine.name == "ray" else ""))
    try:
        reports = run_batch(jobs, out, engine, overwrite=overwrite, progress=_say_job)
    finally:
        engine.close()
    try:
        write_batch_report(out, reports, {"name": engine.name, "workers": engine.workers,
                                          "retries": retries})
    except OSError as e:
        fail(f"--out: cannot write {out}: {e.strerror or e}")
    return reports


@app.command()
def compare(
    sequence: Path = typer.Argument(..., help="Sequence folder with object ground truth."),
    out: Path = typer.Option(Path("compare"), "--out", help="Output folder (one sub-folder per method)."),
    methods: str = typer.Option("quadric-slam,multi-rts,multi-spd", help="Methods to run."),
    overwrite: bool = typer.Option(False, help="Replace non-empty outputs."),
    ray: bool = typer.Option(False, "--ray", help=RAY_HELP),
    ray_address: str | None = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP),
    workers: int | None = typer.Option(None, min=1, help=WORKERS_HELP),
    retries: int = typer.Option(1, min=0, help=RETRIES_HELP),
) -> None:
    """Run several methods on one sequence and write a Table-III-like OUT/table.md (and
    OUT/batch.csv, a line per method run)."""
    from ..evaluation import FRONT_END_NAMES, table_iii
    from ..experiments import Job
    from ..mapping import METHODS

    names = split_option("methods", methods, tuple(METHODS))
    _sequence_path(sequence)
    check_output(out, [sequence])
    seq = _load_sequence(sequence)
    if not seq.objects_gt:
        fail(f"{sequence}: expected object ground truth (objects_gt.txt) to compare methods, got none")
    _check_out(out, overwrite)
    jobs = [Job(name, sequence, name, _settings(name), overlay=False) for name in names]
    reports = _run_jobs(jobs, out, ray, ray_address, workers, retries, overwrite)
    failed = [r for r in reports if r.status != "done"]
    if failed:
        fail(f"{len(failed)} of {len(reports)} methods failed (first: {failed[0].job.name}: "
             f"{failed[0].error}); see {out / 'batch.csv'}", code=1)
    rows, fronts = [], {}
    for r in reports:
        init = METHODS[r.job.method].initialization
        if init not in fronts:
            fronts[init] = r.metrics["front_end"]["summary"]
        rows.append(("back end", r.job.method, r.metrics["summary"]))
    front_rows = [("front end", FRONT_END_NAMES[k], v) for k, v in fronts.items()]
    table = f"# {seq.name}\n\n" + table_iii(front_rows + rows)
    (out / "table.md").write_text(table, encoding="utf-8")
    console.print(table)


@app.command()
def batch(
    manifest: Path = typer.Argument(..., help="The manifest (YAML): jobs of sequence, method and settings "
        "(docs/scaling.md)."),
    out: Path = typer.Option(Path("batch"), "--out", help="Output folder: a sub-folder per job, batch.csv and "
        "batch.json."),
    overwrite: bool = typer.Option(False, help="Replace non-empty job folders."),
    ray: bool = typer.Option(False, "--ray", help=RAY_HELP),
    ray_address: str | None = typer.Option(None, "--ray-address", help=RAY_ADDRESS_HELP),
    workers: int | None = typer.Option(None, min=1, help=WORKERS_HELP),
    retries: int = typer.Option(1, min=0, help=RETRIES_HELP),
) -> None:
    """Run many (sequence, method, settings) jobs of a manifest, each written to OUT/NAME as
    spdslam run writes it; OUT/batch.csv and OUT/batch.json say how each ended. A job that
    fails is reported and the others finish; the exit status is then 1."""
    from ..experiments import read_manifest
    from ..io import SequenceFormatError

    try:
        jobs = read_manifest(manifest)
    except SequenceFormatError as e:
        fail(str(e))
    check_output(out, [manifest] + [j.sequence for j in jobs])
    reports = _run_jobs(jobs, out, ray, ray_address, workers, retries, overwrite)
    failed = [r for r in reports if r.status != "done"]
    console.print(f"{len(reports) - len(failed)} of {len(reports)} jobs done; wrote {out / 'batch.csv'}")
    if failed:
        raise typer.Exit(1)


DEMO_MARKER = ".spdslam-demo"


@app.command()
def demo(
    out: Path = typer.Option(Path("spdslam-demo"), "--out",
                             help="Output folder (replaced if it holds an earlier demo)."),
    seed: int = typer.Option(0, help="Seed of the generator."),
    frames: int = typer.Option(120, min=3, help="Camera frames."),
    objects: int = typer.Option(8, min=1, help="Objects in the room."),
    method: str = typer.Option("multi-spd", help=_METHOD_HELP),
    truncation: bool = typer.Option(False, "--truncation/--no-truncation", help="Keep objects partly outside the "
        "image (boxes clipped to it)."),
    outliers: float = typer.Option(0.0, help="False detections (instance -1), as a fraction of the true ones, in [0, "
        "1)."),
    missed: float = typer.Option(0.0, help="Fraction of the true detections dropped, in [0, 1)."),
    cuboids: bool = typer.Option(False, "--cuboids", help="Box-shaped objects (boxes of their 8 projected corners)."),
    no_ids: bool = typer.Option(False, "--no-ids", help="Write the detections without the instance column (then "
        "mapped with automatic association)."),
    associate: str | None = typer.Option(None, help="Data association: instances or auto (default: auto with "
        "--no-ids, else instances)."),
) -> None:
    """The embedded default: generate a synthetic room sequence (OUT/sequence, canonical
    format) and map it with a method (OUT/run), end to end, without any download.

    With --no-ids the written detections have no instance column and the run uses automatic
    association (the generator's ids only score it: precision and recall)."""
    import dataclasses

    from ..io import write_sequence
    from ..synthetic import make_room_sequence

    # the generator's boxes are the ellipsoids' own projections with independent noise: the
    # demo lets them move the poses (initial_poses input); a recording's default holds the
    # poses of a drifting odometry and closes loops instead (docs/drift.md)
    settings = _settings(method, initial_poses="input", associate=associate if associate is not None
                         else "auto" if no_ids else "instances")
    if no_ids and settings.associate != "auto":
        fail("--associate: the detections have no instance ids (--no-ids): expected auto")
    if out.exists() and not out.is_dir():
        fail(f"--out: {out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not (out / DEMO_MARKER).exists():
        fail(f"--out: {out} exists, is not empty and is not an earlier demo output")
    check_output(out)
    try:
        seq = make_room_sequence(
            seed, frames, objects, truncation=truncation, outliers=outliers, missed=missed,
            object_shape="cuboid" if cuboids else "ellipsoid",
        )
    except ValueError as e:
        fail(f"demo: {e}")
    n_false = sum(d.instance < 0 for d in seq.detections)
    scored_seq = seq
    if no_ids:
        seq = dataclasses.replace(
            seq, detections=[dataclasses.replace(d, instance=None) for d in seq.detections]
        )
    out.mkdir(parents=True, exist_ok=True)
    (out / DEMO_MARKER).write_text("written by spdslam demo\n", encoding="utf-8")
    write_sequence(seq, out / "sequence", overwrite=True)
    console.print(
        f"demo: {len(seq)} frames, {len(seq.objects_gt or ())} objects, {len(seq.detections)} boxes "
        f"({n_false} false) -> {out / 'sequence'}"
    )
    # automatic association ignores the ids; the generator's (scored_seq) only score it
    _run_and_write(scored_seq, settings, out / "run", True, False, source=out / "sequence")


@app.command()
def view(
    out: Path = typer.Argument(..., help="Output folder of spdslam run (map.json and trajectory.txt)."),
    sequence: Path | None = typer.Option(None, "--sequence", help="The sequence the run was made from (camera, "
        "detections, images, ground truth); default: the folder map.json records (spdslam run writes it), else the "
        "demo's sequence/ beside a demo's run/, else none."),
    recording: Path | None = typer.Option(None, "--out", help="The recording to write (default OUT/recording.rrd)."),
    images: bool = typer.Option(True, "--images/--no-images", help="Embed the sequence's images (a long sequence's "
        "recording grows with them)."),
) -> None:
    """Write a rerun recording (.rrd) of a run: the ellipsoids, the trajectories, the camera
    per frame and, with the sequence, its ground truth, images, detections and the projected
    ellipses. Open it with: rerun FILE (needs rerun-sdk, the viewer extra)."""
    from ..io import MapFormatError, SequenceFormatError, read_map, read_tum

    if out.is_file() and out.name == "map.json":
        out = out.parent
    if not out.is_dir():
        fail(f"{out}: expected the output folder of spdslam run, got no such folder")
    recording = recording if recording is not None else out / "recording.rrd"
    _check_recording(recording, "--out")
    try:
        m, objects = read_map(out)
    except MapFormatError as e:
        fail(str(e))
    traj = out / "trajectory.txt"
    if not traj.is_file():
        fail(f"{traj}: expected the trajectory written by spdslam run, got no such file")
    try:
        poses = read_tum(traj, str(traj))
    except SequenceFormatError as e:
        fail(str(e))
    recorded = m.get("sequence")
    if sequence is None and isinstance(recorded, str) and recorded:
        if Path(recorded).is_dir():
            sequence = Path(recorded)  # the folder spdslam run recorded in map.json
            console.print(f"sequence: {sequence} (from map.json; --sequence to choose another)")
        else:
            err_console.print(f"the sequence recorded in map.json, {recorded}, is not there")
    if sequence is None and (out.parent / DEMO_MARKER).is_file() and (out.parent / "sequence").is_dir():
        sequence = out.parent / "sequence"  # a demo's run/: its sequence/ beside it
        console.print(f"sequence: {sequence}")
    seq = _load_sequence(sequence) if sequence is not None else None
    if seq is None:
        err_console.print("no --sequence: the recording has no camera image view, detections or ground truth")
    _write_recording(recording, "--out", objects, poses, seq, m.get("to_groundtruth"), images)


@app.command()
def warmup(
    sequence: Path | None = typer.Argument(None, help="A sequence whose camera and priors to warm up for (default: "
        "the demo room's)."),
    method: str = typer.Option("multi-spd", help=_METHOD_HELP),
    frames: int = typer.Option(300, min=3, help="Frames of the synthetic room replayed online."),
    objects: int = typer.Option(40, min=1, help="Objects in that room."),
) -> None:
    """Compile ahead, into the compilation cache (SPDSLAM_CACHE_DIR): the batch run of the
    demo room (`spdslam run`'s programs) and an online replay of a synthetic room with the
    camera and priors of SEQUENCE (`spdslam run --online` and OnlineMapper's). A later
    process loads the programs instead of compiling them (docs/performance.md, "6. The first run")."""
    import time

    from ..mapping import OnlineMapper, run_sequence
    from ..solver import ensure_compilation_cache
    from ..synthetic import make_room_sequence

    settings = _settings(method)
    where = ensure_compilation_cache()
    if where is None:
        fail("the compilation cache is off (SPDSLAM_CACHE_DIR=off) or cannot be written: nothing to warm up")
    t0 = time.perf_counter()
    demo = make_room_sequence(0)
    base = _load_sequence(sequence) if sequence is not None else demo
    run_sequence(demo, settings)
    console.print(f"warmup: batch run of the demo room, {time.perf_counter() - t0:.1f} s")
    room = make_room_sequence(0, frames, objects, camera=base.camera, truncation=True)
    try:
        mapper = OnlineMapper(base.camera, base.priors, settings.replace(associate="auto"))
    except ValueError as e:
        fail(f"--method: {e}")
    seconds = mapper.warmup(room)
    console.print(f"warmup: online replay of a {frames}-frame room with {objects} objects, {seconds:.1f} s; "
                  f"cache {where}")
