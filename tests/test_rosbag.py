"""ROS 2 bags (``spdslam import BAG SEQ``, ``io.import_rosbag``): small bags written with
rosbags' own writer (sqlite3 and mcap storage) from a synthetic room, read back; every
trajectory source (PoseStamped, Odometry, tf), distortion, and the malformed inputs (one
line, exit 2, nothing written)."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("rosbags")

from conftest import assert_cli_error as assert_error
from conftest import cli_invoke as invoke
from conftest import cli_runner
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from spdslam.geometry import Camera, undistort_boxes
from spdslam.io import SequenceFormatError, import_rosbag, read_sequence
from spdslam.synthetic import make_room_sequence

runner = cli_runner()
T0 = 1_700_000_000.0  # ROS stamps are seconds since the epoch; zero means "unset"
STORAGES = [StoragePlugin.SQLITE3, StoragePlugin.MCAP]
PLUMB_BOB = (0.1, -0.2, 0.001, -0.002, 0.05)

# vision_msgs 4.x, written out here independently of the module under test
VISION = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score",
    "vision_msgs/msg/ObjectHypothesisWithPose":
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose",
    "vision_msgs/msg/Detection2D": "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
                                   "vision_msgs/BoundingBox2D bbox\nstring id",
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nvision_msgs/Detection2D[] detections",
}


def typestore(overrides=None):
    store = get_typestore(Stores.ROS2_HUMBLE)
    typs = {}
    for name, text in {**VISION, **(overrides or {})}.items():
        typs.update(get_types_from_msg(text, name))
    store.register(typs)
    return store


# --------------------------------------------------------------------------- bag builder


class Bag:
    """Messages of a few topics, written as a rosbag2 with :meth:`write`."""

    def __init__(self, store=None):
        self.s = store or typestore()
        self.topics = {}  # topic -> (msgtype, [(t_ns, msg)])

    def T(self, name):
        return self.s.types[name]

    def header(self, t, frame=""):
        sec = int(np.floor(t))
        ns = round((t - sec) * 1e9)
        if ns >= 1_000_000_000:
            sec, ns = sec + 1, ns - 1_000_000_000
        return self.T("std_msgs/msg/Header")(stamp=self.T("builtin_interfaces/msg/Time")(sec=sec, nanosec=ns),
                                               frame_id=frame)

    def add(self, topic, msgtype, t, msg):
        self.topics.setdefault(topic, (msgtype, []))[1].append((round(max(t, 1e-3) * 1e9), msg))

    def declare(self, topic, msgtype):
        self.topics.setdefault(topic, (msgtype, []))

    def camera_info(self, cam, t=T0, dist=(), model="plumb_bob", frame="cam_optical", topic="/camera/camera_info",
                    k=None):
        K = np.array(k if k is not None else [cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1], float)
        roi = self.T("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        msg = self.T("sensor_msgs/msg/CameraInfo")(
            header=self.header(t, frame), height=int(cam.height), width=int(cam.width), distortion_model=model,
            d=np.array(dist, float), k=K, r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0, roi=roi)
        self.add(topic, "sensor_msgs/msg/CameraInfo", t, msg)

    def detections(self, t, dets, topic="/detections", theta=0.0, stamp=None):
        """dets: [(box [x1 y1 x2 y2], label, score, id string)]."""
        out = []
        for box, label, score, ident in dets:
            x1, y1, x2, y2 = box
            hyp = self.T("vision_msgs/msg/ObjectHypothesisWithPose")(
                hypothesis=self.T("vision_msgs/msg/ObjectHypothesis")(class_id=label, score=float(score)),
                pose=self.T("geometry_msgs/msg/PoseWithCovariance")(pose=self.pose(np.zeros(3), [0, 0, 0, 1]),
                                                                    covariance=np.zeros(36)))
            center = self.T("vision_msgs/msg/Pose2D")(
                position=self.T("vision_msgs/msg/Point2D")(x=(x1 + x2) / 2, y=(y1 + y2) / 2), theta=theta)
            bbox = self.T("vision_msgs/msg/BoundingBox2D")(center=center, size_x=x2 - x1, size_y=y2 - y1)
            out.append(self.T("vision_msgs/msg/Detection2D")(header=self.header(t, "cam_optical"), results=[hyp],
                                                               bbox=bbox, id=ident))
        st = t if stamp is None else stamp
        msg = self.T("vision_msgs/msg/Detection2DArray")(header=self.header(st, "cam_optical"), detections=out)
        self.add(topic, "vision_msgs/msg/Detection2DArray", t, msg)

    def pose(self, p, q):
        P = self.T("geometry_msgs/msg/Pose")
        return P(position=self.T("geometry_msgs/msg/Point")(x=p[0], y=p[1], z=p[2]),
                 orientation=self.T("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3]))

    def pose_stamped(self, t, p, q, frame="map", topic="/camera/pose"):
        msg = self.T("geometry_msgs/msg/PoseStamped")(header=self.header(t, frame), pose=self.pose(p, q))
        self.add(topic, "geometry_msgs/msg/PoseStamped", t, msg)

    def odometry(self, t, p, q, frame="odom", child="cam_optical", topic="/odom"):
        cov = self.T("geometry_msgs/msg/PoseWithCovariance")(pose=self.pose(p, q), covariance=np.zeros(36))
        z = self.T("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
        tw = self.T("geometry_msgs/msg/TwistWithCovariance")(
            twist=self.T("geometry_msgs/msg/Twist")(linear=z, angular=z), covariance=np.zeros(36))
        msg = self.T("nav_msgs/msg/Odometry")(header=self.header(t, frame), child_frame_id=child, pose=cov, twist=tw)
        self.add(topic, "nav_msgs/msg/Odometry", t, msg)

    def tf(self, t, links, static=False):
        """links: [(parent, child, p, q)] in one TFMessage on /tf (or /tf_static)."""
        trs = []
        for parent, child, p, q in links:
            tr = self.T("geometry_msgs/msg/Transform")(
                translation=self.T("geometry_msgs/msg/Vector3")(x=p[0], y=p[1], z=p[2]),
                rotation=self.T("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3]))
            trs.append(self.T("geometry_msgs/msg/TransformStamped")(header=self.header(t, parent),
                                                                      child_frame_id=child, transform=tr))
        topic = "/tf_static" if static else "/tf"
        self.add(topic, "tf2_msgs/msg/TFMessage", t, self.T("tf2_msgs/msg/TFMessage")(transforms=trs))

    def write(self, path, storage=StoragePlugin.SQLITE3, msgdefs=None):
        """``msgdefs``: {msgtype: (definition text, rihs01)} stored instead of the typestore's
        (an empty text: no definition, as ROS 2 Humble's sqlite3 bags)."""
        with Writer(path, version=9, storage_plugin=storage) as w:
            for topic, (msgtype, msgs) in self.topics.items():
                if msgdefs and msgtype in msgdefs:
                    text, h = msgdefs[msgtype]
                    conn = w.add_connection(topic, msgtype, msgdef=text, rihs01=h)
                else:
                    conn = w.add_connection(topic, msgtype, typestore=self.s)
                for t_ns, msg in msgs:
                    w.write(conn, t_ns, self.s.serialize_cdr(msg, msgtype))
        return path


def room(frames=12, objects=2, seed=0):
    seq = make_room_sequence(seed, frames, objects)
    return dataclasses.replace(
        seq, timestamps=seq.timestamps + T0,
        detections=[dataclasses.replace(d, timestamp=d.timestamp + T0) for d in seq.detections])


def room_bag(seq, poses="pose", dist=(), model="plumb_bob", store=None):
    """A bag of ``seq``: CameraInfo, one Detection2DArray per frame, and the camera poses as
    PoseStamped ("pose"), Odometry ("odom") or tf ("tf": map -> odom static, odom ->
    base_link moving, base_link -> cam_optical static)."""
    b = Bag(store)
    b.camera_info(seq.camera, dist=dist, model=model)
    T_map_odom = (np.array([1.0, -2.0, 0.3]), Rotation.from_euler("z", 30, degrees=True))
    T_base_cam = (np.array([0.1, 0.0, 0.5]), Rotation.from_euler("ZYX", [-90, 0, -90], degrees=True))
    if poses == "tf":
        b.tf(T0, [("map", "odom", T_map_odom[0], T_map_odom[1].as_quat()),
                  ("base_link", "cam_optical", T_base_cam[0], T_base_cam[1].as_quat())], static=True)
    for i, t in enumerate(seq.timestamps):
        p, q = seq.poses_tum[i, :3], seq.poses_tum[i, 3:]
        b.detections(t, [(d.box, d.label, d.score, str(d.instance)) for d in seq.detections_at(i)])
        if poses == "pose":
            b.pose_stamped(t, p, q)
        elif poses == "odom":
            b.odometry(t, p, q)
        else:  # T_odom_base = T_map_odom⁻¹ T_map_cam T_base_cam⁻¹
            R = T_map_odom[1].inv() * Rotation.from_quat(q) * T_base_cam[1].inv()
            c = T_map_odom[1].inv().apply(p - T_map_odom[0]) - R.apply(T_base_cam[0])
            b.tf(t, [("odom", "base_link", c, R.as_quat())])
    return b


def assert_same(got, want, boxes=None):
    assert got.camera == want.camera
    np.testing.assert_allclose(got.timestamps, want.timestamps, rtol=0, atol=1e-6)
    a, b = got.poses_tum.copy(), want.poses_tum.copy()
    b[:, 3:] *= np.sign(np.sum(a[:, 3:] * b[:, 3:], axis=1))[:, None]  # q and -q: one rotation
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    assert len(got.detections) == len(want.detections) > 0
    boxes = np.stack([d.box for d in want.detections]) if boxes is None else boxes
    for g, w, box in zip(got.detections, want.detections, boxes):
        assert (g.frame, g.label, g.instance) == (w.frame, w.label, w.instance)
        assert abs(g.timestamp - w.timestamp) < 1e-6 and g.score == pytest.approx(w.score)
        np.testing.assert_allclose(g.box, box, rtol=0, atol=1e-9)


def one_line_error(excinfo, *fragments):
    msg = str(excinfo.value)
    assert "\n" not in msg
    for f in fragments:
        assert f in msg, (f, msg)
    return msg


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("storage", STORAGES, ids=["sqlite3", "mcap"])
@pytest.mark.parametrize("poses", ["pose", "odom", "tf"])
def test_round_trip_of_each_trajectory_source(tmp_path, storage, poses):
    seq = room()
    path = room_bag(seq, poses).write(tmp_path / "bag", storage)
    got = import_rosbag(path, min_score=0.0)
    assert got.name == "bag"
    assert_same(got, seq)
    # up estimated from the cameras (carried without roll), as the OA-SLAM importer does
    assert np.dot(got.priors.up, seq.priors.up) > np.cos(np.radians(1.0))  # room cameras: ~0.4°


def test_tf_world_frame_elsewhere_in_the_tree(tmp_path):
    """world_frame odom (the camera's ancestor, turned 30° about z under map) and marker (a
    sibling branch under map): T_world_cam = T_map_world⁻¹ T_map_cam."""
    seq = room()
    b = room_bag(seq, "tf")
    marker = (np.array([0.5, 0.2, -0.1]), Rotation.from_euler("xyz", [10, -20, 40], degrees=True))
    b.tf(T0, [("map", "marker", marker[0], marker[1].as_quat())], static=True)
    path = b.write(tmp_path / "bag", StoragePlugin.MCAP)
    for world, (t, R) in [("odom", ([1.0, -2.0, 0.3], Rotation.from_euler("z", 30, degrees=True))),
                          ("marker", marker)]:
        got = import_rosbag(path, min_score=0.0, world_frame=world, camera_frame="cam_optical")
        p = R.inv().apply(seq.poses_tum[:, :3] - t)
        q = (R.inv() * Rotation.from_quat(seq.poses_tum[:, 3:])).as_quat()
        assert_same(got, dataclasses.replace(seq, poses_tum=np.hstack([p, q])))


def test_plumb_bob_distortion_undistorts_the_boxes(tmp_path):
    seq = room()
    path = room_bag(seq, dist=PLUMB_BOB).write(tmp_path / "bag")
    measured = np.stack([d.box for d in seq.detections])
    want = undistort_boxes(measured, seq.camera, np.array(PLUMB_BOB))
    assert np.abs(want - measured).max() > 1.0  # the test means something
    assert_same(import_rosbag(path, min_score=0.0), seq, want)
    assert_same(import_rosbag(path, min_score=0.0, undistort=False), seq, measured)


def test_rational_polynomial_without_denominator_is_plumb_bob_and_with_one_refused(tmp_path):
    seq = room()
    path = room_bag(seq, dist=PLUMB_BOB + (0, 0, 0), model="rational_polynomial").write(tmp_path / "a")
    want = undistort_boxes(np.stack([d.box for d in seq.detections]), seq.camera, np.array(PLUMB_BOB))
    assert_same(import_rosbag(path, min_score=0.0), seq, want)
    path = room_bag(seq, dist=PLUMB_BOB + (0.01, 0, 0), model="rational_polynomial").write(tmp_path / "b")
    with pytest.raises(SequenceFormatError) as e:
        import_rosbag(path)
    one_line_error(e, "topic /camera/camera_info", "rational_polynomial", "k4 = k5 = k6 = 0")


def test_min_score_labels_ids_and_rotated_boxes(tmp_path):
    b = Bag()
    cam = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)
    b.camera_info(cam)
    b.detections(T0, [([10, 20, 110, 220], "dining table", 0.9, "7"), ([300, 300, 340, 320], "cup", 0.3, "track-a"),
                      ([50, 60, 70, 80], "cup", 0.6, "")])
    b.detections(T0 + 0.1, [([100, 100, 140, 120], "book", 0.8, "2")], theta=np.pi / 2)
    for t in (T0, T0 + 0.1):
        b.pose_stamped(t, [0.0, 0.0, 0.0], [0, 0, 0, 1])
    got = import_rosbag(b.write(tmp_path / "bag"))
    assert [(d.frame, d.label, d.instance) for d in got.detections] == [
        (0, "dining_table", 7), (0, "cup", None), (1, "book", 2)]
    np.testing.assert_allclose(got.detections[2].box, [110, 90, 130, 130])  # turned by 90°
    assert len(import_rosbag(tmp_path / "bag", min_score=0.0).detections) == 4


