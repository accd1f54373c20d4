"""spdslam: the back end of object-level SLAM with ellipsoid landmarks on SPD(3) × R³.

Conventions, stated once: poses ``T_wc`` are camera-to-world (as in TUM files); boxes are
``[u_min, v_min, u_max, v_max]`` in pixels; dual quadrics are normalised to Q*[3, 3] = −1.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from . import camera, factors, manifold, matfun, se3, solver, spd  # noqa: E402
from ._version import __version__  # noqa: E402
from .camera import (  # noqa: E402
    Camera,
    box_planes,
    camera_inside,
    in_front,
    look_at,
    project_box,
    project_dual_quadric,
)
from .ellipsoid import Ellipsoid, EllipsoidFull, EllipsoidRTS, as_ellipsoid  # noqa: E402
from .factors import (  # noqa: E402
    BetweenFactor,
    Cauchy,
    ClassicOrientationFactor,
    EllipsoidMeasurementFactor,
    Factor,
    Huber,
    InverseBoxFactor,
    OrientationFactor,
    PriorFactor,
    SemiInverseBoxFactor,
    ShapeFactor,
    SizeFactor,
    SupportPlaneFactor,
)
from .solver import (  # noqa: E402
    FactorGraph,
    GaussNewton,
    LevenbergMarquardt,
    NonlinearFactorGraph,
    OptimizationResult,
    Values,
    solve_batched,
)

__all__ = [
    "__version__",
    "Camera",
    "Ellipsoid",
    "EllipsoidRTS",
    "EllipsoidFull",
    "as_ellipsoid",
    "project_box",
    "project_dual_quadric",
    "box_planes",
    "in_front",
    "camera_inside",
    "look_at",
    "Factor",
    "Huber",
    "Cauchy",
    "InverseBoxFactor",
    "SemiInverseBoxFactor",
    "OrientationFactor",
    "ClassicOrientationFactor",
    "ShapeFactor",
    "SizeFactor",
    "SupportPlaneFactor",
    "EllipsoidMeasurementFactor",
    "PriorFactor",
    "BetweenFactor",
    "Values",
    "NonlinearFactorGraph",
    "FactorGraph",
    "LevenbergMarquardt",
    "GaussNewton",
    "OptimizationResult",
    "solve_batched",
    "camera",
    "factors",
    "solver",
    "manifold",
    "matfun",
    "spd",
    "se3",
]
