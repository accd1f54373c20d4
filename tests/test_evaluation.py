"""Oriented cuboids, exact 3D IoU and orientation error (spdslam.evaluation).

IoU is checked against closed forms (products of interval overlaps for boxes sharing their
axes, the octagonal prism of two cubes turned about z), against Monte Carlo with the
cuboid's definition {c + R q : |q_k| ≤ h_k} as membership test, and for its symmetries.
The orientation error is checked against a brute-force loop with arccos.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.optimize import linprog, minimize
from scipy.spatial import ConvexHull, HalfspaceIntersection

from spdslam import Ellipsoid, EllipsoidFull, EllipsoidRTS
from spdslam.evaluation import (
    MAX_ORIENTATION_ERROR_DEG,
    cuboid_iou,
    cuboid_iou_batch,
    orientation_error_deg,
    signed_permutations,
    translation_error,
)
from spdslam.geometry import Cuboid, as_cuboid


# --- independent helpers --------------------------------------------------------------


def rodrigues(axis, angle) -> np.ndarray:
    """exp(angle [axis]×), axis normalised here."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def all_signed_perms():
    """All 48 signed permutation matrices, built here without the module."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            G = np.zeros((3, 3))
            for col, (row, sg) in enumerate(zip(perm, signs)):
                G[row, col] = sg
            out.append(G)
    return out


def brute_orientation_error(Re, Rg) -> float:
    """min over signed permutations G with det(Rgᵀ Re G) = +1 of arccos((tr − 1)/2)."""
    best = np.inf
    for G in all_signed_perms():
        M = Rg.T @ Re @ G
        if np.linalg.det(M) > 0:
            best = min(best, np.degrees(np.arccos(np.clip((np.trace(M) - 1) / 2, -1, 1))))
    return best


def inside(points, c, R, h) -> np.ndarray:
    """The definition: |Rᵀ(x − c)|_k ≤ h_k."""
    return np.all(np.abs((points - c) @ R) <= h, axis=1)


def random_cuboid(gen, center_scale=0.5, lo=0.2, hi=1.5) -> Cuboid:
    return Cuboid(gen.rng.normal(size=3) * center_scale, gen.rotation(), gen.rng.uniform(lo, hi, 3))


def same_point_set(A, B, tol=1e-12) -> bool:
    d = np.linalg.norm(A[:, None, :] - B[None, :, :], axis=-1)
    return bool(np.all(d.min(axis=1) < tol) and np.all(d.min(axis=0) < tol))


def overlap(lo_a, hi_a, lo_b, hi_b) -> float:
    return float(np.prod(np.maximum(0.0, np.minimum(hi_a, hi_b) - np.maximum(lo_a, lo_b))))


def box(R, lo, hi) -> Cuboid:
    """The box lo ≤ Rᵀx ≤ hi, as a Cuboid."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return Cuboid(R @ ((lo + hi) / 2), R, (hi - lo) / 2)


def square_intersection_area(theta) -> float:
    """Area of [−1, 1]² ∩ its rotation by θ ∈ (0, π/2): the square less four corner
    triangles cut by the lines n·x = 1, n = (cos θ, sin θ) etc."""
    s, c = np.sin(theta), np.cos(theta)
    return 4.0 - 2.0 * (s + c - 1.0) ** 2 / (s * c)


# --- Cuboid ---------------------------------------------------------------------------


@pytest.mark.parametrize("cls", [Ellipsoid, EllipsoidRTS, EllipsoidFull])
def test_from_ellipsoid_matches_cuboid_corners(gen, cls):
    for _ in range(2):
        R, t, s = gen.ellipsoid_params()
        e = Ellipsoid.from_axes(R, t, s)
        x = e if cls is Ellipsoid else cls.from_ellipsoid(e)
        q = Cuboid.from_ellipsoid(x)
        np.testing.assert_allclose(q.corners(), np.asarray(e.cuboid_corners()), atol=1e-9)
        np.testing.assert_allclose(q.center, t, atol=1e-12)
        np.testing.assert_allclose(q.half_extents, np.sort(s)[::-1], rtol=1e-9)
        assert q.volume() == pytest.approx(8 * np.prod(s), rel=1e-9)
        assert np.linalg.det(q.rotation) == pytest.approx(1.0)
        assert as_cuboid(x).volume() == pytest.approx(q.volume())


