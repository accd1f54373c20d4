"""evo (github.com/MichaelGrupp/evo) as the oracle of spdslam's trajectory error (ATE).

spdslam computes its ATE itself (``evaluation.absolute_trajectory_error``), so the core
install needs no evo; these tests recompute it with evo from the same files, with the same
association (nearest timestamps within 0.02 s) and alignment (SE(3) Umeyama on the camera
centres, estimate onto ground truth), and ask for the same figures to 1e-9 m:

- on real outputs: ``spdslam demo`` (40 frames, 2 objects) through the CLI in-process,
  the input and the optimised trajectory against the sequence's ``groundtruth.txt``, via
  evo's Python API and via the ``evo_ape`` command line (HOME in tmp_path: evo's CLI
  writes ~/.evo/settings.json on first use);
- ``spdslam evaluate`` of that run against a ground truth at another rate (50 Hz, shifted
  and jittered) with gaps, where the association decides which poses are compared;
- synthetic trajectories with noise, drift and a known rigid or similarity transform.

Where evo's ``associate_trajectories`` cannot reproduce ours: evo pairs each stamp of the
*shorter* trajectory with its nearest stamp of the longer one, not one-to-one, so when two
stamps of the shorter one share their nearest stamp (possible only when they are within
2·max_diff of each other) evo compares one pose twice, while ours (greedy by increasing
time difference, one-to-one, as TUM's associate.py) uses each pose once. The last test pins
that case down: evo's own pairing then differs, and evo's APE on *our* pairs agrees.
"""

from __future__ import annotations

import inspect
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("evo")

from conftest import cli_runner
from evo.core import metrics as evo_metrics
from evo.core import sync as evo_sync
from evo.tools import file_interface
from scipy.spatial.transform import Rotation, Slerp

from spdslam import cli
from spdslam.evaluation import (
    absolute_trajectory_error,
    associate_timestamps,
    trajectory_alignment,
)
from spdslam.geometry import align_rigid
from spdslam.io import read_tum, tum_text

#: Our association tolerance (s): the default of ``absolute_trajectory_error``, which
#: ``evaluate_run`` uses; evo_ape's default --t_max_diff is 0.01, so it must be passed.
TOL = inspect.signature(absolute_trajectory_error).parameters["tolerance"].default
ABS = 1e-9  # metres
STATS = ("rmse", "mean", "median", "max")
FRAMES, OBJECTS = 40, 2

runner = cli_runner()


# --------------------------------------------------------------------------- helpers


def evo_read(path: Path):
    return file_interface.read_tum_trajectory_file(str(path))


def evo_ate(gt_path, est_path, max_diff=TOL, align=True, correct_scale=False, pairs=None):
    """(stats, ref, est) of evo's APE (translation part) of ``est_path`` against
    ``gt_path``: evo's association within ``max_diff`` (or the given index ``pairs``
    (i_est, i_gt) instead), then evo's Umeyama alignment of the estimate onto the
    reference (SE(3), or Sim(3) with ``correct_scale``), as ``evo_ape tum GT EST -a``."""
    ref, est = evo_read(gt_path), evo_read(est_path)
    if pairs is None:
        ref, est = evo_sync.associate_trajectories(ref, est, max_diff=max_diff)
    else:
        est.reduce_to_ids(np.asarray(pairs[0]))
        ref.reduce_to_ids(np.asarray(pairs[1]))
    if align or correct_scale:
        est.align(ref, correct_scale=correct_scale)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    stats = {k: float(v) for k, v in ape.get_all_statistics().items()}
    stats["pairs"] = int(est.num_poses)
    return stats, ref, est


def assert_same_ate(ours: dict, theirs: dict):
    assert ours["pairs"] == theirs["pairs"]
    for k in STATS:
        assert ours[k] == pytest.approx(theirs[k], rel=0, abs=ABS), (k, ours[k], theirs[k])


def write_tum(path: Path, rows) -> Path:
    path.write_text(tum_text(np.asarray(rows, float)), encoding="utf-8")
    return path


