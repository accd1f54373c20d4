"""Confidence intervals and paired comparisons for Monte Carlo studies.

- Wilson score interval for a binomial proportion k/n:
  (p̂ + z²/2n ± z √(p̂(1−p̂)/n + z²/4n²)) / (1 + z²/n).
- Percentile bootstrap for a statistic of one sample (resampling with replacement,
  vectorised: all resamples drawn as one index array).
- Paired comparison of two methods on the same trials: bootstrap interval of the mean
  difference, of the ratio of means, and the Wilcoxon signed-rank test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats as _st

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


def _z(confidence: float) -> float:
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    return float(_st.norm.ppf(0.5 + confidence / 2))


def wilson(successes: int, n: int, confidence: float = 0.95) -> Interval:
    """Wilson score interval for the success probability."""
    if n <= 0:
        return Interval(float("nan"), 0.0, 1.0, 0)
    if not 0 <= successes <= n:
        raise ValueError(f"successes must be in [0, {n}], got {successes}")
    z = _z(confidence)
    p = successes / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    low = 0.0 if successes == 0 else max(0.0, mid - half)
    high = 1.0 if successes == n else min(1.0, mid + half)
    return Interval(p, low, high, n)


#: Resampled indices drawn at a time (``_resamples``): about 32 MB.
_RESAMPLE_BLOCK = 4_000_000


def _resamples(n: int, resamples: int, seed: int):
    """The bootstrap's index arrays (k, n), ``resamples`` rows in all, in blocks of at most
    ``_RESAMPLE_BLOCK`` entries: the same indices as one (resamples, n) draw from
    ``default_rng(seed)``, in bounded memory."""
    rng = np.random.default_rng(seed)
    rows = max(1, _RESAMPLE_BLOCK // max(n, 1))
    for lo in range(0, resamples, rows):
        yield rng.integers(0, n, size=(min(rows, resamples - lo), n))


def bootstrap(
    x,
    statistic=np.mean,
    confidence: float = 0.95,
    resamples: int = 2000,
    seed: int = 0,
) -> Interval:
    """Percentile bootstrap interval of ``statistic`` (applied along axis 1 of the resamples).

    NaN entries are dropped first; an empty sample gives a NaN interval.
    """
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return Interval(float("nan"), float("nan"), float("nan"), 0)
    boot = np.concatenate([statistic(x[idx], axis=1) for idx in _resamples(x.size, resamples, seed)])
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
    means = [(a[idx].mean(axis=1), b[idx].mean(axis=1)) for idx in _resamples(n, resamples, seed)]
    ma, mb = (np.concatenate(m) for m in zip(*means))
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
        p = float(_st.wilcoxon(a, b, zero_method="wilcox").pvalue)
    return PairedComparison(
        n, float(a.mean()), float(b.mean()), diff, ratio, p, float(np.mean(d < 0)), float(np.mean(d == 0))
    )
