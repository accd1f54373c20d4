"""A detector's output folder, laid out as a user gets it from the tools (issue 38):

```
SEQ/
  camera.yaml          # OpenCV (Camera.fx …), ROS camera_info or Kalibr camchain: recognised by content
  trajectory.txt       # TUM, camera-to-world, from any SLAM (ORB-SLAM3's CameraTrajectory.txt renamed)
  rgb.txt              # TUM "timestamp rgb/NAME.png" per image; or mav0/cam0/data.csv (EuRoC
                       #   "timestamp_ns,NAME.png"); without either, NAME itself is the time (s)
  labels/NAME.txt      # Ultralytics YOLO: "class cx cy w h [conf]", normalised to the image size
  coco_results.json    #   … or COCO detection results [{"image_id", "category_id", "bbox": [x, y, w, h], "score"}]
  coco_images.json     #   with their images [{"id", "file_name", "width", "height"}] (or a COCO file with "images")
  data.yaml            # optional class names (Ultralytics: names as a list or {id: name}); default COCO's
  groundtruth.txt, objects_gt.txt, priors.yaml   # optional, as in the OA-SLAM layout
```

Class ids: YOLO's are 0-based indices into ``data.yaml``'s names (default the 80 COCO
classes, ``COCO80``); COCO results use COCO's category ids 1–90 (``COCO_IDS``, 80 of them
used) unless ``coco_images.json`` lists its own ``categories``. A YOLO index of 80 or more
without names, a COCO id of 0 or one COCO does not use is refused: the two numberings are
never mixed up. Names are matched to the class table in lower case with spaces as
underscores (COCO's "dining table" is spdslam's ``dining_table``). Boxes are undistorted
as in the OA-SLAM layout, through the radial-tangential model or an equidistant (fisheye)
lens (``geometry.Equidistant``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..geometry import Camera, Equidistant, undistort_boxes
from ._formats import SequenceFormat
from ._oaslam import COCO80, DEFAULT_MIN_SCORE, estimate_up, read_opencv_camera, read_quadrics_gt
from ._parse import (
    SequenceFormatError,
    check_box,
    check_columns,
    nearest_stamps,
    optional,
    parse_integer,
    parse_number,
    present,
    read_text,
    read_tum,
    required,
    token_rows,
    yaml_line,
    yaml_mapping,
    yaml_number,
    yaml_root,
    yaml_scalar,
    yaml_vector,
)
from ._readers import read_priors
from ._sequence import Detection, Priors, Sequence

__all__ = ["DetectorFolder", "COCO_IDS", "read_camera_calibration", "read_class_names", "read_yolo_labels",
           "read_coco_results", "read_image_times", "import_detector_folder"]

#: COCO's category ids (1–90, with gaps) of the 80 classes, in ``COCO80``'s order.
COCO_IDS = (*range(1, 12), *range(13, 26), 27, 28, *range(31, 45), *range(46, 66), 67, 70,
            *range(72, 83), *range(84, 91))


def class_name(name: str) -> str:
    """A detector's class name as spdslam's class table spells it: lower case, spaces as
    underscores ("dining table" → "dining_table")."""
    return "_".join(str(name).strip().lower().split())


# --- calibrations ---------------------------------------------------------------------------


def _ros_camera_info(name: str, root) -> tuple[Camera, np.ndarray]:
    """ROS ``camera_info`` YAML: image_width, image_height, camera_matrix {rows, cols, data
    (9)}, distortion_model (plumb_bob, rational_polynomial, equidistant),
    distortion_coefficients {data}."""
    items = {k: (kn, v) for k, kn, v in yaml_mapping(name, root, "a ROS camera_info")}
    for key in ("image_width", "image_height", "camera_matrix", "distortion_model"):
        if key not in items:
            raise SequenceFormatError(name, None, f"a ROS camera_info with {key}", "none")

    def data(key, n):
        node = items[key][1]
        sub = {k: v for k, _, v in yaml_mapping(name, node, key)}
        if "data" not in sub:
            raise SequenceFormatError(name, yaml_line(node), f"{key}: data", "none")
        return yaml_vector(name, sub["data"], n, f"{key}.data")

    K = data("camera_matrix", 9)
    model_node = items["distortion_model"][1]
    model = yaml_scalar(model_node)
    sizes = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
    if model not in sizes:
        raise SequenceFormatError(name, yaml_line(model_node),
                                  "distortion_model plumb_bob, rational_polynomial or equidistant", repr(model))
    n = sizes[str(model)]
    d = np.zeros(n)
    if "distortion_coefficients" in items:
        sub = {k: v for k, _, v in yaml_mapping(name, items["distortion_coefficients"][1],
                                                "distortion_coefficients")}
        node = sub.get("data")
        import yaml

        if node is not None and not (isinstance(node, yaml.SequenceNode) and not node.value):  # [] is none
            d = yaml_vector(name, node, n, "distortion_coefficients.data")
            if n == 8 and np.any(d[5:] != 0):
                raise SequenceFormatError(name, yaml_line(node), "rational_polynomial with k4 = k5 = k6 = 0",
                                          f"k4..k6 = {d[5:].tolist()} (not modelled)")
    dist: Any = Equidistant(*(float(v) for v in d)) if model == "equidistant" else d[:5]
    if K[1] != 0 or K[3] != 0 or K[6] != 0 or K[7] != 0 or K[8] != 1:
        raise SequenceFormatError(name, yaml_line(items["camera_matrix"][1]),
                                  "camera_matrix [fx 0 cx 0 fy cy 0 0 1]", str(K.tolist()))
    w = yaml_number(name, items["image_width"][1], "image_width")
    h = yaml_number(name, items["image_height"][1], "image_height")
    return _camera(name, K[0], K[4], K[2], K[5], w, h), dist


def _kalibr(name: str, root) -> tuple[Camera, np.ndarray]:
    """Kalibr ``camchain.yaml``: cam0 {camera_model pinhole, intrinsics [fu fv pu pv],
    distortion_model radtan (coeffs k1 k2 r1 r2) or equidistant (k1 k2 k3 k4), resolution
    [w h]}."""
    cams = {k: v for k, _, v in yaml_mapping(name, root, "a Kalibr camchain")}
    node = cams["cam0"]
    items = {k: v for k, _, v in yaml_mapping(name, node, "cam0")}
    for key in ("intrinsics", "distortion_model", "resolution"):
        if key not in items:
            raise SequenceFormatError(name, yaml_line(node), f"cam0 with {key}", "none")
    model = yaml_scalar(items.get("camera_model")) if "camera_model" in items else "pinhole"
    if model != "pinhole":
        raise SequenceFormatError(name, yaml_line(items["camera_model"]), "camera_model pinhole", repr(model))
    dmodel = yaml_scalar(items["distortion_model"])
    if dmodel not in ("radtan", "equidistant", "none"):
        raise SequenceFormatError(name, yaml_line(items["distortion_model"]), "distortion_model radtan or equidistant",
                                  repr(dmodel))
    fu, fv, pu, pv = yaml_vector(name, items["intrinsics"], 4, "cam0.intrinsics [fu fv pu pv]")
    w, h = yaml_vector(name, items["resolution"], 2, "cam0.resolution [w h]")
    dist: Any = np.zeros(5)
    if dmodel != "none":
        if "distortion_coeffs" not in items:
            raise SequenceFormatError(name, yaml_line(node), "cam0 with distortion_coeffs", "none")
        what = "[k1 k2 r1 r2]" if dmodel == "radtan" else "[k1 k2 k3 k4]"
        c = yaml_vector(name, items["distortion_coeffs"], 4, f"cam0.distortion_coeffs {what}")
        if dmodel == "radtan":
            dist[:4] = c
        else:
            dist = Equidistant(*(float(v) for v in c))
    return _camera(name, fu, fv, pu, pv, w, h), dist


def _camera(name, fx, fy, cx, cy, w, h) -> Camera:
    values = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": w, "height": h}
    for k, v in values.items():
        if not (math.isfinite(v) and v > 0):
            raise SequenceFormatError(name, None, f"a positive {k}", repr(v))
    return Camera(**{k: float(v) for k, v in values.items()})


def read_camera_calibration(path) -> tuple[Camera, np.ndarray]:
    """(pinhole intrinsics, distortion) of a calibration file, its dialect recognised by
    content: OpenCV / ORB-SLAM (``Camera.fx: …``), ROS ``camera_info`` (``camera_matrix``) or
    Kalibr ``camchain`` (``cam0: intrinsics``). The distortion: radial-tangential (k1, k2,
    p1, p2, k3), or a ``geometry.Equidistant`` fisheye lens (ROS and Kalibr
    ``equidistant``)."""
    path = Path(path)
    name = str(path)
    text = read_text(path, name)
    if "Camera.fx" in text:
        return read_opencv_camera(path)
    root = yaml_root(path, name)
    keys = {k for k, _, _ in yaml_mapping(name, root, "a camera calibration")}
    if "camera_matrix" in keys:
        return _ros_camera_info(name, root)
    if "cam0" in keys:
        return _kalibr(name, root)
    raise SequenceFormatError(name, None, "a calibration: OpenCV (Camera.fx: …), ROS camera_info "
                              "(camera_matrix) or Kalibr (cam0: intrinsics)", f"keys {sorted(keys)}")


# --- image times ----------------------------------------------------------------------------


def read_image_times(folder: Path) -> dict | None:
    """{image name without extension: timestamp (s)} from ``rgb.txt`` (TUM: ``timestamp
    path``) or ``mav0/cam0/data.csv`` (EuRoC: ``timestamp_ns,file``); None without either
    (the names are then the times)."""
    if present(folder / "rgb.txt"):
        name = str(folder / "rgb.txt")
        out: dict = {}
        for line, tok in token_rows(folder / "rgb.txt", name):
            check_columns(name, line, tok, (2,), "timestamp rgb/NAME.png")
            stem = Path(tok[1]).stem
            if stem in out:
                raise SequenceFormatError(name, line, "one line per image", f"{tok[1]!r} again")
            out[stem] = parse_number(name, line, tok[0], "timestamp")
        return out
    csv = folder / "mav0" / "cam0" / "data.csv"
    if present(csv):
        name = str(csv)
        out = {}
        for i, raw in enumerate(read_text(csv, name).splitlines(), start=1):
            body = raw.strip()
            if not body or body.startswith("#"):
                continue
            tok = [t.strip() for t in body.split(",")]
            if len(tok) != 2:
                raise SequenceFormatError(name, i, "'timestamp_ns,NAME.png'", repr(body))
            out[Path(tok[1]).stem] = parse_integer(name, i, tok[0], "timestamp [ns]") * 1e-9
        return out
    return None


def _time_of(stem: str, times: dict | None, where: str) -> float:
    if times is not None:
        if stem not in times:
            raise SequenceFormatError(where, None, "an image listed in rgb.txt or mav0/cam0/data.csv",
                                      f"{stem!r}, which is not")
        return float(times[stem])
    try:
        t = float(stem)
    except ValueError:
        raise SequenceFormatError(where, None, "an image named by its timestamp (s), or rgb.txt / "
                                  "mav0/cam0/data.csv to give the times", repr(stem)) from None
    if not math.isfinite(t):
        raise SequenceFormatError(where, None, "a finite timestamp", repr(stem))
    return t


# --- detections -----------------------------------------------------------------------------


def read_class_names(folder: Path) -> tuple[str, ...] | None:
    """Ultralytics' ``data.yaml`` ``names`` (a list, or {id: name} with ids 0 … n−1), or None."""
    p = optional(folder, "data.yaml")
    if p is None:
        return None
    import yaml

    name = str(p)
    items = {k: v for k, _, v in yaml_mapping(name, yaml_root(p, name), "data.yaml")}
    if "names" not in items:
        raise SequenceFormatError(name, None, "data.yaml with names", "none")
    node = items["names"]
    if isinstance(node, yaml.SequenceNode):
        return tuple(class_name(yaml_scalar(v)) for v in node.value)
    if isinstance(node, yaml.MappingNode):
        pairs = {}
        for k, v in node.value:
            key = yaml_scalar(k)
            if isinstance(key, bool) or not isinstance(key, int) or key < 0:
                raise SequenceFormatError(name, yaml_line(k), "class ids 0, 1, … as names' keys", repr(key))
            pairs[key] = class_name(yaml_scalar(v))
        if sorted(pairs) != list(range(len(pairs))):
            raise SequenceFormatError(name, yaml_line(node), "names with ids 0 … n−1", str(sorted(pairs)))
        return tuple(pairs[k] for k in range(len(pairs)))
    raise SequenceFormatError(name, yaml_line(node), "names as a list or a mapping", "a scalar")


