"""The cuboid-silhouette box model: geometry, residuals, finiteness at repeated radii,
initialisation, mapping, and the fr3_cabinet target."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

import spdslam  # noqa: F401  (float64)
from conftest import random_rotation, ring_of_views, upright_ellipsoid
from spdslam import Camera, Ellipsoid, EllipsoidRTS, look_at
from spdslam.geometry import (
    box_planes,
    cuboid_corners,
    cuboid_in_front,
    project_box,
    project_cuboid_box,
)
from spdslam.factors import (
    InverseCuboidBoxFactor,
    SemiInverseCuboidBoxFactor,
    inverse_cuboid_box_residual,
    semi_inverse_cuboid_box_residual,
    tangent_jacobians,
)
from spdslam.frontend import multi_initialize, MultiFit
from spdslam.mapping import Method, run_sequence
from spdslam.mapping._context import object_shape
from spdslam.io import ClassPrior, Priors

CAM = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)
FR3 = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "tum_fr3_cabinet"
PARAMS = ("spd", "rts", "full")


def _as(e: Ellipsoid, param):
    return {"spd": e, "rts": e.to_rts(), "full": e.to_full()}[param]


def _scene(rng, radii=None):
    """A random ellipsoid and a pose 3-6 m away looking near its centre."""
    R = random_rotation(rng)
    t = rng.uniform(-1, 1, 3)
    s = rng.uniform(0.2, 0.8, 3) if radii is None else np.asarray(radii, float)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    T = look_at(t + rng.uniform(3.0, 6.0) * d, t + 0.1 * rng.normal(size=3), up=rng.normal(size=3))
    return Ellipsoid.from_axes(R, t, s), T, R, t, s


def _brute_corners(R, t, s):
    return np.array([t + R @ (np.array([a, b, c]) * s)
                     for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])


def _brute_box(X, T):
    """Projected extremes of world points X with numpy (independent of spdslam.camera)."""
    M = np.asarray(T.inverse().as_matrix())
    Xc = X @ M[:3, :3].T + M[:3, 3]
    u = CAM.fx * Xc[:, 0] / Xc[:, 2] + CAM.cx
    v = CAM.fy * Xc[:, 1] / Xc[:, 2] + CAM.cy
    return np.array([u.min(), v.min(), u.max(), v.max()]), Xc[:, 2]


# --- geometry ---------------------------------------------------------------------------


@pytest.mark.parametrize("param", PARAMS)
def test_cuboid_box_is_the_box_of_the_projected_corners(param):
    rng = np.random.default_rng(0)
    for _ in range(10):
        e, T, R, t, s = _scene(rng)
        box, depth = _brute_box(_brute_corners(R, t, s), T)
        x = _as(e, param)
        np.testing.assert_allclose(project_cuboid_box(x, T, CAM), box, rtol=1e-9, atol=1e-8)
        assert bool(cuboid_in_front(x, T)) == bool(np.all(depth > 0))
        # the corner set does not depend on the parameterisation's axis order or signs
        got = np.asarray(cuboid_corners(x))
        ref = _brute_corners(R, t, s)
        d = np.linalg.norm(got[:, None] - ref[None], axis=-1)
        assert np.all(d.min(axis=1) < 1e-9)
        # the inscribed ellipsoid's box lies inside the cuboid's
        b_e = np.asarray(project_box(e, T, CAM))
        assert np.all(b_e[:2] >= box[:2] - 1e-9) and np.all(b_e[2:] <= box[2:] + 1e-9)


def test_cuboid_in_front_is_all_corners_in_front():
    """A camera just beside a corner: the ellipsoid is in front, the cuboid is not."""
    e = Ellipsoid.from_axes(np.eye(3), [0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    # looking along +x from x = -1.2 at the height of the top corners: corners (−1, ±1, ±1)
    # are at depth 0.2, but tilt the camera so that one of them goes behind
    T = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_matrix(np.asarray(look_at([-1.3, 0, 0], [0, 2.0, 0]).rotation().as_matrix())),
        jnp.array([-1.3, 0.0, 0.0]),
    )
    _, depth = _brute_box(_brute_corners(np.eye(3), np.zeros(3), np.ones(3)), T)
    assert np.any(depth <= 0)
    assert not bool(cuboid_in_front(e, T))
    f = InverseCuboidBoxFactor("x", "l", [100, 100, 200, 200], CAM)
    assert not bool(f.valid(T, e, *f.args))
    far = look_at([-6.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    assert bool(cuboid_in_front(e, far)) and bool(f.valid(far, e, *f.args))
    # batched: vmap over poses
    Ts = jaxlie.SE3(jnp.stack([T.wxyz_xyz, far.wxyz_xyz]))
    np.testing.assert_array_equal(jax.vmap(lambda TT: cuboid_in_front(e, TT))(Ts), [False, True])


# --- residuals ----------------------------------------------------------------------------


@pytest.mark.parametrize("param", PARAMS)
def test_cuboid_residuals_vanish_at_truth_and_not_when_perturbed(param):
    rng = np.random.default_rng(1)
    for _ in range(10):
        e, T, R, t, s = _scene(rng)
        x = _as(e, param)
        box = np.asarray(project_cuboid_box(x, T, CAM))
        assert np.max(np.abs(inverse_cuboid_box_residual(T, x, box, CAM))) < 1e-9
        assert np.max(np.abs(semi_inverse_cuboid_box_residual(T, x, box, CAM))) < 1e-9
        for wrong in (
            Ellipsoid.from_axes(R, t, 1.2 * s),
            Ellipsoid.from_axes(R, t + 0.1 * rng.normal(size=3), s),
            Ellipsoid.from_axes(R @ np.asarray(jaxlie.SO3.exp(jnp.array([0, 0, 0.2])).as_matrix()), t, s),
        ):
            w = _as(wrong, param)
            assert np.max(np.abs(inverse_cuboid_box_residual(T, w, box, CAM))) > 1.0  # px
            assert np.max(np.abs(semi_inverse_cuboid_box_residual(T, w, box, CAM))) > 1e-3  # m


def test_semi_inverse_cuboid_is_the_signed_gap_of_the_corners():
    """Per edge plane π = [n; d], with the corners' extreme distances m± = max/min n·x + d:
    half-width (m₊ − m₋)/2 minus centre distance |m₊ + m₋|/2 (> 0: the plane cuts the
    cuboid, < 0: it misses it, and then the value is minus the gap to the nearest corner)."""
    rng = np.random.default_rng(2)
    signs = []
    for _ in range(30):
        e, T, R, t, s = _scene(rng)
        box = np.asarray(project_cuboid_box(e, T, CAM)) + rng.normal(scale=15.0, size=4)
        box = np.r_[np.minimum(box[:2], box[2:]), np.maximum(box[:2], box[2:])]
        pl = np.asarray(box_planes(box, T, CAM))
        dist = _brute_corners(R, t, s) @ pl[:, :3].T + pl[:, 3]  # (8 corners, 4 planes)
        hi, lo = dist.max(axis=0), dist.min(axis=0)
        expected = (hi - lo) / 2 - np.abs(hi + lo) / 2
        got = np.asarray(semi_inverse_cuboid_box_residual(T, e, box, CAM))
        np.testing.assert_allclose(got, expected, atol=1e-12)
        separated = (lo > 0) | (hi < 0)
        np.testing.assert_allclose(got[separated], -np.minimum(np.abs(lo), np.abs(hi))[separated],
                                   atol=1e-12)
        signs.append(np.sign(got))
    signs = np.concatenate(signs)
    assert (signs > 0).any() and (signs < 0).any()


def _near_tie_radii():
    return {
        "sphere": [0.5, 0.5, 0.5],
        "spheroid": [0.7, 0.4, 0.4],
        "prolate": [0.4, 0.7, 0.7],
        "near_sphere": [0.5, 0.5 + 1e-9, 0.5 - 1e-9],
        "near_spheroid": [0.7, 0.4 + 1e-9, 0.4],
    }


_JAC = {}


def _jacobians(res):
    if res not in _JAC:
        _JAC[res] = jax.jit(lambda T, x, b: tangent_jacobians(res, (T, x), (b, CAM)))
    return _JAC[res]


@pytest.mark.parametrize("param", PARAMS)
@pytest.mark.parametrize("kind", list(_near_tie_radii()))
def test_cuboid_residuals_finite_at_repeated_radii(param, kind):
    """Values and tangent Jacobians stay finite at exact and near (1e-9) ties."""
    rng = np.random.default_rng(3)
    radii = _near_tie_radii()[kind]
    for k in range(4):
        e, T, _, t, _ = _scene(rng, radii)
        if kind == "sphere" and k == 0:
            e = Ellipsoid(jnp.eye(3) * 0.25, jnp.asarray(t))  # exact s²I
        x = _as(e, param)
        box = np.asarray(project_box(e, T, CAM)) + rng.normal(scale=3.0, size=4)
        box = np.r_[np.minimum(box[:2], box[2:]), np.maximum(box[:2], box[2:])]
        for res in (inverse_cuboid_box_residual, semi_inverse_cuboid_box_residual):
            r, J = _jacobians(res)(T, x, jnp.asarray(box))
            assert np.all(np.isfinite(r)), (res.__name__, r)
            assert all(np.all(np.isfinite(j)) for j in J), res.__name__
        # the residual is that of some cuboid of the right radii: zero at its own box
        b = np.asarray(project_cuboid_box(x, T, CAM))
        assert np.all(np.isfinite(b))
        assert np.max(np.abs(inverse_cuboid_box_residual(T, x, b, CAM))) < 1e-9


def test_cuboid_factor_builders():
    box = [100.0, 120.0, 300.0, 330.0]
    f = InverseCuboidBoxFactor("x", "l", box, CAM)
    g = SemiInverseCuboidBoxFactor("x", "l", box, CAM, sigma=0.02)
    assert f.kind == "inverse_cuboid_box" and g.kind == "semi_inverse_cuboid_box"
    assert len(f.args) == 2 and np.allclose(np.diag(g.sqrt_info), 50.0)
    with pytest.raises(ValueError, match="box must be finite"):
        InverseCuboidBoxFactor("x", "l", [10, 10, 5, 20], CAM)
    with pytest.raises(ValueError, match="truncation_margin"):
        SemiInverseCuboidBoxFactor("x", "l", box, CAM, truncation_margin=-1.0)
    with pytest.raises(TypeError, match="Camera"):
        InverseCuboidBoxFactor("x", "l", box, (500, 500, 320, 240))


# --- initialisation and mapping -------------------------------------------------------------


def test_multi_initialize_cuboid_recovers_a_noise_free_box_object():
    e = upright_ellipsoid()
    poses = ring_of_views(np.asarray(e.center))
    boxes = np.stack([np.asarray(project_cuboid_box(e, T, CAM)) for T in poses])
    got = multi_initialize(boxes, poses, CAM, up=[0, 0, 1], support_plane=[0, 0, 1, 0],
                           fit=MultiFit(shape="cuboid"))
    np.testing.assert_allclose(got.center, e.center, atol=1e-6)
    np.testing.assert_allclose(got.P, e.P, atol=1e-6)
    # the ellipsoid model on the same boxes inflates the radii (the motivation)
    ell = multi_initialize(boxes, poses, CAM, up=[0, 0, 1], support_plane=[0, 0, 1, 0])
    assert np.all(np.asarray(ell.radii) > np.asarray(e.radii) * 1.05)
    with pytest.raises(ValueError, match="shape must be one of"):
        multi_initialize(boxes, poses, CAM, up=[0, 0, 1], fit=MultiFit(shape="box"))


def test_object_shape_from_method_or_class_priors():
    pri = Priors([np.array([0, 0, 1.0, 0])], np.array([0, 0, 1.0]),
                 {"cabinet": ClassPrior([0.4, 0.2, 0.3], 0.1, "cuboid"),
                  "ball": ClassPrior([0.1, 0.1, 0.1], 0.1)})
    m = Method("x")
    assert m.object_shape == "priors"
    assert object_shape(m, pri, "cabinet") == "cuboid"
    assert object_shape(m, pri, "ball") == "ellipsoid"
    assert object_shape(m, pri, "chair") == "ellipsoid"  # no prior
    assert object_shape(m, None, "cabinet") == "ellipsoid"
    assert object_shape(m.replace(object_shape="ellipsoid"), pri, "cabinet") == "ellipsoid"
    assert object_shape(m.replace(object_shape="cuboid"), pri, "ball") == "cuboid"
    with pytest.raises(ValueError, match="object_shape must be one of"):
        Method("x", object_shape="box")
    with pytest.raises(ValueError, match="truncation_margin"):
        Method("x", truncation_margin=float("nan"))
    assert Method("x", truncation_margin=-1).margin is None and m.margin == 5.0


def test_build_graph_uses_the_cuboid_factors_for_cuboid_classes():
    from spdslam.synthetic import make_room_sequence
    from spdslam.frontend import tracks_from_instances
    from spdslam.mapping import build_graph

    seq = make_room_sequence(0, frames=30, objects=1)
    tracks = tracks_from_instances(seq)
    init = {g.id: Ellipsoid.from_axes(g.cuboid.rotation, g.cuboid.center, g.cuboid.half_extents)
            for g in seq.objects_gt}
    assert {tr.id for tr in tracks} <= set(init)
    for shape, kinds in (("cuboid", {"inverse_cuboid_box"}), ("ellipsoid", {"inverse_box"})):
        method = Method("x", object_shape=shape)
        graph = build_graph(seq, tracks, init, method)
        box_kinds = {f.kind for f in graph if "box" in f.kind}
        assert box_kinds == kinds
        # every box factor carries a truncation mask, so they all batch together
        assert all(len(f.args) == 3 for f in graph if "box" in f.kind)
        semi = build_graph(seq, tracks, init, method.replace(box_model="semi"))
        assert {f.kind for f in semi if "box" in f.kind} == {
            k.replace("inverse", "semi_inverse") for k in kinds}


@pytest.mark.slow  # a real-data target study (-m slow); the default suite maps fr3_cabinet in test_mapping.py
@pytest.mark.skipif(not FR3.is_dir(), reason=f"fr3_cabinet data not found at {FR3}")
def test_fr3_cabinet_cuboid_model_target():
    """Issue 5's target: with the cuboid silhouette model, IoU ≥ 0.80 and orientation
    error ≤ 1.0° on fr3_cabinet (the ellipsoid model gives IoU 0.375)."""
    from spdslam.evaluation import evaluate_objects
    from spdslam.io import read_sequence

    seq = read_sequence(FR3)
    r = run_sequence(seq, "multi-spd", object_shape="cuboid")
    _, s = evaluate_objects(r.objects, seq.objects_gt)
    print(f"fr3_cabinet multi-spd cuboid: IoU {s['mean_iou']:.3f}, "
          f"orientation error {s['mean_orientation_deg']:.2f} deg")
    assert s["matched"] == 1
    assert s["mean_iou"] >= 0.80 and s["mean_orientation_deg"] <= 1.0, s


# --- per-axis orientation constraint of cuboid objects ----------------------------------------


def _rot_x(a):
    c, s_ = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s_], [0, s_, c]])


@pytest.mark.parametrize("radii", [(0.5, 0.3, 0.2), (0.3, 0.3, 0.2), (0.3, 0.25, 0.25)])
def test_axis_orientation_residual_value(radii):
    """Each block is (nᵢ × m)(nᵢ·m), of norm ½|sin 2θᵢ|: zero for any axis order and sign,
    and for a tilt θ about x the full strength ½ sin 2θ on two blocks, also when two radii
    are equal, where (Log P m) × m fades (it vanishes for s_y = s_z)."""
    from spdslam.factors import axis_orientation_residual, orientation_residual

    up = np.array([0.0, 0.0, 1.0])
    perm = np.eye(3)[[2, 0, 1]] * np.array([1.0, -1.0, 1.0])  # swapped and flipped axes
    for R in (np.eye(3), perm):
        e = Ellipsoid.from_axes(jnp.asarray(R), jnp.zeros(3), jnp.asarray(radii))
        np.testing.assert_allclose(np.asarray(axis_orientation_residual(e, up)), 0.0, atol=1e-12)
    theta = 0.02
    e = EllipsoidRTS.from_axes(jnp.asarray(_rot_x(theta)), jnp.zeros(3), jnp.asarray(radii))
    r = np.asarray(axis_orientation_residual(e, up)).reshape(3, 3)
    norms = np.linalg.norm(r, axis=1)
    np.testing.assert_allclose(np.sort(norms), [0.0, 0.5 * np.sin(2 * theta), 0.5 * np.sin(2 * theta)], atol=1e-12)
    weak = np.linalg.norm(np.asarray(orientation_residual(e, up)))
    if radii[1] == radii[2]:
        assert weak < 1e-12  # the ellipsoid form cannot see this tilt
    assert np.linalg.norm(r) > 0.02


def test_axis_orientation_finite_at_ties():
    from spdslam.factors import axis_orientation_residual
    from spdslam.factors import tangent_jacobians

    up = jnp.array([0.0, 0.3, 1.0])
    for radii in [(0.3, 0.3, 0.3), (0.3, 0.3, 0.2), (0.3, 0.3 + 1e-9, 0.2)]:
        e = Ellipsoid.from_axes(jnp.asarray(_rot_x(0.3)), jnp.zeros(3), jnp.asarray(radii))
        r, J = tangent_jacobians(axis_orientation_residual, (e,), (up,))
        assert np.all(np.isfinite(np.asarray(r))) and np.all(np.isfinite(np.asarray(J[0])))
