"""The synthetic room generator ``spdslam.demo.make_room_sequence``."""

from __future__ import annotations

import itertools
import time

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from spdslam import Camera, Ellipsoid, camera_inside, in_front, project_box
from spdslam.demo import MARGIN_PX, MIN_BOX_PX, ROOM_CLASSES, make_room_sequence
from spdslam.evaluation import cuboid_iou_batch
from spdslam.se3 import from_tum
from spdslam.sequence import read_sequence, write_sequence
from spdslam.simulation import DEFAULT_CAMERA


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
def test_benchmark_size():
    t0 = time.perf_counter()
    s = make_room_sequence(0, frames=20000, objects=500)
    elapsed = time.perf_counter() - t0
    _, inst, _ = _arrays(s)
    print(f"make_room_sequence(frames=20000, objects=500): {elapsed:.2f} s, {len(inst)} detections, "
          f"views per object min {np.bincount(inst, minlength=500).min()}")
    assert np.bincount(inst, minlength=500).min() >= 10
