"""Objects against drift (docs/drift.md): the odometry's walk and the check of a trajectory
against it, loops verified and closed in a pose graph, a wrong loop rejected and named, and
a drifting trajectory never made worse by default (batch and online)."""

from __future__ import annotations

from dataclasses import replace

import jaxlie
import numpy as np
import pytest
from conftest import assert_cli_error as assert_error
from conftest import assert_cli_ok as assert_ok
from conftest import cli_invoke as invoke
from scipy.spatial.transform import Rotation

from spdslam.evaluation import absolute_trajectory_error
from spdslam.geometry import Ellipsoid
from spdslam.geometry.se3 import from_tum
from spdslam.io import MapObject, write_sequence
from spdslam.mapping import LocalizationError, OnlineMapper, RunSettings, SequenceContext, SettingsError, build_graph, localize_objects, run_online, run_sequence
from spdslam.mapping._graph import mapping_sigmas
from spdslam.mapping._loops import Loop, solve_pose_graph
from spdslam.mapping._odometry import WALK_LIMIT, check_trajectory, odometry_factors, walk_covariances
from spdslam.mapping._reuse import RIVAL_MARGIN, TransformGate
from spdslam.solver import X
from spdslam.synthetic import drifted_sequence, make_room_sequence


def _ate(rows, seq) -> float:
    rows = np.asarray(rows, float)
    rows = np.c_[seq.timestamps, rows] if rows.shape[1] == 7 else rows
    return absolute_trajectory_error(rows, seq.groundtruth_tum)["rmse"]


def _matrices(rows) -> np.ndarray:
    return np.asarray(from_tum(rows).as_matrix())


@pytest.fixture(scope="module")
def truth():
    """A room's true trajectory (120 frames, one closed loop) as an undrifted sequence."""
    room = make_room_sequence(3, frames=120, objects=6, drift=0.0)
    return replace(room, poses_tum=room.groundtruth_tum[:, 1:])


# --------------------------------------------------------------------------- the odometry's walk


def test_the_walk_covariance_is_the_spread_of_drifted_odometry(truth):
    """``walk_covariances`` against 400 drifts of one trajectory (``drifted_sequence``): the
    departure of the last pose from the truth, Log(Tᵢ⁻¹ T̂ᵢ), has the covariance it predicts
    (each σ within 15 %, the rotation's lever on the translation included)."""
    seq = truth.subset(np.arange(40))
    st, sr = 0.01, 0.02
    last = []
    T = jaxlie.SE3.from_matrix(_matrices(seq.poses_tum)[-1])
    for seed in range(400):
        d = drifted_sequence(seq, st, sr, seed)
        last.append(np.asarray((T.inverse() @ jaxlie.SE3.from_matrix(_matrices(d.poses_tum)[-1])).log()))
    s = {"odometry_translation": st, "odometry_rotation": sr, "first_pose": 1e-4}
    ctx = SequenceContext.of(seq)
    predicted = np.sqrt(np.diag(walk_covariances(ctx.wxyz_xyz, s)[-1]))
    measured = np.std(np.stack(last), axis=0)
    np.testing.assert_allclose(measured, predicted, rtol=0.15)
    assert predicted[0] > 3 * st * np.sqrt(39)  # the lever of the rotation's walk dominates


def _drifted(truth, st, sr, seed):
    """``truth`` made a drifting odometry whose priors state its step σ."""
    seq = drifted_sequence(truth, st, sr, seed)
    return replace(seq, priors=seq.priors.replace(trajectory_sigma=[st, sr]))


def test_the_check_refuses_a_trajectory_moved_beyond_the_walk(truth):
    seq = _drifted(truth, 0.005, 0.0025, 0)
    s = mapping_sigmas(seq)
    ctx = SequenceContext.of(seq)
    walk = walk_covariances(ctx.wxyz_xyz, s)
    # the truth is within the walk of the drifted input; the input itself does not move
    ok = check_trajectory("the truth", ctx.wxyz_xyz, SequenceContext.of(truth).wxyz_xyz, walk)
    assert ok.accepted and 0 < ok.worst < WALK_LIMIT
    same = check_trajectory("the input", ctx.wxyz_xyz, ctx.wxyz_xyz, walk)
    assert same.accepted and same.worst == 0 and same.moved_max == 0
    # every camera 2 m away (a diverged replay): refused, and the note says so
    far = ctx.wxyz_xyz.copy()
    far[:, 4] += 2.0
    bad = check_trajectory("the replay", ctx.wxyz_xyz, far, walk)
    assert not bad.accepted and bad.worst > WALK_LIMIT
    assert bad.note().startswith("the replay refused: it moved the cameras by 2e+03 mm median")
    assert "the input poses are kept for this step" in bad.note()
    nan = far.copy()
    nan[5, 4] = np.nan
    assert not check_trajectory("x", ctx.wxyz_xyz, nan, walk).accepted


