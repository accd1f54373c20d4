"""Synthetic single-object scenes in the spirit of the paper's simulation (Sec. IV-A).

One ellipsoid, ``n_views`` cameras looking at it from viewing directions spread over an
``angle_range`` (a cone of directions of that angular diameter, or a horizontal arc: the
``Protocol``'s free choices, named in ``PROTOCOLS``), noise-free or noisy boxes, and an
initial landmark perturbed from the truth:

    R = Exp(θ) R̄,  t = t̄ + δt,  θ ~ N(0, σθ² I),  δt ~ N(0, σt² I),  sᵢ = s̄ᵢ + N(0, (s̄ᵢ σ%)²),

(the paper's T = exp(ξ^) T̄ with the rotation taken about the object centre, so the centre
noise is σt whatever the object's distance from the world origin).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax.numpy as jnp
import jaxlie
import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import Camera, Ellipsoid, conic_box

__all__ = ["NOISE_LEVELS", "DEFAULT_CAMERA", "PATTERNS", "PROTOCOLS", "Protocol", "Scene", "Scenes",
           "get_protocol", "make_scene", "make_scenes", "random_rotations"]

#: Initial-landmark noise (σθ degrees, σt metres, σ% fraction of each radius) and box noise
#: σ_b (pixels per edge), per level, as in the paper.
NOISE_LEVELS = {
    "L": {"rot_deg": 10.0, "trans": 0.1, "scale": 0.1, "box_px": 0.0},
    "M": {"rot_deg": 20.0, "trans": 1.0, "scale": 0.3, "box_px": 5.0},
    "H": {"rot_deg": 40.0, "trans": 3.0, "scale": 0.5, "box_px": 10.0},
}

DEFAULT_CAMERA = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)
#: Viewing patterns: directions in a spherical cap ("cone") or on a horizontal arc ("arc").
PATTERNS = ("cone", "arc")


@dataclass(frozen=True)
class Protocol:
    """The simulation's free choices, where the paper is silent (docs/simulation.md).

    ``focal``: f in px of a camera with the 640 × 480 / f = 500 field of view (image
    1.28 f × 0.96 f, principal point at its centre), so f sets the boxes' size in pixels
    against the fixed pixel noise. ``distance``: camera-to-centre range (m), uniform.
    ``pattern``: "cone", viewing directions uniform in a spherical cap of the viewing
    range's angular diameter around a direction of elevation uniform in ±``elevation_deg``;
    or "arc", azimuths uniform over the viewing range, each view's elevation uniform in
    ±``elevation_deg``. ``n_views`` cameras, each aimed at the centre ± ``aim_jitter`` m.
    """

    name: str = "custom"
    focal: float = 500.0
    distance: tuple[float, float] = (4.0, 6.0)
    pattern: str = "cone"
    elevation_deg: float = 15.0
    n_views: int = 10
    aim_jitter: float = 0.05

    def __post_init__(self):
        lo, hi = (float(x) for x in self.distance)
        object.__setattr__(self, "distance", (lo, hi))
        if not (np.isfinite(self.focal) and self.focal > 0):
            raise ValueError(f"focal must be a positive number of pixels, got {self.focal}")
        if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
            raise ValueError(f"distance must be a range 0 < lo ≤ hi (m), got {self.distance}")
        if self.pattern not in PATTERNS:
            raise ValueError(f"pattern must be one of {', '.join(PATTERNS)}, got {self.pattern!r}")
        if not 0 <= self.elevation_deg < 90:
            raise ValueError(f"elevation_deg must be in [0, 90), got {self.elevation_deg}")
        if int(self.n_views) != self.n_views or self.n_views < 3:
            raise ValueError(f"n_views must be an integer ≥ 3, got {self.n_views}")
        if not (np.isfinite(self.aim_jitter) and self.aim_jitter >= 0):
            raise ValueError(f"aim_jitter must be ≥ 0 (m), got {self.aim_jitter}")

    @property
    def camera(self) -> Camera:
        f = float(self.focal)
        return Camera(f, f, 0.64 * f, 0.48 * f, 1.28 * f, 0.96 * f)

    def replace(self, **overrides) -> "Protocol":
        """A copy with ``overrides`` (None values and unchanged ones ignored), named "custom"
        if anything changed."""
        kw = {k: v for k, v in overrides.items() if v is not None and v != getattr(self, k)}
        if not kw:
            return self
        return dataclasses.replace(self, **{"name": "custom", **kw})


#: Named protocols. "v1": the study until issue 16 (f = 500 px, 4–6 m, cone); "paper": the
#: setting calibrated to the paper's method-independent figures (docs/simulation.md,
#: ``benchmarks/calibrate_protocol.py``), the default of ``spdslam simulate``.
PROTOCOLS = {
    "v1": Protocol("v1"),
    "paper": Protocol("paper", focal=1500.0, distance=(4.0, 6.0), pattern="cone", elevation_deg=30.0),
}


def get_protocol(p) -> Protocol:
    """A Protocol, or the named one of :data:`PROTOCOLS`."""
    if isinstance(p, Protocol):
        return p
    if p not in PROTOCOLS:
        raise ValueError(f"unknown protocol {p!r}: expected one of {', '.join(PROTOCOLS)}")
    return PROTOCOLS[p]


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """n rotation matrices, uniform on SO(3) (normalised Gaussian quaternions)."""
    q = rng.normal(size=(n, 4))
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def _so3_exp(omega: np.ndarray) -> np.ndarray:
    """Exp of rotation vectors (n, 3) → (n, 3, 3) (Rodrigues, numpy)."""
    th = np.linalg.norm(omega, axis=1)[:, None, None]
    K = np.zeros((len(omega), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -omega[:, 2], omega[:, 1], -omega[:, 0]
    K = K - np.swapaxes(K, 1, 2)
    small = th < 1e-12
    a = np.where(small, 1.0, np.sin(th) / np.where(small, 1.0, th))
    b = np.where(small, 0.5, (1 - np.cos(th)) / np.where(small, 1.0, th) ** 2)
    return np.eye(3) + a * K + b * K @ K


def _from_axes(R, t, s) -> Ellipsoid:
    """Batched Ellipsoid with P = R diag(s²) Rᵀ."""
    R, s = np.asarray(R), np.asarray(s)
    P = np.einsum("nij,nj,nkj->nik", R, s**2, R)
    return Ellipsoid(jnp.asarray(0.5 * (P + np.swapaxes(P, 1, 2))), jnp.asarray(t, dtype=float))


@dataclass(frozen=True)
class Scenes:
    """A batch of B single-object scenes with V views each (leading axes B, V)."""

    truth: Ellipsoid  # batched: P (B,3,3), center (B,3)
    initial: Ellipsoid  # batched
    poses: jaxlie.SE3  # batched camera-to-world, wxyz_xyz (B, V, 7)
    boxes: np.ndarray  # (B, V, 4) measured boxes
    camera: Camera

    def __len__(self) -> int:
        return int(self.boxes.shape[0])

    def __getitem__(self, i: int) -> "Scene":
        return Scene(
            Ellipsoid(self.truth.P[i], self.truth.center[i]),
            Ellipsoid(self.initial.P[i], self.initial.center[i]),
            [jaxlie.SE3(w) for w in self.poses.wxyz_xyz[i]],
            np.asarray(self.boxes[i]),
            self.camera,
        )


@dataclass(frozen=True)
class Scene:
    truth: Ellipsoid
    initial: Ellipsoid
    poses: list
    boxes: np.ndarray  # (n_views, 4)
    camera: Camera


def _views_and_boxes(truth: Ellipsoid, eyes: np.ndarray, aims: np.ndarray, camera: Camera):
    """Poses (B, V) looking from ``eyes`` at ``aims`` (as ``geometry.look_at``, up = +z) and
    the boxes of ``truth`` in them, in NumPy: nothing to compile per batch shape."""
    z = aims - eyes
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    R_wc = np.stack([x, np.cross(z, x), z], axis=-1)  # (B, V, 3, 3)
    xyzw = Rotation.from_matrix(R_wc.reshape(-1, 3, 3)).as_quat().reshape(*R_wc.shape[:2], 4)
    poses = jaxlie.SE3(jnp.asarray(np.concatenate([xyzw[..., 3:], xyzw[..., :3], eyes], axis=-1)))
    # M = K [R_cw | t_cw] and C* = M Q* Mᵀ as einsums over (scene, view), as when the
    # committed study (docs/simulation/) was computed: ``geometry.project_dual_quadric``
    # rounds differently (up to 7e-13 px on these boxes), and the study is kept bit for bit.
    R_cw = np.swapaxes(R_wc, -1, -2)
    T_cw = np.concatenate([R_cw, -R_cw @ eyes[..., None]], axis=-1)  # (B, V, 3, 4)
    M = np.einsum("ij,bvjk->bvik", np.asarray(camera.K), T_cw)
    Q = np.asarray(truth.dual_quadric())  # (B, 4, 4)
    C = np.einsum("bvij,bjk,bvlk->bvil", M, Q, M)
    return poses, conic_box(C)


def make_scenes(
    seed,
    n: int,
    noise: str = "M",
    angle_range_deg: float = 120.0,
    n_views: int | None = None,
    box_noise: bool = True,
    camera: Camera | None = None,
    extent=(1.0, 2.0, 3.0),
    min_fraction: float = 0.5,
    center_box=(1.0, 1.0, 1.0),
    distance=None,
    centre_elevation_deg: float | None = None,
    aim_jitter: float | None = None,
    protocol: "Protocol | str" = "v1",
) -> Scenes:
    """n independent scenes, generated with array operations (no loop over scenes).

    Object: an ellipsoid inside a bounded space of ``extent`` (the paper's 1 m × 2 m × 3 m):
    full axis lengths uniform in [min_fraction·eₖ, eₖ] (radii half of that), uniform random
    rotation, centre uniform in a box of size ``center_box`` around the origin. Views: as the
    ``protocol`` (a :class:`Protocol` or a name of :data:`PROTOCOLS`) says, over a viewing
    range of ``angle_range_deg`` (60°: insufficient observation, 120°: sufficient); its
    camera, number of views, distance, elevation spread and aim jitter can be overridden
    here (``n_views``, ``camera``, ``distance``, ``centre_elevation_deg``, ``aim_jitter``).
    With the "v1" protocol (f = 500 px, 4–6 m) a box is about 75–300 px.
    Boxes: the closed-form box of the truth plus N(0, σ_b²) per edge (σ_b of the level).
    ``seed`` may be an int or a sequence of ints (e.g. (seed, cell index)).
    """
    pr = get_protocol(protocol).replace(
        n_views=n_views, distance=distance, elevation_deg=centre_elevation_deg, aim_jitter=aim_jitter)
    camera = pr.camera if camera is None else camera
    n_views = pr.n_views
    rng = np.random.default_rng(seed)
    level = NOISE_LEVELS[noise]
    R = random_rotations(rng, n)
    t = (rng.uniform(size=(n, 3)) - 0.5) * np.asarray(center_box)
    half = 0.5 * np.asarray(extent, dtype=float)
    s = rng.uniform(min_fraction * half, half, size=(n, 3))
    truth = _from_axes(jnp.asarray(R), jnp.asarray(t), jnp.asarray(s))

    # Viewing directions (object → camera).
    az0 = rng.uniform(0, 2 * np.pi, size=n)
    if pr.pattern == "cone":  # a spherical cap of angular diameter angle_range around a
        # centre direction of elevation within ±elevation
        el0 = np.deg2rad(rng.uniform(-pr.elevation_deg, pr.elevation_deg, size=n))
        centre = np.stack([np.cos(el0) * np.cos(az0), np.cos(el0) * np.sin(az0), np.sin(el0)], axis=1)
        e1 = np.cross(centre, [0.0, 0.0, 1.0])
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e2 = np.cross(centre, e1)
        cos_r = np.cos(np.deg2rad(angle_range_deg) / 2)
        ct = rng.uniform(cos_r, 1.0, size=(n, n_views))
        st = np.sqrt(1 - ct**2)
        ph = rng.uniform(0, 2 * np.pi, size=(n, n_views))
        dirs = (
            ct[..., None] * centre[:, None]
            + (st * np.cos(ph))[..., None] * e1[:, None]
            + (st * np.sin(ph))[..., None] * e2[:, None]
        )
    else:  # a horizontal arc of angle_range, each view's elevation within ±elevation
        half_range = np.deg2rad(angle_range_deg) / 2
        az = az0[:, None] + rng.uniform(-half_range, half_range, size=(n, n_views))
        el = np.deg2rad(rng.uniform(-pr.elevation_deg, pr.elevation_deg, size=(n, n_views)))
        dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
    d = rng.uniform(*pr.distance, (n, n_views))
    eyes = t[:, None] + d[..., None] * dirs
    aims = t[:, None] + pr.aim_jitter * rng.normal(size=(n, n_views, 3))
    poses, boxes = _views_and_boxes(truth, eyes, aims, camera)
    boxes = np.asarray(boxes)
    if box_noise and level["box_px"] > 0:
        boxes = boxes + rng.normal(scale=level["box_px"], size=boxes.shape)
        boxes = np.concatenate(
            [np.minimum(boxes[..., :2], boxes[..., 2:]), np.maximum(boxes[..., :2], boxes[..., 2:])], axis=-1
        )

    # Initial landmark (see module docstring).
    dR = _so3_exp(rng.normal(scale=np.deg2rad(level["rot_deg"]), size=(n, 3)))
    s0 = np.abs(s + rng.normal(size=(n, 3)) * s * level["scale"])
    s0 = np.maximum(s0, 0.05 * s)  # keep a proper ellipsoid
    t0 = t + rng.normal(scale=level["trans"], size=(n, 3))
    initial = _from_axes(jnp.asarray(dR @ R), jnp.asarray(t0), jnp.asarray(s0))
    return Scenes(truth, initial, poses, boxes, camera)


def make_scene(
    seed,
    noise: str = "M",
    angle_range_deg: float = 120.0,
    n_views: int | None = None,
    box_noise: bool = True,
    camera: Camera | None = None,
    protocol: "Protocol | str" = "v1",
) -> Scene:
    """One scene (the first of ``make_scenes(seed, 1, ...)``)."""
    return make_scenes(seed, 1, noise, angle_range_deg, n_views, box_noise, camera, protocol=protocol)[0]
