"""The bases of one model (section 3.1.2) and what is done with them: build, estimate, decompose.

A :class:`Bases` bundles the PCA basis, the hierarchical basis, the visible skin and (optionally) the reduced FE
model; it is all estimation and decomposition need, and it keeps its contact-aware estimator once fitted, so a stream
of fields (the estimator node, the CLI) prepares it once. Saving and loading is in :mod:`hood_decomp.io.bases`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from hood_decomp.core.method.coarsening import (
    MIN_NODES_PER_COLUMN,
    SpanLift,
    coarsening_stride,
    kept_rings,
    restricted_field,
    stratified_nodes,
)
from hood_decomp.core.method.contact_estimation import ContactEstimator, stacked_model
from hood_decomp.core.method.decomposition import decompose
from hood_decomp.core.method.estimation import (
    COMPONENTS,
    DEFAULT_MIN_COVERAGE,
    check_field,
    estimate_pca,
    residual_stats,
    stacked_field,
)
from hood_decomp.core.method.hierarchical import HierarchicalBasis
from hood_decomp.core.method.model_spread import PhysicalResponses, factor_spread
from hood_decomp.core.method.pca import PCABasis
from hood_decomp.core.method.residual import (
    DEFAULT_ALPHA,
    DEFAULT_SMOOTH_DEGREE,
    ResidualAnalysis,
    ResidualTest,
    analyse_residual,
    ring_incidence,
)
from hood_decomp.core.method.surface_reading import ReadingOfBasis, ScanReadingBias
from hood_decomp.core.types import (
    Decomposition,
    DisplacementField,
    Ensemble,
    FieldErrorModel,
    ParameterEstimate,
    ReducedModel,
    SkinSurface,
    ToleranceZone,
    side_by_side,
)
from hood_decomp.errors import BasisError, ModelIdMismatchError

if TYPE_CHECKING:
    import scipy.sparse as sp

logger = logging.getLogger(__name__)

METHODS = ("contact", "pca")


@dataclasses.dataclass(frozen=True)
class Bases:
    """Everything a bases file holds. reduced_model is None when the bases were built without one (then only the
    paper's "pca" estimator is available)."""

    model_id: str
    skin: SkinSurface
    pca: PCABasis
    hierarchical: HierarchicalBasis
    reduced_model: ReducedModel | None
    #: the calibration these bases were rebuilt with (core.loop.calibration.Calibration.record as JSON text; "" for
    #: uncalibrated bases)
    calibration: str = ""
    #: response of the part to 1 K of uniform temperature rise (skin normal (N,), pad springs (S,), skin 3D (N, 3), mm;
    #: core.fe.solver.physical_responses), carried by calibrated bases; None: no temperature term
    thermal: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    #: acceptance criteria on the skin (model.yaml ``tolerance_zones``, core.method.tolerance); not the model: they
    #: do not enter ``bases_id`` (io.bases keeps them in an optional group with its own fingerprint)
    tolerance_zones: tuple[ToleranceZone, ...] = ()
    #: what the calibrated model still gets wrong on the skin, (N, k) mm: the model discrepancy delta = D z with
    #: z ~ N(0, I_k) (core.loop.calibration.discrepancy_modes, from the calibration's leave-one-out residuals); the
    #: estimates' covariance and the within-model test count it as a field error. None: uncalibrated (no term)
    discrepancy: np.ndarray | None = None
    #: the parameters that are measured effects (core.loop.measured_effects): basis fields learned from recurring
    #: residuals, without a boundary to adjust; every estimate marks them (ParameterEstimate.measured_effect) and no
    #: correction moves them (core.method.correction.plan_correction)
    measured_effects: tuple[str, ...] = ()
    #: the discrepancy's part outside the smooth modes it is stated on, per skin node (N,) mm^2
    #: (core.loop.calibration.local_discrepancy): the within-model test's one-ring part counts it. None: no term
    discrepancy_local: np.ndarray | None = None
    #: the discrepancy rows' expected noise, (N, K) mm (core.loop.calibration.discrepancy_noise_modes): the
    #: estimates' covariance subtracts W W^T from D D^T along its own gains (the part's own noise is counted by its
    #: measurement term). None: D D^T counted as it is (bases calibrated before session 11)
    discrepancy_noise: np.ndarray | None = None
    #: the calibrated model's error from the calibration entries' noise (its correction and its physical factors),
    #: (N, r) mm (core.loop.calibration, Calibration.calibration_noise): a low-rank field error the covariance and
    #: the test add
    calibration_noise: np.ndarray | None = None
    #: the FE model's responses to the physical factors (gas springs, sheet thickness; core.fe.solver
    #: physical_responses, thickness_sensitivities) of ``reduced_model``'s FE model: with them the estimates consider
    #: thickness and gas-spring force among the model's factors (model_spread). None: these two are not considered.
    #: Not part of the model's value (not in bases_id)
    physics: PhysicalResponses | None = dataclasses.field(default=None, compare=False)
    #: the scan step's smoothing bias of the PCA basis' fields (core.loop.scan_skin.reading_bias, measured when a
    #: bases file is written with its scan skin): what a scan reads in excess of them, which the estimator takes
    #: out of a scanned field inside the basis (:meth:`reading`). None: not measured (only the slide is taken out).
    #: Measured from the bases, not part of their value (not in bases_id)
    scan_reading_bias: ScanReadingBias | None = dataclasses.field(default=None, compare=False)
    # (min_coverage, temperature K, components) -> fitted ContactEstimator; filled on first use, not part of the
    # bases' value
    _contact_estimators: dict[tuple[float, float, str], ContactEstimator] = dataclasses.field(
        default_factory=dict, init=False, repr=False, compare=False)
    # what a three-component fit reads: the PCA basis with its 3D fields (PCABasis.stacked) and the within-model
    # test on the stacked values (ResidualTest.stacked), made on first use
    _stacked: dict[str, PCABasis | ResidualTest] = dataclasses.field(default_factory=dict, init=False, repr=False,
                                                                     compare=False)
    # the skin's within-model test (its smooth modes), prepared on first use
    _tests: dict[str, ResidualTest] = dataclasses.field(default_factory=dict, init=False, repr=False, compare=False)
    # what a scan reads less than the basis' fields (their slide along the skin, the smoothing bias inside the
    # basis), prepared on first use
    _readings: dict[str, ReadingOfBasis] = dataclasses.field(default_factory=dict, init=False, repr=False,
                                                             compare=False)
    # stride -> these bases on a stratified subset of the skin's nodes (a coarsened estimate), made on first use
    _coarsened: dict[int, CoarsenedBases] = dataclasses.field(default_factory=dict, init=False, repr=False,
                                                              compare=False)

    @property
    def names(self) -> tuple[str, ...]:
        return self.pca.names_

    def residual_test(self) -> ResidualTest:
        """The one within-model test on this skin with this model's discrepancy (:class:`~.residual.ResidualTest`),
        prepared once."""
        if "test" not in self._tests:
            self._tests.setdefault("test", self._fit_test())
        return self._tests["test"]

    def _fit_test(self, rings: Callable[[], sp.csr_matrix] | None = None) -> ResidualTest:
        return ResidualTest().fit(self.skin, self.discrepancy, self.discrepancy_dof, self.discrepancy_local,
                                  self.discrepancy_noise, self.calibration_noise, rings)

    def reading(self) -> ReadingOfBasis:
        """What a scan reads less than this model's fields (:mod:`~.surface_reading`: their slide, and the smoothing
        bias inside the basis where ``scan_reading_bias`` is measured), prepared once."""
        if "reading" not in self._readings:
            self._readings.setdefault("reading", ReadingOfBasis.of(self.pca, self.skin, self.scan_reading_bias))
        return self._readings["reading"]

    @property
    def discrepancy_dof(self) -> float:
        """Degrees of freedom of the discrepancy's estimate: the calibration's entries (each one sample of what the
        model gets wrong; the record's ``entries``), inf without a discrepancy or a record."""
        if self.discrepancy is None or not self.calibration:
            return np.inf
        return float(len(json.loads(self.calibration).get("entries", ()))) or np.inf

    def contact_estimator(self, min_coverage: float = DEFAULT_MIN_COVERAGE, temperature_k: float = 0.0,
                          components: str = "normal") -> ContactEstimator:
        """The contact-aware estimator on these bases, fitted on first use and kept (one per ``min_coverage``, part
        temperature ``temperature_k``, K off the model's reference: its thermal response joins the load case, and
        ``components``: "xyz" fits the reduced model's 3D responses, :func:`~.contact_estimation.stacked_model`, its
        factors' changes too, judged by :meth:`stacked_test`).

        Fitting forms the (B + S, N) fields and their Gram matrix, which costs as much as estimating a field; the
        fitted estimator is only read by ``estimate``, so one instance serves every later field.
        """
        if self.reduced_model is None:
            raise BasisError("the bases file holds no reduced model: the contact-aware estimator needs one (use 'pca')")
        xyz = self._components(components)
        key = (min_coverage, float(temperature_k), components)
        estimator = self._contact_estimators.get(key)
        if estimator is None:
            warm = self.at_temperature(temperature_k)
            shift = None if self.reduced_model is warm else warm.z0 - self.reduced_model.z0
            factors = factor_spread(warm, self.calibration, self.physics, full=xyz)
            if xyz:
                warm = stacked_model(warm)
                factors = tuple(dataclasses.replace(factor, plus=stacked_model(factor.plus),
                                                    minus=stacked_model(factor.minus)) for factor in factors)
            estimator = ContactEstimator(min_coverage).fit(warm, self.pca.lower_, self.pca.upper_,
                                                           self.stacked_test() if xyz else self.residual_test(),
                                                           shift, factors)
            estimator = self._contact_estimators.setdefault(key, estimator)
        return estimator

    def stacked_pca(self) -> PCABasis:
        """The PCA basis fitting all three displacement components (:meth:`PCABasis.stacked`), made once."""
        self._components("xyz")
        if "pca" not in self._stacked:
            self._stacked.setdefault("pca", self.pca.stacked())
        return self._stacked["pca"]

    def stacked_test(self) -> ResidualTest:
        """The within-model test of a three-component fit (:meth:`ResidualTest.stacked` of :meth:`residual_test`),
        made once."""
        self._components("xyz")
        if "test" not in self._stacked:
            self._stacked.setdefault("test", self.residual_test().stacked())
        return self._stacked["test"]

    def _components(self, components: str) -> bool:
        """Whether ``components`` is "xyz"; raises BasisError for an unknown one and for "xyz" on bases that state
        a calibrated model's discrepancy (of the normal displacement only: a fit of all three could not count it)."""
        if components not in COMPONENTS:
            raise BasisError(f"unknown displacement components {components!r}, expected one of {COMPONENTS}")
        if components == "xyz" and self.discrepancy is not None:
            raise BasisError("these calibrated bases state the model's discrepancy on the normal displacement only: "
                             "components 'xyz' cannot count it; fit the normal component")
        return components == "xyz"

    def coarsened(self, stride: int) -> CoarsenedBases:
        """These bases on a stratified subset of the skin's nodes (:class:`CoarsenedBases`), made once per stride."""
        if stride not in self._coarsened:
            self._coarsened.setdefault(stride, CoarsenedBases.of(self, stride))
        return self._coarsened[stride]

    def prepare_estimation(self, method: str = "contact", min_coverage: float = DEFAULT_MIN_COVERAGE,
                           temperature_k: float = 0.0, components: str = "normal", scan: bool = False,
                           coarsen: int | str = "auto") -> None:
        """Fit now what :func:`estimate_field` with these arguments fits on its first call (the contact-aware
        estimator, or for "pca" and for bases without a reduced model the within-model test or, for "xyz", the
        stacked basis; with ``scan``, for a scanned field, the reading of the basis' fields and their gradients; for
        a coarsened estimate those of the coarsened bases and their lift), so that estimating then only reads it: a
        node before it serves, a one-off run while it reads its scan."""
        if scan:
            self.reading().prepare()
        # "auto" coarsens a scan's field at paper resolution, not a white or simulated one (coarsening_stride)
        stride = coarsening_stride(coarsen, self.skin.n_nodes, components, None if scan else FieldErrorModel.none())
        if stride > 1:
            self.coarsened(stride).prepare(self, method, min_coverage, temperature_k)
        elif method == "contact" and self.reduced_model is not None:
            self.contact_estimator(min_coverage, temperature_k, components)
        elif self._components(components):
            self.stacked_pca()
            self.stacked_test()
        else:
            self.residual_test()

    def at_temperature(self, temperature_k: float) -> ReducedModel:
        """The reduced model of a part ``temperature_k`` K off the model's reference temperature (uniform)."""
        if self.reduced_model is None:
            raise BasisError("the bases file holds no reduced model")
        if temperature_k == 0.0:
            return self.reduced_model
        if self.thermal is None:
            raise BasisError("these bases carry no thermal response: a part temperature needs calibrated bases "
                             "(`hood-decomp calibrate` adds it)")
        if not np.isfinite(temperature_k):
            raise BasisError(f"part temperature offset must be a finite number of K, got {temperature_k}")
        w, z, w3 = self.thermal
        reduced = self.reduced_model
        return dataclasses.replace(reduced, w0=reduced.w0 + temperature_k * w, z0=reduced.z0 + temperature_k * z,
                                   w0_3d=reduced.w0_3d + temperature_k * w3)


def build_bases(
    ensemble: Ensemble,
    skin: SkinSurface,
    reduced_model: ReducedModel | None = None,
    n_components: int | None = 10,
    explained_variance: float | None = None,
    epsilon: float = 0.1,
    span: str = "whole",
) -> Bases:
    """Build both bases from a full-factorial ensemble (section 3.1.2) and bundle them with the skin and model."""
    for what, other in (("skin", skin.model_id), ("reduced model", getattr(reduced_model, "model_id", None))):
        if other is not None and other != ensemble.model_id:
            raise ModelIdMismatchError(f"{what} model_id {other!r} differs from the ensemble's {ensemble.model_id!r}")
    if skin.n_nodes != ensemble.normal_displacement.shape[1]:
        raise BasisError(f"skin has {skin.n_nodes} nodes, ensemble fields have {ensemble.normal_displacement.shape[1]}")
    pca = PCABasis(n_components=n_components, explained_variance=explained_variance).fit(ensemble)
    logger.info("PCA: %d components, cumulative explained variance %.8f", pca.n_components_,
                pca.cumulative_explained_variance_[pca.n_components_ - 1])
    for note in pca.notes_:
        logger.info("PCA: %s", note)
    hierarchical = HierarchicalBasis(epsilon=epsilon, span=span).fit(ensemble)
    return Bases(ensemble.model_id, skin, pca, hierarchical, reduced_model)


def rebuilt_like(rebuilt: Bases, source: Bases) -> Bases:
    """``rebuilt`` (bases built again from ``source``'s model with an added effect, e.g. by close-loop or the shift's
    measured effects) carrying what ``source`` states beyond its model: its calibration (record, thermal response and
    model discrepancy), its tolerance zones and its measured effects. An added effect does not make the calibrated
    model less wrong where it was wrong, so the discrepancy stays; dropping it would shrink every stated std back to
    the uncalibrated one. Dropping a measured effect's flag would let a correction move it. The physical responses
    stay where the parameters are the same (an added parameter has none)."""
    same = getattr(rebuilt.reduced_model, "names", None) == getattr(source.reduced_model, "names", ())
    return dataclasses.replace(rebuilt, calibration=source.calibration, thermal=source.thermal,
                               physics=source.physics if same else None,
                               discrepancy=source.discrepancy, discrepancy_local=source.discrepancy_local,
                               discrepancy_noise=source.discrepancy_noise, calibration_noise=source.calibration_noise,
                               tolerance_zones=source.tolerance_zones,
                               measured_effects=source.measured_effects)


def estimate_field(
    bases: Bases, field: DisplacementField, method: str = "contact", min_coverage: float = DEFAULT_MIN_COVERAGE,
    temperature_k: float = 0.0, components: str = "normal", coarsen: int | str = "auto",
) -> ParameterEstimate:
    """Estimate a field's parameter states: "contact" (default, needs the reduced model) or "pca" (the paper's).
    temperature_k: the part's temperature minus the model's reference temperature, K (needs bases with a thermal
    response; the PCA estimator removes the thermal field from the measured one, the contact-aware one also lets it
    move the pads).

    components: "normal" (default) fits the normal displacement; "xyz" fits all three components of a field that
    has them (a simulated or FE field without an error model, :func:`~.estimation.stacked_field`) with the model's
    3D fields, as the paper does (section 3.2): the same estimators on the stacked values (3 N of them). A slide
    in the skin's plane (a hinge moved along the hood) the normal values barely show is then seen, and so is an
    in-plane effect the model lacks: the within-model test is the skin's on each component of the stacked residual
    (:meth:`Bases.stacked_test`). Raises FieldError for a field without a 3D displacement or with an
    error model, BasisError for calibrated bases with a discrepancy (:meth:`Bases.stacked_pca`).

    coarsen: the paper's coarsening of the input field (:mod:`~.coarsening`): a stride >= 1 (1: every node) or
    "auto" (a quarter of the nodes on a skin of more than :data:`~.coarsening.AUTO_MIN_NODES` nodes fitted on its
    normal component, the paper-resolution hood, for a field whose errors are correlated enough to lose nothing
    there, a scan's: :func:`~.coarsening.coarsening_stride`; every node otherwise). A coarsened estimate fits and
    tests the field on the kept nodes (:meth:`CoarsenedBases.estimate`); its reconstruction and residual are of every
    node.

    The field is estimated as its nodes' displacement (:func:`node_field`: a scan's slide taken out), so the estimate,
    its residual and its within-model test are of the node displacements the model makes."""
    if method not in METHODS:
        raise BasisError(f"unknown estimation method {method!r}, expected one of {METHODS}")
    xyz = bases._components(components)
    stride = coarsening_stride(coarsen, bases.skin.n_nodes, components, field.errors)
    fitted = stacked_field(field, bases.skin.normals, min_coverage) if xyz else node_field(bases, field, min_coverage)
    if method == "pca" and temperature_k != 0.0 and (
            xyz or np.shape(fitted.normal_displacement) == bases.pca.mean_field_.shape):
        warm = bases.at_temperature(temperature_k)
        thermal = (warm.w0_3d - bases.reduced_model.w0_3d).reshape(-1) if xyz else warm.w0 - bases.reduced_model.w0
        fitted = dataclasses.replace(fitted, normal_displacement=fitted.normal_displacement - thermal)
    if stride > 1:
        estimate = bases.coarsened(stride).estimate(bases, fitted, method, min_coverage, temperature_k)
    else:
        estimate = _estimate_nodes(bases, fitted, method, min_coverage, temperature_k, components)
    if xyz:
        estimate = normal_part(estimate, field, bases.skin.normals)
    if not bases.measured_effects:
        return estimate
    return dataclasses.replace(estimate, measured_effect=np.isin(estimate.names, bases.measured_effects))


def _estimate_nodes(bases: Bases, fitted: DisplacementField, method: str, min_coverage: float, temperature_k: float,
                    components: str = "normal") -> ParameterEstimate:
    """The estimate of ``fitted``, a field of node displacements (:func:`node_field`, the PCA's thermal field taken
    out) on every node of ``bases``."""
    if method == "pca":
        if components == "xyz":
            return estimate_pca(bases.stacked_pca(), fitted, min_coverage, bases.stacked_test())
        return estimate_pca(bases.pca, fitted, min_coverage, bases.residual_test())
    return bases.contact_estimator(min_coverage, temperature_k, components).estimate(fitted)


@dataclasses.dataclass(frozen=True)
class CoarsenedBases:
    """Bases on a stratified subset of their skin's nodes (:mod:`~.coarsening`): a coarsened estimate fits and tests
    a field there and carries its fit back to every node through the span it fitted in.

    stride: cells of ``stride`` node spacings; nodes: (n,) the kept node indices of the whole skin; kept: the bases
    on them (their skin has no triangles: the within-model test's one-ring part uses :func:`~.coarsening.kept_rings`;
    a scan is read on the whole skin first, so they carry no reading of their own; a coarsened fit is of the normal
    component, so their 3D fields and responses are empty).
    """

    stride: int
    nodes: np.ndarray
    kept: Bases
    # method -> the lift of its estimator's span (kept nodes -> coefficients), made on first use
    _lifts: dict[str, SpanLift] = dataclasses.field(default_factory=dict, init=False, repr=False,
                                                                  compare=False)

    @classmethod
    def of(cls, bases: Bases, stride: int) -> CoarsenedBases:
        """``bases`` coarsened with ``stride`` (:func:`~.coarsening.stratified_nodes` of its skin)."""
        nodes = stratified_nodes(bases.skin.points, stride)
        skin = bases.skin
        span = max(bases.pca.n_components_, 0 if bases.reduced_model is None else bases.reduced_model.R.shape[1]
                   + bases.reduced_model.G.shape[1])
        columns = span + (DEFAULT_SMOOTH_DEGREE + 1) * (DEFAULT_SMOOTH_DEGREE + 2) // 2 + 6
        if nodes.size < MIN_NODES_PER_COLUMN * columns:
            raise BasisError(f"coarsening stride {stride} keeps {nodes.size} of {skin.n_nodes} nodes; the fit and its "
                             f"test need at least {MIN_NODES_PER_COLUMN * columns} ({MIN_NODES_PER_COLUMN} per span "
                             "field, smooth mode and rigid-body mode): give a smaller stride")
        kept_skin = SkinSurface(np.asarray(skin.points)[nodes], np.asarray(skin.normals)[nodes],
                                np.zeros((0, 3), np.int64), skin.model_id)

        def rows(array: np.ndarray | None) -> np.ndarray | None:
            return None if array is None else np.asarray(array)[nodes]

        thermal = None if bases.thermal is None else (rows(bases.thermal[0]), bases.thermal[1], bases.thermal[2][:0])
        kept = dataclasses.replace(
            bases, skin=kept_skin, pca=bases.pca.on_nodes(nodes),
            reduced_model=None if bases.reduced_model is None else bases.reduced_model.on_nodes(nodes),
            thermal=thermal, tolerance_zones=(), discrepancy=rows(bases.discrepancy),
            discrepancy_local=rows(bases.discrepancy_local), discrepancy_noise=rows(bases.discrepancy_noise),
            calibration_noise=rows(bases.calibration_noise),
            physics=None if bases.physics is None else bases.physics.on_nodes(nodes), scan_reading_bias=None)
        kept._tests["test"] = kept._fit_test(lambda: kept_rings(ring_incidence(skin), nodes, stride))
        return cls(stride, nodes, kept)

    def prepare(self, bases: Bases, method: str, min_coverage: float, temperature_k: float) -> None:
        """Fit now what :meth:`estimate` of a field of ``bases`` fits on its first call."""
        self.kept.prepare_estimation(method, min_coverage, temperature_k, coarsen=1)
        self._lift(method)

    def estimate(self, bases: Bases, fitted: DisplacementField, method: str, min_coverage: float,
                 temperature_k: float) -> ParameterEstimate:
        """The estimate of ``fitted`` (N node displacements of ``bases``' skin, as :func:`estimate_field` prepares
        them) made on the kept nodes; reconstruction, residual, its RMS and max and the coverage of every node (the
        reconstruction lifted through the fitted span), the rest (values, covariance, within-model test on the kept
        nodes) as the kept bases' estimate states it."""
        kept = _estimate_nodes(self.kept, restricted_field(fitted, self.nodes), method, min_coverage, temperature_k)
        lift = self._lift(method)
        if method == "pca":
            offset, kept_offset = bases.pca.mean_field_, self.kept.pca.mean_field_
        else:
            offset, kept_offset = bases.at_temperature(temperature_k).w0, self.kept.at_temperature(temperature_k).w0
        coefficients = lift(kept.reconstruction - kept_offset)
        if method == "pca":
            reconstruction = coefficients @ bases.pca.components_
            reconstruction += offset  # in place: no second (N,) array
        else:
            model = bases.reduced_model
            reconstruction = offset + model.R @ coefficients[:model.n_bilateral] + model.G @ coefficients[
                model.n_bilateral:]
        values = np.asarray(fitted.normal_displacement, dtype=float)
        valid = np.isfinite(values)
        residual, rms, worst = residual_stats(values, reconstruction, valid)
        return dataclasses.replace(kept, reconstruction=reconstruction, residual=residual, residual_rms=rms,
                                   residual_max=worst, coverage=float(valid.mean()))

    def _lift(self, method: str) -> SpanLift:
        """The lift of the span ``method``'s estimator fits in (the PCA basis' fields; the reduced model's unit and
        pad-spring responses: a part temperature moves only the offset), kept nodes -> coefficients."""
        if method not in self._lifts:
            if method == "pca":
                rows = self.kept.pca.components_.T
            else:
                if self.kept.reduced_model is None:
                    raise BasisError("the bases file holds no reduced model: the contact-aware estimator needs one "
                                     "(use 'pca')")
                rows = side_by_side(self.kept.reduced_model.R, self.kept.reduced_model.G)
            self._lifts.setdefault(method, SpanLift.of(rows))
        return self._lifts[method]


def normal_part(estimate: ParameterEstimate, field: DisplacementField, normals: np.ndarray) -> ParameterEstimate:
    """A ``components="xyz"`` estimate of the stacked values (reconstruction (3 N,) mm) as every consumer reads an
    estimate: its reconstruction and residual the normal part (N,) of the 3D ones (``field``'s normal values minus
    the reconstruction's normal part, NaN where unseen) and residual_rms / residual_max that residual's (consumers
    put them beside a normal fit's and a scan's; the fit and its test read the 3 N values), ``components`` "xyz";
    normals (N, 3) the skin's."""
    reconstruction = np.einsum("na,na->n", estimate.reconstruction.reshape(-1, 3), normals)
    values = np.asarray(field.normal_displacement, dtype=float)
    residual, rms, worst = residual_stats(values, reconstruction, np.isfinite(values))
    return dataclasses.replace(estimate, reconstruction=reconstruction, residual=residual, residual_rms=rms,
                               residual_max=worst, components="xyz")


def node_field(bases: Bases, field: DisplacementField, min_coverage: float = DEFAULT_MIN_COVERAGE
               ) -> DisplacementField:
    """``field`` as the displacement of the model's nodes. A scanned field (error model kind "scan") reads the
    displaced surface at the nominal nodes, which has slid along itself where the part moves in its plane, through
    the scan step's smoothing (:mod:`~.surface_reading`): the slide of the basis field that fits it is added back,
    and where the bases carry the smoothing bias of their fields (``scan_reading_bias``, for a field smoothed with
    the radius it was measured with) the part of it inside the basis is taken out. Other fields (simulated, or
    with a user's stated noise) are node displacements already and are returned as they are. Raises the estimators'
    named errors (:func:`~.estimation.check_field`) for a field they would refuse."""
    if field.errors.kind != "scan":
        return field
    values, _ = check_field(field, bases.model_id, bases.skin.n_nodes, min_coverage)
    added = bases.reading()(values, field.errors.correlation_length_mm)
    return dataclasses.replace(field, normal_displacement=values + added)


def fitted_unknowns(estimate: ParameterEstimate) -> int:
    """Unknowns a contact-aware estimate fitted: the bilateral states and the touching pads' positions."""
    return int(np.count_nonzero(~np.asarray(estimate.lifted, bool)))


def analyse_estimate(bases: Bases, estimate: ParameterEstimate, noise_mm: float | None, alpha: float = DEFAULT_ALPHA
                     ) -> ResidualAnalysis:
    """Residual statistics and exceeding regions of one estimate, decided by the one within-model test the estimate
    carries (:func:`~.residual.check_residual`, run by the estimator) at ``alpha``: the analysis every verb, node and
    application reports (close-loop, shift), so none of them decides "within the model" by a test of its own.

    noise_mm: the level the regions are drawn against (the field's ``noise_rms``; None: the default). Unknowns: a
    contact-aware estimate fits the bilateral states and the touching pads; the paper's estimator its PCA
    pre-factors, with its training error as model floor. Raises BasisError for an estimate without a test.
    """
    if estimate.check is None:
        raise BasisError("the estimate carries no within-model test (estimate with estimate_field on these bases)")
    if estimate.method == "pca":
        n_params, model_mm = bases.pca.n_components_, bases.pca.training_residual_rms_
    else:
        n_params, model_mm = fitted_unknowns(estimate), 0.0
    check = dataclasses.replace(estimate.check, alpha=alpha, within_model=estimate.check.p_value >= alpha)
    return analyse_residual(bases.skin, estimate.residual, n_params, noise_mm, model_mm, alpha, check=check)


def decompose_field(
    bases: Bases, field: DisplacementField, estimate: ParameterEstimate | None = None, **options: float
) -> Decomposition:
    """Steps 3-6 on the hierarchical basis; ``options`` go to :func:`~.decomposition.decompose`. The field is
    decomposed as its nodes' displacement (:func:`node_field`), as :func:`estimate_field` estimates it: a scan's slide
    along its own surface is no boundary's effect (decomposed raw, a scan whose hinges slide the hood a millimetre
    in its plane had the slide spread over the effects' partial displacements)."""
    nodes = node_field(bases, field, float(options.get("min_coverage", DEFAULT_MIN_COVERAGE)))
    return decompose(bases.hierarchical, nodes, estimate, **options)
