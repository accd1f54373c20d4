"""The rerun recording of a run: ``experiments.write_recording``, ``spdslam run --rerun`` and
``spdslam view``.

Every recording is read back from its ``.rrd`` file (``rerun.chunk.RrdReader``) and checked
entity by entity. One small demo (30 frames, 2 objects) pays the JAX compilation once; the
geometric checks use the generator's own objects and poses (no mapping at all).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_cli_error as assert_error
from conftest import assert_cli_ok as assert_ok
from conftest import cli_invoke as invoke
from conftest import cli_runner

rr = pytest.importorskip("rerun")

from spdslam.experiments import write_recording
from spdslam.geometry import Ellipsoid
from spdslam.geometry.se3 import quat_to_matrix
from spdslam.io import MapObject, read_map, read_sequence, read_tum, write_sequence
from spdslam.synthetic import make_room_sequence

runner = cli_runner()
FRAMES, OBJECTS = 30, 2


# --------------------------------------------------------------------------- helpers


class Recording:
    """An .rrd read back: per entity path, its rows (component values, the frame index)."""

    def __init__(self, path):
        from rerun.chunk import RrdReader

        reader = RrdReader(path)
        assert len(reader.recordings()) == 1
        self.rows: dict[str, list[dict]] = {}
        for chunk in reader.store().stream().collect().stream():
            batch = chunk.to_record_batch().to_pydict()
            n = chunk.num_rows
            self.rows.setdefault(chunk.entity_path, []).extend(
                {k: v[i] for k, v in batch.items()} for i in range(n))
        for rows in self.rows.values():
            rows.sort(key=lambda r: r.get("frame") if r.get("frame") is not None else -1)

    @property
    def entities(self) -> set[str]:
        return set(self.rows)

    def static(self, entity: str, component: str) -> np.ndarray:
        rows = self.rows[entity]
        assert len(rows) == 1, (entity, len(rows))
        return np.asarray(rows[0][component], dtype=object if "labels" in component else float)

    def frames(self, entity: str) -> list[int]:
        return [r["frame"] for r in self.rows[entity]]

    def per_frame(self, entity: str, component: str) -> dict[int, list]:
        return {r["frame"]: r[component] or [] for r in self.rows[entity]}


def gt_objects(seq):
    """The generator's objects as a map (P = R diag(h²) Rᵀ of each ground-truth cuboid)."""
    out = []
    for g in seq.objects_gt:
        R, h = g.cuboid.rotation, g.cuboid.half_extents
        out.append(MapObject(g.id, g.label, Ellipsoid((R * h**2) @ R.T, g.cuboid.center)))
    return out


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A small ``spdslam demo``: DEMO/sequence and DEMO/run."""
    d = tmp_path_factory.mktemp("rerun") / "demo"
    assert_ok(invoke("demo", "--out", d, "--frames", FRAMES, "--objects", OBJECTS))
    return d


@pytest.fixture(scope="module")
def clean_seq():
    """Noise- and drift-free: every detection box is the projected box of its object."""
    return make_room_sequence(1, frames=12, objects=3, box_noise_px=0.0, drift=0.0)


# --------------------------------------------------------------------------- write_recording


def test_recording_geometry_matches_the_map_poses_and_detections(tmp_path, clean_seq):
    seq = clean_seq
    objs = gt_objects(seq)
    traj = seq.groundtruth_tum
    path = write_recording(tmp_path / "sub" / "r.rrd", objs, traj, seq)
    assert path == tmp_path / "sub" / "r.rrd" and path.is_file()
    assert sorted(p.name for p in path.parent.iterdir()) == ["r.rrd"]  # no temporary left
    rec = Recording(path)

    # ellipsoids: centre, half-axes and rotation give back P
    c = rec.static("/world/map/ellipsoids", "Ellipsoids3D:centers")
    s = rec.static("/world/map/ellipsoids", "Ellipsoids3D:half_sizes")
    q = rec.static("/world/map/ellipsoids", "Ellipsoids3D:quaternions")
    labels = rec.static("/world/map/ellipsoids", "Ellipsoids3D:labels")
    assert len(c) == len(objs) == 3
    assert list(labels) == [f"{o.label} {o.id}" for o in objs]
    for k, o in enumerate(objs):
        R = quat_to_matrix(q[k])
        np.testing.assert_allclose((R * s[k] ** 2) @ R.T, o.ellipsoid.P, atol=1e-5)
        np.testing.assert_allclose(c[k], o.ellipsoid.center, atol=1e-5)
        assert np.all(np.diff(s[k]) <= 1e-6)  # radii descending

    # ground truth: one box per object, the cuboid's own centre and half-extents
    np.testing.assert_allclose(rec.static("/world/ground_truth/cuboids", "Boxes3D:half_sizes"),
                               [g.cuboid.half_extents for g in seq.objects_gt], atol=1e-6)

    # camera: one pose per frame, T_wc (translation = the centre, quaternion = R_wc)
    assert rec.frames("/world/camera") == list(range(len(seq)))
    for r, row in enumerate(rec.rows["/world/camera"]):
        np.testing.assert_allclose(row["Transform3D:translation"][0], traj[r, 1:4], atol=1e-5)
        R = quat_to_matrix(row["Transform3D:quaternion"][0])
        np.testing.assert_allclose(R, quat_to_matrix(traj[r, 4:8]), atol=1e-5)
    pin = rec.rows["/world/camera/image"][0]
    np.testing.assert_allclose(pin["Pinhole:resolution"][0], [seq.camera.width, seq.camera.height])
    # rerun stores the 3×3 column-major
    K = np.asarray(pin["Pinhole:image_from_camera"][0]).reshape(3, 3).T
    np.testing.assert_allclose(K, seq.camera.K)

    # each detection's box is the bounding box of its object's projected outline
    strips = rec.per_frame("/world/camera/image/ellipses", "LineStrips2D:strips")
    strip_labels = rec.per_frame("/world/camera/image/ellipses", "LineStrips2D:labels")
    centers = rec.per_frame("/world/camera/image/detections", "Boxes2D:centers")
    assert sum(len(v) for v in centers.values()) == len(seq.detections) > 0
    n_checked = 0
    for d in seq.detections:
        label = f"{objs[d.instance].label} {objs[d.instance].id}"
        assert label in strip_labels[d.frame], (d.frame, label)
        pts = np.asarray(strips[d.frame][strip_labels[d.frame].index(label)])
        assert np.allclose(pts[0], pts[-1])  # closed
        np.testing.assert_allclose(np.r_[pts.min(0), pts.max(0)], d.box, atol=0.5)
        n_checked += 1
    assert n_checked == len(seq.detections)
    # detection boxes as logged: centre of [x1, y1, x2, y2]
    for f, v in centers.items():
        want = [0.5 * (d.box[:2] + d.box[2:]) for d in seq.detections_at(f)]
        np.testing.assert_allclose(np.reshape(v, (-1, 2)), np.reshape(want, (-1, 2)), atol=1e-3)


def test_recording_images_and_a_drifted_input_trajectory(tmp_path, clean_seq):
    from PIL import Image

    folder = tmp_path / "images"
    folder.mkdir()
    with_image = range(0, len(clean_seq), 2)  # every other frame
    images = {}
    for f in with_image:
        p = folder / f"{f}.png"
        Image.new("RGB", (int(clean_seq.camera.width), int(clean_seq.camera.height)), (f * 10, 0, 0)).save(p)
        images[float(clean_seq.timestamps[f])] = p
    seq = dataclasses.replace(clean_seq, images=images)
    inp = np.column_stack([seq.timestamps, seq.poses_tum])
    inp[:, 1] += 0.5  # an input trajectory apart from the optimised one
    path = write_recording(tmp_path / "r.rrd", gt_objects(seq), seq.groundtruth_tum, seq,
                           input_trajectory=inp)
    rec = Recording(path)
    rgb = rec.rows["/world/camera/image/rgb"]
    logged = [r["frame"] for r in rgb if r.get("EncodedImage:blob")]
    cleared = [r["frame"] for r in rgb if r.get("Clear:is_recursive") is not None]
    assert logged == list(with_image)
    assert cleared == [f for f in range(len(seq)) if f not in with_image]
    blob = rgb[0]["EncodedImage:blob"][0]
    assert bytes(blob[:8]) == b"\x89PNG\r\n\x1a\n"
    strip = rec.static("/world/trajectory/input", "LineStrips3D:strips")
    np.testing.assert_allclose(strip[0], inp[:, 1:4], atol=1e-5)

    # without images: the same frames, no rgb entity
    path2 = write_recording(tmp_path / "r2.rrd", gt_objects(seq), seq.groundtruth_tum, seq, images=False)
    assert "/world/camera/image/rgb" not in Recording(path2).entities


def test_ellipsoids_of_any_orientation(tmp_path, gen, clean_seq):
    """Centre, half-axes and quaternion (x, y, z, w) of each logged ellipsoid give back P."""
    objs = [MapObject(i, "thing", Ellipsoid(gen.spd(), gen.rng.normal(size=3))) for i in range(6)]
    rec = Recording(write_recording(tmp_path / "r.rrd", objs, clean_seq.groundtruth_tum))
    s = rec.static("/world/map/ellipsoids", "Ellipsoids3D:half_sizes")
    q = rec.static("/world/map/ellipsoids", "Ellipsoids3D:quaternions")
    for k, o in enumerate(objs):
        R = quat_to_matrix(q[k])
        np.testing.assert_allclose((R * s[k] ** 2) @ R.T, o.ellipsoid.P, atol=1e-5 * np.abs(o.ellipsoid.P).max())


def test_outlines_projected_in_blocks_are_the_same(tmp_path, monkeypatch, clean_seq):
    import spdslam.experiments._recording as module

    objs, traj = gt_objects(clean_seq), clean_seq.groundtruth_tum
    whole = Recording(write_recording(tmp_path / "a.rrd", objs, traj, clean_seq))
    monkeypatch.setattr(module, "_BLOCK", 5)  # 12 frames: blocks of 5, 5 and 2
    blocks = Recording(write_recording(tmp_path / "b.rrd", objs, traj, clean_seq))
    key = ("/world/camera/image/ellipses", "LineStrips2D:strips")
    a, b = whole.per_frame(*key), blocks.per_frame(*key)
    assert sorted(a) == sorted(b) == list(range(len(clean_seq)))
    assert sum(len(v) for v in a.values()) > len(clean_seq)
    for f in a:
        np.testing.assert_allclose(np.asarray(a[f], float), np.asarray(b[f], float))


def test_a_keyframe_trajectory_keeps_the_sequence_frame_numbers(tmp_path, clean_seq):
    traj = clean_seq.groundtruth_tum[::3]  # as a run with --keyframes 3
    rec = Recording(write_recording(tmp_path / "r.rrd", gt_objects(clean_seq), traj, clean_seq))
    kept = list(range(0, len(clean_seq), 3))
    assert rec.frames("/world/camera") == kept
    times = [r["time"] for r in rec.rows["/world/camera"]]
    np.testing.assert_allclose([t.total_seconds() for t in times], traj[:, 0], atol=1e-6)
    boxes = rec.per_frame("/world/camera/image/detections", "Boxes2D:centers")
    assert sorted(boxes) == kept
    assert [len(boxes[f]) for f in kept] == [len(clean_seq.detections_at(f)) for f in kept]


def test_recording_without_a_sequence(tmp_path, clean_seq):
    traj = clean_seq.groundtruth_tum[:5]
    rec = Recording(write_recording(tmp_path / "r.rrd", gt_objects(clean_seq), traj))
    assert rec.frames("/world/camera") == list(range(5))
    assert len(rec.static("/world/trajectory/optimized", "LineStrips3D:strips")[0]) == 5
    image_paths = {e for e in rec.entities if e.startswith("/world/camera/image")}
    assert not image_paths and "/world/ground_truth/cuboids" not in rec.entities
    assert "/world/trajectory/input" not in rec.entities


def test_recording_of_another_sequence_is_refused(tmp_path, clean_seq):
    traj = clean_seq.groundtruth_tum.copy()
    traj[:, 0] += 100.0
    with pytest.raises(ValueError, match="not a frame of the sequence"):
        write_recording(tmp_path / "r.rrd", gt_objects(clean_seq), traj, clean_seq)
    assert list(tmp_path.iterdir()) == []


def test_missing_rerun_is_one_clear_error(tmp_path, monkeypatch, clean_seq):
    monkeypatch.setitem(sys.modules, "rerun", None)
    monkeypatch.setitem(sys.modules, "rerun.blueprint", None)
    with pytest.raises(ImportError, match=r"spdslam\[viewer\]"):
        write_recording(tmp_path / "r.rrd", [], clean_seq.groundtruth_tum, clean_seq)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- CLI


def test_view_of_the_demo_run(demo):
    run = demo / "run"
    result = invoke("view", run)
    assert_ok(result)
    path = run / "recording.rrd"
    assert path.is_file() and "rerun" in result.stdout
    rec = Recording(path)
    m, objects = read_map(run)
    poses = read_tum(run / "trajectory.txt", "trajectory.txt")
    seq = read_sequence(demo / "sequence")  # found beside the demo's run without --sequence
    assert len(objects) == OBJECTS
    assert len(rec.static("/world/map/ellipsoids", "Ellipsoids3D:centers")) == len(objects)
    np.testing.assert_allclose(rec.static("/world/map/ellipsoids", "Ellipsoids3D:centers"),
                               [np.asarray(o.ellipsoid.center) for o in objects], atol=1e-5)
    opt = rec.static("/world/trajectory/optimized", "LineStrips3D:strips")[0]
    np.testing.assert_allclose(opt, poses[:, 1:4], atol=1e-5)
    assert len(rec.static("/world/trajectory/input", "LineStrips3D:strips")[0]) == FRAMES
    assert rec.frames("/world/camera") == list(range(FRAMES))
    assert len(rec.static("/world/ground_truth/cuboids", "Boxes3D:centers")) == len(seq.objects_gt)
    n_boxes = sum(len(v) for v in rec.per_frame("/world/camera/image/detections", "Boxes2D:centers").values())
    assert n_boxes == len(seq.detections)
    # the ground truth is drawn in the map's frame: moved by to_groundtruth⁻¹
    T = np.asarray(m["to_groundtruth"])
    gt_c = rec.static("/world/ground_truth/cuboids", "Boxes3D:centers")
    want = [T[:3, :3].T @ (g.cuboid.center - T[:3, 3]) for g in seq.objects_gt]
    np.testing.assert_allclose(gt_c, want, atol=1e-5)


def test_view_without_a_sequence_and_with_out(demo, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(demo / "run", run, ignore=shutil.ignore_patterns("*.rrd"))  # no demo marker beside it
    m = json.loads((run / "map.json").read_text(encoding="utf-8"))
    assert Path(m["sequence"]) == (demo / "sequence").resolve()  # spdslam demo records it
    # the sequence map.json records is found without --sequence
    result = invoke("view", run, "--out", tmp_path / "found.rrd")
    assert_ok(result)
    assert "frommap.json" in "".join(result.stdout.split())  # rich wraps long lines
    assert "/world/camera/image/detections" in Recording(tmp_path / "found.rrd").entities
    # recorded but gone: said on stderr, and the recording has no camera image view
    m["sequence"] = str(tmp_path / "moved-away")
    (run / "map.json").write_text(json.dumps(m), encoding="utf-8")
    target = tmp_path / "deep" / "view.rrd"
    result = invoke("view", run, "--out", target)
    assert_ok(result)
    said = "".join(result.stderr.split())  # rich wraps long lines, paths included
    assert "".join(f"{tmp_path / 'moved-away'}, is not there".split()) in said
    rec = Recording(target)
    assert rec.frames("/world/camera") == list(range(FRAMES))
    assert not any(e.startswith("/world/camera/image") for e in rec.entities)
    assert not (run / "recording.rrd").exists()
    # and with --sequence: the sequence's detections and ground truth
    assert_ok(invoke("view", run, "--sequence", demo / "sequence"))
    assert "/world/camera/image/detections" in Recording(run / "recording.rrd").entities


def test_run_with_rerun(demo, tmp_path):
    out, target = tmp_path / "out", tmp_path / "rec" / "run.rrd"
    result = invoke("run", demo / "sequence", "--out", out, "--rerun", target)
    assert_ok(result)
    rec = Recording(target)
    _, objects = read_map(out)
    np.testing.assert_allclose(rec.static("/world/map/ellipsoids", "Ellipsoids3D:centers"),
                               [np.asarray(o.ellipsoid.center) for o in objects], atol=1e-5)
    assert rec.frames("/world/camera") == list(range(FRAMES))
    assert len(rec.static("/world/ground_truth/cuboids", "Boxes3D:centers")) == OBJECTS


def test_run_rerun_refused_before_the_run(demo, tmp_path, monkeypatch):
    result = invoke("run", demo / "sequence", "--out", tmp_path / "out", "--rerun", tmp_path)
    assert_error(result, "--rerun", "is a folder")
    monkeypatch.setitem(sys.modules, "rerun", None)
    result = invoke("run", demo / "sequence", "--out", tmp_path / "out", "--rerun", tmp_path / "r.rrd")
    assert_error(result, "spdslam[viewer]")
    assert not (tmp_path / "out").exists()  # refused before anything ran


def test_view_errors(demo, tmp_path, monkeypatch):
    assert_error(invoke("view", tmp_path / "nothing"), "nothing", "no such file or folder")
    run = tmp_path / "run"
    shutil.copytree(demo / "run", run, ignore=shutil.ignore_patterns("*.rrd"))
    (run / "map.json").write_text('{"method": "multi-spd", "objects": [', encoding="utf-8")
    assert_error(invoke("view", run), "map.json", "expected JSON")
    assert not (run / "recording.rrd").exists()
    shutil.copy(demo / "run" / "map.json", run / "map.json")
    m = json.loads((run / "map.json").read_text(encoding="utf-8"))
    m["objects"][0]["P"] = [[1, 0], [0, 1]]
    (run / "map.json").write_text(json.dumps(m), encoding="utf-8")
    assert_error(invoke("view", run), "map.json", "expected object 0")
    shutil.copy(demo / "run" / "map.json", run / "map.json")
    (run / "trajectory.txt").unlink()
    assert_error(invoke("view", run), "trajectory.txt", "no such file")
    shutil.copy(demo / "run" / "trajectory.txt", run / "trajectory.txt")
    other = tmp_path / "other"  # a sequence the run was not made from
    write_sequence(make_room_sequence(0, frames=5, objects=1), other)  # frames 0-4 of 30
    assert_error(invoke("view", run, "--sequence", other), "not a frame of the sequence")
    monkeypatch.setitem(sys.modules, "rerun", None)
    assert_error(invoke("view", run), "spdslam[viewer]")
    assert not any(p.suffix in (".rrd", ".tmp") for p in run.iterdir())
