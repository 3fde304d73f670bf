"""Statistics over seeds that papers report: mean, median, IQM and bootstrap intervals."""

from __future__ import annotations

import numpy as np


def iqm(values: np.ndarray) -> float:
    """Interquartile mean: the mean of the middle 50% (Agarwal et al. 2021).

    Uses fractional weights at the 25th/75th percentile boundaries, so it is defined for any
    number of values (for 1-3 values it weighs them like the 25-75% trimmed mean would).
    """
    x = np.sort(np.asarray(values, np.float64).ravel())
    n = x.size
    if n == 0:
        return float("nan")
    # Each value covers [i/n, (i+1)/n) of the distribution; keep the part inside [0.25, 0.75].
    lower = np.arange(n) / n
    upper = lower + 1.0 / n
    weight = np.clip(np.minimum(upper, 0.75) - np.maximum(lower, 0.25), 0.0, None)
    return float(np.sum(weight * x) / np.sum(weight))


def bootstrap_ci(
    values: np.ndarray,
    statistic=np.mean,
    confidence: float = 0.95,
    resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap confidence interval of ``statistic`` over ``values`` (a 1-D array)."""
    x = np.asarray(values, np.float64).ravel()
    if x.size == 0:
        return float("nan"), float("nan")
    if x.size == 1:
        return float(x[0]), float(x[0])
    rng = np.random.default_rng(seed)
    samples = x[rng.integers(0, x.size, size=(resamples, x.size))]
    stats = np.array([statistic(row) for row in samples])
    alpha = (1.0 - confidence) / 2.0
    return float(np.quantile(stats, alpha)), float(np.quantile(stats, 1.0 - alpha))


#: The fewest values whose percentile bootstrap 95% interval of the mean (:func:`bootstrap_ci`,
#: 2,000 resamples from seed 0) is narrower than their range: with 3 or fewer, at least 63 of
#: those resamples (about 74 expected: (1/3)**3 of them) are all the smallest value, and as
#: many all the largest, more than the 50 in each 2.5% tail, so the interval is [min, max] (to
#: the float rounding of a mean).
CI_NARROWER_FROM = 4


def interval_name(count: int) -> str:
    """What :func:`summary`'s interval of ``count`` values is, for a label: ``"95% CI"``, or
    ``"range"`` where it is their [min, max] (:data:`CI_NARROWER_FROM`)."""
    return "95% CI" if count >= CI_NARROWER_FROM else "range"


def summary(values: np.ndarray) -> dict[str, float]:
    """Mean, median, IQM, standard deviation (of the values themselves, ``ddof=0``: NumPy's
    ``std``; not the sample estimate) and 95% bootstrap CI of the mean."""
    x = np.asarray(values, np.float64).ravel()
    low, high = bootstrap_ci(x)
    return {
        "mean": float(x.mean()),
        "median": float(np.median(x)),
        "iqm": iqm(x),
        "std": float(x.std()),
        "ci95_low": low,
        "ci95_high": high,
    }


def return_stats(returns: np.ndarray) -> dict[str, float]:
    """Mean, std, min and max of one member's episode returns."""
    returns = np.asarray(returns, np.float64)
    return {
        "eval_return_mean": float(returns.mean()),
        "eval_return_std": float(returns.std()),
        "eval_return_min": float(returns.min()),
        "eval_return_max": float(returns.max()),
    }


def population_stats(returns: np.ndarray) -> dict[str, float]:
    """Statistics over members of their mean episode return (``returns[members, episodes]``).

    ``eval_return_mean/median/iqm/ci95_*`` are over the members' means; ``eval_return_std`` is
    the standard deviation of the members' means; ``min``/``max`` are over every episode.
    """
    summary_ = summary(np.asarray(returns, np.float64).mean(axis=1))
    return {
        **{f"eval_return_{k}": v for k, v in summary_.items()},
        "eval_return_min": float(np.min(returns)),
        "eval_return_max": float(np.max(returns)),
    }


__all__ = [
    "CI_NARROWER_FROM",
    "bootstrap_ci",
    "interval_name",
    "iqm",
    "population_stats",
    "return_stats",
    "summary",
]
