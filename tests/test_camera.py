"""Camera, projection of ellipsoids to boxes, back-projected planes, visibility predicates.

The reference for every box is a dense sampling of the ellipsoid surface projected with an
independent pinhole model (x_c = R_wcᵀ (x − c), u = fx x/z + cx, v = fy y/z + cy).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from spdslam import (
    Camera,
    Ellipsoid,
    EllipsoidFull,
    EllipsoidRTS,
    box_planes,
    camera_inside,
    in_front,
    project_box,
    project_dual_quadric,
)
from spdslam.geometry import conic_box, depth_range, projection_matrix

KINDS = ("general", "sphere", "spheroid_oblate", "spheroid_prolate")
N_SURFACE = 200_000
BOX_TOL = 1e-2  # pixels (the refined sampling is good to ~1e-5 px)
CAM = Camera(520.0, 510.0, 320.0, 240.0, 640.0, 480.0)


def _sampled_box(gen, R, t, s, R_wc, c, cam, n=N_SURFACE, refine=True):
    """[u_min, v_min, u_max, v_max] of the projected surface samples, and their depths.

    The surface is x = t + R diag(s) u for n nearly uniform unit vectors u. With ``refine``,
    each of the four extremes is then re-sampled on a fine 101×101 grid of directions in a
    small cap around the best sample (a denser sampling where it matters), which takes the
    sampling error from ~1e-2 px to ~1e-5 px.
    """
    U = gen.fibonacci_sphere(n)

    def project(U):
        X = t[None, :] + (U * s[None, :]) @ R.T
        Xc = gen.world_to_camera(X, R_wc, c)
        return gen.pinhole(Xc, cam.fx, cam.fy, cam.cx, cam.cy), Xc[:, 2]

    uv, z = project(U)
    box = np.r_[uv.min(axis=0), uv.max(axis=0)]
    if refine:
        cap = 4.0 * np.sqrt(4 * np.pi / n)
        g = np.linspace(-cap, cap, 101)
        a, b = (x.ravel() for x in np.meshgrid(g, g))
        for k, (col, sign) in enumerate(((0, -1), (1, -1), (0, 1), (1, 1))):
            u0 = U[np.argmax(sign * uv[:, col])]
            e1, e2 = np.linalg.svd(u0[None, :])[2][1:]
            V = u0[None, :] + a[:, None] * e1 + b[:, None] * e2
            V /= np.linalg.norm(V, axis=1, keepdims=True)
            uv_k, _ = project(V)
            box[k] = sign * max(sign * box[k], np.max(sign * uv_k[:, col]))
    return box, z


def _check_box(box, sampled, tol=BOX_TOL):
    """The true box contains every sample, and is within tol of the sampled extremes."""
    box = np.asarray(box)
    lo_ok = box[:2] <= sampled[:2] + 1e-9
    hi_ok = box[2:] >= sampled[2:] - 1e-9
    assert np.all(lo_ok) and np.all(hi_ok), (box, sampled)
    np.testing.assert_allclose(box, sampled, atol=tol)


def _paper_conic_box(C):
    """The paper's printed formula, without the division by C*₃₃."""
    C = np.asarray(C)
    du = np.sqrt(max(C[0, 2] ** 2 - C[0, 0] * C[2, 2], 0.0))
    dv = np.sqrt(max(C[1, 2] ** 2 - C[1, 1] * C[2, 2], 0.0))
    u = sorted([C[0, 2] - du, C[0, 2] + du])
    v = sorted([C[1, 2] - dv, C[1, 2] + dv])
    return np.array([u[0], v[0], u[1], v[1]])


def _configs(gen, n):
    for i in range(n):
        kind = KINDS[i % len(KINDS)]
        R, t, s = gen.ellipsoid_params(kind)
        cam = gen.camera()
        T, R_wc, c = gen.pose_looking_at(R, t, s, dist=(1.5, 8.0), jitter=0.1)
        yield kind, R, t, s, cam, T, R_wc, c


