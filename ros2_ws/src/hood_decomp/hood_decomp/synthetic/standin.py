"""Stand-in parts for calibration tests and benchmarks: fields made by another model than the bases (issue 16).

A real part differs from its FE model. The stand-in is made by CalculiX (S8R shells, :mod:`core.fe.calculix`) on the
same mesh, with perturbed physics:

- per part *family* (a plant's parts share it; what a calibration can learn): Young's modulus x (1 +- 3 %), all
  sheet thicknesses x (1 +- 5 %), pad stiffness x (1 +- 30 %), pad preload x (1 +- 50 %), gas-spring force
  x (1 +- 5 %);
- per *part*: thickness x (1 +- 0.5 %) on top of the family's (what no calibration can learn: the floor).

CalculiX runs cost seconds each, so a family is not one CalculiX run per part: the unit responses (the load split
into gravity and gas springs, one unit motion per bilateral parameter) are solved by CalculiX at three thickness
scales and interpolated quadratically in the thickness scale (responses are smooth in it); the pad spring responses
(most of the jobs) by CalculiX at the nominal thickness, moved to other thicknesses by the embedded solver's
difference (a first-order mix: the part of the stand-in that is not pure CalculiX); Young's modulus scales every
force response by 1/E exactly (the unit motions not at all); pad stiffness and preload enter the pad contact, which
is solved exactly per part with the repository's contact solver on the CalculiX responses (the buffers are the only
nonlinearity): that is what ``ensemble --solver calculix`` does too.

On a mesh whose jobs are too large to run two at a time (the default hood: ~7.7 GB a job), :func:`serial_responses`
makes the load, gas-spring and unit responses at the three thickness scales, one job at a time under a flock,
resumable, and :class:`StandIn` takes the embedded solver's pad responses at every scale (``embedded_pads``: the
default hood's 68 pad springs would be 68 more such jobs at scale 1, out of reach).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from hood_decomp.core.fe.calculix import LoadCase, holding, load_cases, run_case, run_cases
from hood_decomp.core.fe.ensemble import solve_members
from hood_decomp.core.fe.model import PartModel
from hood_decomp.core.fe.solver import PAD_LATTICE, assemble, build_solver, force_boundary_loads, pad_springs, project
from hood_decomp.core.types import ReducedModel
from hood_decomp.errors import SolverError

logger = logging.getLogger(__name__)

#: thickness scales at which CalculiX solves the unit responses (quadratic interpolation between them)
THICKNESS_SCALES = (0.95, 1.0, 1.05)
#: half-widths of the family perturbations (relative, except preload: relative to the model's preload)
FAMILY_SPREAD = {"E": 0.03, "thickness": 0.05, "pad_stiffness": 0.30, "preload": 0.50, "gas_spring": 0.05}
#: half-width of the per-part thickness variation (relative)
PART_THICKNESS_SPREAD = 0.005


def scaled_thickness(model: PartModel, scale: float) -> PartModel:
    """The model with every part's thickness times ``scale`` (mesh and model_id unchanged)."""
    return replace(model, parts=tuple(replace(p, thickness=p.thickness * scale) for p in model.parts))


def stand_in_cases(model: PartModel, scale: float = 1.0, pads: bool = True, pad_lattice: int = PAD_LATTICE
                   ) -> tuple[PartModel, list[LoadCase], np.ndarray]:
    """The stand-in's CalculiX jobs at thickness ``scale``: "load", "unit_<LABEL>" per bilateral parameter, "gas"
    (the gas springs' force alone) and, with ``pads``, "pad_<s>" per pad spring. Returns the scaled model, the cases
    and the constrained DOFs (C,)."""
    scaled = scaled_thickness(model, scale)
    cases, constrained = load_cases(scaled, pad_lattice)
    cases = [c for c in cases if pads or not c.name.startswith("pad_")]
    cases.append(LoadCase("gas", force_boundary_loads(scaled), np.zeros(len(constrained))))
    return scaled, cases, constrained


