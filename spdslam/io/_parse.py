"""Line-based and YAML parsing with ``file:line`` errors, shared by the readers and importers.

Every malformed input raises :class:`SequenceFormatError` (a ``ValueError``) whose message is
one line ``"<file>:<line>: <what was expected>, got <what>"`` (no ``:<line>`` for problems
with a whole file, such as a missing one).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..geometry import Camera

__all__ = ["SequenceFormatError", "MATCH_TOLERANCE", "CAMERA_KEYS", "read_tum", "read_images"]

#: A detection timestamp matches the nearest trajectory pose within this many seconds.
MATCH_TOLERANCE = 0.02
_MATCH_SLACK = 1e-9  # float noise on the tolerance


class SequenceFormatError(ValueError):
    """A malformed sequence file; the message is ``"<file>:<line>: expected, got what"``."""

    def __init__(self, file, line: int | None, expected: str, got: str):
        self.file = str(file)
        self.line = line
        self.expected = expected
        self.got = got
        where = self.file if line is None else f"{self.file}:{line}"
        msg = f"{where}: {expected}, got {got}"
        super().__init__(" ".join(msg.split()))  # always one line


# --- low-level parsing ----------------------------------------------------------------------


def _rows(path: Path, label: str | None = None):
    """(line number, tokens) of the non-empty lines of a text file, ``#`` comments removed."""
    name = label or str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise SequenceFormatError(name, None, "a UTF-8 text file", f"undecodable bytes ({e.reason})") from None
    for i, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if body:
            yield i, body.split()


def _show(tokens) -> str:
    s = " ".join(tokens)
    return repr(s if len(s) <= 80 else s[:77] + "...")


def _check_columns(file, line, tokens, counts, layout):
    if len(tokens) not in counts:
        want = " or ".join(str(c) for c in counts)
        raise SequenceFormatError(
            file, line, f"{want} columns '{layout}'", f"{len(tokens)} columns {_show(tokens)}"
        )


def _number(file, line, token: str, what: str) -> float:
    try:
        v = float(token)
    except ValueError:
        raise SequenceFormatError(file, line, f"a number for {what}", repr(token)) from None
    if not math.isfinite(v):
        raise SequenceFormatError(file, line, f"a finite number for {what}", repr(token))
    return v


def _integer(file, line, token: str, what: str) -> int:
    try:
        return int(token)
    except ValueError:
        raise SequenceFormatError(file, line, f"an integer for {what}", repr(token)) from None


def _unit_quaternion(file, line, q) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    n = float(np.linalg.norm(q))
    if not (n > 1e-6):
        raise SequenceFormatError(
            file, line, "a quaternion 'qx qy qz qw' that normalises to unit length",
            f"norm {n:.3g}",
        )
    return q / n


def read_tum(path: Path, name: str, skip_repeats: bool = False) -> np.ndarray:
    """(N, 8) rows ``timestamp tx ty tz qx qy qz qw``, quaternions normalised, strictly
    increasing timestamps (``skip_repeats``: a row whose timestamp does not exceed the
    previous one is left out instead, as motion-capture files repeat a timestamp now and
    then)."""
    layout = "timestamp tx ty tz qx qy qz qw"
    fields = layout.split()
    rows = []
    for line, tok in _rows(path, name):
        _check_columns(name, line, tok, (8,), layout)
        v = [_number(name, line, t, f) for t, f in zip(tok, fields)]
        v[4:8] = _unit_quaternion(name, line, v[4:8]).tolist()
        if rows and not v[0] > rows[-1][0]:
            if skip_repeats:
                continue
            raise SequenceFormatError(
                name, line, f"a timestamp greater than the previous one ({rows[-1][0]!r})",
                repr(tok[0]),
            )
        rows.append(v)
    if not rows:
        raise SequenceFormatError(name, None, f"at least one line '{layout}'", "an empty file")
    return np.array(rows, dtype=float)


def _match(file, line, t: float, timestamps: np.ndarray) -> int:
    i = int(np.argmin(np.abs(timestamps - t)))
    gap = abs(float(timestamps[i]) - t)
    if gap > MATCH_TOLERANCE + _MATCH_SLACK:
        raise SequenceFormatError(
            file, line, f"a timestamp within {MATCH_TOLERANCE} s of a trajectory pose",
            f"{t!r} (nearest pose {float(timestamps[i])!r} is {gap:.3g} s away)",
        )
    return i