# --- Camera ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad",
    [
        dict(fx=0.0),
        dict(fx=-500.0),
        dict(fy=0.0),
        dict(fy=-1.0),
        dict(width=0.0),
        dict(height=-480.0),
        dict(width=0),
        dict(fx=float("nan")),
        dict(fy=float("inf")),
        dict(cx=float("nan")),
    ],
)
def test_camera_rejects_invalid_intrinsics(bad):
    kw = dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640.0, height=480.0)
    kw.update(bad)
    with pytest.raises(ValueError, match="positive"):
        Camera(**kw)


def test_camera_accepts_valid_intrinsics():
    for kw in (
        dict(fx=500, fy=400, cx=320, cy=240, width=640, height=480),
        dict(fx=np.float32(500), fy=np.float64(400), cx=-3.0, cy=1e4, width=1.0, height=1.0),
    ):
        cam = Camera(**kw)
        K = np.asarray(cam.K)
        np.testing.assert_allclose(K, [[kw["fx"], 0, kw["cx"]], [0, kw["fy"], kw["cy"]], [0, 0, 1]])
        back = Camera.from_array(np.asarray(cam.as_array()))
        np.testing.assert_allclose(np.asarray(back.as_array()), np.asarray(cam.as_array()))


def test_projection_matrix_is_pinhole(gen):
    cam = gen.camera()
    R_wc, c = gen.rotation(), gen.rng.normal(size=3)
    T = gen.pose(R_wc, c)
    X = c + R_wc @ np.array([0.3, -0.2, 4.0]) + gen.rng.normal(size=(20, 3)) * 0.5
    want = gen.pinhole(gen.world_to_camera(X, R_wc, c), cam.fx, cam.fy, cam.cx, cam.cy)
    for pose in (T, np.asarray(T.as_matrix()), jnp.asarray(T.as_matrix())):
        M = np.asarray(projection_matrix(pose, cam))
        x = np.c_[X, np.ones(len(X))] @ M.T
        np.testing.assert_allclose(x[:, :2] / x[:, 2:], want, rtol=1e-10)


# --- project_box ----------------------------------------------------------------------


def test_project_box_matches_dense_sampling(gen):
    for kind, R, t, s, cam, T, R_wc, c in _configs(gen, 12):
        e = Ellipsoid.from_axes(R, t, s)
        sampled, z = _sampled_box(gen, R, t, s, R_wc, c, cam)
        assert z.min() > 0, "premise: the object is in front of the camera"
        _check_box(project_box(e, T, cam), sampled)


def test_project_box_every_parameterisation_and_input_type(gen):
    for kind, R, t, s, cam, T, R_wc, c in _configs(gen, 4):
        e = Ellipsoid.from_axes(R, t, s)
        sampled, _ = _sampled_box(gen, R, t, s, R_wc, c, cam, n=50_000)
        Q = np.asarray(e.dual_quadric())
        want = np.asarray(project_box(e, T, cam))
        _check_box(want, sampled)
        for x in (
            EllipsoidRTS.from_axes(R, t, s),
            EllipsoidFull.from_ellipsoid(e),
            Q,
            jnp.asarray(Q),
            Ellipsoid(jnp.asarray(e.P), jnp.asarray(e.center)),
        ):
            for pose in (T, np.asarray(T.as_matrix())):
                np.testing.assert_allclose(np.asarray(project_box(x, pose, cam)), want, rtol=1e-9, atol=1e-8)


def test_box_of_any_scalar_multiple_of_the_quadric(gen):
    """conic_box divides by C*₃₃, so any multiple of Q* gives the same box; the paper's
    formula without that division is right only when C*₃₃ = 1, and fails for a scaled Q*."""
    for kind, R, t, s, cam, T, R_wc, c in _configs(gen, 6):
        e = Ellipsoid.from_axes(R, t, s)
        sampled, _ = _sampled_box(gen, R, t, s, R_wc, c, cam)
        Q = np.asarray(e.dual_quadric())
        for k in (3.7, 0.01, -1.0, -250.0):
            _check_box(project_box(k * Q, T, cam), sampled)
            _check_box(project_box(EllipsoidFull.from_dual_quadric(k * Q), T, cam), sampled)
            C = np.asarray(project_dual_quadric(k * Q, T, cam))
            _check_box(conic_box(C), sampled)
            # the version without division: right for C/C₃₃ (sanity of the reference) ...
            _check_box(_paper_conic_box(C / C[2, 2]), sampled)
            # ... wrong for the scaled quadric
            err = np.abs(_paper_conic_box(C) - sampled).max()
            assert err > 1.0, err


