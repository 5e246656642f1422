"""The model's own physical factors in an estimate's uncertainty (core/method/model_spread.py, issue 15)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from hood_decomp.core.fe.ensemble import solve_members
from hood_decomp.core.fe.solver import physical_responses, thermal_moves, thickness_sensitivities
from hood_decomp.core.method.bases import estimate_field
from hood_decomp.core.method.model_spread import HALF_WIDTH, PhysicalResponses, factor_spread
from hood_decomp.core.types import DisplacementField, FieldErrorModel
from hood_decomp.synthetic.standin import Family, StandIn, embedded_responses

SIGMA = {name: h / np.sqrt(3.0) for name, h in HALF_WIDTH.items()}


@pytest.fixture(scope="module")
def physics(coarse_hood) -> PhysicalResponses:
    """The coarse hood's responses to gas springs and sheet thickness (what calibrate and bench_discrepancy use)."""
    return PhysicalResponses.from_solver(physical_responses(coarse_hood.solver),
                                         thickness_sensitivities(coarse_hood.model, coarse_hood.reduced),
                                         thermal_moves(coarse_hood.model))


def _changed(reduced, compliance: float = 1.0, stiffness: float = 1.0):
    """The reduced model with every force response times ``compliance`` and the pad stiffness times ``stiffness``
    (what a softer material or softer pads are to the condensed model)."""
    c = compliance
    return dataclasses.replace(reduced, w0=c * reduced.w0, G=c * reduced.G, z0=c * reduced.z0, H=c * reduced.H,
                               w0_3d=c * reduced.w0_3d, G_3d=c * reduced.G_3d, k=stiffness * reduced.k)


def _check_effects(bases, truths: dict, seed: int, full_contact: bool = False) -> None:
    """Per factor name -> truth(sign, state) (the member of the part with that physics changed by sign one sigma; sign
    0: the truth path's nominal part): the estimate's stated effect at the nominal part against the estimate's shift
    from the truth path's nominal part to its changed one, noise-free fields. ``full_contact``: only states where
    every spring of every pad touches (a light touch makes the estimate's contact state a discrete choice that a
    linearisation at one contact state does not follow)."""
    rng = np.random.default_rng(seed)
    states = rng.uniform(bases.pca.lower_, bases.pca.upper_, (40 if full_contact else 3, len(bases.names)))
    if full_contact:
        touching = solve_members(bases.reduced_model, states).contact_fraction.min(axis=1) == 1.0
        states = states[touching][:3]
        assert len(states) == 3, "too few fully touching states drawn"
    checked = 0
    for state in states:
        for name, truth in truths.items():
            field = DisplacementField(bases.skin.model_id, truth(0.0, state).normal_displacement[0], 1.0, 0.02,
                                      FieldErrorModel.stated(0.02, bases.skin.n_nodes))
            estimate = estimate_field(bases, field)
            rows = dict(zip(estimate.model_factors, estimate.model_effects, strict=True))
            shifts = []
            for sign in (1.0, -1.0):
                moved = dataclasses.replace(field, normal_displacement=truth(sign, state).normal_displacement[0])
                shifts.append(estimate_field(bases, moved).values - estimate.values)
            up, down = shifts
            expected = up if np.max(np.abs(up)) >= np.max(np.abs(down)) else -down
            keep = ~estimate.lifted
            np.testing.assert_allclose(rows[name][keep], expected[keep], rtol=0.15, atol=2e-3, err_msg=name)
            checked += int(np.max(np.abs(expected[keep])) > 0.005)
    assert checked >= 2, "no factor moved an estimate by 0.005 mm: the comparison would be empty"


def test_factor_effects_are_the_estimates_shift_under_the_changed_physics(coarse_hood):
    """Fails if an estimate's stated one-sigma effect of the compliance or of the pad stiffness differs by more than 15
    % (+ 0.002 mm: the changed model may change which springs of a touching pad carry load, which the linearisation at
    the estimate's contact state keeps) from the shift of the estimate when the part really has that physics: the
    noise-free field of the changed model (scaled here, not through apply_factors), solved with exact pad contact
    (solve_members), estimated by the nominal bases, minus the estimate of the nominal model's field at the same
    states (a wrong linear map, a sign, a missing 1/E on the pad forces or a stiffness step that is not one sigma).
    The fields state their noise (0.02 mm), as a scan's do: on a field stated noise-free a touch too light to show is
    reported from the fit without it (issue 16), a discrete choice no linearisation at one contact state follows, and
    the gate acts on measured fields. At states where every spring of every pad touches, as the sibling test: at a
    light touch the estimate's contact choice is discrete, and on an AMD EPYC machine's BLAS one drawn state flipped
    it (HINGE_X stated -0.0129 mm against a shift of -0.0083 mm), a linearisation no stated effect can follow."""
    reduced = coarse_hood.bases.reduced_model
    _check_effects(coarse_hood.bases, {
        "compliance (Young's modulus)": lambda sign, state: solve_members(
            _changed(reduced, compliance=np.exp(sign * SIGMA["compliance"])), state[None]),
        "pad stiffness": lambda sign, state: solve_members(
            _changed(reduced, stiffness=np.exp(sign * SIGMA["pad_stiffness"])), state[None])}, seed=16,
        full_contact=True)


