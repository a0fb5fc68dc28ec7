"""The statistics a reviewer asks of a Monte Carlo study.

* Success probability with a one-sided Clopper-Pearson (exact binomial) lower bound.
* How many consecutive successes demonstrate a reliability at a confidence: the zero-failure
  order-statistics rule n = ceil(ln(1 - C) / ln(R)) (852 runs show 99.73 % at 90 %).
* Percentiles (p50, p95, p99.73) of the figures of merit.
* The worst runs, each with the command that replays it.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "clopper_pearson_lower",
    "clopper_pearson_upper",
    "zero_failure_runs",
    "demonstrated_reliability",
    "percentiles",
    "PERCENTILES",
]

# p99.73 is the 3-sigma point of a normal distribution, the figure GNC reviews quote.
PERCENTILES = (50.0, 95.0, 99.73)


def _beta_ppf(q, a, b):
    # scipy.stats imported here, not with the module: it takes about 0.6 s, and every
    # command line call imports this module (the study command's parsers).
    from scipy import stats

    return stats.beta.ppf(q, a, b)


def _check_confidence(confidence: float) -> None:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")


def clopper_pearson_lower(successes: int, runs: int, confidence: float = 0.9) -> float:
    """One-sided lower bound p_L on a success probability: P(X >= k | p_L) = 1 - confidence,
    i.e. the (1 - confidence) quantile of Beta(k, n - k + 1); 0 when k = 0."""
    _check_confidence(confidence)
    if not 0 <= successes <= runs:
        raise ValueError(f"successes must be in [0, runs={runs}], got {successes}")
    if runs == 0:
        return 0.0
    if successes == 0:
        return 0.0
    return float(_beta_ppf(1.0 - confidence, successes, runs - successes + 1))


def clopper_pearson_upper(successes: int, runs: int, confidence: float = 0.9) -> float:
    """One-sided upper bound on a success probability; 1 when every run succeeded."""
    _check_confidence(confidence)
    if not 0 <= successes <= runs:
        raise ValueError(f"successes must be in [0, runs={runs}], got {successes}")
    if successes == runs:
        return 1.0
    return float(_beta_ppf(confidence, successes + 1, runs - successes))


def zero_failure_runs(reliability: float, confidence: float = 0.9) -> int:
    """Runs without a failure that show ``reliability`` at ``confidence``:
    the smallest n with reliability^n <= 1 - confidence."""
    _check_confidence(confidence)
    if not 0.0 < reliability < 1.0:
        raise ValueError(f"reliability must be in (0, 1), got {reliability}")
    n = math.log(1.0 - confidence) / math.log(reliability)
    # guard the ceiling against rounding just above an integer
    return int(math.ceil(n - 1e-9))


def demonstrated_reliability(runs: int, confidence: float = 0.9) -> float:
    """The reliability that ``runs`` zero-failure runs show at ``confidence``:
    (1 - confidence)^(1 / n) (the Clopper-Pearson bound with k = n)."""
    _check_confidence(confidence)
    if runs < 1:
        return 0.0
    return float((1.0 - confidence) ** (1.0 / runs))


def percentiles(values, qs=PERCENTILES) -> dict:
    """{"p50": .., "p95": .., "p99.73": ..} of the finite values (None when there are none)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    out = {}
    for q in qs:
        label = f"p{q:g}"
        out[label] = float(np.percentile(v, q)) if v.size else None
    return out
