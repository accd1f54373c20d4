"""Importer of ROS 2 bags (a rosbag2 folder with ``metadata.yaml``, or one ``.mcap`` /
``.db3`` file), read with the optional ``rosbags`` library (``pip install "spdslam[ros]"``):

- the camera from ``sensor_msgs/msg/CameraInfo``: K (fx = K[0], fy = K[4], cx = K[2],
  cy = K[5]), width, height and the distortion D (``plumb_bob`` k1 k2 p1 p2 k3;
  ``rational_polynomial`` k1 k2 p1 p2 k3 k4 k5 k6 with k4 = k5 = k6 = 0);
- the detections from ``vision_msgs/msg/Detection2DArray`` (vision_msgs 4.x, or the
  definitions stored in the bag): bbox centre and size → ``[x1, y1, x2, y2]`` (a rotated box:
  its axis-aligned bounding box), the best-scored hypothesis → label and score, ``id`` →
  instance when it is an integer;
- the camera trajectory T_wc (camera-to-world, TUM rows ``t tx ty tz qx qy qz qw``) from
  ``geometry_msgs/msg/PoseStamped``, ``nav_msgs/msg/Odometry`` (the pose of the camera's
  optical frame: z forward, x right, y down) or ``tf2_msgs/msg/TFMessage`` (``/tf`` and
  ``/tf_static``: the chain from the world frame to the camera frame, interpolated at the
  detections' timestamps).

A message's time is its ``header.stamp``, or the bag's record time when the stamp is zero.
Every malformed input is a one-line ``SequenceFormatError`` ``"<bag>: topic <t>: expected …,
got …"``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import cast

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import Camera, undistort_boxes
from ..geometry.se3 import interpolate_tum
from ._formats import SequenceFormat
from ._oaslam import DEFAULT_MIN_SCORE, estimate_up
from ._parse import MATCH_TOLERANCE, SequenceFormatError, check_box, nearest_stamps, unit_quaternion
from ._sequence import Detection, Priors, Sequence

__all__ = [
    "CAMERA_INFO",
    "DETECTIONS",
    "POSE_TYPES",
    "VISION_MSGS_DEFINITIONS",
    "import_rosbag",
    "is_rosbag",
]

CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
DETECTIONS = "vision_msgs/msg/Detection2DArray"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
#: The message types a trajectory is read from.
POSE_TYPES = (POSE_STAMPED, ODOMETRY, TF_MESSAGE)

#: The vision_msgs 4.x (ROS 2 Humble, Jazzy) definitions the detections are decoded with
#: when the bag stores none (rosbags ships no vision_msgs).
VISION_MSGS_DEFINITIONS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"),
    "vision_msgs/msg/Detection2D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
        "vision_msgs/BoundingBox2D bbox\nstring id\n"),
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n",
}

_BAG_SUFFIXES = (".mcap", ".db3")
_SHOWN_TOPICS = 8  # topics named in an error message


def is_rosbag(path) -> bool:
    """True for a rosbag2 folder (``metadata.yaml`` present) or a ``.mcap`` / ``.db3`` file."""
    return RosBag2.claims(Path(path))


# --- reading the bag ------------------------------------------------------------------------


def _typestore(bag: str, connections):
    """A typestore with ROS 2 Humble's types, vision_msgs 4.x, and over them the
    definitions stored in the bag (an empty or unreadable stored definition is skipped)."""
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.typesys import (
        Stores,
        get_types_from_idl,
        get_types_from_msg,
        get_typestore,
    )

    typs = dict(get_typestore(Stores.ROS2_HUMBLE).fielddefs)
    for name, text in VISION_MSGS_DEFINITIONS.items():
        typs.update(get_types_from_msg(text, name))
    sep = "=" * 80 + "\n"
    for c in connections:
        fmt, data = c.msgdef.format, c.msgdef.data
        if fmt == MessageDefinitionFormat.NONE or not data.strip():
            continue
        try:
            if fmt == MessageDefinitionFormat.MSG:
                found = get_types_from_msg(data, c.msgtype)
            else:
                found = {}
                parts = data.split(sep)[1:] if data.startswith(sep + "IDL: ") else [data]
                for part in parts:
                    found.update(get_types_from_idl(part.split("\n", 1)[1] if part.startswith("IDL: ") else part))
        except Exception:  # noqa: BLE001, S112 - a definition rosbags cannot parse: the built-in one
            continue
        typs.update(found)
    store = get_typestore(Stores.EMPTY)
    try:
        store.register(typs)
    except Exception as e:  # noqa: BLE001 - rosbags' TypesysError and code generation errors
        raise SequenceFormatError(bag, None, "message definitions rosbags can read",
                                  f"{type(e).__name__}: {e}") from None
    return store


def _open(path: Path, bag: str):
    try:
        from rosbags.rosbag2 import Reader
    except ImportError:
        raise SequenceFormatError(bag, None, "the rosbags library to read a ROS 2 bag "
                                  "(pip install \"spdslam[ros]\")", "it is not installed") from None
    if not path.exists():
        raise SequenceFormatError(bag, None, "a ROS 2 bag (a folder with metadata.yaml, or a .mcap or "
                                  ".db3 file)", "no such file or folder")
    if not is_rosbag(path):
        got = "a folder without metadata.yaml" if path.is_dir() else f"a file named {path.name!r}"
        raise SequenceFormatError(bag, None, "a ROS 2 bag (a folder with metadata.yaml, or a .mcap or "
                                  ".db3 file)", got)
    try:
        reader = Reader(path)
        reader.open()
    except Exception as e:  # noqa: BLE001 - ReaderError, sqlite3/OSError, YAML errors, …
        raise SequenceFormatError(bag, None, "a readable ROS 2 bag", _why(e)) from None
    return reader


def _why(e: Exception) -> str:
    return f"{type(e).__name__}: {e}" if str(e) else type(e).__name__


def _show_topics(topics: dict) -> str:
    items = [f"{t} [{ty}]" for t, ty in sorted(topics.items())]
    if not items:
        return "no topics"
    more = f", … ({len(items) - _SHOWN_TOPICS} more)" if len(items) > _SHOWN_TOPICS else ""
    return ", ".join(items[:_SHOWN_TOPICS]) + more


def _topic_types(reader) -> dict:
    """{topic: message type} (the types of a topic recorded with several joined by ' or ')."""
    out: dict[str, str] = {}
    for c in reader.connections:
        have = out.get(c.topic)
        if have is None:
            out[c.topic] = c.msgtype
        elif c.msgtype not in have.split(" or "):
            out[c.topic] = f"{have} or {c.msgtype}"
    return out


def _choose(bag: str, topics: dict, given: str | None, types: tuple, option: str, what: str) -> str:
    """The topic named ``given`` (which must have one of ``types``), else the single topic
    of one of ``types``."""
    want = " or ".join(types)
    if given is not None:
        if given not in topics:
            raise SequenceFormatError(f"{bag}: topic {given}", None, f"a {want} topic of the bag",
                                      f"no such topic (the bag has {_show_topics(topics)})")
        if topics[given] not in types:
            raise SequenceFormatError(f"{bag}: topic {given}", None, f"a {want} topic", topics[given])
        return given
    cands = sorted(t for t, ty in topics.items() if ty in types and t != "/tf_static")
    if len(cands) != 1:
        got = (f"none (the bag has {_show_topics(topics)})" if not cands
               else f"{len(cands)}: {', '.join(cands)} (choose one with {option})")
        raise SequenceFormatError(bag, None, f"one {want} topic for {what}", got)
    return cands[0]


def _messages(reader, store, bag: str, topic: str, required: bool = True):
    """[(time s, message)] of ``topic`` in record order; the time is the header stamp when
    the message has a non-zero one, else the record time."""
    conns = [c for c in reader.connections if c.topic == topic]
    out: list = []
    where = f"{bag}: topic {topic}"
    try:
        for conn, t_ns, raw in reader.messages(connections=conns):
            try:
                msg = store.deserialize_cdr(raw, conn.msgtype)
            except Exception as e:  # noqa: BLE001 - rosbags' SerdeError, struct errors
                raise SequenceFormatError(where, None, f"messages that decode as {conn.msgtype}",
                                          f"message {len(out)}: {_why(e)}") from None
            out.append((_stamp(getattr(msg, "header", None), t_ns), msg))
    except SequenceFormatError:
        raise
    except Exception as e:  # noqa: BLE001 - a damaged storage file
        raise SequenceFormatError(where, None, "readable messages", _why(e)) from None
    if required and not out:
        raise SequenceFormatError(where, None, "at least one message", "an empty topic")
    return out


def _stamp(header, t_ns: int) -> float:
    if header is not None:
        s = getattr(header, "stamp", None)
        if s is not None and (s.sec or s.nanosec):
            return float(s.sec) + 1e-9 * float(s.nanosec)
    return 1e-9 * float(t_ns)


# --- camera, detections, poses --------------------------------------------------------------


def _camera(bag: str, topic: str, msgs) -> tuple[Camera, np.ndarray, str]:
    """(pinhole intrinsics, distortion (k1, k2, p1, p2, k3), frame id) of CameraInfo messages,
    which must all give the same calibration."""
    where = f"{bag}: topic {topic}"
    first: tuple | None = None
    for i, (t, m) in enumerate(msgs):
        calib = (tuple(float(v) for v in m.k), tuple(float(v) for v in m.d), str(m.distortion_model),
                 int(m.width), int(m.height))
        if first is None:
            first = calib
        elif calib != first:
            raise SequenceFormatError(where, None, "one calibration (every CameraInfo alike)",
                                      f"message {i} at t={t!r} differs from message 0")
    k, d, model, width, height = cast(tuple, first)  # msgs is not empty (_messages)
    m0 = msgs[0][1]
    if not all(math.isfinite(v) for v in k + d):
        raise SequenceFormatError(where, None, "finite K and D", f"K={list(k)} D={list(d)}")
    fx, fy, cx, cy = k[0], k[4], k[2], k[5]
    if not (fx > 0 and fy > 0):
        raise SequenceFormatError(where, None, "a CameraInfo with positive focal lengths K[0], K[4] "
                                  "(a calibrated camera)", f"fx={fx:g} fy={fy:g}")
    if k[1] != 0 or k[3] != 0 or k[6] != 0 or k[7] != 0 or k[8] != 1:
        raise SequenceFormatError(where, None, "K = [fx 0 cx; 0 fy cy; 0 0 1] (no skew)", f"K={list(k)}")
    if not (width > 0 and height > 0):
        raise SequenceFormatError(where, None, "a CameraInfo with positive width and height",
                                  f"width={width} height={height}")
    bx, by = int(m0.binning_x), int(m0.binning_y)
    roi = m0.roi
    if bx > 1 or by > 1 or roi.x_offset or roi.y_offset or roi.width or roi.height:
        raise SequenceFormatError(where, None, "a CameraInfo without binning or region of interest",
                                  f"binning {bx}x{by}, roi {roi.x_offset},{roi.y_offset} {roi.width}x{roi.height}")
    dist = np.zeros(5)
    if any(d):
        if model == "plumb_bob" and len(d) == 5:
            dist = np.array(d)
        elif model == "rational_polynomial" and len(d) == 8 and not any(d[5:]):
            dist = np.array(d[:5])
        else:
            raise SequenceFormatError(
                where, None, "distortion 'plumb_bob' (5 coefficients) or 'rational_polynomial' "
                "(8, with k4 = k5 = k6 = 0)", f"{model!r} with D={list(d)}")
    camera = Camera(fx, fy, cx, cy, float(width), float(height))
    return camera, dist, str(m0.header.frame_id).lstrip("/")


def _detections(bag: str, topic: str, msgs, camera: Camera, min_score: float):
    """(the arrays' times, [(time, box (4,), label, score, instance)] scored ≥ ``min_score``)."""
    times, out = [], []
    for i, (t, arr) in enumerate(msgs):
        times.append(t)
        for j, d in enumerate(arr.detections):
            where = f"{bag}: topic {topic} message {i} detection {j}"
            if not d.results:
                raise SequenceFormatError(where, None, "at least one result (class_id, score)", "none")
            hyps = [(float(r.hypothesis.score), str(r.hypothesis.class_id)) for r in d.results]
            score, label = max(hyps, key=lambda h: h[0])
            label = "_".join(label.replace("#", " ").split())
            if not label or not math.isfinite(score):
                raise SequenceFormatError(where, None, "a class_id and a finite score",
                                          f"class_id {hyps[0][1]!r} score {score!r}")
            c = d.bbox.center
            pos = getattr(c, "position", c)  # vision_msgs 4.x: Pose2D.position; 3.x: x, y
            u, v, theta = float(pos.x), float(pos.y), float(c.theta)
            sx, sy = float(d.bbox.size_x), float(d.bbox.size_y)
            if not all(math.isfinite(x) for x in (u, v, theta, sx, sy)):
                raise SequenceFormatError(where, None, "a finite bbox center and size",
                                          f"center ({u}, {v}, theta {theta}) size {sx} x {sy}")
            if not (sx > 0 and sy > 0):
                raise SequenceFormatError(where, None, "a bbox with positive size_x and size_y",
                                          f"size {sx:g} x {sy:g}")
            ca, sa = abs(math.cos(theta)), abs(math.sin(theta))
            hx, hy = 0.5 * (ca * sx + sa * sy), 0.5 * (sa * sx + ca * sy)
            box = np.array([u - hx, v - hy, u + hx, v + hy])
            check_box(where, None, box, camera)
            ident = str(d.id).strip()
            try:
                inst = int(ident)
            except ValueError:
                inst = None
            if score >= min_score:
                out.append((t, box, label, score, inst))
    return np.array(times), out


def _pose_rows(bag: str, topic: str, msgs, world_frame, camera_frame) -> np.ndarray:
    """(N, 8) TUM rows of PoseStamped or Odometry messages, sorted by time, a repeated time
    left out; every message in one frame (``world_frame`` when given)."""
    where = f"{bag}: topic {topic}"
    rows: list[list[float]] = []
    frames: set[str] = set()
    for i, (t, m) in enumerate(msgs):
        pose = m.pose.pose if hasattr(m, "child_frame_id") else m.pose
        frame = str(m.header.frame_id).lstrip("/")
        if world_frame is not None and frame != world_frame:
            raise SequenceFormatError(where, None, f"poses in the world frame {world_frame!r}",
                                      f"message {i} in {frame!r}")
        if camera_frame is not None and hasattr(m, "child_frame_id") and \
                str(m.child_frame_id).lstrip("/") != camera_frame:
            raise SequenceFormatError(where, None, f"the pose of the camera frame {camera_frame!r}",
                                      f"message {i} of child_frame_id {m.child_frame_id!r}")
        frames.add(frame)
        p, q = pose.position, pose.orientation
        v = [float(p.x), float(p.y), float(p.z)]
        qv = [float(q.x), float(q.y), float(q.z), float(q.w)]
        if not all(math.isfinite(x) for x in v + qv):
            raise SequenceFormatError(where, None, "a finite pose", f"message {i}: position {v}, orientation {qv}")
        rows.append([t, *v, *unit_quaternion(f"{where} message {i}", None, qv)])
    if len(frames) > 1:
        raise SequenceFormatError(where, None, "poses in one frame (header.frame_id)",
                                  ", ".join(repr(f) for f in sorted(frames)))
    table = np.array(sorted(rows, key=lambda r: r[0]))
    keep = np.concatenate([[True], np.diff(table[:, 0]) > 0])
    return table[keep]


class _Edge:
    """The transform T_parent_child of one tf edge: static, or samples over time."""

    def __init__(self, parent: str):
        self.parent = parent
        self.t: list = []
        self.p: list = []
        self.q: list = []
        self.static = False

    def add(self, t, p, q, static):
        if static:  # a later static transform replaces an earlier one
            self.t, self.p, self.q = [t], [p], [q]
        else:
            self.t.append(t), self.p.append(p), self.q.append(q)
        self.static = static

    def at(self, tq: np.ndarray):
        """(translations (n, 3), Rotation of n, covered mask) at times ``tq``: a static
        transform everywhere; samples interpolated (translation linearly, rotation by slerp)
        between the first and last, or the end sample within the matching tolerance."""
        n = tq.size
        if self.static:
            return np.tile(self.p[0], (n, 1)), Rotation.from_quat(np.tile(self.q[0], (n, 1))), np.ones(n, bool)
        order = np.argsort(self.t, kind="stable")
        t = np.asarray(self.t)[order]
        p = np.asarray(self.p)[order]
        q = np.asarray(self.q)[order]
        keep = np.concatenate([[True], np.diff(t) > 0])
        t, p, q = t[keep], p[keep], q[keep]
        if t.size == 1:
            ok = np.abs(tq - t[0]) <= MATCH_TOLERANCE + 1e-9
            return np.tile(p[0], (n, 1)), Rotation.from_quat(np.tile(q[0], (n, 1))), ok
        ok = np.abs(np.clip(tq, t[0], t[-1]) - tq) <= MATCH_TOLERANCE + 1e-9
        pose = interpolate_tum(np.c_[t, p, q], tq)  # the end sample outside [t[0], t[-1]]
        return pose[:, :3], Rotation.from_quat(pose[:, 3:]), ok


def _tf_edges(bag: str, topic: str, msgs, static: bool, edges: dict) -> None:
    for i, (_, m) in enumerate(msgs):
        for j, tr in enumerate(m.transforms):
            where = f"{bag}: topic {topic} message {i} transform {j}"
            parent = str(tr.header.frame_id).lstrip("/")
            child = str(tr.child_frame_id).lstrip("/")
            if not parent or not child or parent == child:
                raise SequenceFormatError(where, None, "distinct, non-empty header.frame_id and child_frame_id",
                                          f"{parent!r} -> {child!r}")
            t = float(tr.header.stamp.sec) + 1e-9 * float(tr.header.stamp.nanosec)
            v, r = tr.transform.translation, tr.transform.rotation
            p = [float(v.x), float(v.y), float(v.z)]
            qv = [float(r.x), float(r.y), float(r.z), float(r.w)]
            if not all(math.isfinite(x) for x in p + qv):
                raise SequenceFormatError(where, None, "a finite transform", f"translation {p}, rotation {qv}")
            q = unit_quaternion(where, None, qv)
            e = edges.get(child)
            if e is None:
                e = edges[child] = _Edge(parent)
            elif e.parent != parent:
                raise SequenceFormatError(where, None, f"one parent of the frame {child!r} (a tf tree)",
                                          f"{e.parent!r} and {parent!r}")
            e.add(t, np.array(p), q, static)


def _chain(edges: dict, frame: str) -> list[str]:
    """``frame`` and its ancestors up to the root."""
    out = [frame]
    while out[-1] in edges and len(out) <= len(edges):
        out.append(edges[out[-1]].parent)
    return out


def _tf_poses(bag: str, topic: str, edges: dict, world: str | None, camera: str, times: np.ndarray):
    """(times covered, T_world_camera TUM rows (without t), covered mask) along the tf tree."""
    where = f"{bag}: topic {topic}"
    frames = sorted(set(edges) | {e.parent for e in edges.values()})
    shown = ", ".join(repr(f) for f in frames[:_SHOWN_TOPICS]) + (", …" if len(frames) > _SHOWN_TOPICS else "")
    if camera not in frames:
        raise SequenceFormatError(where, None, f"the camera frame {camera!r} in the tf tree",
                                  f"frames {shown}")
    up_c = _chain(edges, camera)
    if world is None:
        world = up_c[-1]
    if world not in frames:
        raise SequenceFormatError(where, None, f"the world frame {world!r} in the tf tree", f"frames {shown}")
    up_w = _chain(edges, world)
    common = next((f for f in up_c if f in up_w), None)
    if common is None:
        raise SequenceFormatError(where, None, f"a chain of transforms from {world!r} to {camera!r}",
                                  f"no path between them ({camera!r} reaches {up_c[-1]!r}, "
                                  f"{world!r} reaches {up_w[-1]!r})")
    n = times.size

    def to_common(chain):
        """T_common_frame at ``times`` for chain = frame … common."""
        p, r, ok = np.zeros((n, 3)), Rotation.identity(n), np.ones(n, bool)
        for f in chain[:chain.index(common)]:
            pe, re, oke = edges[f].at(times)
            p, r, ok = re.apply(p) + pe, re * r, ok & oke  # T_parent_f ∘ T_f_frame
        return p, r, ok

    pc, rc, okc = to_common(up_c)
    pw, rw, okw = to_common(up_w)
    rwi = rw.inv()
    p = rwi.apply(pc - pw)
    r = rwi * rc
    return np.hstack([p, r.as_quat()]), okc & okw


# --- the importer ---------------------------------------------------------------------------


def import_rosbag(path, camera_info_topic: str | None = None, detections_topic: str | None = None,
                  pose_topic: str | None = None, world_frame: str | None = None,
                  camera_frame: str | None = None, min_score: float = DEFAULT_MIN_SCORE,
                  undistort: bool = True, name: str | None = None) -> Sequence:
    """A ROS 2 bag (module docstring) as a :class:`Sequence` (trajectory T_wc, TUM rows).

    Topics not given are the bag's single topic of the type (CameraInfo, Detection2DArray;
    PoseStamped, Odometry or TFMessage for the poses); none or several is an error naming
    them. With PoseStamped or Odometry the frames are the pose messages and a detection
    goes to the pose nearest in time within ``MATCH_TOLERANCE`` (0.02 s; others are left
    out); ``world_frame`` / ``camera_frame`` then check the messages' frame ids. With tf,
    the frames are the Detection2DArray times at which the chain from ``world_frame``
    (default: the root of the camera's tree) to ``camera_frame`` (default: CameraInfo's
    frame_id) is known (each moving link interpolated between its samples, or its end
    sample within 0.02 s). Detections scored below ``min_score`` are left out; with
    distortion, boxes are replaced by the pinhole box of their undistorted outline unless
    ``undistort=False``. Priors: only the up direction, estimated from the cameras as for the
    OA-SLAM layout (``estimate_up``) when they determine it; the rest takes the back end's
    defaults."""
    path = Path(path)
    bag = str(path)
    if world_frame is not None:
        world_frame = world_frame.lstrip("/")
    if camera_frame is not None:
        camera_frame = camera_frame.lstrip("/")
    reader = _open(path, bag)
    try:
        topics = _topic_types(reader)
        cam_topic = _choose(bag, topics, camera_info_topic, (CAMERA_INFO,), "--camera-info-topic", "the camera")
        det_topic = _choose(bag, topics, detections_topic, (DETECTIONS,), "--detections-topic", "the detections")
        pose_topic = _choose(bag, topics, pose_topic, POSE_TYPES, "--pose-topic", "the camera poses")
        used = {cam_topic, det_topic, pose_topic}
        is_tf = topics[pose_topic] == TF_MESSAGE
        if is_tf and pose_topic != "/tf_static" and topics.get("/tf_static") == TF_MESSAGE:
            used.add("/tf_static")
        store = _typestore(bag, [c for c in reader.connections if c.topic in used])
        camera, dist, info_frame = _camera(bag, cam_topic, _messages(reader, store, bag, cam_topic))
        det_times, raw = _detections(bag, det_topic, _messages(reader, store, bag, det_topic),
                                     camera, min_score)
        if is_tf:
            edges: dict = {}
            _tf_edges(bag, pose_topic, _messages(reader, store, bag, pose_topic), pose_topic == "/tf_static", edges)
            if "/tf_static" in used:
                _tf_edges(bag, "/tf_static", _messages(reader, store, bag, "/tf_static", required=False),
                          True, edges)
            cam = camera_frame or info_frame
            if not cam:
                raise SequenceFormatError(f"{bag}: topic {cam_topic}", None,
                                          "a header.frame_id naming the camera frame (or --camera-frame)", "''")
            times = np.unique(det_times)
            poses, ok = _tf_poses(bag, pose_topic, edges, world_frame, cam, times)
            if not ok.any():
                raise SequenceFormatError(
                    f"{bag}: topic {pose_topic}", None,
                    f"transforms {world_frame or 'world'} -> {cam} at the detections' times "
                    f"({times[0]!r} … {times[-1]!r})", "none covered (the moving links' samples lie elsewhere)")
            traj = np.column_stack([times[ok], poses[ok]])
        else:
            if camera_frame is not None and topics[pose_topic] == POSE_STAMPED:
                raise ValueError("camera_frame applies to tf and Odometry poses; a PoseStamped names no "
                                 "child frame")
            traj = _pose_rows(bag, pose_topic, _messages(reader, store, bag, pose_topic),
                              world_frame, camera_frame)
    finally:
        reader.close()
    timestamps = traj[:, 0]
    detections = []
    if raw:
        t = np.array([r[0] for r in raw])
        near, ok = nearest_stamps(timestamps, t)
        if not ok.any():
            raise SequenceFormatError(
                f"{bag}: topic {det_topic}", None,
                f"detections within {MATCH_TOLERANCE} s of a pose of {pose_topic}",
                f"none of {len(raw)} (detections {t.min()!r} … {t.max()!r} s, poses "
                f"{timestamps[0]!r} … {timestamps[-1]!r} s)")
        boxes = np.stack([r[1] for r in raw])
        if undistort and np.any(dist):
            boxes = undistort_boxes(boxes, camera, dist)
            bad = ~np.all(np.isfinite(boxes), axis=1) | ~(boxes[:, 2] > boxes[:, 0]) | ~(boxes[:, 3] > boxes[:, 1])
            if bad.any():  # a corner far outside the image, where the lens model diverges
                i = int(np.flatnonzero(bad)[0])
                raise SequenceFormatError(
                    f"{bag}: topic {det_topic}", None,
                    "boxes whose undistorted outline is a finite box of positive area",
                    f"box {[float(v) for v in raw[i][1]]} at t={raw[i][0]!r}")
        for k in np.flatnonzero(ok):
            _, _, label, score, inst = raw[k]
            detections.append(Detection(int(near[k]), float(t[k]), boxes[k], label, score, inst))
    name = name or (path.name if path.is_dir() else path.stem)
    try:  # as the OA-SLAM importer: up from cameras carried without roll, when determined
        priors = Priors([], estimate_up(traj[:, 1:]), {}, None)
    except ValueError:
        priors = None
    return Sequence(name, camera, timestamps, traj[:, 1:], detections, priors=priors)


class RosBag2(SequenceFormat):
    """A ROS 2 bag (module docstring, ``import_rosbag``; needs the rosbags package)."""

    name = "rosbag2"
    title = "a ROS 2 bag"
    layout = "a folder with metadata.yaml, or a .mcap or .db3 file"
    docs = "docs/your-data.md, From a ROS 2 bag"
    options = {
        "camera_info_topic": "the sensor_msgs/msg/CameraInfo topic (default: the bag's only one)",
        "detections_topic": "the vision_msgs/msg/Detection2DArray topic (default: the bag's only one)",
        "pose_topic": "the camera poses: PoseStamped, Odometry or tf (default: the bag's only one)",
        "world_frame": "the world frame of the poses",
        "camera_frame": "the camera's optical frame",
        "min_score": f"leave out detections scored below this (default {DEFAULT_MIN_SCORE:g})",
        "undistort": "replace each box by the pinhole box of its undistorted outline (default true)",
    }
    hints = {"trajectory": "a ROS 2 bag's poses come from --pose-topic"}

    @classmethod
    def claims(cls, path: Path) -> bool:
        return (path.is_dir() and (path / "metadata.yaml").is_file()) or (
            path.is_file() and path.suffix.lower() in _BAG_SUFFIXES)

    @classmethod
    def read(cls, path: Path, **options) -> Sequence:
        return import_rosbag(path, **options)

