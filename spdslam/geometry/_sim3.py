"""Similarity transforms of R³, x ↦ s R x + t, as an optimisation variable.

``Sim3(rotation, translation, log_scale)``: s = exp(log_scale) > 0 always. It moves a
recording's frame into a map's (docs/map-reuse.md); a camera-to-world pose T_wc of the
recording becomes the camera-to-world pose (R R_wc, s R t_wc + t) of the map's frame
(``pose_of``: the camera keeps its own metric units, only its position is scaled).

Manifold: the product SO(3) × R³ × R, tangent δ = (v, ω, ρ) in jaxlie's order,
(R, t, σ) ⊞ δ = (R Exp(ω), t + v, σ + ρ), with blocks (3, 3, 1) for the solver's damping.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from . import manifold

__all__ = ["Sim3", "interpolated_frame"]


@dataclass(frozen=True)
class Sim3:
    """x ↦ exp(log_scale) · R x + t (module docstring)."""

    rotation: jaxlie.SO3
    translation: Any
    log_scale: Any

    @staticmethod
    def from_matrix(T, scale: float = 1.0) -> "Sim3":
        """From a 4×4 rigid transform [[R, t], [0, 1]] and the scale kept apart."""
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"a Sim3 needs a finite 4×4 transform and a scale > 0, got shape {T.shape}, "
                             f"scale {scale!r}")
        return Sim3(jaxlie.SO3.from_matrix(T[:3, :3]), jnp.asarray(T[:3, 3]), jnp.asarray(np.log(scale)))

    @property
    def scale(self):
        return jnp.exp(self.log_scale)

    def as_matrix(self):
        """4×4 [[R, t], [0, 1]] (the scale apart: ``scale``)."""
        return jnp.eye(4).at[:3, :3].set(self.rotation.as_matrix()).at[:3, 3].set(self.translation)

    def apply(self, x):
        """Points (…, 3) moved: s R x + t."""
        return self.scale * jnp.asarray(x) @ self.rotation.as_matrix().T + self.translation

    def pose_of(self, T_wc: jaxlie.SE3) -> jaxlie.SE3:
        """A camera-to-world pose of the source frame as one of the target frame."""
        return jaxlie.SE3.from_rotation_and_translation(
            self.rotation @ T_wc.rotation(), self.apply(T_wc.translation()))

    def retract(self, delta) -> "Sim3":
        d = jnp.asarray(delta)
        return Sim3(self.rotation @ jaxlie.SO3.exp(d[3:6]), self.translation + d[:3], self.log_scale + d[6])

    def local(self, other: "Sim3") -> jax.Array:
        return jnp.concatenate([other.translation - self.translation,
                                (self.rotation.inverse() @ other.rotation).log(),
                                jnp.reshape(other.log_scale - self.log_scale, (1,))])


jax.tree_util.register_dataclass(Sim3, data_fields=["rotation", "translation", "log_scale"], meta_fields=[])
manifold.register(Sim3, tangent_dim=7, blocks=(3, 3, 1), retract=Sim3.retract, local=Sim3.local)


def frame_pose(frame, T_wc: jaxlie.SE3) -> jaxlie.SE3:
    """T_wc of a source frame as a pose of the target frame, for a frame given as a rigid
    ``jaxlie.SE3`` (frame @ T_wc) or a ``Sim3`` (``Sim3.pose_of``)."""
    if isinstance(frame, Sim3):
        return frame.pose_of(T_wc)
    return frame @ T_wc


def interpolated_frame(frame_a: jaxlie.SE3, frame_b: jaxlie.SE3, weight) -> jaxlie.SE3:
    """The rigid frame a fraction ``weight`` ∈ [0, 1] of the way from ``frame_a`` to
    ``frame_b`` along the geodesic: K_a Exp(w Log(K_a⁻¹ K_b)) (K_a at w = 0, K_b at w = 1)."""
    return frame_a @ jaxlie.SE3.exp(weight * (frame_a.inverse() @ frame_b).log())