def test_from_yaw_and_row():
    q = Cuboid.from_yaw([1.0, 2.0, 3.0], np.pi / 6, [0.5, 0.25, 1.0])
    np.testing.assert_allclose(q.rotation[:, 0], [np.cos(np.pi / 6), 0.5, 0], atol=1e-15)
    np.testing.assert_allclose(q.rotation[:, 2], [0, 0, 1])
    assert q.volume() == pytest.approx(1.0)
    r = Cuboid.from_row("1 2 3 0.5235987755982988 0.5 0.25 1".split())
    np.testing.assert_allclose(r.corners(), q.corners(), atol=1e-14)
    # corners are c ± h along the axes: the extents along x' are ±0.5
    along_x = np.sort((q.corners() - q.center) @ q.rotation[:, 0])
    np.testing.assert_allclose(along_x, [-0.5] * 4 + [0.5] * 4)


def test_reflection_is_the_same_solid(gen):
    R = gen.rotation() @ np.diag([1.0, 1.0, -1.0])
    q = Cuboid([0, 1, 2], R, [1, 2, 3])
    assert np.linalg.det(q.rotation) == pytest.approx(1.0)
    signs = np.array(list(itertools.product((-1, 1), repeat=3)))
    corners = np.array([0, 1, 2]) + (signs * [1, 2, 3]) @ R.T
    assert same_point_set(q.corners(), corners)


def test_inputs_are_copied_and_frozen():
    c = np.zeros(3)
    q = Cuboid(c, np.eye(3), np.ones(3))
    c[0] = 5.0  # the caller's array is still writable and not shared
    assert q.center[0] == 0.0 and not q.center.flags.writeable


def test_contains_and_transformed(gen):
    q = random_cuboid(gen)
    x = gen.rng.normal(size=(1000, 3))
    np.testing.assert_array_equal(q.contains(x), inside(x, q.center, q.rotation, q.half_extents))
    Q, u = gen.rotation(), gen.rng.normal(size=3)
    assert same_point_set(q.transformed(Q, u).corners(), q.corners() @ Q.T + u, tol=1e-12)


# --- IoU: closed forms ----------------------------------------------------------------


def test_identical_is_one(gen):
    cs = [random_cuboid(gen, center_scale=10.0) for _ in range(50)]
    np.testing.assert_allclose(cuboid_iou_batch(cs, cs), 1.0, rtol=1e-12)
    e = gen.ellipsoid()
    assert cuboid_iou(e, EllipsoidRTS.from_ellipsoid(e)) == pytest.approx(1.0, abs=1e-9)


def test_disjoint_and_touching_are_zero(gen):
    for _ in range(50):
        a, b = random_cuboid(gen), random_cuboid(gen)
        n = gen.tangent_vec(1.0, 3)
        support = lambda q: np.sum(q.half_extents * np.abs(q.rotation.T @ n))  # noqa: E731
        gap = support(a) + support(b) + (n @ (a.center - b.center)) + gen.rng.uniform(1e-6, 1.0)
        b = Cuboid(b.center + gap * n, b.rotation, b.half_extents)
        assert cuboid_iou(a, b) == 0.0
    R = gen.rotation()
    cube = box(R, [0, 0, 0], [1, 1, 1])
    for lo in ([1, 0, 0], [1, 1, 0], [1, 1, 1], [1, 0.5, 0.5], [0.3, 1, -0.5]):
        touching = box(R, lo, np.asarray(lo) + 1)  # shares a face, an edge or a corner
        assert cuboid_iou(cube, touching) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("grid", [False, True])
