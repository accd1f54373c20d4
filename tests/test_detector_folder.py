"""A detector's output folder (issue 38): YOLO label files or COCO detection results beside an
OpenCV, ROS camera_info or Kalibr calibration, a TUM trajectory and the images' times.

Each test writes a folder as the tools write it (Ultralytics' ``save_txt``/``save_conf``
labels, COCO results with their images, ROS/Kalibr YAML) from a sequence, and reads it back:
the same sequence (times, poses, boxes to 1e-9 px, labels, scores) as the source."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_cli_error, assert_cli_ok, cli_invoke, write_detector_folder

from spdslam.io import (
    SequenceFormatError,
    find_format,
    read_camera_calibration,
    read_sequence,
)
from spdslam.synthetic import make_room_sequence

FR2 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tum_fr2_desk"
DATA = Path(__file__).resolve().parent / "data" / "detector"


def assert_same_sequence(a, b, atol=1e-9, time_atol=0.0):
    np.testing.assert_array_equal(a.timestamps, b.timestamps)
    np.testing.assert_allclose([d.timestamp for d in a.detections], [d.timestamp for d in b.detections],
                               rtol=0, atol=time_atol)
    np.testing.assert_allclose(a.poses_tum, b.poses_tum, rtol=0, atol=1e-15)
    assert (a.camera.fx, a.camera.fy, a.camera.cx, a.camera.cy, a.camera.width, a.camera.height) == \
        (b.camera.fx, b.camera.fy, b.camera.cx, b.camera.cy, b.camera.width, b.camera.height)
    assert len(a.detections) == len(b.detections)
    np.testing.assert_array_equal([d.frame for d in a.detections], [d.frame for d in b.detections])
    assert [d.label for d in a.detections] == [d.label for d in b.detections]
    np.testing.assert_allclose([d.score for d in a.detections], [d.score for d in b.detections], rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.stack([d.box for d in a.detections]), np.stack([d.box for d in b.detections]),
                               rtol=0, atol=atol)


@pytest.mark.parametrize("detector,calibration,times", [
    ("yolo", "ros", "rgb"), ("coco", "kalibr", "rgb"), ("yolo", "opencv", "euroc"), ("coco", "ros", "names")])
def test_a_detector_folder_reads_as_the_sequence_it_was_written_from(tmp_path, detector, calibration, times):
    seq = make_room_sequence(0, frames=30, objects=4)
    folder = write_detector_folder(seq, tmp_path / "seq", detector=detector, calibration=calibration, times=times)
    assert find_format(folder).name == "detector"
    back = read_sequence(folder)
    # EuRoC's nanosecond times: the same frames, a detection's time within a microsecond
    assert_same_sequence(seq, back, time_atol=1e-6 if times == "euroc" else 0.0)


@pytest.mark.skipif(not FR2.is_dir(), reason="../shared/data/tum_fr2_desk is not on this machine")
@pytest.mark.parametrize("detector", ["yolo", "coco"])
def test_fr2_desk_as_a_detector_folder_is_the_oaslam_sequence(tmp_path, detector):
    """fr2_desk's measured (distorted) YOLOv5 boxes written as YOLO label files or COCO
    results beside a ROS camera_info with its lens distortion and a TUM rgb.txt: read back and
    undistorted, the same sequence as the OA-SLAM layout gives, boxes to 1e-9 px (so the
    same map: the run is a function of the sequence). Kalibr's radtan has no k3, which
    fr2_desk's calibration uses: the Kalibr dialect is checked on the demo room."""
    from spdslam.io import read_measured_boxes

    seq = read_sequence(FR2)
    raw, dist = read_measured_boxes(FR2)
    folder = write_detector_folder(raw, tmp_path / "fr2", dist=dist, detector=detector, calibration="ros")
    back = read_sequence(folder)
    assert_same_sequence(seq, back)