def serial_responses(model: PartModel, cache: Path, lock: Path | None = None,
                     scales: tuple[float, ...] = THICKNESS_SCALES, timeout: float = 4 * 3600.0
                     ) -> dict[float, dict[str, np.ndarray]]:
    """CalculiX translations (n, 3) mm of ``model`` without the pad jobs ("load", "gas", "unit_<LABEL>";
    :func:`stand_in_cases`) per thickness scale, in :func:`calculix_responses`' layout, for a mesh too large to run
    two jobs at a time (the default hood: ~7.7 GB and 140-1000 s a job). ``cache``: an .npz (with "model_id" and
    "scales") read when present, its model_id matches and it holds every scale, else made: one job at a time in this
    process, each holding ``lock`` (flock) and stored on completion in ``<cache>.jobs/<model_id>/<name>.npy`` at scale
    1 (the layout of session 14's nominal cache, whose jobs are reused) and ``.../<scale>/<name>.npy`` at the others
    (a rerun resumes), the .npz written under another name and renamed when complete.
    """
    cache = Path(cache)
    if cache.exists():
        with np.load(cache, allow_pickle=False) as data:
            if str(data["model_id"]) != model.model_id:
                raise SolverError(f"{cache}: model_id {data['model_id']} is not {model.model_id}")
            # a cache of fewer scales (session 14's: nominal only, no "scales") is completed from the jobs
            if "scales" in data.files and set(scales) <= set(data["scales"].tolist()):
                return _unpack(data, scales)
    out: dict[float, dict[str, np.ndarray]] = {}
    for scale in scales:
        scaled, cases, constrained = stand_in_cases(model, scale, pads=False)
        jobs = cache.with_suffix(".jobs") / model.model_id
        if scale != 1.0:
            jobs = jobs / f"{float(scale)!r}"
        jobs.mkdir(parents=True, exist_ok=True)
        out[float(scale)] = {}
        for done, case in enumerate(cases, start=1):
            path = jobs / f"{case.name}.npy"
            if not path.exists():
                with holding(lock):
                    # looked at again once the lock is held: another process may have run it meanwhile
                    if not path.exists():
                        partial = path.with_suffix(".partial.npy")
                        np.save(partial, run_case(scaled, case, constrained, timeout=timeout))
                        partial.replace(path)
            out[float(scale)][case.name] = np.load(path)
            logger.info("serial CalculiX responses at thickness %.3f: %s done (%d/%d)", scale, case.name, done,
                        len(cases))
    _store(cache, model, scales, out)
    return out


def _unpack(data, scales: tuple[float, ...]) -> dict[float, dict[str, np.ndarray]]:
    """The responses per scale of an .npz written by :func:`_store` (keys "<scale>|<name>"), at ``scales``."""
    out: dict[float, dict[str, np.ndarray]] = {float(s): {} for s in scales}
    for key in data.files:
        if "|" in key:
            scale, name = key.split("|", 1)
            if float(scale) in out:
                out[float(scale)][name] = data[key]
    return out


def _store(cache: Path, model: PartModel, scales: tuple[float, ...],
           out: dict[float, dict[str, np.ndarray]]) -> None:
    """Write the responses per scale to ``cache`` (.npz with "model_id", "scales" and "<scale>|<name>" keys); written
    under another name (this process's: two processes that waited on each other's jobs store about together) and
    renamed when complete: another process may read the cache once it exists."""
    arrays = {f"{s!r}|{name}": value for s, columns in out.items() for name, value in columns.items()}
    partial = Path(cache).with_suffix(f".{os.getpid()}.partial.npz")
    np.savez_compressed(partial, model_id=np.array(model.model_id), scales=np.array(scales), **arrays)
    partial.replace(cache)


def calculix_responses(model: PartModel, scales: tuple[float, ...] = THICKNESS_SCALES,
                       cache: Path | None = None, pad_lattice: int = PAD_LATTICE) -> dict[float, dict[str, np.ndarray]]:
    """CalculiX translations (n, 3) mm per thickness scale: "load" (gravity + gas springs), "gas" (gas springs
    alone), "unit_<LABEL>" per bilateral parameter at every scale, and "pad_<s>" per pad spring at scale 1 only (the
    pad responses are 28 of 34 jobs on the coarse hood; :class:`StandIn` moves them with thickness by the embedded
    solver's difference). ``cache``: an .npz read when present (and its model_id matches) and written after the runs
    (complete or not at all).
    """
    if cache is not None and Path(cache).exists():
        with np.load(cache, allow_pickle=False) as data:
            if str(data["model_id"]) == model.model_id and tuple(data["scales"]) == tuple(scales):
                return _unpack(data, scales)
    out = {}
    for scale in scales:
        scaled, cases, constrained = stand_in_cases(model, scale, pads=scale == 1.0, pad_lattice=pad_lattice)
        logger.info("stand-in: %d CalculiX jobs at thickness scale %.3f", len(cases), scale)
        out[scale] = run_cases(scaled, cases, constrained)
    if cache is not None:
        _store(cache, model, scales, out)
    return out


