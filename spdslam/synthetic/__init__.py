"""Synthetic data: the paper's single-object simulation scenes (batched) and the demo rooms
(whole sequences with drift, truncation, false and missed detections). Imports
``geometry`` and ``io``.
"""

from ._rooms import MARGIN_PX as MARGIN_PX
from ._rooms import MIN_BOX_PX as MIN_BOX_PX
from ._rooms import ROOM_CLASSES as ROOM_CLASSES
from ._rooms import drifted_sequence as drifted_sequence
from ._rooms import make_room_sequence as make_room_sequence
from ._scenes import DEFAULT_CAMERA as DEFAULT_CAMERA
from ._scenes import NOISE_LEVELS as NOISE_LEVELS
from ._scenes import PATTERNS as PATTERNS
from ._scenes import PROTOCOLS as PROTOCOLS
from ._scenes import Protocol as Protocol
from ._scenes import Scene as Scene
from ._scenes import Scenes as Scenes
from ._scenes import get_protocol as get_protocol
from ._scenes import make_scene as make_scene
from ._scenes import make_scenes as make_scenes
from ._scenes import random_rotations as random_rotations
