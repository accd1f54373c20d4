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

__all__ = ["SequenceFormatError", "MATCH_TOLERANCE", "CAMERA_KEYS", "read_tum", "read_images", "read_text",
           "nearest_stamps", "token_rows", "check_columns", "parse_number", "number_rows", "parse_integer",
           "unit_quaternion", "match_stamp", "match_stamps", "parse_box", "box_faults", "check_box", "yaml_root",
           "yaml_line",
           "yaml_mapping", "yaml_kind", "yaml_scalar", "yaml_number", "yaml_vector",
           "reject_unknown_key"]

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

#: The byte-order mark some editors write at the start of a UTF-8 file.
BOM = "\ufeff"


def _not_a_file(path: Path) -> str | None:
    """Why ``path`` is not a regular file that can be read ("no such file", "a directory",
    "a FIFO", "a symbolic-link loop", …), or None when it is one."""
    import errno
    import stat

    try:
        mode = os.stat(path).st_mode
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "a symbolic-link loop"
        if e.errno in (errno.ENOENT, errno.ENOTDIR):
            return "a broken symbolic link" if os.path.islink(path) else "no such file"
        return e.strerror or type(e).__name__
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if not os.access(path, os.R_OK):
        return "a file without read permission"
    return None


def present(path) -> bool:
    """Whether anything is at ``path`` (a file, a directory, a FIFO, a link, even a broken
    one): an optional file that is present must then be a readable regular file."""
    return os.path.lexists(path)


def read_text(path: Path, name: str | None = None) -> str:
    """The text of a UTF-8 file. One rule for every text and YAML file: a leading byte-order
    mark is dropped, CRLF and CR line ends read as LF; anything but a readable regular file
    is a ``SequenceFormatError`` that says what is there instead."""
    name = name or str(path)
    why = _not_a_file(Path(path))
    if why:
        raise SequenceFormatError(name, None, "a readable file", why)
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise SequenceFormatError(name, None, "a UTF-8 text file", f"undecodable bytes ({e.reason})") from None
    except OSError as e:
        raise SequenceFormatError(name, None, "a readable file", e.strerror or type(e).__name__) from None
    if text.startswith(BOM):
        text = text[1:]
    return text.replace("\r\n", "\n").replace("\r", "\n")


def token_rows(path: Path, label: str | None = None):
    """(line number, tokens) of the non-empty lines of a text file, ``#`` comments removed."""
    name = label or str(path)
    text = read_text(path, name)
    for i, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if body:
            yield i, body.split()


def _show(tokens) -> str:
    s = " ".join(tokens)
    return repr(s if len(s) <= 80 else s[:77] + "...")


def check_columns(file, line, tokens, counts, layout):
    """A row of ``len(tokens)`` columns, one of ``counts``; else ``SequenceFormatError``
    naming the ``layout`` (``"timestamp tx ty …"``)."""
    if len(tokens) not in counts:
        want = " or ".join(str(c) for c in counts)
        raise SequenceFormatError(
            file, line, f"{want} columns '{layout}'", f"{len(tokens)} columns {_show(tokens)}"
        )


def parse_number(file, line, token: str, what: str) -> float:
    """The finite float of ``token`` (``what`` names it in the error); ``1_000``, nan and
    inf are errors."""
    try:
        if "_" in token:  # Python's float() reads 1_000; no text format here does
            raise ValueError(token)
        v = float(token)
    except ValueError:
        raise SequenceFormatError(file, line, f"a number for {what}", repr(token)) from None
    if not math.isfinite(v):
        raise SequenceFormatError(file, line, f"a finite number for {what}", repr(token))
    return v


def parse_integer(file, line, token: str, what: str) -> int:
    """The int of ``token`` (``what`` names it in the error)."""
    try:
        return int(token)
    except ValueError:
        raise SequenceFormatError(file, line, f"an integer for {what}", repr(token)) from None


def unit_quaternion(file, line, q) -> np.ndarray:
    """``q`` (qx qy qz qw) normalised to unit length; a norm ≤ 1e-6 is an error."""
    q = np.asarray(q, dtype=float)
    m = float(np.max(np.abs(q)))
    if m > 0:
        q = q / m  # scaled first: the norm of huge entries does not overflow
    n = m * float(np.linalg.norm(q))
    if not (n > 1e-6):
        raise SequenceFormatError(
            file, line, "a quaternion 'qx qy qz qw' that normalises to unit length",
            f"norm {n:.3g}",
        )
    return q / np.linalg.norm(q)


