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

import os
from pathlib import Path
import zlib

# SPDSLAM_TEST_XLA_FAST=1 compiles the tests' XLA programs with the backend optimisation off
# (--xla_backend_optimization_level=0): most run once, so the suite is ~25 % faster; opt-in.
# test_factor_jacobians.py::test_jacobian_matches_central_differences[ellipsoid_measurement-spd]
# hung under it, and later under XLA's default too (CI, 2026-12-06): jaxlib's batched eigh
# waiting on XLA's intra-op pool from inside it; check_jacobians now keeps each batch below the
# size at which jaxlib splits it (docs/install.md, "XLA's threads").
if os.environ.get("SPDSLAM_TEST_XLA_FAST") == "1" and \
        "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                               " --xla_backend_optimization_level=0").strip()

import numpy as np
import pytest

import spdslam  # noqa: F401  (enables float64 in JAX before anything else runs)
import jax
import jaxlie

from spdslam import Camera, Ellipsoid

jax.config.update("jax_enable_x64", True)
# No test reads or writes JAX's persistent compilation cache: whether JAX uses it is decided
# once per process, at the first compilation, so pointing the cache directory elsewhere
# later does not turn it off (the CLI callback sets the directory; see
# _no_persistent_compilation_cache).
jax.config.update("jax_enable_compilation_cache", False)

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


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """After each test module, drop the compiled solver programs (``solver.clear_caches``):
    a whole-suite process otherwise keeps thousands of XLA executables, each mapped into
    memory, and crashes inside XLA once it reaches the kernel's ``vm.max_map_count``
    (65530 here; seen as segfaults and aborts in compilation and cache code)."""
    yield
    from spdslam.solver import clear_caches

    clear_caches()


@pytest.fixture(autouse=True)
def _no_persistent_compilation_cache(monkeypatch):
    """Every test runs with JAX's persistent compilation cache off (the CLI callback turns it
    on from ``SPDSLAM_CACHE_DIR``): no test reads a program an earlier one compiled or writes
    into the user's home, and the process's former setting comes back afterwards. The tests of
    the cache itself set ``SPDSLAM_CACHE_DIR`` to a directory of their own."""
    old = jax.config.jax_compilation_cache_dir
    monkeypatch.setenv("SPDSLAM_CACHE_DIR", "off")
    yield
    jax.config.update("jax_compilation_cache_dir", old)


@pytest.fixture
def rng(request) -> np.random.Generator:
    return np.random.default_rng(_seed(request.node.nodeid))


@pytest.fixture
def gen(rng) -> Gen:
    return Gen(rng)


# --- shared helpers (imported by the test modules: ``from conftest import …``) --------------


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation matrix (a normalised Gaussian quaternion)."""
    q = rng.normal(size=4)
    return np.asarray(jaxlie.SO3(jax.numpy.asarray(q / np.linalg.norm(q))).as_matrix())


def se3(x) -> jaxlie.SE3:
    """Exp of a 6-vector (v, ω)."""
    return jaxlie.SE3.exp(jax.numpy.asarray(x, dtype=float))


def log_x_residual(T):
    """A residual that is NaN where the x translation of T is negative (non-finite input)."""
    return jax.numpy.log(T.translation()[:1])


def upright_ellipsoid(yaw=0.4, radii=(0.6, 0.35, 0.3), xy=(1.0, -0.5)) -> Ellipsoid:
    """An ellipsoid with its third axis vertical, standing on z = 0."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return Ellipsoid.from_axes(R, [xy[0], xy[1], radii[2]], radii)


def ring_of_views(target, n=6, radius=3.5, height=1.4) -> list:
    """n camera-to-world poses on a horizontal circle around ``target``, looking at it."""
    from spdslam.geometry import look_at

    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    eyes = np.c_[target[0] + radius * np.cos(a), target[1] + radius * np.sin(a), np.full(n, height)]
    return [look_at(e, target) for e in eyes]


def cli_runner():
    """A typer CliRunner that keeps stderr apart (click < 8.2 mixes it in unless told)."""
    from typer.testing import CliRunner

    try:
        return CliRunner(mix_stderr=False)
    except TypeError:  # click >= 8.2 always captures stderr apart
        return CliRunner()


