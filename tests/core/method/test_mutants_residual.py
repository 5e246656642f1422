"""Residual analysis: noise levels, degrees of freedom, the Bonferroni threshold, ring averages, region areas,
statistics and order, refused inputs.

Written against the survivors of benchmarks/mutation.py. References: formulas of the module docstring evaluated
here with numpy/scipy, and a flat grid whose nodal areas are known exactly (dx dy for an interior node).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import chi2, norm

from hood_decomp.core.method.residual import (
    DEFAULT_NOISE_MM,
    analyse_residual,
    chi2_within,
    find_regions,
    noise_level,
)
from hood_decomp.errors import FieldError
from tests.toy_models import make_skin

NX, NY = 31, 21
SKIN = make_skin(NX, NY)  # 1500 x 1000 mm: dx = 50 mm, dy = 50 mm
FLAT = dataclasses.replace(SKIN, points=SKIN.points * [1.0, 1.0, 0.0])


def node(i: int, j: int) -> int:
    return i * NY + j


def test_default_noise_is_two_hundredths():
    """Fails if a field without a stated noise is not judged against 0.02 mm (smoothed structured-light scans)."""
    assert DEFAULT_NOISE_MM == 0.02
    analysis = analyse_residual(SKIN, np.zeros(SKIN.n_nodes), 0)
    assert (analysis.noise_mm, analysis.noise_source) == (0.02, "default")


@pytest.mark.parametrize("stated", [0.0, -0.01, float("nan"), float("inf"), None])
def test_only_a_finite_positive_noise_counts_as_stated(stated):
    """Fails if a zero, negative or non-finite noise is used instead of the default."""
    assert noise_level(stated, 0.03) == (0.03, "default")
    assert noise_level(0.01, 0.03) == (0.01, "stated")


@pytest.mark.parametrize("default", [0.0, -0.02])
def test_default_noise_must_be_positive(default):
    """Fails if a zero or negative default noise is accepted when the field states none."""
    with pytest.raises(FieldError, match="default scan noise must be > 0"):
        noise_level(None, default)


def test_zero_degrees_of_freedom_count_as_one():
    """Fails if chi2_within does not floor the degrees of freedom at 1 (a fit with as many unknowns as nodes)."""
    for dof in (0, -3):
        p_value, within = chi2_within(2.0, dof, 0.05)
        assert p_value == pytest.approx(chi2.sf(2.0, 1)) and within


def test_statistics_and_threshold_follow_their_definitions():
    """Fails if rms, max, mean, dof or the region threshold z (two-sided Bonferroni at alpha over the seen nodes)
    differ from their definitions."""
    rng = np.random.default_rng(5)
    residual = rng.normal(0.01, 0.02, SKIN.n_nodes)
    residual[:40] = np.nan
    analysis = analyse_residual(SKIN, residual, 7, noise_mm=0.02, model_mm=0.015, alpha=0.05)
    r = residual[40:]
    assert analysis.rms_mm == pytest.approx(np.sqrt(np.mean(r**2)), rel=1e-12)
    assert analysis.max_mm == pytest.approx(np.max(np.abs(r)))
    assert analysis.mean_mm == pytest.approx(np.mean(r))
    assert analysis.dof == SKIN.n_nodes - 40 - 7
    assert analysis.chi2 == pytest.approx(np.sum(r**2) / 0.025**2)
    assert analysis.threshold_sigmas == pytest.approx(norm.isf(0.05 / (2 * (SKIN.n_nodes - 40))), rel=1e-12)


def test_region_area_on_a_flat_grid():
    """Fails if a region's area is not the sum of its nodes' tributary areas: on a flat 50 mm grid every triangle has
    1250 mm^2, a third of it per corner (an interior node: 6 triangles, 2500 mm^2; a corner: 1 or 2)."""
    assert np.allclose(np.diff(np.unique(FLAT.points[:, 0])), 50.0)
    assert np.allclose(np.diff(np.unique(FLAT.points[:, 1])), 50.0)
    triangles_at = np.bincount(FLAT.triangles.ravel(), minlength=FLAT.n_nodes)
    for block in ([node(i, j) for i in range(10, 13) for j in range(8, 11)],
                  [node(NX - 1, 0), node(NX - 1, 1), node(NX - 2, 0), node(NX - 2, 1)],
                  [node(0, 0), node(0, 1), node(1, 0)]):
        residual = np.zeros(FLAT.n_nodes)
        residual[block] = 1.0
        regions = find_regions(FLAT, residual, 0.01, 4.0)
        assert len(regions) == 1
        nodes = regions[0].nodes
        assert set(block) <= set(nodes.tolist())
        assert regions[0].area_mm2 == pytest.approx(triangles_at[nodes].sum() * 1250.0 / 3.0, rel=1e-12)
    assert triangles_at[node(10, 10)] == 6


def test_a_single_spike_is_its_own_peak_and_centroid():
    """Fails if the one-ring mean leaves out the node itself: a lone 1 mm spike must be in its region, as its peak
    and (|r|-weighted) centroid."""
    spike = node(15, 10)
    residual = np.zeros(SKIN.n_nodes)
    residual[spike] = 1.0
    analysis = analyse_residual(SKIN, residual, 0, noise_mm=0.01)
    assert len(analysis.regions) == 1
    region = analysis.regions[0]
    assert spike in region.nodes and region.peak_node == spike and region.peak_mm == 1.0
    np.testing.assert_allclose(region.centroid, SKIN.points[spike], atol=1e-9)
    np.testing.assert_allclose(region.peak_point, SKIN.points[spike])


def test_region_statistics_follow_their_definitions():
    """Fails if a region's centroid, rms or energy differ from the |r|-weighted mean position, sqrt(mean r^2) and
    sum r^2 over its nodes."""
    residual = np.zeros(SKIN.n_nodes)
    patch = [node(i, j) for i in range(5, 9) for j in range(4, 8)]
    residual[patch] = np.linspace(0.5, 1.5, len(patch)) * np.where(np.arange(len(patch)) % 3, 1.0, -1.0)
    region = analyse_residual(SKIN, residual, 0, noise_mm=0.01).regions[0]
    r = residual[region.nodes]
    w = np.abs(r)
    np.testing.assert_allclose(region.centroid, w @ SKIN.points[region.nodes] / w.sum(), rtol=1e-12)
    assert region.rms_mm == pytest.approx(np.sqrt(np.mean(r**2)), rel=1e-12)
    assert region.energy_mm2 == pytest.approx(np.sum(r**2), rel=1e-12)
    assert region.peak_mm == residual[patch][np.argmax(np.abs(residual[patch]))]


def test_regions_are_ordered_by_energy():
    """Fails if regions are not listed largest residual energy first (the larger one is placed at higher node
    indices, so node order would list it last)."""
    residual = np.zeros(SKIN.n_nodes)
    residual[[node(3, 3), node(3, 4)]] = 0.5
    residual[[node(25, 15), node(25, 16), node(26, 15)]] = 1.0
    regions = analyse_residual(SKIN, residual, 0, noise_mm=0.01).regions
    assert len(regions) == 2
    assert regions[0].energy_mm2 > regions[1].energy_mm2
    assert node(25, 15) in regions[0].nodes


def test_unseen_nodes_add_nothing_to_their_neighbours():
    """Fails if an unseen node enters its neighbours' ring means as anything but absent: a zero residual with holes
    has no region."""
    residual = np.zeros(SKIN.n_nodes)
    residual[[node(i, j) for i in range(10, 20) for j in range(5, 15)]] = np.nan
    assert analyse_residual(SKIN, residual, 0, noise_mm=0.001).regions == ()


@pytest.mark.parametrize("residual, alpha, message", [
    (np.zeros(SKIN.n_nodes + 1), 0.01, "shape"),
    (np.zeros((SKIN.n_nodes, 1)), 0.01, "shape"),
    (np.zeros(SKIN.n_nodes), 0.0, "alpha"),
    (np.zeros(SKIN.n_nodes), -0.5, "alpha"),
    (np.zeros(SKIN.n_nodes), 1.0, "alpha"),
])
def test_more_bad_input_is_refused(residual, alpha, message):
    """Fails if a residual longer than the skin, a column, or alpha outside (0, 1) is accepted."""
    with pytest.raises(FieldError, match=message):
        analyse_residual(SKIN, residual, 0, noise_mm=0.01, alpha=alpha)
