"""``map.json``: the objects of a map (and how it was made), written by ``spdslam run`` and
read back by ``spdslam evaluate`` (see docs/formats.md)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import Ellipsoid, sorted_axes
from ._json import dumps_strict
from ._parse import SequenceFormatError, read_text

__all__ = ["MAP_KEYS", "MAP_VERSION", "MAP_UNITS", "MAP_CONVENTIONS", "MapObject", "MapFormatError",
           "map_document", "read_map", "write_map"]

#: map.json's schema version (docs/map.schema.json). 1: before it was written (no
#: ``version``); 2: ``version``, ``units``, ``conventions``, each object's ``covariance`` (in
#: ``uncertainty``) and ``observed_by``. ``read_map`` reads both.
MAP_VERSION = 2
#: The units of map.json's numbers.
MAP_UNITS = {"length": "m", "P": "m^2", "angle": "rad", "time": "s"}
#: What map.json's numbers mean, stated in the file.
MAP_CONVENTIONS = {
    "frame": "the map's frame: trajectory.txt's (the input trajectory's, unless localised or merged into "
             "another map's)",
    "poses": "T_wc, camera to world; trajectory.txt holds TUM rows: time x y z qx qy qz qw",
    "object": "an ellipsoid {x: (x - center)^T P^-1 (x - center) <= 1}, P = R diag(radii^2) R^T, the "
              "columns of rotation (R) its axes",
    "covariance": "uncertainty.covariance: 9x9 marginal covariance of (center x, y, z; P xx, xy, xz, yy, "
                  "yz, zz) at the solution",
    "observed_by": "the recordings whose detections the object was estimated from, with how many frames each",
}

#: The keys of map.json, in order, with what each holds (``map_document``; docs/formats.md).
MAP_KEYS = {
    "version": "the schema version (MAP_VERSION; docs/map.schema.json)",
    "units": "the units of the numbers",
    "conventions": "what the numbers mean: frame, poses, objects, covariance",
    "method": "the method's name",
    "parameterization": "spd, rts or full",
    "iterations": "LM iterations of all the run's optimisations",
    "final_cost": "the cost at the end",
    "initial_cost": "the cost at the start of the first optimisation",
    "converged": "whether the last optimisation converged",
    "reason": "why the last optimisation stopped",
    "settings": "the method's fields",
    "objects": "the mapped objects: id, label, center, rotation, radii, P, uncertainty",
    "failed": "{id: why it is not mapped, with the step}",
    "notes": "what the run noticed",
    "association": "how detections were grouped (mode; precision and recall against ids)",
    "cost_by_factor": "{factor kind: its part of the final cost}",
    "trajectory": "a trajectory without a bound on each pose only: where its poses came from, the "
                  "loop closure (submaps, each candidate loop and what became of it) and each check "
                  "against the odometry (docs/drift.md)",
}


class MapFormatError(ValueError):
    """A malformed map.json: ``"<file>: expected …, got …"``."""


@dataclass(frozen=True)
class MapObject:
    """An object of the map: id, label and ellipsoid (P, t); ``uncertainty`` (optional):
    marginal standard deviations of its centre (m) and log-radii, and the covariance of
    (centre, P's upper triangle) (``mapping``); ``observed_by`` (optional): ((recording,
    frames), …), the recordings whose detections it was estimated from."""

    id: int
    label: str
    ellipsoid: Ellipsoid
    uncertainty: dict | None = None
    observed_by: tuple | None = None

    def as_dict(self) -> dict:
        R, s = sorted_axes(np.asarray(self.ellipsoid.to_ellipsoid().P, dtype=float))  # NumPy: nothing to compile
        out = {
            "id": int(self.id),
            "label": self.label,
            "center": np.asarray(self.ellipsoid.center).tolist(),
            "rotation": R.tolist(),
            "radii": s.tolist(),
            "P": np.asarray(self.ellipsoid.P).tolist(),
        }
        if self.uncertainty is not None:
            out["uncertainty"] = self.uncertainty
        if self.observed_by is not None:
            out["observed_by"] = [{"recording": str(r), "frames": int(n)} for r, n in self.observed_by]
        return out


def map_document(*, method: str, parameterization: str, iterations: int, final_cost: float,
                 initial_cost: float, converged: bool, reason: str, settings: dict, objects,
                 failed: dict, notes, association: dict, cost_by_factor: dict,
                 trajectory: dict | None = None) -> dict:
    """The content of map.json (``MAP_KEYS``, in that order; ``trajectory`` only when given
    and not empty) from a run's figures; ``objects`` are ``MapObject`` s. ``spdslam run`` may
    add ``sequence`` (the folder it read) and ``to_groundtruth`` (4×4) after them."""
    out = {
        "version": MAP_VERSION,
        "units": dict(MAP_UNITS),
        "conventions": dict(MAP_CONVENTIONS),
        "method": method,
        "parameterization": parameterization,
        "iterations": int(iterations),
        "final_cost": float(final_cost),
        "initial_cost": float(initial_cost),
        "converged": bool(converged),
        "reason": reason,
        "settings": settings,
        "objects": [o.as_dict() for o in objects],
        "failed": {str(k): v for k, v in failed.items()},
        "notes": list(notes),
        "association": dict(association),
        "cost_by_factor": {k: float(v) for k, v in cost_by_factor.items()},
    }
    if trajectory:
        out["trajectory"] = trajectory
    return out


def write_map(path, map_dict: dict) -> None:
    """Write a map dict (``MapResult.as_dict()``) as strict JSON (NaN as null)."""
    Path(path).write_text(dumps_strict(map_dict) + "\n", encoding="utf-8")


def read_map(path) -> tuple[dict, list]:
    """(map dict, objects as ``MapObject``) of a map.json (or of the folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / "map.json"
    try:
        m = json.loads(read_text(path))
    except SequenceFormatError as e:  # not a readable UTF-8 file: say what is there
        raise MapFormatError(f"{path}: expected a map.json written by spdslam run, got {e.got}") from None
    except json.JSONDecodeError as e:
        raise MapFormatError(f"{path}:{e.lineno}: expected JSON, got {e.msg}") from None
    if not isinstance(m, dict):
        raise MapFormatError(f"{path}: expected a JSON object, got {type(m).__name__}")
    version = m.get("version", 1)
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= MAP_VERSION:
        raise MapFormatError(f"{path}: expected map.json version 1 to {MAP_VERSION} (what this spdslam reads), got "
                             f"{str(version)[:20]}" + (": a newer spdslam wrote it" if isinstance(version, int)
                                                       and version > MAP_VERSION else ""))
    for k, types in (("method", str), ("parameterization", str), ("iterations", int),
                     ("final_cost", (int, float)), ("objects", list)):
        if k not in m or not isinstance(m[k], types) or isinstance(m[k], bool):
            raise MapFormatError(f"{path}: expected the key {k!r} ({getattr(types, '__name__', 'number')}), "
                                 f"got {str(m.get(k, 'nothing'))[:40]}")
    objs = []
    for i, o in enumerate(m["objects"]):
        try:
            P = np.asarray(o["P"], dtype=float)
            c = np.asarray(o["center"], dtype=float)
            oid, label = int(o["id"]), str(o["label"])
            ok = P.shape == (3, 3) and c.shape == (3,) and np.all(np.isfinite(P)) and np.all(np.isfinite(c))
            ok = ok and np.allclose(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)
        except (KeyError, TypeError, ValueError, IndexError):
            ok = False
        if not ok:
            raise MapFormatError(f"{path}: expected object {i} with id, label, a finite SPD 'P' (3×3) and "
                                 f"'center' (3), got {str(o)[:80]}")
        u = o.get("uncertainty")
        objs.append(MapObject(oid, label, Ellipsoid(P, c), u if isinstance(u, dict) else None,
                              _observed_by(path, i, o.get("observed_by"))))
    return m, objs


def _observed_by(path: Path, i: int, value) -> tuple | None:
    """An object's ``observed_by`` ([{recording, frames}]) as ((recording, frames), …)."""
    if value is None:
        return None
    ok = isinstance(value, list) and all(
        isinstance(e, dict) and isinstance(e.get("recording"), str) and isinstance(e.get("frames"), int)
        and not isinstance(e.get("frames"), bool) and e["frames"] >= 0 for e in value)
    if not ok:
        raise MapFormatError(f"{path}: expected object {i}'s observed_by as [{{recording: name, frames: count}}], "
                             f"got {str(value)[:60]}")
    return tuple((e["recording"], e["frames"]) for e in value)
