"""Bases, build_bases, estimate_field and decompose_field on a toy model with planted truth (fast; the hood-sized
checks are in test_method_hood.py).

Written against the survivors of benchmarks/mutation.py. Truth comes from tests/toy_models.py (an exact, enumerated
contact solution) or from a plain numpy SVD of the ensemble, never from the code under test.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from hood_decomp.core.method.bases import Bases, build_bases, decompose_field, estimate_field
from hood_decomp.core.types import ParameterEstimate
from hood_decomp.errors import BasisError, FieldError, ModelIdMismatchError
from tests.toy_models import (
    field_of,
    full_factorial,
    make_ensemble,
    make_reduced_model,
    make_skin,
    random_states,
    simulate,
)


@pytest.fixture(scope="module")
def toy():
    """A 4 + 2 parameter toy model with two buffers, its full-factorial ensemble and its bases."""
    skin = make_skin(16, 12)
    model = make_reduced_model(skin, seed=5)
    states, rank = full_factorial(6)
    ensemble = make_ensemble(model, states, rank)
    return skin, model, ensemble, build_bases(ensemble, skin, model)


@pytest.fixture(scope="module")
def linear():
    """A linear 4-parameter toy model (no pads, 81 members): quick to build bases from."""
    skin = make_skin(12, 8)
    model = make_reduced_model(skin, seed=1, n_pads=0)
    states, rank = full_factorial(4)
    return skin, model, make_ensemble(model, states, rank)


def _svd_count(ensemble, fraction: float) -> int:
    """Components a plain PCA needs for ``fraction`` of the variance (numpy SVD of the centred fields)."""
    x = ensemble.normal_displacement - ensemble.normal_displacement.mean(axis=0)
    s2 = np.linalg.svd(x, compute_uv=False) ** 2
    return int(np.argmax(np.cumsum(s2) / s2.sum() >= fraction) + 1)


def test_defaults_are_the_papers(toy):
    """Fails if build_bases does not default to 10 PCA components and epsilon = 0.1 mm (section 3.1.2)."""
    skin, model, ensemble, bases = toy
    x = ensemble.normal_displacement - ensemble.normal_displacement.mean(axis=0)
    s = np.linalg.svd(x, compute_uv=False)
    assert bases.pca.n_components == 10
    assert bases.pca.n_components_ == min(10, int(np.count_nonzero(s > 1e-7 * s[0])))
    assert bases.hierarchical.epsilon_ == 0.1
    assert bases.model_id == ensemble.model_id and bases.skin is skin and bases.reduced_model is model
    assert bases.names == ensemble.names


def test_component_count_and_epsilon_are_passed_on(linear):
    """Fails if n_components, explained_variance or epsilon do not reach the bases."""
    skin, model, ensemble = linear
    assert build_bases(ensemble, skin, model, n_components=3).pca.n_components_ == 3
    chosen = build_bases(ensemble, skin, None, n_components=None, explained_variance=0.95, epsilon=0.01)
    assert chosen.pca.n_components_ == _svd_count(ensemble, 0.95) == 3
    assert chosen.hierarchical.epsilon_ == 0.01
    assert np.all(chosen.hierarchical.rank_max_error_ <= 0.01)
    assert chosen.reduced_model is None


def test_build_logs_the_explained_variance_of_the_kept_components(linear, caplog):
    """Fails if the log reports another cumulative explained variance than that of the components kept."""
    skin, model, ensemble = linear
    with caplog.at_level(logging.INFO, logger="hood_decomp.core.method.bases"):
        build_bases(ensemble, skin, model, n_components=2)
    x = ensemble.normal_displacement - ensemble.normal_displacement.mean(axis=0)
    s2 = np.linalg.svd(x, compute_uv=False) ** 2
    assert f"PCA: 2 components, cumulative explained variance {s2[:2].sum() / s2.sum():.8f}" in caplog.text


def test_notes_of_the_pca_are_logged(linear, caplog):
    """Fails if a cut component (asking 10 of a rank-4 ensemble) is not reported in the log."""
    skin, model, ensemble = linear
    with caplog.at_level(logging.INFO, logger="hood_decomp.core.method.bases"):
        build_bases(ensemble, skin, model)
    assert "ensemble supports only 4" in caplog.text


def test_a_skin_of_more_than_256_nodes_is_accepted():
    """Fails if the skin's node count is compared by identity instead of value (Python caches ints up to 256 only)."""
    skin = make_skin(24, 16)
    assert skin.n_nodes == 384
    model = make_reduced_model(skin, seed=1, n_pads=0)
    states, rank = full_factorial(4)
    bases = build_bases(make_ensemble(model, states, rank), skin, model, n_components=4)
    assert bases.pca.components_.shape == (4, 384)


def test_model_mismatch_is_refused(toy):
    """Fails if a skin or reduced model of another model, or a skin with another node count, is accepted."""
    skin, model, ensemble, _ = toy
    with pytest.raises(ModelIdMismatchError, match="skin model_id"):
        build_bases(ensemble, dataclasses.replace(skin, model_id="other"), model)
    with pytest.raises(ModelIdMismatchError, match="reduced model model_id"):
        build_bases(ensemble, skin, dataclasses.replace(model, model_id="other"))
    other = make_skin(16, 11)
    with pytest.raises(BasisError, match=f"skin has {other.n_nodes} nodes, ensemble fields have {skin.n_nodes}$"):
        build_bases(ensemble, dataclasses.replace(other, model_id=ensemble.model_id), None)


