"""TORO / g2o pose-graph reader: same measurements and noise models as gtsam.readG2o, and
file:line errors for malformed input."""

from __future__ import annotations

import numpy as np
import pytest

import spdslam  # noqa: F401
from spdslam.io import parse_g2o, pose_graph_factors, read_g2o

gtsam = pytest.importorskip("gtsam")

#: gtsam's Pose3 tangent is (ω, v), jaxlie's (v, ω): the same permutation maps both ways.
SWAP = np.array([3, 4, 5, 0, 1, 2])


def gtsam_edges(path):
    """[(i, j, measured 4x4, information 6x6 in gtsam order (ω, v))] and the initial Values."""
    graph, initial = gtsam.readG2o(str(path), True)
    out = []
    for k in range(graph.size()):
        f = graph.at(k)
        R = f.noiseModel().R()
        out.append((*f.keys(), f.measured().matrix(), R.T @ R))
    return out, initial


def assert_same_as_gtsam(path):
    pg = read_g2o(path)
    ref, initial = gtsam_edges(path)
    assert len(pg.edges) == len(ref)
    for e, (i, j, M, info_gtsam) in zip(pg.edges, ref):
        assert (e.i, e.j) == (i, j)
        np.testing.assert_allclose(np.asarray(e.measured.as_matrix()), M, atol=1e-12)
        np.testing.assert_allclose(e.information[np.ix_(SWAP, SWAP)], info_gtsam,
                                   rtol=1e-9, atol=1e-9 * np.abs(info_gtsam).max())
    for k in initial.keys():
        np.testing.assert_allclose(np.asarray(pg.poses[k].as_matrix()),
                                   initial.atPose3(k).matrix(), atol=1e-12)
    return pg


def test_sphere2500_matches_gtsam():
    pg = assert_same_as_gtsam(gtsam.findExampleDataFile("sphere2500.txt"))
    assert len(pg.edges) == 4949 and len(pg.poses) == 2500 and not pg.has_vertices
    # TORO's first three information entries are rotation in gtsam's reading:
    # sphere2500 has 10 on them and (100, 100, 25) on translation.
    np.testing.assert_allclose(np.diag(pg.edges[0].information), [100, 100, 25, 10, 10, 10])


def random_info(rng):
    A = rng.normal(size=(6, 6))
    return A @ A.T + 3 * np.eye(6)


def fmt(xs):
    return " ".join(f"{x:.17g}" for x in xs)


def test_general_information_and_rotations_match_gtsam(rng, tmp_path):
    """Full (non-diagonal) information matrices, large angles, both edge formats, vertices."""
    iu = np.triu_indices(6)
    lines = []
    for i in range(6):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        lines.append(f"VERTEX_SE3:QUAT {i} {fmt(rng.normal(size=3))} {fmt(q)}")
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 3), (5, 1)]:
        t, info = rng.normal(size=3), random_info(rng)
        if rng.random() < 0.5:
            rpy = rng.uniform(-3, 3, size=3)
            lines.append(f"EDGE3 {i} {j} {fmt(t)} {fmt(rpy)} {fmt(info[iu])}")
        else:
            q = rng.normal(size=4)
            q /= np.linalg.norm(q)
            lines.append(f"EDGE_SE3:QUAT {i} {j} {fmt(t)} {fmt(q)} {fmt(info[iu])}")
    path = tmp_path / "graph.g2o"
    path.write_text("# a comment\n\n" + "\n".join(lines) + "\n")
    pg = assert_same_as_gtsam(path)
    assert pg.has_vertices and sorted(pg.poses) == list(range(6))
    # the same pose written as rpy (TORO) and as a quaternion (g2o) parse to the same pose
    rpy = np.array([0.3, -1.2, 2.5])
    a = parse_g2o(f"EDGE3 0 1 1 2 3 {fmt(rpy)} " + fmt(np.eye(6)[iu])).edges[0]
    g = gtsam.Rot3.Ypr(rpy[2], rpy[1], rpy[0])
    q = g.toQuaternion()
    b = parse_g2o(f"EDGE_SE3:QUAT 0 1 1 2 3 {q.x()} {q.y()} {q.z()} {q.w()} "
                  + fmt(np.eye(6)[iu])).edges[0]
    np.testing.assert_allclose(np.asarray(a.measured.as_matrix()),
                               np.asarray(b.measured.as_matrix()), atol=1e-12)


