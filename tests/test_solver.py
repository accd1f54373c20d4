"""The nonlinear least-squares solver: LM and GN, the linear solvers, batched solves,
fixed variables, robust kernels, validity, history, stopping rules, error messages, and
non-SE(3) variables (the SPD ellipsoid and the Full quadric with its unobservable scale).

Most tests share one pose-graph layout (8 poses, a prior, odometry and two loop closures) so
that the compiled kernels are reused across tests.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

import spdslam  # noqa: F401
from conftest import log_x_residual, se3
from spdslam import Ellipsoid, EllipsoidFull, spd
from spdslam.factors import BetweenFactor, Cauchy, CustomFactor, Huber, PriorFactor
from spdslam.solver import (
    HAVE_CHOLMOD,
    HAVE_CVXOPT,
    GaussNewton,
    LevenbergMarquardt,
    NonlinearFactorGraph,
    Values,
)

N_POSES = 8
LOOPS = [(0, 5), (2, 7)]
SIGMA = np.array([0.05, 0.05, 0.05, 0.02, 0.02, 0.02])  # (translation, rotation)


def pose_graph(seed: int, noise: float = 0.02, init_noise: float = 0.2, outlier=None,
               robust=None):
    """(graph, initial values, true poses): prior on pose 0, odometry, two loop closures;
    measurements perturbed by ``noise``, initial poses by ``init_noise``; an optional
    ``outlier`` loop closure (i, j) with a grossly wrong measurement."""
    rng = np.random.default_rng(seed)
    truth = [se3(rng.normal(size=6))]
    for _ in range(1, N_POSES):
        truth.append(truth[-1] @ se3(np.r_[rng.normal(size=3), 0.3 * rng.normal(size=3)]))
    graph, values = NonlinearFactorGraph(), Values()
    graph.add(PriorFactor(0, truth[0], sigma=0.01))
    edges = [(i, i + 1) for i in range(N_POSES - 1)] + LOOPS
    for i, j in edges:
        z = truth[i].inverse() @ truth[j] @ se3(rng.normal(size=6) * noise)
        graph.add(BetweenFactor(i, j, z, sigma=SIGMA, robust=robust))
    if outlier is not None:
        i, j = outlier
        z = truth[i].inverse() @ truth[j] @ se3([2.0, -1.5, 1.0, 0.8, -0.5, 0.6])
        graph.add(BetweenFactor(i, j, z, sigma=SIGMA, robust=robust))
    for i, T in enumerate(truth):
        values[i] = T @ se3(rng.normal(size=6) * init_noise)
    return graph, values, truth


def pose_matrices(values, keys=range(N_POSES)):
    return np.stack([np.asarray(values[k].as_matrix()) for k in keys])


TIGHT = dict(relative_tolerance=1e-12, gradient_tolerance=1e-12)


# ------------------------------------------------------------------------------ basics


def test_values_and_graph_containers():
    graph, values, _ = pose_graph(0)
    assert len(graph) == N_POSES - 1 + len(LOOPS) + 1
    assert graph.keys() == list(range(N_POSES))
    assert len(values) == N_POSES and 3 in values
    with pytest.raises(KeyError, match="already has a value"):
        values.insert(3, values[3])
    with pytest.raises(TypeError, match="not an optimisation variable type"):
        values["bad"] = np.zeros(3)
    with pytest.raises(TypeError, match="expected a Factor"):
        graph.add("not a factor")
    # error(): Σ ½‖W r‖², computed factor by factor here
    expected = sum(f.error(*[values[k] for k in f.keys]) for f in graph)
    np.testing.assert_allclose(graph.error(values), expected, rtol=1e-12)


def test_lm_and_gn_reach_the_same_optimum():
    graph, values, _ = pose_graph(1)
    before = pose_matrices(values)
    lm = LevenbergMarquardt(**TIGHT).optimize(graph, values)
    gn = GaussNewton(**TIGHT).optimize(graph, values)
    assert lm.converged and gn.converged, (lm.reason, gn.reason)
    assert lm.final_cost < 1e-3 * lm.initial_cost
    np.testing.assert_allclose(lm.final_cost, gn.final_cost, rtol=1e-9)
    np.testing.assert_allclose(pose_matrices(lm.values), pose_matrices(gn.values), atol=1e-8)
    np.testing.assert_allclose(graph.error(lm.values), lm.final_cost, rtol=1e-12)
    assert lm.initial_cost == pytest.approx(graph.error(values), rel=1e-12)
    # the input Values are not modified (the result is a new Values with other poses)
    np.testing.assert_array_equal(pose_matrices(values), before)
    assert not np.allclose(pose_matrices(values), pose_matrices(lm.values))


@pytest.mark.parametrize("kind", ["cholmod", "cvxopt", "scipy"])
def test_sparse_solvers_match_dense(kind):
    if kind == "cholmod" and not HAVE_CHOLMOD:
        pytest.skip("scikit-sparse is not installed")
    if kind == "cvxopt" and not HAVE_CVXOPT:
        pytest.skip("cvxopt is not installed")
    graph, values, _ = pose_graph(2)
    dense = LevenbergMarquardt(linear_solver="dense", **TIGHT).optimize(graph, values)
    sparse = LevenbergMarquardt(linear_solver=kind, **TIGHT).optimize(graph, values)
    assert dense.linear_solver == "dense" and sparse.linear_solver == kind
    assert sparse.iterations == dense.iterations
    np.testing.assert_allclose(sparse.final_cost, dense.final_cost, rtol=1e-10)
    np.testing.assert_allclose(pose_matrices(sparse.values), pose_matrices(dense.values),
                               atol=1e-9)
    np.testing.assert_allclose([r.cost for r in sparse.history],
                               [r.cost for r in dense.history], rtol=1e-8)


def test_auto_solver_choice_and_bad_name():
    graph, values, _ = pose_graph(3)
    assert LevenbergMarquardt(max_iterations=1).optimize(graph, values).linear_solver == "dense"
    big = LevenbergMarquardt(max_iterations=1, dense_threshold=10).optimize(graph, values)
    assert big.linear_solver == ("cholmod" if HAVE_CHOLMOD else "cvxopt" if HAVE_CVXOPT
                                 else "scipy")
    with pytest.raises(ValueError, match="linear_solver must be"):
        LevenbergMarquardt(linear_solver="qr").optimize(graph, values)


@pytest.mark.parametrize("cholmod,cvxopt,expected", [(True, True, "cholmod"),
                                                     (False, True, "cvxopt"),
                                                     (False, False, "scipy")])
def test_auto_falls_back_in_order(monkeypatch, cholmod, cvxopt, expected):
    """Without scikit-sparse "auto" takes cvxopt's CHOLMOD, without either scipy."""
    from spdslam.solver import _linear

    monkeypatch.setattr(_linear, "HAVE_CHOLMOD", cholmod)
    monkeypatch.setattr(_linear, "HAVE_CVXOPT", cvxopt)
    if expected == "scipy":  # the slow last resort says so
        with pytest.warns(RuntimeWarning, match="SuperLU"):
            assert _linear.resolve_linear_solver("auto", 10_000) == expected
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert _linear.resolve_linear_solver("auto", 10_000) == expected
    assert _linear.resolve_linear_solver("auto", 10) == "dense"
    if not cvxopt:
        with pytest.raises(ImportError, match="needs cvxopt"):
            _linear.resolve_linear_solver("cvxopt", 10_000)


