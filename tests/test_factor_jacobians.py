"""The Jacobian of every registered factor type against central differences: one table.

Each factor type of ``spdslam.factors`` (``factor_types()``) has an entry in ``CASES``: the
random configurations its Jacobian is checked on, for each landmark parameterisation it
takes. The test is parametrised over the table, and a factor type without an entry fails
``test_every_factor_type_has_a_jacobian_case``: a new factor type comes with its entry.

Landmark factors: ≥ 200 random configurations per factor and parameterisation, a third of
them exact spheres and a third spheroids, plus the generic case; pose factors: poses near
and far from their measurement. No NaN anywhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from conftest import batched_landmarks, check_jacobians, random_rotation
from scipy.spatial.transform import Rotation

import spdslam  # noqa: F401  (enables float64)
from spdslam import Camera, project_box
from spdslam.factors import factor_types, robust_groups
from spdslam.geometry import interpolated_frame, project_cuboid_box

N = 210
H = 1e-6
CAM = Camera(520.0, 510.0, 320.0, 240.0, 640.0, 480.0)
PARAMS = ("spd", "rts", "full")


@dataclass
class Case:
    """Batched variables and data of one check, the kind of each configuration (0 generic,
    1 spheroid, 2 sphere), and the tie handling (see the shape case)."""

    values: tuple
    args: tuple
    kind: np.ndarray
    symmetric_cols: list | None = None
    h: float = H


#: kind → (case builder (param → Case), the parameterisations it applies to)
CASES: dict[str, tuple[Callable[[str], Case], tuple[str, ...]]] = {}


def case(kind: str, params=PARAMS):
    def register(build):
        CASES[kind] = (build, tuple(params))
        return build

    return register


# --- configurations ---------------------------------------------------------------------------


def _look_at(eye, target, rng):
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, rng.normal(size=3))
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def configurations(seed: int, n: int = N):
    """Ellipsoids (rotation, centre, radii), kinds (0 generic, 1 spheroid, 2 sphere), and a
    camera pose (4×4) looking at each from 3-8 m."""
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
        R.append(random_rotation(rng))
        t.append(rng.uniform(-1, 1, size=3))
        s.append(r)
        kind.append(k)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        T.append(_look_at(t[-1] + rng.uniform(3.0, 8.0) * d, t[-1] + 0.2 * rng.normal(size=3), rng))
    return np.array(R), np.array(t), np.array(s), np.array(kind), np.array(T)


def _noisy_boxes(box_of, lmk, T, seed):
    rng = np.random.default_rng(seed)
    b = np.asarray(jax.vmap(lambda x, TT: box_of(x, TT, CAM))(lmk, jnp.asarray(T)))
    b = b + rng.normal(scale=5.0, size=b.shape)
    return np.concatenate([np.minimum(b[:, :2], b[:, 2:]), np.maximum(b[:, :2], b[:, 2:])], axis=1)


def _cams(n):
    return jax.tree_util.tree_map(lambda x: jnp.full((n,), x), CAM)


def _unit(rng, n):
    m = rng.normal(size=(n, 3))
    return m / np.linalg.norm(m, axis=1, keepdims=True)


def _poses(T):
    return jax.vmap(jaxlie.SE3.from_matrix)(jnp.asarray(T))


# --- the table --------------------------------------------------------------------------------


def _box_case(seed, cuboid, param):
    """Box factors on noisy boxes of views that see the whole object. The cuboid of an
    SPD/Full landmark follows the eigenvectors of P, which are not determined at repeated
    radii: there the residual is not continuous and only its finiteness is checked
    (test_cuboid_model.py). RTS is smooth in its own parameters: every configuration."""
    R, t, s, kind, T = configurations(seed)
    if cuboid and param != "rts":
        use = kind == 0
        R, t, s, kind, T = R[use], t[use], s[use], kind[use], T[use]
    lmk = batched_landmarks(param, R, t, s)
    boxes = _noisy_boxes(project_cuboid_box if cuboid else project_box, lmk, T, seed + 1)
    return Case((_poses(T), lmk), (jnp.asarray(boxes), _cams(len(kind))), kind)


case("inverse_box")(lambda param: _box_case(1, False, param))


@case("frame_box")
def _frame_box(param):
    """Box factors whose camera is given in a recording's frame, moved into the landmark's by
    a random Sim3 (rotation, translation, scale 0.5-2): the same views as the box case."""
    from spdslam.geometry import Sim3

    base = _box_case(3, False, param)
    rng = np.random.default_rng(31)
    n = len(base.kind)
    Rf = np.stack([random_rotation(rng) for _ in range(n)])
    tf, sf = rng.normal(size=(n, 3)), np.exp(rng.uniform(np.log(0.5), np.log(2.0), n))
    frames = jax.vmap(lambda R, t, s: Sim3(jaxlie.SO3.from_matrix(R), t, jnp.log(s)))(
        jnp.asarray(Rf), jnp.asarray(tf), jnp.asarray(sf))
    T = np.asarray(base.values[0].as_matrix())  # the cameras in the landmark's frame
    T_rec = T.copy()  # the same cameras in the recording's: R_fᵀ R_c, R_fᵀ (t_c − t_f) / s
    T_rec[:, :3, :3] = np.einsum("nji,njk->nik", Rf, T[:, :3, :3])
    T_rec[:, :3, 3] = np.einsum("nji,nj->ni", Rf, T[:, :3, 3] - tf) / sf[:, None]
    return Case((frames, base.values[1]), (_poses(T_rec), *base.args), base.kind)
@case("drift_box", params=("spd",))
def _drift_box(param):
    """Box factors seen from a drifting odometry: the views of the box case given in a frame
    that the correction K(t), interpolated between two random knots (rotations up to ~0.3
    rad, translations ~0.2 m) with a random weight, puts back, so the Jacobians are taken
    with respect to both knots at general points (w = 0 and 1 included). The landmark enters
    as in the inverse box case, checked there for every parameterisation: SPD here."""
    base = _box_case(5, False, param)
    rng = np.random.default_rng(51)
    n = len(base.kind)

    def knots():
        return jax.vmap(lambda w, v: jaxlie.SE3.exp(jnp.concatenate([v, w])))(
            jnp.asarray(rng.normal(scale=0.15, size=(n, 3))), jnp.asarray(rng.normal(scale=0.2, size=(n, 3))))

    Ka, Kb = knots(), knots()
    w = rng.uniform(0.0, 1.0, n)
    w[:2] = (0.0, 1.0)
    K = jax.vmap(interpolated_frame)(Ka, Kb, jnp.asarray(w))
    T_odo = jax.vmap(lambda k, T: k.inverse() @ T)(K, base.values[0])  # the cameras, drifted
    return Case((Ka, Kb, base.values[1]), (T_odo, jnp.asarray(w), *base.args), base.kind)


case("semi_inverse_box")(lambda param: _box_case(1, False, param))
case("inverse_cuboid_box")(lambda param: _box_case(14, True, param))
case("semi_inverse_cuboid_box")(lambda param: _box_case(14, True, param))


@case("orientation")
def _orientation(param):
    R, t, s, kind, _ = configurations(3)
    m = _unit(np.random.default_rng(4), N)
    return Case((batched_landmarks(param, R, t, s),), (jnp.asarray(m),), kind)


@case("classic_orientation", params=("rts",))
def _classic_orientation(param):
    R, t, s, kind, _ = configurations(5)
    rng = np.random.default_rng(6)
    m = _unit(rng, N)
    axis = np.eye(3)[rng.integers(3, size=N)]
    return Case((batched_landmarks(param, R, t, s),), (jnp.asarray(m), jnp.asarray(axis)), kind)


@case("classic_shape", params=("rts",))
def _classic_shape(param):
    """The stored scales' ratios: smooth wherever no scale is zero, ties included."""
    R, t, s, kind, _ = configurations(25)
    prior = np.random.default_rng(26).uniform(0.2, 1.0, size=(N, 3))
    return Case((batched_landmarks(param, R, t, s),), (jnp.asarray(prior[:, :2] / prior[:, 2:]),), kind)


