"""The synthetic room generator ``spdslam.synthetic.make_room_sequence``."""

from __future__ import annotations

import dataclasses
import itertools
import time

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from spdslam import Camera, Ellipsoid, camera_inside, in_front, project_box
from spdslam.synthetic import MARGIN_PX, MIN_BOX_PX, ROOM_CLASSES, make_room_sequence
from spdslam.evaluation import cuboid_iou_batch
from spdslam.geometry.se3 import from_tum
from spdslam.io import read_sequence, write_sequence
from spdslam.synthetic import DEFAULT_CAMERA


@pytest.fixture(scope="module")
def default_seq():
    return make_room_sequence()


@pytest.fixture(scope="module")
def clean_seq():
    return make_room_sequence(3, box_noise_px=0.0)


def _arrays(seq):
    frame = np.array([d.frame for d in seq.detections])
    inst = np.array([d.instance for d in seq.detections])
    boxes = np.array([d.box for d in seq.detections])
    return frame, inst, boxes


def test_deterministic():
    a, b = make_room_sequence(5), make_room_sequence(5)
    assert a == b
    c = make_room_sequence(6)
    assert a != c
    assert not np.allclose(a.groundtruth_tum, c.groundtruth_tum)


def test_contents(default_seq):
    s = default_seq
    assert s.name == "demo_room" and s.camera == DEFAULT_CAMERA and len(s) == 120
    np.testing.assert_allclose(s.timestamps, 0.1 * np.arange(120), atol=1e-12)
    assert s.groundtruth_tum.shape == (120, 8)
    np.testing.assert_array_equal(s.groundtruth_tum[:, 0], s.timestamps)
    assert len(s.objects_gt) == 8 and [o.id for o in s.objects_gt] == list(range(8))
    labels = {o.id: o.label for o in s.objects_gt}
    assert set(labels.values()) <= set(ROOM_CLASSES)
    for d in s.detections:
        assert d.label == labels[d.instance] and d.score == 1.0
        assert d.timestamp == s.timestamps[d.frame]
    frame, inst, _ = _arrays(s)
    order = frame * 8 + inst
    assert np.all(np.diff(order) > 0)  # frame-major, one detection per (frame, object)
    # Priors: the floor, +z up, the class means of the labels present.
    p = s.priors
    assert len(p.support_planes) == 1
    np.testing.assert_array_equal(p.support_planes[0], [0, 0, 1, 0])
    np.testing.assert_array_equal(p.up, [0, 0, 1])
    assert set(p.classes) == set(labels.values())
    for label, cp in p.classes.items():
        np.testing.assert_array_equal(cp.radii, ROOM_CLASSES[label])
        assert cp.sigma == 0.2


@pytest.mark.parametrize("seed", [0, 1, 2, 7])
def test_every_object_seen_many_times(seed):
    s = make_room_sequence(seed)
    _, inst, _ = _arrays(s)
    counts = np.bincount(inst, minlength=8)
    assert counts.min() >= 10, counts


def test_boxes_inside_image(default_seq, clean_seq):
    cam = default_seq.camera
    for s in (default_seq, clean_seq):
        _, _, b = _arrays(s)
        assert np.all(b[:, 2] > b[:, 0]) and np.all(b[:, 3] > b[:, 1])
        assert np.all(b[:, :2] >= 0) and np.all(b[:, 2] <= cam.width) and np.all(b[:, 3] <= cam.height)
    _, _, b = _arrays(clean_seq)
    assert np.all(b[:, :2] >= MARGIN_PX)
    assert np.all(b[:, 2] <= cam.width - MARGIN_PX) and np.all(b[:, 3] <= cam.height - MARGIN_PX)
    assert np.all(b[:, 2:] - b[:, :2] >= MIN_BOX_PX)


