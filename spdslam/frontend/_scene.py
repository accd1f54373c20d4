"""Scene knowledge from the initial objects: the horizontal planes several objects rest on.

An object rests on a plane when the lowest point of its ellipsoid along ``up``,

    p = t − P u / √(uᵀPu)   (height h = u·t − √(uᵀPu)),

lies on it. Support planes are the heights that at least ``min_objects`` objects' lowest
points share within ``tolerance``: found greedily (the densest window first), each plane
fitted to its objects' lowest points (total least squares, the normal kept within
``max_tilt`` of ``up``, else ``up`` itself), then its members taken again as the objects
within ``tolerance`` of the fitted plane and the plane refitted to them; each object
belongs to the plane it was taken for, and objects within ``min_separation`` of a plane
that are not on it rest on none (two planes are never closer than that). Nothing here
reads ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SupportPlanes", "estimate_support_planes", "lowest_points"]


@dataclass(frozen=True)
class SupportPlanes:
    """``planes`` (k, 4): [n, d] with n·x + d = 0, unit normals facing up, the most
    populated first; ``assignment`` {object id: plane index}."""

    planes: np.ndarray
    assignment: dict

    def plane_of(self, key):
        """The plane (4,) object ``key`` rests on, or None."""
        i = self.assignment.get(key)
        return None if i is None else self.planes[i]


def lowest_points(centers, shapes, up):
    """(heights (n,), points (n, 3)): the lowest point of each ellipsoid along ``up``."""
    u = np.asarray(up, float) / np.linalg.norm(up)
    c, P = np.asarray(centers, float), np.asarray(shapes, float)
    Pu = P @ u
    r = np.sqrt(np.maximum(Pu @ u, 0.0))[:, None]
    pts = c - Pu / np.maximum(r, 1e-12)
    return pts @ u, pts


def _plane_through(points, up, max_tilt):
    """[n, d] of the plane through ``points`` (total least squares), n within ``max_tilt``
    rad of ``up``, else n = up; d from the median height."""
    n = up
    if len(points) >= 3:
        q = points - points.mean(axis=0)
        _, s, Vt = np.linalg.svd(q, full_matrices=False)
        m = Vt[2] * np.sign(Vt[2] @ up)
        if s[1] > 1e-9 and np.arccos(np.clip(m @ up, -1.0, 1.0)) <= max_tilt:
            n = m
    return np.r_[n, -np.median(points @ n)]


def estimate_support_planes(ellipsoids: dict, up, min_objects: int = 3, tolerance: float = 0.05,
                            min_separation: float = 0.15,
                            max_tilt: float = np.radians(5.0)) -> SupportPlanes:
    """The support planes of the initial ``ellipsoids`` {id: Ellipsoid} (module docstring)
    and the object each carries."""
    u = np.asarray(up, float) / np.linalg.norm(up)
    ids = list(ellipsoids)
    if not ids:
        return SupportPlanes(np.zeros((0, 4)), {})
    h, pts = lowest_points([np.asarray(ellipsoids[k].center) for k in ids],
                           [np.asarray(ellipsoids[k].P) for k in ids], u)
    free = np.ones(len(ids), bool)
    planes: list = []
    assignment: dict = {}
    while free.sum() >= min_objects:
        hf = np.where(free, h, np.inf)
        # the densest window [h_i − tol, h_i + tol] over free objects
        counts = np.sum(free[None, :] & (np.abs(h[None, :] - h[:, None]) <= tolerance), axis=1)
        counts = np.where(free, counts, 0)
        best = int(np.argmax(counts))
        if counts[best] < min_objects:
            break
        members = free & (np.abs(hf - h[best]) <= tolerance)
        centre = np.median(h[members])  # re-centre the window once on its median
        members = free & (np.abs(hf - centre) <= tolerance)
        if members.sum() < min_objects:
            break
        plane = _plane_through(pts[members], u, max_tilt)
        members = free & (np.abs(pts @ plane[:3] + plane[3]) <= tolerance)  # on the fitted plane
        if members.sum() < min_objects:
            break
        plane = _plane_through(pts[members], u, max_tilt)
        for i in np.flatnonzero(members):
            assignment[ids[i]] = len(planes)
        planes.append(plane)
        # no second plane within min_separation of this one: objects there rest on none
        free &= np.abs(pts @ plane[:3] + plane[3]) > min_separation
    return SupportPlanes(np.array(planes).reshape(-1, 4), assignment)
