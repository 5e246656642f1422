"""The part model files: round trip of the hood preset and clear ModelErrors for bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from hood_decomp.core.fe.calculix import load_cases, write_deck
from hood_decomp.core.fe.hood_preset import build_hood
from hood_decomp.core.fe.model import patch_nodes, skin_surface
from hood_decomp.core.fe.solver import build_solver
from hood_decomp.errors import ModelError
from hood_decomp.io.mesh import read_mesh, write_mesh
from hood_decomp.io.model_files import load_model, save_model


@pytest.fixture(scope="module")
def coarse_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("coarse")
    save_model(build_hood("coarse"), directory)
    return directory


def _edited(coarse_dir: Path, tmp_path: Path, edit) -> Path:
    """Copy the coarse model to tmp_path with an edit applied to the parsed model.yaml."""
    document = yaml.safe_load((coarse_dir / "model.yaml").read_text())
    edit(document)
    (tmp_path / "model.yaml").write_text(yaml.safe_dump(document, sort_keys=False))
    (tmp_path / "mesh.vtu").write_bytes((coarse_dir / "mesh.vtu").read_bytes())
    return tmp_path


def test_hood_round_trips_through_yaml_and_vtu(coarse_dir: Path) -> None:
    original = build_hood("coarse")
    loaded = load_model(coarse_dir)
    assert loaded.model_id == original.model_id
    assert loaded.names == ("HINGE_X", "HINGE_Y", "LOCK_L", "LOCK_R", "BUFFER_L", "BUFFER_R")
    assert [b.name for b in loaded.boundaries] == [b.name for b in original.boundaries]
    for a, b in zip(loaded.boundaries, original.boundaries, strict=True):
        assert np.array_equal(patch_nodes(loaded, a), patch_nodes(original, b))


def test_hood_preset_follows_the_paper_setup() -> None:
    model = build_hood("coarse")
    thickness = {p.name: p.thickness for p in model.parts}
    assert thickness["outer_skin"] == 0.7 and thickness["inner_panel"] == 0.7
    assert sorted(t for name, t in thickness.items() if name.startswith("reinf")) == [2.0] * 4
    assert np.all(model.lower == -1.0) and np.all(model.upper == 1.0)
    skin = set(model.skin_nodes.tolist())
    for boundary in model.boundaries:  # every boundary acts on a patch of the inner structure, not the skin
        nodes = patch_nodes(model, boundary)
        assert len(nodes) >= 3 and not skin & set(nodes.tolist())
    surface = skin_surface(model)
    assert surface.normals[:, 2].min() > 0.8  # outward = up, the scanner side
    extent = np.ptp(surface.points, axis=0)
    assert 1200 < extent[0] < 1300 and 1400 < extent[1] < 1500
    gas = [b for b in model.boundaries if b.kind == "force"]
    assert len(gas) == 2 and all(b.force == 580.0 and b.axis[1] == 0.0 for b in gas)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["parameters"][0].update(boundary="hinge_X"), "unknown boundary 'hinge_X'"),
        (lambda d: d["boundaries"][2]["patch"].update(center=[5000.0, 0.0, 0.0]), "selects no nodes"),
        (lambda d: d["parameters"][2].update(range=[1.0, -1.0]), "min <= max"),
        (lambda d: d["parts"][1].pop("thickness"), "missing thickness"),
        (lambda d: d["boundaries"][0].update(kind="welded"), "kind must be one of"),
        (lambda d: d.update(format="something"), "expected format"),
        (lambda d: d["parameters"][0].update(direction="q"), "direction must be x, y or z"),
    ],
    ids=["unknown-boundary", "empty-patch", "min>max", "no-thickness", "bad-kind", "bad-format", "bad-direction"],
)
def test_bad_model_yaml_gives_clear_model_error(coarse_dir: Path, tmp_path: Path, edit, message: str) -> None:
    path = _edited(coarse_dir, tmp_path, edit)
    with pytest.raises(ModelError, match=message):
        load_model(path)


def test_degenerate_element_is_named(coarse_dir: Path, tmp_path: Path) -> None:
    nodes, cells, part = read_mesh(coarse_dir / "mesh.vtu")
    cells[7, 2] = cells[7, 1]  # a quad with a repeated node
    path = _edited(coarse_dir, tmp_path, lambda d: None)
    write_mesh(path / "mesh.vtu", nodes, cells, part)
    with pytest.raises(ModelError, match=r"degenerate element\(s\) \[7\]"):
        load_model(path)


def test_under_constrained_part_names_the_free_motions(coarse_dir: Path, tmp_path: Path) -> None:
    """Only Z held everywhere: translation in X and Y and rotation about Z are free, and the message says so."""

    def z_only(document: dict) -> None:
        for boundary in document["boundaries"]:
            if "dofs" in boundary:
                boundary["dofs"] = ["z"]
        document["parameters"] = [p for p in document["parameters"] if p["direction"] == "z"]

    model = load_model(_edited(coarse_dir, tmp_path, z_only))
    with pytest.raises(ModelError, match="3 free rigid-body motion") as info:
        build_solver(model)
    text = str(info.value)
    assert "translation along X" in text and "translation along Y" in text and "rotation about Z" in text


def test_calculix_deck_is_a_mesh_file_too(coarse_dir: Path, tmp_path: Path) -> None:
    """The .inp deck written for CalculiX (S8R, mid-side nodes after the model's), named as the mesh in model.yaml,
    gives back the very same model: the corners are the cells and the mid-side nodes are not mesh nodes."""
    original = load_model(coarse_dir)
    cases, constrained = load_cases(original)
    path = _edited(coarse_dir, tmp_path, lambda d: d.update(mesh="deck.inp"))
    write_deck(original, cases[0], constrained, path / "deck.inp")
    loaded = load_model(path)
    assert loaded.model_id == original.model_id
    assert np.array_equal(loaded.cell_part, original.cell_part)


def test_missing_model_file_is_a_model_error(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="does not exist"):
        load_model(tmp_path / "nothing")
