"""Factors: residual functions with noise models and robust kernels, one class per factor
type, registered when defined (``factor_types()``).

Landmark factors take any ellipsoid parameterisation (SPD, RTS or Full); pose factors take
``jaxlie.SE3`` camera-to-world poses. Imports only ``spdslam.geometry``.
"""

from ._base import Cauchy as Cauchy
from ._base import CustomFactor as CustomFactor
from ._base import Factor as Factor
from ._base import FactorBatch as FactorBatch
from ._base import GaussianNoise as GaussianNoise
from ._base import Huber as Huber
from ._base import RobustKernel as RobustKernel
from ._base import Sigma as Sigma
from ._base import default_sigmas as default_sigmas
from ._base import diagonal_sqrt_information as diagonal_sqrt_information
from ._base import factor_types as factor_types
from ._base import robust_groups as robust_groups
from ._base import robust_weighting as robust_weighting
from ._base import sqrt_information as sqrt_information
from ._base import tangent_jacobians as tangent_jacobians
from ._box import DEFAULT_TRUNCATION_MARGIN as DEFAULT_TRUNCATION_MARGIN
from ._box import DriftBoxFactor as DriftBoxFactor
from ._box import FrameBoxFactor as FrameBoxFactor
from ._box import InverseBoxFactor as InverseBoxFactor
from ._box import InverseCuboidBoxFactor as InverseCuboidBoxFactor
from ._box import SemiInverseBoxFactor as SemiInverseBoxFactor
from ._box import SemiInverseCuboidBoxFactor as SemiInverseCuboidBoxFactor
from ._box import box_visible as box_visible
from ._box import cuboid_box_visible as cuboid_box_visible
from ._box import drift_box_residual as drift_box_residual
from ._box import frame_box_residual as frame_box_residual
from ._box import inverse_box_residual as inverse_box_residual
from ._box import inverse_cuboid_box_residual as inverse_cuboid_box_residual
from ._box import semi_inverse_box_residual as semi_inverse_box_residual
from ._box import semi_inverse_cuboid_box_residual as semi_inverse_cuboid_box_residual
from ._ellipsoid_measurement import (
    EllipsoidMeasurementFactor as EllipsoidMeasurementFactor,
)
from ._ellipsoid_measurement import (
    ellipsoid_measurement_residual as ellipsoid_measurement_residual,
)
from ._landmark_prior import LandmarkPriorFactor as LandmarkPriorFactor
from ._landmark_prior import landmark_prior_residual as landmark_prior_residual
from ._object import AxisOrientationFactor as AxisOrientationFactor
from ._object import ClassicOrientationFactor as ClassicOrientationFactor
from ._object import ClassicShapeFactor as ClassicShapeFactor
from ._object import OrientationFactor as OrientationFactor
from ._object import RadiusFloorFactor as RadiusFloorFactor
from ._object import ShapeFactor as ShapeFactor
from ._object import SizeFactor as SizeFactor
from ._object import SupportPlaneFactor as SupportPlaneFactor
from ._object import axis_orientation_residual as axis_orientation_residual
from ._object import classic_orientation_residual as classic_orientation_residual
from ._object import classic_shape_residual as classic_shape_residual
from ._object import orientation_residual as orientation_residual
from ._object import radius_floor_residual as radius_floor_residual
from ._object import shape_residual as shape_residual
from ._object import size_residual as size_residual
from ._object import support_plane_residual as support_plane_residual
from ._pose import BetweenFactor as BetweenFactor
from ._pose import PriorFactor as PriorFactor
from ._pose import pose_between_residual as pose_between_residual
from ._pose import pose_prior_residual as pose_prior_residual

# isort: split
# last: the closed forms import the factor modules, which register their groups in the order above
from ._closed_form import ClosedForm as ClosedForm
from ._closed_form import closed_form as closed_form
from ._closed_form import eigenvalue_steps as eigenvalue_steps
from ._closed_form import ellipsoid_boxes as ellipsoid_boxes
from ._closed_form import inverse_box_linearization as inverse_box_linearization
from ._closed_form import orientation_linearization as orientation_linearization
from ._closed_form import pose_between_linearization as pose_between_linearization
from ._closed_form import pose_prior_linearization as pose_prior_linearization
from ._closed_form import radius_floor_linearization as radius_floor_linearization
from ._closed_form import shape_linearization as shape_linearization
from ._closed_form import size_linearization as size_linearization
