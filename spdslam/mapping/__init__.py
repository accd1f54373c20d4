"""Mapping a sequence: the back-end methods of Table III, the factor graph of a sequence and
the run (associate → initialise → build the graph → solve). Imports ``geometry``,
``factors``, ``solver``, ``io`` and ``frontend``; never ``evaluation``.
"""

from ._context import SequenceContext as SequenceContext
from ._context import object_shape as object_shape
from ._graph import BOX_FACTORS as BOX_FACTORS
from ._graph import build_graph as build_graph
from ._graph import mapping_sigmas as mapping_sigmas
from ._graph import measured_objects as measured_objects
from ._graph import support_plane as support_plane
from ._keyframes import KEYFRAME_MODES as KEYFRAME_MODES
from ._keyframes import parse_keyframes as parse_keyframes
from ._keyframes import select_keyframes as select_keyframes
from ._methods import BOX_MODELS as BOX_MODELS
from ._methods import DEFAULT_MAPPING_SIGMAS as DEFAULT_MAPPING_SIGMAS
from ._methods import INITIALIZATIONS as INITIALIZATIONS
from ._methods import MAPPING_SIGMAS as MAPPING_SIGMAS
from ._methods import METHODS as METHODS
from ._methods import OBJECT_SHAPE_CHOICES as OBJECT_SHAPE_CHOICES
from ._methods import ORIENTATIONS as ORIENTATIONS
from ._methods import PARAMETERIZATIONS as PARAMETERIZATIONS
from ._methods import ROBUST_KERNELS as ROBUST_KERNELS
from ._methods import SHAPE_FORMS as SHAPE_FORMS
from ._methods import Method as Method
from ._methods import check_sigma as check_sigma
from ._methods import parse_robust as parse_robust
from ._methods import robust_kernel as robust_kernel
from ._methods import sigma_units as sigma_units
from ._online import FrameRecord as FrameRecord
from ._online import OnlineMap as OnlineMap
from ._online import OnlineMapper as OnlineMapper
from ._online import run_online as run_online
from ._run import ASSOCIATIONS as ASSOCIATIONS
from ._run import MAX_CENTER_SIGMA as MAX_CENTER_SIGMA
from ._run import MAX_LOG_RADIUS_SIGMA as MAX_LOG_RADIUS_SIGMA
from ._run import MIN_DETECTION_RATE as MIN_DETECTION_RATE
from ._run import MIN_RADIUS as MIN_RADIUS
from ._run import MIN_RADIUS_RATIO as MIN_RADIUS_RATIO
from ._run import SUPPORT_PLANES as SUPPORT_PLANES
from ._run import Association as Association
from ._run import Initialization as Initialization
from ._run import MapResult as MapResult
from ._run import associate_tracks as associate_tracks
from ._run import degenerate as degenerate
from ._run import detection_rate as detection_rate
from ._run import initialize as initialize
from ._run import initialize_from_measurements as initialize_from_measurements
from ._run import initialize_objects as initialize_objects
from ._run import mapped_uncertainty as mapped_uncertainty
from ._run import map_result as map_result
from ._run import merged_track as merged_track
from ._run import object_uncertainty as object_uncertainty
from ._run import overlapping_duplicates as overlapping_duplicates
from ._run import poorly_observed as poorly_observed
from ._run import run_sequence as run_sequence
