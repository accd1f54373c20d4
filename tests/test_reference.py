"""The independent reference (SciPy TRF on the study's residuals) and our LM beside it."""

import numpy as np
import pytest

from spdslam.experiments import StudyConfig, compare_with_reference, reference_solve, run_study
from spdslam.experiments._reference import _Chart
from spdslam.experiments._study import all_scenes, box_sigma
from spdslam.geometry import dual_quadric_of


@pytest.mark.parametrize("param", ["F", "S", "O"])
def test_each_chart_starts_at_the_initial_landmark(param):
    cfg = StudyConfig(trials=3, noise=("M",), angles=(60.0,))
    scenes, _, _ = all_scenes(cfg)
    P0, t0 = np.asarray(scenes.initial.P[1]), np.asarray(scenes.initial.center[1])
    chart = _Chart(param, P0, t0)
    np.testing.assert_allclose(chart.quadrics(chart.x0)[0], dual_quadric_of(P0, t0), atol=1e-12)
    P, t = chart.ellipsoid(chart.x0)
    np.testing.assert_allclose(P, P0, atol=1e-9)
    np.testing.assert_allclose(t, t0, atol=1e-12)


@pytest.mark.parametrize("model", ["inv", "semi"])
def test_reference_has_our_cost_and_solves_noise_free_trials(model):
    """Same residuals: the reference's cost at the start is ours; from L starts (exact
    boxes) it reaches the truth's cost, 0, as our LM does."""
    cfg = StudyConfig(trials=6, noise=("L",), angles=(120.0,), params=("O",), models=(model,))
    res = run_study(cfg)
    scenes, _, _ = all_scenes(cfg)
    for param in ("F", "S", "O"):
        ref = reference_solve(model, param, scenes, box_sigma(model, cfg), workers=1)
        ours0 = np.array([r["initial_cost"] for r in res.rows])
        np.testing.assert_allclose(ref.initial_cost, ours0, rtol=1e-9)
        assert np.all(ref.cost <= 1e-6 * ours0), (param, ref.cost)
        assert np.all(ref.nfev <= 100)


def test_semi_inverse_spd_finds_the_optimum_at_high_noise():
    """The solver issue's headline trials (H, 60°): with Marquardt's damping and the gated
    semi-inverse factor our LM succeeded in 33 of 60 (the reference: 59)."""
    cfg = StudyConfig(trials=60, noise=("H",), angles=(60.0,), params=("O",), models=("semi",))
    res = run_study(cfg)
    assert np.mean([r["success"] for r in res.rows]) >= 0.9


@pytest.mark.slow
def test_ours_beside_the_reference_on_a_sample():
    """60 trials per cell at M and H, every structure: our success rate is not below the
    reference's by more than 0.03 plus two standard errors of the paired difference
    (√(discordant trials)/n, McNemar's); the 1000-trial figures are in docs/simulation.md."""
    cfg = StudyConfig(trials=60, noise=("M", "H"))
    out = compare_with_reference(cfg)
    for c in out["cells"]:
        assert c["max_initial_cost_mismatch"] < 1e-9
        n, discordant = c["trials"], c["only_ours"] + c["only_reference"]
        shortfall = (c["only_reference"] - c["only_ours"]) / n
        if c["param"] != "F":  # TRF on the raw entries of Q* is the weaker solver for F
            assert shortfall <= 0.03 + 2 * discordant**0.5 / n, c
