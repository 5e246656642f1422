"""Closing the loop on missing effects that are not a candidate column (issue 14), on the coarse hood.

Each truth is made by the FE model with a physical change the candidates do not contain, through its own solver
(a model factorised anew, or ``simulate_setting``), never through the candidate or augmentation code:

- a hinge moved obliquely (between two candidate directions) -> both candidates named, their magnitudes within 3 std
  of the move's projections, the fields back within the model;
- a candidate's move applied at a patch shifted by 30 mm -> that candidate named, status "partial", the residual RMS
  at least halved;
- a 10 % stiffer region of the inner panel -> no boundary named, "unexplained";
- a gas spring acting 10 deg off its axis -> the spring named by its force candidate (on the skin the off-axis force
  is, within the noise, an axial force change: the boundary at fault, with its equivalent force);
- a field made by CalculiX -> a within-model alarm and no boundary named.
In every case the declared estimates are no worse after than before, and the before/after report says what happened.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hood_decomp.core.fe.ensemble import simulate_setting, solve_members
from hood_decomp.core.fe.solver import build_solver, reduce_model
from hood_decomp.core.loop.candidates import candidate_fields, enumerate_candidates
from hood_decomp.core.loop.close_loop import PARTIAL_MIN, close_loop, trace_effect
from hood_decomp.core.method.bases import estimate_field
from hood_decomp.core.types import DisplacementField
from hood_decomp.io.close_loop_report import close_loop_report

TRUTH = {"HINGE_X": 0.3, "HINGE_Y": -0.4, "LOCK_L": 0.6, "LOCK_R": -0.5, "BUFFER_L": 0.4, "BUFFER_R": -0.3}
DECLARED = tuple(TRUTH)


@pytest.fixture(scope="module")
def candidates(coarse_hood):
    return candidate_fields(coarse_hood.solver, enumerate_candidates(coarse_hood.model))


def noisy(hood, values: np.ndarray, sigma: float, seed: int) -> DisplacementField:
    noise = np.random.default_rng(seed).normal(0.0, sigma, values.shape)
    return DisplacementField(hood.model.model_id, values + noise, 1.0, sigma)


def member(reduced, setting: dict[str, float]) -> np.ndarray:
    """Skin normal displacement (N,) mm of ``setting`` (labels of ``reduced``; others 0) with exact pad contact."""
    return solve_members(reduced, np.array([[setting.get(n, 0.0) for n in reduced.names]])).normal_displacement[0]


def with_boundary(model, name: str, **changes):
    """The model with boundary ``name`` changed (dataclasses.replace of the Boundary)."""
    return dataclasses.replace(model, boundaries=tuple(
        dataclasses.replace(b, **changes) if b.name == name else b for b in model.boundaries))


def declared_errors(estimate) -> dict[str, float]:
    """label -> |error| of the declared parameters whose commanded value the field shows (not reported lifted)."""
    return {n: abs(float(v) - TRUTH[n]) for n, v, lifted in zip(estimate.names, estimate.values, estimate.lifted,
                                                                strict=True) if n in TRUTH and not lifted}


def assert_declared_no_worse(before, after) -> None:
    """Every declared parameter seen before is seen after, and none is worse than the worst before (or than 3 of its
    own std after, where the before error was already at the noise)."""
    errors_before, errors_after = declared_errors(before), declared_errors(after)
    assert set(errors_after) >= set(errors_before)
    worst_before = max(errors_before.values())
    for name, error in errors_after.items():
        std = float(after.std[after.names.index(name)])
        assert error <= max(worst_before, 3.0 * std), (name, error, worst_before)


def trace(hood, candidates, field):
    bases = hood.bases
    before = estimate_field(bases, field)
    return before, trace_effect(bases.reduced_model, bases.pca.lower_, bases.pca.upper_, [field], candidates,
                                [before], [field.noise_rms], bases.residual_test())


def test_oblique_hinge_move_names_both_candidates(coarse_hood, candidates):
    """Fails if a hinge moved between two candidate directions (x 0.5, z 0.3 mm) is not named as the pair of both,
    with magnitudes within 3 std of the move's projections and the field back within the model (e.g. pairs never
    tried, a pair that misses the best single, or a single forced onto it as "found")."""
    move = {"hinge_R.x": 0.5, "hinge_R.z": 0.3}
    exact = simulate_setting(coarse_hood.solver, {**TRUTH, **move}).normal_displacement
    for seed in (1, 2):
        before, result = trace(coarse_hood, candidates, noisy(coarse_hood, exact, 0.005, seed))
        assert result.outcome == "found" and set(result.named) == set(move), result.reason
        assert not result.within_after  # the best single alone does not close the gap
        pair = result.pairs[0]
        assert pair.within_after and pair.p_adjusted < 0.01
        for j, name in enumerate(pair.names):
            assert abs(pair.values[0, j] - move[name]) <= 3.0 * pair.std[0, j] + 1e-4, (name, pair.values[0, j])
        assert_declared_no_worse(before, result.named_estimates[0])


def test_an_undecidable_second_effect_is_not_named(coarse_hood, candidates):
    """Fails if, where two pairs explain a field alike, one of them is named anyway. On the skin an in-plane move of
    hinge_R along y or along x looks alike next to the declared HINGE_X/HINGE_Y (x 0.3 with z 0.4 mm at 0.02 mm noise:
    likelihood ratio ~2.5 between the pairs): only hinge_R.z, which both share, is added, as "partial"."""
    exact = simulate_setting(coarse_hood.solver, {**TRUTH, "hinge_R.y": 0.4, "hinge_R.z": 0.3}).normal_displacement
    _, result = trace(coarse_hood, candidates, noisy(coarse_hood, exact, 0.02, 7))
    assert result.outcome == "partial" and result.named == ("hinge_R.z",), result.reason
    assert result.pairs[0].within_after and result.pairs[1].within_after
    assert "alike" in result.reason


def test_move_at_a_shifted_patch_is_partial(coarse_hood, candidates):
    """Fails if hinge_R raised 0.5 mm at a patch 30 mm from the candidate's is not named as hinge_R.z with status
    "partial" (the residual RMS at least halved with it, but not back to noise), if the approximate column is added
    anyway (on this field it would move HINGE_X from 0.15 to 0.32 mm off), or if the report says otherwise than the
    estimates."""
    patch = coarse_hood.model.boundary("hinge_R").patch
    centre = patch.center
    shifted = with_boundary(coarse_hood.model, "hinge_R",
                            patch=dataclasses.replace(patch, center=(centre[0] - 30.0, centre[1], centre[2])))
    exact = simulate_setting(build_solver(shifted), {**TRUTH, "hinge_R.z": 0.5}).normal_displacement
    field = noisy(coarse_hood, exact, 0.01, 3)
    result = close_loop(coarse_hood.bases, [field], candidates, ensemble=coarse_hood.ensemble)
    assert result.status == "partial", result.message
    trace = result.traces[0]
    assert trace.named == ("hinge_R.z",) and trace.best.explained >= PARTIAL_MIN and not trace.within_after
    assert result.added == () and result.bases_after is None and result.after == ()  # declared estimates unchanged
    before = result.analyses_before[0]
    named = trace.named_estimates[0]
    with_it = float(np.sqrt(np.nansum(named.residual**2) / before.n_seen))
    assert with_it <= 0.5 * before.rms_mm
    assert abs(trace.best.values[0] - 0.5) < 0.15  # the nearest candidate's equivalent move
    # the approximate column would make a declared estimate worse, which is why it is not added
    assert max(declared_errors(named).values()) > max(declared_errors(result.before[0]).values())
    payload = close_loop_report(result, [{**TRUTH, "hinge_R.z": 0.5}])
    assert payload["status"] == "partial" and payload["within_model_after"] is None
    assert payload["effects_found"] == [] and payload["residual_rms_before_mm"] == [before.rms_mm]
    assert payload["effects_named"][0]["name"] == "hinge_R.z"
    assert payload["effects_named"][0]["residual_rms_with_it_mm"] == [pytest.approx(with_it)]
    assert payload["traces"][0]["outcome"] == "partial" and payload["traces"][0]["named"] == ["hinge_R.z"]
    assert "partial, nothing added" in result.message and "hinge_R.z" in result.message


def test_stiffer_inner_panel_region_is_unexplained(coarse_hood, candidates):
    """Fails if a 10 % stiffer region of the inner panel (radius 250 mm), which no boundary input makes, is forced onto
    a candidate, or is not seen at all (the within-model test must alarm at 0.005 mm noise)."""
    model = coarse_hood.model
    centres = model.nodes[model.cells].mean(axis=1)
    region = (model.cell_part == model.part_index("inner_panel")) & (
        np.hypot(centres[:, 0] - 600.0, centres[:, 1] + 300.0) < 250.0)
    factor = np.where(region, 1.1, 1.0)
    exact = member(reduce_model(build_solver(model, stiffness_factor=factor)), TRUTH)
    field = noisy(coarse_hood, exact, 0.005, 4)
    result = close_loop(coarse_hood.bases, [field], candidates, ensemble=coarse_hood.ensemble)
    assert not result.within_model_before
    assert result.status == "unexplained", result.message
    assert result.added == () and result.bases_after is None
    assert result.traces[0].best.explained < PARTIAL_MIN


def test_gas_spring_off_axis_names_the_spring(coarse_hood, candidates):
    """Fails if a gas spring pushing 10 deg off its axis (in its X-Z plane) is traced to another boundary, or is not
    seen. On the skin its field is, within the noise, that of an axial force change (the field is back within the
    model with it), so the spring's force candidate, the boundary at fault, is the honest answer."""
    boundary = coarse_hood.model.boundary("gas_spring_R")
    axis = np.asarray(boundary.axis)
    turn = np.radians(10.0)
    rotated = np.cos(turn) * axis + np.sin(turn) * np.array([-axis[2], 0.0, axis[0]])
    model = with_boundary(coarse_hood.model, "gas_spring_R", axis=tuple(float(v) for v in rotated))
    exact = member(reduce_model(build_solver(model)), TRUTH)
    before, result = trace(coarse_hood, candidates, noisy(coarse_hood, exact, 0.01, 5))
    assert result.outcome == "found" and result.named == ("gas_spring_R.force",), result.reason
    assert result.within_after
    assert_declared_no_worse(before, result.named_estimates[0])