def test_tf_is_interpolated_at_the_detection_times_and_world_frame_chooses_the_root(tmp_path):
    b = Bag()
    cam = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)
    b.camera_info(cam, frame="")  # no frame id: --camera-frame names it
    q1 = Rotation.from_euler("z", 90, degrees=True).as_quat()
    b.tf(T0, [("map", "odom", [0, 0, 1.0], [0, 0, 0, 1])], static=True)
    b.tf(T0, [("odom", "cam", [0, 0, 0], [0, 0, 0, 1])])
    b.tf(T0 + 1.0, [("odom", "cam", [2.0, 0, 0], q1)])
    for t in (T0 + 0.5, T0 + 1.01, T0 + 1.5):  # the last is past the samples
        b.detections(t, [([10, 20, 110, 220], "cup", 0.9, "1")])
    path = b.write(tmp_path / "bag", StoragePlugin.MCAP)
    with pytest.raises(SequenceFormatError) as e:
        import_rosbag(path)
    one_line_error(e, "header.frame_id naming the camera frame")
    got = import_rosbag(path, camera_frame="cam")
    np.testing.assert_allclose(got.timestamps, [T0 + 0.5, T0 + 1.01], atol=1e-6)
    np.testing.assert_allclose(got.poses_tum[0, :3], [1.0, 0, 1.0], atol=1e-9)
    np.testing.assert_allclose(got.poses_tum[0, 3:], Rotation.from_euler("z", 45, degrees=True).as_quat(), atol=1e-9)
    np.testing.assert_allclose(got.poses_tum[1, :3], [2.0, 0, 1.0], atol=1e-9)
    assert [d.frame for d in got.detections] == [0, 1]
    odom = import_rosbag(path, camera_frame="cam", world_frame="odom")
    np.testing.assert_allclose(odom.poses_tum[:, 2], 0.0, atol=1e-12)


