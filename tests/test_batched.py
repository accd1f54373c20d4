"""``BatchedProblem``: a template problem solved for many data sets given as arrays.

Checked against ``optimize_batched`` and against a loop of unbatched dense LM / GN solves
(every landmark parameterisation with box factors, and an SE(3) pose graph with a fixed
pose), the lane refill (fewer lanes than problems), broadcasting of template arguments
and values, ``cost`` against ``graph.error``, and the input checks.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

import spdslam  # noqa: F401
from conftest import log_x_residual, se3
from spdslam import Ellipsoid, EllipsoidFull, EllipsoidRTS
from spdslam.factors import (
    BetweenFactor,
    CustomFactor,
    Huber,
    InverseBoxFactor,
    PriorFactor,
    SemiInverseBoxFactor,
)
from spdslam.synthetic import make_scenes
from spdslam.solver import (
    BatchedProblem,
    GaussNewton,
    IterationRecord,
    LevenbergMarquardt,
    NonlinearFactorGraph,
    Values,
    clear_caches,
)

B = 5
VIEWS = 6
CONVERT = {
    Ellipsoid: lambda e: e,
    EllipsoidRTS: jax.jit(jax.vmap(EllipsoidRTS.from_ellipsoid)),
    EllipsoidFull: jax.jit(jax.vmap(EllipsoidFull.from_ellipsoid)),
}


def _row(tree, b):
    return jax.tree.map(lambda a: np.asarray(a)[b], tree)


def box_problems(seed, landmark_cls, factor, n=B, views=VIEWS):
    """Scenes as arrays, and the same problems as lists of graphs and Values."""
    S = make_scenes(seed, n, "M", 60.0, n_views=views)
    init = jax.tree.map(np.asarray, CONVERT[landmark_cls](S.initial))
    poses = np.asarray(S.poses.wxyz_xyz)
    boxes = np.asarray(S.boxes)
    graphs, values = [], []
    for b in range(n):
        g, v = NonlinearFactorGraph(), Values()
        for i in range(views):
            v[("x", i)] = jaxlie.SE3(poses[b, i])
            g.add(factor(("x", i), "o", boxes[b, i], S.camera))
        v["o"] = _row(init, b)
        graphs.append(g)
        values.append(v)
    factor_args = {i: (boxes[:, i], S.camera) for i in range(views)}
    batched_values = {("x", i): jaxlie.SE3(poses[:, i]) for i in range(views)}
    batched_values["o"] = init
    fixed = [("x", i) for i in range(views)]
    return S, graphs, values, factor_args, batched_values, fixed


def landmark_array(value):
    e = spdslam.as_ellipsoid(value)
    return np.concatenate([np.ravel(e.P), np.ravel(e.center)])


def assert_matches_single(res, b, single, rtol=1e-7):
    assert res.reason[b] == single.reason
    assert int(res.iterations[b]) == single.iterations
    np.testing.assert_allclose(res.initial_cost[b], single.initial_cost, rtol=1e-12)
    np.testing.assert_allclose(res.final_cost[b], single.final_cost, rtol=rtol)
    its = single.iterations
    np.testing.assert_allclose(res.cost_history[b, :its], [r.cost for r in single.history],
                               rtol=rtol)
    np.testing.assert_array_equal(res.accepted_history[b, :its],
                                  [r.accepted for r in single.history])
    np.testing.assert_allclose(res.lambda_history[b, :its], [r.damping for r in single.history],
                               rtol=1e-6)
    assert np.all(np.isnan(res.cost_history[b, its:]))


# ------------------------------------------------------------------------------ box factors


@pytest.mark.parametrize("landmark_cls,factor", [
    (Ellipsoid, InverseBoxFactor),
    (EllipsoidRTS, SemiInverseBoxFactor),
    (EllipsoidFull, InverseBoxFactor),
])
def test_box_problems_match_looped_solves(landmark_cls, factor):
    S, graphs, values, fa, bv, fixed = box_problems(3, landmark_cls, factor)
    opts = dict(max_iterations=25, lambda_initial=1.0)
    lm = LevenbergMarquardt(**opts)
    bp = lm.batched(graphs[0], values[0], fixed=fixed)
    res = bp.solve(fa, bv, batch_size=2)  # 2 lanes for 5 problems: lanes are refilled
    assert len(res) == B and res.steps > 0
    assert set(res.values_batched) == {"o"} | set(fixed)
    old = lm.optimize_batched(graphs, values, fixed=fixed)
    np.testing.assert_array_equal(res.iterations, old.iterations)
    np.testing.assert_allclose(res.final_cost, old.final_cost, rtol=1e-8)
    for b in range(B):
        single = LevenbergMarquardt(linear_solver="dense", **opts).optimize(
            graphs[b], values[b], fixed=fixed)
        assert_matches_single(res, b, single)
        est = res.values[b]["o"]
        assert type(est) is landmark_cls
        np.testing.assert_allclose(landmark_array(est), landmark_array(single.values["o"]),
                                   rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(landmark_array(_row(res.values_batched["o"], b)),
                                   landmark_array(est), rtol=0, atol=0)
        np.testing.assert_allclose(landmark_array(old.values[b]["o"]), landmark_array(est),
                                   rtol=1e-6, atol=1e-8)
        # fixed poses are returned as given
        np.testing.assert_array_equal(np.asarray(res.values[b][("x", 2)].wxyz_xyz),
                                      np.asarray(values[b][("x", 2)].wxyz_xyz))
    # the number of lanes changes only the order of the work
    res_all = bp.solve(fa, bv, batch_size=B)
    np.testing.assert_array_equal(res_all.iterations, res.iterations)
    np.testing.assert_allclose(res_all.final_cost, res.final_cost, rtol=1e-9)


def test_cost_matches_graph_error():
    S, graphs, values, fa, bv, fixed = box_problems(4, Ellipsoid, SemiInverseBoxFactor)
    truth_values = dict(bv, o=jax.tree.map(np.asarray, S.truth))
    expected = [graphs[b].error(Values(dict(values[b], o=_row(S.truth, b)))) for b in range(B)]
    expected_init = [graphs[b].error(values[b]) for b in range(B)]
    bp = BatchedProblem(graphs[0], values[0], fixed=fixed, optimizer=LevenbergMarquardt(max_iterations=5))
    # before any solve: the dedicated cost program
    np.testing.assert_allclose(bp.cost(fa, truth_values), expected, rtol=1e-10)
    res = bp.solve(fa, bv)
    np.testing.assert_allclose(res.initial_cost, expected_init, rtol=1e-12)
    # after a solve with inputs of the same layout: the solver's program is reused
    np.testing.assert_allclose(bp.cost(fa, truth_values), expected, rtol=1e-10)
    np.testing.assert_allclose(bp.cost(fa, bv), expected_init, rtol=1e-12)
    # and at the solution: the final costs
    np.testing.assert_allclose(bp.cost(fa, res.values_batched), res.final_cost, rtol=1e-12)


def test_compile_ahead_then_solve_reuses_the_program():
    """``compile`` builds the solver for the inputs' shapes without running it (from threads
    at once, as the study does); ``solve`` then compiles nothing and gives the result of a
    problem solved without it."""
    from concurrent.futures import ThreadPoolExecutor

    runs = []
    for cls, factor in ((Ellipsoid, InverseBoxFactor), (EllipsoidRTS, SemiInverseBoxFactor)):
        _, graphs, values, fa, bv, fixed = box_problems(6, cls, factor)
        runs.append((LevenbergMarquardt(max_iterations=7, lambda_initial=1.0), graphs, values, fa, bv, fixed))
    clear_caches()
    problems = [lm.batched(g[0], v[0], fixed=fx) for lm, g, v, _, _, fx in runs]
    with ThreadPoolExecutor(2) as ex:
        built = list(ex.map(lambda k: problems[k].compile(runs[k][3], runs[k][4]), range(2)))
    assert all(t["compile"] > 0 for t in built)
    assert problems[0].compile(runs[0][3], runs[0][4]) == {"trace": 0.0, "compile": 0.0}
    results = [bp.solve(run[3], run[4]) for run, bp in zip(runs, problems)]
    assert all(r.timings["trace"] == r.timings["compile"] == 0.0 for r in results)
    clear_caches()
    for (lm, g, v, fa, bv, fx), res in zip(runs, results):
        again = lm.batched(g[0], v[0], fixed=fx).solve(fa, bv)
        assert again.timings["compile"] > 0
        np.testing.assert_array_equal(res.final_cost, again.final_cost)
        np.testing.assert_array_equal(res.iterations, again.iterations)


def test_template_arguments_and_values_broadcast():
    S, graphs, values, fa, bv, fixed = box_problems(5, Ellipsoid, InverseBoxFactor)
    bp = LevenbergMarquardt(max_iterations=10, lambda_initial=1.0).batched(
        graphs[0], values[0], fixed=fixed)
    # problem 0's data for every problem, given three ways: all from the template, with
    # shared (unbatched) leaves, and as explicitly repeated batches
    lm0 = _row(bv["o"], 0)
    rep = jax.tree.map(lambda a: np.repeat(np.asarray(a)[None], 3, axis=0), lm0)
    a = bp.solve(values={"o": rep})
    boxes0 = np.asarray(S.boxes)[0]
    b = bp.solve({i: (boxes0[i], S.camera) for i in range(VIEWS)}, {"o": rep})
    c = bp.solve([(np.repeat(boxes0[i][None], 3, 0), S.camera) for i in range(VIEWS)],
                 {"o": rep, ("x", 1): jaxlie.SE3(np.repeat(
                     np.asarray(S.poses.wxyz_xyz)[:1, 1], 3, 0))})
    single = LevenbergMarquardt(linear_solver="dense", max_iterations=10,
                                lambda_initial=1.0).optimize(graphs[0], values[0], fixed=fixed)
    for r in (a, b, c):
        assert len(r) == 3
        for k in range(3):
            assert_matches_single(r, k, single)
    # a camera given per problem (batched intrinsics) is the same as the shared one
    cams = spdslam.Camera(*(np.full(B, getattr(S.camera, f)) for f in
                            ("fx", "fy", "cx", "cy", "width", "height")))
    d = bp.solve({i: (np.asarray(S.boxes)[:, i], cams) for i in range(VIEWS)}, bv)
    e = bp.solve(fa, bv)
    np.testing.assert_array_equal(d.iterations, e.iterations)
    np.testing.assert_allclose(d.final_cost, e.final_cost, rtol=1e-10)


# ------------------------------------------------------------------------------ SE(3) poses


def pose_graph(seed, n_poses=6, robust=None):
    rng = np.random.default_rng(seed)
    truth = [se3(rng.normal(size=6))]
    for _ in range(1, n_poses):
        truth.append(truth[-1] @ se3(np.r_[rng.normal(size=3), 0.3 * rng.normal(size=3)]))
    graph, values = NonlinearFactorGraph(), Values()
    graph.add(PriorFactor(0, truth[0], sigma=0.01))
    graph.add(PriorFactor(1, truth[1], sigma=0.1))
    edges = [(i, i + 1) for i in range(n_poses - 1)] + [(0, n_poses - 2), (1, n_poses - 1)]
    for i, j in edges:
        z = truth[i].inverse() @ truth[j] @ se3(rng.normal(size=6) * 0.02)
        graph.add(BetweenFactor(i, j, z, sigma=0.05, robust=robust))
    for i, T in enumerate(truth):
        values[i] = T @ se3(rng.normal(size=6) * 0.2)
    return graph, values


def stack_problems(graphs, values):
    """factor_args and values of a list of same-layout problems, stacked."""
    fa = [jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]),
                       *[g[i].args for g in graphs]) for i in range(len(graphs[0]))]
    vals = {k: jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]),
                            *[v[k] for v in values]) for k in values[0]}
    return fa, vals


@pytest.mark.parametrize("method,n_poses,robust", [
    ("lm", 6, None), ("gn", 6, None), ("lm", 11, Huber(k=1.0))])
def test_pose_graph_with_a_fixed_pose_matches_looped_solves(method, n_poses, robust):
    """Pose 0 fixed: the prior on it has no free variable, the between factors touching it
    form their own sub-group; 11 poses (n = 60) assemble H from per-factor blocks."""
    problems = [pose_graph(40 + s, n_poses, robust) for s in range(4)]
    graphs = [p[0] for p in problems]
    values = [p[1] for p in problems]
    fa, vals = stack_problems(graphs, values)
    opts = dict(relative_tolerance=1e-12, gradient_tolerance=1e-12, max_iterations=30)
    Opt = GaussNewton if method == "gn" else LevenbergMarquardt
    bp = BatchedProblem(graphs[0], values[0], fixed=[0], optimizer=Opt(**opts))
    assert bp.n == 6 * (n_poses - 1)
    res = bp.solve(fa, vals, batch_size=3)
    for b in range(4):
        single = Opt(linear_solver="dense", **opts).optimize(graphs[b], values[b], fixed=[0])
        assert_matches_single(res, b, single, rtol=1e-6)
        for k in range(n_poses):
            np.testing.assert_allclose(np.asarray(res.values[b][k].as_matrix()),
                                       np.asarray(single.values[k].as_matrix()), atol=1e-7)
        np.testing.assert_array_equal(np.asarray(res.values[b][0].wxyz_xyz),
                                      np.asarray(values[b][0].wxyz_xyz))
    old = Opt(**opts).optimize_batched(graphs, values, fixed=[0])
    np.testing.assert_array_equal(old.iterations, res.iterations)
    np.testing.assert_allclose(old.final_cost, res.final_cost, rtol=1e-9)


# ------------------------------------------------------------------------------ errors


def test_input_errors():
    S, graphs, values, fa, bv, fixed = box_problems(6, Ellipsoid, InverseBoxFactor, n=3)
    bp = BatchedProblem(graphs[0], values[0], fixed=fixed)
    boxes = np.asarray(S.boxes)
    with pytest.raises(ValueError, match="nothing is batched"):
        bp.solve()
    with pytest.raises(ValueError, match=r"factor_args\[1\] leaf 0: shape \(3, 5\), expected "
                                         r"\(4,\) \(shared\) or \(B,\) \+ \(4,\)"):
        bp.solve({1: (np.zeros((3, 5)), S.camera)}, bv)
    with pytest.raises(ValueError, match=r"values\['o'\]: batch size 2, but factor_args\[0\] "
                                         r"has batch size 3"):
        bp.solve(fa, {"o": jax.tree.map(lambda a: a[:2], bv["o"])})
    with pytest.raises(ValueError, match=r"factor_args has 2 entries but the graph has 6"):
        bp.solve([None, None], bv)
    with pytest.raises(ValueError, match=r"factor_args: key 9 is not a factor index"):
        bp.solve({9: (boxes[:, 0], S.camera)}, bv)
    with pytest.raises(ValueError, match=r"factor_args\[0\]: structure"):
        bp.solve({0: (boxes[:, 0],)}, bv)
    with pytest.raises(ValueError, match=r"values: key 'ghost' is not a variable"):
        bp.solve(fa, {"ghost": bv["o"]})
    with pytest.raises(TypeError, match=r"values\['o'\]: expected Ellipsoid, got EllipsoidFull"):
        bp.solve(fa, {"o": jax.vmap(EllipsoidFull.from_ellipsoid)(bv["o"])})
    with pytest.raises(ValueError, match=r"values\['o'\]: leaf shapes"):
        bp.solve(fa, {"o": Ellipsoid(np.zeros((3, 3, 3, 1)), np.zeros((3, 3)))})
    with pytest.raises(ValueError, match="batch_size must be"):
        bp.solve(fa, bv, batch_size=0)
    with pytest.raises(TypeError, match="optimizer must be"):
        BatchedProblem(graphs[0], values[0], fixed=fixed, optimizer="gn")


def test_non_finite_initial_values_name_the_problem():
    T = se3(np.zeros(6))
    graph = NonlinearFactorGraph([CustomFactor(log_x_residual, ("a",), name="LogX"),
                                  PriorFactor("a", T, sigma=1.0)])
    good = jaxlie.SE3.from_rotation_and_translation(T.rotation(), jnp.array([1.0, 0, 0]))
    bp = BatchedProblem(graph, Values({"a": good}))
    xs = np.stack([np.asarray(good.wxyz_xyz)] * 3)
    xs[2, 4] = -1.0  # x translation of problem 2
    with pytest.raises(ValueError, match=r"factor #0 \(LogX, keys \('a',\)\) has a non-finite "
                                         r"residual at the initial values of problem 2"):
        bp.solve(values={"a": jaxlie.SE3(xs)})
    assert np.isnan(bp.cost(values={"a": jaxlie.SE3(xs)})[2])


# ------------------------------------------------------------------------------ every option of the rule


@pytest.mark.parametrize("options", [
    dict(lambda_schedule="fixed", lambda_initial=1e-3),
    dict(damping="identity", lambda_initial=1e-2),
    dict(damping="marquardt"),
    dict(lambda_schedule="fixed", damping="identity", lambda_factor=4.0),
])
def test_every_lm_option_runs_batched_in_lock_step(options):
    """The fixed λ schedule and identity damping are the one rule's, in both drivers."""
    S, graphs, values, fa, bv, fixed = box_problems(8, Ellipsoid, InverseBoxFactor, n=3)
    lm = LevenbergMarquardt(max_iterations=20, **options)
    res = lm.batched(graphs[0], values[0], fixed=fixed).solve(fa, bv)
    for b in range(3):
        single = LevenbergMarquardt(linear_solver="dense", max_iterations=20, **options).optimize(
            graphs[b], values[b], fixed=fixed)
        assert_matches_single(res, b, single)
        # (a ratio of two small differences: round-off shows at the 1e-6 level)
        np.testing.assert_allclose(res.gain_history[b, :single.iterations],
                                   [r.gain_ratio for r in single.history], rtol=1e-4)
    # the schedule is followed: λ ÷/× its factor after an accepted/rejected step
    if options.get("lambda_schedule") == "fixed":
        f = options.get("lambda_factor", 10.0)
        for rec, nxt in zip(res.history(0), res.history(0)[1:]):
            want = max(1e-10, rec.damping / f) if rec.accepted else rec.damping * f
            assert nxt.damping == pytest.approx(want, rel=1e-12)


