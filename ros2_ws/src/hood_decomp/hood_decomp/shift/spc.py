"""Statistical process control of a shift: per boundary, an individuals control chart with limits from a baseline
period, the Western Electric run rules and an EWMA drift chart; process capability against the parameter's range;
the correlation between boundaries; the share of parts outside the model over time.

Individuals chart (Montgomery, Introduction to Statistical Quality Control, ch. 6.4): centre = mean of the first
``baseline`` charted parts, sigma_hat = the larger of the mean moving range / d2 (d2 = 1.128 for ranges of two) and
the sample standard deviation of the baseline, and the chart's sigma = sigma_hat times the **estimation allowance**
sqrt((n - 1) / chi2_{0.1}(n - 1)) of a baseline of n parts (1.07 for 200 parts, 1.10 for 100): the one-sided 90 %
upper confidence bound on sigma. Why: the limits are estimated, and a baseline whose sigma comes out 10 % low (a
two-standard-error event for 200 parts, so in a few % of the (boundary, shift) charts) doubles the false-alarm rate
of every sigma-scaled rule for the whole shift; with the point estimate, 3 of 90 (rule, boundary, shift) charts of
the benchmark's stable shifts exceeded 1 % false alarms (all three with sigma_hat 10-11 % low). The allowance is
the simplest form of "guaranteed in-control performance" (Goedhart, Schoonhoven and Does, 2017: limits widened by the
uncertainty of the estimate rather than by a per-rule constant), one factor for all rules; it costs a little speed
of detection (a 3-spread step is 2.8 charted sigmas). Limits centre +- 3 sigma. The rules are judged on
z = (x - centre) / sigma from the part after the baseline on (phase II):

- ``beyond_3sigma``: one point beyond 3 sigma;
- ``two_of_three``: 2 of 3 consecutive points beyond 2 sigma on the same side;
- ``four_of_five``: 4 of 5 consecutive points beyond 1 sigma on the same side;
- ``nine_in_a_row``: 9 consecutive points on the same side of the centre (Nelson's form of the run rule; the
  Western Electric handbook's 8 points fire on 2 x 0.5^8 = 0.78 % of the windows of a stable process, 0.4 % of its
  parts as events, and exceeded 1 % in 1 of 72 stable (boundary, shift) charts of the benchmark even with limits
  that allow for the baseline: the count of a 0.4 % event in 800 parts exceeds 8 in about 1 % of the shifts; with
  9 points the rate halves and the slow-drift detection rests on the EWMA anyway);
- ``ewma``: the EWMA z_t = lambda x_t + (1 - lambda) z_{t-1} (lambda = 0.2) beyond L = 2.86 of its exact standard
  deviation (in-control average run length about 370 parts, as the 3-sigma rule); sensitive to slow drifts.

An alarm is an event: after a rule fires, the points that made it are not used again by that rule (the EWMA restarts
at the centre), so a persisting shift raises a new alarm only on new evidence and the alarm rate of a stable process
is the rule's false-alarm rate per part. A part whose value is missing (failed, or a lifted buffer whose value is a
position bound, not a state) is left out of the chart and its rules.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from hood_decomp.errors import ShiftError

D2 = 1.128  # mean range of two standard normal draws
#: one-sided confidence of the upper bound on sigma the limits use (the estimation allowance, module docstring)
SIGMA_CONFIDENCE = 0.9
RULES = ("beyond_3sigma", "two_of_three", "four_of_five", "nine_in_a_row", "ewma")
EWMA_LAMBDA = 0.2
EWMA_L = 2.86


@dataclass(frozen=True)
class ControlChart:
    """One boundary's individuals chart over M parts. values: (M,) mm, NaN where not charted. centre, mm; sigma, mm:
    the baseline's estimate times the estimation allowance (module docstring); sigma_estimate: that estimate, mm;
    lcl, ucl: centre -+ 3 sigma. baseline_end: index of the first phase-II part. ewma: (M,) the EWMA (NaN where not
    charted), ewma_limit: (M,) its half-width. alarms: rule -> (K,) indices of the parts where it fired."""

    name: str
    values: np.ndarray
    centre: float
    sigma: float
    lcl: float
    ucl: float
    baseline_end: int
    sigma_estimate: float
    ewma: np.ndarray
    ewma_limit: np.ndarray
    alarms: dict[str, np.ndarray]

    def first_alarm(self, after: int = 0) -> tuple[int, str] | None:
        """(part index, rule) of the first alarm at or after part ``after``, or None."""
        found = [(int(i[i >= after][0]), rule) for rule, i in self.alarms.items() if np.any(i >= after)]
        return min(found) if found else None


def _run_rule(flags: np.ndarray, window: int, needed: int) -> list[int]:
    """Positions where at least ``needed`` of the last ``window`` flags are set, each window used by one alarm only."""
    out, last = [], -1
    for i in range(window - 1, flags.size):
        start = i - window + 1
        if start > last and np.count_nonzero(flags[start:i + 1]) >= needed:
            out.append(i)
            last = i
    return out


def western_electric(z: np.ndarray) -> dict[str, np.ndarray]:
    """Alarm positions (indices into ``z``) of the four run rules on standardised values z (K,) (module docstring)."""
    alarms = {"beyond_3sigma": np.flatnonzero(np.abs(z) > 3.0)}
    for name, window, needed, level in (("two_of_three", 3, 2, 2.0), ("four_of_five", 5, 4, 1.0),
                                        ("nine_in_a_row", 9, 9, 0.0)):
        hits = sorted(set(_run_rule(z > level, window, needed)) | set(_run_rule(z < -level, window, needed)))
        alarms[name] = np.array(hits, dtype=np.int64)
    return alarms


def ewma_alarms(z: np.ndarray, lam: float = EWMA_LAMBDA, width: float = EWMA_L) -> tuple[np.ndarray, np.ndarray,
                                                                                           np.ndarray]:
    """EWMA of standardised values z (K,): (ewma (K,), its limit (K,), alarm positions); restarts after an alarm."""
    ewma, limit, alarms = np.zeros(z.size), np.zeros(z.size), []
    level, steps = 0.0, 0
    for i, value in enumerate(z):
        steps += 1
        level = lam * value + (1 - lam) * level
        ewma[i] = level
        limit[i] = width * np.sqrt(lam / (2 - lam) * (1 - (1 - lam) ** (2 * steps)))
        if abs(level) > limit[i]:
            alarms.append(i)
            level, steps = 0.0, 0
    return ewma, limit, np.array(alarms, dtype=np.int64)


def sigma_allowance(n: int, confidence: float = SIGMA_CONFIDENCE) -> float:
    """The factor sqrt((n - 1) / chi2_{1 - confidence}(n - 1)) that turns a sigma estimated from n parts into its
    one-sided ``confidence`` upper bound (exact for the sample std of normal values; the moving-range estimate has
    fewer degrees of freedom, the larger of the two is used)."""
    return float(np.sqrt((n - 1) / chi2.ppf(1.0 - confidence, n - 1)))


def individuals_chart(name: str, values: np.ndarray, baseline: int) -> ControlChart:
    """The chart of one boundary: values (M,) mm in time order, NaN where not charted; limits from the first
    ``baseline`` charted values (module docstring). Raises ShiftError with fewer than max(baseline, 10) charted values
    or a baseline without spread."""
    values = np.asarray(values, float)
    charted = np.flatnonzero(np.isfinite(values))
    if baseline < 10 or charted.size < baseline:
        raise ShiftError(f"{name}: a control chart needs a baseline of at least 10 parts and that many charted parts; "
                       f"baseline {baseline}, charted {charted.size}")
    base = values[charted[:baseline]]
    centre = float(base.mean())
    estimate = max(float(np.mean(np.abs(np.diff(base))) / D2), float(base.std(ddof=1)))
    if not estimate > 0:
        raise ShiftError(f"{name}: the baseline parts have no spread (moving range 0)")
    sigma = estimate * sigma_allowance(baseline)
    phase2 = charted[baseline:]
    z = (values[phase2] - centre) / sigma
    alarms = {rule: phase2[i] for rule, i in western_electric(z).items()}
    ewma_z, limit_z, ewma_hits = ewma_alarms(z)
    alarms["ewma"] = phase2[ewma_hits]
    ewma = np.full(values.size, np.nan)
    limit = np.full(values.size, np.nan)
    ewma[phase2], limit[phase2] = centre + sigma * ewma_z, sigma * limit_z
    return ControlChart(name, values, centre, sigma, centre - 3 * sigma, centre + 3 * sigma,
                        int(charted[baseline - 1]) + 1, estimate, ewma, limit, alarms)


@dataclass(frozen=True)
class Capability:
    """Capability of one boundary against its declared range [lower, upper] mm. mean, sigma_within (moving range),
    sigma_overall (sample std) over the charted parts; cp, cpk (within), pp, ppk (overall); share_outside: fraction
    of charted parts outside the range."""

    name: str
    lower: float
    upper: float
    mean: float
    sigma_within: float
    sigma_overall: float
    cp: float
    cpk: float
    pp: float
    ppk: float
    share_outside: float


def capability(name: str, values: np.ndarray, lower: float, upper: float) -> Capability:
    """Cp, Cpk, Pp, Ppk of the charted values (NaN left out) against [lower, upper] (Montgomery ch. 8)."""
    x = np.asarray(values, float)
    x = x[np.isfinite(x)]
    if x.size < 2:
        raise ShiftError(f"{name}: capability needs at least 2 charted parts, got {x.size}")
    mean = float(x.mean())
    within = float(np.mean(np.abs(np.diff(x))) / D2)
    overall = float(x.std(ddof=1))

    def ratio(width: float, sigma: float) -> float:
        return width / sigma if sigma > 0 else float("inf")

    return Capability(name, float(lower), float(upper), mean, within, overall,
                      ratio(upper - lower, 6 * within), ratio(min(upper - mean, mean - lower), 3 * within),
                      ratio(upper - lower, 6 * overall), ratio(min(upper - mean, mean - lower), 3 * overall),
                      float(np.mean((x < lower) | (x > upper))))


def correlation(values: np.ndarray) -> np.ndarray:
    """Pearson correlation (P, P) between the columns of values (M, P) over the rows where every column is finite
    (NaN where a column has no spread)."""
    rows = np.all(np.isfinite(values), axis=1)
    x = values[rows]
    if x.shape[0] < 3:
        return np.full((values.shape[1], values.shape[1]), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.corrcoef(x, rowvar=False)


def rolling_share(flags: np.ndarray, window: int) -> np.ndarray:
    """Share of True in the last ``window`` entries at every position (M,) (fewer at the start)."""
    flags = np.asarray(flags, float)
    cumulative = np.concatenate([[0.0], np.cumsum(flags)])
    index = np.arange(1, flags.size + 1)
    start = np.maximum(index - window, 0)
    return (cumulative[index] - cumulative[start]) / (index - start)