def test_definitions_stored_in_the_bag_are_preferred_and_a_bag_without_any_is_read(tmp_path):
    # a Detection2D whose id comes first: decoded with vision_msgs 4.x it would be garbage
    moved = {"vision_msgs/msg/Detection2D": "std_msgs/Header header\nstring id\n"
                                            "vision_msgs/ObjectHypothesisWithPose[] results\nvision_msgs/BoundingBox2D bbox"}
    seq = room(frames=6)
    path = room_bag(seq, store=typestore(moved)).write(tmp_path / "moved", StoragePlugin.MCAP)
    assert_same(import_rosbag(path, min_score=0.0), seq)
    # ROS 2 Humble's sqlite3 bags store no definitions: the built-in ones decode them
    b = room_bag(seq)
    none = {ty: ("", "RIHS01_" + "0" * 64) for ty, _ in b.topics.values()}
    assert_same(import_rosbag(b.write(tmp_path / "bare", msgdefs=none), min_score=0.0), seq)


def test_zero_header_stamps_fall_back_to_the_record_time(tmp_path):
    b = Bag()
    b.camera_info(Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0))
    b.pose_stamped(T0 + 1, [0.0, 0.0, 0.0], [0, 0, 0, 1])
    b.detections(T0 + 1.005, [([10, 20, 110, 220], "cup", 0.9, "1")], stamp=0.0)
    got = import_rosbag(b.write(tmp_path / "bag"))
    assert got.detections[0].timestamp == pytest.approx(T0 + 1.005, abs=1e-6)


