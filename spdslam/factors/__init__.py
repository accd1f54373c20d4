"""Factors: residual functions with noise models and robust kernels.

Landmark factors take any ellipsoid parameterisation (SPD, RTS or Full); pose factors take
``jaxlie.SE3`` camera-to-world poses.
"""

from ._base import Cauchy, Factor, Huber, RobustKernel, sqrt_information
from ._pose import BetweenFactor, PriorFactor, pose_between_residual, pose_prior_residual

__all__ = [
    "Factor",
    "RobustKernel",
    "Huber",
    "Cauchy",
    "sqrt_information",
    "PriorFactor",
    "BetweenFactor",
    "pose_prior_residual",
    "pose_between_residual",
]