def test_common_axes_product_of_overlaps(gen, grid):
    """Boxes with the same axes: |A ∩ B| = Π_k overlap of the intervals. ``grid`` draws the
    bounds from the grid ½ℤ so that faces, edges and corners coincide often."""
    A, B, expect = [], [], []
    for i in range(200):
        R = np.eye(3) if i % 2 else gen.rotation()
        if grid:
            lo_a, lo_b = gen.rng.integers(0, 4, size=(2, 3)) / 2.0
            hi_a, hi_b = (lo_a, lo_b) + gen.rng.integers(1, 5, size=(2, 3)) / 2.0
        else:
            lo_a, lo_b = gen.rng.uniform(-1, 1, size=(2, 3))
            hi_a, hi_b = lo_a + gen.rng.uniform(0.1, 2, 3), lo_b + gen.rng.uniform(0.1, 2, 3)
        va, vb = np.prod(hi_a - lo_a), np.prod(hi_b - lo_b)
        vi = overlap(lo_a, hi_a, lo_b, hi_b)
        A.append(box(R, lo_a, hi_a))
        B.append(box(R, lo_b, hi_b))
        expect.append(vi / (va + vb - vi))
    got = cuboid_iou_batch(A, B)
    np.testing.assert_allclose(got, expect, rtol=1e-9, atol=1e-9)
    assert np.mean(np.asarray(expect) > 0) > 0.2  # a fair share overlap; others apart or touching


def test_nested(gen):
    for _ in range(20):
        a = random_cuboid(gen, lo=1.0, hi=2.0)
        c = a.center + 0.1 * gen.rng.normal(size=3)
        b = Cuboid(c, gen.rotation(), gen.rng.uniform(0.1, 0.4, 3))
        assert cuboid_iou(a, b) == pytest.approx(b.volume() / a.volume(), rel=1e-10)


def test_signed_permutation_of_axes_is_the_same_solid(gen):
    """c, R G, |G|ᵀh describe the same solid for any signed permutation G (e.g. a 90° turn
    about an axis with two extents swapped)."""
    for G in all_signed_perms():
        a = random_cuboid(gen, center_scale=3.0)
        b = Cuboid(a.center, a.rotation @ G, np.abs(G).T @ a.half_extents)
        assert same_point_set(a.corners(), b.corners(), tol=1e-12)
        assert cuboid_iou(a, b) == pytest.approx(1.0, abs=1e-12)
    a = Cuboid([0, 0, 0], np.eye(3), [1, 2, 3])
    b = Cuboid([0, 0, 0], rodrigues([0, 0, 1], np.pi / 2), [2, 1, 3])
    assert cuboid_iou(a, b) == pytest.approx(1.0, abs=1e-12)


def test_cubes_turned_about_z_octagonal_prism(gen):
    """Half-extent-1 cubes, one turned by 45° about z: A ∩ B is a regular octagonal prism,
    cross-section 8(√2 − 1) (inradius 1), height 2 − dz when shifted by dz along z."""
    a = Cuboid([0, 0, 0], np.eye(3), [1, 1, 1])
    for dz in (0.0, 0.5, 1.3):
        b = Cuboid([0, 0, dz], rodrigues([0, 0, 1], np.pi / 4), [1, 1, 1])
        vi = 8 * (np.sqrt(2) - 1) * (2 - dz)
        assert cuboid_iou(a, b) == pytest.approx(vi / (16 - vi), rel=1e-12)
    # any angle, any common rigid motion and scale
    for _ in range(20):
        theta, k = gen.rng.uniform(0.01, np.pi / 2 - 0.01), gen.rng.uniform(0.1, 10)
        Q, u = gen.rotation(), gen.rng.normal(size=3) * 5
        a = Cuboid(u, Q, [k, k, k])
        b = Cuboid(u, Q @ rodrigues([0, 0, 1], theta), [k, k, k])
        vi = square_intersection_area(theta) * 2 * k**3
        assert cuboid_iou(a, b) == pytest.approx(vi / (16 * k**3 - vi), rel=1e-10)
    assert square_intersection_area(np.pi / 4) == pytest.approx(8 * (np.sqrt(2) - 1))


def halfspace_iou(a: Cuboid, b: Cuboid) -> float:
    """A second exact method: A ∩ B as the intersection of the 12 half-spaces
    ±R_kᵀ(x − c) ≤ h_k, seeded with its Chebyshev centre (a linear programme); 0 when that
    programme is infeasible."""
    H = []
    for q in (a, b):
        for sign in (1.0, -1.0):
            normals = sign * q.rotation.T
            H.append(np.hstack([normals, -(normals @ q.center + q.half_extents)[:, None]]))
    H = np.vstack(H)
    A, off = H[:, :3], H[:, 3]
    res = linprog([0, 0, 0, -1], A_ub=np.hstack([A, np.ones((12, 1))]), b_ub=-off,
                  bounds=[(None, None)] * 3 + [(0, None)])
    if res.status == 2 or res.x[3] < 1e-9:
        return 0.0
    vi = ConvexHull(HalfspaceIntersection(H, res.x[:3]).intersections).volume
    return vi / (a.volume() + b.volume() - vi)