def test_callback_and_verbose_in_the_batched_loop(capsys):
    """The callback sees every iteration of every problem (the same records as the host
    loop's) and stops the problem it returns True for; verbose prints each of them."""
    S, graphs, values, fa, bv, fixed = box_problems(9, Ellipsoid, InverseBoxFactor, n=3)
    seen: list[IterationRecord] = []

    def stop_problem_1_at_2(rec):
        seen.append(rec)
        return rec.problem == 1 and rec.iteration == 2

    lm = LevenbergMarquardt(max_iterations=15, callback=stop_problem_1_at_2, verbose=True)
    res = lm.batched(graphs[0], values[0], fixed=fixed).solve(fa, bv, batch_size=2)
    assert res.reason[1] == "callback" and res.iterations[1] == 2 and not res.converged[1]
    for b in (0, 2):
        single = LevenbergMarquardt(linear_solver="dense", max_iterations=15).optimize(
            graphs[b], values[b], fixed=fixed)
        assert_matches_single(res, b, single)
        mine = [r for r in seen if r.problem == b]
        assert [r.iteration for r in mine] == list(range(1, single.iterations + 1))
        np.testing.assert_allclose([r.cost for r in mine], [r.cost for r in single.history], rtol=1e-7)
        assert [r.accepted for r in mine] == [r.accepted for r in single.history]
        assert all(r.time >= 0 and np.isfinite(r.time) for r in mine)
    out = capsys.readouterr().out.splitlines()
    assert len(out) == len(seen) and all(line.startswith("problem ") for line in out)
    # without them, the program compiled for the options is not reused: no callback runs
    seen.clear()
    plain = LevenbergMarquardt(max_iterations=15).batched(graphs[0], values[0], fixed=fixed)
    again = plain.solve(fa, bv, batch_size=2)
    assert not seen and again.reason[1] != "callback"


