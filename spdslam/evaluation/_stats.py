"""Confidence intervals and paired comparisons for Monte Carlo studies.

- Wilson score interval for a binomial proportion k/n, without continuity correction
  (``scipy.stats.binomtest(k, n).proportion_ci(method="wilson")``):
  (p̂ + z²/2n ± z √(p̂(1−p̂)/n + z²/4n²)) / (1 + z²/n), with the bound 0 at k = 0 and 1 at k = n.
- Percentile bootstrap for a statistic of one sample (resampling with replacement,
  ``scipy.stats.bootstrap``: vectorised, the resamples drawn a block of index rows at a time
  from ``default_rng(seed)``).
- Paired comparison of two methods on the same trials: bootstrap interval of the mean
  difference, of the ratio of means, and the Wilcoxon signed-rank test.

The percentiles of SciPy's bootstrap distribution are taken here with ``np.quantile``
(linear), not read from its ``confidence_interval``, whose percentile step rounds differently
from one SciPy release to the next (``np.percentile`` at 100 q in 1.11, ``scipy.stats.quantile``
in 1.17) by ~1e-15, enough to print a bound of exactly 0 as −1.4e-17: so the intervals, and
the committed tables (docs/simulation), do not depend on the SciPy version. The ratio of
means also leaves out the resamples whose mean of b is 0, which SciPy's interval would not.
"""

from __future__ import annotations

import inspect
import warnings
from dataclasses import dataclass

import numpy as np

__all__ = ["Interval", "wilson", "bootstrap", "PairedComparison", "paired_comparison"]


@dataclass(frozen=True)
class Interval:
    estimate: float
    low: float
    high: float
    n: int

    def __str__(self) -> str:
        return f"{self.estimate:.3g} [{self.low:.3g}, {self.high:.3g}]"

    def as_dict(self) -> dict:
        return {"estimate": self.estimate, "low": self.low, "high": self.high, "n": self.n}


def wilson(successes: int, n: int, confidence: float = 0.95) -> Interval:
    """Wilson score interval for the success probability."""
    if n <= 0:
        return Interval(float("nan"), 0.0, 1.0, 0)
    if not 0 <= successes <= n:
        raise ValueError(f"successes must be in [0, {n}], got {successes}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    from scipy import stats  # imported where used: its import is slow, and a run needs none

    ci = stats.binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return Interval(successes / n, max(0.0, float(ci.low)), min(1.0, float(ci.high)), n)


#: Resampled indices drawn at a time (``scipy.stats.bootstrap``'s ``batch``): about 32 MB.
_RESAMPLE_BLOCK = 4_000_000
def _rng_keyword(bootstrap) -> str:
    """``scipy.stats.bootstrap``'s keyword for the generator (``random_state`` before SciPy 1.15)."""
    return "rng" if "rng" in inspect.signature(bootstrap).parameters else "random_state"


def _distribution(samples, statistic, resamples: int, seed: int, paired: bool = False) -> np.ndarray:
    """The bootstrap distribution (…, resamples) of ``statistic(*samples, axis=-1)``: the
    rows of indices drawn from ``default_rng(seed)`` as one (resamples, n) draw, in blocks of
    at most ``_RESAMPLE_BLOCK`` entries (``paired``: the same rows for every sample). SciPy
    needs two observations; every resample of one is the sample itself."""
    from scipy import stats

    n = samples[0].size
    if n == 1:
        return statistic(*(x[np.zeros((resamples, 1), int)] for x in samples), axis=-1)
    with warnings.catch_warnings():
        # SciPy's interval and standard error, computed beside the distribution, are not used
        # here: not their warnings either (a NaN statistic; the spread of a single resample)
        warnings.filterwarnings("ignore", category=stats.DegenerateDataWarning)
        if resamples < 2:
            warnings.filterwarnings("ignore", category=RuntimeWarning)
        res = stats.bootstrap(samples, statistic, n_resamples=resamples, batch=max(1, _RESAMPLE_BLOCK // n),
                              vectorized=True, paired=paired, method="percentile",
                              **{_rng_keyword(stats.bootstrap): np.random.default_rng(seed)})
    return np.asarray(res.bootstrap_distribution)


def bootstrap(
    x,
    statistic=np.mean,
    confidence: float = 0.95,
    resamples: int = 2000,
    seed: int = 0,
) -> Interval:
    """Percentile bootstrap interval of ``statistic`` (called with ``axis=-1``, along each
    resample).

    NaN entries are dropped first; an empty sample gives a NaN interval.
    """
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return Interval(float("nan"), float("nan"), float("nan"), 0)
    boot = _distribution((x,), statistic, resamples, seed)
    a = (1 - confidence) / 2
    lo, hi = np.quantile(boot, [a, 1 - a])
    return Interval(float(statistic(x)), float(lo), float(hi), int(x.size))


@dataclass(frozen=True)
class PairedComparison:
    """Method A against method B on the same trials (pairs where both are finite)."""

    n: int
    mean_a: float
    mean_b: float
    mean_difference: Interval  # mean(a − b)
    ratio_of_means: Interval  # mean(a) / mean(b)
    wilcoxon_p: float  # two-sided signed-rank test of a − b
    fraction_a_less: float  # share of pairs with a < b
    fraction_equal: float

    def as_dict(self) -> dict:
        return {
            "n": self.n,
            "mean_a": self.mean_a,
            "mean_b": self.mean_b,
            "mean_difference": self.mean_difference.as_dict(),
            "ratio_of_means": self.ratio_of_means.as_dict(),
            "wilcoxon_p": self.wilcoxon_p,
            "fraction_a_less": self.fraction_a_less,
            "fraction_equal": self.fraction_equal,
        }


def _means(a, b, axis=-1):
    """(mean of a, mean of b) along ``axis``: the paired bootstrap's statistic."""
    return np.stack([a.mean(axis=axis), b.mean(axis=axis)])


def paired_comparison(a, b, confidence: float = 0.95, resamples: int = 4000, seed: int = 0) -> PairedComparison:
    """Paired bootstrap (same resampled trials for both methods) and Wilcoxon test."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"paired samples need equal shapes, got {a.shape} and {b.shape}")
    keep = np.isfinite(a) & np.isfinite(b)
    a, b = a[keep], b[keep]
    n = int(a.size)
    nan = Interval(float("nan"), float("nan"), float("nan"), n)
    if n == 0:
        return PairedComparison(0, np.nan, np.nan, nan, nan, np.nan, np.nan, np.nan)
    ma, mb = _distribution((a, b), _means, resamples, seed, paired=True)
    q = [(1 - confidence) / 2, (1 + confidence) / 2]
    d = a - b
    lo, hi = map(float, np.quantile(ma - mb, q))
    diff = Interval(float(d.mean()), lo, hi, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = ma / mb  # a resample whose mean of b is 0 has no ratio: left out
        r = r[np.isfinite(r)]
        lo, hi = map(float, np.quantile(r, q)) if r.size else (np.nan, np.nan)
        ratio = Interval(float(a.mean() / b.mean()), lo, hi, n)
    if np.all(d == 0):
        p = 1.0
    else:
        from scipy import stats

        p = float(stats.wilcoxon(a, b, zero_method="wilcox").pvalue)
    return PairedComparison(
        n, float(a.mean()), float(b.mean()), diff, ratio, p, float(np.mean(d < 0)), float(np.mean(d == 0))
    )