def test_initial_poses_compose_the_odometry_chain(rng):
    iu = np.triu_indices(6)
    text = "\n".join(
        f"EDGE3 {i} {i + 1} {fmt(rng.normal(size=3))} {fmt(rng.uniform(-1, 1, 3))} "
        + fmt(np.eye(6)[iu]) for i in range(3, 8)
    ) + "\nEDGE3 3 8 0 0 0 0 0 0 " + fmt(np.eye(6)[iu])
    pg = parse_g2o(text)
    assert sorted(pg.poses) == list(range(3, 9))
    T = np.eye(4)
    np.testing.assert_allclose(np.asarray(pg.poses[3].as_matrix()), T, atol=1e-15)
    for e in pg.edges[:-1]:
        T = T @ np.asarray(e.measured.as_matrix())
        np.testing.assert_allclose(np.asarray(pg.poses[e.j].as_matrix()), T, atol=1e-12)


BAD = [
    ("EDGE3 0 1 1 2 3", r"bad\.g2o:3: expected EDGE3 followed by 29 numbers"),
    ("EDGE3 0 x " + "1 " * 27, r"bad\.g2o:3: expected integer ids"),
    ("VERTEX_SE3:QUAT 0 1 2 3 0 0 0 one", r"bad\.g2o:3: expected numbers"),
    ("EDGE_SE2 0 1 1 2 3", r"bad\.g2o:3: expected one of"),
    ("VERTEX_SE3:QUAT 0 1 2 3 0 0 0 0", r"bad\.g2o:3: expected a non-zero quaternion"),
    ("EDGE3 0 1 0 0 0 0 0 0 " + " ".join(["-1"] * 21),
     r"bad\.g2o:3: expected a positive definite information matrix"),
    ("EDGE3 0 1 0 0 0 0 0 nan " + " ".join(["1"] * 21), r"bad\.g2o:3: expected finite"),
]


@pytest.mark.parametrize("line, message", BAD)
def test_malformed_lines_name_file_and_line(tmp_path, line, message):
    iu = np.triu_indices(6)
    good = "EDGE3 0 1 1 2 3 0 0 0 " + fmt(np.eye(6)[iu])
    path = tmp_path / "bad.g2o"
    path.write_text(f"# header\n{good}\n{line}\n")
    with pytest.raises(ValueError, match=message) as err:
        read_g2o(path)
    assert "\n" not in str(err.value)


def test_missing_odometry_edge_is_reported():
    iu = np.triu_indices(6)
    with pytest.raises(ValueError, match=r"no odometry edge 1 -> 2"):
        parse_g2o("EDGE3 0 1 0 0 0 0 0 0 " + fmt(np.eye(6)[iu])
                  + "\nEDGE3 2 3 0 0 0 0 0 0 " + fmt(np.eye(6)[iu]), name="f.txt")


def test_pose_graph_factors_error_matches_gtsam(tmp_path, rng):
    """The graph built from a file has gtsam's cost at the same values (prior on pose 0)."""
    iu = np.triu_indices(6)
    lines = []
    for i in range(5):
        lines.append(f"EDGE3 {i} {i + 1} {fmt(rng.normal(size=3))} {fmt(rng.uniform(-1, 1, 3))} "
                     + fmt(random_info(rng)[iu]))
    lines.append(f"EDGE3 0 5 {fmt(rng.normal(size=3))} {fmt(rng.uniform(-1, 1, 3))} "
                 + fmt(random_info(rng)[iu]))
    path = tmp_path / "loop.txt"
    path.write_text("\n".join(lines) + "\n")
    pg = read_g2o(path)
    graph, values = pose_graph_factors(pg, prior_sigma=1e-3)
    assert len(graph) == len(pg.edges) + 1
    g, _ = gtsam.readG2o(str(path), True)
    g.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    vals = gtsam.Values()
    for k, T in values.items():
        vals.insert(k, gtsam.Pose3(np.asarray(T.as_matrix())))
    np.testing.assert_allclose(graph.error(values), g.error(vals), rtol=1e-9)