def read_yolo_labels(folder: Path, camera: Camera, names, times: dict | None,
                     min_score: float) -> list:
    """(timestamp, box [x1 y1 x2 y2] px, label, score) of every ``labels/NAME.txt`` line
    ``class cx cy w h [conf]`` (normalised to the image; conf 1 when absent) at or above
    ``min_score``."""
    out = []
    default = names is None
    names = COCO80 if names is None else names
    W, H = camera.width, camera.height
    for p in sorted((folder / "labels").glob("*.txt")):
        name = str(p)
        t = _time_of(p.stem, times, name)
        for line, tok in token_rows(p, name):
            check_columns(name, line, tok, (5, 6), "class cx cy w h [conf]")
            k = parse_integer(name, line, tok[0], "class")
            if not 0 <= k < len(names):
                hint = " (a COCO category id? YOLO numbers the 80 classes 0-79)" if default and k < 91 else ""
                raise SequenceFormatError(name, line, f"a class index in 0…{len(names) - 1}{hint}", str(k))
            cx, cy, w, h = (parse_number(name, line, v, f) for v, f in zip(tok[1:5], ("cx", "cy", "w", "h")))
            if not (0 <= cx <= 1 and 0 <= cy <= 1 and 0 < w <= 1 and 0 < h <= 1):
                raise SequenceFormatError(name, line, "cx cy w h normalised to the image (in [0, 1], w h > 0)",
                                          " ".join(tok[1:5]))
            s = parse_number(name, line, tok[5], "conf") if len(tok) == 6 else 1.0
            if not 0 <= s <= 1:
                raise SequenceFormatError(name, line, "a confidence in [0, 1]", tok[5])
            if s < min_score:
                continue
            box = np.array([(cx - w / 2) * W, (cy - h / 2) * H, (cx + w / 2) * W, (cy + h / 2) * H])
            out.append((t, box, names[k], s))
    return out


