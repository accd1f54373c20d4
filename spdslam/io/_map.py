"""``map.json``: the objects of a map (and how it was made), written by ``spdslam run`` and
read back by ``spdslam evaluate`` (see docs/formats.md)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import Ellipsoid
from ._json import dumps_strict
from ._parse import SequenceFormatError, read_text

__all__ = ["MAP_KEYS", "MapObject", "MapFormatError", "map_document", "read_map", "write_map"]

#: The keys of map.json, in order, with what each holds (``map_document``; docs/formats.md).
MAP_KEYS = {
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
    marginal standard deviations of its centre (m) and log-radii (``mapping``)."""

    id: int
    label: str
    ellipsoid: Ellipsoid
    uncertainty: dict | None = None

    def as_dict(self) -> dict:
        R, s = (np.asarray(a) for a in self.ellipsoid.axes())
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
        return out


def map_document(*, method: str, parameterization: str, iterations: int, final_cost: float,
                 initial_cost: float, converged: bool, reason: str, settings: dict, objects,
                 failed: dict, notes, association: dict, cost_by_factor: dict,
                 trajectory: dict | None = None) -> dict:
    """The content of map.json (``MAP_KEYS``, in that order; ``trajectory`` only when given
    and not empty) from a run's figures; ``objects`` are ``MapObject`` s. ``spdslam run`` may
    add ``sequence`` (the folder it read) and ``to_groundtruth`` (4×4) after them."""
    out = {
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
        objs.append(MapObject(oid, label, Ellipsoid(P, c), u if isinstance(u, dict) else None))
    return m, objs
