"""The synthetic shift generator (hood_decomp.synthetic.shift) against independent paths: the FE forward solve of
each part's setting (simulate_setting, its own reduced model), a bump written out here, and the process model's
declared statistics."""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.core.fe.ensemble import simulate_setting
from hood_decomp.errors import ModelError
from hood_decomp.synthetic.shift import ProcessModel, make_part, plan_shift
from tests.hood20 import hood20


def _setting(names, truth):
    return dict(zip(names, (float(v) for v in truth), strict=True))


def test_parts_are_the_fe_solution_of_their_declared_states_and_effects():
    """Fails if a part's clean field is not the forward solve of its states (wrong column order, candidate input
    lost, contact ignored), if the bump has the wrong shape, place or size, or if noise and holes are not as
    declared."""
    case = hood20()
    process = ProcessModel(candidate_share=0.3, bump_share=0.3, noise_mm=0.02)
    plan = plan_shift(case.reduced.names, process, 30, seed=3)
    kinds = {plan.effect_of(i): i for i in range(plan.n_parts)}
    assert set(kinds) == {"none", "candidate", "bump"}
    points = case.skin.points
    for kind, index in kinds.items():
        part = make_part(plan, index, case.truth_model, case.skin)
        setting = _setting(case.reduced.names, part.truth)
        if kind == "candidate":
            setting["hinge_R.z"] = part.amplitude
            assert 0.27 <= part.amplitude <= 0.33
        expected = simulate_setting(case.solver, setting).normal_displacement
        if kind == "bump":
            assert 0.1 <= part.amplitude <= 0.2
            d2 = (points[:, 0] - 185.0) ** 2 + (points[:, 1] + 609.5) ** 2
            expected = expected + part.amplitude * np.exp(-d2 / (2 * 90.0**2))
        np.testing.assert_allclose(part.clean, expected, atol=1e-9)
        seen = np.isfinite(part.field.normal_displacement)
        assert 0.5 < seen.mean() < 1.0 and part.field.coverage == pytest.approx(seen.mean())
        noise = part.field.normal_displacement[seen] - part.clean[seen]
        assert abs(noise.std() / 0.02 - 1) < 0.15 and abs(noise.mean()) < 0.006


def test_plan_follows_the_process_model():
    """Fails if the step, the drift, the spread or the shares of undeclared effects differ from the process model
    (checked against their sampling error over 2,000 parts) or if the plan depends on anything but (seed, part)."""
    names = hood20().reduced.names
    process = ProcessModel(drift_start=1000, drift_per_part=0.05, step_start=1000, step_size=3.0,
                           candidate_share=0.1, bump_share=0.2)
    plan = plan_shift(names, process, 2000, seed=7)
    before, after = slice(0, 1000), slice(1000, 2000)
    step = plan.truth[:, names.index("HINGE_Y")]
    se = 0.05 * np.sqrt(2 / 1000)
    assert abs(step[after].mean() - step[before].mean() - 0.15) < 4 * se
    drift = plan.truth[:, names.index("LOCK_L")]
    slope = np.polyfit(np.arange(1000), drift[after] - drift[before].mean(), 1)[0]
    assert abs(slope - 0.05 * 0.05) < 0.1 * 0.0025
    assert abs(plan.truth[before, names.index("BUFFER_L")].mean() - 0.4) < 4 * 0.05 / np.sqrt(1000)
    assert abs(plan.truth[before, names.index("HINGE_X")].std() / 0.05 - 1) < 0.1
    for kind, share in ((1, 0.1), (2, 0.2)):
        observed = np.mean(plan.effect == kind)
        assert abs(observed - share) < 4 * np.sqrt(share * (1 - share) / 2000)
    again = plan_shift(names, process, 10, seed=7)
    np.testing.assert_array_equal(again.truth, plan.truth[:10])


def test_plan_refuses_unknown_labels():
    """Fails if a process model naming a parameter the model lacks is accepted silently."""
    with pytest.raises(ModelError, match="NOT_A_LABEL"):
        plan_shift(hood20().reduced.names, ProcessModel(step_label="NOT_A_LABEL"), 10)
