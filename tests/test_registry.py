"""The factor registry: one class per factor type, declared once; the noise arguments every
type takes; immutable, copyable, picklable factors; the checks a new type gets."""

from __future__ import annotations

import pickle

import jaxlie
import numpy as np
import pytest

import spdslam  # noqa: F401
from spdslam import Camera, Ellipsoid, L, NonlinearFactorGraph, Values, X
from spdslam.factors import (
    AxisOrientationFactor,
    BetweenFactor,
    ClassicOrientationFactor,
    ClassicShapeFactor,
    CustomFactor,
    DriftBoxFactor,
    EllipsoidMeasurementFactor,
    Factor,
    FrameBoxFactor,
    GaussianNoise,
    Huber,
    InverseBoxFactor,
    InverseCuboidBoxFactor,
    LandmarkPriorFactor,
    OrientationFactor,
    PriorFactor,
    RadiusFloorFactor,
    SemiInverseBoxFactor,
    SemiInverseCuboidBoxFactor,
    ShapeFactor,
    Sigma,
    SizeFactor,
    SupportPlaneFactor,
    default_sigmas,
    factor_types,
    robust_groups,
)
from spdslam.mapping._methods import DEFAULT_MAPPING_SIGMAS, MAPPING_SIGMAS
from spdslam.solver import LevenbergMarquardt

CAM = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)
BOX = [100.0, 120.0, 300.0, 260.0]
T = jaxlie.SE3.identity()

#: One factor of every registered type, from its constructor's measurements.
EXAMPLES = {
    "inverse_box": lambda **n: InverseBoxFactor(X(0), L(0), BOX, CAM, **n),
    "semi_inverse_box": lambda **n: SemiInverseBoxFactor(X(0), L(0), BOX, CAM, **n),
    "inverse_cuboid_box": lambda **n: InverseCuboidBoxFactor(X(0), L(0), BOX, CAM, **n),
    "semi_inverse_cuboid_box": lambda **n: SemiInverseCuboidBoxFactor(X(0), L(0), BOX, CAM, **n),
    "frame_box": lambda **n: FrameBoxFactor("F", L(0), T, BOX, CAM, **n),
    "drift_box": lambda **n: DriftBoxFactor("K0", "K1", L(0), T, 0.25, BOX, CAM, **n),
    "ellipsoid_measurement": lambda **n: EllipsoidMeasurementFactor(
        X(0), L(0), np.eye(3), [0.0, 0.0, 2.0], **n),
    "orientation": lambda **n: OrientationFactor(L(0), [0, 0, 1], **n),
    "axis_orientation": lambda **n: AxisOrientationFactor(L(0), [0, 0, 1], **n),
    "classic_orientation": lambda **n: ClassicOrientationFactor(L(0), [0, 0, 1], 2, **n),
    "shape": lambda **n: ShapeFactor(L(0), [0.3, 0.2, 0.1], **n),
    "classic_shape": lambda **n: ClassicShapeFactor(L(0), [0.3, 0.2, 0.1], **n),
    "size": lambda **n: SizeFactor(L(0), [0.3, 0.2, 0.1], **n),
    "radius_floor": lambda **n: RadiusFloorFactor(L(0), 0.01, **n),
    "landmark_prior": lambda **n: LandmarkPriorFactor(
        L(0), Ellipsoid.from_axes(np.eye(3), [0.0, 0.0, 1.0], [0.3, 0.2, 0.1]), **n),
    "support_plane": lambda **n: SupportPlaneFactor(L(0), [0, 0, 1, 0], **n),
    "prior": lambda **n: PriorFactor(X(0), T, **n),
    "between": lambda **n: BetweenFactor(X(0), X(1), T, **n),
}


def _library_types():
    return {k: c for k, c in factor_types().items() if c.__module__.startswith("spdslam.")}