def smooth_gt(t: np.ndarray) -> np.ndarray:
    """TUM rows of a smooth, non-planar camera path at times ``t``."""
    p = np.column_stack([3.0 * np.cos(0.5 * t), 2.0 * np.sin(0.7 * t), 1.2 + 0.3 * np.sin(1.3 * t)])
    q = Rotation.from_rotvec(np.column_stack([0.2 * np.sin(t), 0.1 * t, 0.5 * np.cos(0.3 * t)])).as_quat()
    return np.column_stack([t, p, q])


def transformed(rows, R, t, s=1.0) -> np.ndarray:
    """TUM rows moved by the similarity x ↦ s R x + t (orientations rotated by R)."""
    rows = np.array(rows, float)
    rows[:, 1:4] = s * rows[:, 1:4] @ R.T + t
    rows[:, 4:8] = (Rotation.from_matrix(R) * Rotation.from_quat(rows[:, 4:8])).as_quat()
    return rows


def noisy_drifting(rows, rng, sigma=0.01, drift=(0.02, -0.01, 0.005)) -> np.ndarray:
    """Rows with white noise (σ m) and a linear drift (m/s) added to the positions."""
    rows = np.array(rows, float)
    rows[:, 1:4] += sigma * rng.standard_normal((len(rows), 3))
    rows[:, 1:4] += (rows[:, :1] - rows[0, 0]) * np.asarray(drift)
    return rows


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    """OUT of ``spdslam demo --out OUT --frames 40 --objects 2`` (OUT/sequence, OUT/run)."""
    out = tmp_path_factory.mktemp("evo") / "demo"
    result = runner.invoke(cli.app, ["demo", "--out", str(out), "--frames", str(FRAMES),
                                     "--objects", str(OBJECTS)])
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    return out


def demo_ate(demo: Path) -> dict:
    return json.loads((demo / "run" / "metrics.json").read_text(encoding="utf-8"))["ate"]


# --------------------------------------------------------------------------- the files


def test_tolerance_is_the_documented_one():
    assert TOL == 0.02  # docs and the evo_ape command line pass --t_max_diff 0.02


@pytest.mark.parametrize("name", ["sequence/groundtruth.txt", "sequence/trajectory.txt",
                                  "run/trajectory.txt"])
def test_evo_reads_the_files_as_written(demo, name):
    """evo reads spdslam's TUM files as they are (the '# …' header line skipped, columns
    t tx ty tz qx qy qz qw) to the same numbers as spdslam's reader."""
    path = demo / name
    first = path.read_text(encoding="utf-8").splitlines()[0]
    assert first.startswith("# timestamp tx ty tz qx qy qz qw")
    ours = read_tum(path, str(path))
    traj = evo_read(path)
    assert traj.num_poses == len(ours) == FRAMES
    np.testing.assert_array_equal(traj.timestamps, ours[:, 0])
    np.testing.assert_array_equal(traj.positions_xyz, ours[:, 1:4])
    # evo stores w first; ours are normalised on reading (written normalised already)
    np.testing.assert_allclose(traj.orientations_quat_wxyz, ours[:, [7, 4, 5, 6]], rtol=0, atol=1e-15)


# --------------------------------------------------------------------------- real outputs


@pytest.mark.parametrize("key, est", [("input", "sequence/trajectory.txt"),
                                      ("optimized", "run/trajectory.txt")])
def test_demo_ate_equals_evo(demo, key, est):
    ours = demo_ate(demo)[key]
    theirs, _, _ = evo_ate(demo / "sequence/groundtruth.txt", demo / est)
    assert theirs["pairs"] == FRAMES
    assert_same_ate(ours, theirs)
    assert ours["rmse"] > 1e-4  # a real error, not two copies of one path


def test_demo_report_quotes_the_evo_figure(demo):
    theirs, _, _ = evo_ate(demo / "sequence/groundtruth.txt", demo / "run/trajectory.txt")
    report = (demo / "run" / "report.md").read_text(encoding="utf-8")
    assert f"optimised {1e3 * theirs['rmse']:.2f} mm ({FRAMES} poses)" in report


