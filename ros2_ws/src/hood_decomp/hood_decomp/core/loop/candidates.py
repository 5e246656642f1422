"""Candidate effects the model lacks, enumerated from the model itself, and their response fields.

A candidate is one boundary input that is not a declared parameter, with a unit response the factorised solver gives
by a pair of triangular solves (:class:`~hood_decomp.core.fe.solver.ShellSolver`):

- ``motion``: a 1 mm motion of a boundary patch along x, y or z (:meth:`ShellSolver.boundary_response`). For every
  fixed or prescribed boundary, each translation that no parameter declares (hood: hinge_R.x/y/z, hinge_L.z) and the
  in-plane translations it does not constrain (lock_L.x/y: the lock holds the part sideways and is displaced); for
  every pad, its translations other than the declared one (buffer_L.x/y: a pad that holds the part by friction).
- ``force``: a 1 N total force spread over a boundary patch along an axis (:meth:`ShellSolver.force_response`). Every
  force boundary along its own axis ("gas_spring_L.force": a gas spring force change), and every pad along its axis
  ("buffer_L.stick": an extra pad force; negative means the pad pulls, a buffer that does not release).
- user candidates: a ``candidates:`` list in model.yaml, e.g. ``{boundary: lock_L, kind: force, direction: y}``
  (parsed by :func:`candidates_from_document`; :func:`hood_decomp.io.model_files.load_model_with_candidates` reads it
  with the model). A location that is no boundary yet becomes one by adding a ``force`` boundary with ``force: 0`` to
  model.yaml: its force candidate is then enumerated.

Responses are computed once per model (hundreds of candidates: seconds) and appended to a reduced model as extra
bilateral inputs by :func:`augment_reduced` (the same columns :func:`~hood_decomp.core.fe.solver.reduce_model` builds
for ``extra`` motions). Progress goes to this module's logger.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from hood_decomp.core.fe.model import AXES, PartModel, skin_surface
from hood_decomp.core.fe.solver import ShellSolver
from hood_decomp.core.types import ReducedModel
from hood_decomp.errors import ModelError

logger = logging.getLogger(__name__)

KINDS = ("motion", "force")
UNITS = {"motion": "mm", "force": "N"}
#: a candidate whose largest skin response is below this fraction of the largest of all candidates moves nothing
NEGLIGIBLE_RTOL = 1e-9


@dataclass(frozen=True)
class Candidate:
    """One candidate effect: ``kind`` "motion" (unit 1 mm along ``axis``, a coordinate axis) or "force" (unit 1 N
    along ``axis``, spread over the patch) of boundary ``boundary``. name: e.g. "hinge_R.z", "gas_spring_L.force".
    unit: "mm" or "N". description: one line for reports."""

    name: str
    boundary: str
    kind: str
    axis: tuple[float, float, float]
    description: str

    @property
    def unit(self) -> str:
        return UNITS[self.kind]

    @property
    def direction(self) -> str:
        """The coordinate axis of a motion ("x", "y" or "z")."""
        return "xyz"[int(np.argmax(np.abs(self.axis)))]


def _unit_axis(direction: str) -> tuple[float, float, float]:
    axis = [0.0, 0.0, 0.0]
    axis[AXES[direction]] = 1.0
    return (axis[0], axis[1], axis[2])


def motion(boundary: str, direction: str, description: str = "") -> Candidate:
    """A unit boundary motion candidate named "boundary.direction"."""
    if direction not in AXES:
        raise ModelError(f"candidate motion direction must be x, y or z, got {direction!r}")
    return Candidate(f"{boundary}.{direction}", boundary, "motion", _unit_axis(direction),
                     description or f"{boundary} moves along {direction}")


def force(boundary: str, axis: Sequence[float], name: str, description: str) -> Candidate:
    """A unit (1 N) force candidate along ``axis`` (normalised)."""
    vector = np.asarray(axis, dtype=float)
    length = float(np.linalg.norm(vector)) if vector.shape == (3,) else 0.0
    if not length > 0 or not np.isfinite(length):
        raise ModelError(f"candidate {name!r}: force axis must be a non-zero 3-vector, got {list(axis)}")
    vector = vector / length
    return Candidate(name, boundary, "force", (float(vector[0]), float(vector[1]), float(vector[2])), description)


def enumerate_candidates(model: PartModel, user: Sequence[Candidate] = ()) -> tuple[Candidate, ...]:
    """Every boundary input of ``model`` that no parameter declares (module docstring), then ``user`` candidates.

    A user candidate with the name of an enumerated one replaces it. Raises ModelError for a user candidate on an
    unknown boundary.
    """
    declared = {(p.boundary, p.direction) for p in model.parameters}
    found: dict[str, Candidate] = {}
    for boundary in model.boundaries:
        name = boundary.name
        if boundary.kind in ("fixed", "prescribed"):
            for direction in AXES:
                if (name, direction) in declared:
                    continue
                held = "held" if direction in boundary.dofs else "in-plane, not constrained"
                found[f"{name}.{direction}"] = motion(name, direction, f"{name} moves along {direction} ({held})")
        elif boundary.kind == "unilateral":
            for direction in AXES:
                if (name, direction) not in declared:
                    found[f"{name}.{direction}"] = motion(name, direction,
                                                          f"pad {name} drags the part along {direction}")
            found[f"{name}.stick"] = force(name, boundary.axis, f"{name}.stick",
                                           f"extra force of pad {name} along its axis (< 0: the pad sticks and pulls)")
        elif boundary.kind == "force":
            found[f"{name}.force"] = force(name, boundary.axis, f"{name}.force", f"force of {name} changes")
    for candidate in user:
        model.boundary(candidate.boundary)
        found[candidate.name] = candidate
    return tuple(found.values())


def candidates_from_document(entries: object) -> tuple[Candidate, ...]:
    """Parse the ``candidates:`` list of a model.yaml document (already loaded with yaml.safe_load).

    Each entry: ``{boundary: B, kind: motion, direction: x|y|z}`` or ``{boundary: B, kind: force, direction: x|y|z}``
    or ``{boundary: B, kind: force, axis: [ax, ay, az]}``; optional ``name`` and ``description``. None: no candidates.
    Raises ModelError naming the entry for anything else.
    """
    if entries is None:
        return ()
    if not isinstance(entries, list):
        raise ModelError(f"model.yaml 'candidates' must be a list, got {type(entries).__name__}")
    out = []
    for index, entry in enumerate(entries):
        if not isinstance(entry, dict) or "boundary" not in entry or entry.get("kind") not in KINDS:
            raise ModelError(f"candidates entry #{index} {entry!r}: expected a mapping with 'boundary' and "
                             f"'kind' one of {KINDS}")
        boundary, kind = str(entry["boundary"]), str(entry["kind"])
        direction = str(entry.get("direction", "")).lower()
        description = str(entry.get("description", ""))
        if kind == "motion":
            candidate = motion(boundary, direction, description)
        elif "axis" in entry:
            axis = entry["axis"]
            if not isinstance(axis, list | tuple) or len(axis) != 3:
                raise ModelError(f"candidates entry #{index}: axis must be 3 numbers, got {axis!r}")
            name = f"{boundary}.force[{','.join(f'{float(a):g}' for a in axis)}]"
            candidate = force(boundary, [float(a) for a in axis], name, description or f"force on {boundary}")
        elif direction in AXES:
            candidate = force(boundary, _unit_axis(direction), f"{boundary}.force_{direction}",
                              description or f"force on {boundary} along {direction}")
        else:
            raise ModelError(f"candidates entry #{index}: a force needs 'direction' (x|y|z) or 'axis', got {entry!r}")
        if "name" in entry:
            candidate = replace(candidate, name=str(entry["name"]))
        out.append(candidate)
    return tuple(out)


@dataclass(frozen=True)
class CandidateFields:
    """Unit responses of candidates (C of them) on the visible skin (N nodes) and at the pad springs (S).

    candidates: (C,). normal: (N, C) skin normal displacement per unit input (mm/mm or mm/N). vectors: (N, 3, C)
    the same as 3D vectors. pad: (S, C) pad spring axial displacement per unit input. dropped: names of candidates
    left out because they move nothing on the skin (e.g. a force on a held direction).
    """

    candidates: tuple[Candidate, ...]
    normal: np.ndarray
    vectors: np.ndarray
    pad: np.ndarray
    dropped: tuple[str, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.candidates)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise ModelError(f"unknown candidate {name!r}; known: {list(self.names)}") from None


def candidate_response(solver: ShellSolver, candidate: Candidate) -> np.ndarray:
    """Full displacement (6n,) mm of one candidate's unit input from the factorised solver."""
    if candidate.kind == "motion":
        return solver.boundary_response(candidate.boundary, candidate.direction)
    # force_response is linear in the force direction: combine the coordinate responses the axis needs
    return sum(a * solver.force_response(candidate.boundary, d) for d, a in zip("xyz", candidate.axis, strict=True)
               if a != 0.0)


