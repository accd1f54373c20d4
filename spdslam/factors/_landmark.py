"""The paper's object factors, for any landmark parameterisation (SPD, RTS or Full).

Notation: landmark (P, t) with Q* = [[P − ttᵀ, −t], [−tᵀ, −1]]; camera pose T_wc
(camera-to-world); box b = [u_min, v_min, u_max, v_max] in pixels; planes π = [n; d] with
‖n‖ = 1, so π·[x; 1] is a signed distance. For such a plane

    πᵀ Q* π = nᵀPn − (n·t + d)²,

the squared support distance minus the squared centre distance: zero iff π is tangent.

Box-like objects are boxed by the silhouette of the circumscribed cuboid (axes R, half-extents
s): the cuboid box factors use its 8 projected corners, or its support function
h(n) = n·t + Σᵢ sᵢ|n·Rᵢ| for the edge planes.

Truncation: every box factor takes a (4,) 0/1 mask ``keep`` of the edges that bound the
object (``camera.truncation_mask``: edges farther than ``truncation_margin`` px from the
image border); the residual of a dropped edge is 0. The builders pass ``keep`` as
measurement data only when a margin is given, so factors built alike batch together.

Each ``*_residual`` is a plain function of variable values then measurement data; each
``*Factor`` builds a :class:`Factor` with its noise model (defaults below, in the units of
the residual) and an optional robust kernel.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..camera import (
    Camera,
    box_planes,
    cuboid_half_axes,
    cuboid_in_front,
    in_front,
    project_box,
    project_cuboid_box,
    truncation_mask,
)
from ..ellipsoid import EllipsoidRTS, as_ellipsoid, dual_quadric
from ..matfun import eigh, logm
from ._base import Factor, RobustKernel, sqrt_information

__all__ = [
    "inverse_box_residual",
    "semi_inverse_box_residual",
    "box_visible",
    "inverse_cuboid_box_residual",
    "semi_inverse_cuboid_box_residual",
    "cuboid_box_visible",
    "InverseCuboidBoxFactor",
    "axis_orientation_residual",
    "AxisOrientationFactor",
    "SemiInverseCuboidBoxFactor",
    "DEFAULT_TRUNCATION_MARGIN",
    "orientation_residual",
    "classic_orientation_residual",
    "shape_residual",
    "size_residual",
    "support_plane_residual",
    "InverseBoxFactor",
    "SemiInverseBoxFactor",
    "OrientationFactor",
    "ClassicOrientationFactor",
    "ShapeFactor",
    "SizeFactor",
    "SupportPlaneFactor",
    "DEFAULT_SIGMAS",
]

#: Default standard deviations, in the units of each residual.
DEFAULT_SIGMAS = {
    "inverse_box": 2.0,  # px per box edge
    "semi_inverse_box": 0.01,  # m² per edge plane (≈ 2 px for a 0.3 m object at 3 m, f = 500)
    "inverse_cuboid_box": 2.0,  # px per box edge
    "semi_inverse_cuboid_box": 0.01,  # m per edge plane (≈ 2 px at 2.5 m, f = 500)
    "orientation": 0.05,  # per component of (Log P m) × m
    "classic_orientation": 0.05,
    "axis_orientation": 0.05,  # per component of (nᵢ × m)(nᵢ·m) (≈ rad)  # per component of ±n × m (≈ rad)
    "shape": 0.1,  # per axis ratio
    "size": 0.1,  # log of the geometric-mean radius ratio
    "support_plane": 0.01,  # m²
}


#: A detected box edge within this many pixels of the image border is taken as truncated.
DEFAULT_TRUNCATION_MARGIN = 5.0


def _unit(v):
    v = jnp.asarray(v, dtype=float)
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


# --- box measurements --------------------------------------------------------------------
def _masked(r, keep):
    """r ∘ keep (keep None: every edge)."""
    return r if keep is None else r * keep


def inverse_box_residual(T_wc, landmark, box, camera: Camera, keep=None):
    """Inverse model: (the closed-form box of C* = M Q* Mᵀ minus the detected box) ∘ keep
    (px, 4)."""
    return _masked(project_box(landmark, T_wc, camera) - box, keep)


def semi_inverse_box_residual(T_wc, landmark, box, camera: Camera, keep=None):
    """Semi-inverse model: πᵢᵀ Q* πᵢ · keepᵢ for the 4 edge planes πᵢ = Mᵀ lᵢ, each with
    unit normal.

    One residual per edge (m²): the paper's single sum Σᵢ πᵢᵀQ*πᵢ lets edges that are too
    tight cancel edges that are too loose.
    """
    planes = box_planes(box, T_wc, camera)
    Q = dual_quadric(landmark)
    return _masked(jnp.einsum("ki,ij,kj->k", planes, Q, planes), keep)


def box_visible(T_wc, landmark, box, camera: Camera, keep=None, min_depth: float = 1e-3):
    """Validity of a box factor: the whole ellipsoid is in front of the camera
    (which also rules out the camera being inside it)."""
    return in_front(landmark, T_wc, min_depth)


def inverse_cuboid_box_residual(T_wc, landmark, box, camera: Camera, keep=None):
    """Inverse cuboid model: (the box of the 8 projected corners t + Σᵢ ±sᵢRᵢ of the
    circumscribed cuboid minus the detected box) ∘ keep (px, 4)."""
    return _masked(project_cuboid_box(landmark, T_wc, camera) - box, keep)


def semi_inverse_cuboid_box_residual(T_wc, landmark, box, camera: Camera, keep=None):
    """Semi-inverse cuboid model, per edge plane π = [n; d] (unit n), in m:

        rᵢ = (Σⱼ sⱼ|n·Rⱼ| − |n·t + d|) · keepᵢ,

    the cuboid's half-width along n (its support function minus n·t) minus the centre's
    distance to the plane: zero iff the plane touches the cuboid with the cuboid on one
    side, > 0 where it cuts it (box too tight), < 0 where it misses it (box too loose).
    """
    planes = box_planes(box, T_wc, camera)
    H, t = cuboid_half_axes(landmark)
    half_width = jnp.sum(jnp.abs(planes[:, :3] @ H), axis=1)
    return _masked(half_width - jnp.abs(planes[:, :3] @ t + planes[:, 3]), keep)


def cuboid_box_visible(T_wc, landmark, box, camera: Camera, keep=None, min_depth: float = 1e-3):
    """Validity of a cuboid box factor: all 8 corners of the circumscribed cuboid are in
    front of the camera (depth > ``min_depth``)."""
    return cuboid_in_front(landmark, T_wc, min_depth)


def _box_factor(residual, kind, pose_key, landmark_key, box, camera, sigma, robust,
                truncation_margin, valid=box_visible):
    box = np.asarray(box, dtype=float)
    if box.shape != (4,) or not np.all(np.isfinite(box)) or box[2] < box[0] or box[3] < box[1]:
        raise ValueError(f"box must be finite [u_min, v_min, u_max, v_max], got {box.tolist()}")
    if not isinstance(camera, Camera):
        raise TypeError("camera must be a spdslam.Camera")
    args = (box, camera)
    if truncation_margin is not None:
        if not (np.isfinite(truncation_margin) and truncation_margin >= 0):
            raise ValueError(f"truncation_margin must be finite and ≥ 0 px, got {truncation_margin!r}")
        args = (box, camera, np.asarray(truncation_mask(box, camera, float(truncation_margin))))
    sigma = DEFAULT_SIGMAS[kind] if sigma is None else sigma
    return Factor(
        residual,
        (pose_key, landmark_key),
        args,
        sqrt_information(4, sigma=sigma),
        robust,
        valid,
        kind,
    )


def InverseBoxFactor(
    pose_key, landmark_key, box, camera: Camera, sigma=None, robust: RobustKernel | None = None,
    truncation_margin: float | None = None,
) -> Factor:
    """Detected box vs the closed-form box of the projected ellipsoid (residual in px).

    ``truncation_margin`` (px, e.g. ``DEFAULT_TRUNCATION_MARGIN``): edges within it of the
    image border carry no bound; None (default) keeps every edge and the args (box, camera).
    """
    return _box_factor(
        inverse_box_residual, "inverse_box", pose_key, landmark_key, box, camera, sigma, robust,
        truncation_margin,
    )


def SemiInverseBoxFactor(
    pose_key, landmark_key, box, camera: Camera, sigma=None, robust: RobustKernel | None = None,
    truncation_margin: float | None = None,
) -> Factor:
    """Tangency of the 4 back-projected box-edge planes (residual πᵀQ*π in m² per edge);
    ``truncation_margin`` as for :func:`InverseBoxFactor`."""
    return _box_factor(
        semi_inverse_box_residual, "semi_inverse_box", pose_key, landmark_key, box, camera,
        sigma, robust, truncation_margin,
    )


def InverseCuboidBoxFactor(
    pose_key, landmark_key, box, camera: Camera, sigma=None, robust: RobustKernel | None = None,
    truncation_margin: float | None = None,
) -> Factor:
    """Detected box vs the box of the projected circumscribed cuboid (residual in px);
    ``truncation_margin`` as for :func:`InverseBoxFactor`."""
    return _box_factor(
        inverse_cuboid_box_residual, "inverse_cuboid_box", pose_key, landmark_key, box, camera,
        sigma, robust, truncation_margin, cuboid_box_visible,
    )


def SemiInverseCuboidBoxFactor(
    pose_key, landmark_key, box, camera: Camera, sigma=None, robust: RobustKernel | None = None,
    truncation_margin: float | None = None,
) -> Factor:
    """Contact of the 4 back-projected box-edge planes with the circumscribed cuboid
    (residual in m per edge); ``truncation_margin`` as for :func:`InverseBoxFactor`."""
    return _box_factor(
        semi_inverse_cuboid_box_residual, "semi_inverse_cuboid_box", pose_key, landmark_key,
        box, camera, sigma, robust, truncation_margin, cuboid_box_visible,
    )


# --- orientation -------------------------------------------------------------------------
def orientation_residual(landmark, direction):
    """Improved orientation constraint, smooth in P:

        r = (Log(P) m) × m = Σᵢ log(sᵢ²) (nᵢ × m)(nᵢ·m)   ∈ R³,

    the paper's per-axis term (nᵢ × m)(nᵢ·m) for every axis nᵢ, weighted by the log of its
    squared radius. It is zero iff every axis is parallel or perpendicular to m (m is an
    eigenvector of P), for any axis order and sign. The weights matter: with equal weights
    the sum is (Σ nᵢnᵢᵀ m) × m = m × m ≡ 0. It is scale-invariant (Log(cP) = Log P + log c·I)
    and stays differentiable at repeated radii, where the axes themselves are undefined
    (a sphere satisfies it for every m).
    """
    m = _unit(direction)
    L = logm(as_ellipsoid(landmark).P)
    return jnp.cross(L @ m, m)


def classic_orientation_residual(landmark, direction, axis):
    """Classic form: one fixed object axis n = R e_axis parallel to m,

        r = sign(n·m) (n × m)   ∈ R³,   ‖r‖ = sin θ,

    θ ∈ [0, 90°] the angle between the line of n and m: blind to the axis sign but not to
    its order (a fixed column of an RTS rotation), so an object whose rotation has another
    axis up is pulled by up to 90°. Smooth at θ = 0 (an angle θ ≥ 0 would have a kink
    there that stalls Gauss-Newton); the sign flips only at θ = 90°. ``axis`` is a one-hot
    3-vector selecting the column.
    """
    if not isinstance(landmark, EllipsoidRTS):
        raise TypeError(
            "the classic orientation factor constrains a fixed axis of an RTS landmark "
            f"(EllipsoidRTS), got {type(landmark).__name__}; use OrientationFactor for SPD/Full"
        )
    m = _unit(direction)
    n = landmark.rotation.as_matrix() @ axis
    return jnp.where(n @ m < 0, -1.0, 1.0) * jnp.cross(n, m)


def axis_orientation_residual(landmark, direction):
    """Per-axis orientation constraint for cuboid-shaped objects, the paper's term for each
    axis nᵢ of the object stacked (not summed):

        r = [(n₁ × m)(n₁·m); (n₂ × m)(n₂·m); (n₃ × m)(n₃·m)]   ∈ R⁹,

    zero iff every axis is parallel or perpendicular to m, whatever their order and signs;
    each block has norm ½|sin 2θᵢ| ≈ θᵢ. Unlike (Log P m) × m its strength does not fade as
    two radii approach each other: a cuboid with two equal half-extents still has an
    orientation about the third axis, an ellipsoid does not. The axes are those of the
    circumscribed cuboid (``camera.cuboid_half_axes``: eigenvectors of P, or the rotation of
    an RTS landmark), so like the cuboid itself it is undefined at exactly repeated radii
    (finite there, not continuous).
    """
    m = _unit(direction)
    H, _ = cuboid_half_axes(landmark)
    N = H / jnp.linalg.norm(H, axis=0, keepdims=True)  # unit axes as columns
    return (jnp.cross(N.T, m) * (N.T @ m)[:, None]).reshape(9)


def OrientationFactor(
    landmark_key, direction, sigma=None, robust: RobustKernel | None = None
) -> Factor:
    """Improved orientation constraint against a world direction m (e.g. gravity up)."""
    m = np.asarray(direction, dtype=float)
    if m.shape != (3,) or not np.all(np.isfinite(m)) or np.linalg.norm(m) == 0:
        raise ValueError(f"direction must be a non-zero 3-vector, got {m.tolist()}")
    sigma = DEFAULT_SIGMAS["orientation"] if sigma is None else sigma
    return Factor(
        orientation_residual,
        (landmark_key,),
        (m / np.linalg.norm(m),),
        sqrt_information(3, sigma=sigma),
        robust,
        None,
        "orientation",
    )


def AxisOrientationFactor(
    landmark_key, direction, sigma=None, robust: RobustKernel | None = None
) -> Factor:
    """Per-axis orientation constraint (cuboid-shaped objects) against a world direction m."""
    m = np.asarray(direction, dtype=float)
    if m.shape != (3,) or not np.all(np.isfinite(m)) or np.linalg.norm(m) == 0:
        raise ValueError(f"direction must be a non-zero 3-vector, got {m.tolist()}")
    sigma = DEFAULT_SIGMAS["axis_orientation"] if sigma is None else sigma
    return Factor(
        axis_orientation_residual,
        (landmark_key,),
        (m / np.linalg.norm(m),),
        sqrt_information(9, sigma=sigma),
        robust,
        None,
        "axis_orientation",
    )


def ClassicOrientationFactor(
    landmark_key, direction, axis: int = 2, sigma=None, robust: RobustKernel | None = None
) -> Factor:
    """Classic orientation constraint: column ``axis`` of an RTS landmark's rotation ∥ m."""
    m = np.asarray(direction, dtype=float)
    if m.shape != (3,) or not np.all(np.isfinite(m)) or np.linalg.norm(m) == 0:
        raise ValueError(f"direction must be a non-zero 3-vector, got {m.tolist()}")
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2, got {axis!r}")
    sigma = DEFAULT_SIGMAS["classic_orientation"] if sigma is None else sigma
    return Factor(
        classic_orientation_residual,
        (landmark_key,),
        (m / np.linalg.norm(m), np.eye(3)[axis]),
        sqrt_information(3, sigma=sigma),
        robust,
        None,
        "classic_orientation",
    )


