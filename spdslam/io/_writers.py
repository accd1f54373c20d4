"""Writers: the canonical sequence folder and TUM trajectories, written atomically (a
folder is never left half-written)."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..geometry.se3 import matrix_to_quat
from ._parse import CAMERA_KEYS, check_box
from ._sequence import Sequence

__all__ = ["write_sequence", "write_folder_atomically", "tum_text"]




def _f(x) -> str:
    """Shortest round-tripping text of a float."""
    return repr(float(x))


def _yf(x) -> str:
    """A float PyYAML reads back as a float (it needs a dot before an exponent; .inf)."""
    if np.isinf(x):
        return ".inf" if x > 0 else "-.inf"
    r = _f(x)
    if "e" in r and "." not in r:
        m, e = r.split("e")
        r = f"{m}.0e{e}"
    return r


def _ylist(v) -> str:
    return "[" + ", ".join(_yf(x) for x in np.asarray(v).ravel()) + "]"


def _token(label: str, what: str) -> str:
    if not label or any(c.isspace() for c in label) or "#" in label:
        raise ValueError(f"{what} must be a non-empty token without whitespace or '#', got {label!r}")
    return label


def _tum_lines(rows) -> str:
    return "".join(" ".join(_f(x) for x in r) + "\n" for r in np.asarray(rows))


def tum_text(rows, header: str = "timestamp tx ty tz qx qy qz qw (camera-to-world)") -> str:
    """TUM rows (N, 8) as text, one ``timestamp tx ty tz qx qy qz qw`` line each (shortest
    round-tripping floats), after a ``# header`` line."""
    return f"# {header}\n" + _tum_lines(rows)


def _write_files(seq: Sequence, out: Path, final: Path) -> None:
    cam = seq.camera
    (out / "camera.yaml").write_text(
        "".join(f"{k}: {_yf(getattr(cam, k))}\n" for k in CAMERA_KEYS), encoding="utf-8"
    )
    (out / "trajectory.txt").write_text(
        tum_text(np.column_stack([seq.timestamps, seq.poses_tum])), encoding="utf-8")
    lines = ["# timestamp x1 y1 x2 y2 label score [instance]\n"]
    for i, d in enumerate(seq.detections):  # never a file that the reader would refuse
        check_box(f"detection {i} of {seq.name!r}", None, d.box, cam)
        cols = [_f(d.timestamp), *(_f(x) for x in d.box), _token(d.label, "a label"), _f(d.score)]
        if d.instance is not None:
            cols.append(str(int(d.instance)))
        lines.append(" ".join(cols) + "\n")
    (out / "detections.txt").write_text("".join(lines), encoding="utf-8")
    if seq.ellipsoids is not None:
        lines = ["# timestamp label qx qy qz qw cx cy cz a b c [instance] (camera frame, semi-axes)\n"]
        for e in seq.ellipsoids:
            vals = [*matrix_to_quat(e.rotation), *e.center, *e.radii]
            cols = [_f(e.timestamp), _token(e.label, "a label"), *(_f(x) for x in vals)]
            if e.instance is not None:
                cols.append(str(int(e.instance)))
            lines.append(" ".join(cols) + "\n")
        (out / "ellipsoids.txt").write_text("".join(lines), encoding="utf-8")
    if seq.objects_gt is not None:
        lines = ["# id label cx cy cz qx qy qz qw hx hy hz (world frame, half-extents)\n"]
        for o in seq.objects_gt:
            c = o.cuboid
            vals = [*c.center, *matrix_to_quat(c.rotation), *c.half_extents]
            lines.append(f"{int(o.id)} {_token(o.label, 'a label')} " + " ".join(_f(x) for x in vals) + "\n")
        (out / "objects_gt.txt").write_text("".join(lines), encoding="utf-8")
    if seq.groundtruth_tum is not None:
        (out / "groundtruth.txt").write_text(
            tum_text(seq.groundtruth_tum, "timestamp tx ty tz qx qy qz qw"), encoding="utf-8")
    if seq.priors is not None:
        p = seq.priors
        text = "support_planes:" + ("\n" if p.support_planes else " []\n")
        text += "".join(f"  - {_ylist(pl)}\n" for pl in p.support_planes)
        if p.up is not None:
            text += f"up: {_ylist(p.up)}\n"
        text += "classes:" + ("\n" if p.classes else " {}\n")
        for label, cp in p.classes.items():
            shape = "" if cp.shape == "ellipsoid" else f", shape: {cp.shape}"
            text += f"  {json.dumps(str(label))}: {{radii: {_ylist(cp.radii)}, sigma: {_yf(cp.sigma)}{shape}}}\n"
        if not p.builtin_classes:
            text += "builtin_classes: false\n"
        if p.trajectory_sigma is not None:
            text += f"trajectory_sigma: {_ylist(p.trajectory_sigma)}\n"
        if p.trajectory_absolute_sigma is not None:
            text += f"trajectory_absolute_sigma: {_ylist(p.trajectory_absolute_sigma)}\n"
        (out / "priors.yaml").write_text(text, encoding="utf-8")
    if seq.images is not None:
        lines = ["# timestamp path\n"]
        root = Path(os.path.abspath(final))
        for t, path in sorted(seq.images.items()):
            image = Path(path)
            try:
                rel = Path(os.path.abspath(image)).relative_to(root)
                text = rel.as_posix()
            except ValueError:
                text = os.path.abspath(image)
            if any(c.isspace() for c in text):
                raise ValueError(f"image paths must not contain whitespace, got {text!r}")
            lines.append(f"{_f(t)} {text}\n")
        (out / "rgb.txt").write_text("".join(lines), encoding="utf-8")


def write_file_atomically(path, write):
    """Run ``write(tmp)`` on a temporary file beside ``path``, then rename it into place, so
    ``path`` is never half-written; returns what ``write`` returns. On failure the
    temporary file is removed and ``path`` is as it was."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        out = write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return out


def write_folder_atomically(folder, write, overwrite: bool = False):
    """Run ``write(tmp)`` on a temporary folder beside ``folder``, then rename it into place,
    so ``folder`` is never half-written; returns what ``write`` returns. An existing
    non-empty ``folder`` raises ``FileExistsError`` unless ``overwrite`` (it is replaced
    only once the new one is complete); on failure nothing changes."""
    folder = Path(folder)
    parent = folder.parent
    parent.mkdir(parents=True, exist_ok=True)
    if folder.exists() and not folder.is_dir():
        raise FileExistsError(f"{folder} exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise FileExistsError(f"{folder} exists and is not empty (use overwrite)")
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.tmp-", dir=parent))
    backup = None
    try:
        out = write(tmp)
        if folder.is_dir():
            backup = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old-", dir=parent))
            backup.rmdir()
            os.rename(folder, backup)
        os.rename(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if backup is not None and backup.exists() and not folder.exists():
            os.rename(backup, folder)
        raise
    if backup is not None:
        shutil.rmtree(backup, ignore_errors=True)
    return out


def write_sequence(seq: Sequence, folder, overwrite: bool = False) -> Path:
    """Write ``seq`` in the canonical format into ``folder``, atomically.

    The files are written into a temporary folder beside ``folder`` that is renamed into
    place at the end, so ``folder`` is never left half-written. An existing non-empty
    ``folder`` raises ``FileExistsError`` unless ``overwrite``. Images are not copied:
    ``rgb.txt`` lists them relative to ``folder`` when inside it, else by absolute path.
    """
    write_folder_atomically(folder, lambda tmp: _write_files(seq, tmp, folder), overwrite)
    return folder
