"""Solver options added for performance work: CHOLMOD factorisation mode and fill-reducing
ordering, the fixed (gtsam-style) λ schedule and identity damping. Each must reach the same
optimum as the defaults; the schedule must follow its rule; bad values raise clearly."""

from __future__ import annotations

import numpy as np
import pytest
from test_solver import TIGHT, pose_graph, pose_matrices

from spdslam.solver import HAVE_CHOLMOD, HAVE_CVXOPT, LevenbergMarquardt, marginal_covariances

needs_cholmod = pytest.mark.skipif(not HAVE_CHOLMOD, reason="scikit-sparse is not installed")
needs_cvxopt = pytest.mark.skipif(not HAVE_CVXOPT, reason="cvxopt is not installed")


@needs_cholmod
@pytest.mark.parametrize("mode,ordering", [("simplicial", "amd"), ("supernodal", "metis"),
                                           ("auto", "natural"), ("simplicial", "nesdis")])
def test_cholmod_modes_and_orderings_match_dense(mode, ordering):
    graph, values, _ = pose_graph(3)
    dense = LevenbergMarquardt(linear_solver="dense", **TIGHT).optimize(graph, values)
    res = LevenbergMarquardt(linear_solver="cholmod", cholmod_mode=mode, cholmod_ordering=ordering,
                             **TIGHT).optimize(graph, values)
    assert res.iterations == dense.iterations
    np.testing.assert_allclose(res.final_cost, dense.final_cost, rtol=1e-10)
    np.testing.assert_allclose(pose_matrices(res.values), pose_matrices(dense.values), atol=1e-9)


@needs_cvxopt
@pytest.mark.parametrize("ordering", ["default", "amd", "natural"])
def test_cvxopt_orderings_match_dense(ordering):
    graph, values, _ = pose_graph(3)
    dense = LevenbergMarquardt(linear_solver="dense", **TIGHT).optimize(graph, values)
    res = LevenbergMarquardt(linear_solver="cvxopt", cholmod_ordering=ordering,
                             **TIGHT).optimize(graph, values)
    assert res.linear_solver == "cvxopt" and res.iterations == dense.iterations
    np.testing.assert_allclose(res.final_cost, dense.final_cost, rtol=1e-10)
    np.testing.assert_allclose(pose_matrices(res.values), pose_matrices(dense.values), atol=1e-9)


def _spd_lower(n, seed, density=0.05):
    """(lower-triangle data, CSC pattern) of a random sparse SPD matrix, and the matrix."""
    import scipy.sparse as sps

    rng = np.random.default_rng(seed)
    B = sps.random(n, n, density=density, random_state=rng, format="csc")
    A = (B @ B.T + n * sps.eye(n)).tocsc()
    L = sps.tril(A).tocsc()
    L.sort_indices()
    diag = np.array([L.indptr[j] for j in range(n)])  # the diagonal is first in each column
    assert np.all(L.indices[diag] == np.arange(n))
    pattern = dict(indices=L.indices, indptr=L.indptr, diag=diag, nnz=L.nnz)
    return L.data.copy(), pattern, A.toarray()


@needs_cvxopt
def test_cvxopt_solver_any_storage_order_many_rhs_and_indefinite():
    from spdslam.solver._linear import make_linear_solver

    n = 60
    data, pattern, A = _spd_lower(n, 0)
    b = np.random.default_rng(1).standard_normal((n, 3))
    s = make_linear_solver("cvxopt", pattern, n)
    np.testing.assert_allclose(A @ s.solve(data, b), b, atol=1e-10)
    np.testing.assert_allclose(A @ s.solve(data, b[:, 0]), b[:, 0], atol=1e-10)
    # the same matrix given with the entries of each column in reverse order
    ip = pattern["indptr"]
    perm = np.concatenate([np.arange(ip[j], ip[j + 1])[::-1] for j in range(n)])
    rev = dict(pattern, indices=pattern["indices"][perm],
               diag=np.array([ip[j + 1] - 1 for j in range(n)]))
    s2 = make_linear_solver("cvxopt", rev, n)
    assert s2._order is not None  # cvxopt sorts: the values are written in its order
    np.testing.assert_allclose(s2.solve(data[perm], b), s.solve(data, b), atol=1e-12)
    # refactorising on the same analysis with other values
    np.testing.assert_allclose((2 * A) @ s.solve(2 * data, b), b, atol=1e-10)
    bad = data.copy()
    bad[pattern["diag"][7]] = -1.0
    assert s.solve(bad, b) is None  # not positive definite
    assert s.solve(data, b) is not None  # and the next solve works again


