"""Manifold axioms for every optimisation variable type, through the registry.

Parametrised over jaxlie.SE3, jaxlie.SO3, Sim3, Ellipsoid (SPD × R³, including exact spheres and
spheroids), EllipsoidRTS, EllipsoidFull, and raw SPD matrices via spd.retract_vec/local_vec.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
import scipy.linalg as sla
from hypothesis import given, settings
from hypothesis import strategies as st

from spdslam import Ellipsoid, EllipsoidFull, EllipsoidRTS, manifold, spd
from spdslam.geometry import Sim3


def _hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _small_rotation(gen, angle):
    return sla.expm(_hat(gen.tangent_vec(angle, 3)))


@dataclass
class Case:
    """How to draw, compare and perturb one variable type."""

    name: str
    dim: int
    make: Callable[[Any], Any]  # gen -> x
    arrays: Callable[[Any], list]  # x -> list of arrays that determine x
    nearby: Callable[[Any, Any], Any]  # (gen, x) -> y near x, built independently of retract
    retract: Callable = manifold.retract
    local: Callable = manifold.local


def _se3_nearby(gen, T):
    twist = np.zeros((4, 4))
    twist[:3, :3] = _hat(gen.tangent_vec(0.2, 3))
    twist[:3, 3] = gen.tangent_vec(0.3, 3)
    return jaxlie.SE3.from_matrix(np.asarray(T.as_matrix()) @ sla.expm(twist))


def _spd_nearby(gen, P):
    # a multiplicative perturbation, so that it stays SPD: (I + E) P (I + E)ᵀ
    E = gen.rng.normal(size=(3, 3)) * 0.05
    Q = (np.eye(3) + E) @ np.asarray(P) @ (np.eye(3) + E).T
    return 0.5 * (Q + Q.T)


def _ellipsoid_case(kind):
    return Case(
        name=f"Ellipsoid-{kind}",
        dim=9,
        make=lambda gen: gen.ellipsoid(kind),
        arrays=lambda e: [e.P, e.center],
        nearby=lambda gen, e: Ellipsoid(_spd_nearby(gen, e.P), np.asarray(e.center) + gen.rng.normal(size=3) * 0.1),
    )


def _rts_make(gen):
    R, t, s = gen.ellipsoid_params()
    return EllipsoidRTS.from_axes(R, t, s)


CASES = [
    Case(
        name="SE3",
        dim=6,
        make=lambda gen: gen.pose_random(),
        arrays=lambda T: [T.as_matrix()],
        nearby=_se3_nearby,
    ),
    Case(
        name="SO3",
        dim=3,
        make=lambda gen: jaxlie.SO3.from_matrix(gen.rotation()),
        arrays=lambda R: [R.as_matrix()],
        nearby=lambda gen, R: jaxlie.SO3.from_matrix(np.asarray(R.as_matrix()) @ _small_rotation(gen, 0.3)),
    ),
    Case(
        name="Sim3",
        dim=7,
        make=lambda gen: Sim3(jaxlie.SO3.from_matrix(gen.rotation()), gen.rng.normal(size=3),
                              np.float64(gen.rng.uniform(-1.0, 1.0))),
        arrays=lambda S: [S.rotation.as_matrix(), S.translation, S.log_scale],
        nearby=lambda gen, S: Sim3(jaxlie.SO3.from_matrix(np.asarray(S.rotation.as_matrix()) @ _small_rotation(gen, 0.3)),
                                   np.asarray(S.translation) + gen.rng.normal(size=3) * 0.1,
                                   np.float64(S.log_scale) + gen.rng.uniform(-0.2, 0.2)),
    ),
    _ellipsoid_case("general"),
    _ellipsoid_case("sphere"),
    _ellipsoid_case("spheroid_oblate"),
    _ellipsoid_case("spheroid_prolate"),
    Case(
        name="EllipsoidRTS",
        dim=9,
        make=_rts_make,
        arrays=lambda e: [e.orientation.as_matrix(), e.center, e.scale],
        nearby=lambda gen, e: EllipsoidRTS.from_axes(
            np.asarray(e.orientation.as_matrix()) @ _small_rotation(gen, 0.3),
            np.asarray(e.center) + gen.rng.normal(size=3) * 0.1,
            np.asarray(e.scale) + gen.rng.uniform(-0.1, 0.1, size=3),
        ),
    ),
    Case(
        name="EllipsoidFull",
        dim=10,
        make=lambda gen: EllipsoidFull.from_ellipsoid(gen.ellipsoid()),
        arrays=lambda e: [e.q],
        nearby=lambda gen, e: EllipsoidFull(np.asarray(e.q) + gen.rng.normal(size=10) * 0.05),
    ),
    Case(
        name="SPD-raw",
        dim=6,
        make=lambda gen: gen.spd("general"),
        arrays=lambda P: [P],
        nearby=_spd_nearby,
        retract=spd.retract_vec,
        local=spd.local_vec,
    ),
    Case(
        name="SPD-raw-sphere",
        dim=6,
        make=lambda gen: gen.spd("sphere"),
        arrays=lambda P: [P],
        nearby=_spd_nearby,
        retract=spd.retract_vec,
        local=spd.local_vec,
    ),
]
IDS = [c.name for c in CASES]


def assert_same(case, x, y, atol=1e-10):
    for a, b in zip(case.arrays(x), case.arrays(y)):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=atol * max(1.0, np.abs(b).max()))


# --- axioms ---------------------------------------------------------------------------


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_retract_zero_is_identity(gen, case):
    for _ in range(3):
        x = case.make(gen)
        assert_same(case, case.retract(x, np.zeros(case.dim)), x, atol=1e-13)
        np.testing.assert_allclose(np.asarray(case.local(x, x)), np.zeros(case.dim), atol=1e-12)


@pytest.mark.parametrize("case", CASES, ids=IDS)
@pytest.mark.parametrize("norm", [1e-6, 1e-2, 0.3])
def test_local_inverts_retract(gen, case, norm):
    for _ in range(3):
        x = case.make(gen)
        v = gen.tangent_vec(norm, case.dim)
        y = case.retract(x, v)
        got = np.asarray(case.local(x, y))
        assert got.shape == (case.dim,)
        np.testing.assert_allclose(got, v, rtol=1e-7, atol=1e-10)


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_retract_inverts_local(gen, case):
    for _ in range(3):
        x = case.make(gen)
        y = case.nearby(gen, x)
        d = case.local(x, y)
        assert np.all(np.isfinite(np.asarray(d)))
        assert_same(case, case.retract(x, d), y)


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_tangent_dim_and_input_types(gen, case):
    x = case.make(gen)
    if not case.name.startswith("SPD"):
        assert manifold.tangent_dim(x) == case.dim == manifold.tangent_dim(type(x))
    v = gen.tangent_vec(0.1, case.dim)
    want = case.retract(x, jnp.asarray(v))
    assert_same(case, case.retract(x, v), want, atol=1e-14)
    assert_same(case, case.retract(x, list(v)), want, atol=1e-14)


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_jacobian_of_local_retract_is_identity(gen, case):
    """d/dv local(x, retract(x, v)) at v = 0 is the identity, finite at spheres too."""
    x = case.make(gen)
    J = np.asarray(_jac_local_retract(case.retract, case.local)(x, jnp.zeros(case.dim)))
    np.testing.assert_allclose(J, np.eye(case.dim), atol=1e-9)


_JAC_CACHE: dict = {}


def _jac_local_retract(retract, local):
    """jit(v ↦ ∂/∂v local(x, retract(x, v))), one compiled function per pair of maps."""
    key = (retract, local)
    if key not in _JAC_CACHE:
        _JAC_CACHE[key] = jax.jit(lambda x, v: jax.jacfwd(lambda w: local(x, retract(x, w)))(v))
    return _JAC_CACHE[key]


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_vmap_and_jit(gen, case):
    n = 4
    xs = [case.make(gen) for _ in range(n)]
    vs = np.stack([gen.tangent_vec(0.2, case.dim) for _ in range(n)])
    xb = jax.tree_util.tree_map(lambda *a: jnp.stack([jnp.asarray(b) for b in a]), *xs)
    yb = jax.jit(jax.vmap(case.retract))(xb, vs)
    db = jax.jit(jax.vmap(case.local))(xb, yb)
    for i in range(n):
        yi = jax.tree_util.tree_map(lambda a: a[i], yb)
        assert_same(case, yi, case.retract(xs[i], vs[i]))
    np.testing.assert_allclose(np.asarray(db), vs, rtol=1e-7, atol=1e-10)


# --- retraction conventions (checked against independent formulas) -------------------


def test_se3_so3_right_perturbation(gen):
    """T ⊞ δ = T · exp(δ), δ = (v, ω) translation first (jaxlie order)."""
    T = gen.pose_random()
    d = gen.rng.normal(size=6) * 0.5
    twist = np.zeros((4, 4))
    twist[:3, :3] = _hat(d[3:])
    twist[:3, 3] = d[:3]
    np.testing.assert_allclose(
        np.asarray(manifold.retract(T, d).as_matrix()), np.asarray(T.as_matrix()) @ sla.expm(twist), atol=1e-12
    )
    R = jaxlie.SO3.from_matrix(gen.rotation())
    w = gen.rng.normal(size=3)
    np.testing.assert_allclose(
        np.asarray(manifold.retract(R, w).as_matrix()), np.asarray(R.as_matrix()) @ sla.expm(_hat(w)), atol=1e-12
    )


def test_ellipsoid_retractions_follow_their_definitions(gen):
    e = gen.ellipsoid()
    d = gen.rng.normal(size=9)
    P = np.asarray(e.P)
    Ph = np.real(sla.sqrtm(P))
    want_P = Ph @ sla.expm(np.asarray(spd.vec_to_sym(d[:6]))) @ Ph
    y = manifold.retract(e, d)
    np.testing.assert_allclose(np.asarray(y.P), want_P, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(y.center), np.asarray(e.center) + d[6:], atol=1e-14)

    r = e.to_rts()
    y = manifold.retract(r, d)
    np.testing.assert_allclose(
        np.asarray(y.orientation.as_matrix()), np.asarray(r.orientation.as_matrix()) @ sla.expm(_hat(d[:3])), atol=1e-12
    )
    np.testing.assert_allclose(np.asarray(y.center), np.asarray(r.center) + d[3:6], atol=1e-14)
    np.testing.assert_allclose(np.asarray(y.scale), np.asarray(r.scale) + d[6:], atol=1e-14)

    f = e.to_full()
    d10 = gen.rng.normal(size=10)
    np.testing.assert_allclose(np.asarray(manifold.retract(f, d10).q), np.asarray(f.q) + d10, atol=1e-14)


# --- SPD stays SPD for large steps ----------------------------------------------------


@pytest.mark.parametrize("kind", ["general", "sphere", "spheroid_oblate", "identity"])
def test_spd_large_steps_stay_positive_definite(gen, kind):
    for _ in range(25):
        P = gen.spd(kind)
        c = gen.tangent_vec(gen.rng.uniform(1.0, 20.0), 6)
        for X in (
            np.asarray(spd.retract_vec(P, c)),
            np.asarray(manifold.retract(Ellipsoid(P, np.zeros(3)), np.concatenate([c, np.zeros(3)])).P),
        ):
            assert np.all(np.isfinite(X))
            np.testing.assert_array_equal(X, X.T)
            assert np.linalg.eigvalsh(X)[0] > 0
            np.linalg.cholesky(X)  # raises if not positive definite
            assert bool(spd.is_spd(X))


def test_spd_worst_case_large_step(gen):
    """Steps of norm 20 along the most stretching direction (a, 0, −a) (eigenvalue ratio
    e^(20√2) ≈ 2·10¹²), from P with condition number 100: the result has condition number
    up to ~2·10¹⁴, still resolvable in float64, and must come out SPD."""
    for _ in range(20):
        R = gen.rotation()
        P = gen.spd_from(R, np.array([9.0, 1.0, 0.09]))
        a = 20 / np.sqrt(2)
        U = gen.rotation() if gen.rng.random() < 0.5 else R
        c = np.asarray(spd.sym_to_vec(gen.spd_from(U, np.array([a, 0.0, -a]))))
        np.testing.assert_allclose(np.linalg.norm(c), 20.0)
        X = np.asarray(spd.retract_vec(P, c))
        np.testing.assert_array_equal(X, X.T)
        assert np.linalg.eigvalsh(X)[0] > 0


@pytest.mark.parametrize("norm", [2.0, 5.0])
def test_spd_round_trip_moderately_large_steps(gen, norm):
    P = gen.spd("general", lo=0.5, hi=2.0)
    c = gen.tangent_vec(norm, 6)
    np.testing.assert_allclose(np.asarray(spd.local_vec(P, spd.retract_vec(P, c))), c, atol=1e-9)


# --- EllipsoidFull regularisation -----------------------------------------------------


def _check_is_ellipsoid(f: EllipsoidFull):
    Q = np.asarray(f.matrix())
    assert np.all(np.isfinite(Q))
    np.testing.assert_allclose(Q[3, 3], -1.0, rtol=1e-14)
    e = f.to_ellipsoid()
    P = np.asarray(e.P)
    np.testing.assert_allclose(P, P.T, atol=1e-14 * np.abs(P).max())
    assert np.linalg.eigvalsh(P)[0] > 0
    # P, t recovered from Q* agree with Q* = [[P − ttᵀ, −t], [−tᵀ, −1]]
    t = -Q[:3, 3]
    np.testing.assert_allclose(P, Q[:3, :3] + np.outer(t, t), atol=1e-12 * max(1, np.abs(P).max()))


def _random_symmetric4(gen, how):
    A = gen.rng.normal(size=(4, 4)) * gen.rng.uniform(0.1, 10.0)
    A = 0.5 * (A + A.T)
    if how == "q33_positive":
        A[3, 3] = abs(A[3, 3]) + 0.1
    elif how == "q33_negative":
        A[3, 3] = -abs(A[3, 3]) - 0.1
    elif how == "q33_zero":
        A[3, 3] = 0.0
    elif how == "negative_definite_block":
        A[:3, :3] = -np.asarray(gen.spd("general")) * 5
    return A


@pytest.mark.parametrize("how", ["plain", "q33_positive", "q33_negative", "q33_zero", "negative_definite_block"])
def test_regularized_random_symmetric_is_ellipsoid_and_idempotent(gen, how):
    for _ in range(10):
        A = _random_symmetric4(gen, how)
        f = EllipsoidFull.from_dual_quadric(A)
        np.testing.assert_allclose(np.asarray(f.matrix()), A, atol=1e-15)
        g = f.regularized()
        _check_is_ellipsoid(g)
        h = g.regularized()
        np.testing.assert_allclose(np.asarray(h.q), np.asarray(g.q), rtol=1e-10, atol=1e-12 * np.abs(g.q).max())
        r = manifold.regularize(f)
        np.testing.assert_allclose(np.asarray(r.q), np.asarray(g.q), atol=0)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.floats(-1e3, 1e3, allow_nan=False, allow_subnormal=False), min_size=10, max_size=10),
    st.sampled_from([1e-8, 1.0, 1e6]),
)
def test_regularized_property(entries, scale):
    """Any 10 entries (zeros, ties, Q*₃₃ = 0, tiny/huge scales): an idempotent projection."""
    f = EllipsoidFull(jnp.asarray(entries) * scale)
    g = _REGULARIZED(f)
    _check_is_ellipsoid(g)
    h = _REGULARIZED(g)
    # compared as ellipsoids: Q*[:3, :3] = P − ttᵀ can cancel badly, so q itself is only
    # reproducible to rounding relative to |P| and |t|², not relative to |q|
    eg, eh = g.to_ellipsoid(), h.to_ellipsoid()
    scale = np.abs(np.asarray(eg.P)).max()
    np.testing.assert_allclose(np.asarray(eh.P), np.asarray(eg.P), atol=1e-9 * scale)
    np.testing.assert_allclose(np.asarray(eh.center), np.asarray(eg.center), atol=1e-9 * np.sqrt(scale))


_REGULARIZED = jax.jit(lambda f: f.regularized())


@pytest.mark.parametrize("kind", ["general", "sphere", "spheroid_prolate"])
def test_regularized_leaves_valid_ellipsoid_unchanged(gen, kind):
    for _ in range(5):
        e = gen.ellipsoid(kind)
        f = EllipsoidFull.from_ellipsoid(e)
        g = f.regularized()
        np.testing.assert_allclose(np.asarray(g.q), np.asarray(f.q), rtol=1e-10, atol=1e-12 * np.abs(f.q).max())
        # a scalar multiple of the same quadric (any sign) regularises to the normalised one
        # (tiny and huge scales included: the test for a vanishing Q*₃₃ must be relative)
        for c in (3.7, -0.2, -25.0, 1e-13, -1e-9, 1e12):
            gs = EllipsoidFull.from_dual_quadric(c * np.asarray(e.dual_quadric())).regularized()
            np.testing.assert_allclose(np.asarray(gs.q), np.asarray(f.q), rtol=1e-10, atol=1e-12 * np.abs(f.q).max())


def test_regularize_is_identity_for_true_manifolds(gen):
    T = gen.pose_random()
    assert manifold.regularize(T) is T
    e = gen.ellipsoid()
    assert manifold.regularize(e) is e
    r = e.to_rts()
    assert manifold.regularize(r) is r


def test_regularized_under_vmap_and_jit(gen):
    As = np.stack([_random_symmetric4(gen, "plain") for _ in range(6)])
    qs = jnp.stack([EllipsoidFull.from_dual_quadric(A).q for A in As])
    out = jax.jit(jax.vmap(lambda q: EllipsoidFull(q).regularized().q))(qs)
    for A, q in zip(As, np.asarray(out)):
        np.testing.assert_allclose(q, np.asarray(EllipsoidFull.from_dual_quadric(A).regularized().q), rtol=1e-10, atol=1e-12)


# --- registry -------------------------------------------------------------------------


def test_registry():
    assert manifold.tangent_dim(jaxlie.SE3) == 6
    assert manifold.tangent_dim(jaxlie.SO3) == 3
    assert manifold.tangent_dim(Ellipsoid) == 9
    assert manifold.tangent_dim(EllipsoidRTS) == 9
    assert manifold.tangent_dim(EllipsoidFull) == 10
    for cls in (jaxlie.SE3, jaxlie.SO3, Ellipsoid, EllipsoidRTS, EllipsoidFull):
        assert manifold.is_registered(cls)
    assert not manifold.is_registered(np.ndarray)
    with pytest.raises(TypeError, match="not an optimisation variable type"):
        manifold.ops(np.eye(3))
    with pytest.raises(TypeError, match="Ellipsoid"):
        manifold.retract(np.eye(3), np.zeros(6))


def test_every_manifold_declares_blocks_that_tile_its_tangent_space():
    from spdslam.geometry import manifold

    for cls, op in manifold._REGISTRY.items():
        assert sum(op.blocks) == op.tangent_dim and min(op.blocks) >= 1, cls
    with pytest.raises(ValueError, match="sum to tangent_dim"):
        manifold.register(type("Bad", (), {}), tangent_dim=3, retract=None, local=None,
                          blocks=(2, 2))


def test_from_tum_slices_on_the_host_and_rounds_as_xla():
    """``from_tum`` of host rows: the same bits as the eager JAX operations it replaced (XLA's
    norm and division, the slicing and concatenation exact), in any shape; a traced call agrees
    to round-off."""
    from spdslam.geometry.se3 import from_tum

    def eager(values):
        v = jnp.asarray(values, dtype=float)
        q = v[..., 3:7] / jnp.linalg.norm(v[..., 3:7], axis=-1, keepdims=True)
        return jaxlie.SE3.from_rotation_and_translation(
            jaxlie.SO3(jnp.concatenate([q[..., 3:4], q[..., :3]], axis=-1)), v[..., :3])

    rng = np.random.default_rng(5)
    for shape in [(7,), (1, 7), (3, 7), (8, 7), (400, 7), (2893, 7), (2, 5, 7)]:
        v = rng.normal(size=shape) * rng.uniform(0.01, 100.0)
        got = from_tum(v)
        assert isinstance(got.wxyz_xyz, jax.Array)
        np.testing.assert_array_equal(np.asarray(got.wxyz_xyz), np.asarray(eager(v).wxyz_xyz))
        np.testing.assert_allclose(np.asarray(jax.jit(from_tum)(v).wxyz_xyz), np.asarray(got.wxyz_xyz),
                                   rtol=1e-15, atol=1e-15)