def cli_subprocess(*args, timeout: float = 900, env: dict | None = None):
    """``spdslam ARGS…`` in a fresh Python process with XLA's default optimisation (for the
    few tests whose time is spent running, not compiling, programs: a real recording):
    the ``CompletedProcess`` with text stdout and stderr."""
    import subprocess
    import sys

    env = dict(os.environ if env is None else env)
    flags = [f for f in env.get("XLA_FLAGS", "").split() if "xla_backend_optimization_level" not in f]
    env["XLA_FLAGS"] = " ".join(flags)
    code = "import sys; from spdslam.cli import app; sys.argv[0] = 'spdslam'; app()"
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, env=env, check=False)


def cli_invoke(*args):
    """``spdslam ARGS…`` through a CliRunner, every argument passed as ``str``."""
    from spdslam import cli

    return cli_runner().invoke(cli.app, [str(a) for a in args])


def assert_cli_ok(result):
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)


def assert_cli_error(result, *fragments) -> str:
    """Exit status 2 (a ``SystemExit``, no traceback) and exactly one line ``spdslam: error:
    …`` on stderr holding every fragment; returns that line."""
    assert result.exit_code == 2, (result.exit_code, result.stdout, result.stderr, result.exception)
    assert isinstance(result.exception, SystemExit), result.exception
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("spdslam: error: "), lines[0]
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


def batched_landmarks(param: str, R, t, s):
    """Batched landmarks (leading axis n) of one parameterisation ("spd", "rts", "full")
    from axes R (n, 3, 3), centres t (n, 3) and radii s (n, 3); exact spheres stay exactly
    s²I (no rounding through R R^T)."""
    from spdslam import EllipsoidFull, EllipsoidRTS

    P = np.einsum("nij,nj,nkj->nik", R, s**2, R)
    sphere = np.all(s == s[:, :1], axis=1)
    P[sphere] = (s[sphere, 0] ** 2)[:, None, None] * np.eye(3)
    e = Ellipsoid(jax.numpy.asarray(P), jax.numpy.asarray(t))
    if param == "spd":
        return e
    if param == "rts":
        return EllipsoidRTS(jax.vmap(jaxlie.SO3.from_matrix)(jax.numpy.asarray(R)),
                            jax.numpy.asarray(t), jax.numpy.asarray(s))
    if param == "full":
        return jax.vmap(EllipsoidFull.from_ellipsoid)(e)
    raise ValueError(param)


def _central_differences(residual, values, args, which, h):
    """∂r/∂δ of variable ``which`` by central differences along its tangent basis."""
    from spdslam import manifold

    dim = manifold.tangent_dim(values[which])

    def f(delta):
        vals = list(values)
        vals[which] = manifold.retract(vals[which], delta)
        return jax.numpy.atleast_1d(residual(*vals, *args))

    steps = jax.numpy.concatenate([h * jax.numpy.eye(dim), -h * jax.numpy.eye(dim)])
    r = jax.vmap(f)(steps)  # one traced copy of the residual for all 2·dim steps
    return ((r[:dim] - r[dim:]) / (2 * h)).T


#: Configurations per vectorised chunk of ``check_jacobians``: with tangent spaces of at most
#: 10 dimensions, 32 × 2 × 10 = 640 matrices per LAPACK call.
CHECK_CHUNK = 32


def check_jacobians(residual, values, args, kind=None, symmetric_cols=None, h=1e-6, tol=2e-5):
    """Assert that the tangent Jacobians of ``residual`` (``factors.tangent_jacobians``, by
    forward-mode autodiff through each variable's retraction) match central differences,
    batched over a leading axis of ``values`` and ``args``, and that nothing is NaN.

    Exact spheres (``kind == 2``) are compared only in ``symmetric_cols`` of the last
    variable when given (see test_factor_jacobians). Returns (r, [J per variable]).
    """
    from spdslam.factors import tangent_jacobians

    def one(vals, a):
        r, J = tangent_jacobians(residual, vals, a)
        return r, J, [_central_differences(residual, vals, a, k, h) for k in range(len(vals))]

    # In chunks of CHECK_CHUNK configurations (lax.map): each of jaxlib's batched LAPACK calls
    # then holds ≤ CHECK_CHUNK × 2 × dim matrices, below the 1 482 3×3 eigen-decompositions at
    # which it splits the batch over XLA's pool and can wait for itself (docs/install.md).
    r, J, J_fd = jax.jit(lambda v, a: jax.lax.map(lambda va: one(*va), (v, a), batch_size=CHECK_CHUNK))(
        tuple(values), tuple(args))
    assert np.all(np.isfinite(np.asarray(r))), "NaN/inf residual"
    for k, (Ja, Jn) in enumerate(zip(J, J_fd)):
        Ja, Jn = np.asarray(Ja), np.asarray(Jn)
        assert np.all(np.isfinite(Ja)), f"non-finite Jacobian for variable {k}"
        scale = 1.0 + np.max(np.abs(Jn), axis=(1, 2), keepdims=True)
        err = np.abs(Ja - Jn) / scale
        if symmetric_cols is not None and k == len(values) - 1:
            keep = np.zeros(err.shape[-1], dtype=bool)
            keep[list(symmetric_cols)] = True
            mask = np.ones_like(err, dtype=bool)
            mask[np.asarray(kind) == 2] = keep[None, :]
            err = np.where(mask, err, 0.0)
        worst = np.unravel_index(np.argmax(err), err.shape)
        assert err.max() < tol, (
            f"variable {k}: max scaled error {err.max():.3g} at configuration {worst[0]}"
            + ("" if kind is None else f" (kind {np.asarray(kind)[worst[0]]})")
            + f", entry {worst[1:]}\nanalytic {Ja[worst[0]]}\ncentral differences {Jn[worst[0]]}"
        )
    return np.asarray(r), [np.asarray(j) for j in J]