def test_against_halfspace_intersection(gen):
    """Random pairs, pairs on a common face plane turned about its normal, slabs 10⁻³ thin,
    and near-identical pairs (perturbed by 10⁻⁷)."""
    A, B = [], []
    for i in range(160):
        a = random_cuboid(gen, lo=0.1, hi=2.0)
        R, h = a.rotation, a.half_extents
        kind = i % 4
        hb = gen.rng.uniform(0.1, 2, 3)
        if kind == 0:
            b = Cuboid(a.center + 0.7 * gen.rng.normal(size=3), gen.rotation(), hb)
        elif kind == 1:
            up = gen.rng.choice([-1.0, 1.0]) * (h[2] + hb[2])
            c = a.center + R[:, :2] @ gen.rng.normal(size=2) * 0.5 + up * R[:, 2]
            b = Cuboid(c, rodrigues(R[:, 2], gen.rng.uniform(0, np.pi)) @ R, hb)
        elif kind == 2:
            b = Cuboid(a.center + 0.3 * gen.rng.normal(size=3), gen.rotation(), hb * [1, 1e-3, 1])
        else:
            Q = rodrigues(gen.rng.normal(size=3), 1e-7)
            eps = 1e-7 * gen.rng.normal(size=(2, 3))
            b = Cuboid(a.center + eps[0], Q @ R, h * (1 + eps[1]))
        A.append(a)
        B.append(b)
    expect = [halfspace_iou(a, b) for a, b in zip(A, B)]
    np.testing.assert_allclose(cuboid_iou_batch(A, B), expect, rtol=1e-11, atol=1e-13)


# --- IoU: Monte Carlo and symmetries --------------------------------------------------


def test_monte_carlo(gen):
    n = 200_000
    checked = 0
    while checked < 8:
        a, b = random_cuboid(gen, center_scale=0.4), random_cuboid(gen, center_scale=0.4)
        iou = cuboid_iou(a, b)
        if not 0.02 < iou < 0.98:
            continue
        checked += 1
        # IoU: uniform points in the bounding box of both
        pts = np.concatenate([a.corners(), b.corners()])
        x = gen.rng.uniform(pts.min(0), pts.max(0), size=(n, 3))
        ia = inside(x, a.center, a.rotation, a.half_extents)
        ib = inside(x, b.center, b.rotation, b.half_extents)
        n_union = np.count_nonzero(ia | ib)
        se = np.sqrt(iou * (1 - iou) / n_union)
        assert abs(np.count_nonzero(ia & ib) / n_union - iou) < 3 * se
        # |A ∩ B| / |A|: uniform points in A
        x = a.center + (gen.rng.uniform(-1, 1, size=(n, 3)) * a.half_extents) @ a.rotation.T
        f = iou * (a.volume() + b.volume()) / (1 + iou) / a.volume()
        se = np.sqrt(f * (1 - f) / n)
        assert abs(np.mean(inside(x, b.center, b.rotation, b.half_extents)) - f) < 3 * se


def test_symmetric_and_rigid_invariant(gen):
    A = [random_cuboid(gen) for _ in range(200)]
    B = [random_cuboid(gen) for _ in range(200)]
    ab = cuboid_iou_batch(A, B)
    np.testing.assert_allclose(ab, cuboid_iou_batch(B, A), rtol=1e-10, atol=1e-12)
    single = [cuboid_iou(a, b) for a, b in zip(A[:20], B[:20])]
    np.testing.assert_allclose(ab[:20], single, rtol=1e-12)
    Q, u = gen.rotation(), gen.rng.normal(size=3) * 20
    moved = cuboid_iou_batch([a.transformed(Q, u) for a in A], [b.transformed(Q, u) for b in B])
    np.testing.assert_allclose(moved, ab, rtol=1e-9, atol=1e-12)
    assert np.all((ab >= 0) & (ab <= 1)) and np.mean(ab > 0) > 0.5


