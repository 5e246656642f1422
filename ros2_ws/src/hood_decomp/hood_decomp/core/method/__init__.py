"""The paper's method: PCA basis (section 3.1.2), hierarchical basis (Fig. 5), the paper's and the contact-aware
estimators with their shared least squares (eq. 5), decomposition and contributions (eqs. 6-8), the residual test, the
correction for the adjustment robot, the interaction map of an ensemble, and the :class:`Bases` that bundles them.

May import: ``hood_decomp.core.types`` and ``hood_decomp.errors`` only (never ``fe``, ``scan`` or ``loop``).
"""

from hood_decomp.core.method.bases import (
    Bases,
    analyse_estimate,
    build_bases,
    decompose_field,
    estimate_field,
    node_field,
)
from hood_decomp.core.method.contact_estimation import ContactEstimator
from hood_decomp.core.method.correction import CorrectionPolicy, plan_correction
from hood_decomp.core.method.decomposition import decompose
from hood_decomp.core.method.estimation import estimate_pca
from hood_decomp.core.method.hierarchical import HierarchicalBasis
from hood_decomp.core.method.interactions import InteractionMap, interaction_map
from hood_decomp.core.method.pca import PCABasis
from hood_decomp.core.method.residual import analyse_residual

__all__ = [
    "Bases", "ContactEstimator", "CorrectionPolicy", "HierarchicalBasis", "InteractionMap", "PCABasis",
    "analyse_estimate", "analyse_residual", "build_bases", "decompose", "decompose_field", "estimate_field",
    "estimate_pca", "interaction_map", "node_field", "plan_correction",
]