def test_every_type_has_an_example_and_declares_itself():
    assert set(EXAMPLES) == set(_library_types())
    groups = robust_groups()
    for kind, cls in _library_types().items():
        f = EXAMPLES[kind]()
        assert type(f) is cls and f.kind == kind and cls.residual is f.residual
        assert len(f.keys) == len(cls.variables) and isinstance(cls.dim, int) and cls.dim > 0
        assert kind in groups[cls.group]
        assert f.sqrt_info.shape == (cls.dim, cls.dim)


@pytest.mark.parametrize("kind", sorted(EXAMPLES))
def test_one_noise_argument_for_every_type(kind):
    cls = factor_types()[kind]
    dim = cls.dim
    sigma = np.linspace(0.1, 0.5, dim)
    cov = np.diag(sigma**2)
    if dim > 1:  # a correlated pair
        cov[0, 1] = cov[1, 0] = 0.3 * sigma[0] * sigma[1]
    W = EXAMPLES[kind](covariance=cov).sqrt_info
    np.testing.assert_allclose(W.T @ W, np.linalg.inv(cov), rtol=1e-10)
    for kw in ({"information": np.linalg.inv(cov)}, {"noise": GaussianNoise.covariance(cov)}):
        np.testing.assert_allclose(EXAMPLES[kind](**kw).sqrt_info, W, rtol=1e-10)
    np.testing.assert_allclose(EXAMPLES[kind](sigma=sigma).sqrt_info, np.diag(1 / sigma))
    np.testing.assert_allclose(EXAMPLES[kind](noise=GaussianNoise.sigmas(sigma)).sqrt_info,
                               np.diag(1 / sigma))
    default = cls.default_sigma()
    want = np.eye(dim) if default is None else np.diag(1.0 / default)
    np.testing.assert_allclose(EXAMPLES[kind]().sqrt_info, want)
    with pytest.raises(ValueError, match="at most one"):
        EXAMPLES[kind](sigma=1.0, covariance=cov)
    with pytest.raises(ValueError, match=f"{dim}x{dim}"):
        EXAMPLES[kind](covariance=np.eye(dim + 1))
    with pytest.raises(ValueError, match="sigma"):
        EXAMPLES[kind](sigma=-1.0)


def test_factors_are_immutable_copyable_and_picklable():
    f = EXAMPLES["inverse_box"](sigma=3.0)
    with pytest.raises(AttributeError, match="immutable"):
        f.keys = (X(1), L(0))
    g = f.with_robust(Huber(2.0))
    assert g.robust == Huber(2.0) and f.robust is None and g.keys == f.keys
    h = f.replace(keys=(X(5), L(5)))
    assert h.keys == (X(5), L(5)) and f.keys == (X(0), L(0)) and type(h) is type(f)
    with pytest.raises(TypeError, match="cannot replace"):
        f.replace(residual=None)
    p = pickle.loads(pickle.dumps(g))
    assert type(p) is InverseBoxFactor and p.keys == g.keys and p.robust == g.robust
    np.testing.assert_array_equal(p.sqrt_info, g.sqrt_info)
    np.testing.assert_array_equal(p.args[0], g.args[0])


def test_the_flattened_args_are_computed_once_and_follow_a_replace():
    """``Factor.flat_args`` (what the solver stacks factors by) is kept on the factor; a copy
    with other args flattens its own, and a pickled factor carries none of it."""
    f = EXAMPLES["inverse_box"]()
    leaves, treedef, shapes = f.flat_args()
    assert f.flat_args()[0] is leaves
    assert all(isinstance(a, np.ndarray) for a in leaves)
    assert shapes == tuple((a.shape, a.dtype.str) for a in leaves)
    box = np.asarray(f.args[0]) + 1.0
    g = f.replace(args=(box,) + tuple(f.args[1:]))
    np.testing.assert_array_equal(g.flat_args()[0][0], box)
    np.testing.assert_array_equal(f.flat_args()[0][0], box - 1.0)
    assert f.with_robust(Huber(1.0)).flat_args()[2] == shapes
    p = pickle.loads(pickle.dumps(f))
    assert "_flat" not in f.__getstate__()
    np.testing.assert_array_equal(p.flat_args()[0][0], leaves[0])
    with pytest.raises(TypeError, match="cannot replace"):
        f.replace(_flat=None)


