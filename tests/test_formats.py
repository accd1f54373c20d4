"""The sequence-format registry (``spdslam.io.SequenceFormat``, issue 29): each layout is one
class, found by ``read_sequence``, ``spdslam run`` and ``spdslam import``; a path that two
formats claim, or none, or that is not there or loops, is refused with one line."""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

import pytest
from conftest import assert_cli_error as assert_error
from conftest import cli_invoke as invoke

from spdslam.io import (
    FORMATS,
    SequenceFormat,
    SequenceFormatError,
    find_format,
    formats,
    formats_table,
    read_sequence,
    write_sequence,
)
from spdslam.io import _formats
from spdslam.synthetic import make_room_sequence

ROOT = Path(__file__).resolve().parents[1]
BUILTIN = ("canonical", "oaslam", "detector", "fr3_cabinet", "rosbag2")


@pytest.fixture
def registry():
    """The registry as it was, restored after the test (formats defined in it vanish)."""
    saved = dict(FORMATS)
    yield FORMATS
    FORMATS.clear()
    FORMATS.update(saved)


@pytest.fixture(scope="module")
def canonical(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("formats") / "room"
    write_sequence(make_room_sequence(0, frames=8, objects=2), folder)
    return folder


def _error(path, **options) -> str:
    with pytest.raises(SequenceFormatError) as e:
        read_sequence(path, **options)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(path)), msg
    return msg


def test_the_built_in_formats_are_registered_and_described():
    assert [f.name for f in formats()][: len(BUILTIN)] == list(BUILTIN)
    for f in formats():
        assert f.title and f.layout and f.docs, f
        assert set(f.hints) <= {o for g in formats() for o in g.options}, f
    assert [f.name for f in formats() if f.writes] == ["canonical"]


def test_each_built_in_format_names_a_section_that_describes_it():
    for f in formats():
        if f.name not in BUILTIN:
            continue
        page, _, title = f.docs.rpartition(", ") if f.docs.startswith("docs/") else ("docs/formats.md", "", f.docs)
        headings = [line.lstrip("#").strip() for line in
                    (ROOT / page).read_text(encoding="utf-8").splitlines() if line.startswith("#")]
        assert any(h.startswith(title) for h in headings), (f.name, page, title)


def test_docs_formats_md_lists_the_registry():
    """docs/formats.md's table of formats is the registry's, row for row."""
    text = (ROOT / "docs" / "formats.md").read_text(encoding="utf-8")
    assert formats_table() in text


def test_each_reference_layout_is_claimed_by_exactly_its_format(canonical):
    assert find_format(canonical).name == "canonical"
    data = ROOT.parent / "shared" / "data"
    for name, fmt in (("tum_fr3_cabinet", "fr3_cabinet"), ("tum_fr2_desk", "oaslam")):
        if (data / name).is_dir():
            assert [f.name for f in formats() if f.claims(data / name)] == [fmt]


def test_a_path_claimed_by_two_formats_or_none_is_refused_naming_the_candidates(canonical, tmp_path):
    both = tmp_path / "both"
    shutil.copytree(canonical, both)
    (both / "detections_yolo.json").write_text("[]\n", encoding="utf-8")
    msg = _error(both)
    assert "canonical (camera.yaml, trajectory.txt, detections.txt)" in msg
    assert "oaslam (a detections*.json" in msg and "all claim" in msg
    empty = tmp_path / "empty"
    empty.mkdir()
    msg = _error(empty)
    assert "none of their layouts" in msg
    for f in formats():
        assert f"{f.name}, {f.describe()}" in msg
    plain = tmp_path / "notes.txt"
    plain.write_text("x\n", encoding="utf-8")
    assert "none of their layouts" in _error(plain)


def test_paths_that_are_not_there_or_loop(tmp_path):
    assert "got no such file or folder" in _error(tmp_path / "absent")
    loop = tmp_path / "loop"
    os.symlink(loop, loop)
    assert "got a symbolic-link loop" in _error(loop)
    a, b = tmp_path / "a", tmp_path / "b"
    os.symlink(b, a)
    os.symlink(a, b)
    assert "got a symbolic-link loop" in _error(a)
    broken = tmp_path / "broken"
    os.symlink(tmp_path / "nowhere", broken)
    assert "got a broken symbolic link" in _error(broken)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert "neither a folder nor a regular file" in _error(fifo)


def test_a_looped_sequence_path_ends_spdslam_run_in_one_line(tmp_path):
    """Before issue 29 this was a RuntimeError traceback (Python's resolve of the --out check)."""
    loop = tmp_path / "loop"
    os.symlink(loop, loop)
    for args in (("run", loop, "--out", tmp_path / "out"), ("compare", loop, "--out", tmp_path / "out"),
                 ("import", loop, tmp_path / "dest"), ("check", loop, "--json", tmp_path / "c.json")):
        assert_error(invoke(*args), str(loop), "symbolic-link loop")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["loop"]


