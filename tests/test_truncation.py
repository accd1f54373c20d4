"""Truncated detections: box edges at the image border carry no bound."""

from __future__ import annotations

import numpy as np
import pytest

import spdslam  # noqa: F401  (float64)
from spdslam import Camera, Ellipsoid, look_at
from spdslam.geometry import project_box, project_cuboid_box, truncation_mask
from spdslam.factors import (
    DEFAULT_TRUNCATION_MARGIN,
    InverseBoxFactor,
    InverseCuboidBoxFactor,
    SemiInverseBoxFactor,
    SemiInverseCuboidBoxFactor,
    inverse_box_residual,
)
from spdslam.frontend import InitializationError, multi_initialize, MultiFit, svd_initialize
from spdslam.solver import LevenbergMarquardt, NonlinearFactorGraph, Values

CAM = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)
FACTORS = {
    InverseBoxFactor: project_box,
    SemiInverseBoxFactor: project_box,
    InverseCuboidBoxFactor: project_cuboid_box,
    SemiInverseCuboidBoxFactor: project_cuboid_box,
}


def _clip(box):
    return np.clip(box, 0.0, [CAM.width, CAM.height, CAM.width, CAM.height])


def _object():
    c, s = np.cos(0.5), np.sin(0.5)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return Ellipsoid.from_axes(R, [0.3, -0.2, 0.35], [0.6, 0.4, 0.35])


