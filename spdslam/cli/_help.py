"""What the commands' help says of the registries and of a run's settings, read without
importing them.

The help of ``spdslam run`` and the others lists the methods, the sigmas, the robust kernels
and factor groups, the sequence formats, and the settings' defaults and help. They live in
``mapping``, ``factors`` and ``io``, which import JAX and SciPy (≈1 s), so :data:`FACTS`
holds a copy of them: ``spdslam --help`` and ``spdslam COMMAND --help`` import none of those
packages; a command imports what it uses when it runs. :func:`live_facts` reads the same
from the packages, and tests/test_cli.py checks that the two are equal; after a change there
(a method, a sigma, a factor group, a format, a setting's default or help), replace
``FACTS`` by what this prints::

    python3 -c "from spdslam.cli._help import facts_source, live_facts; print(facts_source(live_facts()))"

A setting the help names and ``FACTS["settings"]`` lacks is read from the packages (the
help then imports them) until ``FACTS`` is renewed. The sequence formats that installed
packages add (entry points) are read from the registry, as before: only then does the help
import ``spdslam.io``.
"""

from __future__ import annotations

import enum
import json
from typing import Any

__all__ = ["FACTS", "facts_source", "formats_help", "live_facts", "setting"]

FACTS: dict[str, Any] = {
    "methods": ("quadric-slam", "multi-rts", "multi-rts-nearest", "multi-spd"),
    "sigmas": (
        "absolute_rotation", "absolute_translation", "axis_orientation", "classic_orientation", "classic_shape",
        "ellipsoid_center", "ellipsoid_shape", "first_pose", "inverse_box", "inverse_box_relative",
        "inverse_cuboid_box", "inverse_cuboid_box_relative", "odometry_rotation", "odometry_translation", "orientation",
        "radius_floor", "semi_inverse_box", "semi_inverse_cuboid_box", "shape", "size", "support_plane",
    ),
    "robust_choices": ("auto", "none", "huber", "cauchy"),
    "robust_kernels": ("none", "huber", "cauchy"),
    "auto_box_kernel": ("cauchy", 6.0),
    "robust_groups": (
        "box", "ellipsoid", "landmark_prior", "orientation", "shape", "size", "radius_floor", "support_plane", "prior",
        "odometry",
    ),
    "overrides": {
        "parameterization": "override the landmark's parameterisation: spd, rts, full",
        "box_model": "override the box model: inverse, semi, semi-then-inverse",
        "object_shape": "silhouette model: priors, ellipsoid, cuboid (priors: per class, priors.yaml 'shape')",
        "truncation_margin": (
            "box edges within this many px of the image border carry no bound (negative: keep all; default 5)"
        ),
        "robust": "robust kernels: KERNEL or TYPE=KERNEL[:K], a list",
        "robust_k": "threshold of a plain KERNEL (whitened units, default 1)",
    },
    "settings": {
        "associate": (
            None,
            "data association: instances (the instance ids) or auto; default: instances when every detection has an "
            "id, else auto",
        ),
        "max_iterations": (100, "LM iteration budget per stage"),
        "keyframes": ("all", "frames to use: all, motion (a keyframe per 5 cm or 5°) or K (every K-th)"),
        "support_planes": (
            "priors",
            "support planes: priors (priors.yaml's only), initial (estimated from the initial objects) or optimised "
            "(from the objects optimised without planes)",
        ),
        "tolerance": (1e-06, "LM stops at this relative decrease of the cost"),
        "min_views": (3, "views an object needs to be initialised"),
        "hold_trajectory": (False, "hold the poses at their input values (objects only, no odometry)"),
        "screen": (True, "leave out detections that cannot be a box of an object first"),
        "class_table": (True, "classes without a priors.yaml entry take the built-in size table"),
        "online.window": (30, "frames whose poses the fixed-lag problem keeps free"),
        "online.every": (10, "frames between optimisations"),
        "online.iterations": (5, "LM iterations per optimisation"),
        "online.warmup": (
            False,
            "compile before the first frame (a synthetic room replayed with the camera; OnlineMapper.warmup), as a "
            "live mapper would",
        ),
        "online.final_batch": (
            True,
            "after the last frame, one batch optimisation of every frame and view from the online state "
            "(max_iterations); without it the map is the online estimates",
        ),
        "online.background": (
            False,
            "optimise in a worker thread: a frame's own work returns at once and each optimisation publishes its map "
            "when it ends (the same maps; latency.csv's lag says when)",
        ),
        "online.realtime": (
            False,
            "replay a recording at its own rate: each frame is added when its time since the first frame has passed, "
            "as a camera delivers it",
        ),
        "drift_interval": (
            0.0,
            "seconds between the knots of a drift correction of a trajectory without a bound on each pose "
            "(trajectory_absolute_sigma: .inf), fitted to the boxes before the joint optimisation (docs/map-reuse.md); "
            "0: none",
        ),
        "initial_poses": (
            "auto",
            "where the poses come from on a trajectory without a bound on each pose (trajectory_absolute_sigma: .inf): "
            "input (the joint optimisation starts from the input poses), incremental (the frames replayed through the "
            "online mapper first), loops (the drift taken out by loops closed between submaps, the poses then held at "
            "the corrected trajectory, refined by the boxes only where a cross-validation between halves of the labels "
            "accepts it; online, the loops as the frames come); auto: loops "
            "(docs/drift.md)",
        ),
    },
    "format_entry_points": "spdslam.formats",
    "formats": (
        "a canonical sequence folder (camera.yaml, trajectory.txt, detections.txt)",
        "an OA-SLAM-style folder (a detections*.json, beside a camera YAML and TUM trajectories)",
        "a detector's output folder (labels/*.txt (YOLO) or coco_results.json, beside camera.yaml and trajectory.txt)",
        "a TUM fr3_cabinet-style folder (bbox/ and truth_objects.txt)",
        "a ROS 2 bag (a folder with metadata.yaml, or a .mcap or .db3 file)",
    ),
}