# ------------------------------------------------------------------------------ batched


def test_batched_matches_looped_unbatched_solves():
    problems = [pose_graph(10 + s, init_noise=0.3) for s in range(4)]
    graphs = [p[0] for p in problems]
    values = [p[1] for p in problems]
    batched = LevenbergMarquardt(**TIGHT).optimize_batched(graphs, values)
    assert len(batched) == 4
    for b, (graph, init, _) in enumerate(problems):
        single = LevenbergMarquardt(linear_solver="dense", **TIGHT).optimize(graph, init)
        assert batched.converged[b] and batched.reason[b] == single.reason
        np.testing.assert_allclose(batched.initial_cost[b], single.initial_cost, rtol=1e-12)
        np.testing.assert_allclose(batched.final_cost[b], single.final_cost, rtol=1e-9)
        np.testing.assert_allclose(pose_matrices(batched.values[b]),
                                   pose_matrices(single.values), atol=1e-8)
        its = int(batched.iterations[b])
        assert its == single.iterations
        np.testing.assert_allclose(batched.cost_history[b, :its],
                                   [r.cost for r in single.history], rtol=1e-7)
        np.testing.assert_allclose(batched.lambda_history[b, :its],
                                   [r.damping for r in single.history], rtol=1e-6)
        np.testing.assert_array_equal(batched.accepted_history[b, :its],
                                      [r.accepted for r in single.history])
        np.testing.assert_allclose(batched.step_norm_history[b, :its],
                                   [r.step_norm for r in single.history], rtol=1e-6)
        # padded after convergence
        assert np.all(np.isnan(batched.cost_history[b, its:]))
        assert not batched.accepted_history[b, its:].any()


