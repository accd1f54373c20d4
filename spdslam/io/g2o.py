"""Read 3-D pose-graph files (TORO and g2o), with gtsam's interpretation of both.

Lines (whitespace separated; blank lines and lines starting with ``#`` are skipped):

    VERTEX3          id x y z roll pitch yaw
    EDGE3            i j x y z roll pitch yaw  I₁₁ I₁₂ … I₁₆ I₂₂ … I₆₆      (TORO)
    VERTEX_SE3:QUAT  id x y z qx qy qz qw
    EDGE_SE3:QUAT    i j x y z qx qy qz qw     I₁₁ I₁₂ … I₁₆ I₂₂ … I₆₆      (g2o)
    FIX              id …

A pose is T = (R, t); the measurement of edge (i, j) is T̄ᵢⱼ ≈ Tᵢ⁻¹Tⱼ. The 21 numbers are the
upper triangle, row by row, of the 6×6 information matrix. As gtsam (``readG2o``) reads them:

- roll/pitch/yaw: R = Rz(yaw) Ry(pitch) Rx(roll) (gtsam ``Rot3::Ypr(yaw, pitch, roll)``);
- EDGE3 information is in (rotation, translation) order, gtsam's own Pose3 tangent order;
- EDGE_SE3:QUAT information is in (translation, rotation) order, g2o's and jaxlie's.

Edges returned here carry information in jaxlie's order (v, ω), translation first.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Hashable

import jaxlie
import numpy as np

__all__ = ["PoseGraph", "Edge", "read_g2o", "parse_g2o", "rpy_to_quaternion", "pose_graph_factors"]

# (rotation, translation) → (translation, rotation), and back (an involution).
SWAP_ROT_TRANS = np.array([3, 4, 5, 0, 1, 2])
_IU = np.triu_indices(6)


@dataclass
class Edge:
    """A relative-pose measurement T̄ᵢⱼ ≈ Tᵢ⁻¹Tⱼ with 6×6 information in jaxlie order (v, ω)."""

    i: int
    j: int
    measured: jaxlie.SE3
    information: np.ndarray


@dataclass
class PoseGraph:
    """poses: id → initial pose (from the vertices, else the odometry chain);
    edges: in file order; fixed: ids from FIX lines; source: the file name."""

    poses: dict[int, jaxlie.SE3]
    edges: list[Edge]
    fixed: list[int] = field(default_factory=list)
    source: str = ""
    has_vertices: bool = False


def rpy_to_quaternion(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(w, x, y, z) of Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    cp, sp = np.cos(0.5 * pitch), np.sin(0.5 * pitch)
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def _se3(wxyz, xyz) -> jaxlie.SE3:
    q = np.asarray(wxyz, dtype=float)
    q = q / np.linalg.norm(q)
    return jaxlie.SE3(np.concatenate([q, np.asarray(xyz, dtype=float)]))


# tag: (number of numbers after the tag, description)
_LAYOUT = {
    "VERTEX3": (7, "id x y z roll pitch yaw"),
    "EDGE3": (29, "i j x y z roll pitch yaw and 21 information entries"),
    "VERTEX_SE3:QUAT": (8, "id x y z qx qy qz qw"),
    "EDGE_SE3:QUAT": (30, "i j x y z qx qy qz qw and 21 information entries"),
}


def _upper_to_info(vals) -> np.ndarray:
    M = np.zeros((6, 6))
    M[_IU] = vals
    return M + np.triu(M, 1).T


def parse_g2o(text: str, name: str = "<string>") -> PoseGraph:
    """Parse the contents of a pose-graph file (see the module docstring)."""
    vertices: dict[int, jaxlie.SE3] = {}
    edges: list[Edge] = []
    fixed: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        tag = tok[0]
        where = f"{name}:{lineno}"
        if tag == "FIX":
            try:
                fixed.extend(int(t) for t in tok[1:])
            except ValueError:
                raise ValueError(f"{where}: expected integer ids after FIX") from None
            continue
        if tag not in _LAYOUT:
            raise ValueError(
                f"{where}: expected one of {', '.join(_LAYOUT)} or FIX, got {tag!r}"
            )
        count, desc = _LAYOUT[tag]
        if len(tok) - 1 != count:
            raise ValueError(
                f"{where}: expected {tag} followed by {count} numbers ({desc}), "
                f"got {len(tok) - 1}"
            )
        nid = 1 if tag.startswith("VERTEX") else 2
        try:
            ids = [int(t) for t in tok[1 : 1 + nid]]
        except ValueError:
            raise ValueError(f"{where}: expected integer ids in {tag}, got {tok[1:1 + nid]}") from None
        try:
            num = np.array([float(t) for t in tok[1 + nid :]])
        except ValueError:
            raise ValueError(f"{where}: expected numbers after the ids of {tag}") from None
        if not np.all(np.isfinite(num)):
            raise ValueError(f"{where}: expected finite numbers in {tag}")
        if tag in ("VERTEX3", "EDGE3"):
            pose = _se3(rpy_to_quaternion(*num[3:6]), num[:3])
        else:
            q = num[3:7]
            if np.linalg.norm(q) < 1e-12:
                raise ValueError(f"{where}: expected a non-zero quaternion qx qy qz qw")
            pose = _se3([q[3], q[0], q[1], q[2]], num[:3])
        if tag.startswith("VERTEX"):
            vertices[ids[0]] = pose
            continue
        info = _upper_to_info(num[-21:])
        if tag == "EDGE3":  # gtsam reads it in (ω, v) order
            info = info[np.ix_(SWAP_ROT_TRANS, SWAP_ROT_TRANS)]
        if np.any(np.linalg.eigvalsh(info) <= 0):
            raise ValueError(f"{where}: expected a positive definite information matrix")
        edges.append(Edge(ids[0], ids[1], pose, info))

    poses = dict(vertices)
    if not vertices and edges:
        poses = _odometry_chain(edges, name)
    return PoseGraph(poses, edges, fixed, name, bool(vertices))


def _odometry_chain(edges: list[Edge], name: str) -> dict[int, jaxlie.SE3]:
    """T_first = I, T_{i+1} = T_i T̄_{i,i+1}, over the ids from the smallest to the largest."""
    odo: dict[int, np.ndarray] = {}
    ids: set[int] = set()
    for e in edges:
        ids.update((e.i, e.j))
        if e.j == e.i + 1 and e.i not in odo:
            odo[e.i] = np.asarray(e.measured.as_matrix())
    first, last = min(ids), max(ids)
    T = np.eye(4)
    poses = {first: jaxlie.SE3.identity()}
    mats = [T]
    for i in range(first, last):
        if i not in odo:
            raise ValueError(f"{name}: no vertices, and no odometry edge {i} -> {i + 1} "
                             "to build the initial poses from")
        T = T @ odo[i]
        mats.append(T)
    wxyz_xyz = np.asarray(jaxlie.SE3.from_matrix(np.stack(mats)).wxyz_xyz)
    return {first + k: jaxlie.SE3(wxyz_xyz[k]) for k in range(len(mats))}


def read_g2o(path: str | os.PathLike) -> PoseGraph:
    """Read a TORO/g2o 3-D pose-graph file; malformed lines raise ``ValueError("file:line: …")``."""
    path = os.fspath(path)
    with open(path) as fh:
        return parse_g2o(fh.read(), name=path)


def pose_graph_factors(
    pg: PoseGraph,
    prior_sigma: Any = 1e-6,
    prior_key: Hashable | None = None,
    key: Any = None,
    robust=None,
):
    """(graph, values): one BetweenFactor per edge (its information) and a PriorFactor on the
    first pose (``prior_key``, default the smallest id) at its initial value with ``prior_sigma``
    (jaxlie order). ``key(id)`` maps ids to keys (default: the id itself)."""
    from ..factors import BetweenFactor, PriorFactor
    from ..solver import NonlinearFactorGraph, Values

    key = key or (lambda i: i)
    graph = NonlinearFactorGraph()
    first = min(pg.poses) if prior_key is None else prior_key
    graph.add(PriorFactor(key(first), pg.poses[first], sigma=prior_sigma))
    for e in pg.edges:
        graph.add(BetweenFactor(key(e.i), key(e.j), e.measured, information=e.information,
                                robust=robust))
    values = Values({key(i): T for i, T in sorted(pg.poses.items())})
    return graph, values