def test_batch_inputs():
    assert cuboid_iou_batch([], []).shape == (0,)
    with pytest.raises(ValueError):
        cuboid_iou_batch([Cuboid([0, 0, 0], np.eye(3), [1, 1, 1])], [])
    with pytest.raises(TypeError):
        cuboid_iou(np.zeros(3), np.zeros(3))


# --- orientation error ----------------------------------------------------------------


def test_signed_permutations_group():
    G = signed_permutations()
    assert G.shape == (24, 3, 3)
    np.testing.assert_allclose(np.linalg.det(G), 1.0)
    assert len({g.tobytes() for g in G}) == 24
    np.testing.assert_allclose(np.linalg.det(signed_permutations(proper=False)), -1.0)


def test_zero_for_signed_permutations(gen):
    for _ in range(3):
        R = gen.rotation()
        for G in all_signed_perms():  # det −1 ones too: the axes as lines are the same
            assert orientation_error_deg(R @ G, R) == pytest.approx(0.0, abs=1e-6)
            assert orientation_error_deg(R, R @ G) == pytest.approx(0.0, abs=1e-6)


def test_small_rotation_gives_its_angle(gen):
    """Elements of the group are ≥ 90° apart, so below 45° the nearest one is the identity."""
    for angle in np.concatenate([gen.rng.uniform(0, 44, 30), [1e-9, 1e-6, 1e-3]]):
        R, axis = gen.rotation(), gen.rng.normal(size=3)
        got = orientation_error_deg(R @ rodrigues(axis, np.radians(angle)), R)
        assert got == pytest.approx(angle, rel=1e-9, abs=1e-12)
        # the same about a world axis
        got = orientation_error_deg(rodrigues(axis, np.radians(angle)) @ R, R)
        assert got == pytest.approx(angle, rel=1e-9, abs=1e-12)


def test_against_brute_force_and_symmetries(gen):
    perms = all_signed_perms()
    for _ in range(100):
        Re, Rg, Q = gen.rotation(), gen.rotation(), gen.rotation()
        e = orientation_error_deg(Re, Rg)
        assert e == pytest.approx(brute_orientation_error(Re, Rg), abs=1e-6)
        assert orientation_error_deg(Rg, Re) == pytest.approx(e, abs=1e-9)
        assert orientation_error_deg(Q @ Re, Q @ Rg) == pytest.approx(e, abs=1e-9)
        G = perms[gen.rng.integers(48)]
        assert orientation_error_deg(Re @ G, Rg) == pytest.approx(e, abs=1e-9)
        assert 0.0 <= e <= MAX_ORIENTATION_ERROR_DEG + 1e-9


def test_maximum_is_octahedral_covering_radius(gen):
    theta = np.radians(MAX_ORIENTATION_ERROR_DEG)
    assert np.tan(theta / 2) ** 2 == pytest.approx(23 - 16 * np.sqrt(2))
    assert MAX_ORIENTATION_ERROR_DEG == pytest.approx(62.7994296, abs=1e-6)
    # attained at the vertex of the cubic fundamental zone, a local maximum there
    V = rodrigues([1, 1, np.sqrt(2) - 1], theta)
    assert orientation_error_deg(V, np.eye(3)) == pytest.approx(MAX_ORIENTATION_ERROR_DEG, abs=1e-9)
    for _ in range(200):
        W = V @ rodrigues(gen.rng.normal(size=3), 1e-3)
        assert orientation_error_deg(W, np.eye(3)) < MAX_ORIENTATION_ERROR_DEG
    # never exceeded by random rotations; maximisation from random starts reaches it
    errs = [orientation_error_deg(gen.rotation(), np.eye(3)) for _ in range(5000)]
    assert max(errs) <= MAX_ORIENTATION_ERROR_DEG and max(errs) > 55.0

    def neg(v):
        R = rodrigues(v, np.linalg.norm(v)) if np.any(v) else np.eye(3)
        return -orientation_error_deg(R, np.eye(3))

    opts = dict(xatol=1e-10, fatol=1e-12)
    starts = gen.rng.normal(size=(6, 3))
    best = max(-minimize(neg, x0, method="Nelder-Mead", options=opts).fun for x0 in starts)
    assert MAX_ORIENTATION_ERROR_DEG - 1e-3 < best <= MAX_ORIENTATION_ERROR_DEG + 1e-9


