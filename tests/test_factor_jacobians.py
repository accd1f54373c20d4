"""Every landmark factor's tangent-space Jacobian against central differences.

≥ 200 random configurations per factor and parameterisation, a third of them exact spheres
and a third spheroids, plus the generic case. No NaN anywhere.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

import spdslam  # noqa: F401  (enables float64)
from spdslam import Camera, Ellipsoid, EllipsoidFull, EllipsoidRTS, manifold, project_box
from spdslam.factors._base import tangent_jacobians
from spdslam.factors import _landmark as lm

N = 210
H = 1e-6
CAM = Camera(520.0, 510.0, 320.0, 240.0, 640.0, 480.0)
UP = np.array([0.0, 0.0, 1.0])


def _rotation(rng):
    q = rng.normal(size=4)
    return np.asarray(jaxlie.SO3(jnp.asarray(q / np.linalg.norm(q))).as_matrix())


def _look_at(eye, target, rng):
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, rng.normal(size=3))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def configurations(seed: int, n: int = N):
    """Ellipsoids (rotation, centre, radii), kinds (0 generic, 1 spheroid, 2 sphere), poses."""
    rng = np.random.default_rng(seed)
    R, t, s, kind, T = [], [], [], [], []
    for i in range(n):
        k = i % 3
        r = rng.uniform(0.2, 1.0, size=3)
        if k == 1:
            j = rng.integers(3)
            r[(j + 1) % 3] = r[j]
        elif k == 2:
            r[:] = r[0]
        R.append(_rotation(rng))
        t.append(rng.uniform(-1, 1, size=3))
        s.append(r)
        kind.append(k)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        T.append(_look_at(t[-1] + rng.uniform(3.0, 8.0) * d, t[-1] + 0.2 * rng.normal(size=3), rng))
    return np.array(R), np.array(t), np.array(s), np.array(kind), np.array(T)


def landmarks(param: str, R, t, s):
    if param == "spd":
        P = np.einsum("nij,nj,nkj->nik", R, s**2, R)
        # exact spheres stay exact: s²I without rounding from R R^T
        sphere = np.all(s == s[:, :1], axis=1)
        P[sphere] = (s[sphere, 0] ** 2)[:, None, None] * np.eye(3)
        return Ellipsoid(jnp.asarray(P), jnp.asarray(t))
    if param == "rts":
        return EllipsoidRTS(jax.vmap(jaxlie.SO3.from_matrix)(jnp.asarray(R)), jnp.asarray(t), jnp.asarray(s))
    if param == "full":
        e = jax.vmap(Ellipsoid.from_axes)(jnp.asarray(R), jnp.asarray(t), jnp.asarray(s))
        return jax.vmap(EllipsoidFull.from_ellipsoid)(e)
    raise ValueError(param)


def fd_jacobian(residual, values, args, which, h=H):
    """Central differences along each tangent basis vector of variable ``which``."""
    dim = manifold.tangent_dim(values[which])

    def f(delta):
        vals = list(values)
        vals[which] = manifold.retract(vals[which], delta)
        return jnp.atleast_1d(residual(*vals, *args))

    cols = [(f(h * e) - f(-h * e)) / (2 * h) for e in jnp.eye(dim)]
    return jnp.stack(cols, axis=-1)


def check(residual, values, args, kind, symmetric_cols=None, h=H):
    """Batched analytic vs central-difference Jacobians; returns nothing, asserts."""

    def one(vals, a):
        r, J = tangent_jacobians(residual, vals, a)
        J_fd = [fd_jacobian(residual, vals, a, k, h) for k in range(len(vals))]
        return r, J, J_fd

    r, J, J_fd = jax.jit(jax.vmap(one))(values, args)
    assert np.all(np.isfinite(r)), "NaN/inf residual"
    for k, (Ja, Jn) in enumerate(zip(J, J_fd)):
        Ja, Jn = np.asarray(Ja), np.asarray(Jn)
        assert np.all(np.isfinite(Ja)), f"non-finite Jacobian for variable {k}"
        scale = 1.0 + np.max(np.abs(Jn), axis=(1, 2), keepdims=True)
        err = np.abs(Ja - Jn) / scale
        if symmetric_cols is not None and k == len(values) - 1:
            # Exact spheres: see test_shape docstring; compare tie-symmetric directions only.
            mask = np.ones_like(err, dtype=bool)
            sphere = kind == 2
            keep = np.zeros(err.shape[-1], dtype=bool)
            keep[list(symmetric_cols)] = True
            mask[sphere] = keep[None, :]
            err = np.where(mask, err, 0.0)
        worst = np.unravel_index(np.argmax(err), err.shape)
        assert err.max() < 2e-5, (
            f"variable {k}: max scaled error {err.max():.3g} at config {worst[0]} "
            f"(kind {kind[worst[0]]}), entry {worst[1:]}\nanalytic {Ja[worst[0]]}\nFD {Jn[worst[0]]}"
        )


PARAMS = ["spd", "rts", "full"]


def _boxes(lmk, T, seed):
    rng = np.random.default_rng(seed)
    boxes = jax.vmap(lambda x, TT: project_box(x, TT, CAM))(lmk, jnp.asarray(T))
    noise = rng.normal(scale=5.0, size=boxes.shape)
    b = np.asarray(boxes) + noise
    lo = np.minimum(b[:, :2], b[:, 2:])
    hi = np.maximum(b[:, :2], b[:, 2:])
    return np.concatenate([lo, hi], axis=1)


def _cams(n):
    return jax.tree_util.tree_map(lambda x: jnp.full((n,), x), CAM)


@pytest.mark.parametrize("param", PARAMS)
@pytest.mark.parametrize("model", ["inverse", "semi_inverse"])
def test_box_factor_jacobians(param, model):
    R, t, s, kind, T = configurations(1)
    lmk = landmarks(param, R, t, s)
    boxes = _boxes(lmk, T, 2)
    poses = jax.vmap(jaxlie.SE3.from_matrix)(jnp.asarray(T))
    res = lm.inverse_box_residual if model == "inverse" else lm.semi_inverse_box_residual
    assert np.all(jax.vmap(lambda TT, x: lm.box_visible(TT, x, None, CAM))(poses, lmk))
    check(res, (poses, lmk), (jnp.asarray(boxes), _cams(N)), kind)


@pytest.mark.parametrize("param", PARAMS)
def test_orientation_jacobians(param):
    R, t, s, kind, _ = configurations(3)
    lmk = landmarks(param, R, t, s)
    rng = np.random.default_rng(4)
    m = rng.normal(size=(N, 3))
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    check(lm.orientation_residual, (lmk,), (jnp.asarray(m),), kind)


def test_classic_orientation_jacobians():
    R, t, s, kind, _ = configurations(5)
    lmk = landmarks("rts", R, t, s)
    rng = np.random.default_rng(6)
    m = rng.normal(size=(N, 3))
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    axis = np.eye(3)[rng.integers(3, size=N)]
    check(lm.classic_orientation_residual, (lmk,), (jnp.asarray(m), jnp.asarray(axis)), kind)


# Tangent directions in which an exact sphere's triple tie splits symmetrically (eigenvalue
# changes μ with μ₂ = (μ₁+μ₃)/2): single off-diagonal entries of P, and rigid motions.
SYMMETRIC_AT_SPHERE = {"spd": [3, 4, 5, 6, 7, 8], "rts": [0, 1, 2, 3, 4, 5], "full": [1, 2, 5]}


@pytest.mark.parametrize("param", PARAMS)
def test_shape_jacobians(param):
    """Sorted ratios are not differentiable where radii coincide.

    At a double tie (spheroid) the central difference equals the mean derivative over the
    tie, which is what ``matfun.eigh`` returns, so every direction is checked (with a
    smaller step: at a kink the central difference is only first-order accurate). At a triple
    tie (sphere) the central difference of sorted eigenvalues is not linear in the
    direction, so no Jacobian can match it everywhere: there the check is restricted to
    directions that split the tie symmetrically, and the Jacobian must still be finite.
    """
    R, t, s, kind, _ = configurations(7)
    lmk = landmarks(param, R, t, s)
    rng = np.random.default_rng(8)
    prior = np.sort(rng.uniform(0.2, 1.0, size=(N, 3)), axis=1)[:, ::-1]
    ratios = prior[:, :2] / prior[:, 2:]
    check(lm.shape_residual, (lmk,), (jnp.asarray(ratios),), kind, SYMMETRIC_AT_SPHERE[param], h=1e-8)


def test_shape_rts_sphere_symmetric_radius_direction():
    """RTS sphere: the radius direction (+h, 0, −h) splits the tie symmetrically."""
    R, t, s, kind, _ = configurations(9, 30)
    sphere = kind == 2
    lmk = landmarks("rts", R[sphere], t[sphere], s[sphere])
    ratios = jnp.array([1.7, 1.2])
    v = jnp.array([0, 0, 0, 0, 0, 0, 1.0, 0, -1.0])

    def directional(x):
        _, (J,) = tangent_jacobians(lm.shape_residual, (x,), (ratios,))
        f = lambda h: lm.shape_residual(x.retract(h * v), ratios)  # noqa: E731
        return J @ v, (f(H) - f(-H)) / (2 * H)

    a, n = jax.vmap(directional)(lmk)
    np.testing.assert_allclose(a, n, atol=1e-6)


@pytest.mark.parametrize("param", PARAMS)
def test_size_jacobians(param):
    R, t, s, kind, _ = configurations(10)
    lmk = landmarks(param, R, t, s)
    logv = np.random.default_rng(11).normal(size=N)
    check(lm.size_residual, (lmk,), (jnp.asarray(logv),), kind)


@pytest.mark.parametrize("param", PARAMS)
def test_support_plane_jacobians(param):
    R, t, s, kind, _ = configurations(12)
    lmk = landmarks(param, R, t, s)
    rng = np.random.default_rng(13)
    n = rng.normal(size=(N, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    planes = np.concatenate([n, rng.uniform(-2, 2, size=(N, 1))], axis=1)
    check(lm.support_plane_residual, (lmk,), (jnp.asarray(planes),), kind)


# --- cuboid silhouette and truncated (masked) box residuals ------------------------------


def _cuboid_boxes(lmk, T, seed):
    from spdslam.camera import project_cuboid_box

    rng = np.random.default_rng(seed)
    b = np.asarray(jax.vmap(lambda x, TT: project_cuboid_box(x, TT, CAM))(lmk, jnp.asarray(T)))
    b = b + rng.normal(scale=5.0, size=b.shape)
    return np.concatenate([np.minimum(b[:, :2], b[:, 2:]), np.maximum(b[:, :2], b[:, 2:])], axis=1)


def _take(tree, idx):
    return jax.tree_util.tree_map(lambda a: a[idx], tree)


@pytest.mark.parametrize("param", PARAMS)
@pytest.mark.parametrize("model", ["inverse", "semi_inverse"])
def test_cuboid_box_factor_jacobians(param, model):
    """The cuboid of an SPD/Full landmark follows the eigenvectors of P, which are not
    determined at repeated radii: there the residual is not continuous and only its
    finiteness is checked (test_cuboid_model.py). RTS is smooth in its own parameters:
    every configuration is checked."""
    R, t, s, kind, T = configurations(14)
    use = np.ones(N, bool) if param == "rts" else kind == 0
    R, t, s, kind, T = R[use], t[use], s[use], kind[use], T[use]
    n = len(kind)
    lmk = landmarks(param, R, t, s)
    boxes = _cuboid_boxes(lmk, T, 15)
    poses = jax.vmap(jaxlie.SE3.from_matrix)(jnp.asarray(T))
    res = lm.inverse_cuboid_box_residual if model == "inverse" else lm.semi_inverse_cuboid_box_residual
    assert np.all(jax.vmap(lambda TT, x: lm.cuboid_box_visible(TT, x, None, CAM))(poses, lmk))
    check(res, (poses, lmk), (jnp.asarray(boxes), _cams(n)), kind)


@pytest.mark.parametrize("param", PARAMS)
@pytest.mark.parametrize(
    "name",
    ["inverse_box", "semi_inverse_box", "inverse_cuboid_box", "semi_inverse_cuboid_box"],
)
def test_masked_box_factor_jacobians(param, name):
    """Truncation masks (random 0/1 per edge): masked rows are exactly zero, the rest as
    without a mask, and the Jacobians match central differences."""
    R, t, s, kind, T = configurations(16, 60)
    if "cuboid" in name and param != "rts":
        use = kind == 0
        R, t, s, kind, T = R[use], t[use], s[use], kind[use], T[use]
    n = len(kind)
    lmk = landmarks(param, R, t, s)
    boxes = _cuboid_boxes(lmk, T, 17) if "cuboid" in name else _boxes(lmk, T, 17)
    keep = np.random.default_rng(18).integers(0, 2, size=(n, 4)).astype(float)
    poses = jax.vmap(jaxlie.SE3.from_matrix)(jnp.asarray(T))
    res = getattr(lm, name + "_residual")
    check(res, (poses, lmk), (jnp.asarray(boxes), _cams(n), jnp.asarray(keep)), kind)
    masked = jax.vmap(res)(poses, lmk, jnp.asarray(boxes), _cams(n), jnp.asarray(keep))
    full = jax.vmap(res)(poses, lmk, jnp.asarray(boxes), _cams(n))
    np.testing.assert_array_equal(np.asarray(masked)[keep == 0], 0.0)
    np.testing.assert_array_equal(np.asarray(masked)[keep == 1], np.asarray(full)[keep == 1])


@pytest.mark.parametrize("param", PARAMS)
def test_axis_orientation_jacobians(param):
    """Per-axis (cuboid) orientation: like the cuboid, defined by the axes, so SPD/Full are
    checked where the radii are distinct and RTS everywhere."""
    R, t, s, kind, _ = configurations(19)
    use = np.ones(N, bool) if param == "rts" else kind == 0
    R, t, s, kind = R[use], t[use], s[use], kind[use]
    lmk = landmarks(param, R, t, s)
    m = np.random.default_rng(20).normal(size=(len(kind), 3))
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    check(lm.axis_orientation_residual, (lmk,), (jnp.asarray(m),), kind)
