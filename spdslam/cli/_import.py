"""``import``: a sequence in another registered format written as a sequence folder."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from ._app import app, check_output, console, fail
from ._common import (
    INPUT_HELP,
    format_options,
    sequence_path,
)

__all__ = ["import_"]


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
    source: Path = typer.Argument(..., help=INPUT_HELP),
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
    options.update(format_options(option))
    sequence_path(source)

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
