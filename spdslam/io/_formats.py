"""Sequence formats: each input layout declared once, as a class, and found by a registry.

A format says how a path of its layout is recognised (``claims``), how it is read into a
:class:`Sequence` (``read``, with the keyword ``options`` it takes) and whether a sequence
can be written in it (``writes``, ``write``). Defining a subclass with a ``name`` registers
it, as defining a factor type registers the factor::

    class MyFormat(SequenceFormat):
        name = "mine"
        title = "a folder of my recorder"
        layout = "a recording.json"

        @classmethod
        def claims(cls, path):
            return (path / "recording.json").is_file()

        @classmethod
        def read(cls, path, **options):
            ...  # a Sequence

``read_sequence``, ``spdslam run`` and ``spdslam import`` (which format a path is, and
which options it takes), the CLI's help and docs/formats.md's table all go through the
registry (docs/extending.md, "A new input format"). A path is read by the one format that
claims it: a path that two formats claim, or none, is refused with one line naming the
candidates, as is a path that is not there or is a symbolic-link loop. Installed packages
add formats through the entry-point group ``spdslam.formats`` (each entry a module that
defines them), loaded on the first lookup.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Any, ClassVar

from ._parse import SequenceFormatError
from ._sequence import Sequence

__all__ = [
    "SequenceFormat",
    "register_format",
    "FORMATS",
    "formats",
    "check_sequence_path",
    "find_format",
    "read_sequence",
    "read_measured_boxes",
    "formats_table",
    "ENTRY_POINT_GROUP",
]

#: name → format class, in the order of definition (the built-in ones first).
FORMATS: dict[str, type["SequenceFormat"]] = {}
#: The entry-point group through which installed packages add formats.
ENTRY_POINT_GROUP = "spdslam.formats"
_ENTRY_POINTS_LOADED = False


class SequenceFormat:
    """One input layout. Subclasses set the class attributes and define ``claims`` and
    ``read`` (and ``write`` when ``writes``); a subclass with a ``name`` is registered.

    name:    the registry key, short (``"canonical"``, ``"oaslam"``); ``--format`` values;
    title:   what a path of the layout is, for messages ("an OA-SLAM-style folder");
    layout:  what recognises it, for messages and docs ("one detections*.json");
    docs:    where docs/formats.md describes it (a section title);
    options: the keyword options ``read`` takes beyond the path, name → one line of help;
    hints:   for options of other formats that this one refuses, what to use instead
             (name → a short sentence, added to the refusal);
    writes:  whether ``write`` can write a sequence in this format.
    """

    name: ClassVar[str] = ""
    title: ClassVar[str] = ""
    layout: ClassVar[str] = ""
    docs: ClassVar[str] = ""
    options: ClassVar[dict[str, str]] = {}
    hints: ClassVar[dict[str, str]] = {}
    writes: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        register_format(FORMATS, cls, "sequence format")

    @classmethod
    def claims(cls, path: Path) -> bool:
        """Whether ``path`` (a folder or file that exists) has this layout. Never raises:
        a claim is a look at names, the reader checks the contents."""
        raise NotImplementedError

    @classmethod
    def read(cls, path: Path, **options) -> Sequence:
        """The sequence at ``path``; a malformed input raises ``SequenceFormatError``."""
        raise NotImplementedError

    @classmethod
    def write(cls, seq: Sequence, dest: Path, overwrite: bool = False) -> None:
        """Write ``seq`` at ``dest`` in this format (only when ``writes``)."""
        raise NotImplementedError(f"sequences cannot be written as {cls.name}")

    @classmethod
    def read_measured(cls, path: Path):
        """(the sequence with its boxes as measured, the lens distortion (k1, k2, p1, p2,
        k3)) for a format whose reader undistorts its boxes, else None (``spdslam check``
        compares the two)."""
        return None

    @classmethod
    def describe(cls) -> str:
        """"<title> (<layout>)", as messages name the format."""
        return f"{cls.title} ({cls.layout})"


def register_format(registry: dict, cls, kind: str) -> None:
    """Register a format class under its ``name`` (an intermediate base without one is
    not); its ``title`` and ``layout`` must be set, and a name is another class's only
    once (re-defining a class of the same name replaces it). The sequence formats' and the
    map formats' (``MapFormat``) rule."""
    if not cls.name:
        return
    for attr in ("title", "layout"):
        if not getattr(cls, attr):
            raise TypeError(f"{kind} {cls.__qualname__}: {attr} must be set")
    old = registry.get(cls.name)
    if old is not None and old.__qualname__ != cls.__qualname__:
        raise ValueError(f"a {kind} named {cls.name!r} is already registered ({old.__module__}.{old.__qualname__})")
    registry[cls.name] = cls


