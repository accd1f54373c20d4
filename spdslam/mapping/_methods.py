"""Back-end methods (Table III), their options and the mapping's noise table.

Methods (:data:`METHODS`) mirror Table III: ``quadric-slam`` (Quadric-SVD initialisation,
inverse boxes, Rot-Trans-Scale), ``multi-rts`` (multi-constraint initialisation, every
constraint in its classic form on the axes as the front end labels them, RTS: the paper's
baseline; ``multi-rts-nearest`` keeps the axis nearest up instead and sorts the shape
ratios, the variant used until issue 16) and ``multi-spd`` (the paper's: SPD(3), improved
orientation, sorted shape prior; inverse boxes, because semi-inverse-then-inverse ended in
worse local minima on the demo rooms, see docs/sequences.md). Each field of a method can be
overridden.

The noise table (:data:`DEFAULT_MAPPING_SIGMAS`) is the registered factor types' default
sigmas (``factors.default_sigmas``) with the mapping's own on top: scene knowledge held
nearly hard, the relative box noise, the odometry and the first pose. Robust kernels are
chosen per factor group (``factors.robust_groups``: box, ellipsoid, odometry, orientation,
support_plane, shape, size, prior).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..factors import (
    DEFAULT_TRUNCATION_MARGIN,
    Cauchy,
    Huber,
    default_sigmas,
    robust_groups,
)
from ..geometry import OBJECT_SHAPES

__all__ = [
    "check_sigma",
    "parse_robust",
    "PARAMETERIZATIONS",
    "BOX_MODELS",
    "INITIALIZATIONS",
    "ORIENTATIONS",
    "SHAPE_FORMS",
    "ROBUST_KERNELS",
    "ROBUST_CHOICES",
    "AUTO_BOX_KERNEL",
    "OBJECT_SHAPE_CHOICES",
    "MAPPING_SIGMAS",
    "DEFAULT_MAPPING_SIGMAS",
    "Method",
    "METHODS",
    "RADIUS_FLOOR",
    "robust_kernel",
]

PARAMETERIZATIONS = ("spd", "rts", "full")
BOX_MODELS = ("inverse", "semi", "semi-then-inverse")
INITIALIZATIONS = ("svd", "multi")
#: "classic": the paper's classic constraint, the landmark's fixed third axis ∥ up;
#: "classic-nearest": the initial axis nearest up kept ∥ up (multi-rts until issue 16).
ORIENTATIONS = ("improved", "classic", "classic-nearest", "none")
#: Shape prior: "sorted" ratios (the paper's improved, order-blind) or "classic" (an RTS
#: landmark's stored scales against the class's radii in their stated order).
SHAPE_FORMS = ("sorted", "classic")
ROBUST_KERNELS = ("none", "huber", "cauchy")
#: ``Method.robust``: a kernel, or "auto": ``AUTO_BOX_KERNEL`` on the box factors when the
#: detections are associated automatically, none when instance ids group them (the paper's
#: setting). The threshold is the 95th percentile of the whitened box residuals ‖W r‖ of
#: correctly associated boxes at the optimum (docs/sequences.md, ``benchmarks/fr2_ablation.py``):
#: beyond it a box is more likely a wrong association, a truncation or an occlusion.
ROBUST_CHOICES = ("auto", *ROBUST_KERNELS)
AUTO_BOX_KERNEL = ("cauchy", 6.0)
#: The silhouette model of every object, or "priors": per class from priors.yaml.
OBJECT_SHAPE_CHOICES = ("priors", *OBJECT_SHAPES)

#: The mapping's own noise (value, unit and meaning): its defaults override the factor
#: types' (``factors.default_sigmas``), the others are its own.
MAPPING_SIGMAS = {
    # A detector's box error grows with the box (and so does the misfit of an ellipsoid to
    # a box-shaped object): per edge σ = inverse_box + inverse_box_relative · box size.
    "inverse_box_relative": (0.05, "of the box width (u edges) or height (v edges), added to inverse_box"),
    "inverse_cuboid_box_relative": (0.05, "of the box width or height, added to inverse_cuboid_box"),
    # Scene knowledge is held nearly hard: upright objects standing on their plane.
    "orientation": (0.005, "per component of (Log P m) × m"),
    "classic_orientation": (0.005, "per component of ±n × m (≈ rad)"),
    "axis_orientation": (0.005, "per component of (nᵢ × m)(nᵢ·m) (≈ rad), cuboid objects"),
    "support_plane": (0.001, "m² (πᵀQ*π)"),
    # Accuracy of the input trajectory's motion per frame step when the sequence's
    # priors.yaml does not state it (``trajectory_sigma``) and it cannot be estimated from
    # the trajectory's jitter (fewer than ``_noise.MIN_JITTER_TRIPLETS`` frames).
    "odometry_translation": (0.005, "m per frame step"),
    "odometry_rotation": (0.003, "rad per frame step"),
    # Accuracy of each input pose (a loop-closed SLAM trajectory) unless priors.yaml states
    # it (``trajectory_absolute_sigma``); inf: no bound (odometry that drifts). The value is
    # measured (docs/sequences.md, "The trajectory's noise model").
    "absolute_translation": (0.002, "m, each pose against its input value (inf: none)"),
    "absolute_rotation": (0.002, "rad, each pose against its input value (inf: none)"),
    "first_pose": (1e-4, "m and rad (prior on the first pose)"),
}
#: The smallest floor of ``Method.radius_floor`` (m): twice the radius below which an object
#: is reported degenerate (``mapping.MIN_RADIUS``).
RADIUS_FLOOR = 4e-3
#: Sigmas that may be 0 (an additive relative term).
ZERO_ALLOWED = ("inverse_box_relative", "inverse_cuboid_box_relative")
#: Sigmas that may be infinite (a prior that is not there).
INF_ALLOWED = ("absolute_translation", "absolute_rotation")

#: The default sigmas of a run, by name (``spdslam run --sigma NAME=VALUE``).
DEFAULT_MAPPING_SIGMAS = {
    **{name: float(s.value) for name, s in default_sigmas().items()},
    **{name: v for name, (v, _) in MAPPING_SIGMAS.items()},
}


@dataclass(frozen=True)
class Method:
    """One back end: parameterisation, initialisation, box model and which constraints
    (built with keywords: ``Method("x", parameterization="rts", …)``)."""

    name: str
    _: dataclasses.KW_ONLY
    parameterization: str = "spd"
    initialization: str = "multi"
    box_model: str = "inverse"
    orientation: str = "improved"
    support_plane: bool = True
    shape: bool = True
    size: bool = True
    #: The form of the shape prior (``SHAPE_FORMS``).
    shape_form: str = "sorted"
    #: The kernel of the box and measured-ellipsoid factors (``ROBUST_CHOICES``); "auto" is
    #: resolved by the run (``resolved``), and means none to ``build_graph`` alone.
    robust: str = "auto"
    robust_k: float = 1.0
    #: Kernels per factor group, overriding ``robust`` (which covers box and measured-ellipsoid
    #: factors): ((group, kernel, k), ...) with group a key of ``factors.robust_groups()``.
    robust_by_type: tuple = ()
    #: Silhouette model of every object ("ellipsoid" or "cuboid"), or "priors": per class,
    #: ``priors.classes[label].shape`` ("ellipsoid" for classes without a prior).
    object_shape: str = "priors"
    #: Box edges within this many px of the image border carry no bound (truncated
    #: detections), in the initialisation and in every box factor; negative: keep all edges.
    truncation_margin: float = DEFAULT_TRUNCATION_MARGIN
    #: A one-sided floor on each object's smallest radius (``RadiusFloorFactor``): a
    #: quarter of its class prior's smallest radius, at least ``RADIUS_FLOOR`` m.
    radius_floor: bool = True
    #: The shape and size factors of a built-in class prior (``io.BUILTIN_CLASSES``) carry
    #: a Cauchy kernel (k = ``BUILTIN_PRIOR_CAUCHY``); False: plain factors, as a stated prior.
    robust_builtin_priors: bool = True

    def __post_init__(self):
        for name, allowed in (
            ("parameterization", PARAMETERIZATIONS),
            ("initialization", INITIALIZATIONS),
            ("box_model", BOX_MODELS),
            ("orientation", ORIENTATIONS),
            ("robust", ROBUST_CHOICES),
            ("object_shape", OBJECT_SHAPE_CHOICES),
            ("shape_form", SHAPE_FORMS),
        ):
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        if self.orientation.startswith("classic") and self.parameterization != "rts":
            raise ValueError("the classic orientation constraint needs the rts parameterization")
        if self.shape_form == "classic" and self.parameterization != "rts":
            raise ValueError("the classic shape prior needs the rts parameterization")
        if not self.robust_k > 0:
            raise ValueError(f"robust_k must be > 0, got {self.robust_k}")
        groups = robust_groups()
        rbt = tuple(tuple(x) for x in self.robust_by_type)
        for item in rbt:
            if (len(item) != 3 or item[0] not in groups or item[1] not in ROBUST_KERNELS
                    or not (isinstance(item[2], (int, float)) and item[2] > 0)):
                raise ValueError(
                    f"robust_by_type entries must be (type, kernel, k > 0) with type one of "
                    f"{', '.join(groups)} and kernel one of {', '.join(ROBUST_KERNELS)}, "
                    f"got {item!r}"
                )
        object.__setattr__(self, "robust_by_type", tuple((t, n, float(k)) for t, n, k in rbt))
        if not np.isfinite(self.truncation_margin):
            raise ValueError(f"truncation_margin must be finite (px), got {self.truncation_margin}")

    @property
    def margin(self) -> float | None:
        """The truncation margin handed to initialisers and box factors (None: off)."""
        return None if self.truncation_margin < 0 else float(self.truncation_margin)

    def replace(self, **overrides) -> Method:
        return dataclasses.replace(self, **{k: v for k, v in overrides.items() if v is not None})

    def resolved(self, automatic_association: bool) -> Method:
        """The method with ``robust="auto"`` made concrete: ``AUTO_BOX_KERNEL`` with automatic
        association, "none" with instance ids."""
        if self.robust != "auto":
            return self
        if automatic_association:
            return dataclasses.replace(self, robust=AUTO_BOX_KERNEL[0], robust_k=AUTO_BOX_KERNEL[1])
        return dataclasses.replace(self, robust="none")


METHODS = {
    "quadric-slam": Method(
        "quadric-slam", parameterization="rts", initialization="svd", box_model="inverse",
        orientation="none", support_plane=False, shape=False, size=False, radius_floor=False),
    "multi-rts": Method(
        "multi-rts", parameterization="rts", initialization="multi", box_model="inverse",
        orientation="classic", support_plane=True, shape=True, size=True, shape_form="classic"),
    "multi-rts-nearest": Method(
        "multi-rts-nearest", parameterization="rts", initialization="multi", box_model="inverse",
        orientation="classic-nearest", support_plane=True, shape=True, size=True),
    "multi-spd": Method(
        "multi-spd", parameterization="spd", initialization="multi", box_model="inverse",
        orientation="improved", support_plane=True, shape=True, size=True),
}


def robust_kernel(name: str, k: float):
    """The kernel ``name`` ("none", "huber", "cauchy") with threshold k, None for "none" (and
    for an unresolved "auto", ``Method.resolved``)."""
    return {"huber": Huber, "cauchy": Cauchy}[name](k) if name not in ("none", "auto") else None


def check_sigma(name: str, value) -> float:
    """A run's sigma override (``--sigma NAME=VALUE``, a manifest's ``sigma``) as a float, or
    ``ValueError``: NAME one of ``DEFAULT_MAPPING_SIGMAS``, VALUE finite and positive (0 allowed
    for the additive relative terms, inf for the absolute trajectory sigmas)."""
    import math

    if name not in DEFAULT_MAPPING_SIGMAS:
        raise ValueError(f"expected a sigma among {', '.join(sorted(DEFAULT_MAPPING_SIGMAS))}, got {name!r}")
    v = float(value)
    if not ((math.isfinite(v) or (v == math.inf and name in INF_ALLOWED))
            and (v > 0 or (v == 0 and name in ZERO_ALLOWED))):
        raise ValueError(f"expected a finite positive value for {name}, got {value!r}")
    return v


def parse_robust(items, robust_k: float | None = None) -> dict:
    """Robust kernels in the command line's syntax → ``Method`` overrides, or ``ValueError``:
    each item KERNEL (box and measured-ellipsoid factors, threshold ``robust_k``, default 1)
    or TYPE=KERNEL[:K] (one factor type of ``factors.robust_groups()``)."""
    import math

    groups = robust_groups()
    out, by_type = {}, []
    for item in items or []:
        ftype, sep, rest = item.partition("=")
        if not sep:
            ftype, rest = None, item
        name, colon, k = rest.partition(":")
        try:
            k = float(k) if colon else (robust_k if robust_k is not None else 1.0)
        except ValueError:
            raise ValueError(f"{k!r} is not a number (in {item!r})") from None
        if (ftype is not None and ftype not in groups) \
                or name not in (ROBUST_KERNELS if ftype is not None else ROBUST_CHOICES) \
                or not (math.isfinite(k) and k > 0):
            raise ValueError(
                f"expected KERNEL or TYPE=KERNEL[:K] with KERNEL one of {', '.join(ROBUST_KERNELS)}, "
                f"TYPE one of {', '.join(groups)} and K > 0, got {item!r}")
        if ftype is None:
            out["robust"], out["robust_k"] = name, k
        else:
            by_type.append((ftype, name, k))
    if by_type:
        out["robust_by_type"] = tuple(by_type)
    if robust_k is not None and "robust" not in out:
        out["robust_k"] = robust_k
    return out
