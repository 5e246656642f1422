"""The part model on disk: a human-editable ``model.yaml`` plus a mesh file (.vtu), validated on load.

model.yaml (format hood_decomp.model, version 1)::

    format: hood_decomp.model
    version: 1
    name: hood-default
    mesh: mesh.vtu                 # relative to model.yaml; quad cells with cell data 'part' (index into parts),
                                   # or an ABAQUS/CalculiX deck (.inp): S4/S8R *ELEMENT blocks, ELSET = a part name
    skin_part: outer_skin          # the visible outer skin
    material: {E: 210000.0, nu: 0.3, density: 7.85e-9}    # MPa, -, t/mm^3; optional, default core.fe.model.Material
    gravity: [0.0, 0.0, -9810.0]   # mm/s^2; optional, default core.fe.model.GRAVITY
    parameter_states: effective    # optional: effective (default; a lifted buffer's state is the part's position
                                   # there) or commanded (the paper's convention, preset hood-paper)
    parts:                         # order = the mesh's 'part' index
      - {name: outer_skin, thickness: 0.7}                 # mm
    boundaries:
      - name: hinge_R
        kind: fixed                # fixed | prescribed | unilateral | force
        dofs: [x, y, z]            # fixed/prescribed: constrained translations
        patch: {center: [1175.0, 615.0, 190.0], radius: 30.0, parts: [inner_panel], exclude_parts: [outer_skin]}
      - name: buffer_L
        kind: unilateral           # rubber pad: compression-only springs over the patch
        axis: [0.0, 0.0, 1.0]      # direction the pad pushes the part
        stiffness: 60.0            # N/mm, whole pad
        preload: 0.35              # mm
        patch: {nodes: [12, 13, 14]}     # or an explicit node set
      - name: gas_spring_L
        kind: force
        axis: [0.866, 0.0, 0.5]
        force: 580.0               # N, spread over the patch
        patch: {...}
    parameters:                    # bilateral (prescribed) first, then unilateral
      - {label: HINGE_X, boundary: hinge_L, direction: x, range: [-1.0, 1.0]}   # mm
    candidates:                    # optional: user candidate effects of close-loop (core.loop.candidates)
      - {boundary: lock_L, kind: force, direction: y}

Every problem is a ModelError naming the entry, what was expected and what was found.
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from hood_decomp.core.fe.model import GRAVITY, Boundary, Material, Parameter, Part, PartModel, Patch, validate_model
from hood_decomp.errors import MeshError, ModelError
from hood_decomp.io.mesh import read_inp_mesh, read_mesh, write_mesh

if TYPE_CHECKING:
    from hood_decomp.core.loop.candidates import Candidate

FORMAT = "hood_decomp.model"
VERSION = 1
MODEL_FILE = "model.yaml"
MESH_FILE = "mesh.vtu"


def save_model(model: PartModel, directory: str | Path) -> Path:
    """Write ``directory/model.yaml`` and ``directory/mesh.vtu``; returns the model.yaml path."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    write_mesh(directory / MESH_FILE, model.nodes, model.cells, model.cell_part)
    document = {
        "format": FORMAT,
        "version": VERSION,
        "name": model.name,
        "mesh": MESH_FILE,
        "skin_part": model.skin_part,
        "material": {"E": model.material.E, "nu": model.material.nu, "density": model.material.density},
        "gravity": [float(g) for g in model.gravity],
        "parameter_states": model.parameter_states,
        "parts": [{"name": p.name, "thickness": float(p.thickness)} for p in model.parts],
        "boundaries": [_boundary_dict(b) for b in model.boundaries],
        "parameters": [
            {"label": p.label, "boundary": p.boundary, "direction": p.direction,
             "range": [float(p.lower), float(p.upper)]}
            for p in model.parameters
        ],
    }
    path = directory / MODEL_FILE
    path.write_text(yaml.safe_dump(document, sort_keys=False, default_flow_style=None, width=120))
    return path


def _boundary_dict(boundary: Boundary) -> dict[str, Any]:
    patch: dict[str, Any] = {}
    if boundary.patch.nodes:
        patch["nodes"] = [int(n) for n in boundary.patch.nodes]
    else:
        patch["center"] = [round(float(c), 6) for c in boundary.patch.center]
        patch["radius"] = float(boundary.patch.radius)
    if boundary.patch.parts:
        patch["parts"] = list(boundary.patch.parts)
    if boundary.patch.exclude_parts:
        patch["exclude_parts"] = list(boundary.patch.exclude_parts)
    out: dict[str, Any] = {"name": boundary.name, "kind": boundary.kind}
    if boundary.kind in ("fixed", "prescribed"):
        out["dofs"] = list(boundary.dofs)
    if boundary.kind in ("unilateral", "force"):
        out["axis"] = [round(float(a), 12) for a in boundary.axis]
    if boundary.kind == "unilateral":
        out["stiffness"] = float(boundary.stiffness)
        out["preload"] = float(boundary.preload)
    if boundary.kind == "force":
        out["force"] = float(boundary.force)
    out["patch"] = patch
    return out


def model_path(path: str | Path) -> Path:
    """model.yaml of a model directory (or the file itself)."""
    path = Path(path)
    return path / MODEL_FILE if path.is_dir() else path


def load_model(path: str | Path) -> PartModel:
    """Read and validate a model (directory or model.yaml). Raises ModelError."""
    return _read(path)[0]


def load_model_with_candidates(path: str | Path) -> tuple[PartModel, tuple[Candidate, ...]]:
    """The model (as :func:`load_model`) and the user candidate effects of its optional ``candidates:`` list, from one
    read of model.yaml. Raises ModelError."""
    from hood_decomp.core.loop.candidates import candidates_from_document  # the loop loads only for who asks

    model, document = _read(path)
    return model, candidates_from_document(document.get("candidates"))


