"""The front end: detections grouped into tracks (data association) and each track's
initial ellipsoid (Quadric-SVD, Quadric-Multi), and the support planes the initial objects
rest on. Imports ``geometry`` and ``io``.
"""

from ._association import Association as Association
from ._association import AssociationSettings as AssociationSettings
from ._association import OnlineTracker as OnlineTracker
from ._association import Track as Track
from ._association import associate as associate
from ._association import associate_detailed as associate_detailed
from ._association import merge_tracks as merge_tracks
from ._association import tracks_from_instances as tracks_from_instances
from ._initialization import InitializationError as InitializationError
from ._initialization import MultiFit as MultiFit
from ._initialization import multi_initialize as multi_initialize
from ._initialization import multi_initialize_batch as multi_initialize_batch
from ._initialization import sphere_initialize as sphere_initialize
from ._initialization import svd_initialize as svd_initialize
from ._initialization import triangulate_rays as triangulate_rays
from ._initialization import unoriented_initialize as unoriented_initialize
from ._scene import SupportPlanes as SupportPlanes
from ._scene import estimate_support_planes as estimate_support_planes
from ._scene import lowest_points as lowest_points
from ._screening import SCREEN_REASONS as SCREEN_REASONS
from ._screening import Screening as Screening
from ._screening import screen_detections as screen_detections
from ._screening import screen_frame as screen_frame
from ._screening import screen_summary as screen_summary
