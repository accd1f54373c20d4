"""Behaviour of the landmark factors: zeros where they must be, the paper's slips, errors."""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie
import numpy as np
from scipy.spatial.transform import Rotation
import pytest
from scipy.optimize import brentq

import spdslam  # noqa: F401
from conftest import random_rotation
from spdslam import Camera, Ellipsoid, EllipsoidFull, EllipsoidRTS, box_planes, project_box
from spdslam.factors import (
    Cauchy,
    ClassicOrientationFactor,
    Huber,
    InverseBoxFactor,
    InverseCuboidBoxFactor,
    OrientationFactor,
    SemiInverseBoxFactor,
    SemiInverseCuboidBoxFactor,
    ShapeFactor,
    SizeFactor,
    SupportPlaneFactor,
    classic_orientation_residual,
    inverse_box_residual,
    orientation_residual,
    semi_inverse_box_residual,
    shape_residual,
    size_residual,
    sqrt_information,
    support_plane_residual,
)
from spdslam.solver import L, X

CAM = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def as_param(e: Ellipsoid, param: str):
    return {"spd": e, "rts": e.to_rts(), "full": e.to_full()}[param]


@pytest.mark.parametrize("param", ["spd", "rts", "full"])
def test_box_residuals_vanish_at_truth_for_noise_free_boxes(param):
    rng = np.random.default_rng(0)
    for _ in range(20):
        e = Ellipsoid.from_axes(random_rotation(rng), rng.uniform(-1, 1, 3), rng.uniform(0.2, 1.0, 3))
        T = jaxlie.SE3.from_matrix(look_at(e.center + 5 * rng.normal(size=3) / 1.7, e.center))
        x = as_param(e, param)
        box = project_box(e, T, CAM)
        # Semi-inverse: each πᵀQ*π vanishes to rounding (m², planes with unit normals).
        r = semi_inverse_box_residual(T, x, box, CAM)
        assert np.max(np.abs(r)) < 1e-10
        assert np.max(np.abs(inverse_box_residual(T, x, box, CAM))) < 1e-9


def test_semi_inverse_sum_lets_edges_cancel():
    """The paper's Σᵢ πᵢᵀQ*πᵢ can vanish for a wrong ellipsoid; per-edge residuals cannot."""
    truth = Ellipsoid.from_axes(np.eye(3), [0.0, 0.0, 0.0], [0.5, 0.4, 0.3])
    T = jaxlie.SE3.from_matrix(look_at(np.array([0.0, -4.0, 0.5]), truth.center))
    box = project_box(truth, T, CAM)
    shift = np.array([0.15, 0.0, 0.0])  # sideways: one edge too tight, the opposite too loose

    def wrong(k):
        return Ellipsoid(truth.P * k**2, truth.center + shift)

    def summed(k):
        return float(jnp.sum(semi_inverse_box_residual(T, wrong(k), box, CAM)))

    k = brentq(summed, 0.8, 1.2)  # scale that makes the paper's sum exactly zero
    per_edge = semi_inverse_box_residual(T, wrong(k), box, CAM)
    assert abs(summed(k)) < 1e-12
    assert np.max(np.abs(per_edge)) > 0.05  # m²: clearly not tangent
    assert np.max(np.abs(inverse_box_residual(T, wrong(k), box, CAM))) > 10.0  # px


def test_box_factor_validity_flags_degenerate_geometry():
    e = Ellipsoid.from_axes(np.eye(3), [0.0, 0.0, 0.0], [0.5, 0.4, 0.3])
    box = np.array([100.0, 100.0, 200.0, 200.0])
    f = InverseBoxFactor("x", "l", box, CAM)
    front = jaxlie.SE3.from_matrix(look_at(np.array([0.0, -4.0, 0.0]), e.center))
    behind = jaxlie.SE3.from_matrix(look_at(np.array([0.0, -4.0, 0.0]), np.array([0.0, -8.0, 0.0])))
    inside = jaxlie.SE3.from_matrix(look_at(np.array([0.0, 0.0, 0.1]), np.array([0.0, 5.0, 0.1])))
    assert bool(f.valid(front, e, *f.args))
    assert not bool(f.valid(behind, e, *f.args))
    assert not bool(f.valid(inside, e, *f.args))
    # Residuals stay finite even where the box is meaningless.
    for T in (behind, inside):
        assert np.all(np.isfinite(f.evaluate(T, e)))
        assert np.all(np.isfinite(SemiInverseBoxFactor("x", "l", box, CAM).evaluate(T, e)))


