"""Sequence folders: the canonical readers, their one-line errors, the writer's round trip
and the TUM fr3_cabinet importer (on the shared reference data when it is present)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from spdslam.geometry import Camera, Cuboid
from spdslam.geometry.se3 import matrix_to_quat, quat_to_matrix
from spdslam.io import (
    ClassPrior,
    Detection,
    EllipsoidDetection,
    GroundTruthObject,
    Priors,
    Sequence,
    SequenceFormatError,
    import_fr3_cabinet,
    read_sequence,
    write_sequence,
)

FR3 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tum_fr3_cabinet"

CAMERA = "fx: 500.0\nfy: 505.5\ncx: 320.0\ncy: 240.0\nwidth: 640\nheight: 480\n"
TRAJ = (
    "# timestamp tx ty tz qx qy qz qw\n"
    "1.00 0 0 1 0 0 0 1\n"
    "1.50 0.1 0 1 0 0 0.7071068 0.7071068\n"
    "2.00 0.2 0 1 0 0 0 2\n"  # normalised on reading
)
DETS = (
    "# timestamp x1 y1 x2 y2 label score [instance]\n"
    "1.00 10 20 110 220 chair 0.9 3\n"
    "1.51 11 21 111 221 chair 0.8\n"
    "\n"
    "2.00 0 0 640 480 table 0.5 1  # trailing comment\n"
)
OBJS = "0 chair 1 2 0.5 0 0 0 1 0.4 0.3 0.5\n1 table -1 0 0.4 0 0 0.3826834 0.9238795 1 0.5 0.4\n"
ELLS = (
    "# timestamp label qx qy qz qw cx cy cz a b c [instance]\n"
    "1.00 chair 0 0 0 1 0.1 -0.2 2.5 0.3 0.25 0.5 3\n"
    "1.49 chair 0 0 0.3826834 0.9238795 0 0 3 0.4 0.3 0.2\n"
    "2.00 table 0 0 0 2 1 1 4 1 0.5 0.4 -1  # normalised on reading\n"
)
PRIORS = (
    "support_planes:\n  - [0, 0, 1, 0]\n  - [0.0, 1.0, 0.0, -2.5]\n"
    "up: [0, 0, 1]\n"
    "classes:\n  chair: {radii: [0.3, 0.3, 0.5], sigma: 0.1}\n  table:\n    radii: [1, 0.5, 0.4]\n    sigma: 2e-1\n"
)


def make(folder: Path, **files) -> Path:
    base = {"camera.yaml": CAMERA, "trajectory.txt": TRAJ, "detections.txt": DETS}
    base.update(files)
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in base.items():
        if text is not None:
            (folder / name).write_text(text)
    return folder


def error(folder: Path) -> str:
    with pytest.raises(SequenceFormatError) as e:
        read_sequence(folder)
    msg = str(e.value)
    assert "\n" not in msg
    return msg


# --- canonical readers ----------------------------------------------------------------------


def test_minimal_sequence(tmp_path):
    s = read_sequence(make(tmp_path / "seq"))
    assert s.name == "seq" and len(s) == 3
    assert s.camera == Camera(500.0, 505.5, 320.0, 240.0, 640, 480)
    np.testing.assert_allclose(s.timestamps, [1.0, 1.5, 2.0])
    np.testing.assert_allclose(np.linalg.norm(s.poses_tum[:, 3:], axis=1), 1.0)
    np.testing.assert_allclose(s.poses_tum[2], [0.2, 0, 1, 0, 0, 0, 1])
    assert [d.frame for d in s.detections] == [0, 1, 2]
    d = s.detections[1]
    assert d.timestamp == 1.51 and d.label == "chair" and d.instance is None and d.score == 0.8
    np.testing.assert_array_equal(d.box, [11, 21, 111, 221])
    assert s.detections[0].instance == 3
    assert s.objects_gt is None and s.groundtruth_tum is None and s.priors is None and s.images is None
    assert s.ellipsoids is None and s.ellipsoids_at(0) == []
    assert s.detections_at(2)[0].label == "table"


def test_optional_files(tmp_path):
    folder = make(
        tmp_path / "seq",
        **{
            "objects_gt.txt": OBJS,
            "groundtruth.txt": TRAJ,
            "priors.yaml": PRIORS,
            "rgb.txt": "1.0 rgb/1.png\n1.5 rgb/2.png\n",
        },
    )
    s = read_sequence(folder)
    assert [o.id for o in s.objects_gt] == [0, 1] and s.objects_gt[1].label == "table"
    c = s.objects_gt[1].cuboid
    np.testing.assert_allclose(c.center, [-1, 0, 0.4])
    np.testing.assert_allclose(c.rotation, Cuboid.from_yaw([0, 0, 0], np.pi / 4, [1, 1, 1]).rotation, atol=1e-6)
    np.testing.assert_allclose(c.half_extents, [1, 0.5, 0.4])
    assert s.groundtruth_tum.shape == (3, 8)
    assert len(s.priors.support_planes) == 2
    np.testing.assert_allclose(s.priors.support_planes[1], [0, 1, 0, -2.5])
    np.testing.assert_allclose(s.priors.up, [0, 0, 1])
    assert s.priors.classes["table"] == ClassPrior([1, 0.5, 0.4], 0.2)
    assert s.images[1.5] == (folder / "rgb/2.png").absolute()


def test_ellipsoids_file(tmp_path):
    s = read_sequence(make(tmp_path / "seq", **{"ellipsoids.txt": ELLS}))
    assert [(e.frame, e.label, e.instance) for e in s.ellipsoids] == [(0, "chair", 3), (1, "chair", None), (2, "table", -1)]
    e = s.ellipsoids[1]
    assert e.timestamp == 1.49 and s.ellipsoids_at(1) == [e]
    np.testing.assert_allclose(e.center, [0, 0, 3])
    np.testing.assert_allclose(e.radii, [0.4, 0.3, 0.2])
    c, si = np.cos(np.pi / 4), np.sin(np.pi / 4)
    np.testing.assert_allclose(e.rotation, [[c, -si, 0], [si, c, 0], [0, 0, 1]], atol=1e-7)
    np.testing.assert_allclose(e.P, e.rotation @ np.diag([0.16, 0.09, 0.04]) @ e.rotation.T)
    np.testing.assert_allclose(s.ellipsoids[2].rotation, np.eye(3))
    # the data class checks its own values too; a reflection is the same ellipsoid
    with pytest.raises(ValueError, match="radii must be positive"):
        EllipsoidDetection(0, 1.0, "x", np.eye(3), np.zeros(3), [1, 0, 1])
    with pytest.raises(ValueError, match="orthonormal"):
        EllipsoidDetection(0, 1.0, "x", 2 * np.eye(3), np.zeros(3), [1, 1, 1])
    flipped = EllipsoidDetection(0, 1.0, "x", np.diag([1.0, 1, -1]), np.zeros(3), [1, 2, 3])
    np.testing.assert_array_equal(flipped.rotation, np.eye(3))


def test_quaternion_helpers(rng):
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = -q if q[3] < 0 else q
        R = quat_to_matrix(q)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(matrix_to_quat(R), q, atol=1e-12)


# --- one-line errors naming file and line ---------------------------------------------------

BAD = [
    ("detections.txt", DETS + "2.0 1 2 3 chair 0.5\n", 6, "columns"),
    ("detections.txt", DETS + "2.0 1 2 abc 4 chair 0.5\n", 6, "a number for x2, got 'abc'"),
    ("detections.txt", DETS + "2.0 1 2 nan 4 chair 0.5\n", 6, "finite number"),
    ("detections.txt", DETS + "2.0 10 2 5 4 chair 0.5\n", 6, "x2 > x1"),
    ("detections.txt", DETS + "2.0 1 20 5 4 chair 0.5\n", 6, "y2 > y1"),
    ("detections.txt", DETS + "1.25 1 2 5 4 chair 0.5\n", 6, "within 0.02 s"),
    ("detections.txt", DETS + "2.0 1 2 5 4 chair 0.5 x\n", 6, "an integer for instance"),
    ("trajectory.txt", TRAJ + "3.0 0 0 1 0 0 0\n", 5, "8 columns"),
    ("trajectory.txt", TRAJ + "3.0 0 0 1 0 0 0 inf\n", 5, "finite number"),
    ("trajectory.txt", TRAJ + "3.0 0 0 1 0 0 0 0\n", 5, "normalises to unit length"),
    ("trajectory.txt", TRAJ + "1.5 0 0 1 0 0 0 1\n", 5, "greater than the previous"),
    ("trajectory.txt", TRAJ + "3.0 0 0 1_0 0 0 0 1\n", 5, "a number for tz, got '1_0'"),
    # the rows are checked as arrays: the error still names the first line that fails
    ("trajectory.txt", TRAJ.replace("2.00 0.2", "1.20 0.2") + "3.0 0 0 1 0 0 0 0\n", 4,
     "a timestamp greater than the previous one (1.5), got '1.20'"),
    ("trajectory.txt", TRAJ.replace("0 0 0 2\n", "0 0 0 0\n") + "2.5 0 0 nan 0 0 0 1\n", 4, "normalises to unit"),
    ("detections.txt", DETS.replace("11 21 111 221", "11 21 1 221") + "2.0 10 2 5 4 chair 0.5\n", 3, "x2 > x1"),
    ("detections.txt", DETS.replace("1.51 11", "1.31 11") + "2.0 1 2 abc 4 chair 0.5\n", 3, "within 0.02 s"),
    ("objects_gt.txt", OBJS + "2 x 0 0 0 0 0 0 1 1 1\n", 3, "12 columns"),
    ("objects_gt.txt", OBJS + "2 x 0 0 0 0 0 0 1 1 -1 1\n", 3, "positive half-extents"),
    ("groundtruth.txt", "1.0 0 0 0 0 0 0 1\n1.1 0 0 0 0 0 0 one\n", 2, "a number for qw"),
    ("ellipsoids.txt", ELLS + "2.0 chair 0 0 0 1 0 0 1 1 1\n", 5, "12 or 13 columns"),
    ("ellipsoids.txt", ELLS + "2.0 chair 0 0 0 1 0 0 1 1 1 1 1 1\n", 5, "12 or 13 columns"),
    ("ellipsoids.txt", ELLS + "2.0 chair 0 0 0 1 0 0 1 1 -1 1\n", 5, "positive semi-axes a b c, got 1 -1 1"),
    ("ellipsoids.txt", ELLS + "2.0 chair 0 0 0 1 0 0 1 1 0 1\n", 5, "positive semi-axes"),
    ("ellipsoids.txt", ELLS + "2.0 chair 0 0 0 0 0 0 1 1 1 1\n", 5, "normalises to unit length"),
    ("ellipsoids.txt", ELLS + "2.0 chair 0 0 0 1 0 0 nan 1 1 1\n", 5, "a finite number for cz"),
    ("ellipsoids.txt", ELLS + "2.0 chair 0 0 0 1 0 x 1 1 1 1\n", 5, "a number for cy, got 'x'"),
    ("ellipsoids.txt", ELLS + "1.25 chair 0 0 0 1 0 0 1 1 1 1\n", 5, "within 0.02 s"),
    ("ellipsoids.txt", ELLS + "2.0 chair 0 0 0 1 0 0 1 1 1 1 0.5\n", 5, "an integer for instance"),
    ("rgb.txt", "1.0\n", 1, "2 columns"),
    ("camera.yaml", CAMERA.replace("fy: 505.5", "fy: -1"), 2, "a positive fy"),
    ("camera.yaml", CAMERA.replace("fy: 505.5", "fy: abc"), 2, "a number for fy"),
    ("camera.yaml", CAMERA + "k1: 0.1\n", 7, "a key of camera.yaml"),
    ("camera.yaml", "fx: [1\n", 2, "valid YAML"),
    ("priors.yaml", PRIORS + "foo: 1\n", 10, "a key of priors.yaml"),
    ("priors.yaml", "up: [0, 1]\n", 1, "a list of 3 numbers for up"),
    ("priors.yaml", "classes:\n  chair: {radii: [1, 1, 1]}\n", 2, "radii and sigma"),
    ("priors.yaml", "classes:\n  chair: {radii: [1, 1, 1], sigma: -1}\n", 2, "positive sigma"),
    ("priors.yaml", "support_planes:\n  - [0, 0, 0, 1]\n", 2, "non-zero normal"),
    ("priors.yaml", "classes:\n  c: {radii: [1, 1, 1], sigma: 1, shape: box}\n", 2, "shape ellipsoid or cuboid"),
    ("priors.yaml", "classes:\n  c: {radii: [1, 1, 1], sigma: 1, shape: [1]}\n", 2, "got a list"),
    ("priors.yaml", "trajectory_sigma: [0.01]\n", 1, "a list of 2 numbers for trajectory_sigma"),
    ("priors.yaml", "trajectory_sigma: [0.01, 0]\n", 1, "a positive trajectory_sigma"),
]


def test_to_tum_reads_the_poses_on_the_host():
    """``to_tum`` reads a pose's parameters on the host (nothing to compile): the TUM fields
    of ``from_tum``'s poses back, qw ≥ 0."""
    from spdslam.geometry.se3 import from_tum, to_tum

    rows = np.random.default_rng(7).normal(size=(2000, 7))
    back = to_tum(from_tum(rows))
    assert np.all(back[:, 6] >= 0)
    q = rows[:, 3:7] / np.linalg.norm(rows[:, 3:7], axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", back[:, 3:7], q)), 1.0, atol=1e-12)
    np.testing.assert_array_equal(back[:, :3], rows[:, :3])


@pytest.mark.parametrize("fname, text, line, expected", BAD, ids=[f"{b[0]}-{b[3]}" for b in BAD])
def test_malformed_one_line_error(tmp_path, fname, text, line, expected):
    folder = make(tmp_path / "seq", **{fname: text})
    msg = error(folder)
    assert msg.startswith(f"{folder / fname}:{line}: "), msg
    assert expected in msg and ", got " in msg, msg


@pytest.mark.parametrize("fname", ["camera.yaml", "trajectory.txt", "detections.txt"])
def test_missing_required_file(tmp_path, fname):
    folder = make(tmp_path / "seq", **{fname: None})
    msg = error(folder)
    assert msg.startswith(str(folder / fname)) and "no such file" in msg
    assert isinstance(SequenceFormatError("f", 1, "a", "b"), ValueError)


def test_camera_missing_key(tmp_path):
    msg = error(make(tmp_path / "seq", **{"camera.yaml": "fx: 1\nfy: 1\n"}))
    assert "camera.yaml" in msg and "cx, cy, width, height missing" in msg


# --- writer ---------------------------------------------------------------------------------


def synthetic() -> Sequence:
    cam = Camera(525.0, 525.0, 319.5, 239.5, 640.0, 480.0)
    t = np.array([0.0, 0.1, 0.2, 1341841278.8427])
    q = np.array([[0, 0, 0, 1], [0.1, 0.2, 0.3, 0.9], [0, 0, 1, 0], [-0.4871, 0.7673, -0.3519, 0.2239]])
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    poses = np.column_stack([np.arange(12.0).reshape(4, 3) / 7, q])
    dets = [
        Detection(0, 0.0, [1.5, 2.25, 100.125, 200.0], "chair", 0.9, 0),
        Detection(1, 0.11, [0, 0, 1e-5, 3e10], "class28", 1 / 3, None),
        Detection(3, 1341841278.85, [5, 5, 6, 7], "suitcase", 0.42, 7),
    ]
    objs = [
        GroundTruthObject(0, "chair", Cuboid.from_yaw([1, 2, 0.3], 0.7, [0.2, 0.3, 0.4])),
        GroundTruthObject(5, "suitcase", Cuboid(np.zeros(3), quat_to_matrix(q[1]), [1, 2, 3])),
    ]
    R1 = quat_to_matrix(q[3])
    ells = [
        EllipsoidDetection(0, 0.0, "chair", np.eye(3), [0.1, -0.2, 2.5], [0.3, 0.25, 0.5], 0),
        EllipsoidDetection(1, 0.101, "table", R1, [1 / 3, 1e-9, 7e3], [2e-3, 1.5, 1 / 7], None),
        EllipsoidDetection(3, 1341841278.83, "suitcase", -R1[:, ::-1], [0, 0, 1], [1, 1, 1], -2),
    ]
    priors = Priors(
        [np.array([0, 0, 1.0, 0]), np.array([0, 1.0, 0, -1e-7])],
        np.array([0, 0, 1.0]),
        {"chair": ClassPrior([0.3, 0.3, 0.5], 0.05), "table": ClassPrior([1, 1, 0.4], 2e-12, "cuboid")},
        np.array([0.003, 1e-3]),
    )
    gt = np.column_stack([t + 0.001, poses])
    return Sequence("syn", cam, t, poses, dets, objs, gt, priors, {0.0: "/data/img 0.png".replace(" ", "_")}, ells)


def test_round_trip(tmp_path):
    seq = synthetic()
    out = write_sequence(seq, tmp_path / "syn")
    back = read_sequence(out)
    assert back == seq
    assert back.images[0.0] == Path("/data/img_0.png")
    assert back.ellipsoids == seq.ellipsoids and len(back.ellipsoids) == 3
    # equality sees every field of a measured ellipsoid, and its presence
    e = seq.ellipsoids[1]
    for change in ({"radii": e.radii * (1 + 1e-9)}, {"instance": 0}, {"label": "chair"},
                   {"center": e.center + [0, 1e-9, 0]}, {"rotation": -e.rotation[:, [1, 0, 2]]}):
        other = EllipsoidDetection(**{**{k: getattr(e, k) for k in e.__dataclass_fields__}, **change})
        assert other != e
        assert dataclasses.replace(seq, ellipsoids=[seq.ellipsoids[0], other, seq.ellipsoids[2]]) != seq
    assert dataclasses.replace(seq, ellipsoids=None) != seq
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries left
    # a minimal one: no optional parts
    bare = Sequence("bare", seq.camera, seq.timestamps, seq.poses_tum, [])
    assert read_sequence(write_sequence(bare, tmp_path / "bare")) == bare
    assert sorted(p.name for p in (tmp_path / "bare").iterdir()) == ["camera.yaml", "detections.txt", "trajectory.txt"]


def test_round_trip_relative_images(tmp_path):
    folder = make(tmp_path / "seq", **{"rgb.txt": "1.0 rgb/1.png\n"})
    s = read_sequence(folder)
    write_sequence(s, folder, overwrite=True)
    assert "1.0 rgb/1.png" in (folder / "rgb.txt").read_text()
    assert read_sequence(folder) == s


def test_write_is_atomic(tmp_path):
    seq = synthetic()
    write_sequence(seq, tmp_path / "syn")
    with pytest.raises(FileExistsError):
        write_sequence(seq, tmp_path / "syn")
    bad = Sequence("x", seq.camera, seq.timestamps, seq.poses_tum, [Detection(0, 0.0, [0, 0, 1, 1], "two words", 1.0)])
    with pytest.raises(ValueError):
        write_sequence(bad, tmp_path / "syn", overwrite=True)
    assert read_sequence(tmp_path / "syn") == seq  # the old folder survives intact
    with pytest.raises(ValueError):
        write_sequence(bad, tmp_path / "new")
    assert not (tmp_path / "new").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["syn"]
    write_sequence(bare := Sequence("b", seq.camera, seq.timestamps, seq.poses_tum, []), tmp_path / "syn", overwrite=True)
    assert read_sequence(tmp_path / "syn") == Sequence("syn", *list(bare.__dict__.values())[1:])


# --- the TUM fr3_cabinet importer -----------------------------------------------------------


def fr3_copy(tmp_path, n=3) -> Path:
    """A small synthetic folder in the fr3_cabinet layout."""
    f = tmp_path / "fr3"
    (f / "bbox").mkdir(parents=True)
    (f / "TUM3.yaml").write_text("%YAML:1.0\n# c\nCamera.fx: 535.4\nCamera.fy: 539.2\nCamera.cx: 320.1\nCamera.cy: 247.6\nCamera.k1: 0.0\n")
    (f / "groundtruth.txt").write_text("".join(f"{10 + i}.5 0 0 1 0 0 0 1\n" for i in range(n)))
    (f / "truth_objects.txt").write_text("-1.5 0.45 0.28 3.1 0.39 0.22 0.27 \n")
    (f / "bbox" / "10.5.txt").write_text("0 175 24 560 397 28 0.42 0\n")
    (f / "bbox" / "11.5.txt").write_text("")
    (f / "bbox" / "12.5.txt").write_text("0 1 2 3 4 5 0.5 0\n")
    return f


def test_fr3_layout_small(tmp_path):
    s = read_sequence(fr3_copy(tmp_path))
    assert s.camera == Camera(535.4, 539.2, 320.1, 247.6, 640, 480)
    assert [(d.frame, d.label) for d in s.detections] == [(0, "suitcase"), (2, "class5")]
    assert s.objects_gt[0].id == 0 and s.objects_gt[0].label == "object"  # instance 0 has two labels
    np.testing.assert_allclose(s.priors.support_planes[0], [0, 0, 1, 0])
    np.testing.assert_allclose(s.priors.up, [0, 0, 1])


@pytest.mark.parametrize(
    "where, text, expected",
    [
        ("bbox/11.5.txt", "0 1 2 3 4 28 0.5\n", "8 columns"),
        ("bbox/11.5.txt", "0 9 2 3 4 28 0.5 0\n", "x2 > x1"),
        ("bbox/11.5.txt", "0 1 2 3 4 suitcase 0.5 0\n", "COCO class index"),
        ("bbox/13.9.txt", "0 1 2 3 4 28 0.5 0\n", "within 0.02 s"),
        ("TUM3.yaml", "%YAML:1.0\nCamera.fx: 535.4\nCamera.fy: nan\n", "finite number"),
        ("truth_objects.txt", "1 2 3 0.1 0.5 0.5\n", "7 columns"),
    ],
)
def test_fr3_layout_errors(tmp_path, where, text, expected):
    f = fr3_copy(tmp_path)
    (f / where).write_text(text)
    msg = error(f)
    assert msg.startswith(f"{f / where}"), msg
    assert expected in msg, msg


def test_fr3_cabinet_reference_data(tmp_path):
    if not FR3.is_dir():
        pytest.skip(f"{FR3} (…/tum_fr3_cabinet) not found")
    s = import_fr3_cabinet(FR3)
    assert read_sequence(FR3) == s
    assert len(s) == 58 and s.poses_tum.shape == (58, 7)
    assert len({d.frame for d in s.detections}) == 51
    assert all(d.label == "suitcase" and d.instance == 0 for d in s.detections)
    assert len(s.objects_gt) == 1 and s.objects_gt[0].label == "suitcase"
    np.testing.assert_allclose(s.objects_gt[0].cuboid.center, [-1.53, 0.456, 0.282], atol=2e-3)
    assert s.camera == Camera(535.4, 539.2, 320.1, 247.6, 640, 480)
    np.testing.assert_array_equal(s.groundtruth_tum[:, 0], s.timestamps)
    assert len(s.images) == 58 and all(p.is_file() for p in s.images.values())
    back = read_sequence(write_sequence(s, tmp_path / "tum_fr3_cabinet"))
    assert back == s


def test_box_faults_is_check_boxs_rule(rng):
    """The array form of the box rule refuses exactly the boxes ``check_box`` refuses."""
    from spdslam.io._parse import box_faults, check_box

    boxes = rng.uniform(-100, 800, size=(400, 4))
    boxes[::7, 2] = boxes[::7, 0]  # zero width
    boxes[::11, 1] = np.nan
    cam = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)
    for camera in (None, cam):
        faults = box_faults(boxes, camera)
        for b, f in zip(boxes, faults):
            try:
                check_box("f", 1, b, camera)
                refused = False
            except ValueError:
                refused = True
            assert refused == f
        assert 0 < faults.sum() < len(boxes)