# --------------------------------------------------------------------------- CLI


def test_cli_imports_a_bag_that_spdslam_run_maps(tmp_path):
    seq = room(frames=30, objects=2)
    path = room_bag(seq, "odom").write(tmp_path / "rec", StoragePlugin.MCAP)
    mcap = next(path.glob("*.mcap"))
    dest = tmp_path / "seq"
    result = invoke("import", path, dest, "--min-score", "0", "--pose-topic", "/odom", "--world-frame", "odom",
                    "--camera-frame", "cam_optical")
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    assert f"imported 30 poses, {len(seq.detections)} detections" in result.stdout
    assert_same(read_sequence(dest), dataclasses.replace(seq, name="seq"))
    # the storage file alone is a bag too
    result = invoke("import", mcap, tmp_path / "seq2", "--min-score", "0")
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    assert_same(read_sequence(tmp_path / "seq2"), seq)
    out = tmp_path / "out"
    result = invoke("run", dest, "--out", out, "--max-iterations", "5", "--no-overlay")
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    assert (out / "map.json").is_file() and (out / "trajectory.txt").is_file()


def test_cli_errors_write_nothing(tmp_path):
    seq = room(frames=4)
    path = room_bag(seq).write(tmp_path / "bag")
    dest = tmp_path / "dest"
    for args, fragments in [
        (["--detections-topic", "/nope"], ["topic /nope", "no such topic", "/camera/pose"]),
        (["--pose-topic", "/detections"], ["topic /detections", ": a geometry_msgs/msg/PoseStamped or",
                                           "got vision_msgs/msg/Detection2DArray"]),
        (["--world-frame", "odom"], ["poses in the world frame 'odom'", "'map'"]),
        (["--camera-frame", "cam"], ["PoseStamped names no child frame"]),
        (["--trajectory", "groundtruth"], ["--trajectory", "--pose-topic"]),
    ]:
        assert_error(invoke("import", path, dest, *args), *fragments)
        assert not dest.exists()
    folder = tmp_path / "plain"
    folder.mkdir()
    assert_error(invoke("import", folder, dest, "--pose-topic", "/tf"), "--pose-topic", "expected a ROS 2 bag")
    assert_error(invoke("import", tmp_path / "missing.mcap", dest), "missing.mcap", "no such file")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "plain"]


