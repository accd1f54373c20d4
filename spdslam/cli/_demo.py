"""``demo``, ``view`` and ``warmup``: the embedded demonstration, a run's map in the
viewer, and the compilation cache filled before a first run."""

from __future__ import annotations

from pathlib import Path

import typer

from ._app import app, check_output, console, err_console, fail
from ._common import (
    METHOD_HELP,
    check_recording,
    load_sequence,
    run_and_write,
    run_settings,
    write_recording_file,
)

__all__ = ["DEMO_MARKER", "demo", "view", "warmup"]


DEMO_MARKER = ".spdslam-demo"


@app.command()
def demo(
    out: Path = typer.Option(Path("spdslam-demo"), "--out",
                             help="Output folder (replaced if it holds an earlier demo)."),
    seed: int = typer.Option(0, help="Seed of the generator."),
    frames: int = typer.Option(120, min=3, help="Camera frames."),
    objects: int = typer.Option(8, min=1, help="Objects in the room."),
    method: str = typer.Option("multi-spd", help=METHOD_HELP),
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
    settings = run_settings(method, initial_poses="input", associate=associate if associate is not None
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
    run_and_write(scored_seq, settings, out / "run", True, False, source=out / "sequence")


@app.command()
def view(
    out: Path = typer.Argument(..., help="Output folder of spdslam run (map.json and trajectory.txt), or another "
                               "system's saved map (an Osmap .yaml of GOReloc or VOOM: its objects and keyframes)."),
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
    from ..io import MapFormatError, load_map

    try:
        saved = load_map(out)
    except MapFormatError as e:
        fail(str(e))
    out = saved.path.parent
    if recording is None and not saved.is_spdslam:
        fail(f"{saved.path}: another system's map ({saved.format}): give --out FILE for the recording")
    recording = recording if recording is not None else out / "recording.rrd"
    check_recording(recording, "--out")
    m, objects, poses = saved.document, saved.objects, saved.trajectory
    if poses is None and saved.is_spdslam:
        fail(f"{out / 'trajectory.txt'}: expected the trajectory written by spdslam run, got no such file")
    if poses is None:
        fail(f"{saved.path}: expected the keyframes of the {saved.format} map (its trajectory), got none")
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
    seq = load_sequence(sequence) if sequence is not None else None
    if seq is None:
        err_console.print("no --sequence: the recording has no camera image view, detections or ground truth")
    write_recording_file(recording, "--out", objects, poses, seq, m.get("to_groundtruth"), images)


@app.command()
def warmup(
    sequence: Path | None = typer.Argument(None, help="A sequence whose camera and priors to warm up for (default: "
        "the demo room's)."),
    method: str = typer.Option("multi-spd", help=METHOD_HELP),
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

    settings = run_settings(method)
    where = ensure_compilation_cache()
    if where is None:
        fail("the compilation cache is off (SPDSLAM_CACHE_DIR=off) or cannot be written: nothing to warm up")
    t0 = time.perf_counter()
    demo = make_room_sequence(0)
    base = load_sequence(sequence) if sequence is not None else demo
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