@needs_cvxopt
def test_cvxopt_rejects_what_it_cannot_do():
    graph, values, _ = pose_graph(3)
    for mode, ordering, match in (("simplicial", "default", "cholmod_mode 'simplicial' needs "
                                   "scikit-sparse"),
                                  ("supernodal", "metis", "cholmod_ordering 'metis' needs "
                                   "scikit-sparse")):
        with pytest.raises(ValueError, match=match):
            LevenbergMarquardt(linear_solver="cvxopt", cholmod_mode=mode,
                               cholmod_ordering=ordering).optimize(graph, values)


@needs_cvxopt
def test_marginals_through_cvxopt_match_dense():
    graph, values, _ = pose_graph(5)
    keys = list(values.keys())[:3]
    dense = marginal_covariances(graph, values, keys, linear_solver="dense")
    cvx = marginal_covariances(graph, values, keys, linear_solver="cvxopt")
    for k in keys:
        np.testing.assert_allclose(cvx[k], dense[k], rtol=1e-9, atol=1e-14)


def _libgomp_loaded() -> bool:
    try:
        with open("/proc/self/maps") as f:
            return "libgomp" in f.read()
    except OSError:
        return False


@needs_cholmod
def test_cholmod_threads_are_scoped_and_restored():
    from spdslam.solver import _linear

    if _libgomp_loaded():  # CHOLMOD linked against GNU OpenMP: the control must be found
        assert _linear.HAVE_OPENMP_CONTROL
    if not (_linear.HAVE_OPENMP_CONTROL and _linear.HAVE_BLAS_CONTROL):
        pytest.skip("CHOLMOD is not linked against GNU OpenMP and OpenBLAS")
    gomp, blas = _linear._gomp, _linear._openblas
    levels, threads = gomp.omp_get_max_active_levels(), blas.openblas_get_num_threads()
    assert levels > 0
    with _linear.cholmod_threads(openmp=False, blas=1):
        assert gomp.omp_get_max_active_levels() == 0
        assert blas.openblas_get_num_threads() == 1
    assert (gomp.omp_get_max_active_levels(), blas.openblas_get_num_threads()) == (levels, threads)
    with _linear.cholmod_threads(openmp=True, blas=None):
        assert (gomp.omp_get_max_active_levels(), blas.openblas_get_num_threads()) == (
            levels, threads)
    with pytest.raises(RuntimeError), _linear.cholmod_threads():
        raise RuntimeError("inside")
    assert (gomp.omp_get_max_active_levels(), blas.openblas_get_num_threads()) == (levels, threads)


@needs_cholmod
def test_cholmod_thread_options_give_the_same_solution():
    graph, values, _ = pose_graph(40, init_noise=0.3)
    runs = [LevenbergMarquardt(linear_solver="cholmod", cholmod_openmp=omp,
                               cholmod_blas_threads=blas, **TIGHT).optimize(graph, values)
            for omp, blas in ((False, 1), (True, None))]
    assert runs[0].iterations == runs[1].iterations
    assert runs[0].final_cost == runs[1].final_cost
    np.testing.assert_array_equal(pose_matrices(runs[0].values), pose_matrices(runs[1].values))


