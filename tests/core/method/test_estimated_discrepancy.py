"""The within-model test with a model discrepancy estimated from a handful of samples (a calibration's entries).

Truth made by construction: a discrepancy delta = L z (z ~ N(0, I), L smooth fields) is drawn 13 times and its
covariance estimated from those draws (D = [delta_1 ... delta_13] / sqrt(13), exactly what a 13-entry calibration
hands the bases); parts are new draws of delta plus white noise, each judged by the one within-model test. With the
estimate taken as exact (chi-square / F reference), good parts alarm far above the nominal 1 %; with its 13 degrees
of freedom (Hotelling-type reference, ``discrepancy_dof``) the rate is back near 1 %."""

from __future__ import annotations

import numpy as np

from hood_decomp.core.method.residual import ResidualTest
from hood_decomp.core.types import FieldErrorModel
from tests.toy_models import make_skin, smooth_fields

SKIN = make_skin(40, 28)  # 1,120 nodes
SIGMA = 0.01
ENTRIES = 13


def _false_alarms(dof: float, calibrations: int = 12, parts: int = 100) -> float:
    rng = np.random.default_rng(16)
    fields = smooth_fields(SKIN.points, 8, rng, scale=0.02).T  # (N, 8): the true discrepancy's L, mm
    errors = FieldErrorModel.stated(SIGMA, SKIN.n_nodes)
    alarms = 0
    for _ in range(calibrations):
        sampled = fields @ rng.normal(size=(fields.shape[1], ENTRIES)) / np.sqrt(ENTRIES)
        test = ResidualTest().fit(SKIN, sampled, dof)
        for _ in range(parts):
            residual = fields @ rng.normal(size=fields.shape[1]) + rng.normal(0.0, SIGMA, SKIN.n_nodes)
            alarms += not test.check(residual, None, errors).within_model
    return alarms / (calibrations * parts)


def test_an_estimated_discrepancy_keeps_the_false_alarm_rate_nominal():
    """Fails if the within-model test takes a discrepancy covariance estimated from 13 samples as exact (its
    false-alarm rate on good parts is then several times the nominal 1 %: checked, so the setting has teeth), if the
    degrees of freedom of the estimate do not bring it to at most 3 % over 1,200 good parts, or if it never alarms (a
    reference law far too wide)."""
    exact = _false_alarms(np.inf)
    estimated = _false_alarms(float(ENTRIES))
    assert exact >= 0.05, f"taken as exact, the estimate should alarm often: {exact:.3f}"
    assert 0.0 < estimated <= 0.03, f"false-alarm rate with {ENTRIES} dof: {estimated:.3f} (exact: {exact:.3f})"
