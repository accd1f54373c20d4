"""Osmap maps: the saved maps of the object-SLAM systems built on ORB-SLAM2's Osmap
serialisation (OA-SLAM, GOReloc, VOOM): a YAML header naming protobuf binaries.

The header (OpenCV's ``%YAML:1.0``) names the files beside it with their counts: GOReloc's
and VOOM's ``objectsFile``/``nObjects``, OA-SLAM's ``mapobjectsFile``/``nMapobjects`` and
``objecttracksFile``/``nObjectTracks``; both ``keyframesFile``/``nKeyframes`` and
GOReloc's and VOOM's ``graphsFile``/``nGraphs``. Each binary is one protobuf message (proto3)
holding a repeated field of its records:

- objects (``SerializedObjectArray``; OA-SLAM's ``SerializedMapobjectArray`` has the same
  fields): per object its dual quadric Q* (16 floats, row major), its id (OA-SLAM: its
  track's), and the histogram of the detector's category ids that voted for it (``cat_ids``,
  ``cat_counts``; COCO's 80 classes in YOLO's 0-indexed order; GOReloc only);
- object tracks (OA-SLAM, ``SerializedObjectTrackArray``): each track's id and category;
- keyframes (``SerializedKeyframeArray``): id, T_cw (the first 12 floats of the 4×4 matrix,
  row major) and the image's timestamp: a double, or (a fork of OA-SLAM) a message of
  seconds and nanoseconds — the keyframes are decoded both ways and the one that holds every
  keyframe's time is kept;
- graphs (``SerializedGraphArray``): per keyframe its object nodes (category id, object id),
  read only for objects whose own histogram is empty (VOOM's objects carry none).

An object is the ellipsoid of Q* normalised to Q*₃₃ = −1: t = −Q*[:3, 3], P = Q*[:3, :3] +
t tᵀ (spdslam's convention, ``geometry.Ellipsoid``), refused unless P is positive definite.
The messages are decoded by the protobuf library from a schema declared here
(``OSMAP_MESSAGES``: only the fields read; the others pass as unknown fields).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from ..geometry import Ellipsoid
from ..geometry.se3 import matrix_to_quat
from ._map import MapFormatError, MapObject
from ._map_formats import MapFormat, SavedMap, peer_document
from ._oaslam import COCO80
from ._parse import SequenceFormatError, read_text

__all__ = ["OsmapMap", "OSMAP_MESSAGES", "osmap_messages", "read_osmap"]

#: The header's keys naming the binaries, with their count keys, and the message each holds
#: (with its repeated field) — for GOReloc's and VOOM's layout, and what OA-SLAM's differs in.
_FILES = {"objects": ("objectsFile", "nObjects", "SerializedObjectArray", "object"),
          "keyframes": ("keyframesFile", "nKeyframes", "SerializedKeyframeArray", "keyframe"),
          "graphs": ("graphsFile", "nGraphs", "SerializedGraphArray", "graph")}
_OA_SLAM_FILES = {**_FILES, "objects": ("mapobjectsFile", "nMapobjects", "SerializedObjectArray", "object"),
                  "tracks": ("objecttracksFile", "nObjectTracks", "SerializedObjectTrackArray", "objecttrack")}
#: An object id or category the writer left unset (uint32 −1).
_UNSET = 2**32 - 1

#: message → [(field, number, type, repeated, message type)], proto3, the fields read.
OSMAP_MESSAGES: dict[str, list[tuple[str, int, str, bool, str | None]]] = {
    "SerializedEllipsoid": [("element", 1, "float", True, None)],
    "SerializedPose": [("element", 1, "float", True, None)],
    "SerializedObject": [("ellipsoid", 1, "message", False, "SerializedEllipsoid"),
                         ("object_id", 2, "uint32", False, None),
                         ("cat_ids", 3, "uint32", True, None),
                         ("cat_counts", 4, "uint32", True, None)],
    "SerializedObjectArray": [("object", 1, "message", True, "SerializedObject")],
    "SerializedKeyframe": [("id", 1, "uint32", False, None),
                           ("pose", 2, "message", False, "SerializedPose"),
                           ("timestamp", 6, "double", False, None)],
    "SerializedKeyframeArray": [("keyframe", 1, "message", True, "SerializedKeyframe")],
    "SerializedTimestamp": [("sec", 1, "uint32", False, None), ("nsec", 2, "uint32", False, None)],
    "SerializedKeyframeStamped": [("id", 1, "uint32", False, None),
                                  ("pose", 2, "message", False, "SerializedPose"),
                                  ("timestamp", 6, "message", False, "SerializedTimestamp")],
    "SerializedKeyframeStampedArray": [("keyframe", 1, "message", True, "SerializedKeyframeStamped")],
    "SerializedObjectTrack": [("id", 1, "uint32", False, None), ("cat", 2, "uint32", False, None)],
    "SerializedObjectTrackArray": [("objecttrack", 1, "message", True, "SerializedObjectTrack")],
    "SerializedNode": [("node_id", 1, "uint32", False, None),
                       ("category_id", 2, "uint32", False, None),
                       ("object_id", 4, "uint32", False, None)],
    "SerializedGraph": [("node", 1, "message", True, "SerializedNode")],
    "SerializedGraphArray": [("graph", 1, "message", True, "SerializedGraph")],
}


@lru_cache(maxsize=1)
def osmap_messages() -> dict:
    """The message classes of ``OSMAP_MESSAGES`` (name → class), built once with the
    protobuf library's descriptor pool."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    F = descriptor_pb2.FieldDescriptorProto
    types = {"float": F.TYPE_FLOAT, "double": F.TYPE_DOUBLE, "uint32": F.TYPE_UINT32, "message": F.TYPE_MESSAGE}
    fdp = descriptor_pb2.FileDescriptorProto(name="spdslam_osmap.proto", package="spdslam.osmap",
                                             syntax="proto3")
    for name, fields in OSMAP_MESSAGES.items():
        m = fdp.message_type.add(name=name)
        for fname, number, typ, repeated, tname in fields:
            f = m.field.add(name=fname, number=number, type=types[typ],
                            label=F.LABEL_REPEATED if repeated else F.LABEL_OPTIONAL)
            if tname:
                f.type_name = f".spdslam.osmap.{tname}"
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    return {name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"spdslam.osmap.{name}"))
            for name in OSMAP_MESSAGES}