def _truth(seq):
    """Batched true ellipsoids (from the ground-truth cuboids) and poses."""
    R = np.stack([o.cuboid.rotation for o in seq.objects_gt])
    t = np.stack([o.cuboid.center for o in seq.objects_gt])
    s = np.stack([o.cuboid.half_extents for o in seq.objects_gt])
    P = np.einsum("nij,nj,nkj->nik", R, s**2, R)
    poses = from_tum(seq.groundtruth_tum[:, 1:])
    return P, t, poses


def test_noise_free_boxes_are_the_projected_ellipsoids(clean_seq):
    s = clean_seq
    P, t, poses = _truth(s)
    frame, inst, boxes = _arrays(s)
    cam = s.camera

    def one(P, t, w):
        e, T = Ellipsoid(P, t), jaxlie.SE3(w)
        return project_box(e, T, cam), in_front(e, T, 0.1), camera_inside(e, T)

    want, front, inside = jax.vmap(one)(
        jnp.asarray(P[inst]), jnp.asarray(t[inst]), poses.wxyz_xyz[frame]
    )
    np.testing.assert_allclose(boxes, np.asarray(want), rtol=0, atol=1e-6)
    assert np.all(np.asarray(front)) and not np.any(np.asarray(inside))


def test_box_noise_only_perturbs(clean_seq):
    noisy = make_room_sequence(3)  # same seed, box_noise_px = 2
    clean = {(d.frame, d.instance): d.box for d in clean_seq.detections}
    keys = [(d.frame, d.instance) for d in noisy.detections]
    assert set(keys) <= set(clean) and len(keys) >= 0.9 * len(clean)
    diff = np.array([d.box - clean[k] for d, k in zip(noisy.detections, keys)])
    assert 1.5 < diff.std() < 2.5
    np.testing.assert_array_equal(noisy.groundtruth_tum, clean_seq.groundtruth_tum)


def test_drift():
    drifting = make_room_sequence(1, drift=0.02)
    exact = make_room_sequence(1, drift=0.0)
    gt = drifting.groundtruth_tum[:, 1:]
    np.testing.assert_array_equal(gt, exact.groundtruth_tum[:, 1:])
    np.testing.assert_allclose(exact.poses_tum, gt, atol=1e-12)
    np.testing.assert_allclose(drifting.poses_tum[0], gt[0], atol=1e-12)
    err = np.linalg.norm(drifting.poses_tum[:, :3] - gt[:, :3], axis=1)
    assert err[1] > 0 and err[-1] > 0.05  # accumulates
    assert np.all(np.abs(np.linalg.norm(drifting.poses_tum[:, 3:], axis=1) - 1) < 1e-12)
    # Only the trajectory depends on the drift.
    assert drifting.detections == exact.detections
    assert drifting.objects_gt == exact.objects_gt


def test_camera_loop(default_seq):
    g = default_seq.groundtruth_tum
    c = g[:, 1:4]
    assert np.all((c[:, 2] > 1.1) & (c[:, 2] < 1.6))
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    closing = np.linalg.norm(c[0] - c[-1])
    assert closing < 2 * steps.max()  # a closed loop
    assert steps.max() < 1.5 * np.median(steps)  # evenly spaced


@pytest.mark.parametrize("seed, objects", [(0, 8), (4, 40)])
def test_objects_rest_on_the_floor_without_overlap(seed, objects):
    s = make_room_sequence(seed, frames=10, objects=objects)
    cub = [o.cuboid for o in s.objects_gt]
    for q in cub:
        assert abs(q.center[2] - q.half_extents[2]) < 1e-12  # bottom at z = 0
        np.testing.assert_allclose(q.rotation[:, 2], [0, 0, 1], atol=1e-12)
    xy = np.stack([q.center[:2] for q in cub])
    rho = np.array([np.hypot(*q.half_extents[:2]) for q in cub])
    pairs = list(itertools.combinations(range(objects), 2))
    i, j = np.array(pairs).T
    assert np.all(np.linalg.norm(xy[i] - xy[j], axis=1) > rho[i] + rho[j])
    assert np.all(cuboid_iou_batch([cub[k] for k in i], [cub[k] for k in j]) == 0.0)
    # Radii within the jitter of their class means.
    for o in s.objects_gt:
        ratio = o.cuboid.half_extents / np.array(ROOM_CLASSES[o.label])
        assert np.all((ratio >= 0.9 - 1e-12) & (ratio <= 1.1 + 1e-12))