def test_bad_options_raise():
    graph, values, _ = pose_graph(3)
    with pytest.raises(ValueError, match="cholmod_ordering must be one of"):
        LevenbergMarquardt(cholmod_ordering="rcm").optimize(graph, values)
    with pytest.raises(ValueError, match="cholmod_mode must be one of"):
        LevenbergMarquardt(cholmod_mode="fast").optimize(graph, values)
    if HAVE_CHOLMOD:
        with pytest.raises(ValueError, match="cholmod_blas_threads must be >= 1"):
            LevenbergMarquardt(linear_solver="cholmod", cholmod_blas_threads=0
                               ).optimize(graph, values)
    with pytest.raises(ValueError, match="lambda_schedule must be"):
        LevenbergMarquardt(lambda_schedule="gtsam").optimize(graph, values)
    with pytest.raises(ValueError, match="lambda_factor must be > 1"):
        LevenbergMarquardt(lambda_schedule="fixed", lambda_factor=1.0).optimize(graph, values)


@pytest.mark.parametrize("damping", ["isotropic", "marquardt", "identity"])
def test_fixed_schedule_follows_its_rule_and_reaches_the_optimum(damping):
    graph, values, _ = pose_graph(4, init_noise=0.5)
    ref = LevenbergMarquardt(linear_solver="dense", **TIGHT).optimize(graph, values)
    res = LevenbergMarquardt(linear_solver="dense", lambda_schedule="fixed", lambda_factor=10.0,
                             lambda_initial=1e-5, damping=damping,
                             **TIGHT).optimize(graph, values)
    assert res.converged, res.reason
    np.testing.assert_allclose(res.final_cost, ref.final_cost, rtol=1e-9)
    np.testing.assert_allclose(pose_matrices(res.values), pose_matrices(ref.values), atol=1e-7)
    h = res.history
    assert h[0].damping == pytest.approx(1e-5)
    for a, b in zip(h, h[1:]):
        expected = max(1e-10, a.damping / 10) if a.accepted else a.damping * 10
        assert b.damping == pytest.approx(expected, rel=1e-12)
    # the Nielsen rule changes λ by other factors, so the two histories differ
    assert [r.damping for r in ref.history][:3] != [r.damping for r in h][:3]


def test_isotropic_damping_is_the_largest_curvature_of_each_block():
    from spdslam.solver._lm import StepRule, damping

    h = dict(min_diagonal=1e-6, max_diagonal=1e32)
    diag = np.array([1.0, 4.0, 2.0, 0.0, 9.0, 3.0, 5.0, 1e-9, 7.0, 8.0])
    blocks = ((2, (3, 2)), (0, (4,)))  # two variables of a (3, 2)-block type, none of another
    D = damping(diag, StepRule(damping="isotropic"), h, np, blocks)
    np.testing.assert_array_equal(D, [4, 4, 4, 9, 9, 5, 5, 5, 8, 8])
    np.testing.assert_array_equal(damping(diag, StepRule(damping="identity"), h, np), 1.0)
    np.testing.assert_array_equal(damping(diag, StepRule(damping="marquardt"), h, np),
                                  np.clip(diag, 1e-6, 1e32))
    with pytest.raises(ValueError, match="damping must be one of"):
        LevenbergMarquardt(damping="diag")


def test_nielsens_rule_shrinks_lambda_by_a_third_at_most_and_silently_for_any_gain():
    """An accepted step whose model predicted almost no decrease has a huge gain ratio; λ
    then shrinks by the rule's limit, 1/3, without an overflow warning (a long online run
    printed one)."""
    import warnings

    from spdslam.solver import LevenbergMarquardtParams
    from spdslam.solver._lm import StepRule, decide, hyper

    h = hyper(LevenbergMarquardtParams())
    for pred, shrink in ((1.0, 1.0 - (2.0 * 0.5 - 1.0) ** 3), (1e-300, 1.0 / 3.0), (0.25, 1.0 / 3.0)):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            accepted, gain, lam, _, _ = decide(StepRule(), h, 1.0, 0.5, True, True, pred, 1.0, 1.0, 2.0, 2.0, np)
        assert accepted
        assert lam == pytest.approx(2.0 * shrink, rel=1e-15)


