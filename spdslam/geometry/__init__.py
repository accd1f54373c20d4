"""Geometry: ellipsoid landmarks, SPD(3), SE(3), the pinhole camera, image boxes and cuboids.

The lowest layer: it imports nothing else of spdslam. Every function here is written once
and serves NumPy and JAX alike (``array_namespace``): NumPy in, NumPy out, no JAX dispatch;
JAX in (or traced), JAX out, differentiable.

Namespaces: ``matfun`` (spectral functions of symmetric matrices with derivatives finite at
repeated eigenvalues), ``spd`` (the manifold SPD(3): retraction, log map, distance),
``se3`` (poses and the camera-to-world convention), ``manifold`` (the registry of
optimisation variable types), ``native`` (the compiled kernels, where built).
"""

from . import manifold as manifold
from . import matfun as matfun
from . import native as native
from . import se3 as se3
from . import spd as spd
from ._align import align_rigid as align_rigid
from ._align import align_rigid_many as align_rigid_many
from ._arrays import array_namespace as array_namespace
from ._boxes import box_iou as box_iou
from ._camera import Camera as Camera
from ._camera import Equidistant as Equidistant
from ._camera import box_lines as box_lines
from ._camera import box_planes as box_planes
from ._camera import camera_inside as camera_inside
from ._camera import conic_box as conic_box
from ._camera import cuboid_depth_range as cuboid_depth_range
from ._camera import cuboid_in_front as cuboid_in_front
from ._camera import depth_range as depth_range
from ._camera import distort_points as distort_points
from ._camera import in_front as in_front
from ._camera import look_at as look_at
from ._camera import normalize_plane as normalize_plane
from ._camera import project_box as project_box
from ._camera import project_cuboid_box as project_cuboid_box
from ._camera import project_dual_quadric as project_dual_quadric
from ._camera import project_points as project_points
from ._camera import projection_matrix as projection_matrix
from ._camera import truncation_mask as truncation_mask
from ._camera import undistort_boxes as undistort_boxes
from ._camera import undistort_points as undistort_points
from ._cuboid import CORNER_SIGNS as CORNER_SIGNS
from ._cuboid import CUBOID_EDGES as CUBOID_EDGES
from ._cuboid import OBJECT_SHAPES as OBJECT_SHAPES
from ._cuboid import Cuboid as Cuboid
from ._cuboid import as_cuboid as as_cuboid
from ._cuboid import checked_rotation as checked_rotation
from ._cuboid import checked_vector as checked_vector
from ._ellipsoid import Ellipsoid as Ellipsoid
from ._ellipsoid import EllipsoidFull as EllipsoidFull
from ._ellipsoid import EllipsoidRTS as EllipsoidRTS
from ._ellipsoid import Landmark as Landmark
from ._ellipsoid import as_ellipsoid as as_ellipsoid
from ._ellipsoid import cuboid_corners as cuboid_corners
from ._ellipsoid import cuboid_half_axes as cuboid_half_axes
from ._ellipsoid import dual_quadric as dual_quadric
from ._ellipsoid import dual_quadric_of as dual_quadric_of
from ._ellipsoid import moved_covariance as moved_covariance
from ._ellipsoid import sorted_axes as sorted_axes
from ._sim3 import Sim3 as Sim3
from ._sim3 import frame_pose as frame_pose
from ._sim3 import interpolated_frame as interpolated_frame