def test_sphere_on_the_optical_axis_closed_form(gen):
    """A sphere of radius r at depth Z on the axis: half-width f·r/√(Z² − r²)."""
    cam = gen.camera()
    for _ in range(5):
        r, Z = gen.rng.uniform(0.2, 2.0), gen.rng.uniform(3.0, 10.0)
        R_wc, c = gen.rotation(), gen.rng.normal(size=3)
        t = c + Z * R_wc[:, 2]
        e = Ellipsoid.from_axes(np.eye(3), t, np.full(3, r))
        hw = r / np.sqrt(Z**2 - r**2)
        want = [cam.cx - cam.fx * hw, cam.cy - cam.fy * hw, cam.cx + cam.fx * hw, cam.cy + cam.fy * hw]
        np.testing.assert_allclose(np.asarray(project_box(e, gen.pose(R_wc, c), cam)), want, rtol=1e-10)


# --- box planes -----------------------------------------------------------------------


def test_box_planes_through_centre_tangent_and_projecting_to_box_lines(gen):
    for kind, R, t, s, cam, T, R_wc, c in _configs(gen, 8):
        e = Ellipsoid.from_axes(R, t, s)
        Q = np.asarray(e.dual_quadric())
        P = np.asarray(e.P)
        box = np.asarray(project_box(e, T, cam))
        planes = np.asarray(box_planes(box, T, cam))
        assert planes.shape == (4, 4)
        X = gen.surface_points(R, t, s, 5000)
        for k, pi in enumerate(planes):
            n, d = pi[:3], pi[3]
            np.testing.assert_allclose(np.linalg.norm(n), 1.0, rtol=1e-12)
            # through the camera centre
            assert abs(n @ c + d) < 1e-9 * max(1.0, np.abs(c).max())
            # tangent: πᵀQ*π = nᵀPn − (n·t + d)² = 0 relative to its terms
            scale = n @ P @ n + (n @ t + d) ** 2
            assert abs(pi @ Q @ pi) < 1e-9 * scale
            # the whole ellipsoid is on one side
            side = X @ n + d
            assert np.all(side >= -1e-9 * scale) or np.all(side <= 1e-9 * scale)
            # points of the plane in front of the camera project onto the box line
            basis = np.linalg.svd(n[None, :])[2][1:]  # two unit vectors ⟂ n
            dirs = gen.rng.normal(size=(50, 2)) @ basis
            dirs = dirs * np.sign(dirs @ R_wc[:, 2])[:, None]  # towards the front
            Y = c + dirs * gen.rng.uniform(0.5, 10.0, size=(50, 1))
            Yc = gen.world_to_camera(Y, R_wc, c)
            keep = Yc[:, 2] > 1e-2 * np.linalg.norm(Yc, axis=1)
            uv = gen.pinhole(Yc[keep], cam.fx, cam.fy, cam.cx, cam.cy)
            coord = uv[:, k % 2]  # u for lines 0, 2 and v for lines 1, 3
            np.testing.assert_allclose(coord, box[k], atol=1e-6 * max(1.0, abs(box[k])))


def test_box_planes_of_arbitrary_box(gen):
    """Any box: the planes pass through the centre and project to the box lines."""
    cam = gen.camera()
    T = gen.pose_random()
    R_wc, c = np.asarray(T.rotation().as_matrix()), np.asarray(T.translation())
    box = np.array([100.0, 50.0, 400.0, 300.0]) + gen.rng.normal(size=4)
    planes = np.asarray(box_planes(box, T, cam))
    for k, pi in enumerate(planes):
        assert abs(pi[:3] @ c + pi[3]) < 1e-9
        # the ray through pixel (box[k] on its axis, anything on the other) lies in the plane
        for other in (0.0, 200.0, 480.0):
            u, v = (box[k], other) if k % 2 == 0 else (other, box[k])
            ray = R_wc @ np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0])
            assert abs(pi[:3] @ (c + 3.0 * ray) + pi[3]) < 1e-9 * max(1, np.abs(c).max())


