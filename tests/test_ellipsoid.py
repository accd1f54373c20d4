"""Ellipsoid parameterisations, their conversions, dual quadric and circumscribed cuboid.

Geometry is checked against definitions, not against formulas copied from the code: the
surface is sampled as t + R diag(s) u with u on the unit sphere, tangency is πᵀQ*π = 0, and
the support function of the ellipsoid in direction n is max n·(x − t) over the surface.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from spdslam import Ellipsoid, EllipsoidFull, EllipsoidRTS, as_ellipsoid
from spdslam.geometry import dual_quadric

KINDS = ("general", "sphere", "spheroid_oblate", "spheroid_prolate")
SIGNS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))


def _unit(gen, n):
    v = gen.rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _quadric_definition(P, t):
    """Q* = T diag(P, −1) Tᵀ with T = [[I, t], [0, 1]]: the dual of the ellipsoid
    {x : (x−t)ᵀP⁻¹(x−t) ≤ 1}, which is the unit sphere's dual diag(I, −1) moved by x ↦ L x + t
    (L Lᵀ = P)."""
    T = np.eye(4)
    T[:3, 3] = t
    D = np.zeros((4, 4))
    D[:3, :3] = P
    D[3, 3] = -1.0
    return T @ D @ T.T


def _assert_same_ellipsoid(a, b, tol=1e-10):
    a, b = as_ellipsoid(a), as_ellipsoid(b)
    scale = max(1.0, np.abs(np.asarray(b.P)).max())
    np.testing.assert_allclose(np.asarray(a.P), np.asarray(b.P), atol=tol * scale)
    np.testing.assert_allclose(np.asarray(a.center), np.asarray(b.center), atol=tol * scale)


# --- axes -----------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_from_axes_axes_round_trip(gen, kind):
    for _ in range(10):
        R, t, s = gen.ellipsoid_params(kind)
        e = Ellipsoid.from_axes(R, t, s)
        np.testing.assert_allclose(np.asarray(e.P), (R * s**2) @ R.T, rtol=1e-12, atol=1e-14)
        R2, s2 = (np.asarray(x) for x in e.axes())
        # radii: the same multiset, sorted descending
        np.testing.assert_allclose(s2, np.sort(s)[::-1], rtol=1e-10)
        assert np.all(np.diff(s2) <= 0)
        # rotation: orthonormal and right-handed
        np.testing.assert_allclose(R2.T @ R2, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(R2), 1.0, atol=1e-12)
        # and it describes the same ellipsoid
        _assert_same_ellipsoid(Ellipsoid.from_axes(R2, t, s2), e)
        np.testing.assert_allclose(np.asarray(e.radii), s2)
        np.testing.assert_allclose(np.asarray(e.rotation), R2)
        if kind == "general":
            # each axis is ± the input column of the same radius
            order = np.argsort(s)[::-1]
            for k in range(3):
                np.testing.assert_allclose(abs(R2[:, k] @ R[:, order[k]]), 1.0, atol=1e-9)


def test_axes_right_handed_whatever_eigh_returns(gen):
    """eigh returns det ±1 eigenvector bases; axes() must always return det +1."""
    dets, raw = [], []
    for _ in range(40):
        e = gen.ellipsoid("general")
        R, _ = e.axes()
        dets.append(float(np.linalg.det(np.asarray(R))))
        raw.append(np.linalg.det(np.linalg.eigh(np.asarray(e.P))[1][:, ::-1]))
    np.testing.assert_allclose(dets, 1.0, atol=1e-12)
    # premise: raw eigenvectors in descending order are left-handed a good part of the time
    assert 0 < np.sum(np.array(raw) < 0) < 40


def test_from_axes_accepts_so3_lists_and_unsorted_radii(gen):
    R, t, s = gen.ellipsoid_params()
    e = Ellipsoid.from_axes(R, t, s)
    _assert_same_ellipsoid(Ellipsoid.from_axes(jaxlie.SO3.from_matrix(R), t, s), e)
    _assert_same_ellipsoid(Ellipsoid.from_axes(R.tolist(), t.tolist(), s.tolist()), e)
    _assert_same_ellipsoid(Ellipsoid.from_axes(jnp.asarray(R), jnp.asarray(t), jnp.asarray(s)), e)
    perm = [2, 0, 1]
    _assert_same_ellipsoid(Ellipsoid.from_axes(R[:, perm], t, s[perm]), e)
    # a semi-axis sign flip is the same ellipsoid
    _assert_same_ellipsoid(Ellipsoid.from_axes(R * np.array([1, -1, -1]), t, s), e)


def test_volume_and_contains(gen):
    for kind in KINDS:
        R, t, s = gen.ellipsoid_params(kind)
        e = Ellipsoid.from_axes(R, t, s)
        np.testing.assert_allclose(float(e.volume()), 4 / 3 * np.pi * np.prod(s), rtol=1e-12)
        assert bool(e.contains(t))
        for k in range(3):
            for sg in (-1, 1):
                assert bool(e.contains(t + sg * 0.99 * s[k] * R[:, k]))
                assert not bool(e.contains(t + sg * 1.01 * s[k] * R[:, k]))
        X = gen.surface_points(R, t, s, 1000)
        inner = t + 0.999 * (X - t)
        outer = t + 1.001 * (X - t)
        assert np.all(np.asarray(e.contains(inner)))
        assert not np.any(np.asarray(e.contains(outer)))


# --- conversions ----------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_conversions_are_lossless(gen, kind):
    for _ in range(5):
        R, t, s = gen.ellipsoid_params(kind)
        e = Ellipsoid.from_axes(R, t, s)
        Q = np.asarray(e.dual_quadric())
        r = e.to_rts()
        f = e.to_full()
        assert isinstance(r, EllipsoidRTS) and isinstance(f, EllipsoidFull)
        assert e.to_ellipsoid() is e
        # SPD -> RTS -> SPD, SPD -> Full -> SPD, through the dual quadric, and mixed chains
        for x in (
            r,
            f,
            r.to_ellipsoid(),
            f.to_ellipsoid(),
            Ellipsoid.from_dual_quadric(Q),
            EllipsoidRTS.from_ellipsoid(f.to_ellipsoid()),
            EllipsoidFull.from_ellipsoid(r.to_ellipsoid()),
            EllipsoidFull.from_dual_quadric(np.asarray(r.dual_quadric())),
            EllipsoidRTS.from_axes(R, t, s),
            EllipsoidRTS.from_axes(jaxlie.SO3.from_matrix(R), t, s),
        ):
            _assert_same_ellipsoid(x, e)
            np.testing.assert_allclose(np.asarray(dual_quadric(x)), Q, atol=1e-10 * np.abs(Q).max())
        # RTS stores sorted radii and a proper rotation, and its views are those of every
        # parameterisation: sorted radii, the axes as a rotation matrix
        np.testing.assert_allclose(np.asarray(r.scale), np.sort(s)[::-1], rtol=1e-10)
        np.testing.assert_allclose(np.linalg.det(np.asarray(r.orientation.as_matrix())), 1.0, atol=1e-12)
        for x in (r, f, e):
            np.testing.assert_allclose(np.asarray(x.radii), np.sort(s)[::-1], rtol=1e-9)
            if kind == "general":  # the axes are unique up to sign
                np.testing.assert_allclose(np.abs(np.asarray(x.rotation).T @ np.asarray(e.rotation)),
                                           np.eye(3), atol=1e-6)
            np.testing.assert_allclose(np.asarray(x.P), np.asarray(e.P), atol=1e-9 * np.abs(e.P).max())
            np.testing.assert_allclose(np.asarray(x.center), np.asarray(e.center), atol=1e-9)
        # Full stores the 10 entries of Q* and gives it back
        np.testing.assert_allclose(np.asarray(f.matrix()), Q, atol=1e-15 * np.abs(Q).max())
        np.testing.assert_allclose(np.asarray(f.q), Q[np.triu_indices(4)], atol=0)


def test_from_dual_quadric_any_scale(gen):
    for _ in range(5):
        e = gen.ellipsoid()
        Q = np.asarray(e.dual_quadric())
        for c in (1e-3, 2.5, -1.0, -7.3, 1e4):
            _assert_same_ellipsoid(Ellipsoid.from_dual_quadric(c * Q), e)
            f = EllipsoidFull.from_dual_quadric(c * Q)
            _assert_same_ellipsoid(f.to_ellipsoid(), e)
            np.testing.assert_allclose(np.asarray(f.dual_quadric()), Q, atol=1e-10 * np.abs(Q).max())
            np.testing.assert_allclose(np.asarray(f.matrix()), c * Q, atol=1e-12 * np.abs(c * Q).max())


def test_as_ellipsoid_and_dual_quadric_dispatch(gen):
    e = gen.ellipsoid()
    assert as_ellipsoid(e) is e
    with pytest.raises(TypeError, match="not an ellipsoid"):
        as_ellipsoid(np.eye(4))
    Q = np.asarray(e.dual_quadric())
    np.testing.assert_allclose(np.asarray(dual_quadric(Q)), Q)
    np.testing.assert_allclose(np.asarray(dual_quadric(Q.tolist())), Q)


# --- dual quadric ---------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_dual_quadric_definition(gen, kind):
    R, t, s = gen.ellipsoid_params(kind)
    e = Ellipsoid.from_axes(R, t, s)
    Q = np.asarray(e.dual_quadric())
    np.testing.assert_allclose(Q, _quadric_definition((R * s**2) @ R.T, t), atol=1e-12 * np.abs(Q).max())
    np.testing.assert_allclose(Q, Q.T, atol=0)
    assert Q[3, 3] == -1.0
    # the primal quadric (Q*)⁻¹ vanishes on the surface and is negative inside
    Qp = np.linalg.inv(Q)
    X = np.c_[gen.surface_points(R, t, s, 500), np.ones(500)]
    vals = np.einsum("ni,ij,nj->n", X, Qp, X)
    # scale: the value at the centre
    c = np.r_[t, 1.0]
    inside = c @ Qp @ c
    np.testing.assert_allclose(vals / abs(inside), 0.0, atol=1e-9)
    # the primal quadric changes sign across the surface
    Xo = np.c_[t + 1.1 * (X[:, :3] - t), np.ones(500)]
    outside = np.einsum("ni,ij,nj->n", Xo, Qp, Xo)
    assert np.all(np.sign(outside) == -np.sign(inside))


def _tangent_planes(P, t, n):
    """The two planes n·x + d = 0 tangent to the ellipsoid, normals n (m×3): d = −(n·t ± σ)."""
    sigma = np.sqrt(np.einsum("ni,ij,nj->n", n, P, n))
    nt = n @ t
    return np.c_[n, -(nt + sigma)], np.c_[n, -(nt - sigma)], sigma


def test_sign_slip_paper_dual_quadric(gen):
    """Our Q* has −t off the diagonal; the paper prints +t. Planes tangent by construction
    satisfy πᵀQ*π = 0 for ours, but not for the paper's version, unless t = 0."""
    for _ in range(5):
        R, t, s = gen.ellipsoid_params()
        t = t + np.sign(t) * 0.5  # well away from 0
        e = Ellipsoid.from_axes(R, t, s)
        Q = np.asarray(e.dual_quadric())
        Q_paper = Q.copy()
        Q_paper[:3, 3] = t
        Q_paper[3, :3] = t
        planes_a, planes_b, sigma = _tangent_planes(np.asarray(e.P), t, _unit(gen, 200))
        for pi in (planes_a, planes_b):
            scale = sigma**2 + (pi[:, :3] @ t) ** 2 + pi[:, 3] ** 2
            ours = np.einsum("ni,ij,nj->n", pi, Q, pi) / scale
            paper = np.einsum("ni,ij,nj->n", pi, Q_paper, pi) / scale
            np.testing.assert_allclose(ours, 0.0, atol=1e-12)
            # πᵀQ*π for the paper's version is σ² − (d − n·t)² = −4 (n·t)(n·t ± σ): O(1)
            assert np.median(np.abs(paper)) > 1e-2
    # at t = 0 the two agree, and both are right
    R, _, s = gen.ellipsoid_params()
    e0 = Ellipsoid.from_axes(R, np.zeros(3), s)
    Q0 = np.asarray(e0.dual_quadric())
    Q0_paper = Q0.copy()
    Q0_paper[:3, 3] = Q0_paper[3, :3] = np.zeros(3)
    np.testing.assert_array_equal(Q0, Q0_paper)
    pa, _, _ = _tangent_planes(np.asarray(e0.P), np.zeros(3), _unit(gen, 50))
    np.testing.assert_allclose(np.einsum("ni,ij,nj->n", pa, Q0, pa), 0.0, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
def test_tangent_planes_and_support_function(gen, kind):
    R, t, s = gen.ellipsoid_params(kind)
    e = Ellipsoid.from_axes(R, t, s)
    P, Q = np.asarray(e.P), np.asarray(e.dual_quadric())
    n = _unit(gen, 64)
    pa, pb, sigma = _tangent_planes(P, t, n)
    for pi in (pa, pb):
        scale = sigma**2 + (n @ t) ** 2 + pi[:, 3] ** 2
        np.testing.assert_allclose(np.einsum("ni,ij,nj->n", pi, Q, pi) / scale, 0.0, atol=1e-12)
        # a plane moved off the ellipsoid by 0.1 % of σ is not tangent
        off = pi.copy()
        off[:, 3] += 1e-3 * sigma
        assert np.all(np.abs(np.einsum("ni,ij,nj->n", off, Q, off)) / scale > 1e-4 * sigma**2 / scale)
    # support function = max over a dense surface sampling
    X = gen.surface_points(R, t, s, 200_000)
    proj = (X - t) @ n.T  # (N, m)
    hi, lo = proj.max(axis=0), proj.min(axis=0)
    assert np.all(hi <= sigma * (1 + 1e-12))
    assert np.all(lo >= -sigma * (1 + 1e-12))
    np.testing.assert_allclose(hi, sigma, rtol=1e-4)
    np.testing.assert_allclose(lo, -sigma, rtol=1e-4)


# --- cuboid ---------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_cuboid_corners(gen, kind):
    R, t, s = gen.ellipsoid_params(kind)
    e = Ellipsoid.from_axes(R, t, s)
    C = np.asarray(e.cuboid_corners())
    assert C.shape == (8, 3)
    # The 8 points t + R diag(s) σ (as a set; order and axis labels are the code's choice).
    # With a repeated radius the axes, hence the cuboid, are not unique: then the cuboid is
    # built on the axes e.axes() reports, which must be principal axes of P.
    Rc, sc = (np.asarray(x) for x in e.axes())
    np.testing.assert_allclose(np.asarray(e.P) @ Rc, Rc * sc**2, atol=1e-10 * s.max() ** 2)
    for Rw, sw in ((Rc, sc),) if kind != "general" else ((Rc, sc), (R, s)):
        want = t + (SIGNS * sw) @ Rw.T
        D = np.linalg.norm(C[:, None, :] - want[None, :, :], axis=-1)
        assert sorted(np.argmin(D, axis=1)) == list(range(8))
        np.testing.assert_allclose(D.min(axis=1), 0.0, atol=1e-9 * max(1, np.abs(t).max()))
    np.testing.assert_allclose(C.mean(axis=0), t, atol=1e-12 * max(1, np.abs(t).max()))
    # every face touches the ellipsoid
    Q = np.asarray(e.dual_quadric())
    Pinv = np.linalg.inv(np.asarray(e.P))
    for k in range(3):
        for sg in (-1.0, 1.0):
            n = sg * Rc[:, k]
            on_face = np.abs(C @ n - (n @ t + sc[k])) < 1e-9 * max(1, np.abs(C).max())
            assert on_face.sum() == 4, "4 corners on each face"
            assert np.all(C[~on_face] @ n < n @ t + sc[k]), "others behind it"
            pi = np.r_[n, -(n @ t + sc[k])]
            assert abs(pi @ Q @ pi) < 1e-10 * (sc[k] ** 2 + (n @ t) ** 2)
            # it touches at the face centre, a point of the surface
            centre = C[on_face].mean(axis=0)
            np.testing.assert_allclose((centre - t) @ Pinv @ (centre - t), 1.0, rtol=1e-10)
    # and the ellipsoid lies inside the cuboid
    X = gen.surface_points(R, t, s, 2000)
    assert np.all(np.abs((X - t) @ Rc) <= sc * (1 + 1e-10))


# --- JAX: pytrees, vmap, jit, derivatives ---------------------------------------------


def _stack(items):
    return jax.tree_util.tree_map(lambda *a: jnp.stack([jnp.asarray(b) for b in a]), *items)


def test_vmap_jit_over_ellipsoids(gen):
    es = [gen.ellipsoid(k) for k in KINDS]
    eb = _stack(es)
    Qb = jax.jit(jax.vmap(lambda e: e.dual_quadric()))(eb)
    Cb = jax.vmap(lambda e: e.cuboid_corners())(eb)
    Rb, sb = jax.jit(jax.vmap(lambda e: e.axes()))(eb)
    for i, e in enumerate(es):
        np.testing.assert_allclose(np.asarray(Qb[i]), np.asarray(e.dual_quadric()), atol=1e-14)
        np.testing.assert_allclose(np.asarray(Cb[i]), np.asarray(e.cuboid_corners()), atol=1e-12)
        np.testing.assert_allclose(np.asarray(sb[i]), np.asarray(e.radii), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(np.asarray(Rb[i])), 1.0, atol=1e-12)
    # RTS and Full batches convert to the same quadrics
    rb = _stack([e.to_rts() for e in es])
    fb = _stack([e.to_full() for e in es])
    np.testing.assert_allclose(np.asarray(jax.vmap(lambda r: r.dual_quadric())(rb)), np.asarray(Qb), atol=1e-10)
    np.testing.assert_allclose(np.asarray(jax.jit(jax.vmap(lambda f: f.dual_quadric()))(fb)), np.asarray(Qb), atol=1e-12)
    # construction under jit and vmap, from numpy arrays
    R, t, s = gen.ellipsoid_params()
    ej = jax.jit(Ellipsoid.from_axes)(R, t, s)
    _assert_same_ellipsoid(ej, Ellipsoid.from_axes(R, t, s))
    Rs = np.stack([gen.rotation() for _ in range(3)])
    ts, ss = gen.rng.normal(size=(3, 3)), gen.rng.uniform(0.2, 3, size=(3, 3))
    ev = jax.vmap(Ellipsoid.from_axes)(Rs, ts, ss)
    for i in range(3):
        _assert_same_ellipsoid(jax.tree_util.tree_map(lambda a: a[i], ev), Ellipsoid.from_axes(Rs[i], ts[i], ss[i]))


@jax.jit
def _ELLIPSOID_JACOBIANS(e):
    return [
        jax.jacfwd(fn)(e)
        for fn in (
            lambda e: e.dual_quadric(),
            lambda e: e.cuboid_corners(),
            lambda e: e.to_rts().dual_quadric(),
            lambda e: e.volume(),
        )
    ]


_QUADRIC_JAC_T = jax.jit(lambda P, c: jax.jacfwd(lambda c: Ellipsoid(P, c).dual_quadric())(c))


@pytest.mark.parametrize("kind", KINDS)
def test_derivatives_finite_at_spheres(gen, kind):
    """Derivatives of quadric, corners and conversions exist (no NaN) also at exact ties."""
    R, t, s = gen.ellipsoid_params(kind)
    e = Ellipsoid.from_axes(R, t, s)
    for leaf in jax.tree_util.tree_leaves(_ELLIPSOID_JACOBIANS(e)):
        assert np.all(np.isfinite(np.asarray(leaf)))
    # the dual quadric is linear in P and quadratic in t: check against central differences
    JP = np.asarray(_QUADRIC_JAC_T(e.P, e.center))
    h = 1e-6
    fd = np.stack(
        [(_quadric_definition(np.asarray(e.P), t + h * u) - _quadric_definition(np.asarray(e.P), t - h * u)) / (2 * h) for u in np.eye(3)],
        axis=-1,
    )
    np.testing.assert_allclose(JP, fd, atol=1e-8)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
def test_sorted_axes_of_a_batch(n):
    """sorted_axes on (n, 3, 3) gives each matrix's own axes (radii descending, det +1),
    for every batch size (the sign fix once broadcast (n, 1) against (n,))."""
    from scipy.spatial.transform import Rotation

    from spdslam.geometry import sorted_axes

    R = Rotation.random(n, random_state=n).as_matrix()
    s = np.sort(np.random.default_rng(n).uniform(0.2, 2.0, (n, 3)), axis=1)[:, ::-1]
    P = R @ (s[:, :, None] ** 2 * np.eye(3)) @ np.swapaxes(R, 1, 2)
    Rb, sb = (np.asarray(a) for a in sorted_axes(P))
    assert Rb.shape == (n, 3, 3) and sb.shape == (n, 3)
    np.testing.assert_allclose(sb, s, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.det(Rb), 1.0, atol=1e-12)
    np.testing.assert_allclose(Rb @ (sb[:, :, None] ** 2 * np.eye(3)) @ np.swapaxes(Rb, 1, 2), P,
                               atol=1e-12)
    for k in range(n):  # the same as one matrix at a time
        Rk, sk = (np.asarray(a) for a in sorted_axes(P[k]))
        np.testing.assert_allclose(Rb[k], Rk, atol=1e-12)
        np.testing.assert_allclose(sb[k], sk, atol=1e-12)


def test_sorted_axes_in_numpy_equal_jax_to_the_bit():
    """A NumPy P takes NumPy's path (what map.json's writer uses: nothing to compile); it is
    the same LAPACK decomposition as JAX's, so the axes are the same to the bit, ties too."""
    import jax.numpy as jnp

    from spdslam.geometry import sorted_axes

    rng = np.random.default_rng(5)
    A = rng.normal(size=(200, 3, 3))
    P = np.concatenate([A @ np.swapaxes(A, 1, 2) + 0.01 * np.eye(3),
                        np.stack([np.diag([1.0, 1.0, 2.0]), np.eye(3), np.diag([3.0, 2.0, 2.0])])])
    R, s = sorted_axes(P)
    assert isinstance(R, np.ndarray) and isinstance(s, np.ndarray)
    Rj, sj = sorted_axes(jnp.asarray(P))
    np.testing.assert_array_equal(R, np.asarray(Rj))
    np.testing.assert_array_equal(s, np.asarray(sj))
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
