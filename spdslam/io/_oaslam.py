"""The OA-SLAM-style layout of real recordings (e.g. ``tum_fr2_desk``):

- ``detections*.json``: OA-SLAM's detection file, a list of ``{"file_name": "<timestamp>.png",
  "detections": [{"category_id": k, "detection_score": s, "bbox": [x1, y1, x2, y2]}]}``, k a
  0-indexed COCO-80 class, boxes in pixels of the (distorted) image, no instance ids;
- a camera YAML in OpenCV / ORB-SLAM style (``Camera.fx: …``, ``Camera.k1 k2 p1 p2 k3``,
  ``Camera.width/height``);
- TUM trajectories: the odometry (``odometry.txt`` or ``*orb*.txt``, the visual SLAM's
  camera-to-world poses) and ``groundtruth.txt`` (motion capture, gaps allowed);
- ``objects_gt.txt``: gtsam-quadrics-style ground-truth ellipsoids
  ``name roll pitch yaw cx cy cz r1 r2 r3 coco`` (degrees, R = Rz(yaw)Ry(pitch)Rx(roll), semi-
  axes along R's columns, ``coco`` = ``<id>:<name>`` of the class the detector reports, ``-:none``
  for none); evaluated as their circumscribed cuboids.

Boxes are undistorted (``geometry.undistort_boxes``) so that the sequence is a pinhole one. The
mapping never reads ground truth; it stays in its own (motion-capture) frame, and the
evaluation aligns the trajectory to it (``evaluation.to_groundtruth``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import Camera, Cuboid, undistort_boxes
from ._formats import SequenceFormat
from ._parse import (
    CAMERA_KEYS,
    SequenceFormatError,
    box_faults,
    camera_from,
    check_box,
    nearest_stamps,
    optional,
    parse_number,
    read_text,
    read_tum,
    required,
    token_rows,
)
from ._readers import read_priors
from ._sequence import Detection, GroundTruthObject, Priors, Sequence

__all__ = ["OASlamFolder", "COCO80", "is_oaslam_layout", "import_oaslam", "read_opencv_camera",
           "read_detections_json", "read_quadrics_gt", "estimate_up"]

#: The 80 COCO classes in YOLO's 0-indexed order.
COCO80 = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic_light", "fire_hydrant", "stop_sign", "parking_meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports_ball", "kite",
    "baseball_bat", "baseball_glove", "skateboard", "surfboard", "tennis_racket", "bottle",
    "wine_glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich",
    "orange", "broccoli", "carrot", "hot_dog", "pizza", "donut", "cake", "chair", "couch",
    "potted_plant", "bed", "dining_table", "toilet", "tv", "laptop", "mouse", "remote",
    "keyboard", "cell_phone", "microwave", "oven", "toaster", "sink", "refrigerator", "book",
    "clock", "vase", "scissors", "teddy_bear", "hair_drier", "toothbrush",
)

DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")
#: Detections below this score are left out by default (YOLO's usual deployment threshold).
DEFAULT_MIN_SCORE = 0.5
#: σ of the trajectory's motion per frame step (m, rad) when it is the motion capture (as
#: the fr3_cabinet importer), unless priors.yaml gives one. A visual SLAM's trajectory states
#: none: the back end estimates it from the trajectory's jitter (``mapping._noise``).
GROUNDTRUTH_SIGMA = (1e-4, 1e-4)


def _json_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.glob("detections*.json") if p.is_file())


def _odometry_files(folder: Path) -> list[Path]:
    c = [folder / "odometry.txt"] + sorted(folder.glob("*orb*.txt")) + sorted(folder.glob("*ORB*.txt"))
    seen, out = set(), []
    for p in c:
        if p.is_file() and p not in seen:
            seen.add(p)
            out.append(p)
    return out


def _camera_files(folder: Path) -> list[Path]:
    out = []
    for p in sorted(folder.glob("*.yaml")):
        if p.name in ("camera.yaml", "priors.yaml") or not p.is_file():
            continue
        try:
            head = p.read_text(encoding="utf-8", errors="replace")[:4096]
        except OSError:
            continue
        if "Camera.fx" in head:
            out.append(p)
    return out


def is_oaslam_layout(folder) -> bool:
    """True for a folder with a ``detections*.json`` (``OASlamFolder.claims``)."""
    return OASlamFolder.claims(Path(folder))


def read_opencv_camera(path: Path) -> tuple[Camera, np.ndarray]:
    """(pinhole intrinsics, distortion (k1, k2, p1, p2, k3)) of ``Camera.<key>: <number>``
    lines (``%YAML:1.0`` header; 640×480 and no distortion unless given)."""
    name = str(path)
    values, lines = {}, {}
    for line, tok in token_rows(path, name):
        body = " ".join(tok)
        if not body.startswith("Camera."):
            continue
        key, sep, val = body[len("Camera."):].partition(":")
        key = key.strip()
        if key not in CAMERA_KEYS and key not in DISTORTION_KEYS:
            continue
        if not sep or not val.strip():
            raise SequenceFormatError(name, line, f"'Camera.{key}: <number>'", repr(body))
        values[key] = parse_number(name, line, val.strip(), f"Camera.{key}")
        lines[key] = line
    values.setdefault("width", 640.0)
    values.setdefault("height", 480.0)
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in values]
    if missing:
        raise SequenceFormatError(
            name, None, "lines Camera.fx, Camera.fy, Camera.cx, Camera.cy",
            f"{', '.join('Camera.' + k for k in missing)} missing",
        )
    dist = np.array([values.pop(k, 0.0) for k in DISTORTION_KEYS])
    for k in DISTORTION_KEYS:
        lines.pop(k, None)
    return camera_from(name, values, lines), dist


def read_detections_json(path: Path, min_score: float = DEFAULT_MIN_SCORE,
                         camera: Camera | None = None):
    """[(timestamp, box (4,), label, score)] of an OA-SLAM detection file, scores ≥
    ``min_score``; errors name the entry (``<file>: entry <i>``); every box of positive
    area and, with ``camera``, overlapping its (distorted) image (``check_box``). The
    detections are checked as arrays; when any fails they are checked one by one, so the
    error is the first in the file."""
    name = str(path)
    try:
        data = json.loads(read_text(path, name))
    except json.JSONDecodeError as e:
        raise SequenceFormatError(name, e.lineno, "valid JSON", e.msg) from None
    if not isinstance(data, list):
        raise SequenceFormatError(name, None, "a JSON list of images", type(data).__name__)
    times: list[float] = []
    labels: list = []
    scores: list[float] = []
    boxes: list = []
    at: list[tuple[int, int]] = []

    def check_so_far():
        """The detections read so far, each checked alone: an earlier one's error comes
        first, as in the file."""
        return [_detection(f"{name}: entry {i} detection {j}", data[i]["detections"][j], camera)[2] for i, j in at]

    for i, entry in enumerate(data):
        try:
            t, detections = _entry(f"{name}: entry {i}", entry)
            for j, d in enumerate(detections):
                try:
                    k, s, b = d["category_id"], float(d["detection_score"]), d["bbox"]
                except (KeyError, TypeError, ValueError):
                    _detection(f"{name}: entry {i} detection {j}", d, camera)  # raises
                times.append(t)
                labels.append(k)
                scores.append(s)
                boxes.append(b)
                at.append((i, j))
        except SequenceFormatError:
            check_so_far()
            raise
    if not boxes:
        return []
    # the boxes, labels and scores checked as arrays; the first detection that fails is
    # checked alone (``_detection``) for its error
    try:
        B = np.array(boxes, dtype=float).reshape(len(boxes), 4)
        K = np.array(labels)
        ok = (K.dtype.kind == "i" and bool(np.all((K >= 0) & (K < len(COCO80))))
              and bool(np.all(np.isfinite(B))) and bool(np.all(np.isfinite(scores)))
              and not np.any(box_faults(B, camera)))
    except (ValueError, TypeError):
        ok = False
    if not ok:
        B = np.stack(check_so_far())
    keep = np.asarray(scores, dtype=float) >= min_score
    return [(t, b, COCO80[k], s) for t, b, k, s, u in zip(times, B, labels, scores, keep) if u]


def _entry(where: str, entry):
    """(timestamp, detections) of one image entry, checked; else ``SequenceFormatError``."""
    if not isinstance(entry, dict) or "file_name" not in entry or "detections" not in entry:
        raise SequenceFormatError(where, None, "an object with 'file_name' and 'detections'", repr(entry)[:80])
    stem = Path(str(entry["file_name"])).stem
    try:
        t = float(stem)
    except ValueError:
        t = math.nan
    if not math.isfinite(t):
        raise SequenceFormatError(where, None, "a file_name '<timestamp>.png'", repr(entry["file_name"]))
    if not isinstance(entry["detections"], list):
        raise SequenceFormatError(where, None, "a list of detections", repr(entry["detections"])[:80])
    return t, entry["detections"]


def _detection(where: str, d, camera: Camera | None):
    """(category id, score, box (4,)) of one detection, each checked; else
    ``SequenceFormatError`` at ``where``."""
    try:
        k = d["category_id"]
        s = float(d["detection_score"])
        b = np.asarray(d["bbox"], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise SequenceFormatError(where, None, "category_id, detection_score and bbox [x1, y1, x2, y2]",
                                  repr(d)[:80]) from None
    if not (isinstance(k, int) and 0 <= k < len(COCO80)):
        raise SequenceFormatError(where, None, "a COCO-80 category_id in 0…79", repr(k))
    if b.shape != (4,) or not np.all(np.isfinite(b)) or not math.isfinite(s):
        raise SequenceFormatError(where, None, "a finite bbox [x1, y1, x2, y2] and score", repr(d.get("bbox")))
    check_box(where, None, b, camera)
    return k, s, b


def read_quadrics_gt(path: Path) -> list[GroundTruthObject]:
    """Ground-truth ellipsoids ``name roll pitch yaw cx cy cz r1 r2 r3 [coco]`` as the
    circumscribed cuboids; the label is the ``coco`` class name when given (the detector's
    name for the object), else ``name``."""
    name = str(path)
    layout = "name roll pitch yaw cx cy cz r1 r2 r3 [coco]"
    out = []
    for i, (line, tok) in enumerate(token_rows(path, name)):
        if len(tok) not in (10, 11):
            raise SequenceFormatError(name, line, f"10 or 11 columns '{layout}'", f"{len(tok)} columns")
        v = [parse_number(name, line, t, f) for t, f in zip(tok[1:10], layout.split()[1:10])]
        if not all(r > 0 for r in v[6:9]):
            raise SequenceFormatError(name, line, "positive semi-axes r1 r2 r3", " ".join(tok[7:10]))
        R = Rotation.from_euler("ZYX", [v[2], v[1], v[0]], degrees=True).as_matrix()
        label = tok[0]
        if len(tok) == 11:
            k, _, cname = tok[10].partition(":")
            if k != "-":
                label = cname or tok[0]
        out.append(GroundTruthObject(i, label, Cuboid(np.array(v[3:6]), R, np.array(v[6:9]))))
    return out


def _one(files: list[Path], folder: Path, what: str) -> Path:
    if len(files) != 1:
        got = "none" if not files else ", ".join(p.name for p in files)
        raise SequenceFormatError(folder, None, f"exactly one {what}", got)
    return files[0]


def estimate_up(poses_tum: np.ndarray) -> np.ndarray:
    """The world's up direction from camera-to-world poses carried without roll: their x
    axes are horizontal, so up is the direction most orthogonal to all of them (the
    smallest right singular vector of the stacked x axes), signed so that the image's
    down (+y) points against it on average. Needs x axes spanning a plane (a camera that
    turns about the vertical); raises ``ValueError`` otherwise."""
    R = Rotation.from_quat(np.asarray(poses_tum)[:, 3:7]).as_matrix()
    x = R[:, :, 0]
    # Vt 3×3 for any number of poses; U only as wide as needed (not N×N)
    _, sv, Vt = np.linalg.svd(x, full_matrices=len(x) < 3)
    if sv.size < 2 or not sv[1] > 0.05 * sv[0]:
        raise ValueError("the cameras' x axes do not span a plane: the up direction is not "
                         "determined (give up in priors.yaml)")
    up = Vt[2]
    if np.mean(R[:, :, 1] @ up) > 0:
        up = -up
    return up


def import_oaslam(folder, trajectory: str = "odometry", min_score: float = DEFAULT_MIN_SCORE,
                  undistort: bool = True) -> Sequence:
    """The OA-SLAM-style layout (module docstring) as a :class:`Sequence`.

    ``trajectory``: "odometry" (the visual SLAM's poses, as the paper) or "groundtruth" (the
    ground-truth poses nearest to the images with detections).
    Detections of frames without a pose within 0.02 s are left out; boxes are undistorted;
    ``priors.yaml`` is read when present; ``up`` is estimated from the cameras
    (``estimate_up``) and, for the ground-truth trajectory, ``trajectory_sigma`` is
    ``GROUNDTRUTH_SIGMA`` unless it gives one. ``undistort=False`` keeps the measured boxes
    (to measure what the distortion does). The ground truth (trajectory and objects) stays
    in its own frame: the evaluation aligns the trajectory to it
    (``evaluation.to_groundtruth``)."""
    folder = Path(folder)
    if trajectory not in ("odometry", "groundtruth"):
        raise ValueError(f"trajectory must be 'odometry' or 'groundtruth', got {trajectory!r}")
    camera, dist = read_opencv_camera(_one(_camera_files(folder), folder,
                                           "camera YAML with Camera.fx lines"))
    gt = None
    if optional(folder, "groundtruth.txt"):
        gt = read_tum(folder / "groundtruth.txt", str(folder / "groundtruth.txt"), skip_repeats=True)
    if trajectory == "odometry":
        path = _one(_odometry_files(folder), folder, "odometry trajectory (odometry.txt or *orb*.txt)")
        traj = read_tum(path, str(path))
    else:
        traj = read_tum(required(folder, "groundtruth.txt"), str(folder / "groundtruth.txt"),
                        skip_repeats=True)
    json_path = _one(_json_files(folder), folder, "detections*.json")
    raw = read_detections_json(json_path, min_score, camera)
    if trajectory == "groundtruth" and raw:
        # the motion capture runs at 100 Hz: the camera's frames are the poses nearest to
        # the images (those with a detection), within the matching tolerance
        near, ok = nearest_stamps(traj[:, 0], np.array([r[0] for r in raw]))
        traj = traj[np.unique(near[ok])]
    timestamps = traj[:, 0]
    detections = []
    if raw:
        t = np.array([r[0] for r in raw])
        near, ok = nearest_stamps(timestamps, t)
        boxes = undistort_boxes(np.stack([r[1] for r in raw]), camera, dist) if undistort and np.any(dist) \
            else np.stack([r[1] for r in raw])
        bad = ~np.all(np.isfinite(boxes), axis=1) | ~(boxes[:, 2] > boxes[:, 0]) | ~(boxes[:, 3] > boxes[:, 1])
        if bad.any():  # a corner far outside the image, where the lens model diverges
            i = int(np.flatnonzero(bad)[0])
            raise SequenceFormatError(
                json_path, None, "boxes whose undistorted outline is a finite box of positive area",
                f"bbox {[float(v) for v in raw[i][1]]} of the image at {raw[i][0]!r}")
        for k in np.flatnonzero(ok):
            detections.append(Detection(int(near[k]), float(t[k]), boxes[k], raw[k][2], float(raw[k][3])))
    objects = read_quadrics_gt(folder / "objects_gt.txt") if optional(folder, "objects_gt.txt") else None
    priors = read_priors(folder / "priors.yaml") if optional(folder, "priors.yaml") else None
    if priors is None:
        priors = Priors([], None, {})
    if priors.trajectory_sigma is None and trajectory == "groundtruth":
        priors = priors.replace(trajectory_sigma=GROUNDTRUTH_SIGMA)
    if priors.up is None:
        try:
            up = estimate_up(traj[:, 1:])
        except ValueError as e:
            raise SequenceFormatError(folder, None, "an up direction (priors.yaml) or cameras "
                                      "that turn about the vertical", str(e)) from None
        priors = priors.replace(up=up)
    return Sequence(folder.name, camera, timestamps, traj[:, 1:], detections, objects, gt, priors)


class OASlamFolder(SequenceFormat):
    """The OA-SLAM-style layout of real recordings (module docstring, ``import_oaslam``)."""

    name = "oaslam"
    title = "an OA-SLAM-style folder"
    layout = "a detections*.json, beside a camera YAML and TUM trajectories"
    docs = "The OA-SLAM layout: real recordings"
    options = {
        "trajectory": "the poses to map with: odometry (the visual SLAM's, default) or groundtruth",
        "min_score": f"leave out detections scored below this (default {DEFAULT_MIN_SCORE:g})",
        "undistort": "replace each box by the pinhole box of its undistorted outline (default true)",
    }

    @classmethod
    def claims(cls, path: Path) -> bool:
        return path.is_dir() and bool(_json_files(path))

    @classmethod
    def read(cls, path: Path, **options) -> Sequence:
        return import_oaslam(path, **options)

    @classmethod
    def read_measured(cls, path: Path):
        cams = _camera_files(Path(path))
        if len(cams) != 1:
            return None
        _, dist = read_opencv_camera(cams[0])
        if not np.any(dist):
            return None
        return import_oaslam(path, undistort=False), dist

