"""Quadric-SVD initialisation recovers a noise-free ellipsoid from 3 or more views."""

import numpy as np
import pytest

from spdslam import Camera, Ellipsoid, look_at, project_box, spd
from spdslam.frontend import InitializationError, svd_initialize
from spdslam.synthetic import random_rotations

CAM = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)


def views(center, n, rng, spread=np.pi):
    az = rng.uniform(0, spread, n)
    el = rng.uniform(0.1, 0.6, n)
    d = rng.uniform(4.0, 6.0, n)
    eyes = center + d[:, None] * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    return [look_at(e, center + 0.05 * rng.normal(size=3)) for e in eyes]


@pytest.mark.parametrize("n_views", [3, 4, 10])
def test_svd_recovers_noise_free_ellipsoids(n_views):
    rng = np.random.default_rng(n_views)
    for R in random_rotations(rng, 10):
        truth = Ellipsoid.from_axes(R, rng.uniform(-1, 1, 3), rng.uniform(0.2, 1.0, 3))
        poses = views(np.asarray(truth.center), n_views, rng)
        boxes = [np.asarray(project_box(truth, T, CAM)) for T in poses]
        est = svd_initialize(boxes, poses, CAM)
        assert float(spd.distance(est.P, truth.P)) < 1e-6
        np.testing.assert_allclose(est.center, truth.center, atol=1e-7)


def test_svd_with_noisy_boxes_is_close():
    rng = np.random.default_rng(7)
    truth = Ellipsoid.from_axes(np.eye(3), [0.2, -0.1, 0.4], [0.8, 0.5, 0.3])
    poses = views(np.asarray(truth.center), 12, rng, spread=2 * np.pi)
    boxes = [np.asarray(project_box(truth, T, CAM)) + rng.normal(scale=1.0, size=4) for T in poses]
    est = svd_initialize(boxes, poses, CAM)
    assert np.linalg.norm(np.asarray(est.center - truth.center)) < 0.1
    np.testing.assert_allclose(np.sort(np.asarray(est.radii)), [0.3, 0.5, 0.8], atol=0.1)


def test_too_few_or_degenerate_views_are_reported():
    rng = np.random.default_rng(8)
    truth = Ellipsoid.from_axes(np.eye(3), [0.0, 0.0, 0.0], [0.8, 0.5, 0.3])
    poses = views(np.zeros(3), 2, rng)
    boxes = [np.asarray(project_box(truth, T, CAM)) for T in poses]
    with pytest.raises(InitializationError, match="at least 3 views"):
        svd_initialize(boxes, poses, CAM)
    same = [poses[0]] * 4  # one viewpoint repeated: 4 distinct planes only
    with pytest.raises(InitializationError, match="do not determine"):
        svd_initialize([boxes[0]] * 4, same, CAM)
    with pytest.raises(ValueError, match="boxes but"):
        svd_initialize(boxes, poses[:1], CAM)
