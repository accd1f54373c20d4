"""``export``: a saved map written for other tools (a Spark-DSG scene graph, a glTF scene)."""

from __future__ import annotations

from pathlib import Path

import typer

from ._app import app, console, fail

__all__ = ["export"]


def _up(text: str | None):
    if text is None:
        return None
    import numpy as np

    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) == 0:
        fail(f"--up: expected three numbers x,y,z of a direction, got {text!r}")
    return v


@app.command()
def export(
    map_path: Path = typer.Argument(..., metavar="MAP", help="A saved map: the output folder of spdslam run (or its "
                                    "map.json), or another system's (an Osmap .yaml of GOReloc or VOOM)."),
    format: str = typer.Option(..., "--format", help="spark-dsg (a scene graph for spark_dsg / Hydra's tools: "
                               ".json or .sparkdsg) or gltf (an ellipsoid mesh per object for any 3D viewer: .glb "
                               "or .gltf)."),
    out: Path = typer.Option(..., "--out", help="The file to write."),
    up: str | None = typer.Option(None, "--up", help="gltf: the map's up direction x,y,z, turned to glTF's +y "
                                  "(default: the map's frame as it is)."),
    overwrite: bool = typer.Option(False, help="Replace an existing OUT."),
) -> None:
    """Write a map for other tools: a Spark-DSG scene graph (an object node per object:
    position, oriented bounding box, label; covariance and the recordings that saw it as
    metadata) or a glTF scene (an ellipsoid mesh per object, named by label and id; the
    trajectory as a line). docs/map-reuse.md, "Exports"."""
    from ..io import EXPORT_FORMATS, MapFormatError, export_map, load_map

    if format not in EXPORT_FORMATS:
        fail(f"--format: expected one of {', '.join(EXPORT_FORMATS)}, got {format!r}")
    suffixes = EXPORT_FORMATS[format][1]
    if out.suffix not in suffixes:
        fail(f"--out: expected a file name ending in {' or '.join(suffixes)} for {format}, got {out.name}")
    direction = _up(up)
    if direction is not None and format != "gltf":
        fail(f"--up: turns a glTF scene only, not {format}")
    if out.is_dir():
        fail(f"--out: {out} is a folder: expected a file name")
    if out.exists() and not overwrite:
        fail(f"--out: {out} exists: give --overwrite to replace it")
    try:
        saved = load_map(map_path)
    except MapFormatError as e:
        fail(str(e))
    if out.resolve() == saved.path.resolve():
        fail(f"--out: {out} is the map itself: expected another file")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        export_map(saved, format, out, direction)
    except ImportError as e:
        fail(str(e))
    except OSError as e:
        fail(f"{out}: cannot write: {e.strerror or e}")
    console.print(f"wrote {out}: {len(saved.objects)} objects ({EXPORT_FORMATS[format][0]})")