def test_one_function_makes_the_odometry_of_the_batch_and_of_a_window():
    """The batch graph's trajectory factors are ``odometry_factors``'; a window from frame k
    has those that involve frames k … F − 1 (the step into k included), in a joined
    sequence none across a segment's start."""
    seq = make_room_sequence(0, frames=30, objects=2)
    seq = replace(seq, segments=(20,), priors=seq.priors.replace(trajectory_absolute_sigma=[0.01, 0.01]))
    ctx = SequenceContext.of(seq)
    s = mapping_sigmas(ctx)
    graph = build_graph(ctx, [], {}, RunSettings().method, odometry=True)
    mine = [f.keys for f in build_graph(ctx, [], {}, RunSettings().method, odometry=False)]
    assert mine == []
    whole = sorted(f.keys for f in graph)
    assert whole == sorted(f.keys for f in _expand(odometry_factors(ctx.wxyz_xyz, seq.segments, s)))
    window = [f.keys for f in _expand(odometry_factors(ctx.wxyz_xyz, seq.segments, s, start=25))]
    assert (X(24), X(25)) in window and (X(23), X(24)) not in window
    assert (X(20), X(26)) in window  # a later segment's poses bounded relative to its first
    assert all(min(k.index for k in keys) >= 20 or max(k.index for k in keys) >= 25 for keys in window)
    assert (X(19), X(20)) not in whole and (X(20),) in whole  # no odometry across the join; its weak hold


def _expand(factors):
    from spdslam.solver import NonlinearFactorGraph

    return list(NonlinearFactorGraph(factors))


# --------------------------------------------------------------------------- loops


def _corrections(truth, drifted, frames):
    """The true correction C_a⁻¹ C_b (x_earlier = T x_later) of each frame pair (a, b), C the
    world correction T_true T̂⁻¹ of a drifted pose."""
    Tt, Td = _matrices(truth.poses_tum), _matrices(drifted.poses_tum)
    C = Tt @ np.linalg.inv(Td)
    return [np.linalg.inv(C[a]) @ C[b] for a, b in frames]


def _loop(a, b, T, sigma=(0.01, 0.005)):
    cov = np.diag(np.r_[np.full(3, sigma[0] ** 2), np.full(3, sigma[1] ** 2)])
    return Loop(earlier=(a - 5, a + 5), later=(b - 5, b + 5), frames=(a, b), status="verified", matches=5, T=T,
                covariance=cov)


def test_loops_close_a_drifting_trajectory_and_a_wrong_one_is_rejected_and_named(truth):
    """Three right loops between the start and the end of a drifting room take most of its
    drift out; a fourth, 15° off (a wrong match), disagrees with them and the odometry in the
    pose graph: rejected, named, and the trajectory as good as without it."""
    seq = _drifted(truth, 0.004, 0.003, 2)
    ctx = SequenceContext.of(seq)
    s = mapping_sigmas(ctx)
    frames = [(8, 110), (12, 113), (5, 106)]
    good = [_loop(a, b, T) for (a, b), T in zip(frames, _corrections(truth, seq, frames))]
    wrong = _corrections(truth, seq, [(10, 108)])[0]
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.radians(15.0)]).as_matrix()
    loops = good + [_loop(10, 108, turn @ wrong)]
    poses, out = solve_pose_graph(ctx, s, list(loops))
    assert [lp.status for lp in out] == ["verified"] * 3 + ["rejected"]
    assert out[3].reason.startswith("disagrees with the odometry and the other loops (χ² ")
    assert all(lp.chi2_graph < 22.5 for lp in out[:3])
    before, after = _ate(seq.poses_tum, seq), _ate(_tum(poses), seq)
    clean, _ = solve_pose_graph(ctx, s, list(good))
    assert after < 0.5 * before
    assert after == pytest.approx(_ate(_tum(clean), seq), rel=1e-3)