def _weighted_axis_sum(P, m):
    w, V = np.linalg.eigh(np.asarray(P))
    return sum(np.log(w[i]) * np.cross(V[:, i], m) * (V[:, i] @ m) for i in range(3))


def test_orientation_residual_is_the_log_weighted_per_axis_sum():
    rng = np.random.default_rng(1)
    for _ in range(30):
        e = Ellipsoid.from_axes(random_rotation(rng), np.zeros(3), rng.uniform(0.2, 1.0, 3))
        m = rng.normal(size=3)
        m /= np.linalg.norm(m)
        np.testing.assert_allclose(orientation_residual(e, m), _weighted_axis_sum(e.P, m), atol=1e-12)
        # the unweighted sum of the per-axis terms is identically zero
        _, V = np.linalg.eigh(np.asarray(e.P))
        unweighted = sum(np.cross(V[:, i], m) * (V[:, i] @ m) for i in range(3))
        assert np.linalg.norm(unweighted) < 1e-12


def test_orientation_zero_iff_axis_parallel_or_perpendicular():
    up = np.array([0.0, 0.0, 1.0])
    radii = [0.6, 0.4, 0.25]
    for perm in ([0, 1, 2], [2, 0, 1], [1, 2, 0]):
        for sign in (1.0, -1.0):
            R = np.eye(3)[:, perm] * np.array([1.0, 1.0, sign])
            e = Ellipsoid.from_axes(R, np.zeros(3), radii)
            assert np.linalg.norm(orientation_residual(e, up)) < 1e-12
            # The same ellipsoid as RTS with permuted axes: still zero.
            assert np.linalg.norm(orientation_residual(EllipsoidRTS.from_axes(R, np.zeros(3), radii), up)) < 1e-12
    tilted = jaxlie.SO3.from_x_radians(np.deg2rad(30.0)).as_matrix()
    e = Ellipsoid.from_axes(tilted, np.zeros(3), radii)
    assert np.linalg.norm(orientation_residual(e, up)) > 0.05
    # scale invariance
    big = Ellipsoid(e.P * 9.0, e.center)
    np.testing.assert_allclose(orientation_residual(big, up), orientation_residual(e, up), atol=1e-12)


def test_classic_orientation_depends_on_axis_order():
    """The flaw of the classic form: the same upright object, axes listed in another order."""
    up = np.array([0.0, 0.0, 1.0])
    radii = np.array([0.6, 0.4, 0.25])
    upright = EllipsoidRTS.from_axes(np.eye(3), np.zeros(3), radii)
    perm = [2, 0, 1]
    swapped = EllipsoidRTS.from_axes(np.eye(3)[:, perm], np.zeros(3), radii[perm])
    np.testing.assert_allclose(swapped.to_ellipsoid().P, upright.to_ellipsoid().P, atol=1e-12)
    z = np.eye(3)[2]
    assert float(np.linalg.norm(classic_orientation_residual(upright, up, z))) < 1e-12
    # sin 90°: the largest pull there is
    np.testing.assert_allclose(np.linalg.norm(classic_orientation_residual(swapped, up, z)), 1.0, atol=1e-12)
    tilted = EllipsoidRTS.from_axes(Rotation.from_rotvec([0.3, 0, 0]).as_matrix(), np.zeros(3), radii)
    np.testing.assert_allclose(np.linalg.norm(classic_orientation_residual(tilted, up, z)), np.sin(0.3))
    # …while the improved form sees the same object.
    assert np.linalg.norm(orientation_residual(swapped, up)) < 1e-12
    with pytest.raises(TypeError, match="RTS"):
        classic_orientation_residual(swapped.to_ellipsoid(), up, z)