def test_gauss_newton_is_the_same_rule_batched():
    S, graphs, values, fa, bv, fixed = box_problems(10, Ellipsoid, SemiInverseBoxFactor, n=3)
    res = GaussNewton(max_iterations=15).batched(graphs[0], values[0], fixed=fixed).solve(fa, bv)
    for b in range(3):
        single = GaussNewton(linear_solver="dense", max_iterations=15).optimize(
            graphs[b], values[b], fixed=fixed)
        assert_matches_single(res, b, single)


@pytest.mark.parametrize("param", [Ellipsoid, EllipsoidRTS])
def test_dogleg_runs_batched_in_lock_step(param):
    """Powell's dogleg is the one rule's too: the batched loop takes the host's steps."""
    from spdslam.solver import Dogleg

    S, graphs, values, fa, bv, fixed = box_problems(10, param, InverseBoxFactor, n=3)
    opt = Dogleg(max_iterations=25, trust_radius_initial=0.5)
    res = opt.batched(graphs[0], values[0], fixed=fixed).solve(fa, bv)
    for b in range(3):
        single = Dogleg(linear_solver="dense", max_iterations=25,
                        trust_radius_initial=0.5).optimize(graphs[b], values[b], fixed=fixed)
        assert_matches_single(res, b, single)
        steps = [r.step_norm for r in single.history]
        radii = [r.damping for r in single.history]
        assert all(r.radius for r in single.history) and all(r.radius for r in res.history(b))
        assert all(s <= d * (1 + 1e-9) for s, d in zip(steps, radii))  # inside the region