def test_thickness_and_gas_spring_effects_are_the_shift_of_a_resolved_part(coarse_hood, physics):
    """Fails if the stated one-sigma effect of the sheet thickness or of the gas-spring force differs by more than 15
    % (+ 0.002 mm) from the estimate's shift on a part that really has that physics, made by another path than the
    first-order sensitivities the effects use: the embedded solver re-assembled and re-factorised at three thickness
    scales and interpolated (synthetic.standin, harness (ii)'s parts), the gas springs' own response scaled. Also
    fails if bases that carry the physical responses do not consider these two factors (they then left up to 0.011
    mm of a lock's error outside its stated uncertainty, benchmarks/RESULTS.md)."""
    standin = StandIn(coarse_hood.model, embedded_responses(coarse_hood.model))
    bases = dataclasses.replace(coarse_hood.bases, physics=physics)
    _check_effects(bases, {
        "sheet thickness": lambda sign, state: solve_members(
            standin.reduced(Family(thickness=float(np.exp(sign * SIGMA["thickness"])))), state[None]),
        "gas-spring force": lambda sign, state: solve_members(
            standin.reduced(Family(gas_spring=1.0 + sign * SIGMA["gas_spring"])), state[None])}, seed=17,
        full_contact=True)


def test_the_spread_is_the_prior_or_the_calibrations(coarse_hood, physics):
    """Fails if uncalibrated bases do not consider the issue's ranges as uniform half-widths (std = h / sqrt 3: E 3 %,
    thickness 5 %, pad stiffness 30 %, preload 50 % of the model's, gas-spring force 5 %), if bases without the
    physical responses claim to consider thickness or gas springs, or if calibrated bases do not take their
    calibration's fitted factor std per pad and for gas springs and thickness (a calibrated stiffness of 1 % must not
    still be considered uncertain by 17 %)."""
    model = coarse_hood.reduced
    pads = model.names[model.n_bilateral:]
    bare = {f.name: f for f in factor_spread(model)}
    assert set(bare) == {"compliance (Young's modulus)", "pad stiffness", "pad preload"}
    prior = {f.name: f for f in factor_spread(model, physics=physics)}
    assert set(prior) == set(bare) | {"sheet thickness", "gas-spring force"}
    s = SIGMA
    np.testing.assert_allclose(prior["compliance (Young's modulus)"].plus.H, np.exp(s["compliance"]) * model.H)
    np.testing.assert_allclose(prior["pad stiffness"].minus.k, np.exp(-s["pad_stiffness"]) * model.k)
    np.testing.assert_allclose(prior["pad preload"].plus.preload - model.preload,
                               s["preload"] * np.abs(model.preload))  # the hood's preload is uniform per pad
    np.testing.assert_allclose(prior["gas-spring force"].plus.w0 - model.w0, s["gas_spring"] * physics.gas_w,
                               atol=1e-12)
    skin_group = next(iter(physics.thickness))
    np.testing.assert_allclose(prior["sheet thickness"].plus.R - model.R,
                               s["thickness"] * sum(d.R for d in physics.thickness.values()), atol=1e-12)
    record = json.dumps({"factor_std": {"compliance": 0.004, f"pad_stiffness:{pads[0]}": 0.01,
                                        f"preload:{pads[0]}": 0.003, "gas_spring": 0.02,
                                        f"thickness:{skin_group}": 0.006}})
    calibrated = {f.name: f for f in factor_spread(model, record, physics)}
    assert set(calibrated) == {"calibrated compliance", f"calibrated pad stiffness of {pads[0]}",
                               f"calibrated preload of {pads[0]}", "calibrated gas spring",
                               f"calibrated thickness of {skin_group}"}
    springs = model.pad_of == 0
    np.testing.assert_allclose(calibrated[f"calibrated pad stiffness of {pads[0]}"].plus.k,
                               model.k * np.where(springs, np.exp(0.01), 1.0))
    np.testing.assert_allclose(calibrated[f"calibrated preload of {pads[0]}"].minus.preload,
                               model.preload - np.where(springs, 0.003, 0.0))
    np.testing.assert_allclose(calibrated["calibrated gas spring"].minus.z0 - model.z0, -0.02 * physics.gas_z,
                               atol=1e-12)
    np.testing.assert_allclose(calibrated[f"calibrated thickness of {skin_group}"].plus.G - model.G,
                               0.006 * physics.thickness[skin_group].G, atol=1e-12)
    assert "calibrated gas spring" not in {f.name for f in factor_spread(model, record)}