def test_options():
    cam = Camera(525.0, 525.0, 319.5, 239.5, 640.0, 480.0)
    s = make_room_sequence(2, frames=30, objects=3, camera=cam, size_jitter=0.0, room_size=9.0,
                           name="tiny")
    assert s.name == "tiny" and s.camera == cam and len(s) == 30
    for o in s.objects_gt:
        np.testing.assert_allclose(o.cuboid.half_extents, ROOM_CLASSES[o.label], atol=1e-12)
        assert np.all(np.abs(o.cuboid.center[:2]) < 4.5)
    assert np.all(np.abs(s.groundtruth_tum[:, 1:3]) < 4.5)


def test_round_trip(tmp_path, default_seq):
    folder = write_sequence(default_seq, tmp_path / default_seq.name)
    assert read_sequence(folder) == default_seq


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"frames": 2}, "frames"),
        ({"frames": 10.5}, "frames"),
        ({"objects": 0}, "objects"),
        ({"objects": True}, "objects"),
        ({"seed": -1}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"box_noise_px": -1.0}, "box_noise_px"),
        ({"box_noise_px": float("nan")}, "box_noise_px"),
        ({"drift": -0.1}, "drift"),
        ({"drift": float("inf")}, "drift"),
        ({"size_jitter": 1.0}, "size_jitter"),
        ({"size_jitter": -0.1}, "size_jitter"),
        ({"room_size": 0.0}, "room_size"),
        ({"room_size": 3.0}, "room_size"),
        ({"room_size": 8.0, "objects": 60}, "room_size"),
        ({"camera": "kinect"}, "camera"),
        ({"name": ""}, "name"),
        ({"name": "two words"}, "name"),
    ],
)
def test_argument_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_room_sequence(**kwargs)


def test_moderately_large():
    t0 = time.perf_counter()
    s = make_room_sequence(0, frames=2000, objects=50)
    elapsed = time.perf_counter() - t0
    _, inst, _ = _arrays(s)
    print(f"make_room_sequence(frames=2000, objects=50): {elapsed:.2f} s, {len(inst)} detections")
    assert len(s) == 2000 and len(s.objects_gt) == 50
    assert np.bincount(inst, minlength=50).min() >= 10


@pytest.mark.slow
@pytest.mark.parametrize("options", [{}, {"truncation": True, "outliers": 0.1}])
def test_benchmark_size(options):
    t0 = time.perf_counter()
    s = make_room_sequence(0, frames=20000, objects=500, **options)
    elapsed = time.perf_counter() - t0
    _, inst, _ = _arrays(s)
    true = inst[inst >= 0]
    print(f"make_room_sequence(frames=20000, objects=500, {options}): {elapsed:.2f} s, "
          f"{len(inst)} detections ({len(inst) - len(true)} false), "
          f"views per object min {np.bincount(true, minlength=500).min()}")
    assert np.bincount(true, minlength=500).min() >= 10
    assert len(inst) - len(true) == round(options.get("outliers", 0.0) * len(true))


# --- detector imperfections: truncation, missed and false detections, cuboid objects -------


#: Figures of sequences made before the options existed (the generator of commit 7ca56dd):
#: (kwargs, detections, sha256[:16] of the int64 frame and instance columns, Σ boxes,
#: Σ poses_tum). The defaults must keep reproducing them.
BEFORE_OPTIONS = [
    ({}, 567, "b0f43bb7496e48e4", 603521.323883481, 172.48163731532424),
    ({"seed": 3, "box_noise_px": 0.0}, 561, "4591ae0ef850b76f", 578415.9954732975, 170.497230908054),
    ({"seed": 4, "frames": 300, "objects": 40}, 1699, "d077bd9dcf738ecb", 1765890.102578139,
     241.16195751308834),
]