def _tum(wxyz_xyz):
    from spdslam.geometry.se3 import to_tum

    return to_tum(jaxlie.SE3(np.asarray(wxyz_xyz)))


def test_a_rival_that_nearly_matches_as_many_is_refused():
    """A transform matching five objects against a rival's four is refused (the rule behind
    ``RIVAL_MARGIN``: a wrong transform of a drifting office recording matched five against a
    right one's four); with a gate that admits only transforms near the truth the rival is not
    considered and the transform is found."""
    assert RIVAL_MARGIN == 2
    row = [MapObject(i, "bottle", Ellipsoid.from_axes(np.eye(3), (0.25 * i, 0.0, 0.8), (0.04, 0.04, 0.12)))
           for i in range(5)]
    extra = [MapObject(9, "cup", Ellipsoid.from_axes(np.eye(3), (0.5, 0.6, 0.8), (0.05, 0.05, 0.06)))]
    seq_objects = row[:5] + extra
    map_objects = row + [MapObject(7, "bottle", Ellipsoid.from_axes(np.eye(3), (1.25, 0.0, 0.8),
                                                                     (0.04, 0.04, 0.12)))] + extra
    # shifted by one bottle the row matches 5 of its 5 again: a rival as good as the answer
    with pytest.raises(LocalizationError, match="ambiguous: a transform matches .* and another .* apart"):
        localize_objects(seq_objects, map_objects)
    gate = TransformGate(np.eye(4), 0.1, np.radians(2.0))
    loc = localize_objects(seq_objects, map_objects, gate=gate)
    np.testing.assert_allclose(loc.T_map_sequence, np.eye(4), atol=1e-6)
    assert sorted(loc.matches) == [(i, i) for i in range(5)] + [(9, 9)]
    with pytest.raises(ValueError, match="a gate is an SE\\(3\\) guess"):
        localize_objects(seq_objects, map_objects, gate=gate, sim3=True)


# --------------------------------------------------------------------------- runs


@pytest.fixture(scope="module")
def drifting():
    """A room whose odometry drifts, no bound on each pose, its detections without ids."""
    seq = make_room_sequence(1, frames=80, objects=5, drift=0.01)
    return replace(seq, detections=[replace(d, instance=None) for d in seq.detections])


def test_the_joint_optimisation_of_free_poses_is_checked_against_the_odometry():
    """``initial_poses="input"`` lets the boxes move each pose; the result is checked against
    the odometry's walk and map.json's ``trajectory`` says so."""
    seq = make_room_sequence(1, frames=30, objects=3, drift=0.01)
    free = run_sequence(seq, "multi-spd", initial_poses="input")
    assert free.trajectory["start"] == "input"
    (check,) = free.trajectory["checks"]
    assert check["step"] == "the joint optimisation" and check["accepted"] and check["worst_sigma"] < WALK_LIMIT


@pytest.mark.parametrize("kwargs, message", [
    ({"initial_poses": "loops", "hold_trajectory": True}, "initial_poses: loops move the poses"),
    ({"initial_poses": "loops", "drift_interval": 5.0}, "initial_poses: a drift correction starts from"),
    ({"initial_poses": "replay"}, "initial_poses: expected one of input, incremental, loops, auto, got 'replay'"),
])
def test_loops_that_cannot_be_are_refused(kwargs, message):
    with pytest.raises(SettingsError, match=message):
        RunSettings.of("multi-spd", **kwargs)


def test_the_online_mapper_follows_the_odometry_of_a_drifting_trajectory(drifting):
    """Without a bound on each pose the online mapper does not let the boxes move the poses
    (it diverged to metres on a real recording): every estimate, online and after the final
    batch, is the input's; with ``initial_poses="input"`` the boxes move them as before."""
    result, _ = run_online(drifting, "multi-spd")
    np.testing.assert_allclose(result.poses_tum[:, 1:], drifting.poses_tum, atol=1e-9)
    assert result.trajectory["start"] == "loops"  # no loop verified: the input, exactly
    assert not any(lp["status"] == "verified" for lp in result.trajectory["loop_closure"]["loops"])
    assert any("the poses follow the odometry" in n for n in result.notes)
    assert any(n.startswith("loop closure") for n in result.notes)
    m = OnlineMapper(drifting.camera, drifting.priors, "multi-spd")
    assert m.hold_poses and m.loop_closure is not None
    free = OnlineMapper(drifting.camera, drifting.priors, "multi-spd", initial_poses="input")
    assert not free.hold_poses and free.loop_closure is None
    replayed = OnlineMapper(drifting.camera, drifting.priors, "multi-spd", initial_poses="incremental")
    assert replayed.hold_poses and replayed.loop_closure is None


