"""plan_correction at the edges of its policy: exact boundaries, both ends of a range, malformed estimates.

Written against the survivors of benchmarks/mutation.py. Every expectation comes from the policy's definition in
the module docstring (an estimate is acted on when coverage >= min_coverage, std <= max_std_mm and the value lies in
[lower - tol, upper + tol]); the numbers are binary fractions so that the boundaries are exact.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hood_decomp.core.method.correction import CorrectionPolicy, plan_correction
from hood_decomp.core.types import ParameterEstimate
from tests.core.method.test_correction import estimate as correction_estimate


def estimate(**changes) -> ParameterEstimate:
    """test_correction's estimate with binary-fraction values, zero std and full coverage (exact boundaries)."""
    exact = dict(values=np.array([0.25, -0.5, 0.125]), std=np.zeros(3), residual_rms=0.0, residual_max=0.0,
                 coverage=1.0)
    return correction_estimate(**{**exact, **changes})


def test_default_policy_is_the_documented_one():
    """Fails if the defaults drift from coverage 0.6, std 0.0045 mm, range tolerance 0.02 mm (the documented policy;
    issue 15: an applied correction wrong by more than 0.02 mm must be a 4.5-std event)."""
    policy = CorrectionPolicy()
    assert (policy.min_coverage, policy.max_std_mm, policy.range_tolerance_mm) == (0.6, 0.0045, 0.02)


def test_policy_is_immutable():
    """Fails if a CorrectionPolicy can be changed after it is made (it is shared as a default argument)."""
    with pytest.raises(dataclasses.FrozenInstanceError):
        CorrectionPolicy().max_std_mm = 1.0  # type: ignore[misc]


def test_default_policy_blocks_low_coverage_and_large_std():
    """Fails if the default policy acts on 59 % coverage or on a 0.0047 mm std (both beyond its documented limits)."""
    assert plan_correction(estimate(coverage=0.625)).safe_to_apply
    assert not plan_correction(estimate(coverage=0.59)).safe_to_apply
    assert plan_correction(estimate(std=np.array([0.0044, 0.0, 0.0]))).safe_to_apply
    blocked = plan_correction(estimate(std=np.array([0.0047, 0.0, 0.0])))
    assert not blocked.safe_to_apply and "HINGE_X uncertainty" in blocked.reason


def test_coverage_exactly_at_the_minimum_is_enough():
    """Fails if coverage equal to min_coverage is refused (the condition is coverage >= min_coverage)."""
    policy = CorrectionPolicy(min_coverage=0.75)
    assert plan_correction(estimate(coverage=0.75), policy).safe_to_apply
    assert not plan_correction(estimate(coverage=0.75 - 2.0**-20), policy).safe_to_apply


def test_std_exactly_at_the_maximum_is_enough():
    """Fails if a std equal to max_std_mm is refused (the condition is std <= max_std_mm)."""
    policy = CorrectionPolicy(max_std_mm=0.125)
    assert plan_correction(estimate(std=np.array([0.125, 0.125, 0.125])), policy).safe_to_apply
    assert not plan_correction(estimate(std=np.array([0.0, 0.125 + 2.0**-20, 0.0])), policy).safe_to_apply


@pytest.mark.parametrize("value, inside", [
    (-1.25, True), (-1.25 - 2.0**-20, False), (1.25, True), (1.25 + 2.0**-20, False),
    (-1.0, True), (1.0, True), (-1.125, True), (1.125, True), (-2.0, False), (2.0, False),
])
def test_range_with_tolerance_on_both_ends(value, inside):
    """Fails if [lower - tol, upper + tol] (here [-1.25, 1.25]) is not what decides, at either end, boundaries
    included."""
    policy = CorrectionPolicy(range_tolerance_mm=0.25)
    correction = plan_correction(estimate(values=np.array([0.0, value, 0.0])), policy)
    assert correction.safe_to_apply is inside
    assert ("LOCK_L" in correction.reason) is (not inside)


def test_range_below_lower_is_named():
    """Fails if a value below its lower limit (beyond the tolerance) is not named as outside its range."""
    correction = plan_correction(estimate(values=np.array([-0.5, -3.0, 0.0]), lower=np.array([-1.0, -2.0, -1.0])))
    assert not correction.safe_to_apply
    assert correction.reason == "LOCK_L = -3.000 mm outside its range [-2, 1] mm"


@pytest.mark.parametrize("field", ["values", "std", "lifted"])
def test_mismatched_lengths_are_refused(field):
    """Fails if an estimate whose arrays do not match its names is silently truncated instead of refused."""
    short = {"values": np.array([0.25, -0.5]), "std": np.array([0.0, 0.0]), "lifted": np.array([False, False])}
    with pytest.raises(ValueError):
        plan_correction(estimate(**{field: short[field]}))


def test_lifted_notes_follow_the_problems():
    """Fails if the lifted-boundary note is missing or placed before the problems (reason = problems, then notes)."""
    correction = plan_correction(estimate(coverage=0.5, lifted=np.array([False, False, True])))
    assert correction.reason == ("coverage 0.50 below minimum 0.60; "
                                 "BUFFER_R lifted: commanded position not observable, not corrected")
    np.testing.assert_array_equal(correction.corrections, [-0.25, 0.5, 0.0])
