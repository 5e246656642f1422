"""PCA basis of an ensemble (paper section 3.1.2, Fig. 8).

Every member is condensed to the signed normal displacement of the visible skin; PCA of those scalar fields gives,
per principal component, weights over the members. The same weights applied to the members' 3D displacement fields
and to their parameter states turn each component into a pair (3D basis field, parameter state): eqs. (4)-(5) then
estimate a parameter state by the same linear combination that reconstructs the field.

Deviation from a plain PCA, on purpose: components whose singular value is below ``rtol`` times the largest are cut
(and reported in ``notes_``) even when asked for, because their weights are 1 / singular value: a component the data
does not support turns round-off into parameter states of size 1e13.
"""

from __future__ import annotations

import copy

import numpy as np

from hood_decomp.core.types import Ensemble
from hood_decomp.errors import BasisError

_MIN_MEMBERS = 3
# Leading eigenpairs computed at least, when a component count is given (the explained-variance curve, Fig. 8).
CURVE_LENGTH = 20


class PCABasis:
    """PCA basis fields with their parameter states (section 3.1.2).

    Parameters
    ----------
    n_components: number of components to keep (paper: 10), or None to choose by ``explained_variance``.
    explained_variance: cumulative explained variance ratio to reach (e.g. 0.999999) when ``n_components`` is None.
    rtol: singular values below ``rtol * s_max`` are not supported by the data and are always cut.

    Fitted attributes (N skin nodes, K components, P parameters, U unilateral parameters, M members):
    model_id_, names_, n_bilateral_, lower_, upper_: copied from the ensemble.
    mean_field_ (N,) mm, mean_field_3d_ (N, 3) mm, mean_state_ (P,) mm (effective states), mean_reaction_ (U,) N.
    components_ (K, N) mm: normal basis fields B_k; components_3d_ (K, N, 3) mm; component_states_ (K, P) mm;
    component_reactions_ (K, U) N.
    singular_values_ (C,): leading singular values of the centred ensemble (C = all M when choosing by explained
    variance, else max(K + 1, 20) capped at M), for the Fig. 8 curve.
    explained_variance_ratio_ (C,): per component, relative to the total variance; n_components_ = K;
    reaction_scale_ (U,) N, the largest reaction per unilateral boundary in the ensemble;
    training_residual_rms_ mm, worst member's RMS residual when reconstructed with K components (the model error
    floor); gram_ (K, K) B B^T over all nodes; notes_: human-readable remarks (cut components).
    """

    def __init__(self, n_components: int | None = 10, explained_variance: float | None = None, rtol: float = 1e-7):
        self.n_components = n_components
        self.explained_variance = explained_variance
        self.rtol = rtol

    def fit(self, ensemble: Ensemble) -> PCABasis:
        """Build the basis from ``ensemble`` (its ``effective`` states are the component states)."""
        x = np.asarray(ensemble.normal_displacement, dtype=float)
        m = x.shape[0]
        if m < _MIN_MEMBERS:
            raise BasisError(f"PCA needs at least {_MIN_MEMBERS} ensemble members, got {m}")
        if not np.all(np.isfinite(x)):
            raise BasisError("ensemble normal displacement holds NaN or inf values; members must be complete fields")
        if self.n_components is None and self.explained_variance is None:
            raise BasisError("give n_components or explained_variance")
        if self.n_components is not None and self.n_components < 1:
            raise BasisError(f"n_components must be >= 1, got {self.n_components}")
        if self.explained_variance is not None and not 0.0 < self.explained_variance <= 1.0:
            raise BasisError(f"explained_variance must be in (0, 1], got {self.explained_variance}")

        mean = x.mean(axis=0)
        xc = x - mean
        # Gram matrix route: M x M eigenproblem instead of an SVD of the M x N matrix (N ~ 2e5 >> M ~ 7e2). With a
        # component count only the leading eigenpairs are computed (at least CURVE_LENGTH, for the Fig. 8 curve);
        # the total variance is the trace, so the ratios stay exact.
        gram = xc @ xc.T
        import scipy.linalg  # fitting only: a verb that loads fitted bases does not pay its import

        total = float(np.trace(gram))
        if self.n_components is not None and self.n_components + 1 < m:
            count = min(m, max(self.n_components + 1, CURVE_LENGTH))
            eigval, eigvec = scipy.linalg.eigh(gram, subset_by_index=[m - count, m - 1], driver="evr")
        else:
            eigval, eigvec = scipy.linalg.eigh(gram)
        order = np.argsort(eigval)[::-1]
        eigval = np.clip(eigval[order], 0.0, None)
        eigvec = eigvec[:, order]
        singular = np.sqrt(eigval)
        ratio = eigval / total if total > 0 else np.zeros_like(eigval)

        supported = int(np.count_nonzero(singular > self.rtol * singular[0])) if singular[0] > 0 else 0
        if supported == 0:
            raise BasisError("the ensemble has no variance: every member has the same field")
        if self.n_components is not None:
            wanted = int(self.n_components)
        else:
            wanted = int(np.searchsorted(np.cumsum(ratio), self.explained_variance - 1e-15) + 1)
        notes = []
        if wanted > supported:
            notes.append(
                f"asked for {wanted} components but the ensemble supports only {supported} "
                f"(singular values below {self.rtol:g} x largest are round-off); using {supported}"
            )
        k = min(wanted, supported)

        # Component k as a combination of centred members: weights U_k / s_k (so the normal field is unit length).
        weights = eigvec[:, :k] / singular[:k]
        self.model_id_ = ensemble.model_id
        self.names_ = tuple(ensemble.names)
        self.n_bilateral_ = int(ensemble.n_bilateral)
        self.lower_ = np.asarray(ensemble.lower, dtype=float)
        self.upper_ = np.asarray(ensemble.upper, dtype=float)
        self.mean_field_ = mean
        self.components_ = weights.T @ xc
        disp = np.asarray(ensemble.displacement, dtype=float)
        mean3 = disp.mean(axis=0)
        self.mean_field_3d_ = mean3
        # W^T (D - mean) without the centred copy of the (M, N, 3) array.
        self.components_3d_ = np.tensordot(weights.T, disp, axes=1) - weights.sum(axis=0)[:, None, None] * mean3
        states = np.asarray(ensemble.effective, dtype=float)
        self.mean_state_ = states.mean(axis=0)
        self.component_states_ = weights.T @ (states - self.mean_state_)
        # The pad reactions ride along the same combination: they let the paper's estimator say whether a unilateral
        # boundary is in contact (a lifted buffer's field carries no trace of its commanded position).
        reactions = np.asarray(ensemble.reactions, dtype=float).reshape(m, -1)
        self.mean_reaction_ = reactions.mean(axis=0)
        self.component_reactions_ = weights.T @ (reactions - self.mean_reaction_)
        self.reaction_scale_ = reactions.max(axis=0) if reactions.size else np.zeros(0)
        self.singular_values_ = singular
        self.explained_variance_ratio_ = ratio
        self.n_components_ = k
        coeff = xc @ self.components_.T
        resid = xc - coeff @ self.components_
        self.training_residual_rms_ = float(np.sqrt((resid**2).mean(axis=1)).max())
        self.gram_ = self.components_ @ self.components_.T
        self.notes_ = tuple(notes)
        return self

    def stacked(self) -> PCABasis:
        """This basis with its 3D fields as the fields it fits (a ``components="xyz"`` estimate, paper section 3.2):
        mean_field_ (3 N,) and components_ (K, 3 N) are mean_field_3d_ and components_3d_ node by node x, y, z,
        gram_ their Gram; the pre-factors, states and reactions are the same pairs (the 3D field of component k is
        made by the same member weights as its normal field). training_residual_rms_ stays the normal fields' (the
        3D fields' is not kept): the model floor the covariance and the within-model test count on each of the
        3 N values. A copy; this basis is unchanged."""
        stacked = copy.copy(self)
        stacked.mean_field_ = self.mean_field_3d_.reshape(-1)
        stacked.components_ = self.components_3d_.reshape(self.components_3d_.shape[0], -1)
        stacked.gram_ = stacked.components_ @ stacked.components_.T
        return stacked

    def on_nodes(self, nodes: np.ndarray) -> PCABasis:
        """This basis on the kept skin ``nodes`` (n,) (a coarsened estimate, of the normal component:
        :mod:`~.coarsening`): its normal fields' values there (mean_field_ (n,), components_ (K, n)) and their Gram over
        them, its 3D fields empty (0 nodes); pre-factors, states, reactions and the training residual (a per-node RMS)
        as they are. A copy; this basis is unchanged."""
        kept = copy.copy(self)
        kept.mean_field_ = self.mean_field_[nodes]
        kept.components_ = np.ascontiguousarray(self.components_[:, nodes])
        kept.mean_field_3d_ = self.mean_field_3d_[:0]
        kept.components_3d_ = self.components_3d_[:, :0]
        kept.gram_ = kept.components_ @ kept.components_.T
        return kept

    @property
    def cumulative_explained_variance_(self) -> np.ndarray:
        """(C,) cumulative explained variance ratio (the orange curve of Fig. 8)."""
        return np.cumsum(self.explained_variance_ratio_)


# Attribute names that make up a fitted PCABasis (used by the HDF5 writer/reader).
PCA_FITTED_ARRAYS = (
    "lower_",
    "upper_",
    "mean_field_",
    "mean_field_3d_",
    "mean_state_",
    "mean_reaction_",
    "components_",
    "components_3d_",
    "component_states_",
    "component_reactions_",
    "reaction_scale_",
    "gram_",
    "singular_values_",
    "explained_variance_ratio_",
)