def _slowed(seq, factor):
    """``seq`` with its time stretched by ``factor`` (more submaps of the same frames)."""
    t = seq.timestamps[0] + factor * (seq.timestamps - seq.timestamps[0])
    return replace(seq, timestamps=t, detections=[replace(d, timestamp=t[d.frame]) for d in seq.detections],
                   groundtruth_tum=np.c_[t, seq.groundtruth_tum[:, 1:]])


def test_online_candidates_are_the_batch_candidates_of_each_new_submap(truth):
    """The online loop closure tries, for each submap once it is complete, the revisits the
    batch's rule finds between it and the earlier ones: together, the batch's candidates."""
    from spdslam.mapping._loops import candidates, submaps_of

    seq = _slowed(drifted_sequence(truth, 0.002, np.radians(0.3), 1), 5.0)
    seq = replace(seq, priors=seq.priors.replace(trajectory_sigma=[0.002, np.radians(0.3)]))
    ctx = SequenceContext.of(seq)
    s = mapping_sigmas(ctx, {})
    subs = submaps_of(seq.timestamps, 5.0)
    every = candidates(ctx, subs, s)
    assert every, "the slowed room comes back to its start: a candidate revisit"
    by_submap = [c for li in range(len(subs)) for c in candidates(ctx, subs, s, later=[li])]
    assert sorted(by_submap) == sorted(every)
    assert candidates(ctx, subs, s, later=[]) == []


def test_a_closed_loop_corrects_the_online_map_and_the_final_batch_holds_it(drifting):
    """Once the online loop closure accepts a corrected trajectory, ``current_map`` gives
    it (later frames follow the odometry from its last frame) with each object moved by the
    correction at the middle of its views, and ``finish`` holds the poses there; map.json's
    ``trajectory`` says the loops did it."""
    m = OnlineMapper(drifting.camera, drifting.priors, "multi-spd", every=5)
    by_frame = {}
    for d in drifting.detections:
        by_frame.setdefault(d.frame, []).append(d)
    from spdslam.mapping._online import replay

    replay(drifting, m, by_frame, {})
    before = m.current_map()
    assert before.objects
    F = len(m)
    q = np.asarray(from_tum(drifting.poses_tum).wxyz_xyz)
    twist = jaxlie.SE3.exp(np.r_[0.05, -0.02, 0.0, 0.0, 0.0, np.radians(2.0)])
    half = F // 2  # the closure covered the first half; the rest follows the odometry
    m.loop_closure.poses = np.asarray((twist @ jaxlie.SE3(q[:half])).wxyz_xyz)
    after = m.current_map()
    C = np.asarray(twist.as_matrix())
    want = np.asarray((twist @ jaxlie.SE3(q)).as_matrix())
    np.testing.assert_allclose(_matrices(after.poses_tum[:, 1:]), want, atol=1e-9)
    for k, (label, e) in before.objects.items():
        moved = after.objects[k][1]
        np.testing.assert_allclose(moved.center, C[:3, :3] @ e.center + C[:3, 3], atol=1e-9)
        np.testing.assert_allclose(moved.P, C[:3, :3] @ e.P @ C[:3, :3].T, atol=1e-9)
    result = m.finish()
    np.testing.assert_allclose(_matrices(result.poses_tum[:, 1:]), want, atol=1e-9)
    assert result.trajectory["start"] == "loops"
    assert {"loop_closure", "checks"} <= set(result.trajectory)


def test_a_joined_recording_replayed_online_has_no_odometry_across_the_join():
    seq = make_room_sequence(0, frames=24, objects=3)
    seq = replace(seq, priors=seq.priors.replace(trajectory_absolute_sigma=[0.002, 0.002]))
    joined = replace(seq, segments=(12,))
    m = OnlineMapper(seq.camera, seq.priors, "multi-spd", associate="instances", every=4, window=30,
                     initial_poses="input")
    from spdslam.mapping._online import replay

    by_frame = {}
    for d in joined.detections:
        by_frame.setdefault(d.frame, []).append(d)
    replay(joined, m, by_frame, {})
    assert m.sequence().segments == (12,)
    pairs = {tuple(sorted(k.index for k in keys)) for f in m._smoother.last[0] if f.kind == "between"
             for keys in ([f.keys] if len(f.keys) == 2 else [f.keys[i:i + 2] for i in range(0, len(f.keys), 2)])}
    assert (10, 11) in pairs and (12, 13) in pairs and (11, 12) not in pairs
    with pytest.raises(ValueError, match="a new segment needs a pose"):
        OnlineMapper(seq.camera, seq.priors, "multi-spd").add_frame(0.0, seq.poses_tum[0], new_segment=True)


