"""Synthetic single-object scenes in the spirit of the paper's simulation (Sec. IV-A).

One ellipsoid, ``n_views`` cameras looking at it from viewing directions spread over an
``angle_range`` (degrees of azimuth around the object), noise-free or noisy boxes, and an
initial landmark perturbed from the truth:

    R = Exp(θ) R̄,  t = t̄ + δt,  θ ~ N(0, σθ² I),  δt ~ N(0, σt² I),  sᵢ = s̄ᵢ + N(0, (s̄ᵢ σ%)²),

(the paper's T = exp(ξ^) T̄ with the rotation taken about the object centre, so the centre
noise is σt whatever the object's distance from the world origin).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import jaxlie
import numpy as np

from .camera import Camera, look_at, project_box
from .ellipsoid import Ellipsoid

__all__ = ["NOISE_LEVELS", "Scene", "random_ellipsoid", "sample_views", "perturb_ellipsoid", "make_scene"]

#: Initial-landmark noise (σθ degrees, σt metres, σ% fraction of each radius) and box noise
#: σ_b (pixels per edge), per level, as in the paper.
NOISE_LEVELS = {
    "L": {"rot_deg": 10.0, "trans": 0.1, "scale": 0.1, "box_px": 0.0},
    "M": {"rot_deg": 20.0, "trans": 1.0, "scale": 0.3, "box_px": 5.0},
    "H": {"rot_deg": 40.0, "trans": 3.0, "scale": 0.5, "box_px": 10.0},
}

DEFAULT_CAMERA = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return np.asarray(jaxlie.SO3(jnp.asarray(q / np.linalg.norm(q))).as_matrix())


def random_ellipsoid(
    rng: np.random.Generator,
    space=(1.0, 2.0, 3.0),
    radius_range=(0.1, 0.5),
) -> Ellipsoid:
    """Centre uniform in a box of size ``space`` (centred at the origin), random rotation,
    radii uniform in ``radius_range``."""
    center = (rng.uniform(size=3) - 0.5) * np.asarray(space)
    return Ellipsoid.from_axes(random_rotation(rng), center, rng.uniform(*radius_range, size=3))


def sample_views(
    target,
    n_views: int,
    angle_range_deg: float,
    rng: np.random.Generator,
    distance=(3.0, 4.0),
    elevation_deg=(5.0, 30.0),
    aim_jitter: float = 0.05,
) -> list[jaxlie.SE3]:
    """Camera-to-world poses around ``target``: azimuths spread uniformly over
    ``angle_range_deg`` around a random heading, random elevation and distance."""
    heading = rng.uniform(0, 2 * np.pi)
    half = np.deg2rad(angle_range_deg) / 2
    az = heading + np.linspace(-half, half, n_views) + rng.uniform(-0.1, 0.1, n_views) * half
    el = np.deg2rad(rng.uniform(*elevation_deg, n_views))
    d = rng.uniform(*distance, n_views)
    target = np.asarray(target, dtype=float)
    eyes = target + d[:, None] * np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1
    )
    aims = target + aim_jitter * rng.normal(size=(n_views, 3))
    return [look_at(e, a) for e, a in zip(eyes, aims)]


def perturb_ellipsoid(
    e: Ellipsoid, rot_deg: float, trans: float, scale: float, rng: np.random.Generator
) -> Ellipsoid:
    """Initial landmark: rotation, centre and each radius perturbed (see module docstring)."""
    R, s = (np.asarray(a) for a in e.axes())
    dR = np.asarray(jaxlie.SO3.exp(jnp.asarray(rng.normal(scale=np.deg2rad(rot_deg), size=3))).as_matrix())
    s_new = np.abs(s + rng.normal(size=3) * s * scale)
    s_new = np.maximum(s_new, 0.05 * s)  # keep a proper ellipsoid
    t_new = np.asarray(e.center) + rng.normal(scale=trans, size=3)
    return Ellipsoid.from_axes(dR @ R, t_new, s_new)


@dataclass(frozen=True)
class Scene:
    truth: Ellipsoid
    initial: Ellipsoid
    poses: list
    boxes: np.ndarray  # (n_views, 4)
    camera: Camera


def make_scene(
    seed: int,
    noise: str = "M",
    angle_range_deg: float = 120.0,
    n_views: int = 10,
    box_noise: bool = True,
    camera: Camera = DEFAULT_CAMERA,
) -> Scene:
    """One random object, its views, boxes (with the level's σ_b unless ``box_noise`` is
    False) and a perturbed initial landmark."""
    rng = np.random.default_rng(seed)
    level = NOISE_LEVELS[noise]
    truth = random_ellipsoid(rng)
    poses = sample_views(truth.center, n_views, angle_range_deg, rng)
    boxes = np.stack([np.asarray(project_box(truth, T, camera)) for T in poses])
    if box_noise and level["box_px"] > 0:
        boxes = boxes + rng.normal(scale=level["box_px"], size=boxes.shape)
        boxes = np.concatenate(
            [np.minimum(boxes[:, :2], boxes[:, 2:]), np.maximum(boxes[:, :2], boxes[:, 2:])], axis=1
        )
    initial = perturb_ellipsoid(truth, level["rot_deg"], level["trans"], level["scale"], rng)
    return Scene(truth, initial, poses, boxes, camera)