def _json(path: Path):
    name = str(path)
    try:
        return json.loads(read_text(path, name))
    except json.JSONDecodeError as e:
        raise SequenceFormatError(name, e.lineno, "valid JSON", e.msg) from None


def read_coco_results(folder: Path, camera: Camera, times: dict | None, min_score: float) -> list:
    """(timestamp, box px, label, score) of COCO detection results (``coco_results.json``:
    [{image_id, category_id, bbox [x, y, w, h], score}]) with their images
    (``coco_images.json``: a list, or a COCO file with ``images``; its ``categories`` name the
    ids, else COCO's own 1–90)."""
    res_path = folder / "coco_results.json"
    img_path = required(folder, "coco_images.json")
    results, images = _json(res_path), _json(img_path)
    rname, iname = str(res_path), str(img_path)
    cats = None
    if isinstance(images, dict):
        cats = images.get("categories")
        images = images.get("images")
    if not isinstance(images, list):
        raise SequenceFormatError(iname, None, "a list of images (or a COCO file with 'images')",
                                  type(images).__name__)
    by_id = {}
    for i, im in enumerate(images):
        where = f"{iname}[{i}]"
        if not (isinstance(im, dict) and isinstance(im.get("id"), int) and isinstance(im.get("file_name"), str)):
            raise SequenceFormatError(where, None, "an image {id, file_name, width, height}", repr(im)[:80])
        wh = (im.get("width"), im.get("height"))
        sizes = [float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None for v in wh]
        if wh != (None, None) and sizes != [camera.width, camera.height]:
            raise SequenceFormatError(where, None, f"the calibration's image size {camera.width:g}×{camera.height:g}",
                                      f"{wh[0]}×{wh[1]}")
        by_id[im["id"]] = _time_of(Path(im["file_name"]).stem, times, where)
    if cats is not None:
        if not isinstance(cats, list) or not all(isinstance(c, dict) and isinstance(c.get("id"), int)
                                                 and isinstance(c.get("name"), str) for c in cats):
            raise SequenceFormatError(iname, None, "categories [{id, name}]", repr(cats)[:80])
        names = {c["id"]: class_name(c["name"]) for c in cats}
    else:
        names = dict(zip(COCO_IDS, COCO80))
    if not isinstance(results, list):
        raise SequenceFormatError(rname, None, "a JSON list of detections", type(results).__name__)
    out = []
    for i, r in enumerate(results):
        where = f"{rname}[{i}]"
        if not isinstance(r, dict) or not {"image_id", "category_id", "bbox", "score"} <= set(r):
            raise SequenceFormatError(where, None, "a detection {image_id, category_id, bbox, score}", repr(r)[:80])
        k = r["category_id"]
        if isinstance(k, bool) or not isinstance(k, int) or k not in names:
            hint = " (0 is a YOLO index: COCO numbers its categories from 1)" if k == 0 and cats is None else ""
            raise SequenceFormatError(where, None, f"a category_id of {'the categories' if cats else 'COCO (1-90)'}"
                                      + hint, repr(k))
        if r["image_id"] not in by_id:
            raise SequenceFormatError(where, None, "an image_id of coco_images.json", repr(r["image_id"]))
        b, s = r["bbox"], r["score"]
        if not (isinstance(b, list) and len(b) == 4 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                           and math.isfinite(v) for v in b) and b[2] > 0 and b[3] > 0):
            raise SequenceFormatError(where, None, "bbox [x, y, w, h] with w, h > 0 (pixels)", repr(b)[:80])
        if isinstance(s, bool) or not isinstance(s, (int, float)) or not 0 <= s <= 1:
            raise SequenceFormatError(where, None, "a score in [0, 1]", repr(s))
        if s < min_score:
            continue
        box = np.array([b[0], b[1], b[0] + b[2], b[1] + b[3]], float)
        check_box(where, None, box, camera)
        out.append((by_id[r["image_id"]], box, names[k], float(s)))
    return out