def test_cli_run_of_a_drifting_room_moves_its_poses_only_by_loops_or_a_validated_refinement(drifting, tmp_path):
    """By default (``initial_poses="auto"`` → loops) the boxes move the poses of a trajectory
    without a bound on each pose only when the cross-validation between halves of the labels
    accepts it: without it and without a verified loop the run's trajectory is its input,
    exactly; never above the input's ATE; report.md, map.json's ``trajectory`` and
    map_top.png say how the poses came about; loops asked for with a held trajectory are
    refused in one line."""
    from spdslam.io import read_map

    folder = tmp_path / "room"
    write_sequence(drifting, folder)
    out = tmp_path / "run"
    assert_ok(invoke("run", folder, "--out", out))
    m, _ = read_map(out)
    t = m["trajectory"]
    assert t["start"] == "loops" and "loop_closure" in t
    rows = np.loadtxt(out / "trajectory.txt")
    rounds = t["refinement"]
    refined = rounds[0]["accepted"]
    # round by round until the halves refuse (or the most rounds): only the last may be refused
    assert all(rf["accepted"] for rf in rounds[:-1]) and [rf["round"] for rf in rounds] == list(range(1, len(rounds) + 1))
    if not refined and not any(lp["status"] == "verified" for lp in t["loop_closure"]["loops"]):
        np.testing.assert_allclose(rows[:, 1:], drifting.poses_tum, atol=1e-6)
    assert _ate(rows, drifting) <= _ate(drifting.poses_tum, drifting) * (1 + 1e-6)
    assert any(n.startswith("loop closure: 8 submaps") for n in m["notes"])
    assert any(n.startswith("poses refined by the boxes, round 1" if refined
                            else "poses not refined by the boxes, round 1") for n in m["notes"])
    assert refined or any(n.startswith("trajectory held at the") for n in m["notes"])
    report = (out / "report.md").read_text()
    assert "## Drift" in report and "Loop closure:" in report and "Poses refined by the boxes" in report
    assert ("its poses: loops, then refined by the boxes" in report) is refined
    assert report.count("- round ") == len(rounds)
    assert (out / "map_top.png").stat().st_size > 0
    assert_error(invoke("run", folder, "--out", tmp_path / "x", "--initial-poses", "loops", "--hold-trajectory"),
                 "--initial-poses: loops move the poses, which hold_trajectory holds")
    assert not (tmp_path / "x").exists()


# --- the boxes' refinement, cross-validated between halves of the labels ----------------------


def test_label_halves_split_the_boxes_evenly_by_label():
    from spdslam.mapping._refine import label_halves

    a, b = label_halves(["cup"] * 5 + ["book"] * 4 + ["tv"] * 2 + ["mouse"] * 2 + ["bowl"])
    assert a | b == {"cup", "book", "tv", "mouse", "bowl"} and not a & b
    assert {a, b} == {frozenset({"cup", "tv"}), frozenset({"book", "mouse", "bowl"})}  # 7 and 7 boxes
    assert label_halves(["cup"] * 9) is None and label_halves([]) is None


