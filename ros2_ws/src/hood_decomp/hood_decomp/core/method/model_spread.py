"""What the model's own physical factors make uncertain in an estimate (consider parameters, Schmidt-Kalman style).

The bases are one FE model; a real part's physics differs from it (Young's modulus, sheet thickness, pad stiffness,
pad preload, gas-spring force, ...). A softer pad looks in one field exactly like a pad moved by its compression
times the stiffness change: the field is explained, the within-model test cannot alarm, and the measurement std says
nothing about it. Such factors are not estimated; they are *considered*: each factor's one-sigma change is applied to
the reduced model (:func:`apply_factors`, the calibration's own model of the factors) and the pad contact solved at
the estimated state and contact state; the change of the skin field it makes is taken through the estimator's own
linear map into the parameters, and the result is the factor's one-sigma effect (P,) mm on the reported values.
Their sum of outer products is the model covariance (``ParameterEstimate.model_covariance``); the safety gate
(:func:`~hood_decomp.core.method.correction.plan_correction`) acts on sqrt(std^2 + model_std^2) and names the dominant
factor per boundary.

Spreads (:func:`factor_spread`): uncalibrated bases take issue 15's ranges of a plant's parts as *uniform
half-widths* (:data:`HALF_WIDTH`, the physics harness (ii) draws; a uniform of half-width h has std h / sqrt(3)):
compliance 1/E 3 %, every sheet's thickness 5 % (one factor: the harness and a coil's gauge move all together), pad
stiffness 30 % (one factor for all pads, as a family shares it), pad preload 50 % of the model's, gas-spring force
5 % (a gas spring's force tolerance class, e.g. +-5 % of the nominal force at 20 C, is of this size). Stiffness and
thickness are log scales (exp(+-sigma)). Calibrated bases (``hood-decomp calibrate``) take the fitted factors' std
from the calibration record (``factor_std``: compliance, gas_spring, thickness per sheet group, per pad stiffness and
preload). Thickness and gas-spring force need the FE model's responses to them (:class:`PhysicalResponses`,
``Bases.physics``); bases without them do not consider these two, and the estimate's ``model_factors`` says which
were.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from hood_decomp.core.types import SENSITIVE_ARRAYS, ReducedModel

#: issue 15's ranges of a plant's parts about the uncalibrated model (relative uniform half-widths; preload: of the
#: model's preload)
HALF_WIDTH = {"compliance": 0.03, "thickness": 0.05, "pad_stiffness": 0.30, "preload": 0.50, "gas_spring": 0.05}


@dataclass(frozen=True)
class PhysicalResponses:
    """The FE responses behind the physical factors (core.fe.solver.physical_responses): gas springs at their stated
    force and 1 K of uniform temperature rise, each as skin normal (N,), pad springs (S,), skin translations (N, 3);
    thermal_moves (B,) mm per K, the unit responses' share of the thermal response (core.fe.solver.thermal_moves)."""

    gas_w: np.ndarray
    gas_z: np.ndarray
    gas_w3: np.ndarray
    thermal_w: np.ndarray
    thermal_z: np.ndarray
    thermal_w3: np.ndarray
    #: thickness group -> d(reduced model arrays)/d(log thickness) (core.fe.solver.thickness_sensitivities)
    thickness: dict[str, ReducedModel]
    thermal_moves: np.ndarray
    #: where the 3D parts were left unread (a bases file's /physics, io.bases): reads them, checked, and returns these
    #: responses whole. None: the 3D arrays are held (or empty, :meth:`on_nodes`)
    load_3d: Callable[[], PhysicalResponses] | None = field(default=None, compare=False, repr=False)

    @staticmethod
    def from_solver(responses: dict[str, tuple], thickness: dict[str, ReducedModel],
                    thermal_moves: np.ndarray) -> PhysicalResponses:
        (gw, gz, g3), (tw, tz, t3) = responses["gas_spring"], responses["thermal"]
        return PhysicalResponses(gw, gz, g3, tw, tz, t3, thickness, np.asarray(thermal_moves, float))

    def with_3d(self) -> PhysicalResponses:
        """These responses with their 3D arrays: themselves when they hold them, else read now (:attr:`load_3d`; only
        a fit of all three components and a calibration need them)."""
        return self if self.load_3d is None else self.load_3d()

    def on_nodes(self, nodes: np.ndarray) -> PhysicalResponses:
        """These responses' normal skin values on the kept skin ``nodes`` (n,) (a coarsened estimate, of the normal
        component: :mod:`.coarsening`), their 3D values empty (0 nodes)."""
        return PhysicalResponses(self.gas_w[nodes], self.gas_z, self.gas_w3[:0], self.thermal_w[nodes],
                                 self.thermal_z, self.thermal_w3[:0],
                                 {group: sens.on_nodes(nodes) for group, sens in self.thickness.items()},
                                 self.thermal_moves)

    def thermal(self, model: ReducedModel, calibrated: ReducedModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The thermal response (skin normal (N,), pad springs (S,), skin 3D (N, 3) mm per K) of a calibrated reduced
        model: the FE model's (of ``model``, the reduced model these responses belong to) with its unit responses'
        share (:attr:`thermal_moves`) moved by what the calibration changed in them. Without it a calibrated part's
        thermal response keeps the FE model's unit response error: 1.7 % RMS on the coarse hood against CalculiX,
        0.011-0.031 mm in the estimates at 5 K."""
        m, whole = self.thermal_moves, self.with_3d()
        return (self.thermal_w + (calibrated.R - model.R) @ m, self.thermal_z + (calibrated.Sa - model.Sa) @ m,
                whole.thermal_w3 + (calibrated.R_3d - model.R_3d) @ m)


def factor_names(reduced: ReducedModel, physics: PhysicalResponses) -> list[str]:
    """Names of the physical factors: compliance, gas_spring, thickness per sheet group, then per pad stiffness and
    preload."""
    pads = reduced.names[reduced.n_bilateral:]
    return ["compliance", "gas_spring", *(f"thickness:{g}" for g in physics.thickness),
            *(f"pad_stiffness:{p}" for p in pads), *(f"preload:{p}" for p in pads)]


def apply_factors(reduced: ReducedModel, physics: PhysicalResponses, theta: np.ndarray,
                  full: bool = True) -> ReducedModel:
    """The reduced model with physical factors theta (:func:`factor_names` order): compliance exp(theta_0) on the load
    and pad-force responses, gas-spring force x (1 + theta_1), each sheet group's thickness x exp(theta) (first order
    through its sensitivity), pad stiffness x exp, preload + theta (mm). ``full``: False leaves the 3D arrays as they
    are (the fit reads only the normal ones; True reads the responses' 3D parts, :meth:`PhysicalResponses.with_3d`)."""
    if full:
        physics = physics.with_3d()
    n_pads = len(reduced.names) - reduced.n_bilateral
    n_groups = len(physics.thickness)
    c, g = float(np.exp(theta[0])), float(theta[1])
    stiffness = np.exp(np.asarray(theta[2 + n_groups:2 + n_groups + n_pads]))
    preload = np.asarray(theta[2 + n_groups + n_pads:2 + n_groups + 2 * n_pads])
    arrays = SENSITIVE_ARRAYS if full else tuple(name for name in SENSITIVE_ARRAYS if not name.endswith("_3d"))
    # an array no factor changes is shared, not copied: a factor's changed models are kept per estimator, and at
    # paper resolution a copy of G is 97 MB
    if np.any(theta[2:2 + n_groups]):
        reduced = replace(reduced, **{name: getattr(reduced, name) + sum(
            t * getattr(sens, name) for t, sens in zip(theta[2:2 + n_groups], physics.thickness.values(),
                                                       strict=True)) for name in arrays})
    if c != 1.0 or g != 0.0:
        reduced = replace(reduced, w0=c * (reduced.w0 + g * physics.gas_w), z0=c * (reduced.z0 + g * physics.gas_z))
    if c != 1.0:
        reduced = replace(reduced, G=c * reduced.G, H=c * reduced.H)
    reduced = replace(reduced, k=reduced.k * stiffness[reduced.pad_of],
                      preload=reduced.preload + preload[reduced.pad_of])
    if not full or (c == 1.0 and g == 0.0):
        return reduced
    return replace(reduced, w0_3d=c * (reduced.w0_3d + g * physics.gas_w3), G_3d=c * reduced.G_3d)


@dataclass(frozen=True)
class Factor:
    """One considered factor: its name and the reduced model changed by plus and minus its one-sigma change
    (:func:`apply_factors`; the normal arrays, the 3D ones kept). calibrated: the change is a calibration's own
    uncertainty of a fitted factor (not a plant's spread about an uncalibrated model): what it moves where no field
    shows it, a lifted pad's position read through the pad springs, is part of the estimate's stated covariance
    (:class:`~.contact_estimation.ContactEstimator`), not only of its model effects."""

    name: str
    plus: ReducedModel
    minus: ReducedModel
    calibrated: bool = False


def factor_spread(model: ReducedModel, calibration: str = "",
                  physics: PhysicalResponses | None = None, full: bool = False) -> tuple[Factor, ...]:
    """The considered factors of ``model`` with their one-sigma changes: from the calibration record (JSON text,
    ``Bases.calibration``; its ``factor_std``) when there is one, else the uncalibrated prior :data:`HALF_WIDTH`.
    ``physics``: the FE model's responses to gas springs and thickness (None: these two are not considered).
    ``full``: the changed models' 3D arrays changed too (:func:`apply_factors`; a fit of all three components reads
    them), else kept."""
    known = physics is not None
    if physics is None:
        n, s = model.w0.shape[0], model.k.size
        physics = PhysicalResponses(np.zeros(n), np.zeros(s), np.zeros((n, 3)), np.zeros(n), np.zeros(s),
                                    np.zeros((n, 3)), {}, np.zeros(model.n_bilateral))
    names = factor_names(model, physics)
    pads = model.names[model.n_bilateral:]
    record = json.loads(calibration).get("factor_std", {}) if calibration else None
    changes: list[tuple[str, dict[str, float]]]
    if record is None:
        uniform = 1.0 / np.sqrt(3.0)
        preload = {f"preload:{pad}": HALF_WIDTH["preload"] * uniform
                   * float(np.sum(np.abs(model.preload[model.pad_of == p])) / max(np.sum(model.pad_of == p), 1))
                   for p, pad in enumerate(pads)}
        changes = [("compliance (Young's modulus)", {"compliance": HALF_WIDTH["compliance"] * uniform}),
                   ("sheet thickness", {name: HALF_WIDTH["thickness"] * uniform for name in names
                                        if name.startswith("thickness:")}),
                   ("pad stiffness", {f"pad_stiffness:{pad}": HALF_WIDTH["pad_stiffness"] * uniform
                                      for pad in pads}),
                   ("pad preload", preload),
                   ("gas-spring force", {"gas_spring": HALF_WIDTH["gas_spring"] * uniform if known else 0.0})]
    else:
        changes = [(" of ".join(("calibrated " + name.split(":")[0].replace("_", " "), *name.split(":")[1:])),
                    {name: float(record.get(name, 0.0))}) for name in names if known or name != "gas_spring"]
    factors = []
    for label, change in changes:
        theta = np.array([change.get(name, 0.0) for name in names])
        if np.any(theta):
            factors.append(Factor(label, apply_factors(model, physics, theta, full=full),
                                  apply_factors(model, physics, -theta, full=full), calibrated=record is not None))
    return tuple(factors)


@dataclass(frozen=True)
class SkinChange:
    """How a changed reduced model's skin normal arrays differ from the nominal's: w0' = scale w0 + (w0' - scale w0),
    G' = scale G + (G' - scale G), R' = R + (R' - R), each flag telling whether its remainder is more than round-off
    (1e-13 of the array). Any scale makes the split exact; the one fitted to G makes a changed compliance (w0 and G
    scaled, :func:`apply_factors`) a pure scale and a changed pad stiffness or preload no skin change at all, so
    their field changes lie in the estimator's own span and cost no pass over the nodes (:func:`factor_effects`)."""

    scale: float
    w0: bool
    R: bool
    G: bool

    @staticmethod
    def between(model: ReducedModel, changed: ReducedModel) -> SkinChange:
        """The change from ``model`` to ``changed`` (the same skin and springs)."""
        new, old = (changed.G, model.G) if model.G.size else (changed.w0, model.w0)
        scale = _scale(new, old) if _differs(new, old) else 1.0

        def scaled(array: np.ndarray) -> np.ndarray:  # the array itself at scale 1: a shared one is not compared
            return array if scale == 1.0 else scale * array

        return SkinChange(scale, _differs(changed.w0, scaled(model.w0)), _differs(changed.R, model.R),
                          _differs(changed.G, scaled(model.G)))


def _scale(new: np.ndarray, old: np.ndarray) -> float:
    """The least-squares scale s of ``old`` to ``new`` (new ~ s old); 1 for a zero ``old``."""
    norm = float(np.vdot(old, old))
    return float(np.vdot(new, old)) / norm if norm > 0 else 1.0


def _differs(new: np.ndarray, old: np.ndarray) -> bool:
    """Whether ``new`` differs from ``old`` by more than 1e-13 of its largest entry."""
    if new is old or new.size == 0:
        return False
    return bool(np.max(np.abs(new - old)) > 1e-13 * max(float(np.max(np.abs(new))), 1e-300))


def _forces(model: ReducedModel, active: np.ndarray, pads: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The pad springs' forces (S,) N of ``model`` at theta = (a, b of the touching ``pads``) with the springs
    ``active`` in contact (the estimate's contact state); 0 on the free springs."""
    n_b = model.n_bilateral
    f = np.zeros(model.k.size)
    idx = np.flatnonzero(active)
    if idx.size:
        b = np.zeros(int(model.pad_of.max()) + 1)
        b[pads] = theta[n_b:]
        compliance = np.diag(1.0 / model.k[idx]) + model.H[np.ix_(idx, idx)]
        f[idx] = np.linalg.solve(compliance, b[model.pad_of[idx]] + model.preload[idx] - model.z0[idx]
                                 - model.Sa[idx] @ theta[:n_b])
    return f


def factor_effects(model: ReducedModel, factors: tuple[Factor, ...], changes: tuple[tuple[SkinChange, SkinChange],
                   ...], active: np.ndarray, theta: np.ndarray, normal: np.ndarray,
                   project: Callable[[np.ndarray], np.ndarray], to_theta: Callable[[np.ndarray], np.ndarray],
                   report: Callable[[np.ndarray, ReducedModel | None], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(F, P) mm: each factor's one-sigma effect on the reported values, and (F, P) mm the part of it read through
    the pad springs (report(theta, None) - report(theta, changed): a lifted pad's position z - preload; zero for the
    bilateral states and a touching pad's commanded position), which no field shows.

    changes: per factor the (plus, minus) :class:`SkinChange` of its changed models against ``model``; active: (S,)
    bool the estimate's contact state; theta: (n_theta,) its unknowns; normal: (B + S, B + S) the estimator's
    weighted normal matrix F W F^T over the seen nodes (F = [R G]^T); project(x): F W x (B + S, m) for skin fields x
    (N, m) mm over the seen nodes; to_theta(rhs): the estimator's linear map from a right-hand side change (B + S,)
    to theta; report(theta, springs): the (P,) reported values, read with the pad springs of ``springs`` (None: the
    model's). The effect is what the estimate (read with the model) reports minus what the changed part is (read
    with its own springs): a lifted pad's value is the part's position z - preload, which the change moves too. A
    factor's change is applied with both signs; the larger shift of the two (by its largest entry) is kept, signed
    as the + change's, so a nonlinear factor (the pad compliance 1/k) is not understated.

    The changed part's field less the nominal one at the estimate's state, w0' + R' a + G' f' - (w0 + R a + G f),
    is (s - 1) w0 + G (s f' - f) + e with e = (w0' - s w0) + (R' - R) a + (G' - s G) f' (:class:`SkinChange`, s its
    scale): its G part reaches the right-hand side through ``normal``, w0 and the e that are not zero through one
    ``project`` of all of them. Before, each factor and sign made its field and projected it: 60 of the 107 ms of a
    paper-resolution estimate (benchmarks/RESULTS.md issue 15 run 19 P).
    """
    n_b = model.n_bilateral
    pads = np.unique(model.pad_of[active])
    nominal = _forces(model, active, pads, theta)
    reported = report(theta, None)
    solved, columns = [], []
    for factor, pair in zip(factors, changes, strict=True):
        for changed, change in zip((factor.plus, factor.minus), pair, strict=True):
            forces = _forces(changed, active, pads, theta)
            column = None
            if change.w0 or change.R or change.G:
                extra = np.zeros(model.w0.shape[0])
                if change.w0:
                    extra += changed.w0 - change.scale * model.w0
                if change.R:
                    extra += (changed.R - model.R) @ theta[:n_b]
                if change.G:
                    extra += changed.G @ forces - change.scale * (model.G @ forces)
                column = len(columns)
                columns.append(extra)
            solved.append((changed, change, forces, column))
    scaled = any(change.scale != 1.0 for _, change, _, _ in solved)
    projected = project(np.column_stack([*columns, model.w0] if scaled else columns)) if columns or scaled else None
    effects, read = np.zeros((2, len(factors), reported.size))
    for i in range(len(factors)):
        shifts = []
        for changed, change, forces, column in solved[2 * i:2 * i + 2]:
            rhs = normal[:, n_b:] @ (change.scale * forces - nominal)
            if change.scale != 1.0:
                rhs = rhs + (change.scale - 1.0) * projected[:, -1]
            if column is not None:
                rhs = rhs + projected[:, column]
            part = report(theta, changed)
            shifts.append((np.nan_to_num(report(theta + to_theta(rhs), None) - part), np.nan_to_num(reported - part)))
        (up, up_read), (down, down_read) = shifts
        effects[i], read[i] = (up, up_read) if np.max(np.abs(up)) >= np.max(np.abs(down)) else (-down, -down_read)
    return effects, read