def test_dogleg_step_follows_the_dogleg_path():
    from spdslam.solver._lm import dogleg_step

    H = np.diag([4.0, 1.0])
    g = np.array([-4.0, -2.0])
    gn = -np.linalg.solve(H, g)  # (1, 2), ‖·‖ = √5
    np.testing.assert_allclose(dogleg_step(gn, g, H @ g, 3.0, np), gn)  # fits: GN itself
    alpha = (g @ g) / (g @ H @ g)  # Cauchy point −αg, ‖·‖ = α‖g‖ ≈ 0.83
    tiny = dogleg_step(gn, g, H @ g, 0.1, np)  # Cauchy point outside: along −g
    np.testing.assert_allclose(tiny, -0.1 * g / np.linalg.norm(g))
    mid = dogleg_step(gn, g, H @ g, 1.5, np)  # on the segment Cauchy → GN, on the boundary
    assert np.linalg.norm(mid) == pytest.approx(1.5)
    d_sd = -alpha * g
    t = (mid - d_sd) / (gn - d_sd)
    assert t[0] == pytest.approx(t[1]) and 0 < t[0] < 1


def test_dogleg_reaches_the_optimum_and_checks_its_radius():
    from spdslam.solver import Dogleg

    graph, values, _ = pose_graph(4, init_noise=0.5)
    ref = LevenbergMarquardt(linear_solver="dense", **TIGHT).optimize(graph, values)
    res = Dogleg(linear_solver="dense", **TIGHT).optimize(graph, values)
    assert res.converged, res.reason
    np.testing.assert_allclose(res.final_cost, ref.final_cost, rtol=1e-9)
    np.testing.assert_allclose(pose_matrices(res.values), pose_matrices(ref.values), atol=1e-7)
    assert res.history[0].damping == 1.0
    # the records' damping is Δ, marked and printed as the radius (LM's is λ)
    assert all(r.radius for r in res.history) and not any(r.radius for r in ref.history)
    assert " radius 1.00e+00 " in res.history[0].line() and " lambda " in ref.history[0].line()
    for a, b in zip(res.history, res.history[1:]):  # Δ only shrinks after a poor step
        if b.damping < a.damping:
            assert a.gain_ratio < 0.25
    with pytest.raises(ValueError, match="trust_radius_initial"):
        Dogleg(trust_radius_initial=0.0)


@pytest.mark.parametrize("linear_solver", ["dense", pytest.param("cholmod", marks=needs_cholmod)])
def test_a_result_gives_the_marginals_and_costs_of_its_final_values(linear_solver):
    """``OptimizationResult.marginal_covariances`` / ``cost_by_kind`` reuse the run's last
    linearisation and problem: the same numbers, to the bit, as laying the graph out again
    at the final values (``marginal_covariances``, one problem per kind)."""
    from spdslam.solver import NonlinearFactorGraph

    graph, values, _ = pose_graph(5)
    fixed = [list(values.keys())[0]]
    res = LevenbergMarquardt(linear_solver=linear_solver, **TIGHT).optimize(graph, values, fixed=fixed)
    keys = list(values.keys())[1:4]
    again = marginal_covariances(graph, res.values, keys, linear_solver=linear_solver, fixed=fixed)
    reused = res.marginal_covariances(keys)
    for k in keys:
        np.testing.assert_array_equal(reused[k], again[k])
    kinds = {}
    for f in graph:
        kinds.setdefault(f.kind, []).append(f)
    each = {k: float(NonlinearFactorGraph(fs).error(res.values)) for k, fs in kinds.items()}
    assert res.cost_by_kind() == each and list(res.cost_by_kind()) == list(each)
    assert abs(sum(each.values()) - res.final_cost) <= 1e-9 * res.final_cost
    with pytest.raises(ValueError, match="not a free variable"):
        res.marginal_covariances(fixed)