# --- visibility -----------------------------------------------------------------------


def test_in_front_and_depth_range(gen):
    for kind, R, t, s, cam, T, R_wc, c in _configs(gen, 8):
        e = Ellipsoid.from_axes(R, t, s)
        _, z = _sampled_box(gen, R, t, s, R_wc, c, cam, n=50_000)
        zr = np.asarray(depth_range(e, T))
        np.testing.assert_allclose(zr, [z.min(), z.max()], rtol=1e-3)
        assert zr[0] <= z.min() + 1e-9 and zr[1] >= z.max() - 1e-9
        # in front
        assert bool(in_front(e, T))
        assert bool(in_front(e.to_rts(), np.asarray(T.as_matrix())))
        assert bool(in_front(e.to_full(), T))
        assert bool(in_front(e, T, min_depth=0.99 * zr[0]))
        assert not bool(in_front(e, T, min_depth=1.01 * zr[0]))
        assert not bool(camera_inside(e, T))
        # behind: the same camera turned around (rotated by π about its y axis)
        R_back = R_wc @ np.diag([-1.0, 1.0, -1.0])
        T_back = gen.pose(R_back, c)
        assert not bool(in_front(e, T_back))
        assert gen.world_to_camera(t[None], R_back, c)[0, 2] < 0
        # straddling: camera beside the object, looking along a direction ⟂ to (t − c), so
        # the principal plane z_c = 0 passes through the centre and cuts the ellipsoid
        side = gen.tangent_vec(1.0, 3)
        c_side = t + 2.0 * s.max() * side
        R_side = gen.look_at(c_side, c_side + np.cross(side, gen.tangent_vec(1.0, 3)))
        T_side = gen.pose(R_side, c_side)
        _, z_side = _sampled_box(gen, R, t, s, R_side, c_side, cam, n=20_000)
        assert z_side.min() < 0 < z_side.max()
        assert not bool(in_front(e, T_side))


def test_in_front_barely(gen):
    """Just in front of / just cutting the principal plane, decided by the support function."""
    for _ in range(5):
        R, t, s = gen.ellipsoid_params()
        R_wc = gen.rotation()
        z = R_wc[:, 2]
        h = np.sqrt(z @ ((R * s**2) @ R.T) @ z)  # half-extent along the optical axis
        e = Ellipsoid.from_axes(R, t, s)
        for depth, want in ((1.001 * h, True), (0.999 * h, False), (-2 * h, False)):
            c = t - depth * z + 0.3 * R_wc[:, 0]
            assert bool(in_front(e, gen.pose(R_wc, c))) is want


def test_camera_inside(gen):
    for kind in KINDS:
        R, t, s = gen.ellipsoid_params(kind)
        e = Ellipsoid.from_axes(R, t, s)
        R_wc = gen.rotation()
        assert bool(camera_inside(e, gen.pose(R_wc, t)))
        assert not bool(in_front(e, gen.pose(R_wc, t)))
        for k in range(3):
            for sg in (-1, 1):
                assert bool(camera_inside(e, gen.pose(R_wc, t + sg * 0.95 * s[k] * R[:, k])))
                assert not bool(camera_inside(e, gen.pose(R_wc, t + sg * 1.05 * s[k] * R[:, k])))
        assert not bool(camera_inside(e.to_rts(), np.asarray(gen.pose(R_wc, t + 10 * s.max()).as_matrix())))
        assert bool(camera_inside(e.to_full(), gen.pose(R_wc, t)))


# --- JAX: jit, vmap, derivatives ------------------------------------------------------