@pytest.mark.parametrize("costs, moved, accepted, said", [
    ({"given": 10.0, "moved": 5.0}, True, True, ""),
    ({"given": 10.0, "moved": 9.0}, True, False, "at 90 % of their cost"),
    ({"given": 10.0, "moved": 5.0}, False, False, "did not move the poses (a camera 9σ away)"),
])
def test_the_refinement_is_accepted_only_when_each_half_confirms_the_other(costs, moved, accepted, said):
    """Each half refines the poses, the other half's boxes judge them: both must fit the
    refined poses at most ``REFINE_MAX_RATIO`` of their cost on the poses given."""
    from spdslam.mapping._refine import REFINE_MAX_RATIO, validate_refinement

    asked = []

    def refine(half):
        asked.append(("refine", sorted(half)))
        return np.zeros((3, 7)) if moved else "a camera 9σ away"

    def held_cost(half, poses):
        asked.append(("cost", sorted(half), poses is None))
        return costs["given"] if poses is None else costs["moved"]

    got = validate_refinement(["cup", "cup", "tv", "book"], refine, held_cost)
    assert got.accepted is accepted and said in got.reason
    assert got.note().startswith("poses refined by the boxes, round 1" if accepted
                                 else "poses not refined by the boxes, round 1")
    if accepted:
        assert got.ratios == (0.5, 0.5) and max(got.ratios) <= REFINE_MAX_RATIO
        # each half refined once and judged by the other, on the poses given and the refined ones
        assert asked == [("refine", ["cup"]), ("cost", ["book", "tv"], True), ("cost", ["book", "tv"], False),
                         ("refine", ["book", "tv"]), ("cost", ["cup"], True), ("cost", ["cup"], False)]
    assert not validate_refinement(["cup"] * 4, refine, held_cost).accepted


def _biased(seq, px: float, seed: int):
    """The room's boxes, each object's shifted by the same offset (σ ``px`` per coordinate)
    in every view: a detector's bias, shared over the object's views; ids dropped."""
    rng = np.random.default_rng(seed)
    off = {k: rng.normal(0.0, px, 4) for k in sorted({d.instance for d in seq.detections})}
    return replace(seq, detections=[replace(d, box=d.box + off[d.instance], instance=None) for d in seq.detections])


def test_biased_boxes_on_an_odometry_that_barely_drifts_do_not_move_it():
    """Biased boxes (8 px per object, the same in each view) on a trajectory that drifts
    0.5 mm a step: the poses one half of the labels refines fit the other half's boxes no
    better (they moved for the first half's biases): refused, and the trajectory is the
    input, exactly."""
    seq = _biased(make_room_sequence(1, frames=80, objects=5, drift=0.0005), 8.0, 1)
    res = run_sequence(seq, "multi-spd")
    (rf,) = res.trajectory["refinement"]
    assert not rf["accepted"] and "refined at" in rf["reason"], rf
    np.testing.assert_allclose(res.poses_tum[:, 1:], seq.poses_tum, atol=1e-9)
    assert any(n.startswith("poses not refined by the boxes, round 1: the boxes of") for n in res.notes)


def test_a_drifting_room_is_refined_by_its_boxes_when_the_halves_agree(drifting):
    """The drifting room (no bound on each pose, no ids, boxes with independent noise): each
    half of the labels fits the poses the other refined far better; the run refines the poses
    with every box, again from there until the halves refuse, and ends well below the input's
    ATE, each round within the odometry's walk from the input."""
    from spdslam.mapping._refine import REFINE_MAX_ROUNDS

    res = run_sequence(drifting, "multi-spd")
    rounds = res.trajectory["refinement"]
    assert rounds[0]["accepted"] and max(rounds[0]["ratios"]) <= 0.5, rounds
    assert not rounds[-1]["accepted"] or len(rounds) == REFINE_MAX_ROUNDS
    assert _ate(res.poses_tum, drifting) <= 0.6 * _ate(drifting.poses_tum, drifting)
    checks = [c for c in res.trajectory["checks"] if c["step"] == "pose refinement"]
    assert len(checks) == sum(rf["accepted"] for rf in rounds)
    assert all(c["accepted"] and c["worst_sigma"] <= WALK_LIMIT for c in checks)


def test_a_half_of_the_labels_that_cannot_be_mapped_refuses_the_refinement_and_the_run_goes_on():
    """One label of the two left with two boxes: its half maps no object (its mapping
    fails for the whole half); the refinement is refused and says why, the run maps the
    other label's objects on the input poses, exactly."""
    seq = make_room_sequence(1, frames=80, objects=5, drift=0.01)
    big, small = sorted({d.label for d in seq.detections})[1], sorted({d.label for d in seq.detections})[0]
    few = [d for d in seq.detections if d.label == small][:2]
    seq = replace(seq, detections=[replace(d, instance=None) for d in seq.detections if d.label == big or d in few])
    res = run_sequence(seq, "multi-spd")
    (rf,) = res.trajectory["refinement"]
    assert not rf["accepted"] and rf["reason"], rf
    assert any(n.startswith("poses not refined by the boxes, round 1: ") for n in res.notes)
    assert {o.label for o in res.objects} == {big}
    np.testing.assert_allclose(res.poses_tum[:, 1:], seq.poses_tum, atol=1e-9)