def pytest_collection_modifyitems(config, items):
    """Studies marked ``slow`` (run on demand) may take longer than the suite's per-test
    timeout (pyproject.toml): they get none."""
    for item in items:
        if item.get_closest_marker("slow") is not None and item.get_closest_marker("timeout") is None:
            item.add_marker(pytest.mark.timeout(0))


#: ``-n auto`` (pyproject.toml) starts one test process per core, but no more than this: each
#: holds its own JAX runtime and compiled programs (a few GB on the largest tests).
MAX_TEST_PROCESSES = 4


def pytest_xdist_auto_num_workers(config):
    """The process count of ``-n auto``: the cores this process may use, at most
    ``MAX_TEST_PROCESSES``."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_TEST_PROCESSES))


# --- a detector's output folder (issue 38), as the tools write it ---------------------------


def _calibration(camera, dist, dialect: str) -> str:
    """A calibration file's text in a dialect: "opencv", "ros" (camera_info) or "kalibr";
    ``dist`` radial-tangential (5) or a ``geometry.Equidistant`` lens (ROS and Kalibr)."""
    from spdslam.geometry import Equidistant

    fx, fy, cx, cy, w, h = camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
    d = [float(v) for v in dist]
    if isinstance(dist, Equidistant):
        if dialect == "ros":
            return (f"image_width: {int(w)}\nimage_height: {int(h)}\ncamera_name: fisheye\n"
                    f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: [{fx!r}, 0, {cx!r}, 0, {fy!r}, {cy!r}, 0, 0, 1]\n"
                    f"distortion_model: equidistant\ndistortion_coefficients:\n  rows: 1\n  cols: 4\n  data: {d!r}\n")
        assert dialect == "kalibr", dialect
        return (f"cam0:\n  camera_model: pinhole\n  intrinsics: [{fx!r}, {fy!r}, {cx!r}, {cy!r}]\n"
                f"  distortion_model: equidistant\n  distortion_coeffs: {d!r}\n  resolution: [{int(w)}, {int(h)}]\n")
    if dialect == "opencv":
        return "%YAML:1.0\n" + "".join(f"Camera.{k}: {v!r}\n" for k, v in zip(
            ("fx", "fy", "cx", "cy", "width", "height", "k1", "k2", "p1", "p2", "k3"), [fx, fy, cx, cy, w, h, *d]))
    if dialect == "ros":
        return (f"image_width: {int(w)}\nimage_height: {int(h)}\ncamera_name: rgb\n"
                f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: [{fx!r}, 0, {cx!r}, 0, {fy!r}, {cy!r}, 0, 0, 1]\n"
                f"distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: {d!r}\n")
    assert dialect == "kalibr" and d[4] == 0.0  # radtan has no k3
    return (f"cam0:\n  camera_model: pinhole\n  intrinsics: [{fx!r}, {fy!r}, {cx!r}, {cy!r}]\n"
            f"  distortion_model: radtan\n  distortion_coeffs: {d[:4]!r}\n  resolution: [{int(w)}, {int(h)}]\n"
            f"  rostopic: /cam0/image_raw\n")


def write_detector_folder(seq, dest, *, dist=None, boxes=None, detector: str = "yolo",
                          calibration: str = "ros", times: str = "rgb"):
    """``seq`` as a detector's output folder (``boxes``: the boxes to write, default the
    sequence's; the measured, distorted ones when ``dist`` is given). Labels outside COCO's
    80 get their own names: data.yaml for YOLO, categories for COCO. Returns ``dest``."""
    import json

    from spdslam.io import COCO80, COCO_IDS

    dist = np.zeros(5) if dist is None else dist
    dest.mkdir(parents=True)
    coco = all(d.label in COCO80 for d in seq.detections)
    classes = list(COCO80) if coco else sorted({d.label for d in seq.detections})
    cam = seq.camera
    (dest / "camera.yaml").write_text(_calibration(cam, dist, calibration))
    rows = np.c_[seq.timestamps, seq.poses_tum]
    (dest / "trajectory.txt").write_text("".join(" ".join(repr(float(v)) for v in r) + "\n" for r in rows))
    boxes = np.stack([d.box for d in seq.detections]) if boxes is None else np.asarray(boxes)
    stamps = sorted({d.timestamp for d in seq.detections})
    names = {t: f"img_{i:05d}" for i, t in enumerate(stamps)}
    if times == "rgb":
        (dest / "rgb.txt").write_text("# timestamp filename\n"
                                      + "".join(f"{t!r} rgb/{n}.png\n" for t, n in names.items()))
    elif times == "euroc":
        (dest / "mav0" / "cam0").mkdir(parents=True)
        (dest / "mav0" / "cam0" / "data.csv").write_text(
            "#timestamp [ns],filename\n" + "".join(f"{round(t * 1e9)},{n}.png\n" for t, n in names.items()))
    else:
        names = {t: repr(t) for t in stamps}
    if detector == "yolo":
        (dest / "labels").mkdir()
        if not coco:  # Ultralytics' names, as {id: name}
            (dest / "data.yaml").write_text("names:\n" + "".join(f"  {i}: {n}\n" for i, n in enumerate(classes)))
        lines: dict = {t: [] for t in stamps}
        for d, b in zip(seq.detections, boxes):
            cx, cy = float(b[0] + b[2]) / 2 / cam.width, float(b[1] + b[3]) / 2 / cam.height
            w, h = float(b[2] - b[0]) / cam.width, float(b[3] - b[1]) / cam.height
            lines[d.timestamp].append(f"{classes.index(d.label)} {cx!r} {cy!r} {w!r} {h!r} {float(d.score)!r}\n")
        for t, text in lines.items():
            (dest / "labels" / f"{names[t]}.txt").write_text("".join(text))
    else:
        ids = {t: i + 1 for i, t in enumerate(stamps)}
        images = [{"id": ids[t], "file_name": f"{names[t]}.png", "width": int(cam.width), "height": int(cam.height)}
                  for t in stamps]
        category = {n: COCO_IDS[i] for i, n in enumerate(COCO80)} if coco else {n: i + 1 for i, n in enumerate(classes)}
        results = [{"image_id": ids[d.timestamp], "category_id": category[d.label],
                    "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])], "score": d.score}
                   for d, b in zip(seq.detections, boxes)]
        (dest / "coco_results.json").write_text(json.dumps(results))
        doc: dict = {"images": images}
        if not coco:
            doc["categories"] = [{"id": k, "name": n} for n, k in category.items()]
        (dest / "coco_images.json").write_text(json.dumps(doc))
    return dest


def write_truth_run(seq, folder) -> Path:
    """A run folder (map.json, trajectory.txt) as ``spdslam run`` writes one, with the
    sequence's ground-truth objects as the map (each cuboid's inscribed ellipsoid) and its
    input poses as the trajectory: for tests of what reads a run, without mapping one."""
    from spdslam.io import MapObject, map_document, write_map

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    objects = [MapObject(o.id, o.label, Ellipsoid.from_axes(o.cuboid.rotation, o.cuboid.center,
                                                            o.cuboid.half_extents))
               for o in seq.objects_gt or ()]
    doc = map_document(method="multi-spd", parameterization="spd", iterations=0, final_cost=0.0,
                       initial_cost=0.0, converged=True, reason="written from the ground truth",
                       settings={}, objects=objects, failed={}, notes=[], association={},
                       cost_by_factor={})
    write_map(folder / "map.json", doc)
    rows = np.column_stack([seq.timestamps, seq.poses_tum])
    np.savetxt(folder / "trajectory.txt", rows, fmt="%.9f")
    return folder
