"""What a real recording needs of the back end (issue 27): the trajectory's noise from the
input itself with a bound on each pose, the screen of impossible boxes, the robust kernel
with automatic association, no implausibly flat object, a front end that is not snapped
upright."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spdslam.frontend import multi_initialize, MultiFit, screen_detections
from spdslam.geometry import Camera, Ellipsoid, project_box
from spdslam.io import ClassPrior, Detection, Priors, SequenceFormatError, read_priors, read_sequence, write_sequence
from spdslam.mapping import METHODS, build_graph, run_sequence
from spdslam.mapping._graph import mapping_sigmas
from spdslam.mapping._methods import AUTO_BOX_KERNEL, check_sigma
from spdslam.mapping._run import MIN_PLAUSIBLE_RADIUS, implausibly_flat
from spdslam.mapping._noise import estimate_step_sigma
from spdslam.synthetic import make_room_sequence


def _trajectory(n=400, noise=0.0, rot_noise=0.0, seed=0, dt=1 / 30):
    """A smooth circle at walking speed with white pose noise (m, rad per axis)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    a = 0.3 * t
    c = np.c_[2 * np.cos(a), 2 * np.sin(a), np.full(n, 1.5)] + noise * rng.standard_normal((n, 3))
    r = Rotation.from_rotvec(np.c_[np.zeros(n), np.zeros(n), a]) * \
        Rotation.from_rotvec(rot_noise * rng.standard_normal((n, 3)))
    return t, np.c_[c, r.as_quat()]


@pytest.mark.parametrize("noise", [0.002, 0.0005])
def test_the_step_sigma_is_estimated_from_the_jitter(noise):
    t, P = _trajectory(noise=noise, rot_noise=noise)
    st, sr = estimate_step_sigma(t, P)
    # a relative motion of two poses with σ each: √2 σ (the circle's own curvature adds little)
    assert st == pytest.approx(np.sqrt(2) * noise, rel=0.2)
    assert sr == pytest.approx(np.sqrt(2) * noise, rel=0.2)
    assert estimate_step_sigma(t[:10], P[:10]) is None


def test_dropped_frames_do_not_inflate_the_estimate():
    t, P = _trajectory(noise=0.001)
    keep = np.ones(len(t), bool)
    keep[::7] = False  # a dropped frame every 7: steps of two periods beside steps of one
    st, _ = estimate_step_sigma(t[keep], P[keep])
    assert st == pytest.approx(np.sqrt(2) * 0.001, rel=0.25)


def test_where_the_trajectory_sigmas_come_from():
    seq = make_room_sequence(0, frames=40, objects=2)
    src = {}
    s = mapping_sigmas(seq, None, src)  # the demo states a drifting odometry
    assert src["odometry_translation"] == "priors.yaml" and np.isinf(s["absolute_translation"])
    t, P = _trajectory(n=40, noise=0.001)
    seq2 = dataclasses.replace(seq, poses_tum=P, timestamps=t, priors=Priors(up=[0, 0, 1.0]))
    s = mapping_sigmas(seq2, None, src)
    assert src["odometry_translation"] == "estimated from the trajectory's jitter"
    assert src["absolute_translation"] == "default" and s["absolute_translation"] == 0.002
    s = mapping_sigmas(seq2, {"absolute_rotation": np.inf}, src)
    assert src["absolute_rotation"] == "--sigma" and np.isinf(s["absolute_rotation"])
    assert check_sigma("absolute_translation", "inf") == np.inf
    with pytest.raises(ValueError):
        check_sigma("odometry_translation", "inf")


def test_every_pose_is_bound_to_its_input_unless_the_bound_is_infinite():
    seq = make_room_sequence(0, frames=12, objects=1)
    lms = {}
    kinds = lambda g: [f.kind for f in g]  # noqa: E731
    g = build_graph(seq, [], lms, METHODS["multi-spd"])
    assert kinds(g).count("prior") == 1 and kinds(g).count("between") == 11  # drifting: no bound
    bound = dataclasses.replace(seq, priors=seq.priors.replace(trajectory_absolute_sigma=[0.01, 0.02]))
    g = build_graph(bound, [], lms, METHODS["multi-spd"])
    assert kinds(g).count("prior") == 12
    assert kinds(build_graph(bound, [], lms, METHODS["multi-spd"], odometry=False)) == []


def test_the_absolute_sigma_round_trips_through_priors_yaml(tmp_path):
    seq = make_room_sequence(0, frames=5, objects=1)
    out = write_sequence(seq, tmp_path / "s")
    assert "trajectory_absolute_sigma: [.inf, .inf]" in (out / "priors.yaml").read_text()
    assert read_sequence(out).priors == seq.priors
    (tmp_path / "p.yaml").write_text("trajectory_absolute_sigma: [0.01, -1]\n")
    with pytest.raises(SequenceFormatError, match="p.yaml:1"):
        read_priors(tmp_path / "p.yaml")


def _det(frame, box, label="cup", score=0.9):
    return Detection(frame, 0.1 * frame, np.asarray(box, float), label, score)