def test_a_factors_effect_is_the_estimates_shift_by_its_changed_field_at_the_same_state():
    """Fails if the stated effect of a factor differs (beyond 1e-9 mm) from the estimator's own shift when the field
    changes by what the factor changes in the part at the estimate's state and contact state: the changed model's
    field (w0' + R' a + G' f', f' solved here with the changed springs) added to a noise-free field and estimated
    again. That is factor_effects' definition, made by another path than its split through the normal matrix
    (model_spread.SkinChange): a factor scaling w0 and G (compliance), one changing the pads only (stiffness), and
    one changing w0, R and G arbitrarily, on a weighted fit (non-uniform node std, a third of the nodes unseen;
    without a pose the weight's scale cancels, so the shifted field has the same estimator) and an ordinary one. A
    wrong scale term, a remainder left out or the pads' forces taken at the nominal springs turn it red."""
    from dataclasses import replace

    from hood_decomp.core.method.contact_estimation import ContactEstimator
    from hood_decomp.core.method.model_spread import Factor
    from hood_decomp.core.method.residual import ResidualTest
    from tests.toy_models import make_reduced_model, make_skin

    skin = make_skin()
    model = make_reduced_model(skin, seed=0, springs_per_pad=3)
    rng = np.random.default_rng(5)
    n, s = skin.n_nodes, model.k.size

    def scaled(c: float):
        return replace(model, w0=c * model.w0, G=c * model.G, H=c * model.H, z0=c * model.z0)

    def general(sign: float):
        return replace(model, w0=(1 + 0.1 * sign) * model.w0 + sign * 0.01 * np.sin(skin.points[:, 0] / 40.0),
                       R=model.R + sign * 0.002 * rng.normal(size=model.R.shape),
                       G=(1 - 0.05 * sign) * model.G + sign * 2e-4 * rng.normal(size=(n, s)),
                       k=model.k * (1 + 0.1 * sign))

    factors = (Factor("compliance", scaled(1.03), scaled(1 / 1.03)),
               Factor("pads", replace(model, k=1.3 * model.k), replace(model, k=model.k / 1.3)),
               Factor("general", general(1.0), general(-1.0)))
    lower, upper = np.full(6, -1.0), np.full(6, 1.0)
    estimator = ContactEstimator().fit(model, lower, upper, ResidualTest().fit(skin), factors=factors)
    state = np.array([0.3, -0.2, 0.1, 0.4, 0.5, 0.6])  # both pads pressed: every spring touches
    a, b = state[:4], state[4:]

    def field(m):
        f = np.linalg.solve(np.diag(1.0 / m.k) + m.H, b[m.pad_of] + m.preload - m.z0 - m.Sa @ a)
        assert np.all(f > 0), "not every spring touches"
        return m.w0 + m.R @ a + m.G @ f

    unseen = skin.points[:, 1] < np.quantile(skin.points[:, 1], 0.33)
    std = 0.01 + 0.02 * rng.uniform(size=n)
    weighted = FieldErrorModel("scan", std, np.ones(n), 0.0)
    checked = 0
    for errors in (weighted, FieldErrorModel.none()):
        def estimate(values, errors=errors):
            return estimator.estimate(DisplacementField(skin.model_id, np.where(unseen, np.nan, values), 0.67,
                                                        float("nan"), errors))

        nominal = field(model)
        at = estimate(nominal)
        np.testing.assert_allclose(at.values, state, atol=1e-9)
        assert at.weighting == ("generalised" if errors is weighted else "ordinary")
        for factor, effect in zip(factors, at.model_effects, strict=True):
            up, down = (estimate(field(m)).values - at.values
                        for m in (factor.plus, factor.minus))
            expected = up if np.max(np.abs(up)) >= np.max(np.abs(down)) else -down
            np.testing.assert_allclose(effect, expected, atol=1e-9, err_msg=factor.name)
            checked += int(np.max(np.abs(expected)) > 1e-3)
    assert checked >= 4, "the factors hardly move the estimate: the comparison would be empty"