def _header(path: Path) -> dict:
    """The header's top-level ``key: value`` scalars, each with its line."""
    try:
        text = read_text(path)
    except SequenceFormatError as e:
        raise MapFormatError(str(e)) from None
    out: dict = {}
    for i, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].rstrip() if not raw.startswith("%") else ""
        if not line or line == "---" or line[0] in " \t-":
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise MapFormatError(f"{path}:{i}: expected 'key: value', got {raw.strip()[:60]!r}")
        out[key.strip()] = (value.strip().strip('"').strip("'"), i)
    return out


def _count(path: Path, header: dict, key: str) -> int | None:
    if key not in header:
        return None
    value, line = header[key]
    try:
        n = int(value)
    except ValueError:
        n = -1
    if n < 0:
        raise MapFormatError(f"{path}:{line}: expected {key}: a count, got {value[:40]!r}")
    return n


def _message(path: Path, header: dict, files: dict, what: str, required: bool, message: str | None = None):
    """The binary ``what`` named by the header (``files``: the layout's keys), parsed as its
    message (or ``message``, with the same repeated field) (None when not named and not
    ``required``), with its record count checked against the header's."""
    file_key, count_key, name_of, field = files[what]
    if file_key not in header:
        if required:
            raise MapFormatError(f"{path}: expected the key {file_key} (the {what} file), got none")
        return None
    name, line = header[file_key]
    binary = path.parent / name
    try:
        data = binary.read_bytes()
    except OSError as e:
        raise MapFormatError(f"{path}:{line}: expected the {what} file {name}, got "
                             f"{e.strerror or type(e).__name__}") from None
    from google.protobuf.message import DecodeError

    cls = osmap_messages()[message or name_of]
    msg = cls()
    try:
        msg.ParseFromString(data)
    except DecodeError as e:
        raise MapFormatError(f"{binary}: expected a protobuf {cls.DESCRIPTOR.name}, got bytes it cannot "
                             f"decode ({e})") from None
    records = getattr(msg, field)
    n = _count(path, header, count_key)
    if n is not None and len(records) != n:
        raise MapFormatError(f"{binary}: expected {n} {what} ({count_key} in {path.name}), got {len(records)} "
                             "(a truncated or foreign file)")
    return records