def candidate_fields(solver: ShellSolver, candidates: Sequence[Candidate]) -> CandidateFields:
    """Solve every candidate's unit response (one factorisation, shared) and condense it to the skin and pads."""
    model = solver.model
    if not candidates:
        raise ModelError("no candidate effects to trace: the model declares every boundary input as a parameter")
    normals = skin_surface(model).normals
    skin = model.skin_nodes
    columns = []
    for index, candidate in enumerate(candidates):
        columns.append(candidate_response(solver, candidate))
        logger.info("candidate %d/%d %s solved", index + 1, len(candidates), candidate.name)
    U = np.stack(columns, axis=1)
    vectors = U.reshape(len(model.nodes), 6, -1)[skin, :3]
    normal = np.einsum("nak,na->nk", vectors, normals)
    pads = solver.pads.loads
    pad = np.asarray(pads.T @ U) if pads.shape[1] else np.zeros((0, U.shape[1]))
    size = np.abs(normal).max(axis=0)
    keep = size > NEGLIGIBLE_RTOL * max(size.max(), 1e-300)
    return CandidateFields(
        candidates=tuple(c for c, k in zip(candidates, keep, strict=True) if k),
        normal=normal[:, keep], vectors=vectors[:, :, keep], pad=pad[:, keep],
        dropped=tuple(c.name for c, k in zip(candidates, keep, strict=True) if not k),
    )


def augment_reduced(reduced: ReducedModel, fields: CandidateFields, names: Sequence[str]) -> ReducedModel:
    """``reduced`` with the named candidates appended as bilateral inputs (after the existing bilateral ones).

    Inputs are named by the candidate names; their state is in the candidate's unit (mm or N). Raises ModelError for
    a candidate already in the model or unknown.
    """
    if set(names) & set(reduced.names):
        raise ModelError(f"candidates {sorted(set(names) & set(reduced.names))} are already inputs of the model")
    columns = [fields.index(name) for name in names]
    b = reduced.n_bilateral
    return replace(
        reduced,
        names=(*reduced.names[:b], *names, *reduced.names[b:]),
        n_bilateral=b + len(columns),
        R=np.hstack([reduced.R, fields.normal[:, columns]]),
        Sa=np.hstack([reduced.Sa, fields.pad[:, columns]]),
        R_3d=np.concatenate([reduced.R_3d, fields.vectors[:, :, columns]], axis=2),
    )