@pytest.fixture(scope="module")
def yolo_room(tmp_path_factory):
    seq = make_room_sequence(0, frames=12, objects=2)
    return seq, write_detector_folder(seq, tmp_path_factory.mktemp("det") / "yolo", detector="yolo")


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def _first_label(folder: Path) -> Path:
    return sorted((folder / "labels").glob("*.txt"))[0]


@pytest.mark.parametrize("case,edit,fragments", [
    ("normalised above 1", lambda f: _first_label(f).write_text("0 1.2 0.5 0.1 0.1 0.9\n"),
     ["img_00000.txt:1", "normalised"]),
    ("a COCO id where YOLO's are expected", lambda f: (f / "data.yaml").unlink() or _first_label(f).write_text(
        "85 0.5 0.5 0.1 0.1 0.9\n"), ["img_00000.txt:1", "0…79", "COCO category id"]),
    ("a bad line", lambda f: _first_label(f).write_text("0 0.5 0.5 0.1\n"), ["img_00000.txt:1", "class cx cy w h"]),
    ("an image missing from rgb.txt", lambda f: (f / "labels" / "img_99999.txt").write_text("0 0.5 0.5 0.1 0.1\n"),
     ["img_99999.txt", "listed in rgb.txt"]),
    ("no times", lambda f: (f / "rgb.txt").unlink(), ["img_0000", "named by its timestamp"]),
    ("a calibration without a field", lambda f: (f / "camera.yaml").write_text(
        (f / "camera.yaml").read_text().replace("image_height: 480\n", "")), ["camera.yaml", "image_height"]),
    ("a fisheye lens with five coefficients", lambda f: (f / "camera.yaml").write_text(
        (f / "camera.yaml").read_text().replace("plumb_bob", "equidistant")),
     ["camera.yaml:", "4 numbers for distortion_coefficients"]),
    ("names with a gap", lambda f: (f / "data.yaml").write_text("names:\n  0: chair\n  2: cup\n"),
     ["data.yaml", "ids 0"]),
])
def test_a_bad_detector_folder_is_refused_in_one_line(yolo_room, tmp_path, case, edit, fragments):
    """Each refused by the reader naming the file (and line), and by ``spdslam run`` in one
    line with exit 2 and nothing written."""
    _, src = yolo_room
    folder = _copy(src, tmp_path / "bad")
    if not (folder / "data.yaml").exists():
        (folder / "data.yaml").write_text("names: [" + ", ".join(sorted({"chair", "cup", "tv", "plant",
                                                                           "book", "bottle", "monitor"})) + "]\n")
    edit(folder)
    with pytest.raises(SequenceFormatError) as e:
        read_sequence(folder)
    for f in fragments:
        assert f in str(e.value), (case, str(e.value))
    out = tmp_path / "out"
    assert_cli_error(cli_invoke("run", folder, "--out", out), fragments[0])
    assert not out.exists()


def test_coco_ids_and_yolo_indices_are_never_mixed_up(tmp_path):
    """COCO results with id 0 (a YOLO index) or an id COCO does not use are refused; COCO's
    id 62 is a chair, YOLO's index 56 is the same chair."""
    from dataclasses import replace

    seq = make_room_sequence(0, frames=12, objects=2)
    seq = replace(seq, detections=[replace(d, label="chair") for d in seq.detections])
    folder = write_detector_folder(seq, tmp_path / "coco", detector="coco", calibration="kalibr")
    res = json.loads((folder / "coco_results.json").read_text())
    assert {r["category_id"] for r in res} == {62} and "categories" not in (folder / "coco_images.json").read_text()
    assert {d.label for d in read_sequence(folder).detections} == {"chair"}
    yolo = write_detector_folder(seq, tmp_path / "yolo", detector="yolo")
    assert {ln.split()[0] for p in (yolo / "labels").glob("*.txt") for ln in p.read_text().splitlines()} == {"56"}
    assert {d.label for d in read_sequence(yolo).detections} == {"chair"}
    for bad, fragment in ((0, "0 is a YOLO index"), (12, "category_id")):
        broken = _copy(folder, tmp_path / f"bad{bad}")
        res[0]["category_id"] = bad
        (broken / "coco_results.json").write_text(json.dumps(res))
        with pytest.raises(SequenceFormatError, match=fragment):
            read_sequence(broken)


