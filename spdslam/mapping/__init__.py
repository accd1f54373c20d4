"""Mapping a sequence: the back-end methods of Table III, the factor graph of a sequence and
the run (associate → initialise → build the graph → solve), online, and reuse of a saved
map. Imports ``geometry``, ``factors``, ``solver``, ``io`` and ``frontend``; never
``evaluation``. What a user calls is below (docs/core.md says what each is); the rest is
private to the package.
"""

from ._batch import run_sequence as run_sequence
from ._context import SequenceContext as SequenceContext
from ._graph import OBJECT_FACTORS as OBJECT_FACTORS
from ._graph import ObjectFactorRule as ObjectFactorRule
from ._graph import build_graph as build_graph
from ._localizing import LocalizingMapper as LocalizingMapper
from ._methods import METHODS as METHODS
from ._methods import Method as Method
from ._online import OnlineMapper as OnlineMapper
from ._online import run_online as run_online
from ._reuse import Localization as Localization
from ._reuse import LocalizationError as LocalizationError
from ._reuse import confirm_by_boxes as confirm_by_boxes
from ._reuse import joined_sequence as joined_sequence
from ._reuse import localize_objects as localize_objects
from ._reuse import localized_result as localized_result
from ._reuse import moved_sequence as moved_sequence
from ._reuse import refine_localization as refine_localization
from ._reuse import transform_ellipsoid as transform_ellipsoid
from ._run import MappingError as MappingError
from ._run import MapResult as MapResult
from ._settings import SETTINGS as SETTINGS
from ._settings import OnlineSettings as OnlineSettings
from ._settings import RunSettings as RunSettings
from ._settings import SettingsError as SettingsError