def test_a_new_format_is_one_class(registry, canonical, tmp_path):
    """Defining a subclass registers it: read_sequence finds it, with its options; options
    it does not take are refused; a second format of the same name is refused."""

    class Renamed(SequenceFormat):
        """A canonical folder marked by a RENAMED file, read with a name option."""

        name = "renamed"
        title = "a renamed folder"
        layout = "a RENAMED file"
        options = {"label": "the sequence's name"}

        @classmethod
        def claims(cls, path):
            return (path / "RENAMED").is_file()

        @classmethod
        def read(cls, path, label="renamed"):
            seq = FORMATS["canonical"].read(path / "inner")
            return dataclasses.replace(seq, name=label)

    assert FORMATS["renamed"] is Renamed and Renamed in formats()
    folder = tmp_path / "outer"
    shutil.copytree(canonical, folder / "inner")
    (folder / "RENAMED").write_text("", encoding="utf-8")
    assert read_sequence(folder).name == "renamed"
    assert read_sequence(folder, label="mine").name == "mine"
    with pytest.raises(ValueError, match="takes no option 'min_score'"):
        read_sequence(folder, min_score=0.3)
    with pytest.raises(SequenceFormatError, match="a path it does not claim"):
        read_sequence(canonical, format="renamed")
    assert read_sequence(canonical, format="canonical") == read_sequence(canonical)
    with pytest.raises(ValueError, match="unknown sequence format 'nope'"):
        read_sequence(canonical, format="nope")
    assert "| `renamed` | a renamed folder | a RENAMED file | `--label` | no |" in formats_table()

    with pytest.raises(ValueError, match="already registered"):
        type("Other", (SequenceFormat,), {"name": "renamed", "title": "t", "layout": "l"})
    with pytest.raises(TypeError, match="title must be set"):
        type("Untitled", (SequenceFormat,), {"name": "untitled", "layout": "l"})
    assert "untitled" not in FORMATS


def test_the_cli_passes_and_refuses_format_options(canonical, tmp_path):
    out = tmp_path / "out"
    assert_error(invoke("run", canonical, "--out", out, "--option", "min_score=0.3"),
                 "--option", "the canonical format takes no option 'min_score'")
    assert_error(invoke("run", canonical, "--out", out, "--option", "nonsense"), "--option", "NAME=VALUE")
    assert_error(invoke("import", canonical, tmp_path / "dest", "--min-score", "0.3"),
                 "--min-score", "an OA-SLAM-style folder", "a ROS 2 bag", "a canonical sequence folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_the_cli_help_lists_the_registry():
    for cmd in ("run", "import"):
        result = invoke(cmd, "--help")
        assert result.exit_code == 0
        text = " ".join(result.stdout.replace("│", " ").split())
        for f in formats():
            assert f.title in text, (cmd, f.name)


def test_entry_points_add_formats(registry, monkeypatch, tmp_path):
    """A package names a module in the group spdslam.formats; the first lookup imports it."""
    mod = tmp_path / "my_formats.py"
    mod.write_text(
        "from spdslam.io import SequenceFormat\n"
        "class Marked(SequenceFormat):\n"
        "    name, title, layout = 'marked', 'a marked folder', 'a MARK file'\n"
        "    @classmethod\n"
        "    def claims(cls, path):\n"
        "        return (path / 'MARK').is_file()\n", encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))

    class EntryPoint:
        name, value = "marked", "my_formats"

        def load(self):
            import importlib

            return importlib.import_module(self.value)

    import importlib.metadata as md

    monkeypatch.setattr(md, "entry_points", lambda group: [EntryPoint()] if group == "spdslam.formats" else [])
    monkeypatch.setattr(_formats, "_ENTRY_POINTS_LOADED", False)
    assert "marked" in [f.name for f in formats()]
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "MARK").write_text("", encoding="utf-8")
    assert find_format(tmp_path / "m").name == "marked"


def test_a_broken_entry_point_is_named(monkeypatch):
    class Broken:
        name, value = "broken", "no_such_module_here"

        def load(self):
            raise ModuleNotFoundError("No module named 'no_such_module_here'")

    import importlib.metadata as md

    monkeypatch.setattr(md, "entry_points", lambda group: [Broken()])
    monkeypatch.setattr(_formats, "_ENTRY_POINTS_LOADED", False)
    with pytest.raises(ImportError, match="entry point 'broken' .no_such_module_here. failed to load"):
        formats()


def test_a_file_is_written_whole_or_left_as_it_was(tmp_path):
    from spdslam.io import write_file_atomically

    path = tmp_path / "metrics.json"
    path.write_text("old")

    def broken(tmp):
        tmp.write_text("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_file_atomically(path, broken)
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["metrics.json"]
    assert write_file_atomically(path, lambda tmp: tmp.write_text("new")) == 3
    assert path.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["metrics.json"]
