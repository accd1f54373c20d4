"""Maps exported for other tools: a Spark-DSG scene graph and a glTF scene.

``export_map(saved, format, path)`` writes a ``SavedMap`` (``load_map``: a run of spdslam,
or another system's map) as one file, atomically; ``EXPORT_FORMATS`` names the formats:

- ``spark-dsg``: a 3D scene graph of the ``spark_dsg`` library (Hydra's): a node per object
  in the OBJECTS layer, symbol ``O``/id, with its position (the centre), its oriented
  bounding box (the circumscribed cuboid: dimensions 2 × radii, rotation the ellipsoid's
  axes), ``world_R_object``, its name ("label id") and semantic label (COCO's index for a
  COCO class, else 1000 + its rank among the other labels; the layer's labelspace names
  them), and as metadata spdslam's fields (radii, P, uncertainty with the covariance,
  observed_by); the graph's metadata says where the map came from. A ``.json`` path gets
  spark_dsg's JSON, any other its binary. Needs ``spark-dsg`` (``pip install
  spdslam[export]``).
- ``gltf``: a glTF 2.0 scene (``.glb``: binary; ``.gltf``: JSON with the buffer inline),
  metres, the map's frame as it is (``up`` rotates the map's up direction to glTF's +y):
  a node and mesh per object named "label id", the ellipsoid's surface (a latitude-longitude
  sphere of ``GLTF_SEGMENTS``, moved by x = t + R diag(r) u, normals along P⁻¹(x − t)), one
  material per label; the camera trajectory (when the map has one) as lines between
  consecutive camera centres. Written
  here from the specification, without a library.
"""

from __future__ import annotations

import base64
import json
import os
import struct
from pathlib import Path
from typing import Callable

import numpy as np

from ..geometry.se3 import matrix_to_quat
from ._map_formats import SavedMap
from ._oaslam import COCO80
from ._writers import write_file_atomically

__all__ = ["EXPORT_FORMATS", "export_map", "gltf_document", "GLTF_SEGMENTS"]

#: (latitude bands, longitude segments) of an object's mesh in a glTF export.
GLTF_SEGMENTS = (16, 32)


def _semantic_ids(labels) -> dict:
    """{label: integer}: COCO's index for a COCO class, else 1000 + rank among the others."""
    others = sorted({lab for lab in labels if lab not in COCO80})
    return {lab: (COCO80.index(lab) if lab in COCO80 else 1000 + others.index(lab)) for lab in set(labels)}


def _axes(o):
    """(R, radii) of an object's ellipsoid, R a rotation (det +1)."""
    R, r = (np.array(a, float) for a in o.ellipsoid.axes())
    if np.linalg.det(R) < 0:
        R[:, 2] = -R[:, 2]
    return R, r