def test_the_screen_drops_duplicates_truncated_and_impossible_boxes():
    cam = Camera(500, 500, 320, 240, 640, 480)
    seq = make_room_sequence(0, frames=3, objects=1)
    dets = [
        _det(0, [100, 100, 150, 160], "cup", 0.9),
        _det(0, [101, 101, 151, 160], "bottle", 0.6),  # the same object boxed twice: dropped
        _det(1, [0, 0, 640, 480], "chair"),  # every edge at the border
        _det(2, [100, 100, 400, 120], "cup"),  # 15:1, no cup looks like that
        _det(2, [300, 100, 340, 150], "cup"),  # kept
    ]
    s = screen_detections(dataclasses.replace(seq, camera=cam, detections=dets, priors=Priors()))
    assert s.counts() == {"duplicate": 1, "truncated": 1, "aspect": 1}
    assert [d.label for d in s.sequence.detections] == ["cup", "cup"]
    assert "3 of 5 detections left out" in s.summary()


def test_a_flat_object_is_implausible_unless_its_class_is_flat():
    flat = Ellipsoid.from_axes(np.eye(3), np.zeros(3), [0.2, 0.1, 0.002])
    thin = Ellipsoid.from_axes(np.eye(3), np.zeros(3), [0.5, 0.3, 0.01])  # 0.02 of its largest
    fine = Ellipsoid.from_axes(np.eye(3), np.zeros(3), [0.2, 0.1, 0.02])
    assert "flat" in implausibly_flat(flat) and "flat" in implausibly_flat(thin)
    assert implausibly_flat(fine) == ""
    paper = ClassPrior([0.15, 0.1, 0.001], 0.2)
    assert implausibly_flat(flat, paper) == ""
    assert MIN_PLAUSIBLE_RADIUS == 3e-3


def test_the_robust_kernel_follows_the_association():
    m = METHODS["multi-spd"]
    assert m.robust == "auto"
    assert (m.resolved(True).robust, m.resolved(True).robust_k) == AUTO_BOX_KERNEL
    assert m.resolved(False).robust == "none"
    assert m.replace(robust="huber").resolved(True).robust == "huber"
    seq = make_room_sequence(0, frames=30, objects=2)
    r = run_sequence(seq, "multi-spd", initial_poses="input")  # instance ids: the paper's setting, no kernel
    assert r.method.robust == "none" and r.as_dict()["settings"]["robust"] == "none"
    assert set(r.costs) >= {"inverse_box", "between"}


def test_the_multi_constraint_start_is_not_snapped_upright():
    """An object tilted by 4° (a monitor leaning back): the upright fit cannot follow it, the
    start with the tilt set free moves towards it (part of the way: the prior, σ
    ``TILT_SIGMA`` ≈ 1.1°, pulls back against boxes that change by a few pixels)."""
    cam = Camera(500, 500, 320, 240, 640, 480)
    tilt = Rotation.from_rotvec([np.radians(4.0), 0, 0]).as_matrix()
    truth = Ellipsoid.from_axes(tilt, [0.0, 0.0, 0.8], [0.3, 0.2, 0.1])
    from spdslam.geometry import look_at

    poses = [look_at([2.5 * np.cos(a), 2.5 * np.sin(a), 1.4], [0, 0, 0.8]) for a in np.linspace(-1.2, 1.2, 12)]
    boxes = np.stack([np.asarray(project_box(truth, T, cam)) for T in poses])
    up = np.array([0.0, 0.0, 1.0])

    def tilt_deg(e):
        R, _ = (np.asarray(a) for a in e.axes())
        return np.degrees(np.arccos(np.max(np.abs(R.T @ up))))

    upright = multi_initialize(boxes, poses, cam, up, fit=MultiFit(tilt_sigma=None))
    free = multi_initialize(boxes, poses, cam, up)
    assert tilt_deg(upright) < 1e-6
    assert 0.25 < tilt_deg(free) < 4.0


def test_an_object_held_trajectory_run_keeps_the_poses():
    seq = make_room_sequence(1, frames=30, objects=2)
    r = run_sequence(seq, "multi-spd", hold_trajectory=True)
    np.testing.assert_allclose(r.poses_tum[:, 1:], seq.poses_tum, atol=1e-12)
    assert "between" not in r.costs and r.notes[0] == "trajectory held at the input poses"
    assert r.objects


def test_an_implausibly_flat_result_is_reported_not_mapped():
    """A result thinner than the rule (a book 2 mm thick) goes to the failures with its
    reason (``map_result``), whatever made it."""
    from spdslam.factors import LandmarkPriorFactor, PriorFactor
    from spdslam.geometry.se3 import from_tum
    from spdslam.mapping._run import Optimised, map_result
    from spdslam.solver import L, NonlinearFactorGraph, Values, X

    seq = make_room_sequence(0, frames=3, objects=1)
    flat = Ellipsoid.from_axes(np.eye(3), [0, 0, 0.5], [0.3, 0.2, 0.002])
    T0 = from_tum(seq.poses_tum[0])
    values = Values({L(0): flat, X(0): T0})
    graph = NonlinearFactorGraph([LandmarkPriorFactor(L(0), flat, sigma=0.01), PriorFactor(X(0), T0, sigma=0.01)])

    class _Res:
        final_cost, converged, reason = 0.0, True, "test"

    solved = Optimised(values=values, graph=graph, result=_Res(), initial_cost=0.0)
    r = map_result(METHODS["multi-spd"], solved, {0: "book"}, {}, seq.timestamps[:1], {}, priors=Priors())
    assert not r.objects and "poorly observed: flat" in r.failed[0]

