"""Recurring residuals over a synthetic shift (hood_decomp.core.loop.measured_effects) against the generator's truth:
the hinge_R.z parts are traced to that FE candidate with their magnitudes, the buffer bump is offered as a measured
effect that, cross-validated, brings residuals and declared estimates back, and a shift without an undeclared effect
gets nothing. 20 x 20 hood (400 skin nodes)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from hood_decomp.core.loop.candidates import candidate_fields, enumerate_candidates
from hood_decomp.core.loop.measured_effects import analyse_recurring, augmented_bases
from hood_decomp.core.method.bases import analyse_estimate, estimate_field
from hood_decomp.core.method.correction import plan_correction
from hood_decomp.core.types import DisplacementField
from hood_decomp.synthetic.shift import ProcessModel, bump_field, make_part, plan_shift
from tests.hood20 import hood20


@functools.cache
def _candidates():
    case = hood20()
    return candidate_fields(case.solver, enumerate_candidates(case.model))


def _estimate(field):
    case = hood20()
    estimate = estimate_field(case.bases, field)
    return estimate, analyse_estimate(case.bases, estimate, field.noise_rms, 0.01).within_model


@functools.cache
def _shift(candidate_share, bump_share, n, seed):
    case = hood20()
    process = ProcessModel(candidate_share=candidate_share, bump_share=bump_share, drift_label=None, step_label=None)
    plan = plan_shift(case.reduced.names, process, n, seed=seed)
    parts = [make_part(plan, i, case.truth_model, case.skin) for i in range(n)]
    results = [_estimate(p.field) for p in parts]
    outside = np.array([not within for _, within in results])
    values = np.array([e.values for e, _ in results])
    residuals = np.array([e.residual for e, _ in results])
    state = np.median(values[~outside], axis=0)
    found = analyse_recurring(case.bases, residuals[outside], np.full(outside.sum(), 0.02), values[outside], state,
                              _candidates())
    return plan, parts, np.flatnonzero(outside), found


def test_hinge_is_traced_and_bump_offered_as_measured_effect():
    """Fails if the hinge_R.z parts are not traced to hinge_R.z with magnitudes within 3 std of the truth, if the bump
    is not offered as a measured effect, or if that effect, learned on one half and judged on the other, leaves
    residuals above 1.5 x the noise or fails to remove the bump's bias from the declared estimates."""
    case = hood20()
    plan, parts, outside, found = _shift(0.1, 0.1, 600, seed=1)
    assert [m.kind for m in found.modes] == ["candidate", "measured"], found.message
    hinge, bump = found.modes
    assert hinge.name == "hinge_R.z"
    rows = outside[hinge.parts]
    effects = [plan.effect_of(i) for i in rows]
    # a noise-only part the within-model test flags (its 1 % false alarms, by design) may carry the mode by chance
    # (|z| > 3 along it): one such part at most, never a bump part
    assert "bump" not in effects and effects.count("none") <= 1, effects
    assert effects.count("candidate") >= 0.95 * np.sum(plan.effect[outside] == 1)
    z = (hinge.amplitude[hinge.parts] - plan.amplitude[rows]) / hinge.std[hinge.parts]
    assert np.mean(np.abs(z) <= 3.0) >= 0.95, np.round(z, 2)
    assert abs(np.mean(hinge.amplitude[hinge.parts]) - np.mean(plan.amplitude[rows])) <= 3 * np.sqrt(
        np.sum(hinge.std[hinge.parts] ** 2)) / len(rows)

    rows = outside[bump.parts]
    assert {plan.effect_of(i) for i in rows} == {"bump"}
    # every bump part the test flags whose bump stands out of its own noise (4 std) carries the mode
    clear = (plan.effect[outside] == 2) & (np.abs(plan.amplitude[outside]) > 4 * bump.std)
    assert np.mean(bump.parts[clear]) >= 0.95 and clear.sum() >= 0.8 * np.sum(plan.effect == 2)
    truth = bump_field(case.skin, plan.process.bump_center, plan.process.bump_radius_mm)
    assert bump.field @ truth / np.linalg.norm(bump.field) / np.linalg.norm(truth) > 0.98
    assert bump.n_judge >= 20 and bump.rms_after.size >= 10
    assert np.all(bump.rms_after <= 1.5 * bump.expected_rms)
    assert np.all(bump.rms_before > bump.rms_after)
    # declared estimates: against the estimate of the same part (same noise, same holes) without the bump
    without = np.array([_estimate(DisplacementField(case.skin.model_id, parts[i].field.normal_displacement
                                                    - plan.amplitude[i] * truth, 1.0, 0.02))[0].values
                        for i in rows])
    values = np.array([_estimate(parts[i].field)[0].values for i in rows])
    before = np.abs(values - without).max(axis=1)
    after = np.abs(bump.values_after[bump.parts] - without).max(axis=1)
    assert np.median(before) > 0.07
    # on 400 nodes the bump amplitude of one part carries ~0.012 mm std, ~0.01 mm on BUFFER_L: the 0.02 mm target
    # holds for the typical part here and for every part at default resolution (benchmarks/bench_shift.py)
    assert np.median(after) <= 0.02 and after.max() <= 0.04, np.round(after, 3)


@pytest.mark.parametrize("candidate_share", [0.0, 0.1])
def test_no_measured_effect_without_one(candidate_share):
    """Fails if a measured effect is offered on a shift whose parts carry none (noise alone, or only an effect an FE
    candidate explains)."""
    _, _, _, found = _shift(candidate_share, 0.0, 200, seed=5)
    assert not found.measured, found.message
    assert [m.name for m in found.modes] == (["hinge_R.z"] if candidate_share else [])


def test_bases_rebuilt_with_the_measured_effect():
    """Fails if bases rebuilt with the measured effect do not estimate its amplitude as a parameter (within 3 std of
    the true bump), leave the bump parts outside the model, keep the bump's bias in the declared estimates, or let
    the correction move something for the effect."""
    case = hood20()
    plan, parts, outside, found = _shift(0.1, 0.1, 600, seed=1)
    measured = found.measured
    rebuilt = augmented_bases(case.bases, case.ensemble, measured)
    name = measured[0].name
    column = rebuilt.names.index(name)
    assert rebuilt.names[:column] == case.bases.names[:column] and name in rebuilt.hierarchical.effect_names_
    truth = bump_field(case.skin, plan.process.bump_center, plan.process.bump_radius_mm)
    rows = [i for i in outside[measured[0].parts]][:12]
    for i in rows:
        estimate = estimate_field(rebuilt, parts[i].field)
        assert abs(estimate.values[column] - plan.amplitude[i]) <= 3 * estimate.std[column] + 0.005, i
        assert analyse_estimate(rebuilt, estimate, 0.02, 0.01).within_model, i
        without = _estimate(DisplacementField(case.skin.model_id, parts[i].field.normal_displacement
                                              - plan.amplitude[i] * truth, 1.0, 0.02))[0].values
        assert np.abs(np.delete(estimate.values, column) - without).max() <= 0.03, i
    assert rebuilt.measured_effects == (name,) and estimate.measured_effect[column]
    correction = plan_correction(estimate)
    assert correction.corrections[column] == 0.0 and f"{name} is a measured effect" in correction.reason
