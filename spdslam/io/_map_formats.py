"""Map formats: the saved maps spdslam reads, each declared once, as a class, and found by a
registry (as the sequence formats are, ``_formats``).

A map format says how a path of its layout is recognised (``claims``) and how it is read
into a :class:`SavedMap`: the objects (``MapObject``), the camera trajectory the map was
made with when it keeps one (TUM rows of T_wc: keyframes for a SLAM system's map), and a
document in map.json's shape (for the report). Defining a subclass with a ``name``
registers it::

    class MyMap(MapFormat):
        name = "mine"
        title = "my system's saved map"
        layout = "a objects.csv"

        @classmethod
        def claims(cls, path):
            return path.name == "objects.csv"

        @classmethod
        def read(cls, path):
            ...  # a SavedMap

``load_map`` finds a path's format: the one that claims it; ``spdslam evaluate``,
``localize --map``, ``merge``, ``view`` and ``export`` take any registered map
(docs/map-reuse.md, "From another system's map"). Every malformed file gives a one-line
``MapFormatError`` naming the file.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from ._formats import register_format
from ._map import MapFormatError, read_map
from ._parse import SequenceFormatError, read_tum

__all__ = ["MapFormat", "MAP_FORMATS", "SavedMap", "SpdslamMap", "find_map_format", "load_map",
           "map_formats", "peer_document", "PEER_MODE"]

#: name → map format class, in the order of definition (spdslam's own first).
MAP_FORMATS: dict[str, type["MapFormat"]] = {}

#: map.json's ``association.mode`` of a map another system made: its object ids are that
#: system's, not the sequence's instance ids (``evaluation.evaluate_run`` matches by overlap).
PEER_MODE = "peer"


@dataclass(frozen=True)
class SavedMap:
    """A map read from disk: ``document`` (map.json's keys, or for another system's map the
    few that ``peer_document`` gives), ``objects`` (``MapObject``), ``trajectory`` (TUM rows
    (N, 8) t x y z qx qy qz qw of T_wc, sorted by time, or None), the ``format``'s name and
    the ``path`` read."""

    document: dict
    objects: list
    trajectory: np.ndarray | None
    format: str
    path: Path
    notes: list = field(default_factory=list)

    @property
    def is_spdslam(self) -> bool:
        """Whether spdslam made it (a run folder: its recording, settings and report)."""
        return self.format == SpdslamMap.name


class MapFormat:
    """One saved-map layout. Subclasses set the class attributes and define ``claims`` and
    ``read``; a subclass with a ``name`` is registered.

    name:   the registry key (``"spdslam"``, ``"osmap"``);
    title:  what a path of the layout is, for messages ("an Osmap map (ORB-SLAM2 systems)");
    layout: what recognises it, for messages and docs ("a .yaml naming objectsFile");
    docs:   where docs/formats.md describes it.
    """

    name: ClassVar[str] = ""
    title: ClassVar[str] = ""
    layout: ClassVar[str] = ""
    docs: ClassVar[str] = ""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        register_format(MAP_FORMATS, cls, "map format")

    @classmethod
    def claims(cls, path: Path) -> bool:
        """Whether ``path`` (a folder or file that exists) has this layout; never raises."""
        raise NotImplementedError

    @classmethod
    def read(cls, path: Path) -> SavedMap:
        """The map at ``path``; a malformed one raises ``MapFormatError`` (one line)."""
        raise NotImplementedError

    @classmethod
    def describe(cls) -> str:
        return f"{cls.title} ({cls.layout})"


def map_formats() -> list[type[MapFormat]]:
    """The registered map formats, in the order of definition."""
    return list(MAP_FORMATS.values())


def _check_path(path: Path) -> None:
    try:
        os.stat(path)
    except OSError as e:
        why = "a symbolic-link loop" if e.errno == errno.ELOOP else "no such file or folder"
        raise MapFormatError(f"{path}: expected a saved map (a run folder with map.json, or another system's "
                             f"map file), got {why}") from None


def find_map_format(path, name: str | None = None) -> type[MapFormat]:
    """The format of ``path``: the one registered format that claims it (or the format
    ``name``, which must claim it). One-line ``MapFormatError`` when none or several do."""
    path = Path(path)
    _check_path(path)

    def claims(f):
        try:
            return bool(f.claims(path))
        except OSError:
            return False

    if name is not None:
        fmt = MAP_FORMATS.get(name)
        if fmt is None:
            raise ValueError(f"unknown map format {name!r}: expected one of {', '.join(MAP_FORMATS)}")
        if not claims(fmt):
            raise MapFormatError(f"{path}: expected {fmt.describe()}, got a path it does not claim")
        return fmt
    found = [f for f in map_formats() if claims(f)]
    if len(found) == 1:
        return found[0]
    if not found:
        raise MapFormatError(f"{path}: expected a saved map: "
                             + "; ".join(f"{f.name}, {f.describe()}" for f in map_formats())
                             + ", got none of their layouts")
    raise MapFormatError(f"{path}: expected a path of one map format, got one that "
                         + " and ".join(f"{f.name} ({f.layout})" for f in found) + " all claim")


def load_map(path, format: str | None = None) -> SavedMap:
    """The saved map at ``path`` in its format (``find_map_format``)."""
    return find_map_format(path, format).read(Path(path))


def peer_document(fmt: str, path: Path, objects, keyframes: int, notes=()) -> dict:
    """map.json's keys for a map another system made: what it is, where it was read, its
    objects, and ``association.mode`` ``PEER_MODE`` (its ids are not instance ids)."""
    return {
        "method": f"{fmt} map",
        "format": fmt,
        "source": str(path),
        "keyframes": int(keyframes),
        "objects": [o.as_dict() for o in objects],
        "notes": list(notes),
        "association": {"mode": PEER_MODE},
    }


class SpdslamMap(MapFormat):
    """A run folder of ``spdslam run`` (its map.json, and trajectory.txt when there), or
    the map.json itself."""

    name = "spdslam"
    title = "a map written by spdslam run"
    layout = "a folder with map.json, or a map.json"
    docs = "map.json"

    @classmethod
    def claims(cls, path: Path) -> bool:
        if path.is_dir():
            return (path / "map.json").is_file()
        return path.suffix == ".json"

    @classmethod
    def read(cls, path: Path) -> SavedMap:
        doc, objects = read_map(path)
        folder = path if path.is_dir() else path.parent
        traj_path = folder / "trajectory.txt"
        trajectory = None
        if traj_path.is_file():
            try:
                trajectory = read_tum(traj_path, str(traj_path))
            except SequenceFormatError as e:
                raise MapFormatError(str(e)) from None
        file = path / "map.json" if path.is_dir() else path
        return SavedMap(doc, objects, trajectory, cls.name, file)