@case("axis_orientation")
def _axis_orientation(param):
    """Per-axis (cuboid) orientation: like the cuboid, defined by the axes, so SPD/Full are
    checked where the radii are distinct and RTS everywhere."""
    R, t, s, kind, _ = configurations(19)
    use = np.ones(N, bool) if param == "rts" else kind == 0
    R, t, s, kind = R[use], t[use], s[use], kind[use]
    m = _unit(np.random.default_rng(20), len(kind))
    return Case((batched_landmarks(param, R, t, s),), (jnp.asarray(m),), kind)


#: Tangent directions in which an exact sphere's triple tie splits symmetrically (eigenvalue
#: changes μ with μ₂ = (μ₁+μ₃)/2): single off-diagonal entries of P, and rigid motions.
SYMMETRIC_AT_SPHERE = {"spd": [3, 4, 5, 6, 7, 8], "rts": [0, 1, 2, 3, 4, 5], "full": [1, 2, 5]}


@case("shape")
def _shape(param):
    """Sorted ratios are not differentiable where radii coincide. At a double tie
    (spheroid) the central difference equals the mean derivative over the tie, which is
    what ``matfun.eigh`` returns, so every direction is checked (with a smaller step: at a
    kink the central difference is only first-order accurate). At a triple tie (sphere) the
    central difference of sorted eigenvalues is not linear in the direction, so no Jacobian
    can match it everywhere: there the check is restricted to directions that split the tie
    symmetrically, and the Jacobian must still be finite."""
    R, t, s, kind, _ = configurations(7)
    prior = np.sort(np.random.default_rng(8).uniform(0.2, 1.0, size=(N, 3)), axis=1)[:, ::-1]
    ratios = prior[:, :2] / prior[:, 2:]
    return Case((batched_landmarks(param, R, t, s),), (jnp.asarray(ratios),), kind,
                SYMMETRIC_AT_SPHERE[param], h=1e-8)


