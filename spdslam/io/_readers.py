"""Readers of the canonical sequence folder (see docs/formats.md)::

    camera.yaml       required  fx, fy, cx, cy, width, height
    trajectory.txt    required  TUM ``timestamp tx ty tz qx qy qz qw`` (camera-to-world)
    detections.txt    required  ``timestamp x1 y1 x2 y2 label score [instance]``
    ellipsoids.txt    optional  ``timestamp label qx qy qz qw cx cy cz a b c [instance]``
                                (measured ellipsoids, camera frame: RGB-D / LiDAR)
    objects_gt.txt    optional  ``id label cx cy cz qx qy qz qw hx hy hz`` (world frame)
    groundtruth.txt   optional  TUM format
    priors.yaml       optional  support_planes, up, classes, trajectory_sigma
    rgb.txt           optional  TUM style ``timestamp path``

Every malformed input raises ``SequenceFormatError`` (one line, ``file:line: expected, got``).
Pure NumPy (and PyYAML).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry import OBJECT_SHAPES, Camera, Cuboid
from ..geometry.se3 import quat_to_matrix
from ._classes import ClassPrior
from ._formats import SequenceFormat
from ._parse import (
    CAMERA_KEYS,
    SequenceFormatError,
    box_faults,
    camera_from,
    check_columns,
    match_stamp,
    match_stamps,
    number_rows,
    optional,
    parse_box,
    parse_integer,
    parse_number,
    present,
    read_images,
    read_tum,
    reject_unknown_key,
    required,
    token_rows,
    unit_quaternion,
    yaml_kind,
    yaml_line,
    yaml_mapping,
    yaml_number,
    yaml_root,
    yaml_scalar,
    yaml_vector,
)
from ._sequence import (
    Detection,
    EllipsoidDetection,
    GroundTruthObject,
    Priors,
    Sequence,
)
from ._writers import write_sequence

__all__ = [
    "CanonicalFolder",
    "read_canonical",
    "read_camera",
    "read_priors",
    "read_detections",
    "read_ellipsoids",
    "read_objects_gt",
]



def read_camera(path, name: str | None = None) -> Camera:
    """``camera.yaml``: a mapping with exactly fx, fy, cx, cy, width, height (all > 0)."""
    path = Path(path)
    name = name or str(path)
    root = yaml_root(path, name)
    values, lines = {}, {}
    for key, knode, vnode in yaml_mapping(name, root, "the camera"):
        if key not in CAMERA_KEYS:
            reject_unknown_key(name, knode, key, CAMERA_KEYS, "camera.yaml")
        values[key] = yaml_number(name, vnode, key)
        lines[key] = yaml_line(vnode)
    missing = [k for k in CAMERA_KEYS if k not in values]
    if missing:
        raise SequenceFormatError(name, None, "keys fx, fy, cx, cy, width, height", f"{', '.join(missing)} missing")
    return camera_from(name, values, lines)


def read_priors(path, name: str | None = None) -> Priors:
    """``priors.yaml``: optional keys support_planes, up, classes, builtin_classes,
    trajectory_sigma, trajectory_absolute_sigma."""
    path = Path(path)
    name = name or str(path)
    root = yaml_root(path, name)
    planes, up, classes, tsig, tabs, builtin = [], None, {}, None, None, True
    allowed = ("support_planes", "up", "classes", "builtin_classes", "trajectory_sigma",
               "trajectory_absolute_sigma")
    import yaml

    for key, knode, vnode in yaml_mapping(name, root, "the priors"):
        if key == "support_planes":
            if not isinstance(vnode, yaml.SequenceNode):
                raise SequenceFormatError(name, yaml_line(vnode), "a list of planes [a, b, c, d]", yaml_kind(vnode))
            for p in vnode.value:
                v = yaml_vector(name, p, 4, "a support plane [a, b, c, d]")
                if not np.linalg.norm(v[:3]) > 0:
                    raise SequenceFormatError(name, yaml_line(p), "a plane with a non-zero normal (a, b, c)",
                                              str(v.tolist()))
                planes.append(v)
        elif key == "up":
            up = yaml_vector(name, vnode, 3, "up")
            if not np.linalg.norm(up) > 0:
                raise SequenceFormatError(name, yaml_line(vnode), "a non-zero up vector", str(up.tolist()))
        elif key == "trajectory_sigma":
            tsig = yaml_vector(name, vnode, 2, "trajectory_sigma [metres, radians]")
            if not np.all(tsig > 0):
                raise SequenceFormatError(name, yaml_line(vnode), "a positive trajectory_sigma", str(tsig.tolist()))
        elif key == "trajectory_absolute_sigma":
            tabs = yaml_vector(name, vnode, 2, "trajectory_absolute_sigma [metres, radians]", allow_inf=True)
            if not np.all(tabs > 0):
                raise SequenceFormatError(name, yaml_line(vnode), "a positive trajectory_absolute_sigma (.inf: none)",
                                          str(tabs.tolist()))
        elif key == "builtin_classes":
            builtin = yaml_scalar(vnode)
            if not isinstance(builtin, bool):
                raise SequenceFormatError(name, yaml_line(vnode), "builtin_classes: true or false", yaml_kind(vnode))
        elif key == "classes":
            for label, lk, cnode in yaml_mapping(name, vnode, "classes"):
                radii = sigma = None
                shape = "ellipsoid"
                for ck, ckn, cv in yaml_mapping(name, cnode, f"class {label!r}"):
                    if ck == "radii":
                        radii = yaml_vector(name, cv, 3, f"the radii of {label!r}")
                        if not np.all(radii > 0):
                            raise SequenceFormatError(name, yaml_line(cv), f"positive radii for {label!r}",
                                                      str(radii.tolist()))
                    elif ck == "sigma":
                        sigma = yaml_number(name, cv, f"the sigma of {label!r}")
                        if not sigma > 0:
                            raise SequenceFormatError(name, yaml_line(cv), f"a positive sigma for {label!r}",
                                                      repr(sigma))
                    elif ck == "shape":
                        shape = yaml_scalar(cv)
                        if shape not in OBJECT_SHAPES:
                            raise SequenceFormatError(
                                name, yaml_line(cv), f"shape {' or '.join(OBJECT_SHAPES)} for {label!r}",
                                yaml_kind(cv),
                            )
                    else:
                        reject_unknown_key(name, ckn, ck, ("radii", "sigma", "shape"), f"class {label!r}")
                if radii is None or sigma is None:
                    raise SequenceFormatError(
                        name, yaml_line(lk), f"radii and sigma for class {label!r}",
                        "radii missing" if radii is None else "sigma missing",
                    )
                classes[label] = ClassPrior(radii, sigma, shape)
        else:
            reject_unknown_key(name, knode, key, allowed, "priors.yaml")
    return Priors(planes, up, classes, tsig, builtin, tabs)


def read_detections(path, timestamps, name: str | None = None, camera: Camera | None = None) -> list:
    """``detections.txt`` rows ``timestamp x1 y1 x2 y2 label score [instance]``; every box
    of positive area and, with ``camera``, overlapping its image (``check_box``)."""
    path = Path(path)
    name = name or str(path)
    timestamps = np.asarray(timestamps, dtype=float)
    layout = "timestamp x1 y1 x2 y2 label score [instance]"
    numbered = list(token_rows(path, name))
    for line, tok in numbered:
        check_columns(name, line, tok, (7, 8), layout)
    # converted and checked as arrays; when any row fails they are read again line by line,
    # whose error names the first line that fails
    v = number_rows([(line, tok[:5] + tok[6:7]) for line, tok in numbered], 6) if numbered else None
    if v is not None and not np.any(box_faults(v[:, 1:5], camera)) and all(
            len(tok) == 7 or _is_integer(tok[7]) for _, tok in numbered):
        frames = match_stamps(v[:, 0], timestamps)
        if frames is not None:
            return [Detection(int(f), float(r[0]), r[1:5].copy(), tok[5], float(r[5]),
                              int(tok[7]) if len(tok) == 8 else None)
                    for f, r, (_, tok) in zip(frames, v, numbered)]
    out = []
    for line, tok in numbered:
        t = parse_number(name, line, tok[0], "timestamp")
        box = parse_box(name, line, tok[1:5], camera=camera)
        score = parse_number(name, line, tok[6], "score")
        inst = parse_integer(name, line, tok[7], "instance") if len(tok) == 8 else None
        frame = match_stamp(name, line, t, timestamps)
        out.append(Detection(frame, t, box, tok[5], score, inst))
    return out


def _is_integer(token: str) -> bool:
    try:
        int(token)
    except ValueError:
        return False
    return True


def read_ellipsoids(path, timestamps, name: str | None = None) -> list:
    """``ellipsoids.txt`` rows ``timestamp label qx qy qz qw cx cy cz a b c [instance]``:
    measured ellipsoids in the camera frame (quaternion: the rotation whose columns are the
    axes; a b c the semi-axes along them, > 0)."""
    path = Path(path)
    name = name or str(path)
    timestamps = np.asarray(timestamps, dtype=float)
    layout = "timestamp label qx qy qz qw cx cy cz a b c [instance]"
    fields = layout.split()
    out = []
    for line, tok in token_rows(path, name):
        check_columns(name, line, tok, (12, 13), layout)
        t = parse_number(name, line, tok[0], "timestamp")
        v = [parse_number(name, line, x, f) for x, f in zip(tok[2:12], fields[2:12])]
        q = unit_quaternion(name, line, v[:4])
        radii = np.array(v[7:10])
        if not np.all(radii > 0):
            raise SequenceFormatError(name, line, "positive semi-axes a b c", " ".join(tok[9:12]))
        inst = parse_integer(name, line, tok[12], "instance") if len(tok) == 13 else None
        frame = match_stamp(name, line, t, timestamps)
        out.append(EllipsoidDetection(frame, t, tok[1], quat_to_matrix(q), np.array(v[4:7]), radii, inst))
    return out


def read_objects_gt(path, name: str | None = None) -> list:
    """``objects_gt.txt`` rows ``id label cx cy cz qx qy qz qw hx hy hz``."""
    path = Path(path)
    name = name or str(path)
    layout = "id label cx cy cz qx qy qz qw hx hy hz"
    fields = layout.split()
    out = []
    for line, tok in token_rows(path, name):
        check_columns(name, line, tok, (12,), layout)
        oid = parse_integer(name, line, tok[0], "id")
        v = [parse_number(name, line, t, f) for t, f in zip(tok[2:], fields[2:])]
        q = unit_quaternion(name, line, v[3:7])
        h = np.array(v[7:10])
        if not np.all(h > 0):
            raise SequenceFormatError(name, line, "positive half-extents hx hy hz", " ".join(tok[9:12]))
        try:
            cub = Cuboid(np.array(v[:3]), quat_to_matrix(q), h)
        except ValueError as e:
            raise SequenceFormatError(name, line, "a valid cuboid", str(e)) from None
        out.append(GroundTruthObject(oid, tok[1], cub))
    return out


def read_canonical(folder) -> Sequence:
    """Read a canonical sequence folder (module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SequenceFormatError(folder, None, "a sequence folder", "no such folder")
    camera = read_camera(required(folder, "camera.yaml"))
    traj = read_tum(required(folder, "trajectory.txt"), str(folder / "trajectory.txt"))
    det = read_detections(required(folder, "detections.txt"), traj[:, 0], camera=camera)

    def read_optional(fname, reader, *args):
        p = optional(folder, fname)
        return None if p is None else reader(p, *args)

    objs = read_optional("objects_gt.txt", read_objects_gt)
    gt = read_optional("groundtruth.txt", read_tum, str(folder / "groundtruth.txt"))
    priors = read_optional("priors.yaml", read_priors)
    images = read_optional("rgb.txt", read_images, folder)
    ell = read_optional("ellipsoids.txt", read_ellipsoids, traj[:, 0])
    return Sequence(folder.name, camera, traj[:, 0], traj[:, 1:], det, objs, gt, priors, images, ell)


class CanonicalFolder(SequenceFormat):
    """spdslam's own folder (module docstring): the only format sequences are written in."""

    name = "canonical"
    title = "a canonical sequence folder"
    layout = "camera.yaml, trajectory.txt, detections.txt"
    docs = "The canonical format"
    writes = True

    @classmethod
    def claims(cls, path: Path) -> bool:
        # a camera.yaml and trajectory.txt beside a detector's output (labels/, COCO results)
        # are the detector folder's
        if not path.is_dir():
            return False
        if present(path / "detections.txt"):
            return True
        return any(present(path / f) for f in ("camera.yaml", "trajectory.txt")) and not (
            (path / "labels").is_dir() or present(path / "coco_results.json"))

    @classmethod
    def read(cls, path: Path, **options) -> Sequence:
        return read_canonical(path)

    @classmethod
    def write(cls, seq: Sequence, dest: Path, overwrite: bool = False) -> None:
        write_sequence(seq, dest, overwrite=overwrite)
