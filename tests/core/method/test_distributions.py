"""The tests' tail probabilities from scipy.special (core/method/distributions.py) against scipy.stats."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from hood_decomp.core.method.distributions import chi2_isf, chi2_sf, f_sf, norm_isf, t_sf

STATISTICS = np.array([-1.0, 0.0, 1e-300, 0.3, 1.0, 2.5, 12.0, 80.0, 1e4, np.inf])
DOFS = (1, 2, 3.7, 25, 1000.0)


@pytest.mark.parametrize("dof", DOFS)
def test_tail_probabilities_equal_scipy_stats(dof):
    """Fails if a tail probability differs from scipy.stats' (relative 1e-12, exact at the ends): swapped arguments
    (fdtrc's degrees of freedom, stdtr's sign), a lower tail for an upper one, or a statistic below the support
    (a negative rounding residue) not taken as 0 as scipy.stats does."""
    np.testing.assert_allclose(chi2_sf(STATISTICS, dof), stats.chi2.sf(STATISTICS, dof), rtol=1e-12, atol=0)
    np.testing.assert_allclose(t_sf(STATISTICS, dof), stats.t.sf(STATISTICS, dof), rtol=1e-12, atol=0)
    np.testing.assert_allclose(t_sf(-STATISTICS, dof), stats.t.sf(-STATISTICS, dof), rtol=1e-12, atol=0)
    for dof1 in (1, 4, 30):
        np.testing.assert_allclose(f_sf(STATISTICS, dof1, dof), stats.f.sf(STATISTICS, dof1, dof), rtol=1e-12,
                                   atol=0)  # fmt: skip
    p = np.array([1e-300, 1e-12, 1e-3, 0.05, 0.5, 0.999])
    np.testing.assert_allclose(chi2_isf(p, dof), stats.chi2.isf(p, dof), rtol=1e-12, atol=0)
    assert float(chi2_sf(3.0, 2)) == pytest.approx(np.exp(-1.5), rel=1e-14)  # closed form for 2 degrees of freedom


def test_normal_quantile_equals_scipy_stats():
    """Fails if the upper normal quantile differs from scipy.stats' or has the wrong sign (z(0.025) = 1.95996...)."""
    p = np.array([1e-300, 1e-12, 1e-3, 0.025, 0.5, 0.9])
    np.testing.assert_allclose(norm_isf(p), stats.norm.isf(p), rtol=1e-12, atol=1e-300)
    assert float(norm_isf(0.025)) == pytest.approx(1.959963984540054, rel=1e-14)