def test_jit_vmap_over_poses_and_cameras(gen):
    R, t, s = gen.ellipsoid_params()
    e = Ellipsoid.from_axes(R, t, s)
    cams, poses = [], []
    for _ in range(5):
        cams.append(gen.camera())
        poses.append(gen.pose_looking_at(R, t, s)[0])
    want = np.stack([np.asarray(project_box(e, T, cm)) for T, cm in zip(poses, cams)])
    Tb = jaxlie.SE3(jnp.stack([T.wxyz_xyz for T in poses]))
    Cb = Camera.from_array(jnp.stack([cm.as_array() for cm in cams]))
    got = jax.jit(jax.vmap(project_box, in_axes=(None, 0, 0)))(e, Tb, Cb)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-10)
    got = jax.vmap(project_box, in_axes=(None, 0, None))(e, Tb, cams[0])
    np.testing.assert_allclose(
        np.asarray(got[1]), np.asarray(project_box(e, poses[1], cams[0])), rtol=1e-10
    )
    # many ellipsoids, one camera
    es = [gen.ellipsoid() for _ in range(3)]
    eb = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *es)
    gb = jax.jit(jax.vmap(project_box, in_axes=(0, None, None)))(eb, poses[0], cams[0])
    for i, ei in enumerate(es):
        np.testing.assert_allclose(np.asarray(gb[i]), np.asarray(project_box(ei, poses[0], cams[0])), rtol=1e-10)
    # the predicates vectorise too
    inf = jax.jit(jax.vmap(in_front, in_axes=(None, 0)))(e, Tb)
    np.testing.assert_array_equal(np.asarray(inf), [bool(in_front(e, T)) for T in poses])
    pl = jax.jit(jax.vmap(box_planes, in_axes=(0, 0, 0)))(jnp.asarray(want), Tb, Cb)
    np.testing.assert_allclose(np.asarray(pl[2]), np.asarray(box_planes(want[2], poses[2], cams[2])), rtol=1e-10, atol=1e-12)


_BOX_FN = None


@pytest.mark.parametrize("kind", ["general", "sphere"])
def test_box_derivatives_finite_and_correct(gen, kind):
    """d box / d (ellipsoid tangent, pose tangent): finite at spheres, = central differences."""
    from spdslam import manifold

    R, t, s = gen.ellipsoid_params(kind)
    e = Ellipsoid.from_axes(R, t, s)
    cam = gen.camera()
    T = gen.pose_looking_at(R, t, s)[0]

    def f(d, e, T, cam):
        return project_box(manifold.retract(e, d[:9]), manifold.retract(T, d[9:]), cam)

    global _BOX_FN
    if _BOX_FN is None:
        _BOX_FN = jax.jit(f), jax.jit(jax.jacfwd(f))
    fj, jac = _BOX_FN
    J = np.asarray(jac(jnp.zeros(15), e, T, cam))
    assert np.all(np.isfinite(J))
    h = 1e-6
    fd = np.stack(
        [(np.asarray(fj(h * u, e, T, cam)) - np.asarray(fj(-h * u, e, T, cam))) / (2 * h) for u in np.eye(15)],
        axis=1,
    )
    np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-5 * np.abs(fd).max())


# --- look_at --------------------------------------------------------------------------


def test_look_at(gen):
    from spdslam.geometry import look_at

    cam = gen.camera()
    # a worked example: at the origin looking north (+y) with z up, east (+x) is to the right
    # of the image (u > cx) and up is upwards in the image (v < cy, image y points down)
    T = look_at([0.0, 0.0, 0.0], [0.0, 5.0, 0.0], up=(0.0, 0.0, 1.0))
    M = np.asarray(projection_matrix(T, cam))

    def uv(X):
        x = M @ np.r_[X, 1.0]
        return x[:2] / x[2], x[2]

    (u, v), z = uv(np.array([0.0, 5.0, 0.0]))
    np.testing.assert_allclose([u, v], [cam.cx, cam.cy], atol=1e-9)
    assert z > 0
    assert uv(np.array([1.0, 5.0, 0.0]))[0][0] > cam.cx
    assert uv(np.array([0.0, 5.0, 1.0]))[0][1] < cam.cy
    for _ in range(10):
        eye, target = gen.rng.normal(size=3) * 3, gen.rng.normal(size=3) * 3
        up = gen.tangent_vec(1.0, 3)
        T = look_at(eye, target, up=up)
        R = np.asarray(T.rotation().as_matrix())
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(T.translation()), eye, atol=1e-14)
        Xc = gen.world_to_camera(target[None], R, eye)[0]
        np.testing.assert_allclose(Xc[:2], 0.0, atol=1e-9 * np.linalg.norm(Xc))
        assert Xc[2] > 0
        # the part of `up` orthogonal to the view direction points to image −y
        f = (target - eye) / np.linalg.norm(target - eye)
        up_perp = up - (up @ f) * f
        assert gen.world_to_camera((target + 0.1 * up_perp)[None], R, eye)[0, 1] < 0
        assert abs(gen.world_to_camera((target + 0.1 * up_perp)[None], R, eye)[0, 0]) < 1e-9