def test_batched_problem_matches_optimize_batched():
    """The template-plus-arrays API on the same problems: identical results."""
    problems = [pose_graph(10 + s, init_noise=0.3) for s in range(4)]
    graphs = [p[0] for p in problems]
    values = [p[1] for p in problems]
    factor_args = [jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]),
                                *[g[i].args for g in graphs]) for i in range(len(graphs[0]))]
    batched_values = {k: jaxlie.SE3(np.stack([np.asarray(v[k].wxyz_xyz) for v in values]))
                      for k in values[0]}
    lm = LevenbergMarquardt(**TIGHT)
    bp = lm.batched(graphs[0], values[0])
    res = bp.solve(factor_args, batched_values, batch_size=3)
    old = lm.optimize_batched(graphs, values)
    assert res.reason == old.reason
    np.testing.assert_array_equal(res.iterations, old.iterations)
    np.testing.assert_allclose(res.final_cost, old.final_cost, rtol=1e-10)
    np.testing.assert_allclose(res.initial_cost, old.initial_cost, rtol=1e-12)
    for b in range(4):
        its = int(res.iterations[b])
        np.testing.assert_allclose(res.cost_history[b, :its], old.cost_history[b, :its],
                                   rtol=1e-9)
        np.testing.assert_allclose(pose_matrices(res.values[b]), pose_matrices(old.values[b]),
                                   atol=1e-9)
        # the batched pytrees hold the same values
        np.testing.assert_allclose(np.asarray(res.values_batched[3].wxyz_xyz)[b],
                                   np.asarray(res.values[b][3].wxyz_xyz), rtol=0, atol=0)
    np.testing.assert_allclose(bp.cost(factor_args, batched_values), res.initial_cost,
                               rtol=1e-12)


def test_batched_rejects_different_structures():
    a = pose_graph(20)
    b = pose_graph(21, outlier=(1, 6))
    with pytest.raises(ValueError, match="problem 1 has a different structure"):
        LevenbergMarquardt().optimize_batched([a[0], b[0]], [a[1], b[1]])


# ------------------------------------------------------------------------------ fixed, robust


def test_fixed_variables_do_not_move():
    graph, values, truth = pose_graph(4)
    fixed = [0, 4]
    res = LevenbergMarquardt(**TIGHT).optimize(graph, values, fixed=fixed)
    assert res.converged
    for k in fixed:
        np.testing.assert_array_equal(np.asarray(res.values[k].wxyz_xyz),
                                      np.asarray(values[k].wxyz_xyz))
    for k in (1, 2, 3, 5, 6, 7):
        assert not np.allclose(np.asarray(res.values[k].wxyz_xyz), np.asarray(values[k].wxyz_xyz))
    # with pose 4 fixed at a perturbed value the optimum is a different one
    free = LevenbergMarquardt(**TIGHT).optimize(graph, values)
    assert res.final_cost > free.final_cost
    with pytest.raises(ValueError, match="no free variables"):
        LevenbergMarquardt().optimize(graph, values, fixed=range(N_POSES))
    with pytest.raises(ValueError, match="fixed key 'nope' has no value"):
        LevenbergMarquardt().optimize(graph, values, fixed=["nope"])


