"""Readers and writer for the canonical sequence folder, and the TUM fr3_cabinet importer.

The canonical folder (see ``docs/formats.md``)::

    camera.yaml       required  fx, fy, cx, cy, width, height
    trajectory.txt    required  TUM ``timestamp tx ty tz qx qy qz qw`` (camera-to-world)
    detections.txt    required  ``timestamp x1 y1 x2 y2 label score [instance]``
    ellipsoids.txt    optional  ``timestamp label qx qy qz qw cx cy cz a b c [instance]``
                                (measured ellipsoids, camera frame: RGB-D / LiDAR)
    objects_gt.txt    optional  ``id label cx cy cz qx qy qz qw hx hy hz`` (world frame)
    groundtruth.txt   optional  TUM format
    priors.yaml       optional  support_planes, up, classes
    rgb.txt           optional  TUM style ``timestamp path``

Every malformed input raises :class:`SequenceFormatError` (a ``ValueError``) whose message is
one line ``"<file>:<line>: <what was expected>, got <what>"`` (no ``:<line>`` for problems
with a whole file, such as a missing one).

Pure numpy (and PyYAML); nothing here runs JAX code.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .camera import Camera
from .evaluation import Cuboid

__all__ = [
    "SequenceFormatError",
    "Detection",
    "EllipsoidDetection",
    "GroundTruthObject",
    "ClassPrior",
    "Priors",
    "Sequence",
    "read_sequence",
    "write_sequence",
    "write_folder_atomically",
    "import_fr3_cabinet",
    "is_fr3_cabinet",
    "quat_to_matrix",
    "matrix_to_quat",
    "MATCH_TOLERANCE",
    "COCO_LABELS",
]

#: A detection timestamp matches the nearest trajectory pose within this many seconds.
MATCH_TOLERANCE = 0.02
#: Object silhouettes a class prior can declare (``shape:`` in priors.yaml).
OBJECT_SHAPES = ("ellipsoid", "cuboid")
_MATCH_SLACK = 1e-9  # float noise on the tolerance

#: Per-step accuracy (m, rad) given to the fr3_cabinet trajectory: motion capture.
FR3_TRAJECTORY_SIGMA = (1e-4, 1e-4)

#: COCO class indices (YOLO numbering) with a name in the importer; others become "class<k>".
COCO_LABELS = {28: "suitcase"}

_FLOAT_TOL = 1e-12  # equality of round-tripped floats


class SequenceFormatError(ValueError):
    """A malformed sequence file; the message is ``"<file>:<line>: expected, got what"``."""

    def __init__(self, file, line: int | None, expected: str, got: str):
        self.file = str(file)
        self.line = line
        self.expected = expected
        self.got = got
        where = self.file if line is None else f"{self.file}:{line}"
        msg = f"{where}: {expected}, got {got}"
        super().__init__(" ".join(msg.split()))  # always one line


# --- data classes ---------------------------------------------------------------------------


def _close(a, b) -> bool:
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    return a.shape == b.shape and bool(np.allclose(a, b, rtol=_FLOAT_TOL, atol=_FLOAT_TOL))


def _frozen_array(x, shape=None) -> np.ndarray:
    a = np.array(x, dtype=float)
    if shape is not None and a.shape != shape:
        raise ValueError(f"expected shape {shape}, got {a.shape}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Detection:
    """A 2D box ``[x1, y1, x2, y2]`` (pixels) seen at trajectory index ``frame``."""

    frame: int
    timestamp: float
    box: np.ndarray
    label: str
    score: float
    instance: int | None = None

    def __post_init__(self):
        object.__setattr__(self, "frame", int(self.frame))
        object.__setattr__(self, "timestamp", float(self.timestamp))
        object.__setattr__(self, "box", _frozen_array(self.box, (4,)))
        object.__setattr__(self, "label", str(self.label))
        object.__setattr__(self, "score", float(self.score))
        if self.instance is not None:
            object.__setattr__(self, "instance", int(self.instance))

    def __eq__(self, other):
        if not isinstance(other, Detection):
            return NotImplemented
        return (
            self.frame == other.frame
            and self.label == other.label
            and self.instance == other.instance
            and _close(self.timestamp, other.timestamp)
            and _close(self.score, other.score)
            and _close(self.box, other.box)
        )


@dataclass(frozen=True, eq=False)
class EllipsoidDetection:
    """A whole ellipsoid measured at trajectory index ``frame`` (an RGB-D or LiDAR front
    end), in that frame's CAMERA coordinates: ``center`` (3,), ``rotation`` (3×3, columns =
    the axes, det +1) and ``radii`` (3,) the semi-axes along them, so that
    P = R diag(radii²) Rᵀ. A reflection (det −1) describes the same ellipsoid: its third
    axis is negated."""

    frame: int
    timestamp: float
    label: str
    rotation: np.ndarray
    center: np.ndarray
    radii: np.ndarray
    instance: int | None = None

    def __post_init__(self):
        object.__setattr__(self, "frame", int(self.frame))
        object.__setattr__(self, "timestamp", float(self.timestamp))
        object.__setattr__(self, "label", str(self.label))
        R = np.array(self.rotation, dtype=float)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
            raise ValueError(f"rotation must be an orthonormal 3x3 matrix, got {R.tolist()}")
        if np.linalg.det(R) < 0:
            R[:, 2] = -R[:, 2]
        object.__setattr__(self, "rotation", _frozen_array(R, (3, 3)))
        c = _frozen_array(self.center, (3,))
        r = _frozen_array(self.radii, (3,))
        if not np.all(np.isfinite(c)):
            raise ValueError(f"center must be finite, got {c.tolist()}")
        if not (np.all(np.isfinite(r)) and np.all(r > 0)):
            raise ValueError(f"radii must be positive, got {r.tolist()}")
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "radii", r)
        if self.instance is not None:
            object.__setattr__(self, "instance", int(self.instance))

    @property
    def P(self) -> np.ndarray:
        """The shape matrix R diag(radii²) Rᵀ (camera frame)."""
        return (self.rotation * self.radii**2) @ self.rotation.T

    def __eq__(self, other):
        if not isinstance(other, EllipsoidDetection):
            return NotImplemented
        return (
            self.frame == other.frame
            and self.label == other.label
            and self.instance == other.instance
            and _close(self.timestamp, other.timestamp)
            and _close(self.rotation, other.rotation)
            and _close(self.center, other.center)
            and _close(self.radii, other.radii)
        )


@dataclass(frozen=True, eq=False)
class GroundTruthObject:
    """A ground-truth object: its id, class label and oriented cuboid (world frame)."""

    id: int
    label: str
    cuboid: Cuboid

    def __eq__(self, other):
        if not isinstance(other, GroundTruthObject):
            return NotImplemented
        a, b = self.cuboid, other.cuboid
        return (
            int(self.id) == int(other.id)
            and self.label == other.label
            and _close(a.center, b.center)
            and _close(a.rotation, b.rotation)
            and _close(a.half_extents, b.half_extents)
        )


@dataclass(frozen=True, eq=False)
class ClassPrior:
    """Prior of a class: radii (3,), their standard deviation ``sigma``, and the ``shape``
    whose silhouette the detector boxes (``"ellipsoid"`` or ``"cuboid"``: box-like objects
    such as cabinets, monitors or tables; the radii are then the cuboid's half-extents)."""

    radii: np.ndarray
    sigma: float
    shape: str = "ellipsoid"

    def __post_init__(self):
        object.__setattr__(self, "radii", _frozen_array(self.radii, (3,)))
        object.__setattr__(self, "sigma", float(self.sigma))
        if self.shape not in OBJECT_SHAPES:
            raise ValueError(f"shape must be one of {', '.join(OBJECT_SHAPES)}, got {self.shape!r}")

    def __eq__(self, other):
        if not isinstance(other, ClassPrior):
            return NotImplemented
        return (
            _close(self.radii, other.radii)
            and _close(self.sigma, other.sigma)
            and self.shape == other.shape
        )


@dataclass(frozen=True, eq=False)
class Priors:
    """Scene priors: support planes ``[a, b, c, d]`` (ax + by + cz + d = 0), the up
    direction, per-class size priors, and the accuracy of the trajectory's relative motion
    per frame step ``trajectory_sigma = (σ_t m, σ_r rad)`` (None: the back end's default)."""

    support_planes: list = field(default_factory=list)
    up: np.ndarray | None = None
    classes: dict = field(default_factory=dict)
    trajectory_sigma: np.ndarray | None = None

    def __post_init__(self):
        if self.trajectory_sigma is not None:
            ts = _frozen_array(self.trajectory_sigma, (2,))
            if not (np.all(np.isfinite(ts)) and np.all(ts > 0)):
                raise ValueError(f"trajectory_sigma must be 2 positive numbers, got {ts.tolist()}")
            object.__setattr__(self, "trajectory_sigma", ts)
        object.__setattr__(
            self, "support_planes", [_frozen_array(p, (4,)) for p in self.support_planes]
        )
        if self.up is not None:
            object.__setattr__(self, "up", _frozen_array(self.up, (3,)))
        object.__setattr__(self, "classes", dict(self.classes))

    def __eq__(self, other):
        if not isinstance(other, Priors):
            return NotImplemented
        if len(self.support_planes) != len(other.support_planes):
            return False
        if not all(_close(a, b) for a, b in zip(self.support_planes, other.support_planes)):
            return False
        if (self.up is None) != (other.up is None):
            return False
        if self.up is not None and not _close(self.up, other.up):
            return False
        if (self.trajectory_sigma is None) != (other.trajectory_sigma is None):
            return False
        if self.trajectory_sigma is not None and not _close(self.trajectory_sigma, other.trajectory_sigma):
            return False
        return self.classes == other.classes


@dataclass(frozen=True, eq=False)
class Sequence:
    """A sequence: camera, trajectory (TUM rows, camera-to-world), detections and the
    optional ground truth, priors, images and measured ellipsoids
    (:class:`EllipsoidDetection`, ``ellipsoids.txt``)."""

    name: str
    camera: Camera
    timestamps: np.ndarray
    poses_tum: np.ndarray
    detections: list
    objects_gt: list | None = None
    groundtruth_tum: np.ndarray | None = None
    priors: Priors | None = None
    images: dict | None = None
    ellipsoids: list | None = None

    def __post_init__(self):
        t = _frozen_array(self.timestamps)
        if t.ndim != 1:
            raise ValueError(f"timestamps must have shape (N,), got {t.shape}")
        object.__setattr__(self, "timestamps", t)
        object.__setattr__(self, "poses_tum", _frozen_array(self.poses_tum, (t.size, 7)))
        object.__setattr__(self, "detections", list(self.detections))
        if self.objects_gt is not None:
            object.__setattr__(self, "objects_gt", list(self.objects_gt))
        if self.ellipsoids is not None:
            object.__setattr__(self, "ellipsoids", list(self.ellipsoids))
        if self.groundtruth_tum is not None:
            g = _frozen_array(self.groundtruth_tum)
            if g.ndim != 2 or g.shape[1] != 8:
                raise ValueError(f"groundtruth_tum must have shape (M, 8), got {g.shape}")
            object.__setattr__(self, "groundtruth_tum", g)
        if self.images is not None:
            object.__setattr__(
                self, "images", {float(k): Path(v) for k, v in self.images.items()}
            )

    def __len__(self) -> int:
        return int(self.timestamps.size)

    def detections_at(self, frame: int) -> list:
        """The detections of trajectory index ``frame``."""
        return [d for d in self.detections if d.frame == frame]

    def ellipsoids_at(self, frame: int) -> list:
        """The measured ellipsoids of trajectory index ``frame`` (none without the file)."""
        return [e for e in self.ellipsoids or () if e.frame == frame]

    def __eq__(self, other):
        if not isinstance(other, Sequence):
            return NotImplemented

        def opt(a, b, eq):
            if (a is None) != (b is None):
                return False
            return a is None or eq(a, b)

        return (
            self.name == other.name
            and self.camera == other.camera
            and _close(self.timestamps, other.timestamps)
            and _close(self.poses_tum, other.poses_tum)
            and self.detections == other.detections
            and opt(self.objects_gt, other.objects_gt, lambda a, b: a == b)
            and opt(self.groundtruth_tum, other.groundtruth_tum, _close)
            and opt(self.priors, other.priors, lambda a, b: a == b)
            and opt(self.ellipsoids, other.ellipsoids, lambda a, b: a == b)
            and opt(
                self.images,
                other.images,
                lambda a, b: len(a) == len(b)
                and all(
                    _close(ka, kb) and Path(va) == Path(vb)
                    for (ka, va), (kb, vb) in zip(sorted(a.items()), sorted(b.items()))
                ),
            )
        )


# --- quaternions ----------------------------------------------------------------------------


def quat_to_matrix(q_xyzw) -> np.ndarray:
    """Rotation matrix of a quaternion ``qx qy qz qw`` (normalised here)."""
    return Rotation.from_quat(np.asarray(q_xyzw, dtype=float)).as_matrix()


def matrix_to_quat(R) -> np.ndarray:
    """Unit quaternion ``qx qy qz qw`` with qw ≥ 0 of a rotation matrix."""
    q = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    return np.where(q[..., 3:] < 0, -q, q)


# --- low-level parsing ----------------------------------------------------------------------


def _rows(path: Path, label: str | None = None):
    """(line number, tokens) of the non-empty lines of a text file, ``#`` comments removed."""
    name = label or str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise SequenceFormatError(name, None, "a UTF-8 text file", f"undecodable bytes ({e.reason})") from None
    for i, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if body:
            yield i, body.split()


def _show(tokens) -> str:
    s = " ".join(tokens)
    return repr(s if len(s) <= 80 else s[:77] + "...")


def _check_columns(file, line, tokens, counts, layout):
    if len(tokens) not in counts:
        want = " or ".join(str(c) for c in counts)
        raise SequenceFormatError(
            file, line, f"{want} columns '{layout}'", f"{len(tokens)} columns {_show(tokens)}"
        )


def _number(file, line, token: str, what: str) -> float:
    try:
        v = float(token)
    except ValueError:
        raise SequenceFormatError(file, line, f"a number for {what}", repr(token)) from None
    if not math.isfinite(v):
        raise SequenceFormatError(file, line, f"a finite number for {what}", repr(token))
    return v


def _integer(file, line, token: str, what: str) -> int:
    try:
        return int(token)
    except ValueError:
        raise SequenceFormatError(file, line, f"an integer for {what}", repr(token)) from None


def _unit_quaternion(file, line, q) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    n = float(np.linalg.norm(q))
    if not (n > 1e-6):
        raise SequenceFormatError(
            file, line, "a quaternion 'qx qy qz qw' that normalises to unit length",
            f"norm {n:.3g}",
        )
    return q / n


def _read_tum(path: Path, name: str) -> np.ndarray:
    """(N, 8) rows ``timestamp tx ty tz qx qy qz qw``, quaternions normalised, strictly
    increasing timestamps."""
    layout = "timestamp tx ty tz qx qy qz qw"
    fields = layout.split()
    rows = []
    for line, tok in _rows(path, name):
        _check_columns(name, line, tok, (8,), layout)
        v = [_number(name, line, t, f) for t, f in zip(tok, fields)]
        v[4:8] = _unit_quaternion(name, line, v[4:8]).tolist()
        if rows and not v[0] > rows[-1][0]:
            raise SequenceFormatError(
                name, line, f"a timestamp greater than the previous one ({rows[-1][0]!r})",
                repr(tok[0]),
            )
        rows.append(v)
    if not rows:
        raise SequenceFormatError(name, None, f"at least one line '{layout}'", "an empty file")
    return np.array(rows, dtype=float)


def _match(file, line, t: float, timestamps: np.ndarray) -> int:
    i = int(np.argmin(np.abs(timestamps - t)))
    gap = abs(float(timestamps[i]) - t)
    if gap > MATCH_TOLERANCE + _MATCH_SLACK:
        raise SequenceFormatError(
            file, line, f"a timestamp within {MATCH_TOLERANCE} s of a trajectory pose",
            f"{t!r} (nearest pose {float(timestamps[i])!r} is {gap:.3g} s away)",
        )
    return i


def _box(file, line, tok, what="x1 y1 x2 y2") -> np.ndarray:
    b = [_number(file, line, t, f) for t, f in zip(tok, what.split())]
    if b[2] < b[0]:
        raise SequenceFormatError(file, line, "x2 >= x1", f"x1={tok[0]} x2={tok[2]}")
    if b[3] < b[1]:
        raise SequenceFormatError(file, line, "y2 >= y1", f"y1={tok[1]} y2={tok[3]}")
    return np.array(b)


# --- YAML with line numbers -----------------------------------------------------------------


def _yaml_root(path: Path, name: str):
    import yaml

    try:
        node = yaml.compose(path.read_text(encoding="utf-8"), Loader=yaml.SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise SequenceFormatError(name, line, "valid YAML", str(getattr(e, "problem", None) or e)) from None
    except UnicodeDecodeError as e:
        raise SequenceFormatError(name, None, "a UTF-8 text file", f"undecodable bytes ({e.reason})") from None
    if node is None:
        raise SequenceFormatError(name, None, "a YAML mapping", "an empty file")
    return node


def _line(node) -> int:
    return node.start_mark.line + 1


def _mapping(name, node, what: str) -> list:
    import yaml

    if not isinstance(node, yaml.MappingNode):
        raise SequenceFormatError(name, _line(node), f"a mapping for {what}", _kind(node))
    out = []
    seen = set()
    for k, v in node.value:
        key = _scalar(k)
        if not isinstance(key, str):
            raise SequenceFormatError(name, _line(k), f"a string key in {what}", repr(key))
        if key in seen:
            raise SequenceFormatError(name, _line(k), f"unique keys in {what}", f"{key!r} twice")
        seen.add(key)
        out.append((key, k, v))
    return out


def _kind(node) -> str:
    import yaml

    if isinstance(node, yaml.MappingNode):
        return "a mapping"
    if isinstance(node, yaml.SequenceNode):
        return "a list"
    return repr(_scalar(node))


def _scalar(node):
    import yaml

    if not isinstance(node, yaml.ScalarNode):
        return None
    return yaml.SafeLoader("").construct_object(node, deep=True)


def _ynumber(name, node, what: str) -> float:
    import yaml

    v = _scalar(node) if isinstance(node, yaml.ScalarNode) else None
    if isinstance(v, str):  # PyYAML reads '1e3' (no dot) as a string
        try:
            v = float(v)
        except ValueError:
            pass
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SequenceFormatError(name, _line(node), f"a number for {what}", _kind(node))
    if not math.isfinite(v):
        raise SequenceFormatError(name, _line(node), f"a finite number for {what}", repr(v))
    return float(v)


def _yvector(name, node, n: int, what: str) -> np.ndarray:
    import yaml

    if not isinstance(node, yaml.SequenceNode) or len(node.value) != n:
        got = f"a list of {len(node.value)}" if isinstance(node, yaml.SequenceNode) else _kind(node)
        raise SequenceFormatError(name, _line(node), f"a list of {n} numbers for {what}", got)
    return np.array([_ynumber(name, v, what) for v in node.value])


def _unknown_key(name, knode, key, allowed, where):
    raise SequenceFormatError(
        name, _line(knode), f"a key of {where} among {', '.join(allowed)}", repr(key)
    )


# --- readers of each file -------------------------------------------------------------------

_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")


def _camera_from(name, values: dict, lines: dict) -> Camera:
    for k in _CAMERA_KEYS:
        if not values[k] > 0:
            raise SequenceFormatError(name, lines.get(k), f"a positive {k}", repr(values[k]))
    return Camera(**{k: values[k] for k in _CAMERA_KEYS})


def read_camera(path, name: str | None = None) -> Camera:
    """``camera.yaml``: a mapping with exactly fx, fy, cx, cy, width, height (all > 0)."""
    path = Path(path)
    name = name or str(path)
    root = _yaml_root(path, name)
    values, lines = {}, {}
    for key, knode, vnode in _mapping(name, root, "the camera"):
        if key not in _CAMERA_KEYS:
            _unknown_key(name, knode, key, _CAMERA_KEYS, "camera.yaml")
        values[key] = _ynumber(name, vnode, key)
        lines[key] = _line(vnode)
    missing = [k for k in _CAMERA_KEYS if k not in values]
    if missing:
        raise SequenceFormatError(name, None, "keys fx, fy, cx, cy, width, height", f"{', '.join(missing)} missing")
    return _camera_from(name, values, lines)


def read_priors(path, name: str | None = None) -> Priors:
    """``priors.yaml``: optional keys support_planes, up, classes, trajectory_sigma."""
    path = Path(path)
    name = name or str(path)
    root = _yaml_root(path, name)
    planes, up, classes, tsig = [], None, {}, None
    allowed = ("support_planes", "up", "classes", "trajectory_sigma")
    import yaml

    for key, knode, vnode in _mapping(name, root, "the priors"):
        if key == "support_planes":
            if not isinstance(vnode, yaml.SequenceNode):
                raise SequenceFormatError(name, _line(vnode), "a list of planes [a, b, c, d]", _kind(vnode))
            for p in vnode.value:
                v = _yvector(name, p, 4, "a support plane [a, b, c, d]")
                if not np.linalg.norm(v[:3]) > 0:
                    raise SequenceFormatError(name, _line(p), "a plane with a non-zero normal (a, b, c)", str(v.tolist()))
                planes.append(v)
        elif key == "up":
            up = _yvector(name, vnode, 3, "up")
            if not np.linalg.norm(up) > 0:
                raise SequenceFormatError(name, _line(vnode), "a non-zero up vector", str(up.tolist()))
        elif key == "trajectory_sigma":
            tsig = _yvector(name, vnode, 2, "trajectory_sigma [metres, radians]")
            if not np.all(tsig > 0):
                raise SequenceFormatError(name, _line(vnode), "a positive trajectory_sigma", str(tsig.tolist()))
        elif key == "classes":
            for label, lk, cnode in _mapping(name, vnode, "classes"):
                radii = sigma = None
                shape = "ellipsoid"
                for ck, ckn, cv in _mapping(name, cnode, f"class {label!r}"):
                    if ck == "radii":
                        radii = _yvector(name, cv, 3, f"the radii of {label!r}")
                        if not np.all(radii > 0):
                            raise SequenceFormatError(name, _line(cv), f"positive radii for {label!r}", str(radii.tolist()))
                    elif ck == "sigma":
                        sigma = _ynumber(name, cv, f"the sigma of {label!r}")
                        if not sigma > 0:
                            raise SequenceFormatError(name, _line(cv), f"a positive sigma for {label!r}", repr(sigma))
                    elif ck == "shape":
                        shape = _scalar(cv)
                        if shape not in OBJECT_SHAPES:
                            raise SequenceFormatError(
                                name, _line(cv), f"shape {' or '.join(OBJECT_SHAPES)} for {label!r}",
                                _kind(cv),
                            )
                    else:
                        _unknown_key(name, ckn, ck, ("radii", "sigma", "shape"), f"class {label!r}")
                if radii is None or sigma is None:
                    raise SequenceFormatError(
                        name, _line(lk), f"radii and sigma for class {label!r}",
                        "radii missing" if radii is None else "sigma missing",
                    )
                classes[label] = ClassPrior(radii, sigma, shape)
        else:
            _unknown_key(name, knode, key, allowed, "priors.yaml")
    return Priors(planes, up, classes, tsig)


def read_detections(path, timestamps, name: str | None = None) -> list:
    """``detections.txt`` rows ``timestamp x1 y1 x2 y2 label score [instance]``."""
    path = Path(path)
    name = name or str(path)
    timestamps = np.asarray(timestamps, dtype=float)
    layout = "timestamp x1 y1 x2 y2 label score [instance]"
    out = []
    for line, tok in _rows(path, name):
        _check_columns(name, line, tok, (7, 8), layout)
        t = _number(name, line, tok[0], "timestamp")
        box = _box(name, line, tok[1:5])
        score = _number(name, line, tok[6], "score")
        inst = _integer(name, line, tok[7], "instance") if len(tok) == 8 else None
        frame = _match(name, line, t, timestamps)
        out.append(Detection(frame, t, box, tok[5], score, inst))
    return out


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
    for line, tok in _rows(path, name):
        _check_columns(name, line, tok, (12, 13), layout)
        t = _number(name, line, tok[0], "timestamp")
        v = [_number(name, line, x, f) for x, f in zip(tok[2:12], fields[2:12])]
        q = _unit_quaternion(name, line, v[:4])
        radii = np.array(v[7:10])
        if not np.all(radii > 0):
            raise SequenceFormatError(name, line, "positive semi-axes a b c", " ".join(tok[9:12]))
        inst = _integer(name, line, tok[12], "instance") if len(tok) == 13 else None
        frame = _match(name, line, t, timestamps)
        out.append(EllipsoidDetection(frame, t, tok[1], quat_to_matrix(q), v[4:7], radii, inst))
    return out


def read_objects_gt(path, name: str | None = None) -> list:
    """``objects_gt.txt`` rows ``id label cx cy cz qx qy qz qw hx hy hz``."""
    path = Path(path)
    name = name or str(path)
    layout = "id label cx cy cz qx qy qz qw hx hy hz"
    fields = layout.split()
    out = []
    for line, tok in _rows(path, name):
        _check_columns(name, line, tok, (12,), layout)
        oid = _integer(name, line, tok[0], "id")
        v = [_number(name, line, t, f) for t, f in zip(tok[2:], fields[2:])]
        q = _unit_quaternion(name, line, v[3:7])
        h = np.array(v[7:10])
        if not np.all(h > 0):
            raise SequenceFormatError(name, line, "positive half-extents hx hy hz", " ".join(tok[9:12]))
        try:
            cub = Cuboid(np.array(v[:3]), quat_to_matrix(q), h)
        except ValueError as e:
            raise SequenceFormatError(name, line, "a valid cuboid", str(e)) from None
        out.append(GroundTruthObject(oid, tok[1], cub))
    return out


def read_images(path, folder, name: str | None = None) -> dict:
    """``rgb.txt`` rows ``timestamp path``; relative paths are taken from ``folder``."""
    path = Path(path)
    name = name or str(path)
    out = {}
    for line, tok in _rows(path, name):
        _check_columns(name, line, tok, (2,), "timestamp path")
        t = _number(name, line, tok[0], "timestamp")
        p = Path(tok[1])
        out[t] = Path(os.path.abspath(p if p.is_absolute() else Path(folder) / p))
    return out


def _required(folder: Path, fname: str) -> Path:
    p = folder / fname
    if not p.is_file():
        raise SequenceFormatError(p, None, f"a required file {fname}", "no such file")
    return p


def is_fr3_cabinet(folder) -> bool:
    """True for the TUM fr3_cabinet layout (a ``bbox/`` folder and ``truth_objects.txt``)."""
    folder = Path(folder)
    return (folder / "bbox").is_dir() and (folder / "truth_objects.txt").is_file()


def read_sequence(folder) -> Sequence:
    """Read a canonical sequence folder (or the fr3_cabinet layout, detected automatically)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SequenceFormatError(folder, None, "a sequence folder", "no such folder")
    if is_fr3_cabinet(folder) and not (folder / "trajectory.txt").exists():
        return import_fr3_cabinet(folder)
    camera = read_camera(_required(folder, "camera.yaml"))
    traj = _read_tum(_required(folder, "trajectory.txt"), str(folder / "trajectory.txt"))
    det = read_detections(_required(folder, "detections.txt"), traj[:, 0])
    objs = read_objects_gt(folder / "objects_gt.txt") if (folder / "objects_gt.txt").is_file() else None
    gt = _read_tum(folder / "groundtruth.txt", str(folder / "groundtruth.txt")) if (folder / "groundtruth.txt").is_file() else None
    priors = read_priors(folder / "priors.yaml") if (folder / "priors.yaml").is_file() else None
    images = read_images(folder / "rgb.txt", folder) if (folder / "rgb.txt").is_file() else None
    ell = read_ellipsoids(folder / "ellipsoids.txt", traj[:, 0]) if (folder / "ellipsoids.txt").is_file() else None
    return Sequence(folder.name, camera, traj[:, 0], traj[:, 1:], det, objs, gt, priors, images, ell)


# --- the TUM fr3_cabinet importer -----------------------------------------------------------


def _read_opencv_camera(path: Path) -> Camera:
    """``Camera.fx: 535.4`` lines of an OpenCV YAML file (``%YAML:1.0`` header)."""
    name = str(path)
    values, lines = {}, {}
    for line, tok in _rows(path, name):
        body = " ".join(tok)
        if not body.startswith("Camera."):
            continue
        key, sep, val = body[len("Camera."):].partition(":")
        key = key.strip()
        if key not in _CAMERA_KEYS:
            continue
        if not sep or not val.strip():
            raise SequenceFormatError(name, line, f"'Camera.{key}: <number>'", repr(body))
        values[key] = _number(name, line, val.strip(), f"Camera.{key}")
        lines[key] = line
    values.setdefault("width", 640.0)
    values.setdefault("height", 480.0)
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in values]
    if missing:
        raise SequenceFormatError(
            name, None, "lines Camera.fx, Camera.fy, Camera.cx, Camera.cy",
            f"{', '.join('Camera.' + k for k in missing)} missing",
        )
    return _camera_from(name, values, lines)


def _coco_label(k: int) -> str:
    return COCO_LABELS.get(k, f"class{k}")


def import_fr3_cabinet(folder) -> Sequence:
    """The TUM fr3_cabinet layout as a :class:`Sequence`.

    - ``groundtruth.txt`` gives the poses: the trajectory (and ``groundtruth_tum``);
    - ``bbox/<timestamp>.txt`` rows ``id x1 y1 x2 y2 label score instance`` (label a COCO
      class index: 28 → "suitcase", others "class<k>"); empty files are frames without
      detections;
    - ``TUM3.yaml`` intrinsics (``Camera.fx: …`` lines; 640×480 unless given);
    - ``truth_objects.txt`` rows ``x y z yaw hx hy hz`` → ``Cuboid.from_yaw``; the object's id
      is its row index and its label that of the detections with that instance;
    - priors: the floor z = 0 ([0, 0, 1, 0]), up = +z, and ``trajectory_sigma`` =
      (1e-4 m, 1e-4 rad) per step: the trajectory is the motion-capture ground truth;
    - ``rgb.txt`` images when present.
    """
    folder = Path(folder)
    for req in ("groundtruth.txt", "TUM3.yaml", "truth_objects.txt"):
        _required(folder, req)
    if not (folder / "bbox").is_dir():
        raise SequenceFormatError(folder / "bbox", None, "a required folder bbox/", "no such folder")
    camera = _read_opencv_camera(folder / "TUM3.yaml")
    traj = _read_tum(folder / "groundtruth.txt", str(folder / "groundtruth.txt"))
    timestamps = traj[:, 0]

    files = []
    for f in (folder / "bbox").iterdir():
        if f.suffix != ".txt":
            continue
        try:
            t = float(f.stem)
        except ValueError:
            raise SequenceFormatError(f, None, "a file named <timestamp>.txt", repr(f.name)) from None
        if not math.isfinite(t):
            raise SequenceFormatError(f, None, "a file named <timestamp>.txt", repr(f.name))
        files.append((t, f))
    files.sort()
    layout = "id x1 y1 x2 y2 label score instance"
    detections = []
    for t, f in files:
        name = str(f)
        frame = None
        for line, tok in _rows(f, name):
            _check_columns(name, line, tok, (8,), layout)
            _integer(name, line, tok[0], "id")
            box = _box(name, line, tok[1:5])
            cls = _integer(name, line, tok[5], "label (a COCO class index)")
            score = _number(name, line, tok[6], "score")
            inst = _integer(name, line, tok[7], "instance")
            if frame is None:
                frame = _match(name, line, t, timestamps)
            detections.append(Detection(frame, t, box, _coco_label(cls), score, inst))

    labels = {}
    for d in detections:
        labels.setdefault(d.instance, set()).add(d.label)
    objects = []
    name = str(folder / "truth_objects.txt")
    for i, (line, tok) in enumerate(_rows(folder / "truth_objects.txt", name)):
        _check_columns(name, line, tok, (7,), "x y z yaw hx hy hz")
        v = [_number(name, line, t, f) for t, f in zip(tok, "x y z yaw hx hy hz".split())]
        if not all(h > 0 for h in v[4:]):
            raise SequenceFormatError(name, line, "positive half-extents hx hy hz", " ".join(tok[4:]))
        lab = labels.get(i, set())
        label = next(iter(lab)) if len(lab) == 1 else "object"
        objects.append(GroundTruthObject(i, label, Cuboid.from_yaw(v[:3], v[3], v[4:])))

    images = None
    if (folder / "rgb.txt").is_file():
        images = read_images(folder / "rgb.txt", folder)
    priors = Priors(
        [np.array([0.0, 0.0, 1.0, 0.0])], np.array([0.0, 0.0, 1.0]), {}, FR3_TRAJECTORY_SIGMA
    )
    return Sequence(
        folder.name, camera, timestamps, traj[:, 1:], detections, objects, traj.copy(), priors, images
    )


# --- writer ---------------------------------------------------------------------------------


def _f(x) -> str:
    """Shortest round-tripping text of a float."""
    return repr(float(x))


def _yf(x) -> str:
    """A float PyYAML reads back as a float (it needs a dot before an exponent)."""
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


def _write_files(seq: Sequence, out: Path, final: Path) -> None:
    import json

    cam = seq.camera
    (out / "camera.yaml").write_text(
        "".join(f"{k}: {_yf(getattr(cam, k))}\n" for k in _CAMERA_KEYS), encoding="utf-8"
    )
    (out / "trajectory.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw (camera-to-world)\n"
        + _tum_lines(np.column_stack([seq.timestamps, seq.poses_tum])),
        encoding="utf-8",
    )
    lines = ["# timestamp x1 y1 x2 y2 label score [instance]\n"]
    for d in seq.detections:
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
            "# timestamp tx ty tz qx qy qz qw\n" + _tum_lines(seq.groundtruth_tum), encoding="utf-8"
        )
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
        if p.trajectory_sigma is not None:
            text += f"trajectory_sigma: {_ylist(p.trajectory_sigma)}\n"
        (out / "priors.yaml").write_text(text, encoding="utf-8")
    if seq.images is not None:
        lines = ["# timestamp path\n"]
        root = Path(os.path.abspath(final))
        for t, path in sorted(seq.images.items()):
            p = Path(path)
            try:
                rel = Path(os.path.abspath(p)).relative_to(root)
                text = rel.as_posix()
            except ValueError:
                text = os.path.abspath(p)
            if any(c.isspace() for c in text):
                raise ValueError(f"image paths must not contain whitespace, got {text!r}")
            lines.append(f"{_f(t)} {text}\n")
        (out / "rgb.txt").write_text("".join(lines), encoding="utf-8")


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