# --- one implementation for NumPy and JAX ------------------------------------------------------


def test_numpy_batches_match_the_jax_results_one_at_a_time(gen):
    """Given NumPy arrays (poses as (R_wc, c), landmarks as Ellipsoids of arrays, cuboids as
    (H, t)), the geometry computes in NumPy, batched, and agrees with the JAX results for
    one jaxlie.SE3 and one landmark at a time; nothing comes back as a JAX array."""
    from spdslam.geometry import (
        Ellipsoid,
        box_planes,
        camera_inside,
        cuboid_half_axes,
        cuboid_in_front,
        depth_range,
        project_cuboid_box,
        project_points,
    )

    n = 12
    Rs, ts, ss, Ts, Rwc, cs = [], [], [], [], [], []
    for _ in range(n):
        R, t, s = gen.ellipsoid_params()
        T, R_wc, c = gen.pose_looking_at(R, t, s)
        Rs.append(R); ts.append(t); ss.append(s); Ts.append(T); Rwc.append(R_wc); cs.append(c)
    Rs, ts, ss, Rwc, cs = map(np.asarray, (Rs, ts, ss, Rwc, cs))
    P = np.einsum("nij,nj,nkj->nik", Rs, ss**2, Rs)
    batch, pose = Ellipsoid(P, ts), (Rwc, cs)
    cub = (Rs * ss[:, None, :], ts)
    boxes = gen.rng.uniform(50, 400, size=(n, 4))
    boxes[:, 2:] += boxes[:, :2]
    got = {
        "project_box": project_box(batch, pose, CAM),
        "in_front": in_front(batch, pose, 0.05),
        "depth_range": depth_range(batch, pose),
        "camera_inside": camera_inside(batch, pose),
        "project_cuboid_box": project_cuboid_box(cub, pose, CAM),
        "cuboid_in_front": cuboid_in_front(cub, pose, 0.05),
        "box_planes": box_planes(boxes, pose, CAM),
        "project_points": project_points(ts[:, None], pose, CAM)[:, 0],
        "projection_matrix": projection_matrix(pose, CAM),
    }
    for name, value in got.items():
        assert isinstance(value, np.ndarray), name
    for i in range(n):
        e = Ellipsoid(jnp.asarray(P[i]), jnp.asarray(ts[i]))
        rts = EllipsoidRTS.from_axes(Rs[i], ts[i], ss[i])
        want = {
            "project_box": project_box(e, Ts[i], CAM),
            "in_front": in_front(e, Ts[i], 0.05),
            "depth_range": depth_range(e, Ts[i]),
            "camera_inside": camera_inside(e, Ts[i]),
            "project_cuboid_box": project_cuboid_box(rts, Ts[i], CAM),
            "cuboid_in_front": cuboid_in_front(rts, Ts[i], 0.05),
            "box_planes": box_planes(boxes[i], Ts[i], CAM),
            "project_points": project_points(jnp.asarray(ts[i])[None], Ts[i], CAM)[0],
            "projection_matrix": projection_matrix(Ts[i], CAM),
        }
        for name, w in want.items():
            assert isinstance(w, jax.Array), name
            np.testing.assert_allclose(got[name][i], np.asarray(w), rtol=1e-9, atol=1e-9, err_msg=name)
        H, t = cuboid_half_axes(cub)
        assert H is cub[0] and t is cub[1]  # a pair (H, t) is a cuboid as it is


def test_conic_box_is_the_same_in_numpy_and_jax(gen):
    C = np.stack([gen.symmetric() for _ in range(50)])
    C[:, 2, 2] = -np.abs(C[:, 2, 2]) - 0.1
    a, b = conic_box(C), conic_box(jnp.asarray(C))
    assert isinstance(a, np.ndarray) and isinstance(b, jax.Array)
    np.testing.assert_array_equal(a, np.asarray(b))