def _write_spark_dsg(saved: SavedMap, path: Path, up, suffix: str) -> None:
    try:
        import spark_dsg as dsg
    except ImportError:
        raise ImportError("exporting a Spark-DSG scene graph needs spark_dsg: pip install spdslam[export] "
                          "(or pip install spark-dsg)") from None
    ids = _semantic_ids([o.label for o in saved.objects])
    G = dsg.DynamicSceneGraph()
    for o in saved.objects:
        R, r = _axes(o)
        c = np.asarray(o.ellipsoid.center, float)
        a = dsg.ObjectNodeAttributes()
        a.position = c
        a.bounding_box = dsg.BoundingBox(dsg.BoundingBoxType.OBB, (2.0 * r).astype(np.float32),
                                         c.astype(np.float32), R.astype(np.float32))
        qx, qy, qz, qw = matrix_to_quat(R)
        a.world_R_object = dsg.Quaternion(qw, qx, qy, qz)
        a.name = f"{o.label} {o.id}"
        a.semantic_label = ids[o.label]
        meta = {"id": int(o.id), "label": o.label, "radii": r.tolist(), "P": np.asarray(o.ellipsoid.P).tolist()}
        if o.uncertainty is not None:
            meta["uncertainty"] = _finite(o.uncertainty)
        if o.observed_by is not None:
            meta["observed_by"] = [{"recording": rec, "frames": int(n)} for rec, n in o.observed_by]
        a.metadata.set({"spdslam": meta})
        G.add_node(dsg.DsgLayers.OBJECTS, dsg.NodeSymbol("O", int(o.id)), a)
    G.metadata.set({"spdslam": {"format": saved.format, "source": str(saved.path),
                                "method": str(saved.document.get("method", "")), "units": "m"}})
    G.set_labelspace(dsg.Labelspace({v: k for k, v in ids.items()}), "OBJECTS")  # kept in the metadata
    tmp = path.with_name(path.name + ".partial" + (".json" if suffix == ".json" else ".sparkdsg"))
    try:
        G.save(str(tmp))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _finite(value):
    """``value`` with non-finite floats as None (JSON has none)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _rotation_to_y(up) -> np.ndarray:
    """The rotation that takes the unit vector ``up`` to +y (identity when None)."""
    if up is None:
        return np.eye(3)
    u = np.asarray(up, float)
    u = u / np.linalg.norm(u)
    y = np.array([0.0, 1.0, 0.0])
    v, c = np.cross(u, y), float(u @ y)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def _sphere(segments=GLTF_SEGMENTS) -> tuple[np.ndarray, np.ndarray]:
    """(unit vectors (V, 3), triangles (T, 3)) of a latitude-longitude sphere, poles shared."""
    nlat, nlon = segments
    theta = np.linspace(0.0, np.pi, nlat + 1)[1:-1]
    phi = np.linspace(0.0, 2.0 * np.pi, nlon, endpoint=False)
    ring = np.stack([np.sin(theta)[:, None] * np.cos(phi), np.sin(theta)[:, None] * np.sin(phi),
                     np.cos(theta)[:, None] * np.ones_like(phi)], axis=-1).reshape(-1, 3)
    verts = np.vstack([[0.0, 0.0, 1.0], ring, [0.0, 0.0, -1.0]])
    south = len(verts) - 1
    tris = []
    j = np.arange(nlon)
    k = (j + 1) % nlon
    tris.append(np.stack([np.zeros(nlon, int), 1 + j, 1 + k], axis=1))
    for b in range(nlat - 2):
        a0, a1 = 1 + b * nlon, 1 + (b + 1) * nlon
        tris.append(np.stack([a0 + j, a1 + j, a1 + k], axis=1))
        tris.append(np.stack([a0 + j, a1 + k, a0 + k], axis=1))
    last = 1 + (nlat - 2) * nlon
    tris.append(np.stack([last + j, np.full(nlon, south), last + k], axis=1))
    return verts, np.vstack(tris)


class _Buffer:
    """glTF's one buffer, its views and accessors, built up as arrays are added."""

    def __init__(self):
        self.data = bytearray()
        self.views: list = []
        self.accessors: list = []

    def add(self, array: np.ndarray, component: int, kind: str, target: int | None, bounds: bool = False) -> int:
        while len(self.data) % 4:
            self.data.append(0)
        raw = np.ascontiguousarray(array).tobytes()
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.data += raw
        self.views.append(view)
        acc = {"bufferView": len(self.views) - 1, "componentType": component,
               "count": int(array.shape[0]), "type": kind}
        if bounds:
            acc["min"], acc["max"] = array.min(axis=0).tolist(), array.max(axis=0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


_FLOAT, _UINT = 5126, 5125
_ARRAY, _ELEMENTS = 34962, 34963
#: colours of the labels' materials, in turn (RGB)
_PALETTE = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16), (0.58, 0.4, 0.74),
            (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5), (0.74, 0.74, 0.13), (0.09, 0.75, 0.81))


