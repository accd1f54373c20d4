"""``spdslam check``: the consistency of a sequence's inputs (``evaluation.check_sequence``).

A synthetic room's boxes are the projections of its ground-truth objects plus noise, so the
check must find them consistent; each corruption a user's data can carry (a time offset
between detections and poses, boxes stored as [x, y, w, h], a camera-frame rotation of the
poses) must be found and named. On fr2_desk (when ../shared is here) it must find what
docs/sequences.md reports: the 0.92° camera-frame rotation between ORB-SLAM2 and the motion
capture, and the can boxed as a bottle.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_cli_error, assert_cli_ok, cli_invoke
from scipy.spatial.transform import Rotation

from spdslam.evaluation import box_iou, check_sequence, interpolate_poses
from spdslam.geometry import Camera, distort_points, undistort_points
from spdslam.geometry import box_iou as geometry_box_iou
from spdslam.geometry.se3 import interpolate_tum
from spdslam.io import write_sequence
from spdslam.synthetic import make_room_sequence

FR2 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tum_fr2_desk"


@pytest.fixture(scope="module")
def room():
    seq = make_room_sequence(3, frames=60, objects=4, drift=0.0, box_noise_px=1.0)
    # the check compares the boxes with the ground truth's poses too: give the room its own
    gt = np.column_stack([seq.timestamps, seq.poses_tum])
    return dataclasses.replace(seq, groundtruth_tum=gt)


def test_interpolated_poses_are_exact_at_samples_and_refused_across_gaps():
    t = np.array([0.0, 1.0, 2.0, 5.0])
    q = Rotation.from_rotvec([[0, 0, 0], [0, 0, 0.2], [0, 0, 0.4], [0, 0, 0.4]]).as_quat()
    P = np.c_[t, np.c_[t, np.zeros(4), np.zeros(4)], q]
    rows, ok = interpolate_poses(P, [0.0, 0.5, 2.0, 3.5, -1.0, 6.0], max_gap=1.5)
    assert ok.tolist() == [True, True, True, False, False, False]
    np.testing.assert_allclose(rows[1, :3], [0.5, 0, 0], atol=1e-12)
    np.testing.assert_allclose(Rotation.from_quat(rows[1, 3:]).as_rotvec(), [0, 0, 0.1], atol=1e-12)
    np.testing.assert_allclose(rows[2, :3], [2.0, 0, 0], atol=1e-12)
    # the interpolation itself (geometry.se3.interpolate_tum): rows in any order, each sample
    # time gives its sample exactly, times outside give the end samples (no extrapolation)
    ends = interpolate_tum(P[::-1], [-1.0, 0.0, 1.0, 5.0, 6.0])
    np.testing.assert_array_equal(ends[:, :3], P[[0, 0, 1, 3, 3], 1:4])
    np.testing.assert_array_equal(ends[:, 3:], Rotation.from_quat(P[[0, 0, 1, 3, 3], 4:]).as_quat())


def test_box_iou_takes_the_same_numbers_on_numpys_direct_path():
    import jax.numpy as jnp

    rng = np.random.default_rng(3)
    a = np.sort(rng.uniform(0, 100, (50, 2, 2)), axis=1).reshape(50, 4)[:, [0, 2, 1, 3]]
    b = np.sort(rng.uniform(0, 100, (50, 2, 2)), axis=1).reshape(50, 4)[:, [0, 2, 1, 3]]
    b[0] = np.nan
    b[1] = [5.0, 5.0, 5.0, 9.0]  # empty
    b[2] = [9.0, 9.0, 1.0, 1.0]  # inverted
    direct = geometry_box_iou(a[:, None], b[None])  # float64 NumPy: the direct path
    generic = np.asarray(geometry_box_iou(jnp.asarray(a)[:, None], jnp.asarray(b)[None]))
    np.testing.assert_array_equal(direct, generic)
    np.testing.assert_array_equal(direct, geometry_box_iou(a[:, None].tolist(), b[None].tolist()))


def test_box_iou_and_the_distortion_round_trip():
    a = np.array([[0, 0, 10, 10], [0, 0, 10, 10]], float)
    b = np.array([[0, 0, 10, 10], [5, 0, 15, 10]], float)
    np.testing.assert_allclose(box_iou(a, b), [1.0, 1 / 3])
    assert box_iou is geometry_box_iou  # one IoU for the check, the screen and the association
    # pairwise by broadcasting; a zero-width or inverted box overlaps nothing, itself included
    odd = np.array([[0, 0, 10, 10], [5, 0, 15, 10], [3, 3, 3, 9], [8, 8, 2, 2]], float)
    np.testing.assert_allclose(box_iou(odd[:, None], odd[None]),
                               [[1, 1 / 3, 0, 0], [1 / 3, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]])
    cam = Camera(500, 500, 320, 240, 640, 480)
    k = (0.23, -0.78, -0.003, -0.0001, 0.92)
    uv = np.array([[10.0, 20.0], [320.0, 240.0], [600.0, 450.0]])
    np.testing.assert_allclose(undistort_points(distort_points(uv, cam, k), cam, k), uv, atol=1e-6)


def test_a_consistent_sequence_is_found_consistent(room):
    r = check_sequence(room)
    assert r["objects"] == "ground-truth objects"
    assert [s["reference"] for s in r["sources"]] == ["given poses"]  # the same poses: one source
    s = r["sources"][0]
    o = s["overall"]
    assert o["pairs"] > 0.9 * len(room.detections)
    assert o["iou"] > 0.9 and max(abs(v) for v in o["center_offset_px"]) < 1.0
    assert all(abs(v - 1) < 0.05 for v in o["size_ratio"])
    assert s["time_offset"]["best_s"] == 0.0
    conv = s["box_convention"]
    assert max(conv, key=conv.get) == "x1 y1 x2 y2"
    assert not any("time offset" in f and "no time offset" not in f for f in r["findings"])
    assert not any("systematic image offset" in f for f in r["findings"])


def test_a_time_offset_is_found(room):
    late = dataclasses.replace(room, detections=[dataclasses.replace(d, timestamp=d.timestamp - 0.2)
                                                 for d in room.detections])
    r = check_sequence(late, offsets=np.round(np.arange(-0.3, 0.301, 0.05), 3))
    t = r["sources"][0]["time_offset"]
    assert t["best_s"] == pytest.approx(0.2)
    assert any("agree best with the poses +0.20 s later" in f for f in r["findings"]), r["findings"]


def test_boxes_stored_as_xywh_are_named(room):
    def xywh(d):
        b = d.box
        return dataclasses.replace(d, box=np.array([b[0], b[1], b[2] - b[0], b[3] - b[1]]))

    # read as corners, the boxes no longer overlap their objects at IoU 0.3: pair loosely
    r = check_sequence(dataclasses.replace(room, detections=[xywh(d) for d in room.detections]), min_iou=0.01)
    conv = r["sources"][0]["box_convention"]
    assert max(conv, key=conv.get) == "x y w h"
    assert any("read as [x y w h]" in f for f in r["findings"]), r["findings"]


def test_a_camera_frame_rotation_of_the_poses_is_measured(room):
    rot = Rotation.from_rotvec(np.radians([1.0, 0.0, 0.0]))
    q = (Rotation.from_quat(room.poses_tum[:, 3:7]) * rot).as_quat()
    tilted = dataclasses.replace(room, poses_tum=np.c_[room.poses_tum[:, :3], q])
    r = check_sequence(tilted)
    assert [s["reference"] for s in r["sources"]] == ["given poses", "ground-truth poses"]
    off = r["camera_frame_offset"]
    assert off["angle_deg"] == pytest.approx(1.0, abs=0.01)
    given, truth = r["sources"]
    assert truth["overall"]["iou"] > given["overall"]["iou"]
    assert any("constant 1.00° in the camera frame" in f for f in r["findings"])


def test_a_map_is_checked_against_its_boxes(room):
    from spdslam.io import MapObject

    objs = [MapObject(g.id, g.label, _ellipsoid(g)) for g in room.objects_gt]
    r = check_sequence(dataclasses.replace(room, objects_gt=None), objs)
    assert r["objects"] == "mapped objects" and r["sources"][0]["overall"]["iou"] > 0.9
    with pytest.raises(ValueError, match="nothing to project"):
        check_sequence(dataclasses.replace(room, objects_gt=None))


def _ellipsoid(g):
    from spdslam.geometry import Ellipsoid

    c = g.cuboid
    return Ellipsoid.from_axes(c.rotation, c.center, c.half_extents)


def test_the_check_command_prints_and_writes_json(room, tmp_path):
    seq_dir = write_sequence(room, tmp_path / "seq")
    res = cli_invoke("check", seq_dir, "--json", tmp_path / "check.json")
    assert_cli_ok(res)
    assert "Findings:" in res.stdout and "given poses" in res.stdout
    report = json.loads((tmp_path / "check.json").read_text())
    assert report["sources"][0]["overall"]["iou"] > 0.9
    assert_cli_error(cli_invoke("check", seq_dir, "--min-iou", "1.5"), "--min-iou")
    assert_cli_error(cli_invoke("check", tmp_path / "nowhere"), "nowhere")
    assert_cli_error(cli_invoke("check", seq_dir, "--json", seq_dir / "c.json"), "--json", "inside the input")


@pytest.mark.skipif(not FR2.is_dir(), reason="../shared/data/tum_fr2_desk is not on this machine")
def test_fr2_desk_inputs_agree_but_orb_slam2_turns_the_camera():
    from spdslam.io import read_measured_boxes, read_sequence

    seq = read_sequence(FR2)
    raw, dist = read_measured_boxes(FR2)
    r = check_sequence(seq, raw=raw, distortion=dist)
    given, truth = r["sources"]
    assert truth["overall"]["iou"] > 0.65 and truth["time_offset"]["best_s"] == 0.0
    assert max(abs(v) for v in truth["overall"]["center_offset_px"]) < 3.5
    assert given["overall"]["center_offset_px"][1] > 5.0  # ORB-SLAM2's poses: 7 px down
    assert r["camera_frame_offset"]["angle_deg"] == pytest.approx(0.92, abs=0.05)
    can = next(o for o in truth["objects"] if o["label"] == "cup")
    assert can["pairs"] == 0 and max(can["other_labels"], key=can["other_labels"].get) == "bottle"
    d = truth["distortion"]
    assert d["undistorted_vs_pinhole"] > d["measured_vs_pinhole"]