DEFAULT_OPTIONS = {"truncation": False, "outliers": 0.0, "missed": 0.0, "object_shape": "ellipsoid"}


@pytest.mark.parametrize("kwargs, n, digest, box_sum, pose_sum", BEFORE_OPTIONS)
def test_defaults_unchanged(kwargs, n, digest, box_sum, pose_sum):
    import hashlib

    s = make_room_sequence(**kwargs)
    frame, inst, boxes = _arrays(s)
    assert len(frame) == n
    ids = frame.astype(np.int64).tobytes() + inst.astype(np.int64).tobytes()
    assert hashlib.sha256(ids).hexdigest()[:16] == digest
    assert boxes.sum() == pytest.approx(box_sum, rel=1e-12)
    assert s.poses_tum.sum() == pytest.approx(pose_sum, rel=1e-12)
    assert all(d.score == 1.0 and d.instance >= 0 for d in s.detections)
    assert all(cp.shape == "ellipsoid" for cp in s.priors.classes.values())
    assert make_room_sequence(**kwargs, **DEFAULT_OPTIONS) == s


def test_new_streams_leave_the_first_five_alone():
    for seed in (0, 7):
        five = np.random.SeedSequence(seed).spawn(5)
        seven = np.random.SeedSequence(seed).spawn(7)[:5]
        for a, b in zip(five, seven):
            np.testing.assert_array_equal(
                np.random.default_rng(a).random(4), np.random.default_rng(b).random(4)
            )


ALL_ON = {"truncation": True, "outliers": 0.2, "missed": 0.1, "object_shape": "cuboid"}


def test_options_deterministic():
    a, b = make_room_sequence(5, **ALL_ON), make_room_sequence(5, **ALL_ON)
    assert a == b
    assert a != make_room_sequence(6, **ALL_ON)


@pytest.fixture(scope="module")
def clean_truncated():
    return make_room_sequence(3, box_noise_px=0.0, truncation=True)


def _on_border(boxes, cam):
    return (
        (boxes[:, 0] == 0) | (boxes[:, 1] == 0) | (boxes[:, 2] == cam.width) | (boxes[:, 3] == cam.height)
    )


def test_truncated_boxes_touch_the_border_and_stay_inside(default_seq):
    s = make_room_sequence(truncation=True)
    cam = s.camera
    _, inst, b = _arrays(s)
    border = _on_border(b, cam)
    assert border.sum() >= 20, border.sum()  # the camera path does produce truncation
    assert np.all(b[:, :2] >= 0) and np.all(b[:, 2] <= cam.width) and np.all(b[:, 3] <= cam.height)
    assert np.all(b[:, 2] > b[:, 0]) and np.all(b[:, 3] > b[:, 1])
    assert not np.any(_on_border(_arrays(default_seq)[2], cam))
    # everything is still a true detection with its object's label, frame-major
    frame, inst, _ = _arrays(s)
    assert np.all(np.diff(frame * 8 + inst) > 0)