def _read(path: str | Path) -> tuple[PartModel, dict]:
    """The validated model and the parsed model.yaml document."""
    path = model_path(path)
    if not path.is_file():
        raise ModelError(f"model file {path} does not exist (expected a model directory or its model.yaml)")
    try:
        document = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise ModelError(f"{path}: not valid YAML: {error}") from error
    if not isinstance(document, dict):
        raise ModelError(f"{path}: expected a mapping at the top level, got {type(document).__name__}")
    if document.get("format") != FORMAT or document.get("version") != VERSION:
        raise ModelError(
            f"{path}: expected format {FORMAT!r} version {VERSION}, got {document.get('format')!r} "
            f"version {document.get('version')!r}"
        )
    mesh_file = path.parent / _required(document, "mesh", "model")
    parts = tuple(_part(entry, i) for i, entry in enumerate(_list(document, "parts")))
    try:
        if mesh_file.suffix.lower() == ".inp":
            nodes, cells, elsets = read_inp_mesh(mesh_file)
            by_name = {part.name.upper(): i for i, part in enumerate(parts)}
            unknown = sorted({e for e in elsets if e.upper() not in by_name})
            if unknown:
                raise ModelError(f"{mesh_file}: ELSETs {unknown} are not parts of {path.name} "
                                 f"({[p.name for p in parts]})")
            cell_part = np.array([by_name[e.upper()] for e in elsets], dtype=np.int64)
        else:
            nodes, cells, cell_part = read_mesh(mesh_file)
    except MeshError as error:
        raise ModelError(str(error)) from error
    material_doc = document.get("material", {})
    material = Material(**{f.name: float(material_doc[f.name]) for f in fields(Material) if f.name in material_doc})
    model = PartModel(
        name=str(document.get("name", path.parent.name)),
        nodes=nodes,
        cells=cells,
        cell_part=cell_part,
        parts=parts,
        material=material,
        boundaries=tuple(_boundary(entry) for entry in _list(document, "boundaries")),
        parameters=tuple(_parameter(entry) for entry in document.get("parameters") or []),
        skin_part=str(_required(document, "skin_part", "model")),
        gravity=np.asarray(document.get("gravity", GRAVITY), dtype=float),
        parameter_states=str(document.get("parameter_states", "effective")),
    )
    validate_model(model)
    return model, document


def _required(entry: dict, key: str, what: str) -> Any:
    if not isinstance(entry, dict) or key not in entry or entry[key] is None:
        raise ModelError(f"{what} entry {entry!r}: missing {key!r}")
    return entry[key]


def _list(document: dict, key: str) -> list:
    value = document.get(key)
    if not isinstance(value, list) or not value:
        raise ModelError(f"model.yaml: {key!r} must be a non-empty list, got {value!r}")
    return value


def _part(entry: dict, index: int) -> Part:
    name = str(_required(entry, "name", f"part #{index}"))
    if "thickness" not in entry or entry["thickness"] is None:
        raise ModelError(f"part {name!r}: missing thickness (mm)")
    try:
        thickness = float(entry["thickness"])
    except (TypeError, ValueError) as error:
        raise ModelError(f"part {name!r}: thickness must be a number of mm, got {entry['thickness']!r}") from error
    return Part(name=name, thickness=thickness)


def _floats(value: Any, n: int, what: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError) as error:
        raise ModelError(f"{what}: expected {n} numbers, got {value!r}") from error
    if len(out) != n:
        raise ModelError(f"{what}: expected {n} numbers, got {len(out)}")
    return out


def _boundary(entry: dict) -> Boundary:
    name = str(_required(entry, "name", "boundary"))
    kind = str(_required(entry, "kind", f"boundary {name!r}"))
    patch_doc = _required(entry, "patch", f"boundary {name!r}")
    known = {"center", "radius", "nodes", "parts", "exclude_parts"}
    if not isinstance(patch_doc, dict) or set(patch_doc) - known:
        raise ModelError(f"boundary {name!r}: patch keys must be among {sorted(known)}, got {patch_doc!r}")
    center = patch_doc.get("center")
    patch = Patch(
        center=_floats(center, 3, f"boundary {name!r} patch center") if center is not None else None,
        radius=float(patch_doc.get("radius", 0.0)),
        nodes=tuple(int(n) for n in patch_doc.get("nodes", [])),
        parts=tuple(str(p) for p in patch_doc.get("parts", [])),
        exclude_parts=tuple(str(p) for p in patch_doc.get("exclude_parts", [])),
    )
    axis = _floats(entry.get("axis", [0.0, 0.0, 1.0]), 3, f"boundary {name!r} axis")
    return Boundary(
        name=name,
        kind=kind,
        patch=patch,
        dofs=tuple(str(d).lower() for d in entry.get("dofs", [])),
        axis=axis,
        force=float(entry.get("force", 0.0)),
        stiffness=float(entry.get("stiffness", 0.0)),
        preload=float(entry.get("preload", 0.0)),
    )


def _parameter(entry: dict) -> Parameter:
    label = str(_required(entry, "label", "parameter"))
    lower, upper = _floats(_required(entry, "range", f"parameter {label!r}"), 2, f"parameter {label!r} range")
    return Parameter(
        label=label,
        boundary=str(_required(entry, "boundary", f"parameter {label!r}")),
        direction=str(_required(entry, "direction", f"parameter {label!r}")).lower(),
        lower=lower,
        upper=upper,
    )
