"""Confidence intervals: known values and coverage."""

import numpy as np
import pytest

from spdslam.evaluation import bootstrap, paired_comparison, wilson


def test_wilson_known_values():
    # Textbook example: 81 successes in 263 trials, 95 %: [0.2553, 0.3662] (Wilson 1927 form)
    iv = wilson(81, 263)
    assert iv.low == pytest.approx(0.2553, abs=5e-4) and iv.high == pytest.approx(0.3662, abs=5e-4)
    all_ok = wilson(24, 24)
    assert all_ok.high == 1.0 and 0.85 < all_ok.low < 0.87  # 24/24: lower bound 0.862
    assert wilson(0, 24).low == 0.0
    with pytest.raises(ValueError):
        wilson(5, 4)
    z = 1.959963984540054  # the closed form (module docstring), no continuity correction
    for k, n in [(0, 7), (1, 7), (3, 7), (7, 7), (81, 263)]:
        p = k / n
        mid, half = p + z * z / (2 * n), z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
        iv = wilson(k, n)
        np.testing.assert_allclose([iv.low, iv.high], [0.0 if k == 0 else (mid - half) / (1 + z * z / n),
                                                       1.0 if k == n else (mid + half) / (1 + z * z / n)],
                                   rtol=1e-12)


def test_wilson_coverage():
    rng = np.random.default_rng(0)
    p, n = 0.8, 50
    k = rng.binomial(n, p, size=4000)
    cover = np.mean([wilson(int(x), n).low <= p <= wilson(int(x), n).high for x in k])
    assert 0.93 < cover < 0.975


def test_bootstrap_mean_coverage_and_nan():
    rng = np.random.default_rng(1)
    hits = 0
    for i in range(300):
        x = rng.exponential(2.0, size=80)
        iv = bootstrap(x, resamples=500, seed=i)
        hits += iv.low <= 2.0 <= iv.high
    assert 0.88 < hits / 300 < 0.99
    iv = bootstrap([1.0, np.nan, 3.0])
    assert iv.n == 2 and iv.estimate == 2.0
    assert np.isnan(bootstrap([np.nan]).estimate)
    one = bootstrap([np.nan, 4.0])  # one value: every resample is the sample
    assert (one.estimate, one.low, one.high, one.n) == (4.0, 4.0, 4.0, 1)


def test_paired_comparison_detects_a_shift():
    rng = np.random.default_rng(2)
    b = rng.integers(5, 30, size=200).astype(float)
    a = b - rng.integers(0, 4, size=200)  # A never slower, 1.5 iterations faster on average
    c = paired_comparison(a, b)
    assert c.mean_difference.high < 0 and c.wilcoxon_p < 1e-6
    assert c.ratio_of_means.high < 1.0 and c.fraction_a_less > 0.5
    same = paired_comparison(b, b)
    assert same.wilcoxon_p == 1.0 and same.fraction_equal == 1.0
    with pytest.raises(ValueError):
        paired_comparison([1.0], [1.0, 2.0])