def test_noise_free_truncated_boxes_are_clipped_projections(clean_seq, clean_truncated):
    s = clean_truncated
    P, t, poses = _truth(s)
    frame, inst, boxes = _arrays(s)
    cam = s.camera

    def one(P, t, w):
        e, T = Ellipsoid(P, t), jaxlie.SE3(w)
        return project_box(e, T, cam), in_front(e, T, 0.1), camera_inside(e, T)

    full, front, inside = jax.vmap(one)(
        jnp.asarray(P[inst]), jnp.asarray(t[inst]), poses.wxyz_xyz[frame]
    )
    full = np.asarray(full)
    np.testing.assert_allclose(
        boxes, np.clip(full, 0, [cam.width, cam.height] * 2), rtol=0, atol=1e-6
    )
    assert np.all(np.asarray(front)) and not np.any(np.asarray(inside))
    assert np.all(boxes[:, 2:] - boxes[:, :2] >= MIN_BOX_PX - 1e-9)  # visible part
    outside = (full[:, :2] < 0).any(1) | (full[:, 2] > cam.width) | (full[:, 3] > cam.height)
    assert outside.sum() >= 10
    # every detection of the untruncated sequence is there, with the same box
    got = {(d.frame, d.instance): d.box for d in s.detections}
    for d in clean_seq.detections:
        np.testing.assert_array_equal(got[(d.frame, d.instance)], d.box)


@pytest.mark.parametrize("shape", ["ellipsoid", "cuboid"])
def test_truncation_cull_is_conservative(monkeypatch, shape):
    """The bounding-sphere cull only saves work: without it the result is the same."""
    from spdslam.synthetic import _rooms

    kw = {"seed": 4, "frames": 300, "objects": 20, "truncation": True, "object_shape": shape}
    culled = make_room_sequence(**kw)
    monkeypatch.setattr(_rooms, "_frustum_planes", lambda camera: np.zeros((0, 3)))
    assert make_room_sequence(**kw) == culled


def test_missed_detections(default_seq):
    n = len(default_seq.detections)
    s = make_room_sequence(missed=0.25)
    assert len(s.detections) == n - round(0.25 * n)
    full = {(d.frame, d.instance): d for d in default_seq.detections}
    assert all(full[(d.frame, d.instance)] == d for d in s.detections)  # a subset, same noise
    frame, inst, _ = _arrays(s)
    assert np.all(np.diff(frame * 8 + inst) > 0)
    assert s.objects_gt == default_seq.objects_gt
    np.testing.assert_array_equal(s.poses_tum, default_seq.poses_tum)


def test_false_detections(default_seq):
    from spdslam.frontend import tracks_from_instances

    n = len(default_seq.detections)
    s = make_room_sequence(outliers=0.2)
    true = [d for d in s.detections if d.instance >= 0]
    false = [d for d in s.detections if d.instance < 0]
    assert true == default_seq.detections
    assert len(false) == round(0.2 * n)
    cam = s.camera
    fb = np.array([d.box for d in false])
    assert np.all(fb[:, :2] >= 0) and np.all(fb[:, 2] <= cam.width) and np.all(fb[:, 3] <= cam.height)
    tb = _arrays(default_seq)[2]
    gap = np.abs((fb[:, None, 2:] - fb[:, None, :2]) - (tb[None, :, 2:] - tb[None, :, :2]))
    assert np.all(gap.max(axis=2).min(axis=1) < 1e-9)  # each the size of some true box
    assert {d.instance for d in false} == {-1}
    scores = np.array([d.score for d in false])
    assert np.all((scores >= 0.3) & (scores <= 1.0)) and scores.std() > 0.1
    assert {d.label for d in false} == set(s.priors.classes)  # all present labels occur
    assert len({d.frame for d in false}) > 0.5 * len(false)
    # frame-major; in a frame the true detections come first
    key = [(d.frame, d.instance < 0) for d in s.detections]
    assert key == sorted(key)
    # manual association leaves them out
    got, want = tracks_from_instances(s), tracks_from_instances(default_seq)
    assert [k.id for k in got] == [k.id for k in want]
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a.frames, b.frames)
        np.testing.assert_array_equal(a.boxes, b.boxes)


def test_missed_then_false_counts():
    s = make_room_sequence(2, missed=0.3, outliers=0.15)
    n_true = sum(d.instance >= 0 for d in s.detections)
    n_all = len(make_room_sequence(2).detections)
    assert n_true == n_all - round(0.3 * n_all)
    assert len(s.detections) - n_true == round(0.15 * n_true)