# --- the folder -----------------------------------------------------------------------------


def _has_detections(folder: Path) -> bool:
    return (folder / "labels").is_dir() or present(folder / "coco_results.json")


def import_detector_folder(folder, min_score: float = DEFAULT_MIN_SCORE, undistort: bool = True) -> Sequence:
    """A detector's output folder (module docstring) as a :class:`Sequence`: detections of
    images without a pose within 0.02 s are left out; boxes undistorted (``undistort``);
    ``priors.yaml``, ``groundtruth.txt`` and ``objects_gt.txt`` read when present; ``up``
    estimated from the cameras (``estimate_up``) unless the priors give it."""
    folder = Path(folder)
    if not (math.isfinite(min_score) and 0 <= min_score <= 1):
        raise ValueError(f"min_score must be in [0, 1], got {min_score!r}")
    camera, dist = read_camera_calibration(required(folder, "camera.yaml"))
    traj = read_tum(required(folder, "trajectory.txt"), str(folder / "trajectory.txt"))
    times = read_image_times(folder)
    yolo, coco = (folder / "labels").is_dir(), present(folder / "coco_results.json")
    if yolo and coco:
        raise SequenceFormatError(folder, None, "one detector output: labels/ or coco_results.json", "both")
    if yolo:
        raw = read_yolo_labels(folder, camera, read_class_names(folder), times, min_score)
    else:
        raw = read_coco_results(folder, camera, times, min_score)
    raw.sort(key=lambda r: r[0])
    timestamps = traj[:, 0]
    detections = []
    if raw:
        t = np.array([r[0] for r in raw])
        near, ok = nearest_stamps(timestamps, t)
        boxes = np.stack([r[1] for r in raw])
        if undistort and np.any(dist):
            boxes = undistort_boxes(boxes, camera, dist)
        bad = ~np.all(np.isfinite(boxes), axis=1) | ~(boxes[:, 2] > boxes[:, 0]) | ~(boxes[:, 3] > boxes[:, 1])
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SequenceFormatError(folder, None, "boxes whose undistorted outline is a finite box of positive area",
                                      f"{[float(v) for v in raw[i][1]]} of the image at {raw[i][0]!r}")
        for k in np.flatnonzero(ok):
            detections.append(Detection(int(near[k]), float(t[k]), boxes[k], raw[k][2], float(raw[k][3])))
    objects = read_quadrics_gt(folder / "objects_gt.txt") if optional(folder, "objects_gt.txt") else None
    gt = read_tum(folder / "groundtruth.txt", str(folder / "groundtruth.txt"), skip_repeats=True) \
        if optional(folder, "groundtruth.txt") else None
    priors = read_priors(folder / "priors.yaml") if optional(folder, "priors.yaml") else Priors([], None, {})
    if priors.up is None:
        try:
            priors = priors.replace(up=estimate_up(traj[:, 1:]))
        except ValueError as e:
            raise SequenceFormatError(folder, None, "an up direction (priors.yaml) or cameras "
                                      "that turn about the vertical", str(e)) from None
    return Sequence(folder.name, camera, timestamps, traj[:, 1:], detections, objects, gt, priors)


class DetectorFolder(SequenceFormat):
    """A detector's output folder: YOLO label files or COCO results beside a calibration and a
    SLAM trajectory (module docstring, ``import_detector_folder``)."""

    name = "detector"
    title = "a detector's output folder"
    layout = "labels/*.txt (YOLO) or coco_results.json, beside camera.yaml and trajectory.txt"
    docs = "A detector's output folder: YOLO labels or COCO results"
    options = {
        "min_score": f"leave out detections scored below this (default {DEFAULT_MIN_SCORE:g})",
        "undistort": "replace each box by the pinhole box of its undistorted outline (default true)",
    }

    @classmethod
    def claims(cls, path: Path) -> bool:
        return path.is_dir() and _has_detections(path)

    @classmethod
    def read(cls, path: Path, **options) -> Sequence:
        return import_detector_folder(path, **options)

    @classmethod
    def read_measured(cls, path: Path):
        _, dist = read_camera_calibration(Path(path) / "camera.yaml")
        if not np.any(dist):
            return None
        return import_detector_folder(path, undistort=False), dist