@case("size")
def _size(param):
    R, t, s, kind, _ = configurations(10)
    logv = np.random.default_rng(11).normal(size=N)
    return Case((batched_landmarks(param, R, t, s),), (jnp.asarray(logv),), kind)


@case("radius_floor")
def _radius_floor(param):
    """Floors above the smallest radius (the hinge active) and below it (zero residual);
    the smallest eigenvalue has the tie rules of the shape case."""
    R, t, s, kind, _ = configurations(23)
    lo = np.sort(s, axis=1)[:, 0]
    factor = np.where(np.arange(N) % 2 == 0, 1.5, 0.5)  # above / below
    return Case((batched_landmarks(param, R, t, s),), (jnp.asarray(np.log(lo * factor)),), kind,
                SYMMETRIC_AT_SPHERE[param], h=1e-8)


@case("support_plane")
def _support_plane(param):
    R, t, s, kind, _ = configurations(12)
    rng = np.random.default_rng(13)
    planes = np.concatenate([_unit(rng, N), rng.uniform(-2, 2, size=(N, 1))], axis=1)
    return Case((batched_landmarks(param, R, t, s),), (jnp.asarray(planes),), kind)


@case("landmark_prior", params=("spd", "rts"))
def _landmark_prior(param):
    """Landmarks near a prior mean (a perturbed copy of each): the residual x ⊟ x̄ and its
    Jacobian through x's retraction."""
    R, t, s, kind, _ = configurations(25)
    rng = np.random.default_rng(26)
    Rm = R @ Rotation.from_rotvec(0.2 * rng.normal(size=(N, 3))).as_matrix()
    tm = t + 0.2 * rng.normal(size=t.shape)
    sm = s * np.exp(0.2 * rng.normal(size=s.shape))
    offset = jnp.asarray(0.1 * rng.normal(size=(N, 9)))
    return Case((batched_landmarks(param, R, t, s),), (batched_landmarks(param, Rm, tm, sm), offset),
                kind)


@case("ellipsoid_measurement")
def _ellipsoid_measurement(param):
    """Noisy camera-frame measurements of each ellipsoid; spheres measured as spheres."""
    R, t, s, kind, T = configurations(21)
    rng = np.random.default_rng(22)
    noise = 0.1
    Rm = R @ Rotation.from_rotvec(noise * rng.normal(size=(N, 3))).as_matrix()
    sm = s * np.exp(noise * rng.normal(size=s.shape))
    sm[kind == 2] = sm[kind == 2, :1]
    Rm[kind == 2] = R[kind == 2]
    Rwc, twc = T[:, :3, :3], T[:, :3, 3]
    Rc = np.einsum("nji,njk->nik", Rwc, Rm)
    tc = np.einsum("nji,nj->ni", Rwc, t + noise * rng.normal(size=t.shape) - twc)
    P = np.einsum("nij,nj,nkj->nik", Rc, sm**2, Rc)
    P[kind == 2] = sm[kind == 2, 0, None, None] ** 2 * np.eye(3)  # exactly c·I
    return Case((_poses(T), batched_landmarks(param, R, t, s)), (jnp.asarray(P), jnp.asarray(tc)),
                kind)


def _random_poses(rng, n, scale=1.5):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return jaxlie.SE3(jnp.asarray(np.concatenate([q, rng.normal(size=(n, 3)) * scale], 1)))


def _perturbed(T, rng, scales):
    """T ⊞ ξ with ξ of the given scale per pose (0: at the measurement)."""
    xi = rng.normal(size=(len(scales), 6)) * np.asarray(scales)[:, None]
    return jax.vmap(lambda a, d: a @ jaxlie.SE3.exp(d))(T, jnp.asarray(xi))


_POSE_NOISE = np.resize([0.0, 0.3, 1.5], 96)