def number_rows(numbered, columns: int) -> np.ndarray | None:
    """The (n, ``columns``) floats of ``numbered`` [(line, tokens)] converted at once, or None
    when a token is not a finite number as ``parse_number`` reads it (the caller then reads
    the rows one by one, for the error of the first line that fails)."""
    flat = [t for _, tok in numbered for t in tok]
    if any("_" in t for t in flat):  # float() reads 1_000; no text format here does
        return None
    try:
        v = np.array(flat, dtype=float).reshape(len(numbered), columns)
    except ValueError:
        return None
    return v if bool(np.isfinite(v).all()) else None


def read_tum(path: Path, name: str, skip_repeats: bool = False) -> np.ndarray:
    """(N, 8) rows ``timestamp tx ty tz qx qy qz qw``, quaternions normalised, strictly
    increasing timestamps (``skip_repeats``: a row whose timestamp does not exceed the
    previous one is left out instead, as motion-capture files repeat a timestamp now and
    then). The rows are converted and checked as arrays; when any fails they are read
    again line by line (``_tum_lines``), whose error names the first line that fails."""
    layout = "timestamp tx ty tz qx qy qz qw"
    numbered = list(token_rows(path, name))
    for line, tok in numbered:
        check_columns(name, line, tok, (8,), layout)
    if not numbered:
        raise SequenceFormatError(name, None, f"at least one line '{layout}'", "an empty file")
    v = number_rows(numbered, 8)
    if v is not None:
        q = v[:, 4:8]
        m = np.max(np.abs(q), axis=1)
        qs = q / np.where(m > 0, m, 1.0)[:, None]  # scaled first: huge entries do not overflow
        norm = np.linalg.norm(qs, axis=1)
        t = v[:, 0]
        # a row is kept when it follows every kept row: its time exceeds all earlier times
        later = t > np.r_[-np.inf, np.maximum.accumulate(t)[:-1]]
        if np.all(m * norm > 1e-6) and (skip_repeats or later.all()):
            v[:, 4:8] = qs / norm[:, None]
            return v[later]
    return _tum_lines(numbered, name, layout, skip_repeats)


def _tum_lines(numbered, name: str, layout: str, skip_repeats: bool) -> np.ndarray:
    """``read_tum``'s rows read one line at a time (its rules, in the order of the lines)."""
    fields = layout.split()
    rows: list[list[float]] = []
    for line, tok in numbered:
        v = [parse_number(name, line, t, f) for t, f in zip(tok, fields)]
        v[4:8] = unit_quaternion(name, line, v[4:8]).tolist()
        if rows and not v[0] > rows[-1][0]:
            if skip_repeats:
                continue
            raise SequenceFormatError(
                name, line, f"a timestamp greater than the previous one ({rows[-1][0]!r})",
                repr(tok[0]),
            )
        rows.append(v)
    return np.array(rows, dtype=float)


def nearest_stamps(sorted_t: np.ndarray, t: np.ndarray):
    """(index of the nearest of ``sorted_t`` (increasing) for each of ``t``, whether it is
    within ``MATCH_TOLERANCE``, 0.02 s)."""
    if len(sorted_t) == 1:
        i = np.zeros(len(t), int)
    else:
        j = np.clip(np.searchsorted(sorted_t, t), 1, len(sorted_t) - 1)
        i = np.where(np.abs(sorted_t[j - 1] - t) < np.abs(sorted_t[j] - t), j - 1, j)
    return i, np.abs(sorted_t[i] - t) <= MATCH_TOLERANCE


def match_stamp(file, line, t: float, timestamps: np.ndarray) -> int:
    """The index of the trajectory pose nearest ``t`` among ``timestamps``, which must lie
    within ``MATCH_TOLERANCE``; else ``SequenceFormatError`` at the row's line."""
    i = int(np.argmin(np.abs(timestamps - t)))
    gap = abs(float(timestamps[i]) - t)
    if gap > MATCH_TOLERANCE + _MATCH_SLACK:
        raise SequenceFormatError(
            file, line, f"a timestamp within {MATCH_TOLERANCE} s of a trajectory pose",
            f"{t!r} (nearest pose {float(timestamps[i])!r} is {gap:.3g} s away)",
        )
    return i