@pytest.mark.parametrize("kernel", [Huber(k=1.0), Cauchy(k=1.0)])
def test_robust_kernel_downweights_an_outlier(kernel):
    clean_graph, values, truth = pose_graph(5, noise=0.01)
    clean = LevenbergMarquardt(**TIGHT).optimize(clean_graph, values)
    plain_graph, _, _ = pose_graph(5, noise=0.01, outlier=(1, 6))
    robust_graph, _, _ = pose_graph(5, noise=0.01, outlier=(1, 6), robust=kernel)
    plain = LevenbergMarquardt(**TIGHT).optimize(plain_graph, values)
    robust = LevenbergMarquardt(max_iterations=200, **TIGHT).optimize(robust_graph, values)
    assert robust.converged, robust.reason
    err_plain = np.abs(pose_matrices(plain.values) - pose_matrices(clean.values)).max()
    err_robust = np.abs(pose_matrices(robust.values) - pose_matrices(clean.values)).max()
    assert err_plain > 0.1
    assert err_robust < 0.1 * err_plain
    # cost convention: Σ ½ ρ(‖W r‖²)
    expected = sum(f.error(*[robust.values[k] for k in f.keys]) for f in robust_graph)
    np.testing.assert_allclose(robust.final_cost, expected, rtol=1e-10)


# ------------------------------------------------------------------------------ history, stopping


def test_history_records():
    graph, values, _ = pose_graph(6)
    seen = []
    res = LevenbergMarquardt(callback=seen.append, **TIGHT).optimize(graph, values)
    assert len(res.history) == res.iterations == len(seen) > 0
    costs = [r.cost for r in res.history]
    assert all(b <= a for a, b in zip([res.initial_cost] + costs, costs))
    assert costs[-1] == res.final_cost
    for k, r in enumerate(res.history, start=1):
        assert r.iteration == k and r.time > 0.0 and r.damping > 0.0
        assert np.isfinite(r.step_norm) and r.step_norm > 0.0 and np.isfinite(r.trial_cost)
        if r.accepted:
            assert r.trial_cost == r.cost and r.gain_ratio > 0
        else:
            assert r.trial_cost >= r.cost
    assert res.linearizations == 1 + sum(r.accepted for r in res.history)
    assert {"setup", "linearize", "solve", "step"} <= set(res.timings)


def test_stopping_reasons():
    graph, values, truth = pose_graph(7)
    lm = LevenbergMarquardt
    r = lm(max_iterations=2).optimize(graph, values)
    assert (r.reason, r.iterations, r.converged) == ("max_iterations", 2, False)
    r = lm(relative_tolerance=1e-3).optimize(graph, values)
    assert (r.reason, r.converged) == ("relative", True)
    r = lm(step_tolerance=1e3).optimize(graph, values)
    assert (r.reason, r.iterations) == ("step", 1)
    r = lm(callback=lambda rec: rec.iteration == 3).optimize(graph, values)
    assert (r.reason, r.iterations, r.converged) == ("callback", 3, False)
    # noise-free measurements, started at the truth: F = 0
    exact, _, truth = pose_graph(7, noise=0.0)
    at_truth = Values({i: T for i, T in enumerate(truth)})
    r = lm().optimize(exact, at_truth)
    assert (r.reason, r.iterations, r.converged) == ("absolute", 0, True)
    r = lm(absolute_tolerance=1e-20, gradient_tolerance=0.0, relative_tolerance=0.0
           ).optimize(exact, values)
    assert r.reason in ("absolute", "step") and r.final_cost < 1e-20, (r.reason, r.final_cost)
    # restarted at the optimum of the noisy problem: ‖g‖∞ ≈ 0 but F > 0 (how close to 0 the
    # relative tolerance stops depends on the machine's round-off: 1e-6 is not always met)
    opt = lm(**TIGHT).optimize(graph, values)
    assert opt.final_cost > 1.0
    r = lm(gradient_tolerance=1e-4).optimize(graph, opt.values)
    assert (r.reason, r.iterations, r.converged) == ("gradient", 0, True)
    assert lm(gradient_tolerance=1e-4).optimize(graph, values).iterations > 0
    assert r.final_cost > 1e-3


def _stay_residual(T, ref):
    return 0.1 * (ref.inverse() @ T).log()