def test_classic_shape_depends_on_axis_order():
    """The classic shape prior reads the stored scales in order: the same object with its axes
    listed in another order misses the prior, the sorted form does not."""
    from spdslam.factors import ClassicShapeFactor, classic_shape_residual

    radii = np.array([0.6, 0.4, 0.25])
    prior = radii / radii[2]
    upright = EllipsoidRTS.from_axes(np.eye(3), np.zeros(3), radii)
    perm = [2, 0, 1]
    swapped = EllipsoidRTS.from_axes(np.eye(3)[:, perm], np.zeros(3), radii[perm])
    assert np.linalg.norm(classic_shape_residual(upright, prior[:2])) < 1e-12
    np.testing.assert_allclose(classic_shape_residual(swapped, prior[:2]),
                               [0.25 / 0.4 - 2.4, 0.6 / 0.4 - 1.6], atol=1e-12)
    assert np.linalg.norm(shape_residual(swapped, np.array([2.4, 1.6]))) < 1e-12
    # the factor keeps the class's stated order (x, y, z) and takes the signs' absolute value
    f = ClassicShapeFactor("l", [0.6, 0.4, 0.25])
    np.testing.assert_allclose(f.args[0], [2.4, 1.6])
    flipped = EllipsoidRTS.from_axes(np.eye(3), np.zeros(3), -radii)
    assert np.linalg.norm(classic_shape_residual(flipped, prior[:2])) < 1e-12
    with pytest.raises(TypeError, match="RTS"):
        classic_shape_residual(swapped.to_ellipsoid(), prior[:2])
    with pytest.raises(ValueError, match="positive"):
        ClassicShapeFactor("l", [0.6, 0.0, 0.25])


def test_shape_and_size_priors():
    prior = np.array([0.5, 0.3, 0.2])
    rng = np.random.default_rng(2)
    for perm in ([0, 1, 2], [2, 1, 0], [1, 0, 2]):
        e = Ellipsoid.from_axes(random_rotation(rng), rng.normal(size=3), prior[perm] * 1.7)
        f = ShapeFactor("l", prior[[2, 0, 1]])
        np.testing.assert_allclose(f.evaluate(e), 0.0, atol=1e-10)  # scale-free, order-free
        assert abs(float(size_residual(e, np.log(prior).sum())[0]) - np.log(1.7)) < 1e-10
    e = Ellipsoid.from_axes(np.eye(3), np.zeros(3), [0.5, 0.5, 0.5])
    np.testing.assert_allclose(shape_residual(e, jnp.array([2.5, 1.5])), [-1.5, -0.5], atol=1e-12)
    np.testing.assert_allclose(SizeFactor("l", prior).evaluate(Ellipsoid.from_axes(np.eye(3), np.zeros(3), prior)), 0.0, atol=1e-12)


def test_support_plane_touching_floor():
    floor = np.array([0.0, 0.0, 1.0, 0.0])
    rng = np.random.default_rng(3)
    R = random_rotation(rng)
    e = Ellipsoid.from_axes(R, [1.0, 2.0, 0.0], [0.5, 0.3, 0.2])
    h = np.sqrt(float(np.asarray(e.P)[2, 2]))  # support function along +z
    touching = Ellipsoid(e.P, jnp.array([1.0, 2.0, h]))
    assert abs(float(support_plane_residual(touching, floor)[0])) < 1e-12
    floating = Ellipsoid(e.P, jnp.array([1.0, 2.0, h + 0.3]))
    assert float(support_plane_residual(floating, floor)[0]) < -0.1
    f = SupportPlaneFactor("l", 2.0 * floor)  # any scale of the plane
    assert abs(float(f.evaluate(touching)[0])) < 1e-10
    for x in (touching.to_rts(), touching.to_full()):
        assert abs(float(support_plane_residual(x, floor)[0])) < 1e-10