# --- shape, size, support ----------------------------------------------------------------
def _sorted_radii(landmark):
    w, _ = eigh(as_ellipsoid(landmark).P)
    return jnp.sqrt(jnp.maximum(w[::-1], 1e-300))


def shape_residual(landmark, prior_ratios):
    """[s₁/s₃, s₂/s₃] − [a/c, b/c], radii sorted s₁ ≥ s₂ ≥ s₃ (and a ≥ b ≥ c).

    Sorting makes the prior blind to axis order. At repeated radii the sorted ratios have
    a kink; the derivative used there is the mean over the tie (see ``matfun.eigh``), which
    is what a central difference measures.
    """
    s = _sorted_radii(landmark)
    return s[:2] / s[2] - prior_ratios


def size_residual(landmark, log_prior_volume):
    """⅓ log(V / V̄) = log of the ratio of geometric-mean radii (s₁s₂s₃)^⅓ / (abc)^⅓.

    ``log_prior_volume`` is log(abc); the 4π/3 factors cancel.
    """
    logdet = jnp.linalg.slogdet(as_ellipsoid(landmark).P)[1]
    return jnp.atleast_1d((0.5 * logdet - log_prior_volume) / 3.0)


def support_plane_residual(landmark, plane):
    """πᵀQ*π for the plane the object stands on (unit normal): zero when it touches it."""
    return jnp.atleast_1d(plane @ dual_quadric(landmark) @ plane)