@dataclass(frozen=True)
class Family:
    """One part family's physics, relative to the model: E, thickness, pad stiffness, gas-spring force as factors;
    preload as a factor on the model's preload."""

    E: float = 1.0
    thickness: float = 1.0
    pad_stiffness: float = 1.0
    preload: float = 1.0
    gas_spring: float = 1.0

    @staticmethod
    def draw(rng: np.random.Generator) -> Family:
        """A family with every factor uniform in 1 +- :data:`FAMILY_SPREAD`."""
        return Family(**{key: float(1.0 + rng.uniform(-spread, spread)) for key, spread in FAMILY_SPREAD.items()})


def embedded_pad_responses(model: PartModel, scale: float, pad_lattice: int = PAD_LATTICE) -> np.ndarray:
    """The embedded solver's pad spring responses (n, 3, S) mm of the model at thickness ``scale``."""
    return build_solver(scaled_thickness(model, scale), validate=False, pad_lattice=pad_lattice).pad_responses()


@dataclass(frozen=True)
class StandInParts:
    """Stand-in parts (m of them): normal_displacement (m, N) mm, noise-free; effective (m, P) mm the parameter states
    (a lifted pad's: the part's position there); reactions (m, U) N total pad reactions; position (m, U) mm the part's
    position at each pad (where it would just touch; below a touching pad's commanded position by its largest spring
    compression)."""

    normal_displacement: np.ndarray
    effective: np.ndarray
    reactions: np.ndarray
    position: np.ndarray


class StandIn:
    """Stand-in parts of one model from CalculiX responses (:func:`calculix_responses`, or :func:`serial_responses`
    with ``embedded_pads``).

    ``reduced(family, thickness)`` is the CalculiX reduced model of a part (thickness: the part's own factor on top of
    the family's); ``fields(family, settings, rng)`` makes the skin normal fields (m, N) of m parts of a family at
    commanded settings (m, P) mm, each with its own thickness variation (:class:`StandInParts`).

    The pad spring responses: CalculiX's at scale 1 (``responses[1.0]["pad_<s>"]``) moved to the other scales by the
    embedded solver's change with thickness; with ``embedded_pads`` (responses without pad jobs: the default hood's
    68 pad jobs of ~7.7 GB each are out of reach) the embedded solver's at every scale.
    """

    def __init__(self, model: PartModel, responses: dict[float, dict[str, np.ndarray]],
                 pad_lattice: int = PAD_LATTICE, embedded_pads: bool = False) -> None:
        self.model = model
        self.scales = np.array(sorted(responses))
        if len(self.scales) != 3 or 1.0 not in self.scales:
            raise SolverError(f"stand-in needs responses at 3 thickness scales including 1.0, got {self.scales}")
        self.pads = pad_springs(model, pad_lattice)
        bilateral = [f"unit_{p.label}" for p in model.bilateral]
        calculix_pads = sorted(name for name in responses[1.0] if name.startswith("pad_"))
        embedded = {float(s): embedded_pad_responses(model, s, pad_lattice) for s in self.scales}
        pad_names = [f"pad_{s:03d}" for s in range(embedded[1.0].shape[2])]
        if embedded_pads and calculix_pads:
            raise SolverError(f"embedded_pads, but the responses hold {len(calculix_pads)} CalculiX pad responses")
        if not embedded_pads and calculix_pads != pad_names:
            raise SolverError(f"{len(calculix_pads)} CalculiX pad responses (pad_000, ...) for {len(pad_names)} "
                              "pad springs; without them pass embedded_pads=True")
        # the projections the reduced model keeps, per scale (linear in the translations: a part interpolates and
        # combines them, not the (n, 3) translations, ~1 s a part on the default hood)
        self._projected = {}
        for scale in map(float, self.scales):
            columns = np.stack([responses[scale][name] for name in ("load", "gas", *bilateral)], axis=2)
            if embedded_pads:
                pads = embedded[scale]
            else:  # CalculiX at scale 1 plus the embedded solver's change with thickness
                pads = np.stack([responses[1.0][name] for name in pad_names], axis=2) + embedded[scale] \
                    - embedded[1.0]
            self._projected[scale] = (project(model, self.pads, columns), project(model, self.pads, pads))

    def _interpolate(self, scale: float) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
        """Quadratic (Lagrange) interpolation of the projections in the thickness scale."""
        x = self.scales
        weights = [np.prod([(scale - x[m]) / (x[i] - x[m]) for m in range(3) if m != i]) for i in range(3)]
        return tuple(tuple(sum(w * self._projected[float(x[i])][side][k] for i, w in enumerate(weights))
                           for k in range(3)) for side in range(2))

    def reduced(self, family: Family, thickness: float = 1.0) -> ReducedModel:
        """The CalculiX reduced model of a part of ``family`` with its own thickness factor ``thickness``."""
        projected, pad_projected = self._interpolate(family.thickness * thickness)
        # columns load, gas, units: the load with the family's gas-spring force, forces over E (not the unit motions)
        projected = tuple(np.concatenate([((p[..., 0] + (family.gas_spring - 1.0) * p[..., 1]) / family.E)[..., None],
                                          p[..., 2:]], axis=-1) for p in projected)
        pad_projected = tuple(p / family.E for p in pad_projected)
        names = tuple(p.label for p in self.model.bilateral) + tuple(p.label for p in self.model.unilateral)
        reduced = assemble(self.model, self.pads, projected, pad_projected, names, len(self.model.bilateral))
        return replace(reduced, k=reduced.k * family.pad_stiffness, preload=reduced.preload * family.preload)

    def fields(self, family: Family, settings: np.ndarray, rng: np.random.Generator,
               part_spread: float = PART_THICKNESS_SPREAD) -> StandInParts:
        """m parts of ``family`` at commanded settings (m, P) mm, each part with its own thickness factor, uniform in
        1 +- ``part_spread``."""
        settings = np.atleast_2d(np.asarray(settings, dtype=float))
        n_pads = len(self.model.unilateral)
        out = np.empty((len(settings), len(self.model.skin_nodes)))
        effective = np.empty_like(settings)
        reactions, position = np.empty((len(settings), n_pads)), np.empty((len(settings), n_pads))
        for i, setting in enumerate(settings):
            # drawn at part_spread 0 too: the same parts and noise draws with and without the variation
            thickness = 1.0 + part_spread * rng.uniform(-1.0, 1.0)
            block = solve_members(self.reduced(family, thickness), setting[None, :])
            out[i], effective[i], reactions[i] = block.normal_displacement[0], block.effective[0], block.reactions[0]
            position[i] = pad_positions(setting[None, :], block.compression, self.pads.pad_of)[0]
        return StandInParts(out, effective, reactions, position)


