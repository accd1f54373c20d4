"""Factors as columns (``FactorBatch``): the same problem as the factors one by one."""

from __future__ import annotations

import jaxlie
import numpy as np
import pytest

import spdslam  # noqa: F401
from spdslam import Camera, Ellipsoid, look_at, project_box
from spdslam.factors import BetweenFactor, FactorBatch, Huber, InverseBoxFactor, PriorFactor
from spdslam.solver import L, LevenbergMarquardt, NonlinearFactorGraph, Problem, Values, X

CAM = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)


def _scene(n_poses: int = 30, n_objects: int = 3, seed: int = 0):
    """Poses on a circle around objects; noisy boxes per object; odometry steps."""
    rng = np.random.default_rng(seed)
    objs = [Ellipsoid.from_axes(np.eye(3), rng.uniform(-0.5, 0.5, 3), rng.uniform(0.1, 0.3, 3))
            for _ in range(n_objects)]
    poses = [look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 1.0]), np.zeros(3))
             for a in np.linspace(0, np.pi, n_poses)]
    boxes = {}
    for j, o in enumerate(objs):
        b = np.stack([np.asarray(project_box(o, T, CAM)) for T in poses]) + rng.normal(0, 2, (n_poses, 4))
        boxes[j] = np.c_[np.minimum(b[:, :2], b[:, 2:]), np.maximum(b[:, :2], b[:, 2:])]
    steps = [poses[i].inverse() @ poses[i + 1] for i in range(n_poses - 1)]
    values = Values()
    for i, T in enumerate(poses):
        values.insert(X(i), T @ jaxlie.SE3.exp(np.r_[rng.normal(0, 0.01, 6)]))
    for j, o in enumerate(objs):
        values.insert(L(j), Ellipsoid(np.asarray(o.P) * 1.2, np.asarray(o.center) + 0.05))
    return poses, boxes, steps, values


def _graphs(poses, boxes, steps, robust=None):
    """The same factors, one by one and as batches (the boxes of object 0 split between a
    batch and single factors, so that one group mixes both)."""
    n = len(poses)
    sigma = np.linspace(1.0, 3.0, 4)
    odo = np.r_[np.full(3, 0.01), np.full(3, 0.02)]
    one = NonlinearFactorGraph([PriorFactor(X(0), poses[0], sigma=1e-3)])
    many = NonlinearFactorGraph([PriorFactor(X(0), poses[0], sigma=1e-3)])
    one.extend(BetweenFactor(X(i), X(i + 1), s, sigma=odo) for i, s in enumerate(steps))
    many.add(BetweenFactor.many([X(i) for i in range(n - 1)], [X(i) for i in range(1, n)], steps, sigma=odo))
    one.extend(PriorFactor(X(i), poses[i], sigma=0.05) for i in range(1, n))
    many.add(PriorFactor.many([X(i) for i in range(1, n)], jaxlie.SE3(np.stack([p.wxyz_xyz for p in poses[1:]])),
                              sigma=0.05))
    for j, b in boxes.items():
        one.extend(InverseBoxFactor(X(i), L(j), b[i], CAM, sigma=sigma, robust=robust) for i in range(n))
        if j == 0:
            h = n // 2
            many.add(InverseBoxFactor.many([X(i) for i in range(h)], L(j), b[:h], CAM, sigma=sigma, robust=robust))
            many.extend(InverseBoxFactor(X(i), L(j), b[i], CAM, sigma=sigma, robust=robust) for i in range(h, n))
        else:
            many.add(InverseBoxFactor.many([X(i) for i in range(n)], L(j), b, CAM, sigma=sigma, robust=robust))
    return one, many


def test_a_batch_is_the_factors_one_by_one():
    poses, boxes, steps, values = _scene()
    one, many = _graphs(poses, boxes, steps, robust=Huber(2.0))
    assert len(one) == len(many) and len(many.entries()) < len(one.entries())
    assert [f.keys for f in one] == [f.keys for f in many] == [f.keys for f in many.factors]
    assert one.keys() == many.keys()
    for a, b in zip(one, many):
        assert type(a) is type(b) and a.robust == b.robust
        np.testing.assert_array_equal(a.sqrt_info, b.sqrt_info)
        (la, ta, sa), (lb, tb, sb) = a.flat_args(), b.flat_args()
        assert ta == tb and sa == sb
        for x, y in zip(la, lb):
            np.testing.assert_array_equal(x, y)
    pa, pb = Problem(one, values), Problem(many, values)
    assert [len(f) for f in pa.group_fids] == [len(f) for f in pb.group_fids]
    for fa, fb in zip(pa.group_fids, pb.group_fids):
        np.testing.assert_array_equal(fa, fb)
    ha, ga, ca, _, _ = pa.linearize(pa.vars)
    hb, gb, cb, _, _ = pb.linearize(pb.vars)
    np.testing.assert_array_equal(ha, hb)
    np.testing.assert_array_equal(ga, gb)
    assert ca == cb and pa.cost_by_kind() == pb.cost_by_kind()
    ra = LevenbergMarquardt(max_iterations=5).optimize(one, values)
    rb = LevenbergMarquardt(max_iterations=5).optimize(many, values)
    assert ra.final_cost == rb.final_cost
    for k in values.keys():
        np.testing.assert_array_equal(np.asarray(ra.values[k].P if hasattr(ra.values[k], "P") else
                                                 ra.values[k].wxyz_xyz),
                                      np.asarray(rb.values[k].P if hasattr(rb.values[k], "P") else
                                                 rb.values[k].wxyz_xyz))