def setting(name: str) -> tuple[Any, str]:
    """(command-line default, help) of a field of ``RunSettings`` or (``online.NAME``)
    ``OnlineSettings``, or the help of a ``mapping.SETTINGS.overrides`` entry (default ``None``)."""
    if name in FACTS["overrides"]:
        return None, FACTS["overrides"][name]
    if name not in FACTS["settings"]:  # a new setting: read from the packages (slow) until
        _MISSING.append(name)  # FACTS is renewed (tests/test_cli.py says so)
        return _live_setting(name)
    return FACTS["settings"][name]


#: Settings the help named that ``FACTS`` lacks (``setting``).
_MISSING: list[str] = []


def _live_setting(name: str) -> tuple[Any, str]:
    from ..mapping import SETTINGS, OnlineSettings, RunSettings

    cls = OnlineSettings if name.startswith("online.") else RunSettings
    return _cli_default(cls.__dataclass_fields__[name.removeprefix("online.")].default), SETTINGS.help(name)


def formats_help() -> str:
    """The registered sequence formats, as the help of a SEQUENCE argument lists them: the
    built-in ones from :data:`FACTS`, unless an installed package adds formats (then from
    the registry, which imports ``spdslam.io``)."""
    from importlib.metadata import entry_points

    if not entry_points(group=FACTS["format_entry_points"]):
        return "; ".join(FACTS["formats"])
    from ..io import FORMATS, formats

    try:
        known = formats()
    except ImportError:  # a broken entry point: reported when a command looks a path up
        known = list(FORMATS.values())
    return "; ".join(f.describe() for f in known)


def _cli_default(value):
    return value.value if isinstance(value, enum.Enum) else value


def live_facts() -> dict[str, Any]:
    """What :data:`FACTS` holds, read from the packages (imports JAX): the settings named
    by ``FACTS["settings"]``, the built-in formats (those defined in spdslam)."""
    from ..factors import robust_groups
    from ..io import ENTRY_POINT_GROUP, FORMATS
    from ..mapping import METHODS, SETTINGS

    return {
        "methods": tuple(METHODS),
        "sigmas": tuple(sorted(SETTINGS.sigmas)),
        "robust_choices": tuple(SETTINGS.robust_choices),
        "robust_kernels": tuple(SETTINGS.robust_kernels),
        "auto_box_kernel": tuple(SETTINGS.auto_box_kernel),
        "robust_groups": tuple(robust_groups()),
        "overrides": dict(SETTINGS.overrides),
        "settings": {name: _live_setting(name) for name in [*FACTS["settings"], *_MISSING]},
        "format_entry_points": ENTRY_POINT_GROUP,
        "formats": tuple(f.describe() for f in FORMATS.values() if f.__module__.startswith("spdslam.")),
    }


def facts_source(facts: dict[str, Any]) -> str:
    """``facts`` as the source of :data:`FACTS` (lines of at most 120 characters)."""
    return "FACTS: dict[str, Any] = " + _literal(facts, 0, _WIDTH) + "\n"


_WIDTH = 120


def _literal(value, indent: int, room: int) -> str:
    """Python source of a value of ``FACTS`` (strings, numbers, None, tuples, dicts) for a
    line indented by ``indent`` spaces on which ``room`` columns are left."""
    pad, inner = " " * indent, " " * (indent + 4)
    if isinstance(value, dict):
        items = []
        for k, v in value.items():
            key = f"{inner}{_literal(k, indent + 4, _WIDTH)}: "
            text = _literal(v, indent + 4, _WIDTH - len(key) - 1)
            if isinstance(v, str) and len(key) + len(text) >= _WIDTH:  # a long string: in parentheses
                text = "(\n" + " " * (indent + 8) + _strings(v, indent + 8) + f"\n{inner})"
            items.append(f"{key}{text},")
        return "{\n" + "\n".join(items) + f"\n{pad}}}"
    if isinstance(value, tuple):
        parts = [_literal(v, indent + 4, _WIDTH - len(inner) - 1) for v in value]
        flat = "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"
        if len(flat) <= room and "\n" not in flat:
            return flat
        lines, line = [], ""
        for p in parts:
            if line and ("\n" in p or len(inner) + len(line) + len(p) + 1 > _WIDTH):
                lines.append(inner + line.rstrip())
                line = ""
            if "\n" in p:
                lines.append(f"{inner}{p},")
            else:
                line += p + ", "
        if line:
            lines.append(inner + line.rstrip())
        return "(\n" + "\n".join(lines) + f"\n{pad})"
    if isinstance(value, str):
        text = json.dumps(value, ensure_ascii=False)
        return text if len(text) <= room else _strings(value, indent)
    return repr(value)


def _strings(value: str, indent: int) -> str:
    """A long string as adjacent literals, one a line (broken after spaces), the lines after
    the first indented by ``indent``."""
    chunks, chunk = [], ""
    for word in value.split(" "):
        if chunk and indent + len(json.dumps(chunk + word, ensure_ascii=False)) >= _WIDTH:
            chunks.append(chunk)
            chunk = ""
        chunk += word + " "
    chunks.append(chunk[:-1])
    return f"\n{' ' * indent}".join(json.dumps(c, ensure_ascii=False) for c in chunks)
