"""The sequence commands of the CLI: ``run``, ``evaluate``, ``import`` and ``demo``.

Everything runs in-process through typer's ``CliRunner`` on a small synthetic room
(40 frames, 2 objects). The first ``run`` pays the JAX compilation (~10-30 s); the few
later ones reuse the compiled functions, so ``run`` is invoked only four times in all
(the shared output folder of :func:`run_out`, one refused overwrite, two ``demo``).
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
from conftest import assert_cli_ok as assert_ok
from conftest import cli_invoke as invoke
from conftest import cli_runner

from spdslam import cli
from spdslam.io import (
    import_fr3_cabinet,
    read_map,
    read_sequence,
    read_tum,
    write_sequence,
)
from spdslam.synthetic import make_room_sequence

runner = cli_runner()

ROOT = Path(__file__).resolve().parents[1]
#: The fr3_cabinet sample, as a path relative to the repository root.
FR3_REL = "../shared/data/tum_fr3_cabinet"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
FRAMES, OBJECTS = 40, 2


# --------------------------------------------------------------------------- helpers


def snapshot(folder: Path) -> dict:
    """{relative path: bytes (files) or None (folders)} of everything under ``folder``."""
    if not folder.exists():
        return {}
    return {
        p.relative_to(folder).as_posix(): (p.read_bytes() if p.is_file() else None)
        for p in sorted(folder.rglob("*"))
    }


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory) -> Path:
    """A small demo room written as a canonical sequence folder."""
    folder = tmp_path_factory.mktemp("sequences") / "room"
    write_sequence(make_room_sequence(0, frames=FRAMES, objects=OBJECTS), folder)
    return folder


@pytest.fixture(scope="module")
def seq(seq_dir):
    return read_sequence(seq_dir)


@pytest.fixture(scope="module")
def run_out(seq_dir, tmp_path_factory):
    """(result, OUT) of ``spdslam run SEQ --out OUT``; tests must not modify OUT."""
    out = tmp_path_factory.mktemp("runs") / "out"
    return invoke("run", seq_dir, "--out", out), out


# --------------------------------------------------------------------------- run


def test_run_writes_all_outputs(run_out):
    result, out = run_out
    assert_ok(result)
    assert "mean IoU" in result.stdout and "wrote" in result.stdout
    for name in ("map.json", "trajectory.txt", "report.md", "metrics.json", "map_top.png"):
        assert (out / name).is_file(), name
    assert (out / "map_top.png").read_bytes()[:8] == PNG_SIGNATURE
    assert not (out / "overlay").exists()  # the demo sequence has no images
    # the atomic write left no temporary folder beside OUT
    assert sorted(p.name for p in out.parent.iterdir()) == ["out"]
    report = (out / "report.md").read_text(encoding="utf-8")
    assert report.startswith("# multi-spd on room")
    assert "mean IoU" in report


def test_run_map_json(run_out, seq, seq_dir):
    result, out = run_out
    assert_ok(result)
    m = json.loads((out / "map.json").read_text(encoding="utf-8"))
    for key in ("method", "parameterization", "iterations", "final_cost", "objects"):
        assert key in m, key
    assert m["method"] == "multi-spd" and m["parameterization"] == "spd"
    assert m["sequence"] == str(seq_dir.resolve())  # the folder read, for spdslam view
    assert isinstance(m["iterations"], int) and m["iterations"] >= 1
    assert 0 < m["final_cost"] < m["initial_cost"]  # noisy boxes: a positive cost, lowered
    gt_labels = {o.id: o.label for o in seq.objects_gt}
    assert len(m["objects"]) == OBJECTS
    assert sorted(o["id"] for o in m["objects"]) == sorted(gt_labels)
    for o in m["objects"]:
        for key in ("id", "label", "center", "rotation", "radii", "P"):
            assert key in o, key
        assert o["label"] == gt_labels[o["id"]]
        c, R, r, P = (np.asarray(o[k], dtype=float) for k in ("center", "rotation", "radii", "P"))
        assert c.shape == (3,) and R.shape == (3, 3) and r.shape == (3,) and P.shape == (3, 3)
        assert np.all(np.isfinite(c))
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
        assert np.all(r > 0)
        np.testing.assert_allclose(P, R @ np.diag(r**2) @ R.T, rtol=1e-9, atol=1e-12 * np.max(r**2))
    # read_map (used by evaluate) accepts what run wrote
    m2, objs = read_map(out)
    assert m2 == m and [o.id for o in objs] == [o["id"] for o in m["objects"]]


def test_run_trajectory_is_tum_one_row_per_frame(run_out, seq):
    result, out = run_out
    assert_ok(result)
    path = out / "trajectory.txt"
    rows = read_tum(path, str(path))
    assert rows.shape == (len(seq), 8) == (FRAMES, 8)
    np.testing.assert_allclose(rows[:, 0], seq.timestamps, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(rows[:, 4:], axis=1), 1.0, atol=1e-9)
    # optimised, but close to the drifted input trajectory
    assert np.max(np.abs(rows[:, 1:4] - seq.poses_tum[:, :3])) < 0.5


def test_run_metrics_json(run_out):
    result, out = run_out
    assert_ok(result)
    metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    s = metrics["summary"]
    assert s["ground_truth_objects"] == OBJECTS and s["matched"] == OBJECTS
    assert 0.5 < s["mean_iou"] <= 1.0
    assert {"input", "optimized"} <= set(metrics["ate"])
    assert f"mean IoU {s['mean_iou']:.3f}" in result.stdout


# --------------------------------------------------------------------------- evaluate


def test_evaluate_reproduces_run_metrics(run_out, seq_dir, tmp_path):
    _, out = run_out
    ev = tmp_path / "copy"
    shutil.copytree(out, ev)
    (ev / "metrics.json").unlink()
    (ev / "report.md").unlink()
    result = invoke("evaluate", ev, seq_dir)
    assert_ok(result)
    assert "mean IoU" in result.stdout
    assert (ev / "report.md").is_file()
    want = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    got = json.loads((ev / "metrics.json").read_text(encoding="utf-8"))
    assert got["summary"]["mean_iou"] == pytest.approx(want["summary"]["mean_iou"], abs=1e-9)
    assert got["summary"]["matched"] == want["summary"]["matched"]
    for a, b in zip(got["objects"], want["objects"]):
        assert a["id"] == b["id"] and a["iou"] == pytest.approx(b["iou"], abs=1e-9)
    assert got["ate"]["optimized"]["rmse"] == pytest.approx(want["ate"]["optimized"]["rmse"], abs=1e-9)


def test_evaluate_accepts_the_map_json_path(run_out, seq_dir, tmp_path):
    _, out = run_out
    ev = tmp_path / "copy"
    shutil.copytree(out, ev)
    result = invoke("evaluate", ev / "map.json", seq_dir)
    assert_ok(result)
    assert "mean IoU" in result.stdout


# --------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    "args, fragments",
    [
        (["--method", "bogus"], ["--method", "'bogus'", "multi-spd"]),
        (["--sigma", "bogus=1"], ["--sigma", "'bogus'", "inverse_box"]),
        (["--sigma", "inverse_box=abc"], ["--sigma", "'abc' is not a number"]),
        (["--sigma", "inverse_box"], ["--sigma", "NAME=VALUE"]),
        (["--sigma", "inverse_box=-1"], ["--sigma", "finite positive"]),
        (["--sigma", "orientation=0"], ["--sigma", "finite positive"]),
        (["--robust", "bogus"], ["--robust", "'bogus'", "huber"]),
        (["--robust", "boxes=huber"], ["--robust", "'boxes=huber'", "odometry"]),
        (["--robust", "box=huber:-1"], ["--robust", "K > 0"]),
        (["--robust", "box=huber:x"], ["--robust", "'x' is not a number"]),
        (["--associate", "bogus"], ["--associate", "instances, auto", "'bogus'"]),
        (["--object-shape", "box"], ["--object-shape", "cuboid", "'box'"]),
    ],
    ids=["method", "sigma-name", "sigma-value", "sigma-no-equals", "sigma-negative", "sigma-zero",
         "robust-kernel", "robust-type", "robust-k", "robust-k-nan", "associate", "object-shape"],
)
def test_run_bad_options(seq_dir, tmp_path, args, fragments):
    out = tmp_path / "out"
    result = invoke("run", seq_dir, "--out", out, *args)
    assert_error(result, *fragments)
    assert result.stdout == ""
    assert list(tmp_path.iterdir()) == []


def test_run_malformed_detections_names_file_and_line(seq_dir, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(seq_dir, bad)
    path = bad / "detections.txt"
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    n = 5  # 1-based; line 1 is the header comment
    tok = lines[n - 1].split()
    tok[1], tok[3] = tok[3], tok[1]  # x1 <-> x2: now x2 < x1
    assert float(tok[3]) < float(tok[1])
    lines[n - 1] = " ".join(tok) + "\n"
    path.write_text("".join(lines), encoding="utf-8")
    before = snapshot(tmp_path)
    out = tmp_path / "out"
    result = invoke("run", bad, "--out", out)
    assert_error(result, f"detections.txt:{n}:", "x2 > x1")
    assert not out.exists()
    assert snapshot(tmp_path) == before


def test_run_missing_sequence_folder(tmp_path):
    missing = tmp_path / "no-such-sequence"
    result = invoke("run", missing, "--out", tmp_path / "out")
    assert_error(result, str(missing), "no such file or folder")
    assert list(tmp_path.iterdir()) == []


def test_run_refuses_non_empty_out(seq_dir, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine\n", encoding="utf-8")
    before = snapshot(tmp_path)
    result = invoke("run", seq_dir, "--out", out)
    assert_error(result, "--out", str(out), "not empty", "--overwrite")
    assert snapshot(tmp_path) == before  # OUT unchanged, no temporary folder left beside it


def test_evaluate_without_map_json(seq_dir, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    result = invoke("evaluate", empty, seq_dir)
    assert_error(result, str(empty), "expected a saved map", "map.json", "none of their layouts")
    assert list(empty.iterdir()) == []


def test_evaluate_corrupted_map_json(run_out, seq_dir, tmp_path):
    _, out = run_out
    ev = tmp_path / "copy"
    shutil.copytree(out, ev)
    (ev / "map.json").write_text('{"method": "multi-spd",\n "objects": [1, 2\n', encoding="utf-8")
    before = snapshot(tmp_path)
    result = invoke("evaluate", ev, seq_dir)
    assert_error(result, str(ev / "map.json"), "expected JSON")
    assert snapshot(tmp_path) == before  # metrics.json and report.md not rewritten


@pytest.mark.parametrize(
    "edit",
    [
        pytest.param(lambda m: [1, 2], id="json-list"),
        pytest.param(lambda m: {**m, "objects": [{"P": "x"}]}, id="object-without-P"),
        pytest.param(lambda m: 5, id="json-number"),
        pytest.param(lambda m: {**m, "objects": 5}, id="objects-not-a-list"),
        pytest.param(lambda m: {**m, "objects": [{k: v for k, v in m["objects"][0].items() if k != "id"}]},
                     id="object-without-id"),
        pytest.param(lambda m: {**m, "final_cost": "low"}, id="final-cost-not-a-number"),
    ],
)
def test_evaluate_malformed_map_json(run_out, seq_dir, tmp_path, edit):
    _, out = run_out
    ev = tmp_path / "copy"
    shutil.copytree(out, ev)
    m = json.loads((ev / "map.json").read_text(encoding="utf-8"))
    (ev / "map.json").write_text(json.dumps(edit(m)), encoding="utf-8")
    before = snapshot(tmp_path)
    result = invoke("evaluate", ev, seq_dir)
    if not isinstance(result.exception, SystemExit):
        raise result.exception  # a traceback instead of an error line
    assert_error(result, str(ev / "map.json"))
    assert snapshot(tmp_path) == before


def test_import_goes_through_the_format_registry(seq_dir, tmp_path):
    """A canonical folder imports as a copy (every registered format reads); a folder no
    format claims, or one two claim, is refused naming the candidates; nothing is written."""
    from spdslam.io import read_sequence

    dest = tmp_path / "dest"
    result = invoke("import", seq_dir, dest)
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    assert read_sequence(dest) == dataclasses.replace(read_sequence(seq_dir), name="dest")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_error(invoke("import", empty, tmp_path / "d2"), str(empty), "none of their layouts",
                 "canonical", "fr3_cabinet", "oaslam", "rosbag2")
    both = tmp_path / "both"
    shutil.copytree(seq_dir, both)
    (both / "bbox").mkdir()
    (both / "truth_objects.txt").write_text("0 0 0 0 1 1 1\n", encoding="utf-8")
    assert_error(invoke("import", both, tmp_path / "d2"), str(both), "canonical (", "fr3_cabinet (",
                 "all claim")
    assert_error(invoke("import", tmp_path / "nowhere", tmp_path / "d2"), str(tmp_path / "nowhere"),
                 "no such file or folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["both", "dest", "empty"]


def test_demo_refuses_a_foreign_non_empty_folder(tmp_path):
    d = tmp_path / "d"
    d.mkdir()
    (d / "thesis.tex").write_text("precious\n", encoding="utf-8")
    before = snapshot(tmp_path)
    result = invoke("demo", "--out", d, "--frames", FRAMES, "--objects", OBJECTS)
    assert_error(result, "--out", str(d), "not an earlier demo output")
    assert snapshot(tmp_path) == before


def test_demo_out_is_a_file(tmp_path):
    f = tmp_path / "file"
    f.write_text("x\n", encoding="utf-8")
    result = invoke("demo", "--out", f, "--frames", FRAMES, "--objects", OBJECTS)
    if not isinstance(result.exception, SystemExit):
        raise result.exception
    assert_error(result, "--out", str(f))
    assert f.read_text(encoding="utf-8") == "x\n"


# --------------------------------------------------------------------------- import


def _fr3_source() -> Path:
    src = ROOT / FR3_REL
    if not src.is_dir():
        pytest.skip(f"fr3_cabinet sample not found at {src} (FR3_REL relative to {ROOT})")
    return src


def test_import_fr3_cabinet(tmp_path, monkeypatch):
    _fr3_source()
    monkeypatch.chdir(ROOT)  # the command is given the path relative to the repository root
    dest = tmp_path / "cabinet"
    result = invoke("import", FR3_REL, dest)
    assert_ok(result)
    assert "imported" in result.stdout
    got = read_sequence(dest)
    want = import_fr3_cabinet(FR3_REL)
    assert got.name == "cabinet" and want.name == "tum_fr3_cabinet"
    assert got.camera == want.camera
    np.testing.assert_array_equal(got.timestamps, want.timestamps)
    np.testing.assert_allclose(got.poses_tum, want.poses_tum, rtol=0, atol=1e-12)
    assert len(got.detections) == len(want.detections) > 0
    assert got.detections == want.detections
    assert got.objects_gt is not None and len(got.objects_gt) > 0
    assert got.objects_gt == want.objects_gt
    np.testing.assert_allclose(got.groundtruth_tum, want.groundtruth_tum, rtol=0, atol=1e-12)
    assert got.priors == want.priors
    assert got.images == want.images
    assert all(os.path.isabs(p) for p in got.images.values())
    # a second import into the now non-empty DEST is refused and leaves it alone
    before = snapshot(dest)
    result = invoke("import", FR3_REL, dest)
    assert_error(result, str(dest), "not empty")
    assert snapshot(dest) == before


# --------------------------------------------------------------------------- demo


def test_demo_writes_sequence_and_run_and_replaces_itself(tmp_path, seq_dir):
    d = tmp_path / "demo"
    result = invoke("demo", "--out", d, "--frames", FRAMES, "--objects", OBJECTS)
    assert_ok(result)
    seq = read_sequence(d / "sequence")
    assert len(seq) == FRAMES
    assert seq.objects_gt is not None and len(seq.objects_gt) == OBJECTS
    assert seq.groundtruth_tum is not None
    want = make_room_sequence(0, frames=FRAMES, objects=OBJECTS)
    assert seq.detections == want.detections and seq.objects_gt == want.objects_gt
    m, objs = read_map(d / "run")
    assert m["method"] == "multi-spd" and len(objs) == OBJECTS
    assert (d / "run" / "metrics.json").is_file()
    # the same sequence as seq_dir's, mapped by the default method with the boxes moving the
    # poses (the demo's initial_poses input): the same map
    metrics = json.loads((d / "run" / "metrics.json").read_text(encoding="utf-8"))
    assert_ok(invoke("run", seq_dir, "--out", tmp_path / "ref", "--initial-poses", "input"))
    ref = json.loads((tmp_path / "ref" / "metrics.json").read_text(encoding="utf-8"))
    assert metrics["summary"]["mean_iou"] == pytest.approx(ref["summary"]["mean_iou"], abs=1e-6)

    # a second demo into the same folder replaces the first
    (d / "run" / "stale.txt").write_text("from before\n", encoding="utf-8")
    result = invoke("demo", "--out", d, "--frames", FRAMES, "--objects", OBJECTS)
    assert_ok(result)
    assert not (d / "run" / "stale.txt").exists()
    assert read_sequence(d / "sequence") == seq
    assert sorted(p.name for p in d.iterdir()) == sorted([cli.DEMO_MARKER, "run", "sequence"])
    read_map(d / "run")
