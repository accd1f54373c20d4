"""spdslam: the back end of object-level SLAM with ellipsoid landmarks on SPD(3) × R³.

Conventions, stated once: poses ``T_wc`` are camera-to-world (as in TUM files); boxes are
``[u_min, v_min, u_max, v_max]`` in pixels; dual quadrics are normalised to Q*[3, 3] = −1.

Layers, each a subpackage that imports only the ones above it in this list:

    geometry     landmarks, SPD(3), SE(3), camera, cuboids (NumPy and JAX)
    factors      residual functions, noise models, the registry of factor types
    solver       Values, graphs, the LM/GN rule, sparse and batched drivers
    io           the sequence model, readers, writers, importers, g2o, map.json
    synthetic    simulated single-object scenes and demo rooms
    frontend     initialisation and data association
    mapping      methods, graph building and the run of a sequence
    evaluation   metrics, statistics, reports, plots (reads ground truth; mapping never)
    experiments  the paper's Table II study
    cli          the ``spdslam`` command

This package re-exports the core (geometry, factors, solver); import the pipelines as
``spdslam.mapping``, ``spdslam.io`` and so on.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from . import factors as factors  # noqa: E402
from . import geometry as geometry  # noqa: E402
from . import solver as solver  # noqa: E402
from ._version import __version__ as __version__  # noqa: E402
from .factors import BetweenFactor as BetweenFactor  # noqa: E402
from .factors import Cauchy as Cauchy  # noqa: E402
from .factors import ClassicOrientationFactor as ClassicOrientationFactor  # noqa: E402
from .factors import CustomFactor as CustomFactor  # noqa: E402
from .factors import EllipsoidMeasurementFactor as EllipsoidMeasurementFactor  # noqa: E402
from .factors import Factor as Factor  # noqa: E402
from .factors import GaussianNoise as GaussianNoise  # noqa: E402
from .factors import Huber as Huber  # noqa: E402
from .factors import InverseBoxFactor as InverseBoxFactor  # noqa: E402
from .factors import OrientationFactor as OrientationFactor  # noqa: E402
from .factors import PriorFactor as PriorFactor  # noqa: E402
from .factors import SemiInverseBoxFactor as SemiInverseBoxFactor  # noqa: E402
from .factors import ShapeFactor as ShapeFactor  # noqa: E402
from .factors import SizeFactor as SizeFactor  # noqa: E402
from .factors import SupportPlaneFactor as SupportPlaneFactor  # noqa: E402
from .geometry import Camera as Camera  # noqa: E402
from .geometry import Ellipsoid as Ellipsoid  # noqa: E402
from .geometry import EllipsoidFull as EllipsoidFull  # noqa: E402
from .geometry import EllipsoidRTS as EllipsoidRTS  # noqa: E402
from .geometry import as_ellipsoid as as_ellipsoid  # noqa: E402
from .geometry import box_planes as box_planes  # noqa: E402
from .geometry import camera_inside as camera_inside  # noqa: E402
from .geometry import in_front as in_front  # noqa: E402
from .geometry import look_at as look_at  # noqa: E402
from .geometry import manifold as manifold  # noqa: E402
from .geometry import matfun as matfun  # noqa: E402
from .geometry import project_box as project_box  # noqa: E402
from .geometry import project_dual_quadric as project_dual_quadric  # noqa: E402
from .geometry import se3 as se3  # noqa: E402
from .geometry import spd as spd  # noqa: E402
from .solver import BatchedProblem as BatchedProblem  # noqa: E402
from .solver import Dogleg as Dogleg  # noqa: E402
from .solver import GaussNewton as GaussNewton  # noqa: E402
from .solver import L as L  # noqa: E402
from .solver import LevenbergMarquardt as LevenbergMarquardt  # noqa: E402
from .solver import NonlinearFactorGraph as NonlinearFactorGraph  # noqa: E402
from .solver import OptimizationResult as OptimizationResult  # noqa: E402
from .solver import Values as Values  # noqa: E402
from .solver import X as X  # noqa: E402