def test_demo_alignment_equals_evo(demo):
    """``to_groundtruth`` in map.json (the frame the objects are judged in) is evo's
    SE(3) Umeyama alignment of the optimised trajectory."""
    _, ref, est = evo_ate(demo / "sequence/groundtruth.txt", demo / "run/trajectory.txt", align=False)
    r, t, s = est.align(ref)
    m = json.loads((demo / "run" / "map.json").read_text(encoding="utf-8"))
    T = np.asarray(m["to_groundtruth"])
    assert s == 1.0
    np.testing.assert_allclose(T[:3, :3], r, rtol=0, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], t, rtol=0, atol=1e-12)


def test_demo_evo_ape_command_line(demo, tmp_path):
    """The documented command, ``evo_ape tum GT trajectory.txt --align --t_max_diff 0.02``,
    gives report.md's optimised ATE."""
    exe = shutil.which("evo_ape") or str(Path(sys.executable).with_name("evo_ape"))
    if not Path(exe).is_file():
        pytest.skip("no evo_ape executable")
    res = tmp_path / "ape.zip"
    env = dict(os.environ, HOME=str(tmp_path), MPLBACKEND="Agg")
    proc = subprocess.run(
        [exe, "tum", str(demo / "sequence/groundtruth.txt"), str(demo / "run/trajectory.txt"),
         "--align", "--t_max_diff", str(TOL), "--save_results", str(res), "--no_warnings"],
        capture_output=True, text=True, env=env, timeout=60, check=False)
    assert proc.returncode == 0, (proc.stdout, proc.stderr)
    assert "with SE(3) Umeyama alignment" in proc.stdout
    stats = file_interface.load_res_file(str(res)).stats
    ours = demo_ate(demo)["optimized"]
    for k in STATS:
        assert ours[k] == pytest.approx(stats[k], rel=0, abs=ABS), k
    assert len(file_interface.load_res_file(str(res)).np_arrays["error_array"]) == ours["pairs"]


def test_evaluate_against_gappy_ground_truth_at_another_rate(demo, tmp_path, rng):
    """``spdslam evaluate`` of the demo run against a 50 Hz ground truth (stamps shifted by
    7 ms, jittered by ≤ 2 ms, two gaps): every 10 Hz pose has up to two ground-truth stamps
    within 0.02 s, those in the gaps none. evo pairs each of the 40 estimated stamps (the
    shorter trajectory; 0.1 s apart > 2·0.02 s) with its nearest, as ours does."""
    seq, run = tmp_path / "seq", tmp_path / "run"
    shutil.copytree(demo / "sequence", seq)
    shutil.copytree(demo / "run", run)
    gt = read_tum(seq / "groundtruth.txt", "gt")
    t = np.arange(gt[0, 0] + 0.007, gt[-1, 0], 0.02)
    t = t + rng.uniform(-0.002, 0.002, t.size)
    t = t[~(((t > 1.05) & (t < 1.55)) | ((t > 2.65) & (t < 2.95)))]
    dense = np.column_stack(
        [t, *(np.interp(t, gt[:, 0], gt[:, k]) for k in (1, 2, 3)),
         Slerp(gt[:, 0], Rotation.from_quat(gt[:, 4:8]))(t).as_quat()])
    write_tum(seq / "groundtruth.txt", dense)
    result = runner.invoke(cli.app, ["evaluate", str(run), str(seq)])
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    ate = json.loads((run / "metrics.json").read_text(encoding="utf-8"))["ate"]

    est = read_tum(run / "trajectory.txt", "est")
    ia, ib = associate_timestamps(est[:, 0], t, TOL)
    near = np.abs(est[:, 0][:, None] - t[None, :]) <= TOL
    assert np.any(near.sum(axis=1) == 2)  # a choice to make
    assert 0 < ia.size < FRAMES  # the gaps leave poses unpaired
    for key, est_name in (("input", seq / "trajectory.txt"), ("optimized", run / "trajectory.txt")):
        theirs, ref_e, est_e = evo_ate(seq / "groundtruth.txt", est_name)
        np.testing.assert_array_equal(est_e.timestamps, est[ia, 0])
        np.testing.assert_array_equal(ref_e.timestamps, t[ib])
        assert ate[key]["pairs"] == ia.size
        assert_same_ate(ate[key], theirs)
    report = (run / "report.md").read_text(encoding="utf-8")
    assert f"optimised {1e3 * ate['optimized']['rmse']:.2f} mm ({ia.size} poses)" in report


