"""A synthetic shift of parts with a known truth: declared states from a process model, undeclared effects in a share
of the parts, scan noise and occlusions (for the shift tests and benchmarks/bench_shift.py).

The process model (per declared parameter, mm): a baseline mean and a part-to-part spread (independent Gaussian),
plus a **drift** on one boundary (``drift_per_part`` spreads per part from ``drift_start`` on) and a **step** on
another (``step_size`` spreads from ``step_start`` on). Every part then carries at most one undeclared effect:

- ``candidate`` (share ``candidate_share``): a boundary input the model does not declare but an FE candidate
  explains (default ``hinge_R.z``, amplitude ``candidate_mm`` +- 10 %); its response comes from the truth reduced
  model, which holds it as an extra bilateral input (``reduce_model(solver, extra=[("hinge_R", "z")])``);
- ``bump`` (share ``bump_share``): a smooth Gaussian bump of the skin along its normal, amplitude uniform in
  ``bump_mm``, centred at ``bump_center`` (x, y mm; default 110 mm inboard of BUFFER_L), radius ``bump_radius_mm``
  (one standard deviation): a springback of the incoming panel that no boundary input explains.

The part's field is the exact contact solution of its states (with the candidate input) plus the bump, Gaussian noise
``noise_mm`` per node and ``holes`` round occlusions of radius ``hole_radius_mm`` (NaN). Everything of part i is
drawn from ``numpy.random.default_rng((seed, i))``, so any part can be made alone, in any process, in any order.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hood_decomp.core.fe.ensemble import solve_members
from hood_decomp.core.types import DisplacementField, ReducedModel, SkinSurface
from hood_decomp.errors import ModelError

EFFECT_KINDS = ("none", "candidate", "bump")


@dataclass(frozen=True)
class ProcessModel:
    """The process a shift is drawn from (module docstring). Dicts map declared parameter labels to mm; a label
    missing from ``mean_mm`` has mean 0, from ``spread_mm`` the spread ``default_spread_mm``."""

    mean_mm: dict[str, float] = field(default_factory=lambda: {"BUFFER_L": 0.4, "BUFFER_R": 0.4})
    spread_mm: dict[str, float] = field(default_factory=dict)
    default_spread_mm: float = 0.05
    drift_label: str | None = "LOCK_L"
    drift_start: int = 200
    drift_per_part: float = 0.05
    step_label: str | None = "HINGE_Y"
    step_start: int = 400
    step_size: float = 3.0
    candidate: str = "hinge_R.z"
    candidate_mm: float = 0.3
    candidate_share: float = 0.0
    bump_mm: tuple[float, float] = (0.1, 0.2)
    bump_share: float = 0.0
    bump_center: tuple[float, float] = (185.0, -609.5)
    bump_radius_mm: float = 90.0
    noise_mm: float = 0.02
    holes: int = 2
    hole_radius_mm: float = 120.0


@dataclass(frozen=True)
class ShiftPart:
    """One synthetic part. truth: (P,) commanded declared states, mm (names of the plan). effect: one of
    :data:`EFFECT_KINDS`; amplitude: its size (mm; 0 for none). clean: (N,) the noise-free field, mm;
    field: the measured field (noise, holes as NaN). displacement: (N, 3) mm, the noise-free 3D displacement."""

    part_id: str
    index: int
    stamp_ns: int
    truth: np.ndarray
    effect: str
    amplitude: float
    clean: np.ndarray
    displacement: np.ndarray
    field: DisplacementField


@dataclass(frozen=True)
class ShiftPlan:
    """The truth of a shift of M parts (every array row is one part). names: (P,) declared labels; truth: (M, P) mm;
    effect: (M,) kind index into :data:`EFFECT_KINDS`; amplitude: (M,) mm; seed, process: what drew them."""

    names: tuple[str, ...]
    truth: np.ndarray
    effect: np.ndarray
    amplitude: np.ndarray
    seed: int
    process: ProcessModel

    @property
    def n_parts(self) -> int:
        return int(self.truth.shape[0])

    def effect_of(self, index: int) -> str:
        return EFFECT_KINDS[int(self.effect[index])]


def plan_shift(names: tuple[str, ...], process: ProcessModel, n_parts: int, seed: int = 0) -> ShiftPlan:
    """Draw the declared states and undeclared effects of ``n_parts`` parts (module docstring)."""
    for label in (*process.mean_mm, *process.spread_mm, process.drift_label, process.step_label):
        if label is not None and label not in names:
            raise ModelError(f"process model names {label!r}, not a declared parameter of {names}")
    if n_parts < 1:
        raise ModelError(f"a shift needs at least one part, got {n_parts}")
    if not 0.0 <= process.candidate_share + process.bump_share <= 1.0:
        raise ModelError("candidate_share + bump_share must lie in [0, 1]")
    mean = np.array([process.mean_mm.get(n, 0.0) for n in names])
    spread = np.array([process.spread_mm.get(n, process.default_spread_mm) for n in names])
    index = np.arange(n_parts)
    truth = np.empty((n_parts, len(names)))
    effect = np.zeros(n_parts, dtype=np.int64)
    amplitude = np.zeros(n_parts)
    for i in index:
        rng = np.random.default_rng((seed, int(i)))
        truth[i] = mean + spread * rng.standard_normal(len(names))
        draw = rng.uniform()
        if draw < process.candidate_share:
            effect[i], amplitude[i] = 1, process.candidate_mm * rng.uniform(0.9, 1.1)
        elif draw < process.candidate_share + process.bump_share:
            effect[i], amplitude[i] = 2, rng.uniform(*process.bump_mm)
    if process.drift_label is not None:
        column = names.index(process.drift_label)
        truth[:, column] += spread[column] * process.drift_per_part * np.clip(index - process.drift_start + 1, 0, None)
    if process.step_label is not None:
        column = names.index(process.step_label)
        truth[:, column] += spread[column] * process.step_size * (index >= process.step_start)
    return ShiftPlan(tuple(names), truth, effect, amplitude, seed, process)


def bump_field(skin: SkinSurface, center_xy: tuple[float, float], radius_mm: float) -> np.ndarray:
    """Unit-amplitude Gaussian bump (N,) along the skin normal: exp(-d^2 / 2 r^2), d the plan distance to the centre."""
    distance2 = np.sum((skin.points[:, :2] - np.asarray(center_xy, float)) ** 2, axis=1)
    return np.exp(-0.5 * distance2 / radius_mm**2)


def make_part(plan: ShiftPlan, index: int, truth_model: ReducedModel, skin: SkinSurface,
              start_ns: int = 1_000_000_000_000, period_ns: int = 1_000_000_000) -> ShiftPart:
    """Part ``index`` of ``plan``: exact contact solution with ``truth_model`` (the declared inputs of the plan plus
    the candidate input), plus the bump, noise and holes."""
    process = plan.process
    if process.candidate not in truth_model.names:
        raise ModelError(f"the truth model must hold the candidate input {process.candidate!r} as an extra input; "
                         f"it has {truth_model.names}")
    if skin.model_id != truth_model.model_id:
        raise ModelError(f"skin model_id {skin.model_id!r} differs from the truth model's {truth_model.model_id!r}")
    state = np.zeros(len(truth_model.names))
    for column, name in enumerate(plan.names):
        state[truth_model.names.index(name)] = plan.truth[index, column]
    kind = plan.effect_of(index)
    if kind == "candidate":
        state[truth_model.names.index(process.candidate)] = plan.amplitude[index]
    solved = solve_members(truth_model, state[None, :])
    clean = solved.normal_displacement[0].copy()
    displacement = solved.displacement[0].copy()
    if kind == "bump":
        bump = plan.amplitude[index] * bump_field(skin, process.bump_center, process.bump_radius_mm)
        clean += bump
        displacement += skin.normals * bump[:, None]
    rng = np.random.default_rng((plan.seed, index, 1))
    measured = clean + process.noise_mm * rng.standard_normal(skin.n_nodes)
    lo, hi = skin.points[:, :2].min(axis=0), skin.points[:, :2].max(axis=0)
    for centre in rng.uniform(lo, hi, size=(process.holes, 2)):
        measured[np.hypot(*(skin.points[:, :2] - centre).T) < process.hole_radius_mm] = np.nan
    seen = np.isfinite(measured)
    field_ = DisplacementField(skin.model_id, measured, float(seen.mean()), process.noise_mm)
    return ShiftPart(f"part-{plan.seed}-{index:05d}", index, start_ns + index * period_ns, plan.truth[index].copy(),
                     kind, float(plan.amplitude[index]), clean, displacement, field_)