def _keyframes(path: Path, header: dict, files: dict):
    """(the keyframes' records, their times (n,)), or None without a keyframes file: decoded
    with the time as a message of seconds and nanoseconds where every keyframe has one (a
    double's bytes are another wire type: then none has), else as a double."""
    stamped = _message(path, header, files, "keyframes", False, "SerializedKeyframeStampedArray")
    if stamped is None:
        return None
    if len(stamped) and all(k.HasField("timestamp") for k in stamped):
        return stamped, np.array([k.timestamp.sec + 1e-9 * k.timestamp.nsec for k in stamped])
    plain = _message(path, header, files, "keyframes", False)
    times = np.array([k.timestamp for k in plain], dtype=float)
    if len(times) > 1 and not np.any(times):  # proto3 writes no zero: none was written
        raise MapFormatError(f"{path.parent / header[files['keyframes'][0]][0]}: expected each keyframe's "
                             "timestamp, got none")
    return plain, times


def _label(binary: Path, oid: int, cats, counts, votes: dict) -> str | None:
    """The object's label: its most counted category (COCO80), else its graph nodes' most
    frequent one, else None."""
    cats, counts = list(cats), list(counts)
    if len(cats) != len(counts):
        raise MapFormatError(f"{binary}: expected object {oid}'s cat_ids and cat_counts of one length, got "
                             f"{len(cats)} and {len(counts)}")
    if not cats:
        tally = votes.get(oid)
        if not tally:
            return None
        cats, counts = list(tally), list(tally.values())
    best = cats[int(np.argmax(counts))]
    if best >= len(COCO80):
        raise MapFormatError(f"{binary}: expected object {oid}'s category ids in COCO's 0–79, got {best}")
    return COCO80[best]


def _ellipsoid(binary: Path, oid: int, elements) -> Ellipsoid:
    """The ellipsoid of a dual quadric's 16 entries (row major)."""
    Q = np.asarray(elements, dtype=float)
    if Q.size != 16 or not np.all(np.isfinite(Q)):
        raise MapFormatError(f"{binary}: expected object {oid}'s dual quadric as 16 finite numbers, got "
                             f"{Q.size} {'numbers' if np.all(np.isfinite(Q)) else 'with non-finite ones'}")
    Q = Q.reshape(4, 4)
    scale = float(np.abs(Q).max())
    if np.abs(Q - Q.T).max() > 1e-5 * scale or abs(Q[3, 3]) <= 1e-12 * scale:
        raise MapFormatError(f"{binary}: expected object {oid}'s dual quadric symmetric with Q*[3,3] ≠ 0, got "
                             f"{np.round(Q, 4).tolist()}")
    Q = -0.5 * (Q + Q.T) / Q[3, 3]  # Q*₃₃ = −1
    t = -Q[:3, 3]
    P = Q[:3, :3] + np.outer(t, t)
    w = np.linalg.eigvalsh(P)
    if not w[0] > 1e-12 * max(w[-1], 1e-300):
        raise MapFormatError(f"{binary}: expected object {oid}'s dual quadric of an ellipsoid (Q*[:3,:3] + t tᵀ "
                             f"positive definite), got eigenvalues {np.round(w, 6).tolist()}")
    return Ellipsoid(P, t)


