"""Factors: residual functions with noise models and robust kernels.

Landmark factors take any ellipsoid parameterisation (SPD, RTS or Full); pose factors take
``jaxlie.SE3`` camera-to-world poses.
"""

from ._base import Cauchy, Factor, Huber, RobustKernel, sqrt_information, tangent_jacobians
from ._landmark import (
    DEFAULT_SIGMAS,
    ClassicOrientationFactor,
    InverseBoxFactor,
    OrientationFactor,
    SemiInverseBoxFactor,
    ShapeFactor,
    SizeFactor,
    SupportPlaneFactor,
    box_visible,
    classic_orientation_residual,
    inverse_box_residual,
    orientation_residual,
    semi_inverse_box_residual,
    shape_residual,
    size_residual,
    support_plane_residual,
)
from ._pose import BetweenFactor, PriorFactor, pose_between_residual, pose_prior_residual

__all__ = [
    "Factor",
    "RobustKernel",
    "Huber",
    "Cauchy",
    "sqrt_information",
    "tangent_jacobians",
    "DEFAULT_SIGMAS",
    "InverseBoxFactor",
    "SemiInverseBoxFactor",
    "OrientationFactor",
    "ClassicOrientationFactor",
    "ShapeFactor",
    "SizeFactor",
    "SupportPlaneFactor",
    "box_visible",
    "inverse_box_residual",
    "semi_inverse_box_residual",
    "orientation_residual",
    "classic_orientation_residual",
    "shape_residual",
    "size_residual",
    "support_plane_residual",
    "PriorFactor",
    "BetweenFactor",
    "pose_prior_residual",
    "pose_between_residual",
]
