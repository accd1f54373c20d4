"""One object, 10 noise-free views, the paper's medium initial noise (20°, 1 m, 30 %):
LM converges to the truth in every parameterisation.

The initial landmark is random, so this is a rate: the paper itself reports 23-24 of 24 at
this level. Failures of SPD(3) seen here are a collapsing axis (a flat-disc local minimum
the log-coordinates descend into); the simulation study (docs/simulation.md) measures it.
"""

from __future__ import annotations

import numpy as np
import pytest

import spdslam
from spdslam import spd
from spdslam.factors import InverseBoxFactor
from spdslam.synthetic import make_scene
from spdslam.solver import LevenbergMarquardt, NonlinearFactorGraph, Values

SEEDS = range(20)
MIN_RATE = 0.9


def solve(seed: int, param: str):
    scene = make_scene(seed, noise="M", angle_range_deg=120.0, n_views=10, box_noise=False)
    graph, values = NonlinearFactorGraph(), Values()
    for i, (T, box) in enumerate(zip(scene.poses, scene.boxes)):
        values[("x", i)] = T
        graph.add(InverseBoxFactor(("x", i), "object", box, scene.camera))
    values["object"] = {
        "spd": scene.initial,
        "rts": scene.initial.to_rts(),
        "full": scene.initial.to_full(),
    }[param]
    # Object-level problems start far from the optimum: begin with stronger damping
    # (λ₀ = 1, relative to diag H) than the solver's general default.
    lm = LevenbergMarquardt(max_iterations=200, lambda_initial=1.0)
    result = lm.optimize(graph, values, fixed=[("x", i) for i in range(len(scene.poses))])
    return scene, result


@pytest.mark.parametrize("param", ["spd", "rts", "full"])
def test_single_object_converges_from_medium_noise(param):
    failures = []
    for seed in SEEDS:
        scene, result = solve(seed, param)
        est = spdslam.as_ellipsoid(result.values["object"])
        shape_err = float(spd.distance(est.P, scene.truth.P))
        centre_err = float(np.linalg.norm(np.asarray(est.center - scene.truth.center)))
        assert type(result.values["object"]) is type(
            {"spd": scene.initial, "rts": scene.initial.to_rts(), "full": scene.initial.to_full()}[param]
        )
        assert np.all(np.isfinite(np.asarray(est.P)))
        ok = (
            result.converged
            and result.final_cost < 1e-8 * max(1.0, result.initial_cost)
            and shape_err < 1e-4
            and centre_err < 1e-5
        )
        if not ok:
            failures.append((seed, result.reason, result.final_cost, np.round(est.radii, 3).tolist()))
    rate = 1 - len(failures) / len(SEEDS)
    assert rate >= MIN_RATE, f"{param}: converged in {rate:.0%} of trials; failures {failures}"