# --------------------------------------------------------------------------- synthetic


def random_rotation(rng) -> np.ndarray:
    return Rotation.from_rotvec(rng.uniform(-np.pi, np.pi, 3) * [1, 0.3, 1]).as_matrix()


@pytest.mark.parametrize("with_noise", [False, True])
def test_synthetic_rigid_transform(tmp_path, rng, with_noise):
    """Ground truth moved by a known rigid motion, with noise and drift or without: the
    same ATE and alignment as evo; the motion's inverse found without noise."""
    gt = smooth_gt(np.arange(0.0, 12.0, 0.1))
    R, t = random_rotation(rng), rng.uniform(-5, 5, 3)
    est = noisy_drifting(gt, rng) if with_noise else gt
    est = transformed(est, R, t)
    g, e = write_tum(tmp_path / "gt.txt", gt), write_tum(tmp_path / "est.txt", est)
    ours = absolute_trajectory_error(read_tum(e, "e"), read_tum(g, "g"))
    theirs, ref_e, est_e = evo_ate(g, e, align=False)
    r, tt, _ = est_e.align(ref_e)
    theirs, _, _ = evo_ate(g, e)
    assert_same_ate(ours, theirs)
    T = trajectory_alignment(read_tum(e, "e"), read_tum(g, "g"))
    np.testing.assert_allclose(T[:3, :3], r, rtol=0, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], tt, rtol=0, atol=1e-10)
    if with_noise:
        assert 0.005 < ours["rmse"] < 0.2
    else:
        assert ours["rmse"] < 1e-9
        np.testing.assert_allclose(T[:3, :3], R.T, atol=1e-9)
        np.testing.assert_allclose(T[:3, 3], -R.T @ t, atol=1e-9)


def test_synthetic_similarity_transform(tmp_path, rng):
    """A known similarity (scale 1.7): our SE(3) ATE equals evo's SE(3) one (large: no
    scale correction); our Sim(3) alignment (``align_rigid(with_scale=True)``) equals evo's
    (``correct_scale``) and finds the scale, leaving the noise and drift."""
    gt = smooth_gt(np.arange(0.0, 10.0, 0.05))
    R, t, s = random_rotation(rng), rng.uniform(-5, 5, 3), 1.7
    est = transformed(noisy_drifting(gt, rng, sigma=0.005, drift=(0.004, 0.002, -0.003)), R, t, s)
    g, e = write_tum(tmp_path / "gt.txt", gt), write_tum(tmp_path / "est.txt", est)
    G, E = read_tum(g, "g"), read_tum(e, "e")
    ours = absolute_trajectory_error(E, G)
    se3, _, _ = evo_ate(g, e)
    assert_same_ate(ours, se3)
    assert ours["rmse"] > 0.5  # the scale is not corrected

    sim3, ref_e, est_e = evo_ate(g, e, align=False)
    r, tt, c = est_e.align(ref_e, correct_scale=True)
    Rs, ts, ss = align_rigid(E[:, 1:4], G[:, 1:4], with_scale=True)
    assert ss == pytest.approx(c, rel=1e-12) and ss == pytest.approx(1 / s, rel=1e-2)
    np.testing.assert_allclose(Rs, r, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ts, tt, rtol=0, atol=1e-10)
    err = np.linalg.norm(G[:, 1:4] - (ss * E[:, 1:4] @ Rs.T + ts), axis=1)
    sim3, _, _ = evo_ate(g, e, correct_scale=True)
    assert np.sqrt(np.mean(err**2)) == pytest.approx(sim3["rmse"], rel=0, abs=ABS)
    assert sim3["rmse"] < 0.05


