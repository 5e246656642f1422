"""decompose: step 3's subset, step 5's defaults and stopping, eqs. 6-8 against numpy least squares, and the zero
field.

Written against the survivors of benchmarks/mutation.py. References: numpy lstsq of the field on every basis field
(the full-basis decomposition is then a plain linear fit), fields planted from single effects of a linear toy model,
and the definitions of the module docstring (contributions and shares 0 where D = 0).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from hood_decomp.core.method import decomposition as dec
from hood_decomp.core.method.decomposition import decompose, select_effects
from hood_decomp.core.method.hierarchical import HierarchicalBasis
from hood_decomp.core.types import ParameterEstimate
from hood_decomp.errors import BasisError
from tests.core.method.test_mutants_hierarchical import random_ensemble
from tests.toy_models import field_of, full_factorial, make_ensemble, make_reduced_model, make_skin


@pytest.fixture(scope="module")
def linear():
    skin = make_skin()
    model = make_reduced_model(skin, seed=9, n_pads=0)
    states, rank = full_factorial(4)
    return skin, model, HierarchicalBasis(epsilon=0.01).fit(make_ensemble(model, states, rank))


def estimate_of(basis, values, names=None, lifted=None, std=None) -> ParameterEstimate:
    n = len(basis.names_)
    return ParameterEstimate(
        basis.model_id_, tuple(names if names is not None else list(basis.names_)), np.asarray(values, float),
        np.zeros(n) if std is None else np.asarray(std, float), -np.ones(n), np.ones(n),
        np.zeros(n, bool) if lifted is None else np.asarray(lifted, bool), np.zeros(1), np.zeros(1), 0.0, 0.0, 1.0,
        True, "contact")


def _rms(field: np.ndarray) -> float:
    return float(np.sqrt(np.mean(field**2)))


def test_defaults_are_the_documented_ones():
    """Fails if the step 3 and step 5 defaults drift (2 % share, 0.002 mm RMS, 0.01 mm zero tolerance)."""
    assert (dec.DEFAULT_MIN_SHARE, dec.DEFAULT_MAX_REMOVED_RMS_MM, dec.DEFAULT_ZERO_TOL_MM) == (0.02, 0.002, 0.01)


def test_small_effects_with_real_shares_are_kept_at_the_defaults(linear):
    """Fails if step 5 at its defaults removes an effect holding a third of the share (both effects below the
    0.002 mm RMS guard, so only the 2 % share keeps them)."""
    skin, model, basis = linear
    a = 0.001 / _rms(model.R[:, 2])
    b = 0.0005 / _rms(model.R[:, 3])
    values = a * model.R[:, 2] + b * model.R[:, 3]
    result = decompose(basis, field_of(skin, values))
    assert {e.name for e in result.effects} == {"LOCK_L", "LOCK_R"}
    assert result.reconstruction_rms < 1e-12


def test_coarsening_stops_at_one_effect(linear):
    """Fails if step 5 does not stop with the one effect a single-parameter field holds (all others are zero)."""
    skin, model, basis = linear
    result = decompose(basis, field_of(skin, 0.5 * model.R[:, 1]))
    assert [e.name for e in result.effects] == ["HINGE_Y"]
    assert result.effects[0].share == 1.0
    np.testing.assert_allclose(result.effects[0].contribution[result.effects[0].partial_displacement > 0], 1.0)


def test_a_zero_field_has_no_shares(linear):
    """Fails if a zero field gets a share or a contribution other than 0 (D = 0 everywhere), or warns."""
    skin, _, basis = linear
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = decompose(basis, field_of(skin, np.zeros(skin.n_nodes)))
    assert result.effects  # nothing to remove: every magnitude is 0, none below 2 % of 0
    for effect in result.effects:
        assert effect.share == 0.0
        assert np.all(effect.contribution == 0.0) and np.all(effect.partial_displacement == 0.0)


def test_names_must_match_exactly(linear):
    """Fails if an estimate with other parameter names (ordered before or after the basis' names) is accepted, or
    one with equal names given as another tuple is refused."""
    skin, model, basis = linear
    values = 0.5 * model.R[:, 1]
    equal = estimate_of(basis, [0.0, 0.5, 0.0, 0.0], names=[str(n) for n in basis.names_])
    assert equal.names is not basis.names_
    assert [e.name for e in decompose(basis, field_of(skin, values), equal).effects] == ["HINGE_Y"]
    for names in (("A", "B", "C", "D"), ("Z", "Y", "X", "W"), tuple(reversed(basis.names_))):
        with pytest.raises(BasisError, match="differ from the basis parameters"):
            select_effects(basis, estimate_of(basis, np.zeros(4), names=names), 0.01)


def test_step3_zero_test_uses_three_std_and_keeps_lifted(linear):
    """Fails if a parameter counts as zero other than |value| <= max(zero_tol, 3 std), or a lifted one is dropped,
    or the test warns."""
    _, _, basis = linear
    names = basis.effect_names_

    def kept(values, std=None, lifted=None):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            mask = select_effects(basis, estimate_of(basis, values, std=std, lifted=lifted), 0.01)
        return {names[i] for i in np.flatnonzero(mask)}

    assert kept([0.5, 0.0, 0.0, 0.0]) == {"LOADS", "HINGE_X"}
    assert kept([0.5, 0.01, 0.0, 0.0]) == {"LOADS", "HINGE_X"}
    assert kept([0.5, 0.0101, 0.0, 0.0]) == {"LOADS", "HINGE_X", "HINGE_Y"}
    assert kept([0.5, 0.2, 0.0, 0.0], std=[0.0, 0.07, 0.0, 0.0]) == {"LOADS", "HINGE_X"}
    assert kept([0.5, 0.22, 0.0, 0.0], std=[0.0, 0.07, 0.0, 0.0]) == {"LOADS", "HINGE_X", "HINGE_Y"}
    assert kept([0.5, 0.0, 0.0, 0.0], lifted=[False, True, False, False]) == {"LOADS", "HINGE_X", "HINGE_Y"}
    assert kept([0.5, 0.0, 0.0, 0.0], std=[0.0, np.nan, 0.0, 0.0]) == {"LOADS", "HINGE_X"}
    assert select_effects(basis, None, 0.01).all()


@pytest.mark.parametrize("seed", [11, 12])
def test_full_basis_decomposition_is_the_least_squares_fit(seed):
    """Fails if, with every effect kept, the coefficients or eq. 6's partial displacements differ from numpy's
    least squares on all basis fields (a random design: every field independent, every effect with two)."""
    ensemble = random_ensemble(2, seed)
    basis = HierarchicalBasis(epsilon=1e-6).fit(ensemble)
    assert basis.independent_.all()
    skin = make_skin(12, 8)
    values = np.random.default_rng(seed).normal(size=len(basis.fields_)) @ basis.fields_
    coeff = np.linalg.lstsq(basis.fields_.T, values, rcond=None)[0]
    result = decompose(basis, field_of(skin, values), min_share=0.0)
    assert len(result.effects) == len(basis.effect_names_)
    for effect in result.effects:
        e = basis.effect_names_.index(effect.name)
        idx = [i for i in basis.effect_fields_[e] if i >= 0]
        expected = np.linalg.norm(np.tensordot(coeff[idx], basis.fields_3d_[idx], axes=1), axis=1)
        np.testing.assert_allclose(effect.partial_displacement, expected, atol=1e-9)
    np.testing.assert_allclose(result.reconstruction, values, atol=1e-9)
