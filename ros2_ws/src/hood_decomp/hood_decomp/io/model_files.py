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
    tolerance_zones:               # optional: acceptance criteria on the skin (core.method.tolerance); they are not
                                   # the model (model_id and bases_id ignore them)
      - name: front_edge
        box: {min: [1100.0, -700.0, -50.0], max: [1250.0, 700.0, 300.0]}   # mm, part frame, bounds included
        sphere: {center: [1175.0, 0.0, 150.0], radius: 400.0}             # mm; with a box: nodes inside both
        lower_mm: -0.3             # allowed signed normal displacement, mm (lower < upper)
        upper_mm: 0.3
        min_coverage: 0.5          # optional (default 0.5): seen fraction of the zone needed for a verdict of OK

Every problem is a ModelError naming the entry, what was expected and what was found: unknown keys (with the nearest
known key: "did you mean 'force'?"), wrong types, non-finite numbers, names with control characters; YAML aliases are
refused (an alias bomb cannot expand) and messages never print more than 80 characters of an entry.
"""

from __future__ import annotations

import difflib
import json
import math
from dataclasses import fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from hood_decomp.core.fe.model import (
    GRAVITY,
    Boundary,
    Material,
    Parameter,
    Part,
    PartModel,
    Patch,
    skin_surface,
    validate_model,
)
from hood_decomp.core.method.tolerance import zone_nodes
from hood_decomp.core.types import ToleranceZone
from hood_decomp.errors import MeshError, ModelError
from hood_decomp.io.mesh import read_inp_mesh, read_mesh, write_mesh
from hood_decomp.io.small_files import read_small_file

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


def model_files(path: str | Path) -> list[Path]:
    """The files a model reads: its model.yaml and, when the document names one, its mesh file (so a command can
    check that no output overwrites them). Never raises for a bad model: loading it reports that."""
    path = model_path(path)
    try:
        mesh = _document(path).get("mesh")
    except ModelError:
        return [path]
    try:
        return [path, _mesh_file(path, mesh)] if isinstance(mesh, str) and mesh else [path]
    except ModelError:
        return [path]


def load_model(path: str | Path) -> PartModel:
    """Read and validate a model (directory or model.yaml), its tolerance zones included. Raises ModelError."""
    return _read(path)[0]


def load_model_with_zones(path: str | Path) -> tuple[PartModel, tuple[ToleranceZone, ...]]:
    """The model (as :func:`load_model`) and its ``tolerance_zones`` resolved to nodes of its visible skin (the node
    order of ``skin_surface(model)``, which is the bases'). Raises ModelError."""
    model, _, zones = _read(path)
    return model, zones


def load_model_with_candidates(path: str | Path) -> tuple[PartModel, tuple[Candidate, ...]]:
    """The model (as :func:`load_model`) and the user candidate effects of its optional ``candidates:`` list, from one
    read of model.yaml. Raises ModelError."""
    from hood_decomp.core.loop.candidates import candidates_from_document  # the loop loads only for who asks

    model, document, _ = _read(path)
    return model, candidates_from_document(document.get("candidates"))


# --- the schema: every key a model.yaml may hold (unknown keys are refused with the nearest known one) ------------
TOP_KEYS = ("format", "version", "name", "mesh", "skin_part", "material", "gravity", "parts", "boundaries",
            "parameters", "candidates", "parameter_states", "tolerance_zones")
MATERIAL_KEYS = tuple(f.name for f in fields(Material))
PART_KEYS = ("name", "thickness")
BOUNDARY_KEYS = ("name", "kind", "dofs", "patch", "axis", "stiffness", "preload", "force")
PATCH_KEYS = ("center", "radius", "nodes", "parts", "exclude_parts")
PARAMETER_KEYS = ("label", "boundary", "direction", "range")
ZONE_KEYS = ("name", "box", "sphere", "lower_mm", "upper_mm", "min_coverage")
BOX_KEYS = ("min", "max")
SPHERE_KEYS = ("center", "radius")
#: a zone judged on less than this seen fraction of its nodes is not OK (model.yaml ``min_coverage`` overrides it)
ZONE_MIN_COVERAGE = 0.5
#: largest model.yaml read (a patch may list many nodes; a hood's file is ~3 kB)
MAX_BYTES = 16 * 2**20
#: a name is printable text without control characters, at most this long
MAX_NAME = 200


class _NoAliasLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses aliases: a few hundred bytes of nested aliases (a "billion laughs" file) expand
    to gigabytes once anything walks the document; model.yaml never needs them."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            mark = self.peek_event().start_mark
            raise yaml.YAMLError(f"line {mark.line + 1}: YAML aliases (*name) are not accepted in model.yaml")
        return super().compose_node(parent, index)


def _show(value: object) -> str:
    """A short repr for messages: never the whole of a large entry."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _document(path: Path) -> dict:
    """The parsed model.yaml: a mapping of the known format and version. ModelError otherwise."""
    if not path.exists():  # anything else that is not a regular file is named by read_small_file
        raise ModelError(f"model file {path} does not exist (expected a model directory or its model.yaml)")
    try:
        text = read_small_file(path, MAX_BYTES, ModelError, "model file").decode("utf-8")
        document = yaml.load(text, Loader=_NoAliasLoader)  # a SafeLoader: no Python objects either
    except OSError as error:
        raise ModelError(f"{path}: cannot be read: {error.strerror}") from error
    except UnicodeDecodeError as error:
        raise ModelError(f"{path}: not UTF-8 text (byte {error.start})") from error
    except yaml.YAMLError as error:
        raise ModelError(f"{path}: not valid YAML: {' '.join(str(error).split())[:200]}") from error
    if not isinstance(document, dict):
        raise ModelError(f"{path}: expected a mapping at the top level, got {type(document).__name__}")
    if document.get("format") != FORMAT or document.get("version") != VERSION:
        raise ModelError(f"{path}: expected format {FORMAT!r} version {VERSION}, got {_show(document.get('format'))} "
                         f"version {_show(document.get('version'))}")
    _keys(document, TOP_KEYS, "model.yaml")
    return document


def _read(path: str | Path) -> tuple[PartModel, dict, tuple[ToleranceZone, ...]]:
    """The validated model, the parsed model.yaml document and the tolerance zones on the model's skin."""
    path = model_path(path)
    document = _document(path)
    mesh_file = _mesh_file(path, _name(_required(document, "mesh", "model"), "model mesh"))
    parts = tuple(_part(entry, i) for i, entry in enumerate(_list(document, "parts")))
    try:
        if mesh_file.suffix.lower() == ".inp":
            nodes, cells, elsets = read_inp_mesh(mesh_file)
            by_name = {part.name.upper(): i for i, part in enumerate(parts)}
            unknown = sorted({e for e in elsets if e.upper() not in by_name})
            if unknown:
                raise ModelError(f"{mesh_file}: ELSETs {_show(unknown)} are not parts of {path.name} "
                                 f"({_show([p.name for p in parts])})")
            cell_part = np.array([by_name[e.upper()] for e in elsets], dtype=np.int64)
        else:
            nodes, cells, cell_part = read_mesh(mesh_file)
    except MeshError as error:
        raise ModelError(str(error)) from error
    material_doc = document.get("material") or {}
    _keys(material_doc, MATERIAL_KEYS, "material")
    material = Material(**{key: _number(material_doc, key, "material") for key in MATERIAL_KEYS
                           if key in material_doc})
    gravity = _numbers(document["gravity"], 3, "gravity") if document.get("gravity") is not None else GRAVITY
    model = PartModel(
        name=_name(document.get("name", path.parent.name), "model name"),
        nodes=nodes,
        cells=cells,
        cell_part=cell_part,
        parts=parts,
        material=material,
        boundaries=tuple(_boundary(entry, i) for i, entry in enumerate(_list(document, "boundaries"))),
        parameters=tuple(_parameter(entry, i) for i, entry in enumerate(_optional_list(document, "parameters"))),
        skin_part=_name(_required(document, "skin_part", "model"), "skin_part"),
        gravity=np.asarray(gravity, dtype=float),
        parameter_states=_name(document.get("parameter_states", "effective"), "parameter_states"),
    )
    validate_model(model)
    points = skin_surface(model).points
    zones = tuple(_zone(entry, i, points) for i, entry in enumerate(_optional_list(document, "tolerance_zones")))
    names = [zone.name for zone in zones]
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise ModelError(f"tolerance_zones: zone names must be unique, {_show(twice)} repeated")
    return model, document, zones


def _mesh_file(path: Path, name: str) -> Path:
    """The mesh named in model.yaml: a file in the model's directory tree (a model.yaml from elsewhere must not make
    the program read /etc/passwd or another user's file as a mesh)."""
    directory = path.parent.resolve()
    mesh = (path.parent / name).resolve()
    if Path(name).is_absolute() or not mesh.is_relative_to(directory):
        raise ModelError(f"{path}: mesh {_show(name)} must be a file in the model's directory ({directory})")
    return path.parent / name


def _keys(entry: object, known: tuple[str, ...], what: str) -> None:
    """Refuse a non-mapping or an unknown key, naming the nearest known key ("did you mean 'force'?")."""
    if not isinstance(entry, dict):
        raise ModelError(f"{what}: expected a mapping with keys among {list(known)}, got {type(entry).__name__}")
    for key in entry:
        if key not in known:
            nearest = difflib.get_close_matches(str(key), known, n=1, cutoff=0.5)
            hint = f"did you mean {nearest[0]!r}?" if nearest else f"known keys: {list(known)}"
            raise ModelError(f"{what}: unknown key {_show(key)}; {hint}")


def _required(entry: dict, key: str, what: str) -> Any:
    if not isinstance(entry, dict) or key not in entry or entry[key] is None:
        raise ModelError(f"{what}: missing {key!r}")
    return entry[key]


def _name(value: object, what: str) -> str:
    """A name: text of 1..MAX_NAME printable characters (numbers are accepted as their text)."""
    if isinstance(value, bool) or not isinstance(value, str | int):
        raise ModelError(f"{what} must be text, got {type(value).__name__} {_show(value)}")
    text = str(value)
    if not text or len(text) > MAX_NAME or not text.isprintable():
        raise ModelError(f"{what} must be 1..{MAX_NAME} printable characters (no newline or control character), "
                         f"got {_show(text)}")
    return text


def _number(entry: dict, key: str, what: str, default: float | None = None) -> float:
    """entry[key] as a finite number (ModelError naming ``what`` and the key otherwise); ``default`` when absent."""
    if key not in entry and default is not None:
        return default
    return _finite(entry.get(key), f"{what} {key}")


def _finite(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ModelError(f"{what} must be a number, got {type(value).__name__} {_show(value)}")
    if not math.isfinite(value):
        raise ModelError(f"{what} must be a finite number, got {value}")
    return float(value)


def _numbers(value: object, n: int, what: str) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != n:
        raise ModelError(f"{what}: expected a list of {n} numbers, got {_show(value)}")
    return tuple(_finite(v, what) for v in value)


def _names(value: object, what: str) -> tuple[str, ...]:
    if not isinstance(value, list):
        raise ModelError(f"{what}: expected a list of names, got {_show(value)}")
    return tuple(_name(v, what) for v in value)


def _list(document: dict, key: str) -> list:
    value = document.get(key)
    if not isinstance(value, list) or not value:
        raise ModelError(f"model.yaml: {key!r} must be a non-empty list, got {_show(value)}")
    return value


def _optional_list(document: dict, key: str) -> list:
    value = document.get(key)
    if value is not None and not isinstance(value, list):
        raise ModelError(f"model.yaml: {key!r} must be a list, got {_show(value)}")
    return value or []


def _part(entry: dict, index: int) -> Part:
    _keys(entry, PART_KEYS, f"part #{index}")
    name = _name(_required(entry, "name", f"part #{index}"), f"part #{index} name")
    if entry.get("thickness") is None:
        raise ModelError(f"part {name!r}: missing thickness (mm)")
    return Part(name=name, thickness=_number(entry, "thickness", f"part {name!r}"))


def _boundary(entry: dict, index: int) -> Boundary:
    _keys(entry, BOUNDARY_KEYS, f"boundary #{index}")
    name = _name(_required(entry, "name", f"boundary #{index}"), f"boundary #{index} name")
    what = f"boundary {name!r}"
    kind = _name(_required(entry, "kind", what), f"{what} kind")
    patch_doc = _required(entry, "patch", what)
    _keys(patch_doc, PATCH_KEYS, f"{what} patch")
    nodes = patch_doc.get("nodes", [])
    if not isinstance(nodes, list) or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0
                                              for n in nodes):
        raise ModelError(f"{what} patch nodes: expected a list of node indices (whole numbers >= 0), got "
                         f"{_show(nodes)}")
    center = patch_doc.get("center")
    patch = Patch(
        center=_numbers(center, 3, f"{what} patch center") if center is not None else None,
        radius=_number(patch_doc, "radius", f"{what} patch", 0.0),
        nodes=tuple(nodes),
        parts=_names(patch_doc.get("parts", []), f"{what} patch parts"),
        exclude_parts=_names(patch_doc.get("exclude_parts", []), f"{what} patch exclude_parts"),
    )
    return Boundary(
        name=name,
        kind=kind,
        patch=patch,
        dofs=tuple(d.lower() for d in _names(entry.get("dofs", []), f"{what} dofs")),
        axis=_numbers(entry.get("axis", [0.0, 0.0, 1.0]), 3, f"{what} axis"),
        force=_number(entry, "force", what, 0.0),
        stiffness=_number(entry, "stiffness", what, 0.0),
        preload=_number(entry, "preload", what, 0.0),
    )


def _parameter(entry: dict, index: int) -> Parameter:
    _keys(entry, PARAMETER_KEYS, f"parameter #{index}")
    label = _name(_required(entry, "label", f"parameter #{index}"), f"parameter #{index} label")
    lower, upper = _numbers(_required(entry, "range", f"parameter {label!r}"), 2, f"parameter {label!r} range")
    return Parameter(
        label=label,
        boundary=_name(_required(entry, "boundary", f"parameter {label!r}"), f"parameter {label!r} boundary"),
        direction=_name(_required(entry, "direction", f"parameter {label!r}"),
                        f"parameter {label!r} direction").lower(),
        lower=lower,
        upper=upper,
    )


def _zone(entry: dict, index: int, points: np.ndarray) -> ToleranceZone:
    """One ``tolerance_zones`` entry resolved to the skin nodes ``points`` (N, 3) mm; a zone that holds no skin node
    is refused by name (a typo in a coordinate must not make a zone that is always OK)."""
    _keys(entry, ZONE_KEYS, f"tolerance zone #{index}")
    name = _name(_required(entry, "name", f"tolerance zone #{index}"), f"tolerance zone #{index} name")
    what = f"tolerance zone {name!r}"
    region: dict[str, Any] = {}
    box = sphere = None
    if entry.get("box") is not None:
        _keys(entry["box"], BOX_KEYS, f"{what} box")
        low = _numbers(_required(entry["box"], "min", f"{what} box"), 3, f"{what} box min")
        high = _numbers(_required(entry["box"], "max", f"{what} box"), 3, f"{what} box max")
        if not all(a < b for a, b in zip(low, high, strict=True)):
            raise ModelError(f"{what} box: expected min < max on every axis, got min {list(low)} max {list(high)}")
        box, region["box"] = (low, high), {"min": list(low), "max": list(high)}
    if entry.get("sphere") is not None:
        _keys(entry["sphere"], SPHERE_KEYS, f"{what} sphere")
        centre = _numbers(_required(entry["sphere"], "center", f"{what} sphere"), 3, f"{what} sphere center")
        radius = _finite(_required(entry["sphere"], "radius", f"{what} sphere"), f"{what} sphere radius")
        if radius <= 0:
            raise ModelError(f"{what} sphere radius: expected > 0 mm, got {radius}")
        sphere, region["sphere"] = (centre, radius), {"center": list(centre), "radius": radius}
    if box is None and sphere is None:
        raise ModelError(f"{what}: expected a region, 'box' and/or 'sphere' (part frame, mm)")
    lower = _finite(_required(entry, "lower_mm", what), f"{what} lower_mm")
    upper = _finite(_required(entry, "upper_mm", what), f"{what} upper_mm")
    if not lower < upper:
        raise ModelError(f"{what}: expected lower_mm < upper_mm, got {lower} and {upper}")
    coverage = _number(entry, "min_coverage", what, ZONE_MIN_COVERAGE)
    if not 0.0 <= coverage <= 1.0:
        raise ModelError(f"{what} min_coverage: expected 0..1, got {coverage}")
    nodes = zone_nodes(points, box=box, sphere=sphere)
    if not nodes.size:
        low, high = (np.round(bound, 1).tolist() for bound in (points.min(axis=0), points.max(axis=0)))
        raise ModelError(f"{what}: its region holds no node of the visible skin ({len(points)} nodes within "
                         f"{low} .. {high} mm)")
    return ToleranceZone(name=name, nodes=nodes, lower_mm=lower, upper_mm=upper, min_coverage=coverage,
                         region=json.dumps(region))
