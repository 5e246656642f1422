"""Tail probabilities of the tests' reference distributions (chi-square, F, Student's t, normal), from
:mod:`scipy.special`.

scipy.stats computes these with the same scipy.special functions but costs about 1 s of imports (its distribution
classes and docstrings are built at import time), more than a whole one-off ``estimate`` of a scan; these give the
same numbers (scipy.stats' ``_sf``/``_isf`` of these distributions are these calls), with a statistic below the
support (x < 0) taken as 0 as scipy.stats does. Elementwise: floats or numpy arrays. scipy.special is imported at
the first call, not with this module: since scipy 1.17 any scipy subpackage costs about 0.16 s of imports (it
clones every numpy submodule), which ``hood-decomp --help`` and verbs that test nothing need not pay.
"""

from __future__ import annotations

import numpy as np

__all__ = ["chi2_isf", "chi2_sf", "f_sf", "norm_isf", "t_sf"]


def _special():  # -> the scipy.special module
    from scipy import special

    return special


def chi2_sf(x, dof):
    """P(X > x) for X chi-square with ``dof`` degrees of freedom (scipy.stats.chi2.sf)."""
    return _special().chdtrc(dof, np.maximum(x, 0.0))


def chi2_isf(p, dof):
    """The x with P(X > x) = p for X chi-square with ``dof`` degrees of freedom (scipy.stats.chi2.isf)."""
    return _special().chdtri(dof, p)


def f_sf(x, dof1, dof2):
    """P(X > x) for X F-distributed with (``dof1``, ``dof2``) degrees of freedom (scipy.stats.f.sf)."""
    return _special().fdtrc(dof1, dof2, np.maximum(x, 0.0))


def t_sf(x, dof):
    """P(X > x) for X Student-t with ``dof`` degrees of freedom (scipy.stats.t.sf)."""
    return _special().stdtr(dof, -np.asarray(x))


def norm_isf(p):
    """The z with P(Z > z) = p for a standard normal Z (scipy.stats.norm.isf)."""
    return -_special().ndtri(p)