def match_stamps(t, timestamps: np.ndarray) -> np.ndarray | None:
    """``match_stamp`` for many times at once: the index of the nearest trajectory pose of
    each (the earlier of two as near; ``timestamps`` increasing), or None when one is not
    within ``MATCH_TOLERANCE`` or the timestamps do not increase (the caller then matches
    row by row, for the error of the first line that fails)."""
    t = np.asarray(t, dtype=float)
    ts = np.asarray(timestamps, dtype=float)
    if len(ts) < 2 or not np.all(np.diff(ts) > 0):
        return None
    j = np.clip(np.searchsorted(ts, t), 1, len(ts) - 1)
    i = np.where(np.abs(ts[j - 1] - t) <= np.abs(ts[j] - t), j - 1, j)
    return None if np.any(np.abs(ts[i] - t) > MATCH_TOLERANCE + _MATCH_SLACK) else i


def parse_box(file, line, tok, what="x1 y1 x2 y2", camera: Camera | None = None) -> np.ndarray:
    """A box ``x1 y1 x2 y2`` of positive area, overlapping ``camera``'s image when given
    (``check_box``)."""
    b = np.array([parse_number(file, line, t, f) for t, f in zip(tok, what.split())])
    check_box(file, line, b, camera)
    return b


def box_faults(boxes, camera: Camera | None = None) -> np.ndarray:
    """(n,) whether each box (n, 4) breaks the rule for impossible boxes, the same in every
    reader: a box must have x2 > x1 and y2 > y1 (a zero-area box fixes no silhouette edge)
    and, when the image size is known, overlap the image (0, 0)–(width, height) (a box
    wholly outside it is no view of an object)."""
    x1, y1, x2, y2 = np.asarray(boxes, dtype=float).reshape(-1, 4).T
    ok = (x2 > x1) & (y2 > y1)
    if camera is not None:
        ok &= (x1 < camera.width) & (x2 > 0) & (y1 < camera.height) & (y2 > 0)
    return ~ok


def check_box(file, line, b, camera: Camera | None = None) -> None:
    """``box_faults``' rule for one box (in scalars: a reader checks one box per line):
    ``SequenceFormatError`` at the box's line naming what is wrong."""
    x1, y1, x2, y2 = (float(v) for v in b)
    if not x2 > x1:
        raise SequenceFormatError(file, line, "a box with x2 > x1 (positive width)", f"x1={x1:g} x2={x2:g}")
    if not y2 > y1:
        raise SequenceFormatError(file, line, "a box with y2 > y1 (positive height)", f"y1={y1:g} y2={y2:g}")
    if camera is not None and not (x1 < camera.width and x2 > 0 and y1 < camera.height and y2 > 0):
        raise SequenceFormatError(
            file, line, f"a box that overlaps the {camera.width:g}x{camera.height:g} image",
            f"[{x1:g}, {y1:g}, {x2:g}, {y2:g}]")


# --- YAML with line numbers -----------------------------------------------------------------


def yaml_root(path: Path, name: str):
    """The root node of a YAML file, composed with line marks (not constructed), every
    scalar checked to be a plain value; invalid or empty YAML is an error."""
    import yaml

    text = read_text(path, name)
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise SequenceFormatError(name, line, "valid YAML", str(getattr(e, "problem", None) or e)) from None
    if node is None:
        raise SequenceFormatError(name, None, "a YAML mapping", "an empty file")
    _check_plain(name, node)
    return node


def _check_plain(name, node) -> None:
    """Every scalar of the document is a plain YAML value: a tag that safe loading cannot
    construct (``!!python/object:…``) is an error at its line, found before any value is read."""
    import yaml

    todo, seen = [node], set()
    while todo:
        n = todo.pop()
        if id(n) in seen:  # aliases make the node graph a DAG, or a cycle (&a [*a])
            continue
        seen.add(id(n))
        if isinstance(n, yaml.ScalarNode):
            try:
                yaml.SafeLoader("").construct_object(n, deep=True)
            except yaml.YAMLError as e:
                raise SequenceFormatError(name, yaml_line(n), "a plain YAML value",
                                          f"the tag {n.tag!r} ({getattr(e, 'problem', None) or e})") from None
        elif isinstance(n, yaml.SequenceNode):
            todo.extend(n.value)
        elif isinstance(n, yaml.MappingNode):
            for k, v in n.value:
                todo += [k, v]