def _box(file, line, tok, what="x1 y1 x2 y2") -> np.ndarray:
    b = [_number(file, line, t, f) for t, f in zip(tok, what.split())]
    if b[2] < b[0]:
        raise SequenceFormatError(file, line, "x2 >= x1", f"x1={tok[0]} x2={tok[2]}")
    if b[3] < b[1]:
        raise SequenceFormatError(file, line, "y2 >= y1", f"y1={tok[1]} y2={tok[3]}")
    return np.array(b)


# --- YAML with line numbers -----------------------------------------------------------------


def _yaml_root(path: Path, name: str):
    import yaml

    try:
        node = yaml.compose(path.read_text(encoding="utf-8"), Loader=yaml.SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise SequenceFormatError(name, line, "valid YAML", str(getattr(e, "problem", None) or e)) from None
    except UnicodeDecodeError as e:
        raise SequenceFormatError(name, None, "a UTF-8 text file", f"undecodable bytes ({e.reason})") from None
    if node is None:
        raise SequenceFormatError(name, None, "a YAML mapping", "an empty file")
    return node


def _line(node) -> int:
    return node.start_mark.line + 1


def _mapping(name, node, what: str) -> list:
    import yaml

    if not isinstance(node, yaml.MappingNode):
        raise SequenceFormatError(name, _line(node), f"a mapping for {what}", _kind(node))
    out = []
    seen = set()
    for k, v in node.value:
        key = _scalar(k)
        if not isinstance(key, str):
            raise SequenceFormatError(name, _line(k), f"a string key in {what}", repr(key))
        if key in seen:
            raise SequenceFormatError(name, _line(k), f"unique keys in {what}", f"{key!r} twice")
        seen.add(key)
        out.append((key, k, v))
    return out


def _kind(node) -> str:
    import yaml

    if isinstance(node, yaml.MappingNode):
        return "a mapping"
    if isinstance(node, yaml.SequenceNode):
        return "a list"
    return repr(_scalar(node))


def _scalar(node):
    import yaml

    if not isinstance(node, yaml.ScalarNode):
        return None
    return yaml.SafeLoader("").construct_object(node, deep=True)


def _ynumber(name, node, what: str) -> float:
    import yaml

    v = _scalar(node) if isinstance(node, yaml.ScalarNode) else None
    if isinstance(v, str):  # PyYAML reads '1e3' (no dot) as a string
        try:
            v = float(v)
        except ValueError:
            pass
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SequenceFormatError(name, _line(node), f"a number for {what}", _kind(node))
    if not math.isfinite(v):
        raise SequenceFormatError(name, _line(node), f"a finite number for {what}", repr(v))
    return float(v)


def _yvector(name, node, n: int, what: str) -> np.ndarray:
    import yaml

    if not isinstance(node, yaml.SequenceNode) or len(node.value) != n:
        got = f"a list of {len(node.value)}" if isinstance(node, yaml.SequenceNode) else _kind(node)
        raise SequenceFormatError(name, _line(node), f"a list of {n} numbers for {what}", got)
    return np.array([_ynumber(name, v, what) for v in node.value])


def _unknown_key(name, knode, key, allowed, where):
    raise SequenceFormatError(
        name, _line(knode), f"a key of {where} among {', '.join(allowed)}", repr(key)
    )


# --- shared by the readers and importers ---------------------------------------------------

CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")


def camera_from(name, values: dict, lines: dict) -> Camera:
    for k in CAMERA_KEYS:
        if not values[k] > 0:
            raise SequenceFormatError(name, lines.get(k), f"a positive {k}", repr(values[k]))
    return Camera(**{k: values[k] for k in CAMERA_KEYS})


def read_images(path, folder, name: str | None = None) -> dict:
    """``rgb.txt`` rows ``timestamp path``; relative paths are taken from ``folder``."""
    path = Path(path)
    name = name or str(path)
    out = {}
    for line, tok in _rows(path, name):
        _check_columns(name, line, tok, (2,), "timestamp path")
        t = _number(name, line, tok[0], "timestamp")
        p = Path(tok[1])
        out[t] = Path(os.path.abspath(p if p.is_absolute() else Path(folder) / p))
    return out


def required(folder: Path, fname: str) -> Path:
    p = folder / fname
    if not p.is_file():
        raise SequenceFormatError(p, None, f"a required file {fname}", "no such file")
    return p