def test_synthetic_unaligned(tmp_path, rng):
    """``align=False``: the raw error, as evo_ape without --align."""
    gt = smooth_gt(np.arange(0.0, 8.0, 0.1))
    est = noisy_drifting(gt, rng)
    g, e = write_tum(tmp_path / "gt.txt", gt), write_tum(tmp_path / "est.txt", est)
    ours = absolute_trajectory_error(read_tum(e, "e"), read_tum(g, "g"), align=False)
    theirs, _, _ = evo_ate(g, e, align=False)
    assert_same_ate(ours, theirs)
    aligned = absolute_trajectory_error(read_tum(e, "e"), read_tum(g, "g"))
    assert aligned["rmse"] < ours["rmse"] - 1e-3  # alignment takes up part of the drift


@pytest.mark.parametrize("gt_hz, est_hz", [(30.0, 20.0), (20.0, 30.0), (100.0, 10.0)])
def test_synthetic_association_rates_and_gaps(tmp_path, rng, gt_hz, est_hz):
    """Different rates, jittered stamps, gaps in the ground truth and an estimate that
    starts late: evo reproduces our pairs exactly whenever the shorter trajectory's stamps
    are more than 2·0.02 s apart (here: 20, 20 and 10 Hz), and so the ATE."""
    t_gt = np.arange(0.0, 10.0, 1 / gt_hz) + rng.uniform(-0.004, 0.004)
    t_gt = t_gt[~(((t_gt > 2.0) & (t_gt < 2.7)) | ((t_gt > 6.1) & (t_gt < 6.5)))]
    t_est = np.arange(0.3, 10.5, 1 / est_hz)
    t_est = t_est + rng.uniform(-0.002, 0.002, t_est.size)
    gt = smooth_gt(t_gt)
    R, t = random_rotation(rng), rng.uniform(-2, 2, 3)
    est = transformed(noisy_drifting(smooth_gt(t_est), rng), R, t)
    g, e = write_tum(tmp_path / "gt.txt", gt), write_tum(tmp_path / "est.txt", est)
    G, E = read_tum(g, "g"), read_tum(e, "e")
    short = t_gt if len(t_gt) < len(t_est) else t_est
    assert np.min(np.diff(short)) > 2 * TOL

    ia, ib = associate_timestamps(E[:, 0], G[:, 0], TOL)
    ours = absolute_trajectory_error(E, G)
    theirs, ref_e, est_e = evo_ate(g, e)
    np.testing.assert_array_equal(est_e.timestamps, E[ia, 0])
    np.testing.assert_array_equal(ref_e.timestamps, G[ib, 0])
    assert 10 < ia.size < min(len(G), len(E))  # some poses left unpaired
    assert_same_ate(ours, theirs)


def test_synthetic_association_evo_cannot_reproduce(tmp_path, rng):
    """Ground truth in 100 Hz bursts (fewer poses than the 30 Hz estimate, so evo drives
    from it): several ground-truth stamps share their nearest estimated stamp, evo pairs
    that estimated pose with each of them, ours uses it once (one-to-one, greedy by time
    difference). The pairings and the ATEs differ; evo's APE on our pairs is ours."""
    t_gt = np.concatenate([a + 0.01 * np.arange(50) for a in (0.5, 2.0, 4.0)])
    t_est = np.arange(0.0, 6.0, 1 / 30)
    gt = smooth_gt(t_gt)
    est = transformed(noisy_drifting(smooth_gt(t_est), rng, sigma=0.02), random_rotation(rng),
                      rng.uniform(-2, 2, 3))
    g, e = write_tum(tmp_path / "gt.txt", gt), write_tum(tmp_path / "est.txt", est)
    G, E = read_tum(g, "g"), read_tum(e, "e")
    assert len(G) < len(E)

    ia, ib = associate_timestamps(E[:, 0], G[:, 0], TOL)
    assert np.unique(ia).size == ia.size and np.unique(ib).size == ib.size
    ours = absolute_trajectory_error(E, G)
    theirs, _, est_e = evo_ate(g, e)
    # evo: one pair per ground-truth stamp, estimated poses repeated
    assert theirs["pairs"] == len(G) > ours["pairs"] == ia.size
    assert np.unique(est_e.timestamps).size < est_e.num_poses
    assert abs(theirs["rmse"] - ours["rmse"]) > 1e-4
    # the same computation on our pairs
    mine, _, _ = evo_ate(g, e, pairs=(ia, ib))
    assert_same_ate(ours, mine)
