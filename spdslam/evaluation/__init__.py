"""Evaluation against ground truth: 3D IoU of oriented cuboids, orientation error up to
axis order and sign, trajectory error, confidence intervals, the run's report and figures.
Imports ``geometry`` and ``io``; it evaluates any map, however it was made, and computes
only: the figures, the recording and the run's folder are ``experiments``'
(``experiments.write_run``).
"""

from ..geometry import box_iou as box_iou  # the IoU of image boxes, used by the check
from ..io import dumps_strict as dumps_strict  # strict JSON, for the layers above io
from ._association import association_scores as association_scores
from ._check import BOX_CONVENTIONS as BOX_CONVENTIONS
from ._check import CheckReference as CheckReference
from ._check import camera_frame_offset as camera_frame_offset
from ._check import check_findings as check_findings
from ._check import check_sequence as check_sequence
from ._check import interpolate_poses as interpolate_poses
from ._check import match_detections as match_detections
from ._check import pair_detections as pair_detections
from ._check import reference_of_ground_truth as reference_of_ground_truth
from ._ellipses import camera_centers as camera_centers
from ._ellipses import conic_ellipse as conic_ellipse
from ._ellipses import conic_ellipses as conic_ellipses
from ._ellipses import conic_outline as conic_outline
from ._ellipses import ellipse_points as ellipse_points
from ._ellipses import ellipses_points as ellipses_points
from ._ellipses import plane_basis as plane_basis
from ._ellipses import top_view_ellipse as top_view_ellipse
from ._metrics import MAX_ORIENTATION_ERROR_DEG as MAX_ORIENTATION_ERROR_DEG
from ._metrics import absolute_trajectory_error as absolute_trajectory_error
from ._metrics import align_rigid as align_rigid
from ._metrics import associate_timestamps as associate_timestamps
from ._metrics import cuboid_iou as cuboid_iou
from ._metrics import cuboid_iou_arrays as cuboid_iou_arrays
from ._metrics import cuboid_iou_batch as cuboid_iou_batch
from ._metrics import orientation_error_deg as orientation_error_deg
from ._metrics import orientation_errors_deg as orientation_errors_deg
from ._metrics import signed_permutations as signed_permutations
from ._metrics import trajectory_alignment as trajectory_alignment
from ._metrics import translation_error as translation_error
from ._report import FRONT_END_NAMES as FRONT_END_NAMES
from ._report import ObjectMetrics as ObjectMetrics
from ._report import ate_line as ate_line
from ._report import count_duplicates as count_duplicates
from ._report import evaluate_objects as evaluate_objects
from ._report import evaluate_run as evaluate_run
from ._report import ground_truth_in_map_frame as ground_truth_in_map_frame
from ._report import match_objects as match_objects
from ._report import moved as moved
from ._report import report_markdown as report_markdown
from ._report import shown as shown
from ._report import table_iii as table_iii
from ._report import to_groundtruth as to_groundtruth
from ._stats import Interval as Interval
from ._stats import PairedComparison as PairedComparison
from ._stats import bootstrap as bootstrap
from ._stats import paired_comparison as paired_comparison
from ._stats import wilson as wilson