def yaml_line(node) -> int:
    """The 1-based line where a YAML node starts."""
    return node.start_mark.line + 1


def yaml_mapping(name, node, what: str) -> list:
    """(key, key node, value node) of a YAML mapping node, in order; a node that is not a
    mapping, a key that is not a string and a repeated key are errors."""
    import yaml

    if not isinstance(node, yaml.MappingNode):
        raise SequenceFormatError(name, yaml_line(node), f"a mapping for {what}", yaml_kind(node))
    out = []
    seen = set()
    for k, v in node.value:
        key = yaml_scalar(k)
        if not isinstance(key, str):
            raise SequenceFormatError(name, yaml_line(k), f"a string key in {what}", repr(key))
        if key in seen:
            raise SequenceFormatError(name, yaml_line(k), f"unique keys in {what}", f"{key!r} twice")
        seen.add(key)
        out.append((key, k, v))
    return out


def yaml_kind(node) -> str:
    """What a YAML node is, for the "got" of an error: "a mapping", "a list" or the
    scalar's ``repr``."""
    import yaml

    if isinstance(node, yaml.MappingNode):
        return "a mapping"
    if isinstance(node, yaml.SequenceNode):
        return "a list"
    return repr(yaml_scalar(node))


def yaml_scalar(node):
    """The value of a scalar YAML node (safe loading), None for a mapping or a list."""
    import yaml

    if not isinstance(node, yaml.ScalarNode):
        return None
    return yaml.SafeLoader("").construct_object(node, deep=True)


def yaml_number(name, node, what: str, allow_inf: bool = False) -> float:
    """The finite float of a YAML scalar (``.inf`` too with ``allow_inf``); a quoted string
    and a boolean are errors."""
    import yaml

    if isinstance(node, yaml.ScalarNode) and node.style in ("'", '"'):
        raise SequenceFormatError(name, yaml_line(node), f"a number for {what} (not quoted)",
                                  f"the string {node.value!r}")
    v = yaml_scalar(node) if isinstance(node, yaml.ScalarNode) else None
    if isinstance(v, str):  # PyYAML reads an unquoted 1e3 (no dot) as a string
        try:
            v = float(v)
        except ValueError:
            pass
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SequenceFormatError(name, yaml_line(node), f"a number for {what}", yaml_kind(node))
    if not (math.isfinite(v) or (allow_inf and v == math.inf)):
        raise SequenceFormatError(name, yaml_line(node), f"a finite number for {what}"
                                  + (" (or .inf)" if allow_inf else ""), repr(v))
    return float(v)


def yaml_vector(name, node, n: int, what: str, allow_inf: bool = False) -> np.ndarray:
    """The ``n`` numbers (``yaml_number``) of a YAML list of length ``n``."""
    import yaml

    if not isinstance(node, yaml.SequenceNode) or len(node.value) != n:
        got = f"a list of {len(node.value)}" if isinstance(node, yaml.SequenceNode) else yaml_kind(node)
        raise SequenceFormatError(name, yaml_line(node), f"a list of {n} numbers for {what}", got)
    return np.array([yaml_number(name, v, what, allow_inf) for v in node.value])


def reject_unknown_key(name, knode, key, allowed, where):
    """Raise ``SequenceFormatError`` at ``knode``'s line: ``key`` is not a key of ``where``
    (one of ``allowed``)."""
    raise SequenceFormatError(
        name, yaml_line(knode), f"a key of {where} among {', '.join(allowed)}", repr(key)
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
    for line, tok in token_rows(path, name):
        check_columns(name, line, tok, (2,), "timestamp path")
        t = parse_number(name, line, tok[0], "timestamp")
        p = Path(tok[1])
        out[t] = Path(os.path.abspath(p if p.is_absolute() else Path(folder) / p))
    return out


def required(folder: Path, fname: str) -> Path:
    """``folder / fname``, which must be a readable regular file."""
    p = folder / fname
    why = _not_a_file(p)
    if why:
        raise SequenceFormatError(p, None, f"a required file {fname}", why)
    return p


def optional(folder: Path, fname: str) -> Path | None:
    """``folder / fname`` when anything is there (then the reader checks that it is a
    readable regular file: a directory named priors.yaml is an error, not an absent file),
    else None."""
    p = folder / fname
    return p if present(p) else None
