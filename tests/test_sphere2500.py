"""spdslam's LM against gtsam's on gtsam's sphere2500 pose graph (and its first 500 poses).

Both get the same problem: gtsam's reading of ``sphere2500.txt`` (gtsam.readG2o) plus a prior
on pose 0 at the identity with σ = 1e-6 (PriorFactorPose3 / PriorFactor), and the same initial
values, the odometry chain composed from the identity. Both run LM to a relative cost decrease
of 1e-10; the final costs must agree to 1e-6 relative, evaluated both by gtsam's own
``graph.error`` and by spdslam.
"""

from __future__ import annotations

import numpy as np
import pytest

import spdslam  # noqa: F401
from spdslam.io import pose_graph_factors, read_g2o
from spdslam.solver import LevenbergMarquardt

gtsam = pytest.importorskip("gtsam")

PRIOR_SIGMA = 1e-6
RELATIVE_TOLERANCE = 1e-10


def build(n_poses: int | None):
    """(spdslam graph, spdslam values, gtsam graph, gtsam values) on poses < n_poses."""
    path = gtsam.findExampleDataFile("sphere2500.txt")
    pg = read_g2o(path)
    if n_poses is not None:
        pg.edges = [e for e in pg.edges if e.i < n_poses and e.j < n_poses]
        pg.poses = {k: T for k, T in pg.poses.items() if k < n_poses}
    graph, values = pose_graph_factors(pg, prior_sigma=PRIOR_SIGMA)
    full, _ = gtsam.readG2o(path, True)
    g = gtsam.NonlinearFactorGraph()
    for k in range(full.size()):
        f = full.at(k)
        if n_poses is None or max(f.keys()) < n_poses:
            g.add(f)
    prior_noise = gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)
    g.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), prior_noise))
    init = to_gtsam(values)
    return graph, values, g, init


def to_gtsam(values):
    out = gtsam.Values()
    for k, T in values.items():
        out.insert(k, gtsam.Pose3(np.asarray(T.as_matrix())))
    return out


def compare(n_poses):
    graph, values, g, init = build(n_poses)
    assert len(graph) == g.size()
    np.testing.assert_allclose(graph.error(values), g.error(init), rtol=1e-10)

    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(RELATIVE_TOLERANCE)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(1000)
    ref = gtsam.LevenbergMarquardtOptimizer(g, init, params).optimize()

    res = LevenbergMarquardt(relative_tolerance=RELATIVE_TOLERANCE, max_iterations=1000
                             ).optimize(graph, values)
    assert res.converged, res.reason
    mine = to_gtsam(res.values)
    cost_gtsam = g.error(ref)
    # both solutions evaluated by gtsam, and spdslam's cost of its own solution
    np.testing.assert_allclose(g.error(mine), cost_gtsam, rtol=1e-6)
    np.testing.assert_allclose(res.final_cost, cost_gtsam, rtol=1e-6)
    np.testing.assert_allclose(res.final_cost, g.error(mine), rtol=1e-10)
    return res


def test_sphere2500_first_500_poses_matches_gtsam():
    res = compare(500)
    assert res.linear_solver in ("cholmod", "cvxopt", "scipy")  # 3000 tangent dims: sparse


@pytest.mark.slow  # the first 500 poses run in the default suite
def test_sphere2500_matches_gtsam():
    """The whole graph (2500 poses, 4949 edges), on demand (about 30-60 s): the first 500
    poses, above, are the default suite's."""
    compare(None)