def pad_positions(settings: np.ndarray, compression: np.ndarray, pad_of: np.ndarray) -> np.ndarray:
    """The part's position (m, U) mm at each pad of members at commanded settings (m, P) mm (the pads last) with
    spring compressions (m, S) mm (:class:`~hood_decomp.core.fe.ensemble.MemberBlock`) and pad_of (S,): where the pad
    would just touch, below a touching pad's commanded position by its largest spring compression."""
    n_pads = int(pad_of.max()) + 1
    # b - compression = z - preload per spring; its minimum is the part's position at the pad
    return np.stack([np.min(settings[:, -n_pads + u, None] - compression[:, pad_of == u], axis=1)
                     for u in range(n_pads)], axis=1)


def embedded_responses(model: PartModel, scales: tuple[float, ...] = THICKNESS_SCALES,
                       pad_lattice: int = PAD_LATTICE) -> dict[float, dict[str, np.ndarray]]:
    """The embedded solver's translations (n, 3) mm in :func:`calculix_responses`' layout ("load", "gas",
    "unit_<LABEL>" per scale, "pad_<s>" at scale 1), so :class:`StandIn` makes perturbed-physics parts from the bases'
    own solver: a discrepancy of physics alone, with no change of element or mesh (issue 15, harness (ii) a)."""
    out: dict[float, dict[str, np.ndarray]] = {}
    for scale in scales:
        solver = build_solver(scaled_thickness(model, scale), validate=False, pad_lattice=pad_lattice)
        n = len(model.nodes)
        gas = np.zeros((n, 6))
        gas[:, :3] = force_boundary_loads(solver.model)
        columns = {"load": solver.load_response(), "gas": solver.solve(gas.ravel())}
        columns.update({f"unit_{p.label}": solver.boundary_response(p.boundary, p.direction)
                        for p in model.bilateral})
        out[float(scale)] = {name: value.reshape(n, 6)[:, :3] for name, value in columns.items()}
        if scale == 1.0:
            pads = solver.pad_responses()
            out[1.0].update({f"pad_{s:03d}": pads[:, :, s] for s in range(pads.shape[2])})
    return out
