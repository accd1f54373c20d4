"""The settings of a run, validated once, where they enter.

``spdslam run``'s options, a manifest's job, the Python API (``run_sequence``,
``run_online``) and ``OnlineMapper`` all build one :class:`RunSettings` (with an
:class:`OnlineSettings` for an online run) before any work starts; its fields keep their
names from the command line (``--max-iterations`` → ``max_iterations``) and a manifest's
keys to the solver. A bad value is a :class:`SettingsError` naming the field.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping

from ..factors import DEFAULT_TRUNCATION_MARGIN
from ._keyframes import parse_keyframes
from ._methods import (
    AUTO_BOX_KERNEL,
    BOX_MODELS,
    DEFAULT_MAPPING_SIGMAS,
    METHODS,
    OBJECT_SHAPE_CHOICES,
    PARAMETERIZATIONS,
    ROBUST_CHOICES,
    ROBUST_KERNELS,
    Method,
    check_sigma,
    parse_robust,
)

__all__ = [
    "Associate",
    "METHOD_FIELDS",
    "OnlineSettings",
    "PlaneSource",
    "RUN_OVERRIDES",
    "RUN_SETTING_NAMES",
    "RunSettings",
    "SETTINGS",
    "SettingsError",
    "SettingsReference",
    "InitialPoses",
    "as_online_settings",
    "as_settings",
    "default_association",
    "setting_help",
]


class Associate(enum.StrEnum):
    """How detections are grouped into objects: by their instance ids, or automatically
    (``frontend.associate``, which ignores the ids)."""

    INSTANCES = "instances"
    AUTO = "auto"


class InitialPoses(enum.StrEnum):
    """Where a batch run's poses come from on a trajectory without a bound on each pose
    (drifting odometry). input: the joint optimisation starts from the input poses, each pose
    as free as the trajectory's noise model lets it (the boxes move the poses); incremental:
    from the poses the online mapper ends at when the frames are replayed through it first
    (its objects and, with automatic association, its tracks are taken too); loops: the
    objects mapped on the input poses held, the drift taken out by the loops their objects
    close between submaps (``close_loops``), and the poses then held at the corrected
    trajectory; the boxes move them only when a cross-validation between halves of the
    labels says they help (``_refine``). auto: loops on a trajectory without a bound
    on each pose (neither ``hold_trajectory`` nor a drift interval), else input. Every
    trajectory a step proposes is checked against the odometry's walk
    (``check_trajectory``)."""

    INPUT = "input"
    INCREMENTAL = "incremental"
    LOOPS = "loops"
    AUTO = "auto"


class PlaneSource(enum.StrEnum):
    """Where support planes come from: the priors only; else estimated from the initial
    objects; else from the objects optimised without planes (then optimised again)."""

    PRIORS = "priors"
    INITIAL = "initial"
    OPTIMISED = "optimised"


class SettingsError(ValueError):
    """A setting out of its range: ``"<field>: <reason>"``; ``field`` names it (a field of
    ``RunSettings``, ``online.<field>`` for ``OnlineSettings``, or a ``Method`` field)."""

    def __init__(self, name: str, reason: str):
        super().__init__(f"{name}: {reason}")
        self.field = name
        self.reason = reason


def _help(text: str, **more) -> dict:
    return {"help": text, **more}


def _integer(name: str, value, least: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        try:  # NumPy integers and integral floats from a caller's arithmetic
            ok = (not isinstance(value, (bool, str)) and float(value) == int(value)
                  and int(value) >= least)
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise SettingsError(name, f"expected an integer ≥ {least}, got {value!r}")
    return int(value)


def _boolean(name: str, value) -> bool:
    if not isinstance(value, bool):
        raise SettingsError(name, f"expected true or false, got {value!r}")
    return value


def _choice(name: str, kind: type[enum.StrEnum], value):
    try:
        return kind(value)
    except ValueError:
        raise SettingsError(name, f"expected one of {', '.join(kind)}, got {value!r}") from None


#: What the online mapper maps with: landmark parameterisations and box models.
ONLINE_PARAMETERIZATIONS = ("spd", "rts")
ONLINE_BOX_MODELS = ("inverse", "semi")


def maps_online(method: Method) -> bool:
    """Whether the online mapper takes ``method`` (``ONLINE_PARAMETERIZATIONS``,
    ``ONLINE_BOX_MODELS``)."""
    return method.parameterization in ONLINE_PARAMETERIZATIONS and method.box_model in ONLINE_BOX_MODELS


@dataclass(frozen=True)
class OnlineSettings:
    """An online run (``OnlineMapper``, ``spdslam run --online``): a fixed-lag smoother."""

    window: int = field(default=30, metadata=_help(
        "frames whose poses the fixed-lag problem keeps free", least=2))
    every: int = field(default=10, metadata=_help("frames between optimisations", least=1))
    iterations: int = field(default=5, metadata=_help("LM iterations per optimisation", least=1))
    final_batch: bool = field(default=True, metadata=_help(
        "after the last frame, one batch optimisation of every frame and view from the online "
        "state (max_iterations); without it the map is the online estimates"))
    warmup: bool = field(default=False, metadata=_help(
        "compile before the first frame (a synthetic room replayed with the camera; "
        "OnlineMapper.warmup), as a live mapper would"))
    background: bool = field(default=False, metadata=_help(
        "optimise in a worker thread: a frame's own work returns at once and each "
        "optimisation publishes its map when it ends (the same maps; latency.csv's lag says "
        "when)"))
    realtime: bool = field(default=False, metadata=_help(
        "replay a recording at its own rate: each frame is added when its time since the first "
        "frame has passed, as a camera delivers it"))

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            name = f"online.{f.name}"
            v = _boolean(name, v) if f.type == "bool" else _integer(name, v, f.metadata["least"])
            object.__setattr__(self, f.name, v)


#: What a ``Method`` override must be, by its field's declared type (``_check_type``).
_KINDS = {"bool": ((bool,), "true or false"), "float": ((int, float), "a number"),
          "str": ((str,), "a string")}


def _check_type(name: str, value) -> None:
    """A ``Method`` override of the wrong type is a ``SettingsError`` (``robust``: a kernel
    or a list of them, in the command line's syntax)."""
    if name == "robust":
        items = [value] if isinstance(value, str) else value
        if not isinstance(items, (list, tuple)) or not all(isinstance(i, str) for i in items):
            raise SettingsError(name, f"expected KERNEL or a list of KERNEL or TYPE=KERNEL[:K], got {value!r}")
        return
    kind = _METHOD_TYPES.get(name)
    if kind in _KINDS:
        types, what = _KINDS[kind]
        if not isinstance(value, types) or (kind == "float" and isinstance(value, bool)):
            raise SettingsError(name, f"expected {what}, got {value!r}")


def default_association(seq) -> Associate:
    """Instance ids when every detection of ``seq`` has one (or there is none), else
    automatic association."""
    has_ids = bool(seq.detections) and all(d.instance is not None for d in seq.detections)
    return Associate.INSTANCES if has_ids or not seq.detections else Associate.AUTO


#: ``Method`` fields that a run may override by name (``RunSettings.of``).
METHOD_FIELDS = tuple(f.name for f in dataclasses.fields(Method) if f.name != "name")
_METHOD_TYPES = {f.name: f.type for f in dataclasses.fields(Method)}
#: The ``Method`` overrides of ``spdslam run``'s options and a manifest's keys, with their help.
RUN_OVERRIDES = {
    "parameterization": f"override the landmark's parameterisation: {', '.join(PARAMETERIZATIONS)}",
    "box_model": f"override the box model: {', '.join(BOX_MODELS)}",
    "object_shape": f"silhouette model: {', '.join(OBJECT_SHAPE_CHOICES)} (priors: per class, "
                    "priors.yaml 'shape')",
    "truncation_margin": "box edges within this many px of the image border carry no bound "
                         f"(negative: keep all; default {DEFAULT_TRUNCATION_MARGIN:g})",
    "robust": "robust kernels: KERNEL or TYPE=KERNEL[:K], a list",
    "robust_k": "threshold of a plain KERNEL (whitened units, default 1)",
}


@dataclass(frozen=True)
class RunSettings:
    """Everything a run is told, checked on construction (``SettingsError``). ``method``: the
    back end with its overrides applied (``RunSettings.of`` takes a name and overrides)."""

    method: Method = field(default=METHODS["multi-spd"], metadata=_help(
        "the back end: a name of METHODS with its overrides"))
    associate: Associate | None = field(default=None, metadata=_help(
        "data association: instances (the instance ids) or auto; default: instances when "
        "every detection has an id, else auto"))
    sigma: Mapping[str, float] = field(default_factory=dict, metadata=_help(
        "noise overrides NAME: VALUE (DEFAULT_MAPPING_SIGMAS)"))
    max_iterations: int = field(default=100, metadata=_help("LM iteration budget per stage"))
    tolerance: float = field(default=1e-6, metadata=_help(
        "LM stops at this relative decrease of the cost"))
    min_views: int = field(default=3, metadata=_help("views an object needs to be initialised"))
    keyframes: str | int = field(default="all", metadata=_help(
        "frames to use: all, motion (a keyframe per 5 cm or 5°) or K (every K-th)"))
    support_planes: PlaneSource = field(default=PlaneSource.PRIORS, metadata=_help(
        "support planes: priors (priors.yaml's only), initial (estimated from the initial "
        "objects) or optimised (from the objects optimised without planes)"))
    hold_trajectory: bool = field(default=False, metadata=_help(
        "hold the poses at their input values (objects only, no odometry)"))
    drift_interval: float = field(default=0.0, metadata=_help(
        "seconds between the knots of a drift correction of a trajectory without a bound on each "
        "pose (trajectory_absolute_sigma: .inf), fitted to the boxes before the joint "
        "optimisation (docs/map-reuse.md); 0: none"))
    initial_poses: InitialPoses = field(default=InitialPoses.AUTO, metadata=_help(
        "where the poses come from on a trajectory without a bound on each pose "
        "(trajectory_absolute_sigma: .inf): input (the joint optimisation starts from the input "
        "poses), incremental (the frames replayed through the online mapper first), loops (the "
        "drift taken out by loops closed between submaps, the poses then held at the corrected "
        "trajectory, refined by the boxes only where a cross-validation between halves of the labels "
        "accepts it; online, the loops as the frames come); auto: loops "
        "(docs/drift.md)"))
    screen: bool = field(default=True, metadata=_help(
        "leave out detections that cannot be a box of an object first"))
    class_table: bool = field(default=True, metadata=_help(
        "classes without a priors.yaml entry take the built-in size table"))
    online: OnlineSettings | None = field(default=None, metadata=_help(
        "replay frame by frame through the online mapper (OnlineSettings) instead of one "
        "batch optimisation"))

    def __post_init__(self):
        if not isinstance(self.method, Method):
            raise SettingsError("method", f"expected a Method, got {self.method!r} (RunSettings.of takes a name)")
        if self.associate is not None:
            object.__setattr__(self, "associate", _choice("associate", Associate, self.associate))
        object.__setattr__(self, "support_planes",
                           _choice("support_planes", PlaneSource, self.support_planes))
        if not isinstance(self.sigma, Mapping):
            raise SettingsError("sigma", f"expected a mapping NAME: VALUE, got {self.sigma!r}")
        sig = {}
        for name, value in self.sigma.items():
            try:
                sig[name] = check_sigma(name, value)
            except (TypeError, ValueError) as e:
                raise SettingsError("sigma", str(e)) from None
        object.__setattr__(self, "sigma", MappingProxyType(sig))
        object.__setattr__(self, "max_iterations", _integer("max_iterations", self.max_iterations, 1))
        object.__setattr__(self, "min_views", _integer("min_views", self.min_views, 1))
        tol = self.tolerance
        if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not (math.isfinite(tol) and tol >= 0):
            raise SettingsError("tolerance", f"expected a finite number ≥ 0, got {tol!r}")
        di = self.drift_interval
        if isinstance(di, bool) or not isinstance(di, (int, float)) or not (math.isfinite(di) and di >= 0):
            raise SettingsError("drift_interval", f"expected a finite number of seconds ≥ 0, got {di!r}")
        object.__setattr__(self, "drift_interval", float(di))
        object.__setattr__(self, "initial_poses",
                           _choice("initial_poses", InitialPoses, self.initial_poses))
        if self.initial_poses in (InitialPoses.LOOPS, InitialPoses.INCREMENTAL):
            moves = "loops move" if self.initial_poses == InitialPoses.LOOPS else "incremental moves"
            if self.hold_trajectory:
                raise SettingsError("initial_poses", f"{moves} the poses, which hold_trajectory holds: "
                                    "expected input or auto")
            if self.drift_interval > 0:
                raise SettingsError("initial_poses", "a drift correction starts from the input poses: "
                                    "expected input or auto with drift_interval")
        if self.initial_poses == InitialPoses.INCREMENTAL:
            if not maps_online(self.method):
                raise SettingsError("initial_poses", "incremental replays the frames through the online "
                                    "mapper, which takes SPD or RTS landmarks and one box model (inverse "
                                    f"or semi), not {self.method.parameterization} with {self.method.box_model}")
        try:
            object.__setattr__(self, "keyframes", parse_keyframes(self.keyframes))
        except ValueError as e:
            raise SettingsError("keyframes", str(e).removeprefix("keyframes ")) from None
        for name in ("hold_trajectory", "screen", "class_table"):
            _boolean(name, getattr(self, name))
        if self.online is not None:
            if not isinstance(self.online, OnlineSettings):
                raise SettingsError("online", f"expected OnlineSettings, got {self.online!r}")
            if self.keyframes != "all":
                raise SettingsError("keyframes", "an online run uses every frame: expected all, "
                                    f"got {self.keyframes!r}")
            if self.support_planes != PlaneSource.PRIORS:
                raise SettingsError("support_planes", "an online run takes support planes from the "
                                    f"priors only: expected priors, got {self.support_planes!r}")
            if self.method.parameterization not in ONLINE_PARAMETERIZATIONS:
                raise SettingsError("parameterization", "online mapping takes SPD or RTS landmarks: "
                                    f"expected spd or rts, got {self.method.parameterization!r}")
            if self.method.box_model not in ONLINE_BOX_MODELS:
                raise SettingsError("box_model", "online mapping takes one box model: expected "
                                    f"inverse or semi, got {self.method.box_model!r}")

    @classmethod
    def of(cls, method: str | Method = "multi-spd", **settings) -> RunSettings:
        """Settings from a method name (or ``Method``) and keywords: the fields of
        ``RunSettings``, ``Method`` fields as overrides (None: the method's), ``robust`` also
        as a list of the command line's KERNEL or TYPE=KERNEL[:K] items, and ``online`` also
        as True or a mapping of ``OnlineSettings``' fields."""
        if isinstance(method, str):
            if method not in METHODS:
                raise SettingsError("method", f"expected one of {', '.join(METHODS)}, got {method!r}")
            method = METHODS[method]
        elif not isinstance(method, Method):
            raise SettingsError("method", f"expected a name of METHODS or a Method, got {method!r}")
        own = {f.name for f in dataclasses.fields(cls)} - {"method"}
        unknown = set(settings) - own - set(METHOD_FIELDS)
        if unknown:
            raise TypeError(f"unknown settings {', '.join(sorted(unknown))}; expected fields of "
                            "RunSettings or Method")
        overrides = {k: v for k, v in settings.items() if k in METHOD_FIELDS and v is not None}
        for k, v in overrides.items():
            _check_type(k, v)
        robust = overrides.get("robust")
        if robust is not None:
            robust = [robust] if isinstance(robust, str) else robust
            overrides.pop("robust")
            try:
                parsed = parse_robust(list(robust), overrides.pop("robust_k", None))
            except ValueError as e:
                raise SettingsError("robust", str(e)) from None
            overrides.update(parsed)
        try:
            method = method.replace(**overrides)
        except (TypeError, ValueError) as e:
            bad = next((k for k in overrides if str(e).startswith(k)), "method")
            raise SettingsError(bad, str(e).removeprefix(f"{bad} ")) from None
        online = settings.get("online")
        if online is True:
            online = OnlineSettings()
        elif online is False:
            online = None
        elif isinstance(online, Mapping):
            unknown = set(online) - {f.name for f in dataclasses.fields(OnlineSettings)}
            if unknown:
                keys = ", ".join(f.name for f in dataclasses.fields(OnlineSettings))
                raise SettingsError("online", f"expected keys among {keys}, got {', '.join(sorted(unknown))}")
            online = OnlineSettings(**online)
        mine = {k: v for k, v in settings.items() if k in own and k != "online"}
        return cls(method=method, online=online, **mine)

    def start(self, unbounded: bool) -> InitialPoses:
        """Where a batch run's poses come from (``InitialPoses``) on a trajectory with
        (``unbounded`` False) or without a bound on each pose: auto is loops on an unbounded
        trajectory, not held, without a drift correction, else input."""
        if self.initial_poses != InitialPoses.AUTO:
            return self.initial_poses
        free = unbounded and not self.hold_trajectory and self.drift_interval == 0
        return InitialPoses.LOOPS if free else InitialPoses.INPUT

    def replace(self, **changes) -> RunSettings:
        """A copy with ``changes`` (checked again)."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        """Plain values (map.json's record of a run)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["method"] = dataclasses.asdict(self.method)
        out["sigma"] = dict(self.sigma)
        out["online"] = None if self.online is None else dataclasses.asdict(self.online)
        for k, v in out.items():
            if isinstance(v, enum.Enum):
                out[k] = v.value
        return out


#: The fields of ``RunSettings``, in order.
RUN_SETTING_NAMES = tuple(f.name for f in dataclasses.fields(RunSettings))


def setting_help(name: str) -> str:
    """The help text of a field of ``RunSettings`` or (``online.NAME``) ``OnlineSettings``
    (the CLI's help and the manifest's documentation)."""
    cls = OnlineSettings if name.startswith("online.") else RunSettings
    rest = name.removeprefix("online.")
    for f in dataclasses.fields(cls):
        if f.name == rest:
            return f.metadata["help"]
    raise KeyError(name)


@dataclass(frozen=True)
class SettingsReference:
    """What the settings are, for the tools that list, parse or document them (the CLI's
    options and help, a batch manifest's keys): ``run_names`` the fields of ``RunSettings``,
    ``method_fields`` those of ``Method`` (each a run's override), ``overrides`` {name: help}
    of the overrides ``spdslam run`` offers, ``sigmas`` {name: default} of the ``sigma``
    overrides, the robust kernels (``robust_choices`` with "auto", ``robust_kernels``,
    ``auto_box_kernel``: (kernel, threshold) that "auto" puts on the box factors);
    ``help(name)`` a setting's help text."""

    run_names: tuple
    method_fields: tuple
    overrides: Mapping
    sigmas: Mapping
    robust_choices: tuple
    robust_kernels: tuple
    auto_box_kernel: tuple

    @staticmethod
    def help(name: str) -> str:
        return setting_help(name)


#: The one reference to the settings (``SettingsReference``).
SETTINGS = SettingsReference(RUN_SETTING_NAMES, METHOD_FIELDS, MappingProxyType(RUN_OVERRIDES),
                             MappingProxyType(DEFAULT_MAPPING_SIGMAS), tuple(ROBUST_CHOICES),
                             tuple(ROBUST_KERNELS), tuple(AUTO_BOX_KERNEL))


def as_online_settings(method, settings: dict) -> RunSettings:
    """``as_settings`` for the online mapper: the fields of ``OnlineSettings`` may be given
    flat among ``settings`` (``window=10``), collected into its ``online`` (given twice, with
    a ``RunSettings`` or an ``online``: ``TypeError``)."""
    names = {f.name for f in dataclasses.fields(OnlineSettings)}
    given = {k: v for k, v in settings.items() if k in names}
    if given:
        if isinstance(method, RunSettings) or "online" in settings:
            raise TypeError(f"online settings given twice: {', '.join(given)} and a RunSettings or online")
        settings = {**{k: v for k, v in settings.items() if k not in names}, "online": given}
    return as_settings(method, settings)


def as_settings(method, settings: dict) -> RunSettings:
    """``method`` when it is a ``RunSettings`` (then ``settings`` must be empty), else
    ``RunSettings.of(method, **settings)``: the Python API's one way in."""
    if isinstance(method, RunSettings):
        if settings:
            raise TypeError(f"settings given twice: a RunSettings and {', '.join(sorted(settings))}")
        return method
    return RunSettings.of(method, **settings)