def test_estimate_field_defaults_to_the_contact_estimator(toy):
    """Fails if estimate_field does not default to the contact-aware estimator, which recovers the planted state
    exactly (bilateral and touching pads: commanded; lifted pads: the part's position)."""
    skin, model, _, bases = toy
    for state in random_states(model, 5, seed=3):
        truth = simulate(model, state)
        estimate = estimate_field(bases, field_of(skin, truth["w"]))
        assert estimate.method == "contact"
        np.testing.assert_allclose(estimate.values, truth["effective"], atol=1e-9)


def test_estimate_field_pca_and_unknown_methods(toy):
    """Fails if method="pca" is not the paper's estimator or an unknown method is not refused."""
    skin, model, _, bases = toy
    truth = simulate(model, np.array([0.5, -0.25, 0.75, 0.0, 0.5, 0.5]))
    estimate = estimate_field(bases, field_of(skin, truth["w"]), method="pca")
    assert estimate.method == "pca"
    np.testing.assert_allclose(estimate.values[:4], truth["effective"][:4], atol=0.05)
    with pytest.raises(BasisError, match="unknown estimation method 'lsq'"):
        estimate_field(bases, field_of(skin, truth["w"]), method="lsq")


@pytest.mark.parametrize("method", ["pca", "contact"])
def test_min_coverage_reaches_the_estimator(toy, method):
    """Fails if min_coverage is not passed on: a half-seen field passes at 0.4 and is refused at 0.6."""
    skin, model, _, bases = toy
    values = simulate(model, np.zeros(6))["w"].copy()
    values[skin.points[:, 0] > 750.0] = np.nan
    coverage = float(np.isfinite(values).mean())
    assert 0.4 < coverage < 0.6
    assert estimate_field(bases, field_of(skin, values), method, min_coverage=0.4).coverage == coverage
    with pytest.raises(FieldError, match="coverage"):
        estimate_field(bases, field_of(skin, values), method, min_coverage=0.6)


def test_contact_estimator_is_fitted_once_per_coverage(toy):
    """Fails if the fitted estimator is not kept (one per min_coverage) or is fitted with other ranges."""
    _, model, ensemble, bases = toy
    first = bases.contact_estimator()
    assert bases.contact_estimator() is first
    other = bases.contact_estimator(0.5)
    assert other is not first and other.min_coverage == 0.5 and bases.contact_estimator(0.5) is other
    assert first.min_coverage == 0.2
    np.testing.assert_array_equal(first.lower_, ensemble.lower)
    np.testing.assert_array_equal(first.upper_, ensemble.upper)
    assert first.model_ is model


def test_contact_estimator_needs_the_reduced_model(toy):
    """Fails if bases without a reduced model hand out a contact estimator instead of saying to use 'pca'."""
    skin, _, _, bases = toy
    bare = dataclasses.replace(bases, reduced_model=None)
    with pytest.raises(BasisError, match="use 'pca'"):
        bare.contact_estimator()
    with pytest.raises(BasisError, match="use 'pca'"):
        estimate_field(bare, field_of(skin, np.zeros(skin.n_nodes)))


def test_the_estimator_cache_is_not_part_of_the_value(toy):
    """Fails if the fitted-estimator cache takes part in equality, in the repr or in the constructor."""
    _, _, _, bases = toy
    bases.contact_estimator()
    fresh = dataclasses.replace(bases)
    assert fresh == bases
    assert "_contact_estimators" not in repr(bases)
    constructor = [f.name for f in dataclasses.fields(Bases) if f.init]
    assert "_contact_estimators" not in constructor
    with pytest.raises(TypeError):  # one value more than the constructor's fields: the cache is not among them
        Bases(*[getattr(bases, name) for name in constructor], {})  # type: ignore[call-arg]
    with pytest.raises(dataclasses.FrozenInstanceError):
        bases.model_id = "x"  # type: ignore[misc]


def test_decompose_field_passes_estimate_and_options(toy):
    """Fails if decompose_field drops the estimate (step 3) or the options (here min_coverage)."""
    skin, model, _, bases = toy
    state = np.array([0.0, 0.0, 0.75, -0.5, 0.0, 0.0])
    values = simulate(model, state)["w"]
    names = bases.names
    known = ParameterEstimate(bases.model_id, names, state, np.zeros(6), -np.ones(6), np.ones(6),
                              np.zeros(6, dtype=bool), np.zeros(1), np.zeros(1), 0.0, 0.0, 1.0, True, "contact")
    decomposition = decompose_field(bases, field_of(skin, values), known, min_share=0.0, max_removed_rms_mm=0.0)
    for effect in decomposition.effects:
        assert set(effect.parameters) <= {"LOCK_L", "LOCK_R"}
    assert "LOCK_L" in [e.name for e in decomposition.effects]
    half = values.copy()
    half[skin.points[:, 0] > 750.0] = np.nan
    with pytest.raises(FieldError, match="coverage"):
        decompose_field(bases, field_of(skin, half), None, min_coverage=0.6)