def test_calibration_dialects_agree(tmp_path):
    """One camera written as OpenCV, ROS camera_info and Kalibr reads the same in each."""
    from conftest import _calibration

    from spdslam import Camera

    cam, dist = Camera(517.3, 516.5, 318.6, 255.3, 640.0, 480.0), np.array([0.26, -0.95, -0.005, 0.002, 0.0])
    got = []
    for dialect in ("opencv", "ros", "kalibr"):
        p = tmp_path / f"{dialect}.yaml"
        p.write_text(_calibration(cam, dist, dialect))
        got.append(read_camera_calibration(p))
    for c, d in got:
        assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
        np.testing.assert_array_equal(d, dist)
    bad = tmp_path / "other.yaml"
    bad.write_text("fx: 500\n")
    with pytest.raises(SequenceFormatError, match="OpenCV .* ROS camera_info .* Kalibr"):
        read_camera_calibration(bad)


def test_import_and_run_read_a_detector_folder(tmp_path):
    """``spdslam import`` writes the canonical folder of the same sequence; ``spdslam run``
    maps the folder directly; a detector's class the class table does not know ("gizmo", from
    data.yaml) is mapped under its own name without a size prior, and the run says so once."""
    from dataclasses import replace

    seq = make_room_sequence(0, frames=30, objects=2)
    first = seq.detections[0].label
    seq = replace(seq, detections=[replace(d, label="gizmo") if d.label == first else d for d in seq.detections])
    folder = write_detector_folder(seq, tmp_path / "yolo")
    assert_cli_ok(cli_invoke("import", folder, tmp_path / "canon"))
    assert_same_sequence(seq, read_sequence(tmp_path / "canon"))
    assert_cli_ok(cli_invoke("run", folder, "--out", tmp_path / "run"))
    doc = json.loads((tmp_path / "run" / "map.json").read_text())
    said = [n for n in doc["notes"] if "without a class prior" in n]
    assert len(said) == 1 and "gizmo" in said[0]
    assert any(o["label"] == "gizmo" for o in doc["objects"])


def _fisheye_forward(uv, cam, k):
    """The equidistant model written out independently: θ = atan r, θ_d = θ(1 + Σ kᵢθ²ⁱ)."""
    x, y = (uv[..., 0] - cam.cx) / cam.fx, (uv[..., 1] - cam.cy) / cam.fy
    r = np.sqrt(x * x + y * y)
    th = np.arctan(r)
    thd = th * (1 + k[0] * th**2 + k[1] * th**4 + k[2] * th**6 + k[3] * th**8)
    s = np.where(r > 0, thd / np.where(r > 0, r, 1), 1.0)
    return np.stack([cam.fx * x * s + cam.cx, cam.fy * y * s + cam.cy], -1)