def test_edge_planes_are_tangent_for_all_params():
    rng = np.random.default_rng(4)
    e = Ellipsoid.from_axes(random_rotation(rng), [0.2, -0.1, 0.3], [0.7, 0.4, 0.3])
    T = jaxlie.SE3.from_matrix(look_at(np.array([3.0, -3.0, 1.5]), e.center))
    planes = box_planes(project_box(e, T, CAM), T, CAM)
    for p in ("spd", "rts", "full"):
        Q = as_param(e, p).dual_quadric()
        np.testing.assert_allclose(jnp.einsum("ki,ij,kj->k", planes, Q, planes), 0.0, atol=1e-10)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: InverseBoxFactor("x", "l", [10, 10, 5, 20], CAM), "box"),
        (lambda: InverseBoxFactor("x", "l", [10, 10, np.nan, 20], CAM), "box"),
        (lambda: SemiInverseBoxFactor("x", "l", [1, 2, 3], CAM), "box"),
        (lambda: InverseBoxFactor("x", "l", [1, 2, 3, 4], (500, 500, 320, 240)), "Camera"),
        (lambda: OrientationFactor("l", [0, 0, 0]), "direction"),
        (lambda: ClassicOrientationFactor("l", [0, 0, 1], axis=3), "axis"),
        (lambda: ShapeFactor("l", [1, 0, 2]), "radii"),
        (lambda: SizeFactor("l", [1, 2]), "radii"),
        (lambda: SupportPlaneFactor("l", [0, 0, 0, 1]), "plane"),
        (lambda: sqrt_information(2, sigma=[1.0, -1.0]), "sigma"),
        (lambda: sqrt_information(2, information=[[1.0, 2.0], [2.0, 1.0]]), "positive definite"),
        (lambda: sqrt_information(2, sigma=1.0, information=np.eye(2)), "at most one"),
        (lambda: Camera(0, 500, 320, 240, 640, 480), "positive"),
    ],
)
def test_bad_input_gives_clear_errors(make, message):
    with pytest.raises((ValueError, TypeError), match=message):
        make()


def test_noise_models_whiten():
    rng = np.random.default_rng(5)
    A = rng.normal(size=(3, 3))
    cov = A @ A.T + np.eye(3)
    W = sqrt_information(3, covariance=cov)
    np.testing.assert_allclose(W.T @ W, np.linalg.inv(cov), atol=1e-12)
    np.testing.assert_allclose(sqrt_information(3, information=np.linalg.inv(cov)), W, atol=1e-10)
    np.testing.assert_allclose(sqrt_information(2, sigma=[2.0, 4.0]), np.diag([0.5, 0.25]))


@pytest.mark.parametrize("kernel", [Huber(1.5), Cauchy(1.5)])
def test_robust_kernels(kernel):
    s = jnp.linspace(0.0, 25.0, 501)
    rho, w = kernel.rho(s), kernel.weight(s)
    assert np.all(np.isfinite(rho)) and np.all(np.isfinite(w))
    np.testing.assert_allclose(rho[:3], s[:3], rtol=0.03, atol=1e-12)  # ρ(s) ≈ s near zero
    assert np.all(np.diff(rho) >= 0) and np.all(np.diff(w) <= 1e-15)  # grows, downweights
    assert float(w[-1]) < 0.5
    # weight is dρ/ds
    ds = 1e-6
    np.testing.assert_allclose((kernel.rho(s[1:] + ds) - kernel.rho(s[1:] - ds)) / (2 * ds), w[1:], rtol=1e-5)


def test_factor_error_uses_whitening_and_kernel():
    e = Ellipsoid.from_axes(np.eye(3), np.zeros(3), [0.5, 0.5, 0.5])
    floor = [0.0, 0.0, 1.0, 1.0]  # 0.5 m below the bottom of the ball
    r = float(support_plane_residual(e, jnp.array(floor))[0])
    f = SupportPlaneFactor("l", floor, sigma=0.1)
    assert f.error(e) == pytest.approx(0.5 * (r / 0.1) ** 2)
    fr = SupportPlaneFactor("l", floor, sigma=0.1, robust=Huber(1.0))
    assert fr.error(e) == pytest.approx(0.5 * (2 * abs(r) / 0.1 - 1.0))
    assert isinstance(e.to_full(), EllipsoidFull)


