"""Shared fixtures and random generators for the spdslam tests.

Everything random is drawn from a ``numpy.random.Generator`` seeded from the test's node id,
so every test is reproducible on its own and independent of the order tests run in.

Fixtures
--------
``rng``  a seeded ``numpy.random.Generator``.
``gen``  a :class:`Gen` bound to that generator: random rotations, SPD matrices (general,
         exact spheres s²I, spheroids R diag(a, b, b) Rᵀ), ellipsoids, cameras and poses
         looking at an ellipsoid, and geometric helpers (surface sampling, projection)
         written independently of the code under test.
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest

import spdslam  # noqa: F401  (enables float64 in JAX before anything else runs)
import jax
import jaxlie

from spdslam import Camera, Ellipsoid

jax.config.update("jax_enable_x64", True)

#: The kinds of SPD matrix ``Gen.spd`` can draw.
SPD_KINDS = ("general", "sphere", "spheroid_oblate", "spheroid_prolate", "identity")


def fibonacci_sphere(n: int) -> np.ndarray:
    """n nearly uniform unit vectors (n×3) on the sphere (golden-angle spiral)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def surface_points(R, t, s, n: int = 20000) -> np.ndarray:
    """n points x = t + R diag(s) u, u on the unit sphere: the surface of the ellipsoid."""
    u = fibonacci_sphere(n)
    return np.asarray(t)[None, :] + (u * np.asarray(s)[None, :]) @ np.asarray(R).T


def world_to_camera(X, R_wc, c):
    """Camera coordinates of world points X (n×3) for a camera at c with axes R_wc (columns)."""
    return (np.asarray(X) - np.asarray(c)[None, :]) @ np.asarray(R_wc)


def pinhole(Xc, fx, fy, cx, cy) -> np.ndarray:
    """Pixel coordinates (n×2) of camera-frame points (n×3)."""
    Xc = np.asarray(Xc)
    return np.stack([fx * Xc[:, 0] / Xc[:, 2] + cx, fy * Xc[:, 1] / Xc[:, 2] + cy], axis=1)


