"""Files: the sequence model and its formats (one ``SequenceFormat`` class per input layout:
the canonical folder, fr3_cabinet, OA-SLAM, a detector's output folder (YOLO labels or COCO
results), ROS 2 bags; ``read_sequence`` finds a path's
format in the registry), g2o/TORO pose graphs, ``map.json`` and saved maps (``MapFormat``:
spdslam's run folders and Osmap maps; ``load_map`` finds a path's).

Every malformed file gives a one-line ``file:line: expected …, got …`` error
(``SequenceFormatError``, ``MapFormatError``). Imports ``geometry``, ``factors`` and
``solver`` (g2o builds pose graphs).
"""

from ._classes import BUILTIN_CLASSES as BUILTIN_CLASSES
from ._classes import CLASS_SOURCES as CLASS_SOURCES
from ._classes import ClassPrior as ClassPrior
from ._classes import builtin_class_prior as builtin_class_prior
from ._classes import class_prior as class_prior
from ._detector import COCO_IDS as COCO_IDS
from ._detector import DetectorFolder as DetectorFolder
from ._detector import import_detector_folder as import_detector_folder
from ._detector import read_camera_calibration as read_camera_calibration
from ._detector import read_class_names as read_class_names
from ._detector import read_coco_results as read_coco_results
from ._detector import read_image_times as read_image_times
from ._detector import read_yolo_labels as read_yolo_labels
from ._export import EXPORT_FORMATS as EXPORT_FORMATS
from ._export import GLTF_SEGMENTS as GLTF_SEGMENTS
from ._export import export_map as export_map
from ._export import gltf_document as gltf_document
from ._formats import ENTRY_POINT_GROUP as ENTRY_POINT_GROUP
from ._formats import FORMATS as FORMATS
from ._formats import SequenceFormat as SequenceFormat
from ._formats import check_sequence_path as check_sequence_path
from ._formats import find_format as find_format
from ._formats import formats as formats
from ._formats import formats_table as formats_table
from ._formats import read_measured_boxes as read_measured_boxes
from ._formats import read_sequence as read_sequence
from ._fr3_cabinet import COCO_LABELS as COCO_LABELS
from ._fr3_cabinet import FR3_TRAJECTORY_SIGMA as FR3_TRAJECTORY_SIGMA
from ._fr3_cabinet import Fr3CabinetFolder as Fr3CabinetFolder
from ._fr3_cabinet import import_fr3_cabinet as import_fr3_cabinet
from ._fr3_cabinet import is_fr3_cabinet as is_fr3_cabinet
from ._g2o import Edge as Edge
from ._g2o import PoseGraph as PoseGraph
from ._g2o import parse_g2o as parse_g2o
from ._g2o import pose_graph_factors as pose_graph_factors
from ._g2o import read_g2o as read_g2o
from ._g2o import rpy_to_quaternion as rpy_to_quaternion
from ._json import dumps_strict as dumps_strict
from ._map import MAP_CONVENTIONS as MAP_CONVENTIONS
from ._map import MAP_KEYS as MAP_KEYS
from ._map import MAP_UNITS as MAP_UNITS
from ._map import MAP_VERSION as MAP_VERSION
from ._map import MapFormatError as MapFormatError
from ._map import MapObject as MapObject
from ._map import map_document as map_document
from ._map import read_map as read_map
from ._map import write_map as write_map
from ._map_formats import MAP_FORMATS as MAP_FORMATS
from ._map_formats import PEER_MODE as PEER_MODE
from ._map_formats import MapFormat as MapFormat
from ._map_formats import SavedMap as SavedMap
from ._map_formats import SpdslamMap as SpdslamMap
from ._map_formats import find_map_format as find_map_format
from ._map_formats import load_map as load_map
from ._map_formats import map_formats as map_formats
from ._map_formats import peer_document as peer_document
from ._oaslam import COCO80 as COCO80
from ._oaslam import OASlamFolder as OASlamFolder
from ._oaslam import estimate_up as estimate_up
from ._oaslam import import_oaslam as import_oaslam
from ._oaslam import is_oaslam_layout as is_oaslam_layout
from ._oaslam import read_detections_json as read_detections_json
from ._oaslam import read_opencv_camera as read_opencv_camera
from ._oaslam import read_quadrics_gt as read_quadrics_gt
from ._osmap import OSMAP_MESSAGES as OSMAP_MESSAGES
from ._osmap import OsmapMap as OsmapMap
from ._osmap import osmap_messages as osmap_messages
from ._osmap import read_osmap as read_osmap
from ._parse import MATCH_TOLERANCE as MATCH_TOLERANCE
from ._parse import SequenceFormatError as SequenceFormatError
from ._parse import nearest_stamps as nearest_stamps
from ._parse import read_images as read_images
from ._parse import read_tum as read_tum

# YAML read node by node, with ``file:line`` errors (experiments' manifests use it too)
from ._parse import yaml_kind as yaml_kind
from ._parse import yaml_line as yaml_line
from ._parse import yaml_mapping as yaml_mapping
from ._parse import yaml_number as yaml_number
from ._parse import yaml_root as yaml_root
from ._parse import yaml_scalar as yaml_scalar

# the built-in formats, registered in this order (canonical first)
from ._readers import CanonicalFolder as CanonicalFolder
from ._readers import read_camera as read_camera
from ._readers import read_canonical as read_canonical
from ._readers import read_detections as read_detections
from ._readers import read_ellipsoids as read_ellipsoids
from ._readers import read_objects_gt as read_objects_gt
from ._readers import read_priors as read_priors
from ._rosbag import RosBag2 as RosBag2
from ._rosbag import import_rosbag as import_rosbag
from ._rosbag import is_rosbag as is_rosbag
from ._sequence import Detection as Detection
from ._sequence import EllipsoidDetection as EllipsoidDetection
from ._sequence import GroundTruthObject as GroundTruthObject
from ._sequence import Priors as Priors
from ._sequence import Sequence as Sequence
from ._sequence import without_class_table as without_class_table
from ._writers import tum_text as tum_text
from ._writers import write_file_atomically as write_file_atomically
from ._writers import write_folder_atomically as write_folder_atomically
from ._writers import write_sequence as write_sequence
