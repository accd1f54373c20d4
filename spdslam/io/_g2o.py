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
from typing import Any

import jaxlie
import numpy as np

from ..factors import BetweenFactor, PriorFactor
from ..geometry.se3 import compose_params
from ..solver import NonlinearFactorGraph, Values

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


def rpy_to_quaternion(roll, pitch, yaw) -> np.ndarray:
    """(w, x, y, z) of Rz(yaw) Ry(pitch) Rx(roll) (stacked on the first axis for arrays)."""
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


# tag: (number of numbers after the tag, description)
_LAYOUT = {
    "VERTEX3": (7, "id x y z roll pitch yaw"),
    "EDGE3": (29, "i j x y z roll pitch yaw and 21 information entries"),
    "VERTEX_SE3:QUAT": (8, "id x y z qx qy qz qw"),
    "EDGE_SE3:QUAT": (30, "i j x y z qx qy qz qw and 21 information entries"),
}


def _upper_to_info(vals) -> np.ndarray:
    """(…, 21) upper-triangle rows → (…, 6, 6) symmetric matrices."""
    vals = np.asarray(vals, dtype=float)
    M = np.zeros(vals.shape[:-1] + (6, 6))
    M[..., _IU[0], _IU[1]] = vals
    M[..., _IU[1], _IU[0]] = vals
    return M


def _rpy_quaternions(rpy: np.ndarray) -> np.ndarray:
    """(n, 3) roll, pitch, yaw → (n, 4) (w, x, y, z) of Rz(yaw) Ry(pitch) Rx(roll)."""
    return rpy_to_quaternion(rpy[:, 0], rpy[:, 1], rpy[:, 2]).T.reshape(-1, 4)


def parse_g2o(text: str, name: str = "<string>") -> PoseGraph:
    """Parse the contents of a pose-graph file (see the module docstring)."""
    # rows: (line number, tag, ids, numbers); the geometry is then converted in bulk
    rows: dict[str, list] = {tag: [] for tag in _LAYOUT}
    order: list[tuple[str, int]] = []  # edges in file order: (tag, row)
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
            raise ValueError(
                f"{where}: expected integer ids after {tag}, got {' '.join(tok[1:1 + nid])}"
            ) from None
        try:
            num = [float(t) for t in tok[1 + nid :]]
        except ValueError:
            raise ValueError(f"{where}: expected numbers after the ids of {tag}") from None
        if not np.all(np.isfinite(num)):
            raise ValueError(f"{where}: expected finite numbers in {tag}")
        if not tag.startswith("VERTEX"):
            order.append((tag, len(rows[tag])))
        rows[tag].append((lineno, ids, num))

    def poses_of(tag):
        """(line numbers, ids (n, k), SE3 wxyz_xyz (n, 7), numbers (n, c)) of one tag."""
        r = rows[tag]
        count = _LAYOUT[tag][0]
        k = 1 if tag.startswith("VERTEX") else 2
        lines = np.array([x[0] for x in r], dtype=int)
        ids = np.array([x[1] for x in r], dtype=int).reshape(len(r), k)
        num = np.array([x[2] for x in r], dtype=float).reshape(len(r), count - k)
        if tag in ("VERTEX3", "EDGE3"):
            q = _rpy_quaternions(num[:, 3:6])
        else:
            q = num[:, [6, 3, 4, 5]]  # (qw, qx, qy, qz)
            norm = np.linalg.norm(q, axis=1)
            if np.any(norm < 1e-12):
                bad = int(lines[np.argmax(norm < 1e-12)])
                raise ValueError(f"{name}:{bad}: expected a non-zero quaternion qx qy qz qw")
            q = q / norm[:, None]
        return lines, ids, np.concatenate([q, num[:, :3]], axis=1), num

    vertices: dict[int, jaxlie.SE3] = {}
    for tag in ("VERTEX3", "VERTEX_SE3:QUAT"):
        if rows[tag]:
            _, ids, wxyz_xyz, _ = poses_of(tag)
            for i, p in zip(ids[:, 0].tolist(), wxyz_xyz):
                vertices[i] = jaxlie.SE3(p)

    built: dict[str, Any] = {}
    for tag in ("EDGE3", "EDGE_SE3:QUAT"):
        if not rows[tag]:
            continue
        lines, ids, wxyz_xyz, num = poses_of(tag)
        info = _upper_to_info(num[:, -21:])
        if tag == "EDGE3":  # gtsam reads TORO information in (ω, v) order
            info = info[:, SWAP_ROT_TRANS][:, :, SWAP_ROT_TRANS]
        ok = np.linalg.eigvalsh(info)[:, 0] > 0
        if not ok.all():
            bad = int(lines[np.argmin(ok)])
            raise ValueError(f"{name}:{bad}: expected a positive definite information matrix")
        built[tag] = (ids.tolist(), wxyz_xyz, info)
    edges = []
    for tag, r in order:
        ids, wxyz_xyz, info = built[tag]
        edges.append(Edge(ids[r][0], ids[r][1], jaxlie.SE3(wxyz_xyz[r]), info[r]))

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
            odo[e.i] = np.asarray(e.measured.wxyz_xyz, dtype=float)
    first, last = min(ids), max(ids)
    p = np.r_[1.0, np.zeros(6)]
    # jaxlie takes NumPy arrays too (its annotations say jax.Array)
    poses = {first: jaxlie.SE3(p)}  # type: ignore[arg-type]
    for i in range(first, last):
        if i not in odo:
            raise ValueError(f"{name}: no vertices, and no odometry edge {i} -> {i + 1} "
                             "to build the initial poses from")
        p = compose_params(p, odo[i])
        p[:4] /= np.linalg.norm(p[:4])
        poses[i + 1] = jaxlie.SE3(p)  # type: ignore[arg-type]
    return poses


def read_g2o(path: str | os.PathLike) -> PoseGraph:
    """Read a TORO/g2o 3-D pose-graph file; malformed lines raise ``ValueError("file:line: …")``."""
    path = os.fspath(path)
    with open(path) as fh:
        return parse_g2o(fh.read(), name=path)


def pose_graph_factors(
    pg: PoseGraph,
    prior_sigma: Any = 1e-6,
    prior_key: int | None = None,
    key: Any = None,
    robust=None,
):
    """(graph, values): one BetweenFactor per edge (its information) and a PriorFactor on the
    first pose (``prior_key``, default the smallest id) at its initial value with ``prior_sigma``
    (jaxlie order). ``key(id)`` maps ids to keys (default: the id itself)."""
    key = key or (lambda i: i)
    graph = NonlinearFactorGraph()
    first = min(pg.poses) if prior_key is None else prior_key
    graph.add(PriorFactor(key(first), pg.poses[first], sigma=prior_sigma))
    for e in pg.edges:
        graph.add(BetweenFactor(key(e.i), key(e.j), e.measured, information=e.information,
                                robust=robust))
    values = Values({key(i): T for i, T in sorted(pg.poses.items())})
    return graph, values