def _views(e, n=8, seed=0):
    """n views around the object; every other one aims beside it so that the object leaves
    the image on one side (a truncated box)."""
    rng = np.random.default_rng(seed)
    t = np.asarray(e.center)
    poses, cut = [], []
    for k, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False)):
        eye = t + np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 1.0 + 0.3 * rng.uniform()])
        side = np.array([-np.sin(a), np.cos(a), 0.0])
        aim = t + (0.0 if k % 2 == 0 else (-1.0) ** (k // 2) * 1.8) * side
        poses.append(look_at(eye, aim))
        cut.append(k % 2 == 1)
    return poses, np.array(cut)


def test_truncation_mask():
    boxes = np.array([[0.0, 3.0, 100.0, 200.0], [10.0, 10.0, 636.0, 476.0], [6.0, 6.0, 634.0, 474.0]])
    np.testing.assert_array_equal(
        truncation_mask(boxes, CAM, 5.0), [[0, 0, 1, 1], [1, 1, 0, 0], [1, 1, 1, 1]]
    )
    np.testing.assert_array_equal(truncation_mask(boxes, CAM, None), np.ones((3, 4)))
    assert DEFAULT_TRUNCATION_MARGIN == 5.0
    # NumPy in, NumPy out (graph building calls it per factor); JAX in (or traced), JAX out
    import jax
    import jax.numpy as jnp

    assert type(truncation_mask(boxes, CAM, 5.0)) is np.ndarray
    jmask = jax.jit(lambda b: truncation_mask(b, CAM, 5.0))(jnp.asarray(boxes))
    assert isinstance(jmask, jax.Array)
    np.testing.assert_array_equal(jmask, truncation_mask(boxes, CAM, 5.0))


@pytest.mark.parametrize("factor", list(FACTORS), ids=lambda f: f.__name__)
def test_clipped_edges_give_zero_residual(factor):
    e = _object()
    poses, cut = _views(e)
    box_of = FACTORS[factor]
    n_cut = 0
    for T, c in zip(poses, cut):
        raw = np.asarray(box_of(e, T, CAM))
        box = _clip(raw)
        f = factor("x", "l", box, CAM, truncation_margin=5.0)
        keep = f.args[2]
        np.testing.assert_array_equal(keep, np.asarray(truncation_mask(box, CAM, 5.0)))
        assert (keep == 0).any() == bool(c)
        n_cut += int((keep == 0).sum())
        r = np.asarray(f.evaluate(T, e))
        assert np.max(np.abs(r)) < 1e-7  # kept edges are exact, clipped ones masked
        if c:  # without the mask the clipped edge is a (wrong) bound
            plain = factor("x", "l", box, CAM)
            assert len(plain.args) == 2
            assert np.max(np.abs(np.asarray(plain.evaluate(T, e)))) > 1.0
    assert n_cut >= 4


def test_residual_without_keep_is_unchanged():
    e = _object()
    T = _views(e)[0][0]
    box = np.asarray(project_box(e, T, CAM)) + 3.0
    np.testing.assert_array_equal(
        inverse_box_residual(T, e, box, CAM), inverse_box_residual(T, e, box, CAM, np.ones(4))
    )


def test_svd_initialize_drops_truncated_planes():
    e = _object()
    poses, _ = _views(e, n=10)
    boxes = np.stack([_clip(np.asarray(project_box(e, T, CAM))) for T in poses])
    est = svd_initialize(boxes, poses, CAM, truncation_margin=5.0)
    np.testing.assert_allclose(est.P, e.P, atol=1e-6)
    np.testing.assert_allclose(est.center, e.center, atol=1e-6)
    biased = svd_initialize(boxes, poses, CAM)
    assert np.abs(np.asarray(biased.P) - np.asarray(e.P)).max() > 1e-3
    # three views with every u edge cut: 6 untruncated edges < 9
    wide = np.array([[0.0, 100.0, 640.0, 300.0]] * 3)
    with pytest.raises(InitializationError, match="only 6 untruncated box edges"):
        svd_initialize(wide, poses[:3], CAM, truncation_margin=5.0)


@pytest.mark.parametrize("shape", ["ellipsoid", "cuboid"])
def test_multi_initialize_is_not_biased_by_truncated_boxes(shape):
    e = _object()
    poses, _ = _views(e)
    box_of = project_cuboid_box if shape == "cuboid" else project_box
    boxes = np.stack([_clip(np.asarray(box_of(e, T, CAM))) for T in poses])
    kw = {"up": [0, 0, 1], "support_plane": [0, 0, 1, 0]}
    est = multi_initialize(boxes, poses, CAM, fit=MultiFit(shape=shape, truncation_margin=5.0), **kw)
    np.testing.assert_allclose(est.P, e.P, atol=1e-5)
    np.testing.assert_allclose(est.center, e.center, atol=1e-5)
    biased = multi_initialize(boxes, poses, CAM, fit=MultiFit(shape=shape), **kw)
    assert np.abs(np.asarray(biased.P) - np.asarray(e.P)).max() > 1e-2
    with pytest.raises(InitializationError, match="every box edge is truncated"):
        multi_initialize(np.array([[0.0, 0.0, 640.0, 480.0]] * 2), poses[:2], CAM,
                         up=[0, 0, 1], fit=MultiFit(truncation_margin=5.0))


def test_back_end_fit_is_not_biased_by_truncated_boxes():
    """LM on box factors with fixed poses, from a perturbed start: with the truncation mask
    the object is recovered; without it the clipped edges pull it into the image."""
    e = _object()
    poses, _ = _views(e)
    start = Ellipsoid.from_axes(np.eye(3), np.asarray(e.center) + [0.05, -0.04, 0.03],
                                [0.5, 0.45, 0.3])

    def solve(margin):
        graph, values = NonlinearFactorGraph(), Values()
        values["o"] = start
        for i, T in enumerate(poses):
            values[("x", i)] = T
            box = _clip(np.asarray(project_box(e, T, CAM)))
            graph.add(InverseBoxFactor(("x", i), "o", box, CAM, sigma=2.0, truncation_margin=margin))
        fixed = [("x", i) for i in range(len(poses))]
        return LevenbergMarquardt(max_iterations=100).optimize(graph, values, fixed=fixed).values["o"]

    good = solve(5.0)
    np.testing.assert_allclose(good.P, e.P, atol=1e-5)
    np.testing.assert_allclose(good.center, e.center, atol=1e-5)
    bad = solve(None)
    assert np.linalg.norm(np.asarray(bad.center) - np.asarray(e.center)) > 0.01