def _load_entry_points() -> None:
    """Import the modules of the ``spdslam.formats`` entry points once (they register
    their formats by defining them); one that fails to import is reported by name."""
    global _ENTRY_POINTS_LOADED
    if _ENTRY_POINTS_LOADED:
        return
    _ENTRY_POINTS_LOADED = True
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            ep.load()
        except Exception as e:  # noqa: BLE001 - a third-party module: say which one
            raise ImportError(f"the sequence-format entry point {ep.name!r} ({ep.value}) "
                              f"failed to load: {type(e).__name__}: {e}") from e


def formats() -> list[type[SequenceFormat]]:
    """The registered formats, in the order of definition."""
    _load_entry_points()
    return list(FORMATS.values())


def check_sequence_path(path) -> Path:
    """``path`` as a Path, when something that can be read is there; else one-line
    ``SequenceFormatError``: nothing there, a symbolic-link loop, or neither a folder nor a
    regular file."""
    import stat

    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except OSError as e:
        if e.errno == errno.ELOOP:
            why = "a symbolic-link loop"
        elif e.errno in (errno.ENOENT, errno.ENOTDIR):
            why = "a broken symbolic link" if os.path.islink(path) else "no such file or folder"
        else:
            why = e.strerror or type(e).__name__
        raise SequenceFormatError(path, None, "a sequence folder or file", why) from None
    if not (stat.S_ISDIR(mode) or stat.S_ISREG(mode)):
        raise SequenceFormatError(path, None, "a sequence folder or file",
                                  "neither a folder nor a regular file")
    return path


def _claims(fmt: type[SequenceFormat], path: Path) -> bool:
    try:
        return bool(fmt.claims(path))
    except OSError:  # e.g. a folder that cannot be listed: not this format's to say
        return False


def find_format(path, name: str | None = None) -> type[SequenceFormat]:
    """The format of ``path``: the one registered format that claims it (or the format
    ``name``, which must claim it too). Raises ``SequenceFormatError`` (one line) when no
    format, or more than one, claims it, naming the candidates."""
    path = check_sequence_path(path)
    known = formats()
    if name is not None:
        fmt = FORMATS.get(name)
        if fmt is None:
            raise ValueError(f"unknown sequence format {name!r}: expected one of "
                             f"{', '.join(f.name for f in known)}")
        if not _claims(fmt, path):
            raise SequenceFormatError(path, None, fmt.describe(), "a path it does not claim")
        return fmt
    claim = [f for f in known if _claims(f, path)]
    if len(claim) == 1:
        return claim[0]
    if not claim:
        raise SequenceFormatError(
            path, None, "one of the sequence formats: "
            + "; ".join(f"{f.name}, {f.describe()}" for f in known),
            "none of their layouts")
    raise SequenceFormatError(
        path, None, "a path of one sequence format",
        "one that " + " and ".join(f"{f.name} ({f.layout})" for f in claim) + " all claim")


def read_sequence(path, format: str | None = None, **options: Any) -> Sequence:
    """Read the sequence at ``path`` in its format (``find_format``; ``format``: a
    registered name, to insist on one). ``options``: keyword options of that format's
    reader (``SequenceFormat.options``); one it does not take is a ``ValueError``."""
    fmt = find_format(path, format)
    unknown = sorted(set(options) - set(fmt.options))
    if unknown:
        takes = ", ".join(fmt.options) or "none"
        raise ValueError(f"{path}: the {fmt.name} format takes no option "
                         f"{', '.join(map(repr, unknown))} (its options: {takes})")
    return fmt.read(Path(path), **options)


def read_measured_boxes(path):
    """(the sequence with its boxes as measured, the lens distortion (k1, k2, p1, p2, k3))
    of a path whose format undistorts its boxes (the OA-SLAM layout), else None: what
    ``spdslam check`` compares the undistorted boxes with."""
    return find_format(path).read_measured(Path(path))


def formats_table() -> str:
    """The registered formats as the markdown table of docs/formats.md."""
    rows = ["| format | what it is | recognised by | `spdslam import` options | written by spdslam | described in |",
            "| --- | --- | --- | --- | --- | --- |"]
    for f in formats():
        opts = ", ".join(f"`--{o.replace('_', '-')}`" for o in f.options) or "none"
        rows.append(f"| `{f.name}` | {f.title} | {f.layout} | {opts} | "
                    f"{'yes' if f.writes else 'no'} | {f.docs or '—'} |")
    return "\n".join(rows) + "\n"
