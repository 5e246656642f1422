"""The bad-input matrix of issue 18: every case a generator here (no stored fixture), run through the real command
line entry point; each must end in exactly one named error line and exit status 2, with no traceback, no output
file written and no input modified. The per-category counts are printed at the end of the test session
(tests/cli/conftest.py).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import h5py
import meshio
import numpy as np
import pytest
import yaml

from hood_decomp.cli import main
from tests.bad_inputs import BOMB, H5_MUTATIONS, SECRET, Workspace, mutated_copy

#: category -> case name -> passed (filled as the cases run; printed by tests/cli/conftest.py)
MATRIX: dict[str, dict[str, bool]] = {}

Build = Callable[[Workspace, Path], list[str]]


@dataclasses.dataclass(frozen=True)
class Case:
    category: str
    name: str
    build: Build  # writes the bad input into the case's directory and returns the argv
    fragment: str = ""  # text the error line must contain (case-insensitive)

    @property
    def id(self) -> str:
        return f"{self.category}: {self.name}"


CASES: list[Case] = []


def add(category: str, name: str, build: Build, fragment: str = "") -> None:
    CASES.append(Case(category, name, build, fragment))


# --- inputs of every verb, with one of them replaced ------------------------------------------------------------
def _verb_with(kind: str, bad: Path, ws: Workspace, tmp: Path) -> list[str]:
    """A command that reads input ``kind`` from ``bad`` and every other input from the valid workspace."""
    model, out = str(ws.model), str(tmp / "out")
    return {
        "bases (estimate)": ["estimate", "--bases", str(bad), "--field", str(ws.field)],
        "bases (decompose)": ["decompose", "--bases", str(bad), "--field", str(ws.field)],
        "bases (close-loop)": ["close-loop", "--model", model, "--bases", str(bad), "--field", str(ws.field),
                               "--out", out],
        "bases (launch)": ["launch", "--bases", str(bad)],
        "field": ["estimate", "--bases", str(ws.bases), "--field", str(bad)],
        "field (close-loop)": ["close-loop", "--model", model, "--bases", str(ws.bases), "--field", str(bad),
                               "--out", out],
        "scan": ["estimate", "--bases", str(ws.bases), "--scan", str(bad)],
        "scan (decompose)": ["decompose", "--bases", str(ws.bases), "--scan", str(bad)],
        "ensemble": ["bases", "--ensemble", str(bad), "--out", str(tmp / "b.h5")],
        "ensemble (export)": ["ensemble", "--export", "training:0", "--out", str(bad), "--field", str(tmp / "f.vtu")],
        "ensemble (close-loop)": ["close-loop", "--model", model, "--bases", str(ws.bases), "--field", str(ws.field),
                                  "--ensemble", str(bad), "--out", out],
        "model (simulate)": ["simulate", "--model", str(bad), "--out", str(tmp / "f.vtu")],
        "model (scan)": ["scan", "--model", str(bad), "--out", str(tmp / "s.ply")],
        "model (ensemble)": ["ensemble", "--model", str(bad), "--out", str(tmp / "e.h5")],
        "model (bases)": ["bases", "--ensemble", str(ws.ensemble), "--model", str(bad), "--out", str(tmp / "b.h5")],
        "truth": ["close-loop", "--model", model, "--bases", str(ws.bases), "--field", str(ws.field), "--truth",
                  str(bad), "--out", out],
    }[kind]


FILE_KINDS = {  # input kind -> suffix of its file
    "bases (estimate)": ".h5", "bases (decompose)": ".h5", "bases (close-loop)": ".h5", "bases (launch)": ".h5",
    "field": ".vtu", "field (close-loop)": ".vtu", "scan": ".ply", "scan (decompose)": ".ply", "ensemble": ".h5",
    "ensemble (export)": ".h5", "ensemble (close-loop)": ".h5", "model (simulate)": ".yaml", "model (scan)": ".yaml",
    "model (ensemble)": ".yaml", "model (bases)": ".yaml", "truth": ".json",
}  # fmt: skip
VALID = {".h5": "bases", ".vtu": "field", ".ply": "scan", ".json": None, ".yaml": None}


def _valid_file(kind: str, ws: Workspace) -> Path:
    if kind.startswith("model"):
        return ws.model / "model.yaml"
    if kind.startswith("ensemble"):
        return ws.ensemble
    if kind == "truth":
        return ws.decoys / "secret.txt"
    return getattr(ws, VALID[FILE_KINDS[kind]])


def _broken(kind: str, how: str) -> Build:
    def build(ws: Workspace, tmp: Path) -> list[str]:
        bad = tmp / f"bad{FILE_KINDS[kind]}"
        if how == "missing":
            pass
        elif how == "empty":
            bad.write_bytes(b"")
        elif how == "a directory":
            bad.mkdir()
        elif how == "garbage":
            bad.write_bytes(np.random.default_rng(len(kind)).bytes(3000))
        elif how == "truncated":
            data = _valid_file(kind, ws).read_bytes()
            bad.write_bytes(data[: len(data) // 2])
        return _verb_with(kind, bad, ws, tmp)

    return build


for _kind in FILE_KINDS:
    for _how in ("missing", "empty", "a directory", "garbage", "truncated"):
        if _kind == "truth" and _how == "truncated":
            continue
        add(f"file {_how}", _kind, _broken(_kind, _how))
add("file wrong format", "a scan given as a field", lambda ws, tmp: _verb_with("field", ws.scan, ws, tmp))
add("file wrong format", "a field given as bases", lambda ws, tmp: _verb_with("bases (estimate)", ws.field, ws, tmp))
add("file wrong format", "bases given as an ensemble", lambda ws, tmp: _verb_with("ensemble", ws.bases, ws, tmp),
    "expected schema")
add("file wrong format", "an ensemble given as bases",
    lambda ws, tmp: _verb_with("bases (estimate)", ws.ensemble, ws, tmp), "not a hood_decomp bases file")
add("file wrong format", "a field given as a scan", lambda ws, tmp: _verb_with("scan", ws.field, ws, tmp),
    "not a PLY file")


# --- HDF5: crafted and broken bases files and ensemble stores ------------------------------------------------------
def _h5(kind: str, mutation: str, target: str) -> Build:
    def build(ws: Workspace, tmp: Path) -> list[str]:
        edit, _ = H5_MUTATIONS[mutation]
        source = ws.ensemble if kind.startswith("ensemble") else ws.bases
        bad = mutated_copy(source, tmp / "bad.h5", lambda h5: edit(h5, target, ws))
        return _verb_with(kind, bad, ws, tmp)

    return build


#: what the error names for a mutation of a per-node numeric dataset: the dimension and where it was fixed
_NUMERIC = {"wrong width": "but skin/points has N = 400", "strings for numbers": "holds str, expected float"}
for _mutation, (_, _fragment) in H5_MUTATIONS.items():
    add("hdf5 crafted bases", f"{_mutation} in pca/components", _h5("bases (estimate)", _mutation, "pca/components"),
        _NUMERIC.get(_mutation, _fragment))
    add("hdf5 crafted ensemble", f"{_mutation} in training/normal_displacement",
        _h5("ensemble", _mutation, "training/normal_displacement"),
        _NUMERIC.get(_mutation, _fragment))
for _mutation in ("external storage (text)", "external link", "missing dataset", "object references",
                  "variable-length numbers"):
    add("hdf5 crafted bases", f"{_mutation} in hierarchical/effect_names",
        _h5("bases (decompose)", _mutation, "hierarchical/effect_names"))
    add("hdf5 crafted ensemble", f"{_mutation} in names", _h5("ensemble", _mutation, "names"))
for _mutation, _target in (("NaN value", "reduced_model/R"), ("wrong width", "skin/normals"),
                           ("missing dataset", "reduced_model/G"), ("inf value", "hierarchical/fields"),
                           ("wrong width", "hierarchical/effect_mask"), ("shape claim of TiB", "reduced_model/R_3d")):
    add("hdf5 crafted bases", f"{_mutation} in {_target}", _h5("bases (estimate)", _mutation, _target))


def _h5_attr(kind: str, edit: Callable[[h5py.File], None]) -> Build:
    def build(ws: Workspace, tmp: Path) -> list[str]:
        bad = mutated_copy(ws.ensemble if kind.startswith("ensemble") else ws.bases, tmp / "bad.h5", edit)
        return _verb_with(kind, bad, ws, tmp)

    return build


def _set_attr(name: str, key: str, value: object) -> Callable[[h5py.File], None]:
    def edit(h5: h5py.File) -> None:
        (h5.attrs if name == "/" else h5[name].attrs)[key] = value

    return edit


def _del_attr(name: str, key: str) -> Callable[[h5py.File], None]:
    def edit(h5: h5py.File) -> None:
        del (h5.attrs if name == "/" else h5[name].attrs)[key]

    return edit


for _name, _key, _value, _fragment in (
    ("/", "schema_version", 1, "schema version 1"), ("/", "schema_version", "two", "expected int"),
    ("/", "format", "something else", "not a hood_decomp bases file"),
    ("/", "model_id", "0123456789abcdef", "differs"),
    ("pca", "n_components", "ten", "expected int"), ("pca", "rtol", np.nan, "finite"),
    ("hierarchical", "epsilon", np.inf, "finite"), ("parameters", "n_bilateral", 99, "n_bilateral"),
    ("skin", "model_id", "ffffffffffffffff", "differs"), ("/", "bases_id", "0000000000000000", "bases_id"),
    ("pca", "notes", "[not json", "not JSON"), ("pca", "n_components", 3, "K"),
):
    add("hdf5 attributes", f"bases {_name} {_key} = {_value!r}", _h5_attr("bases (estimate)",
                                                                          _set_attr(_name, _key, _value)), _fragment)
for _name, _key in (("/", "model_id"), ("/", "bases_id"), ("pca", "training_residual_rms"),
                    ("hierarchical", "model_id")):
    add("hdf5 attributes", f"bases {_name} {_key} missing", _h5_attr("bases (estimate)", _del_attr(_name, _key)),
        "missing")


# --- the bases file's physical responses (/physics, written by `bases --model`; the workspace's bases hold them) --
def _physics(edit: Callable[[h5py.File], None], xyz: bool = False) -> Build:
    """`estimate` from the workspace's bases with /physics edited; ``xyz``: a three-component fit, the first reader
    of the 3D parts."""
    def build(ws: Workspace, tmp: Path) -> list[str]:
        argv = _h5_attr("bases (estimate)", edit)(ws, tmp)
        return [*argv, "--components", "xyz"] if xyz else argv

    return build


def _nudge(name: str) -> Callable[[h5py.File], None]:
    def edit(h5: h5py.File) -> None:
        values = h5[name][()]
        values.flat[values.size // 2] += 1e-6
        h5[name][...] = values

    return edit


def _mutate(mutation: str, name: str) -> Callable[[h5py.File], None]:
    return lambda h5: H5_MUTATIONS[mutation][0](h5, name, None)


def _groups(pick: Callable[[list[str]], list[str]]) -> Callable[[h5py.File], None]:
    def edit(h5: h5py.File) -> None:
        groups = [g.decode() if isinstance(g, bytes) else g for g in h5["physics/groups"][()]]
        del h5["physics/groups"]
        h5["physics"].create_dataset("groups", data=np.array(pick(groups), dtype=object),
                                     dtype=h5py.string_dtype())

    return edit


def _unpaired(h5: h5py.File) -> None:
    del h5["reduced_model"]


for _name, _edit, _xyz, _fragment in (
    ("an edited thickness response", _nudge("physics/thickness_R"), False, "physics_id"),
    ("an edited gas-spring response", _nudge("physics/gas_z"), False, "physics_id"),
    ("an edited 3D thickness response (xyz)", _nudge("physics/thickness_G_3d"), True, "physics_3d_id"),
    ("NaN in gas_w", _mutate("NaN value", "physics/gas_w"), False, "non-finite"),
    ("inf in thickness_H", _mutate("inf value", "physics/thickness_H"), False, "non-finite"),
    ("NaN in thickness_R_3d (xyz)", _mutate("NaN value", "physics/thickness_R_3d"), True, "non-finite"),
    ("wrong width of thickness_G", _mutate("wrong width", "physics/thickness_G"), False, "S ="),
    ("a missing sensitivity (thickness_Sa)", _mutate("missing dataset", "physics/thickness_Sa"), False, "missing"),
    ("a missing 3D sensitivity (thickness_w0_3d)", _mutate("missing dataset", "physics/thickness_w0_3d"), False,
     "missing"),
    ("two group names for three stacked sensitivities", _groups(lambda g: g[:-1]), False, "G ="),
    ("a group named twice", _groups(lambda g: [g[0], *g[:-1]]), False, "distinct"),
    ("physics_id rewritten", _set_attr("physics", "physics_id", "0000000000000000"), False, "physics_id"),
    ("physics_id missing", _del_attr("physics", "physics_id"), False, "missing"),
    ("physics_3d_id rewritten (xyz)", _set_attr("physics", "physics_3d_id", "0000000000000000"), True,
     "physics_3d_id"),
    ("the group without the reduced model", _unpaired, False, "needs the reduced model"),
):
    add("hdf5 crafted physics", _name, _physics(_edit, _xyz), _fragment)
for _edit, _name, _fragment in (
    (_set_attr("/", "model_id", "0123456789abcdef"), "model_id rewritten", "content_id"),
    (_set_attr("training", "complete", False), "incomplete training group", "incomplete"),
    (_set_attr("training", "n_members", 10**9), "n_members claims 1e9", "n_members"),
    (_del_attr("/", "content_id"), "content_id missing", "missing"),
    (_set_attr("/", "n_bilateral", -3), "n_bilateral negative", "n_bilateral"),
):
    add("hdf5 attributes", f"ensemble {_name}", _h5_attr("ensemble", _edit), _fragment)


# --- model.yaml: unknown keys, wrong types, non-finite values, hostile text -----------------------------------------
def _model(edit: Callable[[dict], object] | None = None, text: Callable[[str], str] | None = None,
           verb: str = "model (simulate)") -> Build:
    def build(ws: Workspace, tmp: Path) -> list[str]:
        directory = tmp / "model"
        shutil.copytree(ws.model, directory)
        path = directory / "model.yaml"
        if edit is not None:
            document = yaml.safe_load(path.read_text())
            edit(document)
            path.write_text(yaml.safe_dump(document, sort_keys=False))
        if text is not None:
            path.write_text(text(path.read_text()))
        return _verb_with(verb, directory, ws, tmp)

    return build


def _boundary(name: str, **values: object) -> Callable[[dict], None]:
    def edit(document: dict) -> None:
        entry = next(b for b in document["boundaries"] if b["name"] == name)
        entry.update(values)

    return edit


def _patch(name: str, **values: object) -> Callable[[dict], None]:
    def edit(document: dict) -> None:
        next(b for b in document["boundaries"] if b["name"] == name)["patch"].update(values)

    return edit


def _rename_key(name: str, old: str, new: str) -> Callable[[dict], None]:
    def edit(document: dict) -> None:
        entry = next(b for b in document["boundaries"] if b["name"] == name)
        entry[new] = entry.pop(old)

    return edit


MODEL_CASES: list[tuple[str, str, Build, str]] = [
    ("unknown key", "forse: 580 (typo of force)", _model(_rename_key("gas_spring_L", "force", "forse")),
     "did you mean 'force'"),
    ("unknown key", "preloda (typo of preload)", _model(_rename_key("buffer_L", "preload", "preloda")),
     "did you mean 'preload'"),
    ("unknown key", "top-level 'boundary'", _model(lambda d: d.update(boundary=[])), "did you mean 'boundaries'"),
    ("unknown key", "material 'young'", _model(lambda d: d["material"].update(young=1.0)), "unknown key"),
    ("unknown key", "part 'thicknes'", _model(lambda d: d["parts"][0].update(thicknes=1.0)),
     "did you mean 'thickness'"),
    ("unknown key", "patch 'radious'", _model(_patch("hinge_L", radious=3.0)), "did you mean 'radius'"),
    ("unknown key", "parameter 'rnage'", _model(lambda d: d["parameters"][0].update(rnage=[0, 1])),
     "did you mean 'range'"),
    ("wrong type", "material: [1, 2, 3]", _model(lambda d: d.update(material=[1, 2, 3])), "material"),
    ("wrong type", "radius: big", _model(_patch("hinge_L", radius="big")), "must be a number"),
    ("wrong type", "nodes: [a, b]", _model(_patch("hinge_L", nodes=["a", "b"])), "node indices"),
    ("wrong type", "thickness: thin", _model(lambda d: d["parts"][0].update(thickness="thin")), "must be a number"),
    ("wrong type", "axis: [1, 2]", _model(_boundary("buffer_L", axis=[1, 2])), "3 numbers"),
    ("wrong type", "range: [1]", _model(lambda d: d["parameters"][0].update(range=[1])), "2 numbers"),
    ("wrong type", "gravity: down", _model(lambda d: d.update(gravity="down")), "gravity"),
    ("wrong type", "parts: {}", _model(lambda d: d.update(parts={})), "non-empty list"),
    ("wrong type", "boundaries: []", _model(lambda d: d.update(boundaries=[])), "non-empty list"),
    ("wrong type", "stiffness: true", _model(_boundary("buffer_L", stiffness=True)), "must be a number"),
    ("wrong type", "dofs: x", _model(_boundary("hinge_L", dofs="x")), "list of names"),
    ("wrong type", "name: [list]", _model(lambda d: d["parts"][0].update(name=["a"])), "must be text"),
    ("wrong type", "version: 2", _model(lambda d: d.update(version=2)), "version"),
    ("wrong type", "top level is a list", _model(text=lambda t: "- 1\n- 2\n"), "mapping"),
    ("wrong type", "binary file", _model(text=lambda t: "\x00\x01\x02\xff\xfe" * 40), ""),
    ("wrong type", "not YAML", _model(text=lambda t: "a: [unclosed\n  b: {"), "not valid YAML"),
    ("wrong type", "unknown kind", _model(_boundary("hinge_L", kind="glue")), "kind"),
    ("non-finite", "preload: .nan", _model(_boundary("buffer_L", preload=float("nan"))), "finite"),
    ("non-finite", "force: .inf", _model(text=lambda t: t.replace("force: 580.0", "force: .inf", 1)), "finite"),
    ("non-finite", "thickness: -.inf", _model(lambda d: d["parts"][0].update(thickness=float("-inf"))), "finite"),
    ("non-finite", "E: .nan", _model(lambda d: d["material"].update(E=float("nan"))), "finite"),
    ("non-finite", "range: [.nan, 1]", _model(lambda d: d["parameters"][0].update(range=[float("nan"), 1.0])),
     "finite"),
    ("non-finite", "center with inf", _model(_patch("hinge_L", center=[0.0, float("inf"), 0.0])), "finite"),
    ("non-finite", "gravity with nan", _model(lambda d: d.update(gravity=[0.0, 0.0, float("nan")])), "finite"),
    ("hostile text", "YAML alias bomb", _model(text=lambda t: BOMB), "aliases"),
    ("hostile text", "mesh: /etc/passwd", _model(lambda d: d.update(mesh="/etc/passwd")), "model's directory"),
    ("hostile text", "mesh: ../../secret", _model(lambda d: d.update(mesh="../decoys/secret.txt")),
     "model's directory"),
    ("hostile text", "part name with newline and *INCLUDE", _model(
        lambda d: d["parts"][0].update(name="skin\n*INCLUDE, INPUT=/etc/passwd")), "control character"),
    ("hostile text", "model name with newline and *INCLUDE", _model(
        lambda d: d.update(name="hood\n*INCLUDE, INPUT=/etc/passwd"), verb="model (ensemble)"), "control character"),
    ("hostile text", "python object tag", _model(text=lambda t: t.replace("name: hood",
                                                                          "name: !!python/object/apply:os.system [id]",
                                                                          1)), "not valid YAML"),
    ("hostile text", "16 MiB model.yaml", _model(text=lambda t: t + "#" * (17 * 2**20)), "bytes"),
]
for _category, _name, _build, _fragment in MODEL_CASES:
    add(f"model.yaml {_category}", _name, _build, _fragment)


def _mesh(edit: Callable[[meshio.Mesh], meshio.Mesh] | None = None, raw: bytes | None = None) -> Build:
    def build(ws: Workspace, tmp: Path) -> list[str]:
        directory = tmp / "model"
        shutil.copytree(ws.model, directory)
        if raw is not None:
            (directory / "mesh.vtu").write_bytes(raw)
        else:
            mesh = edit(meshio.read(directory / "mesh.vtu"))
            mesh.write(directory / "mesh.vtu")
        return _verb_with("model (simulate)", directory, ws, tmp)

    return build


add("mesh file", "not XML", _mesh(raw=b"<VTKFile type='UnstructuredGrid'><broken"), "cannot read")
add("mesh file", "unknown data type (meshio calls sys.exit)", _mesh(
    raw=b'<?xml version="1.0"?><VTKFile type="UnstructuredGrid" version="0.1"><UnstructuredGrid>'
        b'<Piece NumberOfPoints="1" NumberOfCells="0"><Points><DataArray type="Float99" NumberOfComponents="3" '
        b'format="ascii">0 0 0</DataArray></Points></Piece></UnstructuredGrid></VTKFile>'), "cannot read")
add("mesh file", "no part cell data", _mesh(lambda m: meshio.Mesh(m.points, m.cells)), "part")
add("mesh file", "triangles instead of quads", _mesh(
    lambda m: meshio.Mesh(m.points, [("triangle", m.cells[0].data[:, :3])], cell_data={"part": m.cell_data["part"]})),
    "quad")
add("mesh file", "cells index missing nodes", _mesh(
    lambda m: meshio.Mesh(m.points[:10], m.cells, cell_data=m.cell_data)), "")


# --- field files -----------------------------------------------------------------------------------------------
def _field(values: Callable[[np.ndarray], np.ndarray] | None = None, model_id: str | None = None,
           raw: Callable[[str], str] | None = None) -> Build:
    def build(ws: Workspace, tmp: Path) -> list[str]:
        from hood_decomp.core.types import DisplacementField
        from hood_decomp.io.bases import load_bases
        from hood_decomp.io.fields import read_field, write_field

        bad = tmp / "bad.vtu"
        if raw is not None:
            bad.write_text(raw(ws.field.read_text()))
        else:
            skin = load_bases(ws.bases).skin
            field, _ = read_field(ws.field)
            new = values(field.normal_displacement.copy()) if values is not None else field.normal_displacement
            skin = dataclasses.replace(skin, model_id=model_id or skin.model_id)
            write_field(bad, skin, DisplacementField(skin.model_id, new, 1.0, 0.0))
        return _verb_with("field", bad, ws, tmp)

    return build


def _scaled(value: float) -> Callable[[np.ndarray], np.ndarray]:
    return lambda v: np.full_like(v, value)


add("field file", "values of 1e30 mm", _field(_scaled(1e30)), "not a deviation")
add("field file", "values of 150 mm", _field(_scaled(150.0)), "100 mm")
add("field file", "an inf value", _field(lambda v: np.where(np.arange(len(v)) == 3, np.inf, v)), "infinite")
add("field file", "all NaN", _field(_scaled(np.nan)), "")
add("field file", "another model's model_id", _field(model_id="0123456789abcdef"), "model_id")
add("field file", "no normal_displacement", _field(raw=lambda t: t.replace('Name="normal_displacement"',
                                                                            'Name="something_else"')),
    "normal_displacement")
add("field file", "model_id with control codes", _field(raw=lambda t: t.replace(
    'Name="model_id" NumberOfTuples="16" format="ascii">', 'Name="model_id" NumberOfTuples="16" format="ascii">7 ')),
    "")


def _plain_field(ws: Workspace, tmp: Path) -> list[str]:
    """A .vtu without model_id (as plain meshio writes) on points that are not the skin's."""
    mesh = meshio.read(ws.field)
    meshio.write(tmp / "bad.vtu", meshio.Mesh(mesh.points + 1.0, mesh.cells, point_data={
        "normal_displacement": mesh.point_data["normal_displacement"]}))
    return _verb_with("field", tmp / "bad.vtu", ws, tmp)


