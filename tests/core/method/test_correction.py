"""The correction sent to the fixture adjustment robot, and every reason it is held back."""

from __future__ import annotations

import numpy as np

from hood_decomp.core.method.correction import CorrectionPolicy, limit_steps, plan_correction, verify_move
from hood_decomp.core.types import BoundaryCorrection, MoveVerification, ParameterEstimate


def estimate(**changes) -> ParameterEstimate:
    base = dict(
        model_id="m", names=("HINGE_X", "LOCK_L", "BUFFER_R"), values=np.array([0.3, -0.5, 0.2]),
        std=np.array([0.001, 0.002, 0.003]), lower=-np.ones(3), upper=np.ones(3),
        lifted=np.array([False, False, False]), reconstruction=np.zeros(4), residual=np.zeros(4),
        residual_rms=0.01, residual_max=0.03, coverage=0.9, within_model=True, method="contact",
    )
    return ParameterEstimate(**{**base, **changes})


def test_safe_correction_negates_the_estimate():
    correction = plan_correction(estimate())
    assert correction.safe_to_apply and correction.reason == ""
    np.testing.assert_array_equal(correction.corrections, [-0.3, 0.5, -0.2])


def test_lifted_buffer_is_not_corrected_and_says_why():
    correction = plan_correction(estimate(lifted=np.array([False, False, True]), values=np.array([0.3, -0.5, 3.0]),
                                          std=np.array([0.001, 0.002, 9.0])))
    assert correction.safe_to_apply  # an unobservable buffer neither blocks nor moves
    assert correction.corrections[2] == 0.0
    assert "BUFFER_R lifted" in correction.reason


def test_every_reason_is_named():
    correction = plan_correction(
        estimate(coverage=0.3, values=np.array([1.5, -0.5, np.nan]), std=np.array([0.001, 0.2, 0.003])),
        CorrectionPolicy(min_coverage=0.6, max_std_mm=0.05),
    )
    assert not correction.safe_to_apply
    for fragment in ("coverage 0.30 below minimum 0.60", "HINGE_X = 1.500 mm outside", "BUFFER_R = nan mm outside",
                     "LOCK_L uncertainty 0.200 mm above 0.05 mm"):
        assert fragment in correction.reason


def test_a_part_the_model_does_not_explain_names_no_boundary():
    """Fails if, when the within-model test alarms, the reason names a boundary (an estimate outside its range, a
    large uncertainty, a lifted flag: under a model discrepancy these are its consequences, and naming one sends the
    engineer to a boundary that may be fine; issue 15 harness (ii)), or drops the model statement or the coverage."""
    correction = plan_correction(
        estimate(coverage=0.3, within_model=False, values=np.array([1.5, -0.5, 0.2]),
                 std=np.array([0.001, 0.2, 0.003]), lifted=np.array([False, False, True])),
        CorrectionPolicy(min_coverage=0.6, max_std_mm=0.05),
    )
    assert not correction.safe_to_apply and not correction.applicable.any()
    assert "coverage 0.30 below minimum 0.60" in correction.reason
    assert "the model does not explain this part" in correction.reason
    assert "differs from the part" in correction.reason
    assert not any(name in correction.reason for name in ("HINGE_X", "LOCK_L", "BUFFER_R")), correction.reason


def test_range_tolerance():
    inside = plan_correction(estimate(values=np.array([1.01, 0.0, 0.0])), CorrectionPolicy(range_tolerance_mm=0.02))
    outside = plan_correction(estimate(values=np.array([1.03, 0.0, 0.0])), CorrectionPolicy(range_tolerance_mm=0.02))
    assert inside.safe_to_apply and not outside.safe_to_apply


def test_applicability_is_stated_per_boundary():
    """Fails if one boundary's large std or out-of-range estimate blocks the others' per-boundary applicability, if
    a lifted boundary is called applicable, or if any boundary is applicable when the model does not explain the
    part (a missing effect moves every estimate, so none may be applied)."""
    policy = CorrectionPolicy(max_std_mm=0.05)
    mixed = plan_correction(estimate(values=np.array([0.3, 1.5, 0.2]), std=np.array([0.001, 0.002, 0.08])), policy)
    assert not mixed.safe_to_apply
    np.testing.assert_array_equal(mixed.applicable, [True, False, False])
    np.testing.assert_array_equal(mixed.std, [0.001, 0.002, 0.08])
    lifted = plan_correction(estimate(lifted=np.array([False, False, True])), policy)
    np.testing.assert_array_equal(lifted.applicable, [True, True, False])
    outside = plan_correction(estimate(within_model=False), policy)
    assert not outside.applicable.any() and "differs from the part" in outside.reason
    assert "HINGE_X" not in outside.reason