def _prior_radii(radii):
    r = np.asarray(radii, dtype=float)
    if r.shape != (3,) or not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ValueError(f"prior radii must be 3 positive numbers, got {r.tolist()}")
    return np.sort(r)[::-1]


def ShapeFactor(landmark_key, prior_radii, sigma=None, robust: RobustKernel | None = None) -> Factor:
    """Class shape prior from semi-axes (a, b, c) in any order."""
    a, b, c = _prior_radii(prior_radii)
    sigma = DEFAULT_SIGMAS["shape"] if sigma is None else sigma
    return Factor(
        shape_residual,
        (landmark_key,),
        (np.array([a / c, b / c]),),
        sqrt_information(2, sigma=sigma),
        robust,
        None,
        "shape",
    )


def SizeFactor(landmark_key, prior_radii, sigma=None, robust: RobustKernel | None = None) -> Factor:
    """Class volume prior from semi-axes (a, b, c)."""
    r = _prior_radii(prior_radii)
    sigma = DEFAULT_SIGMAS["size"] if sigma is None else sigma
    return Factor(
        size_residual,
        (landmark_key,),
        (np.array(np.sum(np.log(r))),),
        sqrt_information(1, sigma=sigma),
        robust,
        None,
        "size",
    )


def SupportPlaneFactor(landmark_key, plane, sigma=None, robust: RobustKernel | None = None) -> Factor:
    """The object touches the plane a·x + b·y + c·z + d = 0 (e.g. the floor)."""
    p = np.asarray(plane, dtype=float)
    if p.shape != (4,) or not np.all(np.isfinite(p)) or np.linalg.norm(p[:3]) == 0:
        raise ValueError(f"plane must be [a, b, c, d] with a non-zero normal, got {p.tolist()}")
    sigma = DEFAULT_SIGMAS["support_plane"] if sigma is None else sigma
    return Factor(
        support_plane_residual,
        (landmark_key,),
        (p / np.linalg.norm(p[:3]),),
        sqrt_information(1, sigma=sigma),
        robust,
        None,
        "support_plane",
    )
