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
``spdslam.mapping``, ``spdslam.io`` and so on. The re-exports are lazy (PEP 562): ``import
spdslam`` costs nothing; a subpackage, and JAX with it, is imported on the first use of one
of its names, so that ``spdslam --help`` or reading a file need not import JAX.
"""

from __future__ import annotations

import importlib as _importlib
import os as _os
import sys as _sys
from typing import TYPE_CHECKING

from ._version import __version__ as __version__

# float64 in JAX everywhere, set before any spdslam code uses JAX and without importing it here:
# JAX reads JAX_ENABLE_X64 when it is first imported (by geometry, the lowest layer, or by the
# caller); a JAX imported already is told directly.
if "jax" in _sys.modules:
    _sys.modules["jax"].config.update("jax_enable_x64", True)
else:
    _os.environ["JAX_ENABLE_X64"] = "1"

#: The subpackages re-exported, and the names each one lends the package.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "factors": (
        "BetweenFactor", "Cauchy", "ClassicOrientationFactor", "CustomFactor", "EllipsoidMeasurementFactor",
        "Factor", "GaussianNoise", "Huber", "InverseBoxFactor", "OrientationFactor", "PriorFactor",
        "SemiInverseBoxFactor", "ShapeFactor", "SizeFactor", "SupportPlaneFactor",
    ),
    "geometry": (
        "Camera", "Ellipsoid", "EllipsoidFull", "EllipsoidRTS", "as_ellipsoid", "box_planes", "camera_inside",
        "in_front", "look_at", "manifold", "matfun", "project_box", "project_dual_quadric", "se3", "spd",
    ),
    "solver": (
        "BatchedProblem", "Dogleg", "GaussNewton", "L", "LevenbergMarquardt", "NonlinearFactorGraph",
        "OptimizationResult", "Values", "X",
    ),
}
_ORIGIN = {name: package for package, names in _EXPORTS.items() for name in names}

if TYPE_CHECKING:
    from . import factors as factors
    from . import geometry as geometry
    from . import solver as solver
    from .factors import BetweenFactor as BetweenFactor
    from .factors import Cauchy as Cauchy
    from .factors import ClassicOrientationFactor as ClassicOrientationFactor
    from .factors import CustomFactor as CustomFactor
    from .factors import EllipsoidMeasurementFactor as EllipsoidMeasurementFactor
    from .factors import Factor as Factor
    from .factors import GaussianNoise as GaussianNoise
    from .factors import Huber as Huber
    from .factors import InverseBoxFactor as InverseBoxFactor
    from .factors import OrientationFactor as OrientationFactor
    from .factors import PriorFactor as PriorFactor
    from .factors import SemiInverseBoxFactor as SemiInverseBoxFactor
    from .factors import ShapeFactor as ShapeFactor
    from .factors import SizeFactor as SizeFactor
    from .factors import SupportPlaneFactor as SupportPlaneFactor
    from .geometry import Camera as Camera
    from .geometry import Ellipsoid as Ellipsoid
    from .geometry import EllipsoidFull as EllipsoidFull
    from .geometry import EllipsoidRTS as EllipsoidRTS
    from .geometry import as_ellipsoid as as_ellipsoid
    from .geometry import box_planes as box_planes
    from .geometry import camera_inside as camera_inside
    from .geometry import in_front as in_front
    from .geometry import look_at as look_at
    from .geometry import manifold as manifold
    from .geometry import matfun as matfun
    from .geometry import project_box as project_box
    from .geometry import project_dual_quadric as project_dual_quadric
    from .geometry import se3 as se3
    from .geometry import spd as spd
    from .solver import BatchedProblem as BatchedProblem
    from .solver import Dogleg as Dogleg
    from .solver import GaussNewton as GaussNewton
    from .solver import L as L
    from .solver import LevenbergMarquardt as LevenbergMarquardt
    from .solver import NonlinearFactorGraph as NonlinearFactorGraph
    from .solver import OptimizationResult as OptimizationResult
    from .solver import Values as Values
    from .solver import X as X


def __getattr__(name: str):
    """A re-exported subpackage or name, imported on first use (then kept in the package)."""
    if name in _EXPORTS:
        value = _importlib.import_module(f"{__name__}.{name}")
    elif name in _ORIGIN:
        value = getattr(_importlib.import_module(f"{__name__}.{_ORIGIN[name]}"), name)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS) | set(_ORIGIN))