def _trajectory(binary: Path, keyframes, times) -> np.ndarray:
    """TUM rows (N, 8) of the keyframes' T_wc at ``times``, sorted by time."""
    rows = []
    for k, stamp in zip(keyframes, times):
        e = np.asarray(k.pose.element, dtype=float)
        if e.size != 12 or not np.all(np.isfinite(e)) or not np.isfinite(stamp):
            raise MapFormatError(f"{binary}: expected keyframe {k.id}'s pose as 12 finite numbers and a finite "
                                 f"timestamp, got {e.size} numbers, timestamp {stamp}")
        T = e.reshape(3, 4)
        U, s, Vt = np.linalg.svd(T[:, :3])
        if abs(s - 1.0).max() > 1e-3:
            raise MapFormatError(f"{binary}: expected keyframe {k.id}'s T_cw with a rotation, got singular "
                                 f"values {np.round(s, 4).tolist()}")
        R_cw = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        R_wc = R_cw.T
        rows.append(np.concatenate([[stamp], -R_wc @ T[:, 3], matrix_to_quat(R_wc)]))
    out = np.array(rows).reshape(-1, 8)
    return out[np.argsort(out[:, 0], kind="stable")]


def read_osmap(path) -> SavedMap:
    """The objects and keyframes of an Osmap map (its ``.yaml`` header; module docstring)."""
    path = Path(path)
    header = _header(path)
    files = _OA_SLAM_FILES if "mapobjectsFile" in header else _FILES
    objects_msg = _message(path, header, files, "objects", required=True)
    keyframes = _keyframes(path, header, files)
    binary = path.parent / header[files["objects"][0]][0]
    votes: dict = {}
    if any(len(o.cat_ids) == 0 for o in objects_msg):
        for g in _message(path, header, files, "graphs", required=False) or ():
            for nd in g.node:
                if nd.object_id != _UNSET and nd.category_id != _UNSET:
                    tally = votes.setdefault(nd.object_id, {})
                    tally[nd.category_id] = tally.get(nd.category_id, 0) + 1
        for tr in (_message(path, header, files, "tracks", required=True) if "tracks" in files else ()):
            votes[tr.id] = {tr.cat: 1}  # OA-SLAM: the object's track's category
    objects, unlabelled, seen = [], [], set()
    for o in objects_msg:
        oid = int(o.object_id)
        if oid in seen:
            raise MapFormatError(f"{binary}: expected distinct object ids, got {oid} twice")
        seen.add(oid)
        label = _label(binary, oid, o.cat_ids, o.cat_counts, votes)
        if label is None:
            unlabelled.append(oid)
        objects.append(MapObject(oid, label or "object", _ellipsoid(binary, oid, o.ellipsoid.element)))
    notes = []
    if unlabelled:
        notes.append(f"{len(unlabelled)} objects carry no category (no cat_ids, no graph node): labelled "
                     f"'object' (ids {unlabelled[:10]}{' …' if len(unlabelled) > 10 else ''})")
    trajectory = None
    if keyframes is None:
        notes.append("no keyframes file: the map has no trajectory (an evaluation compares its objects as "
                     "they are, not aligned to the ground truth)")
    else:
        trajectory = _trajectory(path.parent / header["keyframesFile"][0], *keyframes)
    doc = peer_document(OsmapMap.name, path, objects, 0 if trajectory is None else len(trajectory), notes)
    return SavedMap(doc, objects, trajectory, OsmapMap.name, path, notes)


class OsmapMap(MapFormat):
    """An Osmap map of GOReloc or VOOM (module docstring)."""

    name = "osmap"
    title = "an Osmap map (OA-SLAM, GOReloc, VOOM)"
    layout = "a .yaml naming objectsFile or mapobjectsFile, or a folder with one"
    docs = "Osmap maps"

    @classmethod
    def _header_file(cls, path: Path) -> Path | None:
        if path.is_dir():
            found = [p for p in sorted(path.glob("*.yaml")) if cls._names_objects(p)]
            return found[0] if len(found) == 1 else None
        return path if path.suffix in (".yaml", ".yml") and cls._names_objects(path) else None

    @staticmethod
    def _names_objects(p: Path) -> bool:
        try:
            with open(p, "rb") as f:
                return b"objectsFile" in f.read(4096)
        except OSError:
            return False

    @classmethod
    def claims(cls, path: Path) -> bool:
        return cls._header_file(path) is not None

    @classmethod
    def read(cls, path: Path) -> SavedMap:
        return read_osmap(cls._header_file(path) or path)