def test_calculix_field_alarms_and_names_nothing(coarse_hood, candidates, coarse_calculix_columns):
    """Fails if a part made by another FE solver (CalculiX S8R, both locks up and both buffers lowered so that the
    pads lift by more than 1 mm) passes the within-model test, or if the model difference is traced to a boundary."""
    setting = {**TRUTH, "LOCK_R": 0.5, "BUFFER_L": -1.0, "BUFFER_R": -1.0}
    lifted = solve_members(coarse_hood.reduced, np.array([[setting[n] for n in coarse_hood.reduced.names]]))
    assert np.all(lifted.contact_fraction == 0.0)  # no pad force: the load and unit responses make the field
    skin, normals = coarse_hood.model.skin_nodes, coarse_hood.skin.normals
    displacement = coarse_calculix_columns["load"][skin] + sum(
        setting[p.label] * coarse_calculix_columns[f"unit_{p.label}"][skin] for p in coarse_hood.model.bilateral)
    exact = np.einsum("na,na->n", displacement, normals)
    field = noisy(coarse_hood, exact, 0.01, 6)
    result = close_loop(coarse_hood.bases, [field], candidates, ensemble=coarse_hood.ensemble)
    assert not result.within_model_before and result.p_value_before < 1e-6
    assert result.status in ("unexplained", "ambiguous"), result.message
    assert result.added == ()