# --------------------------------------------------------------------------- malformed bags


CAM = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)


def base_bag(**info):
    b = Bag()
    b.camera_info(CAM, **info)
    b.pose_stamped(T0, [0.0, 0.0, 0.0], [0, 0, 0, 1])
    b.detections(T0, [([10, 20, 110, 220], "cup", 0.9, "1")])
    return b


def refused(tmp_path, bag, *fragments, storage=StoragePlugin.SQLITE3, **options):
    path = bag.write(tmp_path / "bag", storage)
    with pytest.raises(SequenceFormatError) as e:
        import_rosbag(path, **options)
    msg = one_line_error(e, str(path), *fragments)
    dest = tmp_path / "dest"
    assert_error(invoke("import", path, dest), *fragments)
    assert not dest.exists()
    return msg


def test_missing_topic(tmp_path):
    b = base_bag()
    del b.topics["/camera/camera_info"]
    refused(tmp_path, b, ": one sensor_msgs/msg/CameraInfo topic for the camera", "got none", "/camera/pose [geometry_msgs")


def test_several_candidate_topics(tmp_path):
    b = base_bag()
    b.detections(T0, [([10, 20, 110, 220], "cup", 0.9, "1")], topic="/yolo/detections")
    refused(tmp_path, b, "got 2: /detections, /yolo/detections", "--detections-topic")