def _corner_box(cuboid, tum, cam):
    """Box of the 8 projected corners of a cuboid, one detection, plain numpy."""
    from scipy.spatial.transform import Rotation

    R_wc, c = Rotation.from_quat(tum[3:]).as_matrix(), tum[:3]
    corners = [
        cuboid.center + cuboid.rotation @ (cuboid.half_extents * np.array(sg))
        for sg in itertools.product((-1, 1), repeat=3)
    ]
    X = np.array([R_wc.T @ (p - c) for p in corners])
    assert np.all(X[:, 2] > 0.1)
    u = cam.cx + cam.fx * X[:, 0] / X[:, 2]
    v = cam.cy + cam.fy * X[:, 1] / X[:, 2]
    return np.array([u.min(), v.min(), u.max(), v.max()])


@pytest.mark.parametrize("truncation", [False, True])
def test_cuboid_boxes_are_the_projected_corners(clean_seq, truncation):
    s = make_room_sequence(3, box_noise_px=0.0, object_shape="cuboid", truncation=truncation)
    cam = s.camera
    assert s.objects_gt == clean_seq.objects_gt
    assert {k: cp.shape for k, cp in s.priors.classes.items()} == {k: "cuboid" for k in s.priors.classes}
    dets = s.detections
    assert len(dets) > 100
    picks = list(range(0, len(dets), len(dets) // 25))
    if truncation:
        picks += list(np.flatnonzero(_on_border(_arrays(s)[2], cam))[:10])
    for k in picks:
        d = dets[k]
        want = _corner_box(s.objects_gt[d.instance].cuboid, s.groundtruth_tum[d.frame, 1:], cam)
        if truncation:
            want = np.clip(want, 0, [cam.width, cam.height] * 2)
        np.testing.assert_allclose(d.box, want, rtol=0, atol=1e-6)
    _, _, b = _arrays(s)
    if truncation:
        assert _on_border(b, cam).sum() >= 10
    else:
        assert np.all(b[:, :2] >= MARGIN_PX)
        assert np.all(b[:, 2] <= cam.width - MARGIN_PX) and np.all(b[:, 3] <= cam.height - MARGIN_PX)
    assert np.all(b[:, 2:] - b[:, :2] >= MIN_BOX_PX - 1e-9)
    # the inscribed ellipsoid's box lies inside the cuboid's
    cub = {(d.frame, d.instance): d.box for d in dets}
    if not truncation:
        shared = [(d, cub[k]) for d in clean_seq.detections if (k := (d.frame, d.instance)) in cub]
        assert len(shared) > 0.8 * len(clean_seq.detections)
        for d, cb in shared:
            assert np.all(d.box[:2] >= cb[:2] - 1e-9) and np.all(d.box[2:] <= cb[2:] + 1e-9)


def test_options_round_trip(tmp_path):
    s = make_room_sequence(1, frames=60, objects=4, **ALL_ON)
    assert any(d.instance == -1 for d in s.detections)
    folder = write_sequence(s, tmp_path / s.name)
    assert read_sequence(folder) == s


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"truncation": "yes"}, "truncation"),
        ({"truncation": 1}, "truncation"),
        ({"outliers": 1.0}, "outliers"),
        ({"outliers": -0.1}, "outliers"),
        ({"outliers": float("nan")}, "outliers"),
        ({"outliers": True}, "outliers"),
        ({"missed": 1.0}, "missed"),
        ({"missed": -0.5}, "missed"),
        ({"missed": "0.1"}, "missed"),
        ({"object_shape": "sphere"}, "object_shape"),
        ({"object_shape": None}, "object_shape"),
    ],
)
def test_option_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_room_sequence(**kwargs)


# --- the CLI's demo flags (the back end stubbed out: only the generated sequence matters) ---