def test_objects_and_translation(gen):
    R, t, s = gen.ellipsoid_params()
    e = Ellipsoid.from_axes(R, t, s)  # axes() reorders the columns by radius
    for x in (e, e.to_rts(), e.to_full(), Cuboid.from_ellipsoid(e)):
        assert orientation_error_deg(x, R) == pytest.approx(0.0, abs=1e-5)
        assert translation_error(x, t + [3.0, 4.0, 0.0]) == pytest.approx(5.0)
    import jaxlie

    assert orientation_error_deg(jaxlie.SO3.from_matrix(R), R) == pytest.approx(0.0, abs=1e-5)


# --- degenerate inputs ----------------------------------------------------------------


@pytest.mark.parametrize(
    "center, rotation, half",
    [
        ([0, 0, np.nan], np.eye(3), [1, 1, 1]),
        ([0, 0, 0], np.eye(3), [1, 0, 1]),
        ([0, 0, 0], np.eye(3), [1, -1, 1]),
        ([0, 0, 0], np.eye(3), [1, np.inf, 1]),
        ([0, 0, 0], 1.1 * np.eye(3), [1, 1, 1]),
        ([0, 0, 0], [[1, 0.1, 0], [0, 1, 0], [0, 0, 1]], [1, 1, 1]),
        ([0, 0, 0], np.full((3, 3), np.nan), [1, 1, 1]),
        ([0, 0], np.eye(3), [1, 1, 1]),
        ([0, 0, 0], np.eye(2), [1, 1, 1]),
    ],
)
def test_degenerate_cuboid_raises(center, rotation, half):
    with pytest.raises(ValueError) as err:
        Cuboid(center, rotation, half)
    assert "\n" not in str(err.value)


def test_degenerate_inputs_raise():
    for bad in (np.zeros((3, 3)), np.full((3, 3), np.nan), np.eye(3) * 2, np.eye(4)):
        with pytest.raises(ValueError):
            orientation_error_deg(bad, np.eye(3))
    with pytest.raises(ValueError):
        Cuboid.from_yaw([0, 0, 0], np.nan, [1, 1, 1])
    with pytest.raises(ValueError):
        Cuboid.from_row([0, 0, 0, 0, 1, 1])
    with pytest.raises(ValueError):
        translation_error([0, 0, np.nan], [0, 0, 0])
    flat = Ellipsoid.from_axes(np.eye(3), [0, 0, 0], [1.0, 1.0, 0.0])
    with pytest.raises(ValueError):
        Cuboid.from_ellipsoid(flat)


def test_array_versions_match_the_scalar_ones():
    from spdslam.evaluation import (
        cuboid_iou, cuboid_iou_arrays, orientation_error_deg, orientation_errors_deg,
    )  # fmt: skip

    rng = np.random.default_rng(123)
    n = 40
    q = rng.normal(size=(n, 2, 4))
    import jaxlie

    R = np.array([[np.asarray(jaxlie.SO3(x / np.linalg.norm(x)).as_matrix()) for x in pair] for pair in q])
    R[::3, 0, :, 2] *= -1  # some reflections
    c = rng.normal(scale=0.3, size=(n, 2, 3))
    h = rng.uniform(0.2, 1.0, size=(n, 2, 3))
    iou = cuboid_iou_arrays(c[:, 0], R[:, 0], h[:, 0], c[:, 1], R[:, 1], h[:, 1])
    ori = orientation_errors_deg(R[:, 0], R[:, 1])
    for i in range(n):
        a, b = Cuboid(c[i, 0], R[i, 0], h[i, 0]), Cuboid(c[i, 1], R[i, 1], h[i, 1])
        assert iou[i] == pytest.approx(cuboid_iou(a, b), abs=1e-12)
        assert ori[i] == pytest.approx(orientation_error_deg(R[i, 0], R[i, 1]), abs=1e-9)
    bad = R[:2, 0].copy()
    bad[0, 0, 0] = np.nan
    assert np.isnan(orientation_errors_deg(bad, R[:2, 1])[0])
