"""Statistical process control of a shift (hood_decomp.shift.spc): the run rules on hand-made sequences, and the
alarm delays and false-alarm rates on synthetic shifts whose parts went through the core path (generator ->
field -> contact-aware estimate), 20 x 20 hood. The rates over many seeds are in benchmarks/bench_shift.py."""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.core.method.bases import estimate_field
from hood_decomp.errors import ShiftError
from hood_decomp.shift.spc import RULES, capability, individuals_chart, western_electric
from hood_decomp.synthetic.shift import ProcessModel, make_part, plan_shift
from tests.hood20 import hood20


def test_western_electric_rules_on_hand_made_sequences():
    """Fails if a rule misses its textbook pattern, fires on the pattern just short of it, or fires twice on the
    same evidence."""
    z = np.zeros(30)
    z[3] = 3.2
    z[[10, 12]] = 2.2
    z[20:24] = 1.2
    alarms = western_electric(z)
    assert alarms["beyond_3sigma"].tolist() == [3]
    assert alarms["two_of_three"].tolist() == [12]
    assert alarms["four_of_five"].tolist() == [23]
    assert alarms["nine_in_a_row"].size == 0  # zeros are on neither side
    short = np.zeros(30)
    short[[10, 13]] = 2.5
    short[20:23] = 1.5
    assert western_electric(short)["two_of_three"].size == 0 and western_electric(short)["four_of_five"].size == 0
    run = -np.full(20, 0.1)
    assert western_electric(run)["nine_in_a_row"].tolist() == [8, 17]


def test_chart_limits_and_capability_against_hand_computation():
    """Fails if the centre, sigma (larger of moving range / 1.128 and the sample std of the baseline, times the
    90 % upper confidence factor sqrt(9 / chi2_0.1(9)) = 1.3675 of a 10-part baseline) or the capability indices
    differ from their textbook formulas."""
    x = np.array([0.1, 0.3, 0.2, 0.4, 0.1, 0.2, 0.3, 0.2, 0.1, 0.3, 0.9, 0.2])
    chart = individuals_chart("A", x, 10)
    base = x[:10]
    sigma = max(np.mean(np.abs(np.diff(base))) / 1.128, base.std(ddof=1))
    assert chart.centre == pytest.approx(base.mean()) and chart.sigma_estimate == pytest.approx(sigma)
    assert chart.sigma == pytest.approx(sigma * np.sqrt(9 / 4.16816), rel=1e-5)  # chi2_0.1(9) = 4.16816 (tables)
    assert chart.alarms["beyond_3sigma"].tolist() == [10]
    c = capability("A", x, -1.0, 1.0)
    within = np.mean(np.abs(np.diff(x))) / 1.128
    assert c.cp == pytest.approx(2.0 / (6 * within))
    assert c.ppk == pytest.approx((1.0 - x.mean()) / (3 * x.std(ddof=1)))
    with pytest.raises(ShiftError, match="baseline"):
        individuals_chart("A", x, 20)


def _estimated_shift(process, n, seed):
    case = hood20()
    plan = plan_shift(case.reduced.names, process, n, seed=seed)
    values = np.array([estimate_field(case.bases, make_part(plan, i, case.truth_model, case.skin).field).values
                       for i in range(n)])
    return case.reduced.names, values


def test_step_and_drift_raise_alarms_in_time():
    """Fails if a step of 3 spreads on HINGE_Y is not alarmed within 10 parts of its start, or a drift of 0.5 spread
    per 10 parts on LOCK_L within 30 parts, by the chart with limits from the 200 parts before."""
    process = ProcessModel(drift_start=220, step_start=220, drift_per_part=0.05, step_size=3.0)
    names, values = _estimated_shift(process, 260, seed=11)
    step = individuals_chart("HINGE_Y", values[:, names.index("HINGE_Y")], 200).first_alarm(220)
    drift = individuals_chart("LOCK_L", values[:, names.index("LOCK_L")], 200).first_alarm(220)
    assert step is not None and step[0] - 220 < 10, step
    assert drift is not None and drift[0] - 220 < 30, drift


def test_stable_shift_false_alarm_rates():
    """Fails if, on a stable shift of 1,000 parts, any rule raises alarms on more than 1 % of the monitored parts of
    any boundary."""
    process = ProcessModel(drift_label=None, step_label=None)
    names, values = _estimated_shift(process, 1000, seed=12)
    for column, name in enumerate(names):
        chart = individuals_chart(name, values[:, column], 200)
        for rule in RULES:
            assert chart.alarms[rule].size <= 0.01 * 800, (name, rule, chart.alarms[rule])


def test_limits_allow_for_the_baselines_sampling_error():
    """Fails if the chart's sigma is the baseline's point estimate (or any allowance much below the 90 % upper
    confidence bound): then about half the charts of a stable process get limits narrower than the truth, and a
    baseline 10 % low doubles every sigma-scaled rule's false alarms for the whole shift (3 of 90 (rule, boundary,
    shift) charts above 1 % in benchmarks/bench_shift.py before the allowance)."""
    rng = np.random.default_rng(7)
    sigmas = np.array([individuals_chart("A", rng.standard_normal(210), 200).sigma for _ in range(400)])
    # true sigma 1: at most ~10 % of the charts below it (binomial 400 x 0.1: 40 +- 6), half with a point estimate
    assert np.mean(sigmas < 1.0) <= 0.14, np.mean(sigmas < 1.0)
    assert np.mean(sigmas < 1.0) >= 0.03  # ... and not a blanket inflation that would blunt detection