@pytest.fixture
def demo_cli(monkeypatch, tmp_path):
    """(invoke, calls): run ``spdslam demo`` in-process with ``run_and_write`` recorded
    instead of run."""
    from conftest import cli_runner

    from spdslam import cli
    from spdslam.cli import _demo

    runner = cli_runner()
    calls = []
    monkeypatch.setattr(
        _demo, "run_and_write",
        lambda seq, method, out, *a, **k: calls.append((seq, method, out, a)),
    )

    def invoke(*args):
        return runner.invoke(cli.app, ["demo", *(str(a) for a in args)])

    yield invoke, calls


def test_cli_demo_flags(demo_cli, tmp_path):
    invoke, calls = demo_cli
    out = tmp_path / "d"
    r = invoke("--out", out, "--frames", 40, "--objects", 3, "--truncation", "--outliers", 0.2,
               "--missed", 0.1, "--cuboids", "--seed", 2)
    assert r.exit_code == 0, (r.stdout, r.stderr, r.exception)
    want = make_room_sequence(
        2, 40, 3, truncation=True, outliers=0.2, missed=0.1, object_shape="cuboid"
    )
    n_false = sum(d.instance < 0 for d in want.detections)
    assert n_false > 0 and f"({n_false} false)" in r.stdout
    assert read_sequence(out / "sequence") == dataclasses.replace(want, name="sequence")
    assert len(calls) == 1 and calls[0][0] == want and calls[0][2] == out / "run"
    # --no-truncation and no flags: the default sequence
    r = invoke("--out", out, "--frames", 40, "--objects", 3, "--no-truncation")
    assert r.exit_code == 0, (r.stdout, r.stderr, r.exception)
    assert read_sequence(out / "sequence") == make_room_sequence(0, 40, 3, name="sequence")


def test_cli_demo_no_ids(demo_cli, tmp_path):
    invoke, calls = demo_cli
    out = tmp_path / "d"
    r = invoke("--out", out, "--frames", 40, "--objects", 3)
    assert r.exit_code == 0, (r.stdout, r.stderr, r.exception)
    (out / "run").mkdir()  # as an earlier demo's run would be
    (out / "run" / "map.json").write_text("{}\n", encoding="utf-8")
    r = invoke("--out", out, "--frames", 40, "--objects", 3, "--outliers", 0.1, "--no-ids")
    assert r.exit_code == 0, (r.stdout, r.stderr, r.exception)
    # mapped with automatic association; the generator's ids are kept only to score it
    seq, _, run_out, args = calls[-1]
    assert run_out == out / "run" and calls[-1][1].associate == "auto"
    assert all(d.instance is not None for d in seq.detections)
    r = invoke("--out", out, "--frames", 40, "--objects", 3, "--no-ids", "--associate", "instances")
    assert r.exit_code == 2 and "expected auto" in r.stderr
    rows = [ln.split() for ln in (out / "sequence" / "detections.txt").read_text().splitlines()
            if not ln.startswith("#")]
    assert rows and all(len(r) == 7 for r in rows)
    got = read_sequence(out / "sequence")
    want = make_room_sequence(0, 40, 3, outliers=0.1)
    assert all(d.instance is None for d in got.detections)
    assert [(d.frame, d.label, d.score) for d in got.detections] == [
        (d.frame, d.label, d.score) for d in want.detections
    ]
    np.testing.assert_allclose(_arrays(got)[2], _arrays(want)[2], rtol=0, atol=1e-9)


@pytest.mark.parametrize("flag, value", [("--outliers", 1.5), ("--missed", -0.1), ("--missed", 1.0)])
def test_cli_demo_bad_fractions(demo_cli, tmp_path, flag, value):
    invoke, calls = demo_cli
    out = tmp_path / "d"
    r = invoke("--out", out, "--frames", 40, "--objects", 3, flag, value)
    assert r.exit_code == 2 and not calls and not out.exists()
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("spdslam: error: demo: " + flag[2:])