def test_tum_round_trip():
    from spdslam import se3

    rng = np.random.default_rng(9)
    for _ in range(10):
        T = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_matrix(random_rotation(rng)), rng.normal(size=3))
        v = se3.to_tum(T)
        assert v[6] >= 0
        np.testing.assert_allclose(se3.from_tum(v).as_matrix(), T.as_matrix(), atol=1e-12)
    # TUM order is qx qy qz qw: a 90° yaw
    T = se3.from_tum([1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    np.testing.assert_allclose(T.rotation().as_matrix() @ np.array([1.0, 0, 0]), [0, 1, 0], atol=1e-12)


def test_box_factor_jacobians_finite_for_degenerate_geometry():
    """Objects straddling the principal plane, behind the camera or around it: the
    residuals and Jacobians stay finite (the factor reports itself invalid instead)."""
    from spdslam.factors import tangent_jacobians

    e = Ellipsoid.from_axes(np.eye(3), np.zeros(3), [0.8, 0.5, 0.3])
    box = jnp.array([100.0, 100.0, 300.0, 250.0])
    poses = [
        look_at(np.array([0.0, -0.3, 0.1]), np.array([0.0, 5.0, 0.1])),  # straddling
        look_at(np.array([0.0, -3.0, 0.0]), np.array([0.0, -8.0, 0.0])),  # behind
        look_at(np.array([0.1, 0.0, 0.05]), np.array([0.1, 5.0, 0.05])),  # inside
        look_at(np.array([0.0, -0.85, 0.0]), np.array([0.0, 5.0, 0.0])),  # touching
    ]
    for T in poses:
        T = jaxlie.SE3.from_matrix(T)
        for res in (inverse_box_residual, semi_inverse_box_residual):
            for x in (e, e.to_rts(), e.to_full()):
                r, J = tangent_jacobians(res, (T, x), (box, CAM))
                assert np.all(np.isfinite(r)) and all(np.all(np.isfinite(j)) for j in J), (res, type(x))


@pytest.mark.parametrize("margin", [None, 5.0])
@pytest.mark.parametrize("cls", [InverseBoxFactor, SemiInverseBoxFactor, InverseCuboidBoxFactor,
                                 SemiInverseCuboidBoxFactor])
def test_box_factors_built_as_arrays_are_the_factors_built_one_by_one(cls, margin):
    import jax

    cam = Camera(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
    rng = np.random.default_rng(0)
    corner = rng.uniform(0, 300, (40, 2))
    boxes = np.c_[corner, corner + rng.uniform(1, 300, (40, 2))]
    sigma = rng.uniform(1, 3, (40, 4))
    many = cls.many([X(i) for i in range(40)], L(3), boxes, cam, sigma=sigma, robust=Huber(1.0),
                    truncation_margin=margin)
    assert len(many) == 40
    for i, a in enumerate(many):
        b = cls(X(i), L(3), boxes[i], cam, sigma=sigma[i], robust=Huber(1.0), truncation_margin=margin)
        assert type(a) is cls and a.keys == b.keys and a.robust == b.robust
        np.testing.assert_array_equal(a.sqrt_info, b.sqrt_info)
        (la, ta, sa), (lb, tb, sb) = a.flat_args(), b.flat_args()
        assert ta == tb and sa == sb
        for x, y in zip(la + jax.tree.leaves(a.args), lb + jax.tree.leaves(b.args)):
            np.testing.assert_array_equal(x, y)
    default = cls.many([X(0)], [L(1)], boxes[:1], cam)[0]  # the type's default σ
    np.testing.assert_array_equal(default.sqrt_info, cls(X(0), L(1), boxes[0], cam).sqrt_info)
    with pytest.raises(ValueError, match=r"box must be finite \[u_min, v_min, u_max, v_max\], got \[5.0, 0\.0"):
        cls.many([X(0), X(1)], L(1), [boxes[0], [5.0, 0.0, 1.0, 1.0]], cam)
    with pytest.raises(ValueError, match="sigma must be finite and positive"):
        cls.many([X(0)], L(1), boxes[:1], cam, sigma=-1.0)
    with pytest.raises(ValueError, match="2 boxes, 1 pose keys"):
        cls.many([X(0)], L(1), boxes[:2], cam)