def _stay_valid(T, ref):
    """Valid only within 1e-9 of ``ref``: any real step makes it invalid."""
    return jnp.linalg.norm((ref.inverse() @ T).log()) < 1e-9


def test_steps_that_invalidate_a_factor_are_rejected():
    graph, values, _ = pose_graph(8)
    graph.add(CustomFactor(_stay_residual, (3,), args=(values[3],), valid=_stay_valid, name="stay"))
    r = LevenbergMarquardt(lambda_max=1e3).optimize(graph, values)
    assert r.reason == "lambda_max" and not r.converged
    assert not any(rec.accepted for rec in r.history)
    assert r.final_cost == r.initial_cost
    lams = [rec.damping for rec in r.history]
    assert all(b > a for a, b in zip(lams, lams[1:]))
    g = GaussNewton().optimize(graph, values)
    assert (g.reason, g.iterations, g.converged) == ("cost_increase", 1, False)


# ------------------------------------------------------------------------------ errors


def test_error_messages():
    graph, values, _ = pose_graph(9)
    bad = NonlinearFactorGraph(list(graph) + [BetweenFactor(1, "ghost", values[1], sigma=1.0)])
    with pytest.raises(ValueError,
                       match=r"BetweenFactor.*refers to key 'ghost', which has no value"):
        LevenbergMarquardt().optimize(bad, values)
    with pytest.raises(ValueError, match="uses a key more than once"):
        LevenbergMarquardt().optimize(
            NonlinearFactorGraph([BetweenFactor(1, 1, values[1])]), values)
    with pytest.raises(ValueError, match="the graph has no factors"):
        LevenbergMarquardt().optimize(NonlinearFactorGraph(), values)
    with pytest.raises(TypeError, match=r"key 'm'.*not an optimisation variable type"):
        LevenbergMarquardt().optimize(
            NonlinearFactorGraph([CustomFactor(lambda x: x, ("m",))]), {"m": np.zeros(3)})
    with pytest.raises(ValueError, match="sqrt_info has shape"):
        LevenbergMarquardt().optimize(
            NonlinearFactorGraph([CustomFactor(log_x_residual, (1,), sqrt_info=np.eye(2))]), values)
    T = values[2]
    values_neg = Values({2: jaxlie.SE3.from_rotation_and_translation(
        T.rotation(), jnp.array([-1.0, 0, 0]))})
    nan_graph = NonlinearFactorGraph([CustomFactor(log_x_residual, (2,), name="LogX")])
    with pytest.raises(ValueError,
                       match=r"factor #0 \(LogX, keys \(2,\)\) has a non-finite residual"):
        LevenbergMarquardt().optimize(nan_graph, values_neg)


# ------------------------------------------------------------------- other variable types


def _ellipsoid_prior(E, P_ref, t_ref):
    """(P ⊟ P̄ in orthonormal SPD coordinates, t − t̄) ∈ R⁹."""
    return jnp.concatenate([spd.local_vec(P_ref, E.P), E.center - t_ref])


def _centre_in_camera(T, E, p):
    """The ellipsoid's centre seen from pose T (any landmark type): T⁻¹ t − p."""
    return T.inverse() @ spdslam.as_ellipsoid(E).center - p


def _quadric_prior(E, Q_ref):
    """Upper triangle of the normalised Q* minus Q̄*: blind to the scale of E.q."""
    iu = np.triu_indices(4)
    return (E.dual_quadric() - Q_ref)[iu]


@pytest.mark.parametrize("opt", [LevenbergMarquardt, GaussNewton])
def test_spd_ellipsoid_variable(gen, opt):
    """An Ellipsoid (SPD(3) × R³) variable beside a pose; the optimum is the prior's mean."""
    truth = gen.ellipsoid()
    T = gen.pose_random()
    graph = NonlinearFactorGraph([
        CustomFactor(_ellipsoid_prior, ("E",), args=(truth.P, truth.center), name="EllipsoidPrior"),
        CustomFactor(_centre_in_camera, ("x", "E"), args=(T.inverse() @ truth.center,)),
        PriorFactor("x", T, sigma=0.1),
    ])
    start = Ellipsoid.from_axes(gen.rotation(), truth.center + 0.5, truth.radii * 1.5)
    values = Values({"E": start, "x": T @ se3(np.full(6, 0.1))})
    res = opt(**TIGHT).optimize(graph, values)
    assert res.converged and res.final_cost < 1e-16, (res.reason, res.final_cost)
    est = res.values["E"]
    assert isinstance(est, Ellipsoid)
    np.testing.assert_allclose(np.asarray(est.P), np.asarray(truth.P), atol=1e-8)
    np.testing.assert_allclose(np.asarray(est.center), np.asarray(truth.center), atol=1e-8)