def test_batches_index_iterate_and_take_a_kernel():
    poses, boxes, steps, _ = _scene(n_poses=6, n_objects=1)
    b = InverseBoxFactor.many([X(i) for i in range(6)], L(0), boxes[0], CAM)
    assert isinstance(b, FactorBatch) and len(b) == 6 and b.kind == "inverse_box"
    assert b[-1].keys == (X(5), L(0)) and [f.keys for f in b][2] == (X(2), L(0))
    with pytest.raises(IndexError):
        b[6]
    r = b.with_robust(Huber(1.0))
    assert r.robust == Huber(1.0) and b.robust is None and all(f.robust == Huber(1.0) for f in r)
    with pytest.raises(AttributeError, match="immutable"):
        b.robust = None
    empty = InverseBoxFactor.many([], L(0), np.zeros((0, 4)), CAM)
    assert len(empty) == 0 and len(NonlinearFactorGraph([empty])) == 0
    with pytest.raises(ValueError, match="2 first keys and 1 second keys"):
        BetweenFactor.many([X(0), X(1)], [X(1)], steps[:1])
    with pytest.raises(ValueError, match="2 factors but 1 relative poses"):
        BetweenFactor.many([X(0), X(1)], [X(1), X(2)], steps[:1])
    with pytest.raises(ValueError, match="sigma must be finite and positive"):
        PriorFactor.many([X(0)], poses[:1], sigma=0.0)
    with pytest.raises(TypeError, match="expected a Factor or FactorBatch"):
        NonlinearFactorGraph([b, "not a factor"])


def test_batch_errors_name_the_factor():
    poses, boxes, steps, values = _scene(n_poses=6, n_objects=1)
    g = NonlinearFactorGraph([InverseBoxFactor.many([X(i) for i in range(6)], L(0), boxes[0], CAM)])
    without = Values({k: v for k, v in values.items() if k != X(4)})
    with pytest.raises(ValueError, match=r"factor #4 \(InverseBoxFactor, keys .*\) refers to key .* which has no value"):
        Problem(g, without)
    twice = NonlinearFactorGraph([BetweenFactor.many([X(0), X(2)], [X(1), X(2)], steps[:2])])
    with pytest.raises(ValueError, match=r"factor #1 \(BetweenFactor.*uses a key more than once"):
        Problem(twice, values)


def test_a_key_column_of_mixed_types_is_laid_out_one_by_one():
    """Box factors take any parameterisation: a batch whose landmarks are of two types
    gives the same problem as its factors one by one."""
    from spdslam import EllipsoidRTS

    poses, boxes, steps, values = _scene(n_poses=6, n_objects=2)
    values = values.copy()
    values[L(1)] = EllipsoidRTS.from_ellipsoid(values[L(1)])
    keys = [L(0), L(1)] * 3
    b = np.concatenate([boxes[0][:3], boxes[1][3:]])[[0, 3, 1, 4, 2, 5]]
    mixed = InverseBoxFactor.many([X(i) for i in range(6)], keys, b, CAM)
    fixed = [X(i) for i in range(6)]
    pa = Problem(NonlinearFactorGraph(list(mixed)), values, fixed)
    pb = Problem(NonlinearFactorGraph([mixed]), values, fixed)
    assert len(pa.gspecs) == len(pb.gspecs) == 2
    ha, ga, ca, _, _ = pa.linearize(pa.vars)
    hb, gb, cb, _, _ = pb.linearize(pb.vars)
    np.testing.assert_array_equal(ha, hb)
    np.testing.assert_array_equal(ga, gb)
    assert ca == cb


def test_the_batched_solver_takes_a_list_with_batches():
    """A plain list holding a FactorBatch is laid out like the same factors one by one by
    the batched solver too."""
    from spdslam.solver import BatchedProblem

    poses, boxes, steps, values = _scene(n_poses=6, n_objects=1)
    one, many = _graphs(poses, boxes, steps)
    a = BatchedProblem(list(one), values)
    b = BatchedProblem(many.entries(), values)
    assert len(a.factors) == len(b.factors) and [f.keys for f in a.factors] == [f.keys for f in b.factors]