@case("prior", params=("pose",))
def _prior(param):
    rng = np.random.default_rng(23)
    Tbar = _random_poses(rng, len(_POSE_NOISE))
    return Case((_perturbed(Tbar, rng, _POSE_NOISE),), (Tbar,), np.zeros(len(_POSE_NOISE), int))


@case("between", params=("pose",))
def _between(param):
    rng = np.random.default_rng(24)
    n = len(_POSE_NOISE)
    T1, T2 = _random_poses(rng, n), _random_poses(rng, n)
    T12 = _perturbed(jax.vmap(lambda a, b: a.inverse() @ b)(T1, T2), rng, _POSE_NOISE)
    return Case((T1, T2), (T12,), np.zeros(n, int))


TABLE = [(kind, param) for kind, (_, params) in CASES.items() for param in params]


@pytest.mark.parametrize("kind,param", TABLE)
def test_jacobian_matches_central_differences(kind, param):
    cls = factor_types()[kind]
    c = CASES[kind][0](param)
    if cls.valid is not None:  # the configurations are valid ones (objects in front)
        assert np.all(np.asarray(jax.vmap(cls.valid)(*c.values, *c.args)))
    r, _ = check_jacobians(cls.residual, c.values, c.args, c.kind, c.symmetric_cols, c.h)
    assert r.shape[1:] == (cls.dim,)


def test_every_factor_type_has_a_jacobian_case():
    ours = {k for k, cls in factor_types().items() if cls.__module__.startswith("spdslam.")}
    assert ours == set(CASES), f"factor types without a Jacobian case: {sorted(ours - set(CASES))}"


def test_shape_rts_sphere_symmetric_radius_direction():
    """RTS sphere: the radius direction (+h, 0, −h) splits the tie symmetrically."""
    from spdslam.factors import shape_residual, tangent_jacobians

    R, t, s, kind, _ = configurations(9, 30)
    sphere = kind == 2
    lmk = batched_landmarks("rts", R[sphere], t[sphere], s[sphere])
    ratios = jnp.array([1.7, 1.2])
    v = jnp.array([0, 0, 0, 0, 0, 0, 1.0, 0, -1.0])

    def directional(x):
        _, (J,) = tangent_jacobians(shape_residual, (x,), (ratios,))
        f = lambda h: shape_residual(x.retract(h * v), ratios)  # noqa: E731
        return J @ v, (f(H) - f(-H)) / (2 * H)

    a, n = jax.vmap(directional)(lmk)
    np.testing.assert_allclose(a, n, atol=1e-6)


@pytest.mark.parametrize("param", PARAMS)
@pytest.mark.parametrize("kind", robust_groups()["box"])
def test_masked_box_factor_jacobians(param, kind):
    """Truncation masks (random 0/1 per edge): masked rows are exactly zero, the rest as
    without a mask, and the Jacobians match central differences. For every parameterisation
    the residual is the mask times the unmasked one, to the bit, whose Jacobian the table
    checks per parameterisation; the masked Jacobian itself is checked on SPD landmarks."""
    cls = factor_types()[kind]
    cuboid = "cuboid" in kind
    R, t, s, k, T = configurations(16, 60)
    if cuboid and param != "rts":
        use = k == 0
        R, t, s, k, T = R[use], t[use], s[use], k[use], T[use]
    n = len(k)
    lmk = batched_landmarks(param, R, t, s)
    boxes = jnp.asarray(_noisy_boxes(project_cuboid_box if cuboid else project_box, lmk, T, 17))
    keep = jnp.asarray(np.random.default_rng(18).integers(0, 2, size=(n, 4)).astype(float))
    poses = _poses(T)
    if kind == "frame_box":  # the camera is data, the frame (here the identity) the variable
        frames = jax.vmap(lambda _: jaxlie.SE3.identity())(jnp.arange(n))
        values, data = (frames, lmk), (poses, boxes, _cams(n))
    elif kind == "drift_box":  # the camera is data, the knots (here the identity) the variables
        knots = jax.vmap(lambda _: jaxlie.SE3.identity())(jnp.arange(n))
        values, data = (knots, knots, lmk), (poses, jnp.full(n, 0.5), boxes, _cams(n))
    else:
        values, data = (poses, lmk), (boxes, _cams(n))
    if param == "spd":
        check_jacobians(cls.residual, values, (*data, keep), k)
    masked = np.asarray(jax.vmap(cls.residual)(*values, *data, keep))
    full = np.asarray(jax.vmap(cls.residual)(*values, *data))
    np.testing.assert_array_equal(masked[np.asarray(keep) == 0], 0.0)
    np.testing.assert_array_equal(masked[np.asarray(keep) == 1], full[np.asarray(keep) == 1])
