"""Reliability (issue 15): no traceback, no data loss, no silent acceptance of impossible input.

Readers: one rule for BOMs, CRLF and quoted numbers; a directory, FIFO or link loop where a
file belongs says what is there; impossible boxes are rejected with ``file:line``.
Evaluation that cannot be computed is "not computed" (``null`` in strict JSON), and the map
is still written. The CLI refuses an output folder that is, lies in or holds its input, or
that cannot be written, before touching anything.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_cli_error as assert_error
from conftest import cli_invoke as invoke
from conftest import cli_runner

from spdslam.io import (
    SequenceFormatError,
    dumps_strict,
    import_fr3_cabinet,
    read_sequence,
    write_sequence,
)
from spdslam.synthetic import make_room_sequence

runner = cli_runner()


def snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): (p.read_bytes() if p.is_file() else None)
            for p in sorted(folder.rglob("*"))}


def strict_load(text: str):
    """json.loads that refuses NaN and Infinity (RFC 8259)."""
    def bad(name):
        raise ValueError(f"non-strict JSON constant {name}")
    return json.loads(text, parse_constant=bad)


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("reliability") / "room"
    write_sequence(make_room_sequence(0, frames=40, objects=2), folder)
    return folder


@pytest.fixture
def copy(seq_dir, tmp_path):
    """A fresh copy of the room to corrupt."""
    dst = tmp_path / "room"
    shutil.copytree(seq_dir, dst)
    return dst


def _error(folder) -> str:
    with pytest.raises(SequenceFormatError) as e:
        read_sequence(folder)
    msg = str(e.value)
    assert "\n" not in msg
    return msg


# --------------------------------------------------------------------------- readers


def test_bom_and_crlf_read_the_same_in_every_file(copy, seq_dir):
    ref = read_sequence(seq_dir)
    for name in ("camera.yaml", "trajectory.txt", "detections.txt", "objects_gt.txt", "groundtruth.txt"):
        p = copy / name
        text = p.read_text(encoding="utf-8")
        p.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode("utf-8"))
    seq = read_sequence(copy)
    assert np.array_equal(seq.poses_tum, ref.poses_tum) and len(seq.detections) == len(ref.detections)
    assert seq.camera == ref.camera and np.array_equal(seq.groundtruth_tum, ref.groundtruth_tum)


def test_a_quoted_number_is_an_error(copy):
    p = copy / "camera.yaml"
    p.write_text(p.read_text().replace("fy: ", "fy: '", 1).replace("\ncx", "'\ncx", 1))
    assert "camera.yaml:2: a number for fy (not quoted), got the string" in _error(copy)


def test_python_only_number_spellings_are_errors(copy):
    p = copy / "trajectory.txt"
    lines = p.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if line.strip() and not line.startswith("#"))
    tok = lines[k].split()
    tok[1] = "1_000"
    lines[k] = " ".join(tok)
    p.write_text("\n".join(lines) + "\n")
    assert f"trajectory.txt:{k + 1}: a number for tx, got '1_000'" in _error(copy)


@pytest.mark.parametrize("what", ["directory", "fifo"])
def test_an_optional_file_that_is_not_a_file_is_an_error(copy, what):
    p = copy / "priors.yaml"
    if p.exists():
        p.unlink()
    if what == "directory":
        p.mkdir()
        assert "priors.yaml: a readable file, got a directory" in _error(copy)
    else:
        os.mkfifo(p)
        assert "priors.yaml: a readable file, got a FIFO" in _error(copy)


def test_a_required_file_that_is_a_directory_or_a_link_loop(copy):
    (copy / "trajectory.txt").unlink()
    (copy / "trajectory.txt").mkdir()
    assert "trajectory.txt: a required file trajectory.txt, got a directory" in _error(copy)
    (copy / "trajectory.txt").rmdir()
    os.symlink(copy / "trajectory.txt", copy / "trajectory.txt")
    assert "got a symbolic-link loop" in _error(copy)
    (copy / "trajectory.txt").unlink()
    os.symlink(copy / "nowhere.txt", copy / "trajectory.txt")
    assert "got a broken symbolic link" in _error(copy)


@pytest.mark.parametrize("box, why", [
    ("100 50 100 80", "a box with x2 > x1 (positive width), got x1=100 x2=100"),
    ("100 80 120 80", "a box with y2 > y1 (positive height), got y1=80 y2=80"),
    ("-50 -40 -10 -5", "a box that overlaps the 640x480 image, got [-50, -40, -10, -5]"),
    ("700 10 760 50", "a box that overlaps the 640x480 image"),
])
def test_impossible_boxes_are_rejected_at_their_line(copy, box, why):
    p = copy / "detections.txt"
    lines = p.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if line.strip() and not line.startswith("#"))
    tok = lines[k].split()
    tok[1:5] = box.split()
    lines[k] = " ".join(tok)
    p.write_text("\n".join(lines) + "\n")
    msg = _error(copy)
    assert f"detections.txt:{k + 1}: {why}" in msg, msg


def test_fr3_layout_with_a_directory_in_bbox(tmp_path):
    folder = tmp_path / "fr3"
    (folder / "bbox" / "1.0.txt").mkdir(parents=True)
    (folder / "groundtruth.txt").write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n")
    (folder / "TUM3.yaml").write_text("%YAML:1.0\nCamera.fx: 500\nCamera.fy: 500\nCamera.cx: 320\nCamera.cy: 240\n")
    (folder / "truth_objects.txt").write_text("0 0 1 0 0.1 0.1 0.1\n")
    with pytest.raises(SequenceFormatError, match="1.0.txt: a required file 1.0.txt, got a directory"):
        import_fr3_cabinet(folder)


# --------------------------------------------------------------------------- evaluation


def test_strict_json_has_no_nan_or_infinity():
    text = dumps_strict({"a": float("nan"), "b": [1.0, float("inf"), np.float64("-inf")],
                         "c": np.arange(2), "d": (np.int64(3), np.bool_(True))})
    assert strict_load(text) == {"a": None, "b": [1.0, None, None], "c": [0, 1], "d": [3, True]}


@pytest.mark.parametrize("path", ["line", "rotation", "two", "huge"])
def test_evaluation_without_a_usable_ground_truth_path_is_not_computed(path, tmp_path):
    """A straight-line drive, a pure rotation, a two-pose ground truth and one coordinate of
    1e300 fix no alignment:
    the map is evaluated as mapped, the ATE is "not computed" and the JSON strict."""
    from conftest import write_truth_run

    from spdslam.evaluation import evaluate_run, report_markdown
    from spdslam.io import read_map

    seq = make_room_sequence(0, frames=40, objects=2)
    gt = np.array(seq.groundtruth_tum, float)
    if path == "line":
        gt[:, 1:4] = np.linspace(0, 1, len(gt))[:, None] * np.array([1.0, 0.5, 0.0])
    elif path == "rotation":
        gt[:, 1:4] = 0.0
    elif path == "huge":
        gt[3, 1] = 1e300
    else:
        gt = gt[:2]
    seq = dataclasses.replace(seq, groundtruth_tum=gt)
    run, objects = read_map(write_truth_run(seq, tmp_path / "run"))  # the map: the true objects
    m = evaluate_run(run, objects, None, np.c_[seq.timestamps, seq.poses_tum], seq)
    assert "not_aligned" in m and m["ate"]["input"] is None and m["ate"]["optimized"] is None
    assert set(m["ate"]["not_computed"]) == {"input", "optimized"}
    report = report_markdown(m, run)
    assert "ATE RMSE: input not computed (" in report and "nan" not in report
    strict_load(dumps_strict(m))


def test_no_matched_object_reads_not_computed():
    from spdslam import Ellipsoid
    from spdslam.evaluation import evaluate_objects
    from spdslam.evaluation._report import shown
    from spdslam.io import MapObject

    seq = make_room_sequence(0, frames=10, objects=1)
    far = [MapObject(7, "nothing-like-it", Ellipsoid(np.eye(3) * 0.01, np.array([50.0, 0, 0])))]
    rows, s = evaluate_objects(far, seq.objects_gt, by_id=False)
    assert s["matched"] == 0 and shown(s["mean_orientation_deg"], ".2f", "°") == "not computed"
    assert strict_load(dumps_strict(s))["mean_orientation_deg"] is None


def test_a_collapsed_study_estimate_keeps_its_orientation_and_csv_has_no_nan():
    from spdslam import Ellipsoid
    from spdslam.experiments._outputs import _fmt
    from spdslam.experiments._study import _ious_and_orientation

    flat = Ellipsoid(np.diag([0.09, 0.04, 0.0]), np.zeros(3))
    truth = Ellipsoid(np.diag([0.09, 0.04, 0.01]), np.zeros(3))
    batch = lambda e: dataclasses.replace(e, P=np.asarray(e.P)[None], center=np.asarray(e.center)[None])  # noqa: E731
    iou, orient, ratio = _ious_and_orientation(batch(flat), batch(truth))
    assert iou[0] == 0.0 and np.isfinite(orient[0]) and orient[0] < 1e-6
    assert _fmt(float("nan")) == "" and _fmt(0.5) == "0.5"


# --------------------------------------------------------------------------- the CLI


@pytest.mark.parametrize("where", ["same", "inside", "parent"])
def test_run_never_writes_over_its_input(copy, where):
    out = {"same": copy, "inside": copy / "out", "parent": copy.parent}[where]
    before = snapshot(copy.parent)
    assert_error(invoke("run", copy, "--out", out, "--overwrite"), "expected an output folder apart from it")
    assert snapshot(copy.parent) == before


@pytest.mark.parametrize("cmd", ["import", "compare"])
def test_import_and_compare_never_write_over_their_input(copy, cmd):
    before = snapshot(copy.parent)
    args = ["import", copy, copy.parent, "--overwrite"] if cmd == "import" else \
        ["compare", copy, "--out", copy.parent, "--overwrite"]
    assert_error(invoke(*args), "contains the input")
    assert snapshot(copy.parent) == before


@pytest.mark.parametrize("cmd", ["run", "simulate", "demo", "import"])
def test_an_unwritable_output_is_one_line(seq_dir, cmd):
    bad = Path("/proc/spdslam-test/out")
    args = {"run": ["run", seq_dir, "--out", bad], "simulate": ["simulate", "--out", bad],
            "demo": ["demo", "--out", bad], "import": ["import", seq_dir, bad]}[cmd]
    assert_error(invoke(*args), "cannot write")
    assert not bad.parent.exists()


def test_run_with_a_straight_line_ground_truth_writes_everything(copy, tmp_path):
    gt = copy / "groundtruth.txt"
    rows = [line.split() for line in gt.read_text().splitlines() if line.strip() and not line.startswith("#")]
    for i, r in enumerate(rows):
        r[1:4] = [f"{0.05 * i:.6f}", "0", "0"]
    gt.write_text("\n".join(" ".join(r) for r in rows) + "\n")
    out = tmp_path / "out"
    res = invoke("run", copy, "--out", out)
    assert res.exit_code == 0, (res.stdout, res.stderr, res.exception)
    assert "not computed" in res.stdout and "nan" not in res.stdout
    for name in ("map.json", "metrics.json"):
        strict_load((out / name).read_text())
    report = (out / "report.md").read_text()
    assert "the alignment was not computed" in report and "nan" not in report


def test_write_sequence_refuses_a_box_the_reader_would_refuse(tmp_path):
    seq = make_room_sequence(0, frames=10, objects=2)
    d0 = dataclasses.replace(seq.detections[0], box=np.array([5.0, 5.0, 5.0, 9.0]))
    with pytest.raises(ValueError, match="detection 0 of 'demo_room': a box with x2 > x1"):
        write_sequence(dataclasses.replace(seq, detections=[d0, *seq.detections[1:]]), tmp_path / "x")
    assert not list(tmp_path.iterdir())  # nothing written, no temporary left