class Gen:
    """Random geometry for tests, all numpy float64."""

    fibonacci_sphere = staticmethod(fibonacci_sphere)
    surface_points = staticmethod(surface_points)
    world_to_camera = staticmethod(world_to_camera)
    pinhole = staticmethod(pinhole)

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    # --- linear algebra ---------------------------------------------------------------
    def rotation(self) -> np.ndarray:
        """A uniformly random rotation matrix (det +1)."""
        q, r = np.linalg.qr(self.rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(r))[None, :]
        if np.linalg.det(q) < 0:
            q[:, 0] = -q[:, 0]
        return q

    def orthogonal(self) -> np.ndarray:
        """A random orthogonal matrix, det ±1."""
        q = self.rotation()
        if self.rng.random() < 0.5:
            q = q @ np.diag([1.0, 1.0, -1.0])
        return q

    def radii(self, lo: float = 0.2, hi: float = 3.0) -> np.ndarray:
        return self.rng.uniform(lo, hi, size=3)

    def spd(self, kind: str = "general", lo: float = 0.2, hi: float = 3.0) -> np.ndarray:
        """A random SPD matrix R diag(s²) Rᵀ of the given kind.

        ``sphere``: exactly s²I; ``spheroid_oblate``/``_prolate``: R diag(a, b, b) Rᵀ with a
        double eigenvalue (rotated, so the tie is only exact up to rounding);
        ``identity``: I.
        """
        if kind == "general":
            return self.spd_from(self.rotation(), self.radii(lo, hi) ** 2)
        if kind == "sphere":
            return self.rng.uniform(lo, hi) ** 2 * np.eye(3)
        if kind in ("spheroid_oblate", "spheroid_prolate"):
            a, b = np.sort(self.rng.uniform(lo, hi, size=2))
            if kind == "spheroid_prolate":
                a, b = b, a
            return self.spd_from(self.rotation(), np.array([a, b, b]) ** 2)
        if kind == "identity":
            return np.eye(3)
        raise ValueError(kind)

    @staticmethod
    def spd_from(R, w) -> np.ndarray:
        P = (np.asarray(R) * np.asarray(w)[None, :]) @ np.asarray(R).T
        return 0.5 * (P + P.T)

    def symmetric(self, scale: float = 1.0) -> np.ndarray:
        A = self.rng.normal(size=(3, 3)) * scale
        return 0.5 * (A + A.T)

    def tangent_vec(self, norm: float, dim: int = 6) -> np.ndarray:
        """A random vector of the given Euclidean norm."""
        v = self.rng.normal(size=dim)
        return v * (norm / np.linalg.norm(v))

    # --- ellipsoids -------------------------------------------------------------------
    def ellipsoid_params(self, kind: str = "general", center_scale: float = 3.0):
        """(R, t, s) of a random ellipsoid; ``kind`` as in ``spd`` (sphere: all s equal)."""
        R = self.rotation()
        t = self.rng.normal(size=3) * center_scale
        if kind == "general":
            s = self.radii()
        elif kind == "sphere":
            s = np.full(3, self.rng.uniform(0.2, 3.0))
        elif kind in ("spheroid_oblate", "spheroid_prolate"):
            a, b = np.sort(self.rng.uniform(0.2, 3.0, size=2))
            if kind == "spheroid_prolate":
                a, b = b, a
            s = np.array([a, b, b])
        else:
            raise ValueError(kind)
        return R, t, s

    def ellipsoid(self, kind: str = "general", center_scale: float = 3.0) -> Ellipsoid:
        R, t, s = self.ellipsoid_params(kind, center_scale)
        return Ellipsoid.from_axes(R, t, s)

    # --- cameras ----------------------------------------------------------------------
    def camera(self) -> Camera:
        w, h = 640.0, 480.0
        return Camera(
            fx=float(self.rng.uniform(300, 700)),
            fy=float(self.rng.uniform(300, 700)),
            cx=float(w / 2 + self.rng.uniform(-20, 20)),
            cy=float(h / 2 + self.rng.uniform(-20, 20)),
            width=w,
            height=h,
        )

    def look_at(self, c, target, jitter: float = 0.0) -> np.ndarray:
        """Rotation R_wc (columns = camera x, y, z axes in the world) with z towards target."""
        z = np.asarray(target, float) - np.asarray(c, float)
        z = z / np.linalg.norm(z)
        if jitter:
            z = z + self.rng.normal(size=3) * jitter
            z = z / np.linalg.norm(z)
        a = self.rng.normal(size=3)
        x = a - (a @ z) * z
        x = x / np.linalg.norm(x)
        y = np.cross(z, x)
        return np.stack([x, y, z], axis=1)

    @staticmethod
    def pose(R_wc, c) -> jaxlie.SE3:
        """Camera-to-world SE3 from the camera axes R_wc and centre c."""
        return jaxlie.SE3.from_rotation_and_translation(
            jaxlie.SO3.from_matrix(np.asarray(R_wc, float)), np.asarray(c, float)
        )

    def pose_looking_at(self, R, t, s, dist=(3.0, 8.0), jitter: float = 0.05):
        """(T_wc, R_wc, c): a camera at (dist × largest radius) from t looking at it."""
        d = self.rng.uniform(*dist) * float(np.max(s))
        c = np.asarray(t) + d * self.tangent_vec(1.0, 3)
        R_wc = self.look_at(c, t, jitter)
        return self.pose(R_wc, c), R_wc, c

    def pose_random(self, scale: float = 2.0) -> jaxlie.SE3:
        return self.pose(self.rotation(), self.rng.normal(size=3) * scale)


def _seed(nodeid: str) -> int:
    return zlib.crc32(nodeid.encode())


@pytest.fixture
def rng(request) -> np.random.Generator:
    return np.random.default_rng(_seed(request.node.nodeid))


@pytest.fixture
def gen(rng) -> Gen:
    return Gen(rng)