def test_declaration_errors():
    with pytest.raises(TypeError, match="not a factor type"):
        Factor((X(0),), ())
    with pytest.raises(TypeError, match="declares no dim"):
        type("NoDim", (Factor,), {"kind": "test_no_dim", "residual": staticmethod(lambda x: x),
                                  "group": "g"})
    with pytest.raises(TypeError, match="do not cover"):
        type("BadSigmas", (Factor,), {"kind": "test_bad_sigmas", "residual": staticmethod(lambda x: x),
                                      "dim": 3, "group": "g", "sigmas": (Sigma(1.0, "m", size=2),)})
    with pytest.raises(TypeError, match="already registered"):
        type("Impostor", (Factor,), {"kind": "inverse_box", "residual": staticmethod(lambda x: x),
                                     "dim": 4, "group": "box"})

    class OneLandmark(Factor):  # no kind: a base, not registered
        residual = staticmethod(lambda landmark: landmark.center)
        variables = ("landmark",)

    assert OneLandmark((L(0),)).keys == (L(0),) and "OneLandmark" not in str(factor_types())
    with pytest.raises(ValueError, match=r"connects 1 variables \(landmark\), got 2 keys"):
        OneLandmark((L(0), L(1)))


def test_the_solver_checks_the_declared_dimension():
    def two(landmark):
        return landmark.center[:2]

    class WrongDim(Factor):
        kind = "test_wrong_dim"
        residual = staticmethod(two)
        variables = ("landmark",)
        dim = 3
        group = "test"

        def __init__(self, key):
            super().__init__((key,), ())

    try:
        graph = NonlinearFactorGraph([WrongDim(L(0))])
        values = Values({L(0): Ellipsoid.from_axes(np.eye(3), np.zeros(3), [1.0, 1.0, 1.0])})
        for _ in range(2):  # the second layout takes the residual's dimension from a cache
            with pytest.raises(ValueError, match=r"WrongDim, keys \(l0,\)\): the residual has dimension 2, "
                                                 r"but WrongDim declares dim = 3"):
                LevenbergMarquardt().optimize(graph, values)
    finally:
        from spdslam.factors import _base

        _base._REGISTRY.pop("test_wrong_dim", None)


def test_a_residual_that_fails_is_named_at_every_layout():
    """A residual that cannot be traced is reported with its factor each time a problem is
    laid out (only dimensions that were found are kept)."""
    def broken(landmark):
        return landmark.center @ np.ones(4)  # (3,) @ (4,): no such product

    graph = NonlinearFactorGraph([CustomFactor(broken, (L(0),), sqrt_info=np.eye(1))])
    values = Values({L(0): Ellipsoid.from_axes(np.eye(3), np.zeros(3), [1.0, 1.0, 1.0])})
    for _ in range(2):
        with pytest.raises(ValueError, match=r"factor #0 \(broken, keys \(l0,\)\): residual failed"):
            LevenbergMarquardt().optimize(graph, values)


def test_custom_factors_stay_possible():
    f = CustomFactor(lambda x: x.center, (L(0),), sqrt_info=np.eye(3), name="centre")
    assert f.kind == "centre" and "centre" not in factor_types()
    e = Ellipsoid.from_axes(np.eye(3), [1.0, 2.0, 3.0], [1.0, 1.0, 1.0])
    assert f.error(e) == pytest.approx(0.5 * 14.0)


def test_the_mapping_noise_table_is_the_registry_plus_its_own():
    table = DEFAULT_MAPPING_SIGMAS  # made when spdslam.mapping was imported
    ours = {s.name or k: s for k, c in _library_types().items() for s in c.sigmas}
    assert set(ours) <= set(default_sigmas()) and len(ours) == 14
    for name, s in ours.items():
        assert name in table
        if name not in MAPPING_SIGMAS:
            assert table[name] == s.value
    for name, (value, unit) in MAPPING_SIGMAS.items():
        assert table[name] == value and unit
    assert {"ellipsoid_shape", "ellipsoid_center", "inverse_box", "odometry_translation"} <= set(table)