def test_the_equidistant_lens_round_trips():
    """``undistort_points`` inverts the equidistant model (written out here independently),
    ``distort_points`` is it, at the image's corners too; a ray the pinhole cannot hold (90° or
    more) is not finite; and a box measured through the lens undistorts to one that holds
    the undistorted points of everything inside it."""
    from spdslam import Camera
    from spdslam.geometry import Equidistant, distort_points, undistort_boxes, undistort_points

    cam, k = Camera(300.0, 300.0, 320.0, 240.0, 640.0, 480.0), Equidistant(-0.05, 0.01, -0.002, 0.0003)
    rng = np.random.default_rng(2)
    uv = rng.uniform([0, 0], [640, 480], size=(500, 2))
    corners = np.array([[0.0, 0.0], [640.0, 480.0], [320.0, 240.0]])
    for pts in (uv, corners):
        np.testing.assert_allclose(_fisheye_forward(undistort_points(pts, cam, k), cam, k), pts, atol=1e-8)
        np.testing.assert_allclose(distort_points(pts, cam, k), _fisheye_forward(pts, cam, k), atol=1e-9)
    np.testing.assert_allclose(undistort_points(uv, cam, Equidistant()), np.c_[
        cam.cx + cam.fx * np.tan(np.hypot(*((uv - [cam.cx, cam.cy]) / cam.fx).T)) * ((uv[:, 0] - cam.cx) / cam.fx)
        / np.hypot(*((uv - [cam.cx, cam.cy]) / cam.fx).T),
        cam.cy + cam.fy * np.tan(np.hypot(*((uv - [cam.cx, cam.cy]) / cam.fx).T)) * ((uv[:, 1] - cam.cy) / cam.fy)
        / np.hypot(*((uv - [cam.cx, cam.cy]) / cam.fx).T)], rtol=1e-9)
    assert not np.all(np.isfinite(undistort_points(np.array([[320.0 + 300.0 * 1.7, 240.0]]), cam, Equidistant())))
    box = np.array([30.0, 40.0, 280.0, 300.0])
    g = np.stack(np.meshgrid(np.linspace(30, 280, 30), np.linspace(40, 300, 30)), -1).reshape(-1, 2)
    ub = undistort_boxes(box, cam, k)
    q = undistort_points(g, cam, k)
    # to the sampling of the outline (16 points per edge): the bowed edge's extreme may lie
    # between two samples, here by 0.01 px
    assert np.all(q >= ub[:2] - 0.02) and np.all(q <= ub[2:] + 0.02)


@pytest.mark.parametrize("dialect", ["ros", "kalibr"])
def test_a_fisheye_calibration_reads_as_an_equidistant_lens(tmp_path, dialect):
    """ROS's and Kalibr's equidistant models give a ``geometry.Equidistant``; a detector folder
    with one reads its boxes through it: boxes measured through the lens come back as the
    pinhole boxes they were made from, to the outline's bow."""
    from conftest import _calibration

    from spdslam import Camera
    from spdslam.geometry import Equidistant, distort_points

    cam, k = Camera(300.0, 300.0, 320.0, 240.0, 640.0, 480.0), Equidistant(-0.05, 0.01, -0.002, 0.0003)
    p = tmp_path / "camera.yaml"
    p.write_text(_calibration(cam, k, dialect))
    got_cam, got = read_camera_calibration(p)
    assert isinstance(got, Equidistant) and got == k and got_cam.fx == cam.fx
    seq = make_room_sequence(1, frames=12, objects=2, camera=cam)
    pin = np.stack([d.box for d in seq.detections])
    corners = np.stack([pin[:, [0, 1]], pin[:, [2, 1]], pin[:, [0, 3]], pin[:, [2, 3]]], axis=1)
    d = distort_points(corners, cam, k)  # a box's corners through the lens: the measured box holds them
    measured = np.c_[d.min(axis=1), d.max(axis=1)]
    folder = write_detector_folder(seq, tmp_path / "fish", dist=k, boxes=measured, calibration=dialect)
    back = np.stack([b.box for b in read_sequence(folder).detections])
    assert np.all(back[:, :2] <= pin[:, :2] + 0.02) and np.all(back[:, 2:] >= pin[:, 2:] - 0.02)
    assert np.abs(back - pin).max() < 0.05 * max(cam.width, cam.height)