@pytest.mark.parametrize("opt", [LevenbergMarquardt, GaussNewton])
def test_full_quadric_variable_with_singular_scale(gen, opt):
    """EllipsoidFull: every residual ignores the overall scale of q, so H is singular along
    q; the damping (LM) or ridge (GN) handles it and ``regularized`` renormalises Q*."""
    truth = gen.ellipsoid()
    Q = truth.dual_quadric()
    graph = NonlinearFactorGraph([CustomFactor(_quadric_prior, ("Q",), args=(Q,), name="QuadricPrior")])
    start = EllipsoidFull.from_ellipsoid(
        Ellipsoid.from_axes(gen.rotation(), truth.center + 0.3, truth.radii * 1.3))
    start = EllipsoidFull(3.0 * start.q)  # not normalised: Q*₃₃ = −3
    res = opt(**TIGHT).optimize(graph, Values({"Q": start}))
    assert res.converged and res.final_cost < 1e-16, (res.reason, res.final_cost)
    est = res.values["Q"]
    assert isinstance(est, EllipsoidFull)
    np.testing.assert_allclose(np.asarray(est.matrix())[3, 3], -1.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(est.matrix()), np.asarray(Q), atol=1e-8)


def test_solver_linearisation_matches_tangent_jacobians():
    """The solver's grouped, vmapped Jacobians equal the per-factor tangent Jacobians that
    tests/test_factor_jacobians.py checks against central differences."""
    import jaxlie

    from spdslam import Camera, Ellipsoid, InverseBoxFactor, SemiInverseBoxFactor, look_at, project_box
    from spdslam.factors import Huber, tangent_jacobians
    from spdslam.solver import Problem

    cam = Camera(500.0, 500.0, 320.0, 240.0, 640.0, 480.0)
    truth = Ellipsoid.from_axes(np.eye(3), [0.1, 0.2, 0.3], [0.6, 0.4, 0.3])
    guess = Ellipsoid.from_axes(jaxlie.SO3.from_z_radians(0.3).as_matrix(), [0.2, 0.1, 0.4], [0.5, 0.5, 0.3])
    graph, values = NonlinearFactorGraph(), Values()
    for i, a in enumerate(np.linspace(0, 2, 4)):
        T = look_at([4 * np.cos(a), 4 * np.sin(a), 1.0], truth.center)
        values[("x", i)] = T
        box = np.asarray(project_box(truth, T, cam)) + 3.0
        graph.add(InverseBoxFactor(("x", i), "o", box, cam, sigma=2.0, robust=Huber(3.0)))
        graph.add(SemiInverseBoxFactor(("x", i), "o", box, cam, sigma=0.05))
    values["o"] = guess
    problem = Problem(graph, values)
    checked = 0
    for k in range(len(problem.gspecs)):
        r, J, fin = (np.asarray(a) for a in problem.group_terms(k))
        assert fin.all()
        members = [f for f in graph if f.kind == problem.gspecs[k].residual.__name__.replace("_residual", "")]
        for row, f in enumerate(members):
            vals = [values[key] for key in f.keys]
            r0, Js = tangent_jacobians(f.residual, vals, f.args)
            W = np.asarray(f.sqrt_info)
            rw = W @ np.asarray(r0)
            s = float(rw @ rw)
            sw = 1.0 if f.robust is None else float(np.sqrt(f.robust.weight(s)))
            np.testing.assert_allclose(r[row], sw * rw, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(J[row], sw * W @ np.concatenate([np.asarray(j) for j in Js], axis=1), rtol=1e-8, atol=1e-8)
            checked += 1
    assert checked == len(graph)
