"""Trajectory metrics (spdslam.evaluation): rigid/similarity alignment, timestamp association
and the absolute trajectory error (ATE)."""

from __future__ import annotations

import numpy as np
import pytest

from spdslam.evaluation import (
    absolute_trajectory_error,
    align_rigid,
    associate_timestamps,
)


def tum_rows(t, xyz, rng) -> np.ndarray:
    """(N, 8) TUM rows with random unit quaternions (irrelevant to the ATE)."""
    q = rng.normal(size=(len(t), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.column_stack([t, xyz, q])


def random_walk(rng, n: int) -> np.ndarray:
    return np.cumsum(rng.normal(scale=0.1, size=(n, 3)), axis=0) + rng.normal(size=3)


# --- align_rigid ---------------------------------------------------------------------------


@pytest.mark.parametrize("with_scale", [False, True])
def test_align_rigid_recovers_a_known_transform(gen, rng, with_scale):
    src = rng.normal(size=(20, 3)) * 2.0
    R, t = gen.rotation(), rng.normal(size=3) * 5.0
    s = float(rng.uniform(0.3, 3.0)) if with_scale else 1.0
    dst = s * src @ R.T + t
    R_, t_, s_ = align_rigid(src, dst, with_scale=with_scale)
    np.testing.assert_allclose(R_, R, atol=1e-10)
    np.testing.assert_allclose(t_, t, atol=1e-9)
    assert s_ == pytest.approx(s, rel=1e-10)
    assert np.linalg.det(R_) == pytest.approx(1.0)


def test_align_rigid_minimal_and_coplanar_sets(gen, rng):
    src = rng.normal(size=(3, 3))  # 3 points always lie in a plane
    R, t = gen.rotation(), rng.normal(size=3)
    R_, t_, s_ = align_rigid(src, src @ R.T + t)
    np.testing.assert_allclose(R_, R, atol=1e-9)
    np.testing.assert_allclose(t_, t, atol=1e-9)
    assert s_ == 1.0


def test_align_rigid_reflected_data_still_gives_a_rotation(rng):
    src = rng.normal(size=(10, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image: no rotation fits exactly
    R, t, _ = align_rigid(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    # It is still the least-squares optimum: no random rotation does better.
    cost = np.sum((src @ R.T + t - dst) ** 2)
    for _ in range(200):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(r))
        if np.linalg.det(q) < 0:
            q[:, 0] *= -1
        tq = dst.mean(0) - src.mean(0) @ q.T
        assert np.sum((src @ q.T + tq - dst) ** 2) >= cost - 1e-9


def test_align_rigid_least_squares_with_noise(gen, rng):
    src = rng.normal(size=(500, 3))
    R, t = gen.rotation(), rng.normal(size=3)
    dst = src @ R.T + t + rng.normal(scale=1e-3, size=src.shape)
    R_, t_, _ = align_rigid(src, dst)
    assert np.abs(R_ - R).max() < 1e-3
    assert np.abs(t_ - t).max() < 1e-3


@pytest.mark.parametrize(
    "src",
    [
        np.zeros((0, 3)),
        np.eye(3)[:2],  # 2 points
        np.outer(np.arange(6.0), [1.0, 2.0, 3.0]) + 1.0,  # collinear
        np.ones((5, 3)),  # coincident
    ],
    ids=["empty", "two", "collinear", "coincident"],
)
def test_align_rigid_degenerate_input_raises(src):
    with pytest.raises(ValueError):
        align_rigid(src, src)


def test_align_rigid_bad_shapes_raise(rng):
    with pytest.raises(ValueError, match="shape"):
        align_rigid(rng.normal(size=(5, 2)), rng.normal(size=(5, 2)))
    with pytest.raises(ValueError, match="same shape"):
        align_rigid(rng.normal(size=(5, 3)), rng.normal(size=(6, 3)))
    bad = rng.normal(size=(5, 3))
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        align_rigid(bad, bad)


def test_align_rigid_collinear_destination_raises(rng):
    src = rng.normal(size=(6, 3))
    dst = np.outer(rng.normal(size=6), [0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="dst"):
        align_rigid(src, dst)


@pytest.mark.parametrize("with_scale", [False, True])
def test_align_rigid_many_is_align_rigid_of_each(rng, with_scale):
    """Triples and sextuples, general, reflected, collinear (either side) and coincident:
    the same transform as one by one, and ok False exactly where ``align_rigid`` raises."""
    from spdslam.geometry import align_rigid_many

    for n in (3, 6):
        src, dst = rng.normal(size=(200, n, 3)), rng.normal(size=(200, n, 3))
        dst[1] = src[1] * [1.0, 1.0, -1.0]  # a reflection of its source
        src[2] = np.outer(rng.normal(size=n), [1.0, 2.0, 0.5])  # collinear
        dst[3] = np.outer(rng.normal(size=n), [0.0, 0.0, 1.0])
        src[4] = 0.0  # coincident
        R, t, s, ok = align_rigid_many(src, dst, with_scale)
        for i in range(len(src)):
            try:
                R1, t1, s1 = align_rigid(src[i], dst[i], with_scale=with_scale)
            except ValueError:
                assert not ok[i], i
                continue
            assert ok[i], i
            np.testing.assert_allclose(R[i], R1, atol=1e-12)
            np.testing.assert_allclose(t[i], t1, atol=1e-12)
            assert s[i] == pytest.approx(s1, abs=1e-12)
        assert not ok[[2, 3, 4]].any() and ok.sum() == len(src) - 3


# --- associate_timestamps -------------------------------------------------------------------


def test_associate_exact_and_shifted():
    a = np.arange(10) * 0.1
    ia, ib = associate_timestamps(a, a[::-1] + 0.005)
    np.testing.assert_array_equal(ia, np.arange(10))
    np.testing.assert_array_equal(ib, np.arange(10)[::-1])


def test_associate_one_to_one_nearest_first():
    a = np.array([0.0, 0.011])
    b = np.array([0.01])  # within tolerance of both; the nearer one (0.011) wins
    ia, ib = associate_timestamps(a, b, tolerance=0.02)
    assert ia.tolist() == [1] and ib.tolist() == [0]


def test_associate_respects_tolerance_and_partial_overlap():
    a = np.arange(0.0, 1.0, 0.1)
    b = np.arange(0.5, 2.0, 0.1) + 0.015
    ia, ib = associate_timestamps(a, b, tolerance=0.02)
    assert np.all(np.abs(a[ia] - b[ib]) <= 0.02)
    assert ia.tolist() == [5, 6, 7, 8, 9]
    assert ib.tolist() == [0, 1, 2, 3, 4]
    ia, ib = associate_timestamps(a, b, tolerance=0.01)
    assert ia.size == 0 and ib.size == 0


def test_associate_dense_against_brute_force(rng):
    a = np.sort(rng.uniform(0, 5, size=150))
    b = rng.uniform(0, 5, size=400)  # unsorted, denser than the tolerance
    ia, ib = associate_timestamps(a, b, tolerance=0.02)
    assert len(set(ia.tolist())) == ia.size and len(set(ib.tolist())) == ib.size
    # Greedy reference over all pairs.
    d = np.abs(a[:, None] - b[None, :])
    pairs = sorted((d[i, j], i, j) for i, j in zip(*np.nonzero(d <= 0.02)))
    ua, ub, ref = set(), set(), []
    for _, i, j in pairs:
        if i not in ua and j not in ub:
            ua.add(i)
            ub.add(j)
            ref.append((i, j))
    assert sorted(ref) == list(zip(ia.tolist(), ib.tolist()))


def test_associate_empty_inputs():
    ia, ib = associate_timestamps([], [1.0, 2.0])
    assert ia.size == 0 and ib.size == 0


# --- absolute_trajectory_error ---------------------------------------------------------------


def test_ate_of_a_rigidly_moved_copy_is_zero(gen, rng):
    t = 1305031102.0 + np.arange(100) / 30.0
    gt_xyz = random_walk(rng, 100)
    R, u = gen.rotation(), rng.normal(size=3) * 3.0
    est = tum_rows(t, gt_xyz @ R.T + u, rng)
    gt = tum_rows(t, gt_xyz, rng)
    ate = absolute_trajectory_error(est, gt)
    assert set(ate) == {"rmse", "mean", "median", "max", "pairs"}
    assert ate["pairs"] == 100
    assert ate["rmse"] < 1e-9 and ate["max"] < 1e-9
    # Without alignment the error is that of the motion.
    raw = absolute_trajectory_error(est, gt, align=False)
    expected = np.linalg.norm(gt_xyz @ R.T + u - gt_xyz, axis=1)
    assert raw["rmse"] == pytest.approx(np.sqrt(np.mean(expected**2)))
    assert raw["max"] == pytest.approx(expected.max())


def test_ate_does_not_correct_scale(rng):
    t = np.arange(50) * 0.1
    xyz = random_walk(rng, 50)
    ate = absolute_trajectory_error(tum_rows(t, 2.0 * xyz, rng), tum_rows(t, xyz, rng))
    assert ate["rmse"] > 1e-3


def test_ate_of_a_noisy_copy_matches_the_noise(gen, rng):
    n, sigma = 4000, 0.01
    t = np.arange(n) * 0.01
    gt_xyz = random_walk(rng, n) * 10.0
    noise = rng.normal(scale=sigma, size=(n, 3))
    R, u = gen.rotation(), rng.normal(size=3)
    est = tum_rows(t, (gt_xyz + noise) @ R.T + u, rng)
    ate = absolute_trajectory_error(est, tum_rows(t, gt_xyz, rng))
    noise_rms = np.sqrt(np.mean(np.sum(noise**2, axis=1)))  # ≈ σ√3
    assert ate["rmse"] == pytest.approx(noise_rms, rel=0.01)
    assert ate["rmse"] <= noise_rms  # the alignment can only reduce the residual
    assert ate["mean"] <= ate["rmse"] <= ate["max"]
    assert ate["median"] <= ate["max"]


def test_ate_partial_timestamp_overlap(gen, rng):
    t_gt = np.arange(200) * 0.01  # 100 Hz ground truth over 2 s
    gt_xyz = random_walk(rng, 200)
    idx = np.arange(100, 200, 3)  # ~33 Hz estimate, second half, jittered stamps
    t_est = t_gt[idx] + rng.uniform(-0.003, 0.003, size=idx.size)
    t_est = np.concatenate([t_est, [5.0, 6.0]])  # and two stamps with no ground truth
    est_xyz = np.vstack([gt_xyz[idx], [[9.0, 9.0, 9.0], [9.0, 9.0, 9.0]]])
    R, u = gen.rotation(), rng.normal(size=3)
    ate = absolute_trajectory_error(tum_rows(t_est, est_xyz @ R.T + u, rng), tum_rows(t_gt, gt_xyz, rng))
    assert ate["pairs"] == idx.size
    assert ate["rmse"] < 1e-9


def test_ate_too_few_pairs_raises(rng):
    gt = tum_rows(np.arange(10) * 0.1, random_walk(rng, 10), rng)
    est = tum_rows(np.array([0.0, 0.1, 50.0, 60.0]), random_walk(rng, 4), rng)
    with pytest.raises(ValueError, match="at least 3 timestamp pairs.*got 2"):
        absolute_trajectory_error(est, gt)
    with pytest.raises(ValueError, match="at least 3"):
        absolute_trajectory_error(est, gt + np.array([100.0] + [0.0] * 7))


def test_ate_bad_shapes_raise(rng):
    gt = tum_rows(np.arange(10) * 0.1, random_walk(rng, 10), rng)
    with pytest.raises(ValueError, match=r"\(N, 8\)"):
        absolute_trajectory_error(gt[:, 1:], gt)
    with pytest.raises(ValueError, match=r"\(N, 8\)"):
        absolute_trajectory_error(gt, gt[:, 1:])