def test_check_compares_fisheye_boxes_through_the_lens(tmp_path):
    """A room seen through an equidistant lens (boxes of the distorted outlines, no noise, no
    drift): ``check_sequence`` names the lens model, the measured boxes agree with the
    objects' outlines pushed through the lens, and the undistorted boxes with the pinhole
    projection better than the measured ones do."""
    from spdslam import Camera, Ellipsoid, project_dual_quadric
    from spdslam.evaluation import check_sequence, conic_ellipses, ellipses_points
    from spdslam.geometry import Equidistant, distort_points, dual_quadric
    from spdslam.geometry.se3 import from_tum
    from spdslam.io import MapObject, read_measured_boxes

    cam, k = Camera(300.0, 300.0, 320.0, 240.0, 640.0, 480.0), Equidistant(-0.05, 0.01, -0.002, 0.0003)
    seq = make_room_sequence(1, frames=16, objects=2, camera=cam, drift=0.0, box_noise_px=0.0)
    gt = {o.id: Ellipsoid.from_axes(o.cuboid.rotation, o.cuboid.center, o.cuboid.half_extents) for o in seq.objects_gt}
    fish = []
    for d in seq.detections:
        T = from_tum(seq.poses_tum[d.frame])
        c, S, _ = conic_ellipses(np.asarray(project_dual_quadric(dual_quadric(gt[d.instance]), T, cam)))
        p = distort_points(ellipses_points(c, S, 256), cam, k)
        fish.append(np.r_[p.min(axis=0), p.max(axis=0)])
    folder = write_detector_folder(seq, tmp_path / "fish", dist=k, boxes=np.array(fish))
    raw, dist = read_measured_boxes(folder)
    assert dist == k
    objects = [MapObject(i, o.label, gt[o.id]) for i, o in enumerate(seq.objects_gt)]
    report = check_sequence(read_sequence(folder), objects=objects, raw=raw, distortion=dist)
    dd = report["sources"][0]["distortion"]
    assert dd["model"] == "equidistant" and dd["coefficients"] == list(k) and dd["pairs"] > 0
    assert dd["measured_vs_distorted"] > 0.99
    # the undistorted box is the box of the undistorted box outline, which the fisheye's
    # corners stretch (0.93 here, f = 300 px): better than the measured box, not exact
    assert dd["undistorted_vs_pinhole"] > 0.9 and dd["undistorted_vs_pinhole"] > dd["measured_vs_pinhole"] + 0.02, dd


def test_the_tools_own_files_read_as_documented():
    """Files as the tools write them (tests/data/detector: a ROS camera_info with its
    rectification and projection matrices, a two-camera Kalibr camchain with the extrinsics,
    a Kalibr fisheye camchain, an Ultralytics data.yaml with paths): the fields spdslam needs,
    the others ignored."""
    from spdslam.geometry import Equidistant
    from spdslam.io import read_class_names, read_yolo_labels

    cam, d = read_camera_calibration(DATA / "camera_info.yaml")
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (517.306408, 516.469215, 318.64304,
                                                                      255.313989, 640.0, 480.0)
    np.testing.assert_array_equal(d, [0.262383, -0.953104, -0.005358, 0.002628, 1.163314])
    cam, d = read_camera_calibration(DATA / "camchain.yaml")  # cam0 of the chain
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (458.654, 457.296, 367.215, 248.375, 752.0, 480.0)
    np.testing.assert_array_equal(d, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])
    cam, d = read_camera_calibration(DATA / "camchain_fisheye.yaml")
    assert isinstance(d, Equidistant) and d.k1 == -0.013721808247486035 and cam.width == 640.0
    names = read_class_names(DATA / "yolo")
    assert names == ("chair", "tv_monitor")
    cam = read_camera_calibration(DATA / "camera_info.yaml")[0]
    rows = read_yolo_labels(DATA / "yolo", cam, names, None, 0.5)
    assert len(rows) == 1 and rows[0][0] == 1305031453.359684 and rows[0][2] == "chair" and rows[0][3] == 0.91
    np.testing.assert_allclose(rows[0][1], [(0.5125 - 0.084375) * 640, (0.604167 - 0.1458335) * 480,
                                            (0.5125 + 0.084375) * 640, (0.604167 + 0.1458335) * 480], atol=1e-9)