def test_step_limit_caps_each_move_and_leaves_the_rest_for_the_next_cycle():
    """Fails if a move beyond its per-cycle maximum step is sent whole, a boundary without a limit (0) is capped,
    the sign of a capped move changes, or the rest is not stated (in ``remaining`` and by name in the reason)."""
    correction = plan_correction(estimate(values=np.array([0.8, -0.1, -0.3])))  # moves -0.8, +0.1, +0.3
    capped = limit_steps(correction, np.array([0.5, 0.0, 0.2]))
    np.testing.assert_allclose(capped.corrections, [-0.5, 0.1, 0.2])
    np.testing.assert_allclose(capped.remaining, [-0.3, 0.0, 0.1])
    assert "HINGE_X: step limited to -0.500 mm of -0.800 mm, -0.300 mm left for the next cycle" in capped.reason
    assert "BUFFER_R" in capped.reason and "LOCK_L" not in capped.reason and capped.safe_to_apply


def test_verification_names_a_move_applied_at_half_as_slipped():
    """Fails if the verification does not tell an achieved move (within its tolerance), a move applied at 50 %
    (PARTIAL, named with its fraction), a move that did not happen or went the wrong way (FAILED) and a boundary that
    was not commanded (not applicable) apart. Truth: the after-state made by hand from the before-state."""
    names = ("A", "B", "C", "D", "E")
    before = estimate(names=names, values=np.array([0.4, -0.3, 0.5, -0.2, 0.6]), std=np.full(5, 0.002),
                      lower=-np.ones(5), upper=np.ones(5), lifted=np.zeros(5, bool))
    sent = plan_correction(before, CorrectionPolicy(max_std_mm=0.01))
    sent = BoundaryCorrection(**{**sent.__dict__, "applicable": np.array([True, True, True, True, False])})
    moved = np.array([0.5, 1.0, 0.0, -1.0, 0.5]) * sent.corrections  # E moved, but was never commanded
    after = estimate(names=names, values=before.values + moved, std=np.full(5, 0.002), lower=-np.ones(5),
                     upper=np.ones(5), lifted=np.zeros(5, bool))
    check = verify_move(before, sent, after)
    assert list(check.outcome) == [MoveVerification.PARTIAL, MoveVerification.ACHIEVED, MoveVerification.FAILED,
                                   MoveVerification.FAILED, MoveVerification.NOT_COMMANDED]
    np.testing.assert_allclose(check.fraction[:4], [0.5, 1.0, 0.0, -1.0])
    assert "A: 50 % of -0.400 mm (PARTIAL)" in check.summary and "B" not in check.summary
    assert "C: 0 % of -0.500 mm (FAILED)" in check.summary and "D: -100 %" in check.summary
    assert not check.all_achieved
    np.testing.assert_allclose(check.std, np.full(5, 0.002 * np.sqrt(2)))
    # all commanded moves made: achieved, nothing named
    whole = verify_move(before, sent, estimate(names=names, values=before.values + sent.corrections * [1, 1, 1, 1, 0],
                                               std=np.full(5, 0.002), lower=-np.ones(5), upper=np.ones(5),
                                               lifted=np.zeros(5, bool)))
    assert whole.all_achieved and whole.summary == ""


def test_a_correction_the_uncalibrated_model_cannot_tell_is_not_applicable():
    """Fails if a boundary whose measurement std is small but whose total uncertainty sqrt(std^2 + model_std^2) (the
    model's physical factors, not calibrated to the part: a softer pad looks like a moved pad) is above max_std is
    still applicable or lets the whole be safe, if the reason does not name that boundary with its dominant factor
    and one-sigma effect, or if a boundary within the limit (LOCK_L: 0.002 and 0.001 mm) is held back too."""
    effects = np.array([[0.0, 0.001, 0.004], [0.0, 0.0, -0.020]])  # (factor, parameter) one-sigma, mm
    correction = plan_correction(estimate(model_factors=("compliance", "pad stiffness"), model_effects=effects))
    assert not correction.safe_to_apply
    np.testing.assert_array_equal(correction.applicable, [True, True, False])
    assert correction.reason == ("model not calibrated to the part: BUFFER_R correction depends on pad stiffness "
                                 "by +-0.020 mm"), correction.reason
    np.testing.assert_array_equal(correction.std, [0.001, 0.002, 0.003])  # the measurement std, unchanged


def test_a_boundary_whose_factors_alone_exceed_the_limit_says_so_beside_its_measurement_std():
    """Fails if a boundary whose measurement std is above max_std hides that the model's factors alone exceed the
    limit too (a better scan would not open its gate: the model must be calibrated), or if a boundary whose factors
    are within the limit gets the model reason beside its std."""
    effects = np.array([[0.0, 0.001, 0.004], [0.0, 0.0, -0.020]])  # (factor, parameter) one-sigma, mm
    correction = plan_correction(estimate(std=np.array([0.001, 0.009, 0.009]), model_effects=effects,
                                          model_factors=("compliance", "pad stiffness")))
    assert correction.reason == ("LOCK_L uncertainty 0.009 mm above 0.0045 mm; BUFFER_R uncertainty 0.009 mm above "
                                 "0.0045 mm; model not calibrated to the part: BUFFER_R correction depends on pad "
                                 "stiffness by +-0.020 mm"), correction.reason
    np.testing.assert_array_equal(correction.applicable, [True, False, False])