def test_poses_from_two_sources_must_be_chosen(tmp_path):
    b = base_bag()
    b.tf(T0, [("map", "cam_optical", [0, 0, 0], [0, 0, 0, 1])])
    refused(tmp_path, b, "got 2: /camera/pose, /tf", "--pose-topic")


def test_empty_topic(tmp_path):
    b = base_bag()
    b.topics["/camera/pose"][1].clear()
    refused(tmp_path, b, "topic /camera/pose", "at least one message", "an empty topic")


def test_zero_focal_length(tmp_path):
    refused(tmp_path, base_bag(k=[0.0] * 9), "topic /camera/camera_info", "positive focal lengths", "fx=0")


def test_unsupported_distortion_model(tmp_path):
    refused(tmp_path, base_bag(dist=(0.1, 0.0, 0.0, 0.0), model="equidistant"), "'equidistant'")


def test_box_of_non_positive_size(tmp_path):
    b = base_bag()
    b.detections(T0, [([10, 20, 110, 220], "cup", 0.9, "1"), ([50, 50, 50, 80], "cup", 0.9, "1")])
    refused(tmp_path, b, "topic /detections message 1 detection 1", "positive size_x and size_y", "size 0 x 30")


def test_box_outside_the_image(tmp_path):
    b = base_bag()
    b.detections(T0, [([700, 20, 800, 220], "cup", 0.9, "1")])
    refused(tmp_path, b, "message 1 detection 0", "overlaps the 640x480 image")


def test_detections_far_from_every_pose(tmp_path):
    b = base_bag()
    b.topics["/camera/pose"][1].clear()
    b.pose_stamped(T0 + 5, [0.0, 0.0, 0.0], [0, 0, 0, 1])
    refused(tmp_path, b, "topic /detections", "within 0.02 s of a pose", "none of 1")


def test_zero_quaternion(tmp_path):
    b = base_bag()
    b.topics["/camera/pose"][1].clear()
    b.pose_stamped(T0, [0.0, 0.0, 0.0], [0, 0, 0, 0])
    refused(tmp_path, b, "topic /camera/pose message 0", "normalises to unit length")


def test_tf_without_a_path_between_the_frames(tmp_path):
    b = base_bag()
    del b.topics["/camera/pose"]
    b.tf(T0, [("map", "odom", [0, 0, 0], [0, 0, 0, 1]), ("base", "cam_optical", [0, 0, 0], [0, 0, 0, 1])])
    path = b.write(tmp_path / "bag", StoragePlugin.MCAP)
    with pytest.raises(SequenceFormatError) as e:
        import_rosbag(path, world_frame="map")
    one_line_error(e, "topic /tf", "a chain of transforms from 'map' to 'cam_optical'", "no path")
    with pytest.raises(SequenceFormatError) as e:
        import_rosbag(path, camera_frame="lidar")
    one_line_error(e, "the camera frame 'lidar' in the tf tree", "'base'")
    assert len(import_rosbag(path)) == 1  # the camera's own tree: base -> cam_optical


def test_tf_that_never_covers_the_detections(tmp_path):
    b = base_bag()
    del b.topics["/camera/pose"]
    b.tf(T0 + 3, [("map", "cam_optical", [0, 0, 0], [0, 0, 0, 1])])
    refused(tmp_path, b, "topic /tf", "at the detections' times", "none covered")


def test_not_a_bag_and_a_damaged_one(tmp_path):
    folder = tmp_path / "folder"
    folder.mkdir()
    with pytest.raises(SequenceFormatError) as e:
        import_rosbag(folder)
    one_line_error(e, "a folder without metadata.yaml")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(SequenceFormatError) as e:
        import_rosbag(junk)
    one_line_error(e, "junk.mcap", "a readable ROS 2 bag")
    assert_error(invoke("import", junk, tmp_path / "dest"), "a readable ROS 2 bag")
    assert not (tmp_path / "dest").exists()


def test_without_rosbags_the_error_says_what_to_install(tmp_path, monkeypatch):
    path = base_bag().write(tmp_path / "bag")
    monkeypatch.setitem(sys.modules, "rosbags.rosbag2", None)  # import fails
    with pytest.raises(SequenceFormatError) as e:
        import_rosbag(path)
    one_line_error(e, 'pip install "spdslam[ros]"', "not installed")