def gltf_document(saved: SavedMap, up=None) -> tuple[dict, bytes]:
    """(the glTF JSON, its buffer) of a map (module docstring)."""
    A = _rotation_to_y(up)
    unit, tris = _sphere()
    buf = _Buffer()
    labels = sorted({o.label for o in saved.objects})
    materials = [{"name": lab, "doubleSided": True, "pbrMetallicRoughness": {
        "baseColorFactor": [*_PALETTE[i % len(_PALETTE)], 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.8}}
        for i, lab in enumerate(labels)]
    meshes, nodes = [], []
    for o in saved.objects:
        R, r = _axes(o)
        t = np.asarray(o.ellipsoid.center, float)
        x = t + (unit * r) @ R.T
        n = (unit / r) @ R.T  # ∝ P⁻¹(x − t): the gradient of the quadric
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        pos = buf.add((x @ A.T).astype(np.float32), _FLOAT, "VEC3", _ARRAY, bounds=True)
        nor = buf.add((n @ A.T).astype(np.float32), _FLOAT, "VEC3", _ARRAY)
        idx = buf.add(tris.reshape(-1).astype(np.uint32), _UINT, "SCALAR", _ELEMENTS)
        name = f"{o.label} {o.id}"
        meshes.append({"name": name, "primitives": [{"attributes": {"POSITION": pos, "NORMAL": nor},
                                                     "indices": idx, "material": labels.index(o.label)}]})
        nodes.append({"name": name, "mesh": len(meshes) - 1,
                      "extras": {"id": int(o.id), "label": o.label, "radii": r.tolist()}})
    if saved.trajectory is not None and len(saved.trajectory) > 1:
        c = (np.asarray(saved.trajectory)[:, 1:4] @ A.T).astype(np.float32)
        pos = buf.add(c, _FLOAT, "VEC3", _ARRAY, bounds=True)
        seg = np.repeat(np.arange(len(c), dtype=np.uint32), 2)[1:-1]  # (0, 1), (1, 2), …
        idx = buf.add(seg, _UINT, "SCALAR", _ELEMENTS)
        materials.append({"name": "trajectory", "pbrMetallicRoughness": {"baseColorFactor": [0.9, 0.1, 0.1, 1.0]}})
        meshes.append({"name": "trajectory", "primitives": [{"attributes": {"POSITION": pos}, "indices": idx,
                                                             "mode": 1, "material": len(materials) - 1}]})
        nodes.append({"name": "trajectory", "mesh": len(meshes) - 1})
    doc = {
        "asset": {"version": "2.0", "generator": "spdslam export"},
        "scene": 0,
        "scenes": [{"name": f"{saved.format} map", "nodes": list(range(len(nodes)))}],
        "nodes": nodes, "meshes": meshes, "materials": materials,
        "accessors": buf.accessors, "bufferViews": buf.views,
        "buffers": [{"byteLength": len(buf.data)}],
    }
    return doc, bytes(buf.data)


def _write_gltf(saved: SavedMap, path: Path, up, suffix: str) -> None:
    doc, data = gltf_document(saved, up)
    if suffix == ".gltf":
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(data).decode("ascii")
        path.write_text(json.dumps(doc), encoding="utf-8")
        return
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    data += b"\0" * (-len(data) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(data), 0x004E4942) + data
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(chunks)) + chunks)


#: name → (what it writes, the suffixes it takes, the writer (saved, path, up, suffix)).
EXPORT_FORMATS: dict[str, tuple[str, tuple[str, ...], Callable]] = {
    "spark-dsg": ("a Spark-DSG scene graph (spark_dsg's JSON, or its binary)", (".json", ".sparkdsg"),
                  _write_spark_dsg),
    "gltf": ("a glTF 2.0 scene: an ellipsoid mesh per object", (".glb", ".gltf"), _write_gltf),
}


def export_map(saved: SavedMap, format: str, path, up=None) -> Path:
    """Write ``saved`` as ``format`` (``EXPORT_FORMATS``) at ``path``, atomically; ``up``:
    the map's up direction, turned to glTF's +y (glTF only). ``ValueError`` for an unknown
    format or a suffix the format does not take."""
    path = Path(path)
    if format not in EXPORT_FORMATS:
        raise ValueError(f"unknown export format {format!r}: expected one of {', '.join(EXPORT_FORMATS)}")
    what, suffixes, write = EXPORT_FORMATS[format]
    if path.suffix not in suffixes:
        raise ValueError(f"{path}: expected a file name ending in {' or '.join(suffixes)} for {format}, got "
                         f"{path.suffix or 'none'}")
    if up is not None and format != "gltf":
        raise ValueError(f"up turns a glTF scene only, not {format}")
    write_file_atomically(path, lambda tmp: write(saved, tmp, up, path.suffix))
    return path