add("field file", "no model_id, points of another part", _plain_field, "model_id")


# --- scan files (PLY) -------------------------------------------------------------------------------------------
def _ply(text: str, binary: bytes = b"") -> Build:
    def build(ws: Workspace, tmp: Path) -> list[str]:
        bad = tmp / "bad.ply"
        bad.write_bytes(text.encode() + binary)
        return _verb_with("scan", bad, ws, tmp)

    return build


_HEAD = "ply\nformat ascii 1.0\n"
_XYZ = "property float x\nproperty float y\nproperty float z\n"
for _name, _text, _fragment in (
    ("ASCII claiming 1e9 points", _HEAD + "element vertex 1000000000\n" + _XYZ + "end_header\n1 2 3\n", "promises"),
    ("element vertex abc", _HEAD + "element vertex abc\n" + _XYZ + "end_header\n1 2 3\n", "whole number"),
    ("negative vertex count", _HEAD + "element vertex -5\n" + _XYZ + "end_header\n", "whole number"),
    ("unknown property type", _HEAD + "element vertex 1\nproperty quaternion x\nend_header\n1\n", "unknown property"),
    ("text token in the data", _HEAD + "element vertex 2\n" + _XYZ + "end_header\n1 2 3\n4 five 6\n", "'five'"),
    ("face count of 1e9", _HEAD + "element vertex 3\n" + _XYZ + "element face 1000000000\n"
     "property list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "promises"),
    ("no end_header", _HEAD + "element vertex 1\n" + _XYZ + "1 2 3\n", "cannot read"),
    ("no end_header, no data", _HEAD + "element vertex 1\n" + _XYZ, "end_header"),
    ("property before element", _HEAD + _XYZ + "element vertex 1\nend_header\n1 2 3\n", "cannot read"),
    ("list property on vertex", _HEAD + "element vertex 1\nproperty list uchar int x\nend_header\n1 1\n", "list"),
    ("property declared twice", _HEAD + "element vertex 1\n" + _XYZ + "property float x\nend_header\n1 2 3 4\n",
     "twice"),
    ("unknown format", "ply\nformat morse 1.0\nelement vertex 1\n" + _XYZ + "end_header\n", "format"),
    ("face index beyond the vertices", _HEAD + "element vertex 3\n" + _XYZ + "element face 1\n"
     "property list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "index vertices"),
    ("quad faces", _HEAD + "element vertex 4\n" + _XYZ + "element face 1\nproperty list uchar int vertex_indices\n"
     "end_header\n0 0 0\n1 0 0\n0 1 0\n1 1 0\n4 0 1 2 3\n", "triangles"),
    ("no x, y, z", _HEAD + "element vertex 1\nproperty float a\nend_header\n1\n", "x, y, z"),
    ("scanner_pose with text", "ply\nformat ascii 1.0\ncomment hood_decomp scanner_pose 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 "
     "one\nelement vertex 1\n" + _XYZ + "end_header\n1 2 3\n", "scanner_pose"),
    ("marker element without its fields", _HEAD + "element vertex 1\n" + _XYZ + "element marker 1\nproperty int id\n"
     "end_header\n1 2 3\n7\n", "marker"),
    ("header line of 1 MB", "ply\ncomment " + "x" * 2**20 + "\n", "longer than"),
    ("no vertices", _HEAD + "element vertex 0\n" + _XYZ + "end_header\n", ""),
):
    add("scan file (PLY)", _name, _ply(_text), _fragment)
add("scan file (PLY)", "binary claiming 1e9 points", _ply(
    "ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n" + _XYZ + "end_header\n", b"\0" * 24),
    "promises")
add("scan file (PLY)", "binary face count 1e9", _ply(
    "ply\nformat binary_little_endian 1.0\nelement vertex 1\n" + _XYZ + "element face 1000000000\n"
    "property list uchar int vertex_indices\nend_header\n", b"\0" * 12), "promises")
add("scan file (PLY)", "big-endian truncated", _ply(
    "ply\nformat binary_big_endian 1.0\nelement vertex 100\n" + _XYZ + "end_header\n", b"\0" * 100), "promises")


# --- command-line values -----------------------------------------------------------------------------------------
def _argv(*argv: str) -> Build:
    """argv with {model}, {bases}, {field}, {ensemble}, {scan} and {out} filled in from the workspace."""
    def build(ws: Workspace, tmp: Path) -> list[str]:
        names = {"model": ws.model, "bases": ws.bases, "field": ws.field, "ensemble": ws.ensemble, "scan": ws.scan,
                 "out": tmp / "out", "tmp": tmp}
        return [a.format(**{k: str(v) for k, v in names.items()}) for a in argv]

    return build


SIMULATE = ("simulate", "--model", "{model}", "--out", "{out}.vtu")
SCAN = ("scan", "--model", "{model}", "--out", "{out}.ply")
BASES = ("bases", "--ensemble", "{ensemble}", "--out", "{out}.h5")
ESTIMATE = ("estimate", "--bases", "{bases}", "--field", "{field}")
DECOMPOSE = ("decompose", "--bases", "{bases}", "--field", "{field}")
CLOSE = ("close-loop", "--model", "{model}", "--bases", "{bases}", "--field", "{field}", "--out", "{out}")
ENSEMBLE = ("ensemble", "--model", "{model}", "--out", "{out}.h5")
for _value in ("HINGE_X=nan", "HINGE_X=inf", "HINGE_X=-inf", "HINGE_X=abc", "=1", "HINGE_X", "HINGE_X=1e400",
               "HINGE_X=0.1,LOCK_L=NaN", "NOPE=1", "hinge_R.w=1", "HINGE_X=1e30"):
    add("option NaN/inf/garbage", f"simulate --set {_value}", _argv(*SIMULATE, "--set", _value))
add("option NaN/inf/garbage", "scan --set LOCK_L=inf", _argv(*SCAN, "--set", "LOCK_L=inf"))
for _verb, _option, _values in (
    (SCAN, "--noise-mm", ("nan", "inf", "-1", "abc", "11")),
    (SCAN, "--points", ("1e11", "0", "abc", "nan", "1.5e3x")),
    (SCAN, "--seed", ("-1", "nan")),
    (SCAN, "--misplacement", ("nan,0,0,0,0,0", "1,2", "inf,0,0,0,0,0")),
    (BASES, "--epsilon", ("nan", "inf", "0", "-1")),
    (BASES, "--components", ("0", "nan", "2.5")),
    (BASES, "--explained-variance", ("2", "nan", "0")),
    (ESTIMATE, "--min-coverage", ("nan", "2", "-0.1")),
    (ESTIMATE, "--marker-std-mm", ("nan", "0", "-0.01", "inf", "11")),
    (ESTIMATE, "--method", ("magic",)),
    (ESTIMATE, "--coarsen", ("0", "two", "1.5", "-2", "400")),
    (DECOMPOSE, "--min-share", ("nan", "1.5")),
    (CLOSE, "--alpha", ("nan", "0", "1")),
    (CLOSE, "--noise-mm", ("nan", "-1", "inf")),
    (CLOSE, "--max-effects", ("0", "nan")),
    (ENSEMBLE, "--validation", ("-1", "1e9", "nan")),
    (ENSEMBLE, "--solver", ("abaqus",)),
    (("replay", "{tmp}/no_bag"), "--timeout", ("nan", "-1")),
):
    for _value in _values:
        add("option NaN/inf/garbage", f"{_verb[0]} {_option} {_value}", _argv(*_verb, _option, _value))
# --- scanner poses (issue 17): POSE.json files and where --scanner-pose stands -------------------------------------
IDENTITY = "[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]"


def _pose(text: str | None, *, directory: bool = False, before: bool = False) -> Build:
    """estimate with --scan and a --scanner-pose holding ``text`` (None: missing; ``directory``: a directory)."""
    def build(ws: Workspace, tmp: Path) -> list[str]:
        pose = tmp / "pose.json"
        if directory:
            pose.mkdir()
        elif text is not None:
            pose.write_text(text)
        scan = ["--scan", str(ws.scan)]
        option = ["--scanner-pose", str(pose)]
        return ["estimate", "--bases", str(ws.bases), *(option + scan if before else scan + option)]

    return build


for _name, _text, _fragment in (
    ("not JSON", "4x4 please", "not a readable JSON"),
    ("a NaN entry", IDENTITY.replace("[1, 0, 0, 0]", "[NaN, 0, 0, 0]"), "NaN is not a JSON number"),
    ("3 x 3", "[[1, 0, 0], [0, 1, 0], [0, 0, 1]]", "4 rows of 4 numbers"),
    ("15 numbers", "[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0]", "4 x 4"),
    ("text entries", IDENTITY.replace("[1, 0, 0, 0]", '["1", 0, 0, 0]'), "4 rows of 4 numbers"),
    ("scaled rotation (metres to mm)", IDENTITY.replace("1, 0, 0, 0]", "1000, 0, 0, 0]"), "not orthonormal"),
    ("a mirror", IDENTITY.replace("[1, 0, 0, 0]", "[-1, 0, 0, 0]"), "mirrors"),
    ("last row not 0 0 0 1", IDENTITY.replace("[0, 0, 0, 1]", "[0, 0, 1, 1]"), "last row"),
    ("an object without a pose", '{"transform": ' + IDENTITY + "}", "'pose' entry"),
    ("huge file", "[" + " " * 100_000 + "]", "bytes"),
):
    add("scanner pose", _name, _pose(_text), _fragment)
add("scanner pose", "missing file", _pose(None), "no such file")
add("scanner pose", "a directory", _pose(None, directory=True), "not a regular file")
add("scanner pose", "--scanner-pose before any --scan", _pose(IDENTITY, before=True), "must follow the --scan")
add("scanner pose", "--scanner-pose after a --field", _argv(*ESTIMATE, "--scanner-pose", "{tmp}/p.json"),
    "must follow the --scan")


def _two_poses(ws: Workspace, tmp: Path) -> list[str]:
    (tmp / "pose.json").write_text(IDENTITY)
    return ["estimate", "--bases", str(ws.bases), "--scan", str(ws.scan), "--scanner-pose", str(tmp / "pose.json"),
            "--scanner-pose", str(tmp / "pose.json")]


def _view_without_pose(ws: Workspace, tmp: Path) -> list[str]:
    (tmp / "pose.json").write_text(IDENTITY)
    second = tmp / "second_view.ply"
    shutil.copyfile(ws.scan, second)
    return ["decompose", "--bases", str(ws.bases), "--scan", str(ws.scan), "--scanner-pose", str(tmp / "pose.json"),
            "--scan", str(second)]


add("scanner pose", "two poses for one scan", _two_poses, "two --scanner-pose")
add("scanner pose", "a view of a multi-view part without a pose", _view_without_pose,
    "second_view.ply: no scanner pose")

add("option NaN/inf/garbage", "unknown verb", _argv("frobnicate"))
add("option NaN/inf/garbage", "unknown option", _argv(*ESTIMATE, "--frobnicate"))
add("option NaN/inf/garbage", "estimate without --field or --scan", _argv("estimate", "--bases", "{bases}"))
add("option NaN/inf/garbage", "close-loop without fields", _argv("close-loop", "--model", "{model}", "--bases",
                                                                  "{bases}", "--out", "{out}"), "at least one")
add("option NaN/inf/garbage", "ensemble --export without --field",
    _argv("ensemble", "--export", "training:0", "--out", "{ensemble}"), "--export")
add("option NaN/inf/garbage", "ensemble --export of member 10**6",
    _argv("ensemble", "--export", "training:1000000", "--out", "{ensemble}", "--field", "{out}.vtu"), "members")
add("option NaN/inf/garbage", "ensemble --export of group 'nope'",
    _argv("ensemble", "--export", "nope:1", "--out", "{ensemble}", "--field", "{out}.vtu"), "")
add("scheduler", "--scheduler garbage", _argv(*ENSEMBLE, "--solver", "calculix", "--scheduler", "garbage"),
    "scheduler")
add("scheduler", "--scheduler unreachable", _argv(*ENSEMBLE, "--solver", "calculix", "--scheduler",
                                                  "tcp://127.0.0.1:9"), "no scheduler answers")
add("scheduler", "--scheduler with the embedded solver", _argv(*ENSEMBLE, "--scheduler", "tcp://127.0.0.1:8786"),
    "only with --solver calculix")
add("scheduler", "--scheduler inproc://", _argv(*ENSEMBLE, "--solver", "calculix", "--scheduler", "inproc://x/1"),
    "scheduler")


def _truth(text: str) -> Build:
    def build(ws: Workspace, tmp: Path) -> list[str]:
        (tmp / "truth.json").write_text(text)
        return _verb_with("truth", tmp / "truth.json", ws, tmp)

    return build


for _name, _text in (("NaN value", '{"LOCK_L": NaN}'), ("Infinity", '{"LOCK_L": Infinity}'),
                     ("text value", '{"LOCK_L": "big"}'), ("list of the wrong length", '[{}, {}, {}]'),
                     ("a number", "3"), ("deep nesting", "[" * 100_000)):
    add("truth JSON", _name, _truth(_text), "--truth")


# --- bags ------------------------------------------------------------------------------------------------------
REPO = Path(__file__).resolve().parents[2]


def _bag(edit: str) -> Build:
    def build(ws: Workspace, tmp: Path) -> list[str]:
        bag = tmp / "bag"
        if edit != "missing":
            shutil.copytree(REPO / "bags" / "clean", bag)
            shutil.copyfile(REPO / "bags" / "clean.json", tmp / "bag.json")
        metadata = bag / "metadata.yaml"
        if edit == "storage file outside the bag":
            metadata.write_text(metadata.read_text().replace("- clean.mcap", f"- ../decoys/{ws.secret.name}")
                                .replace("path: clean.mcap", f"path: {ws.secret}"))
        elif edit == "truncated mcap":
            data = (bag / "clean.mcap").read_bytes()
            (bag / "clean.mcap").write_bytes(data[: len(data) // 3])
        elif edit == "metadata not YAML":
            metadata.write_text("rosbag2_bagfile_information: [unclosed\n")
        return ["replay", str(bag)]

    return build


for _edit, _fragment in (("missing", "not a rosbag2 directory"), ("storage file outside the bag", "outside the bag"),
                         ("truncated mcap", "cannot read bag"), ("metadata not YAML", "metadata")):
    add("bag", _edit, _bag(_edit), _fragment)


# --- outputs -----------------------------------------------------------------------------------------------------
for _name, _argv_out, _fragment in (
    ("bases --out in a missing directory", (*BASES[:-1], "{tmp}/missing/b.h5"), "does not exist"),
    ("bases --out a directory", (*BASES[:-1], "{tmp}"), "is a directory"),
    ("bases --out unwritable", (*BASES[:-1], "/proc/b.h5"), "cannot write"),
    ("bases --out the ensemble", (*BASES[:-1], "{ensemble}"), "overwrite the input"),
    ("simulate --out the mesh", (*SIMULATE[:-1], "{model}/mesh.vtu"), "overwrite the input"),
    ("ensemble --out the model.yaml", (*ENSEMBLE[:-1], "{model}/model.yaml"), "overwrite the input"),
    ("scan --out the model.yaml", (*SCAN[:-1], "{model}/model.yaml"), "overwrite the input"),
    ("export --field the store", ("ensemble", "--export", "training:0", "--out", "{ensemble}", "--field",
                                  "{ensemble}"), "overwrite the input"),
    ("estimate --json the field", (*ESTIMATE, "--json", "{field}"), "overwrite the input"),
    ("decompose --json in a missing directory", (*DECOMPOSE, "--json", "{tmp}/missing/d.json"), "does not exist"),
    ("decompose --plots a file", (*DECOMPOSE, "--plots", "{field}"), "is a file"),
    ("close-loop --out a file", (*CLOSE[:-1], "{field}"), "is a file"),
    ("model --out a file", ("model", "--out", "{field}"), "is a file"),
    ("bases --plots a file", (*BASES, "--plots", "{scan}"), "is a file"),
    ("simulate --out ending in /", (*SIMULATE[:-1], "{tmp}/new/"), "directory"),
    ("scan --out its own sidecar", (*SCAN[:-1], "{tmp}/scan.json"), "sidecar"),
    ("replay --record an existing directory", ("replay", "{tmp}/no_bag", "--record", "{tmp}"), "exists"),
):
    add("output", _name, _argv(*_argv_out), _fragment)


def _link_out(kind: str) -> Build:
    def build(ws: Workspace, tmp: Path) -> list[str]:
        link = tmp / "link.h5"
        (os.link if kind == "hard" else os.symlink)(ws.ensemble, link)
        return ["bases", "--ensemble", str(ws.ensemble), "--out", str(link)]

    return build


add("output", "bases --out a hard link to the ensemble", _link_out("hard"), "overwrite the input")
add("output", "bases --out a symlink to the ensemble", _link_out("soft"), "overwrite the input")


# --- the runner -------------------------------------------------------------------------------------------------
def _hashes(*roots: Path) -> dict[Path, str]:
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for root in roots for p in sorted(root.rglob("*"))
            if p.is_file() and not p.is_symlink()}


def run_cli(argv: list[str]) -> int:
    """The console script's behaviour in this process: ``sys.exit(main())``, argparse's exits included."""
    try:
        return main(argv)
    except SystemExit as stop:
        return stop.code if isinstance(stop.code, int) else 1


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case: Case, tiny_workspace: Workspace, tmp_path: Path, capsys) -> None:
    """Fails if a bad input ends other than in exactly one error line (the last on stderr) naming the problem with
    exit status 2 (a traceback, another status, several error lines, no error), leaks the decoy secret, writes an
    output file, or modifies any input."""
    argv = case.build(tiny_workspace, tmp_path)
    before = _hashes(tiny_workspace.root, tmp_path)
    passed = False
    try:
        status = run_cli(argv)
        out, err = capsys.readouterr()
        lines = err.strip().splitlines()
        errors = [line for line in lines if ": error: " in line]
        assert status == 2, f"exit status {status}; stderr: {err[-2000:]}"
        assert errors and errors == lines[-1:], f"expected one error line, last: {err[-2000:]}"
        assert case.fragment.lower() in errors[0].lower(), f"{case.fragment!r} not in {errors[0]!r}"
        assert len(errors[0]) < 600, f"error line of {len(errors[0])} characters"
        assert "Traceback" not in err and SECRET not in out + err
        assert _hashes(tiny_workspace.root, tmp_path) == before, "an input was modified or an output written"
        passed = True
    finally:
        MATRIX.setdefault(case.category, {})[case.name] = passed


def test_the_matrix_covers_every_category() -> None:
    """Fails if the matrix shrinks below the issue's 163 cases or loses one of its categories."""
    categories = {c.category for c in CASES}
    assert len(CASES) >= 163 and len({c.id for c in CASES}) == len(CASES)
    assert {"file missing", "file empty", "file garbage", "file truncated", "hdf5 crafted bases",
            "hdf5 crafted ensemble", "hdf5 attributes", "model.yaml unknown key", "model.yaml wrong type",
            "model.yaml non-finite", "model.yaml hostile text", "scan file (PLY)", "field file", "mesh file",
            "option NaN/inf/garbage", "scheduler", "output", "truth JSON", "bag", "scanner pose"} <= categories


SUBPROCESS_CASES = ["option NaN/inf/garbage: simulate --set HINGE_X=nan",
                    "hdf5 crafted bases: external storage (text) in hierarchical/effect_names",
                    "mesh file: unknown data type (meshio calls sys.exit)"]


@pytest.mark.parametrize("case_id", SUBPROCESS_CASES)
def test_bad_input_through_the_console_script(case_id: str, tiny_workspace: Workspace, tmp_path: Path) -> None:
    """Fails if, in a process of its own (what a user runs), a bad input does not exit with status 2 and exactly one
    stderr line, or prints anything on stdout (meshio's sys.exit, argparse and a leaked print included)."""
    case = next(c for c in CASES if c.id == case_id)
    argv = case.build(tiny_workspace, tmp_path)
    result = subprocess.run([sys.executable, "-m", "hood_decomp.cli", *argv], capture_output=True, text=True,
                            timeout=120, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and ": error: " in lines[0], result.stderr[-2000:]
    assert result.stdout == ""


def test_estimate_through_the_console_script_writes_its_whole_output(tiny_workspace: Workspace, tmp_path: Path,
                                                                      capsys) -> None:
    """Fails if `estimate` in a process of its own (which ends without the interpreter's teardown and with one BLAS
    thread, cli.entry) loses output: its JSON on a pipe (block-buffered stdout) cut short or differing from the same
    call in this process, a --json file incomplete, or a status other than 0."""
    argv = ["estimate", "--bases", str(tiny_workspace.bases), "--scan", str(tiny_workspace.scan), "--min-coverage", "0"]
    result = subprocess.run([sys.executable, "-m", "hood_decomp.cli", *argv], capture_output=True, text=True,
                            timeout=120, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert result.returncode == 0, result.stderr[-2000:]
    assert main(argv) == 0
    in_process = json.loads(capsys.readouterr().out)
    on_pipe = json.loads(result.stdout)
    assert on_pipe.keys() == in_process.keys()
    for name, value in in_process["parameters_mm"].items():
        assert abs(on_pipe["parameters_mm"][name] - value) < 1e-9
    out = tmp_path / "estimate.json"
    result = subprocess.run([sys.executable, "-m", "hood_decomp.cli", *argv, "--json", str(out)], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0 and result.stderr.rstrip().endswith(f"wrote {out}"), result.stderr[-2000:]
    assert json.loads(out.read_text())["parameters_mm"].keys() == in_process["parameters_mm"].keys()
