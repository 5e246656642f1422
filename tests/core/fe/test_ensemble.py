"""Sampling plans, the HDF5 ensemble store, field export and the model / simulate / ensemble command line."""

from __future__ import annotations

import json
from math import comb
from pathlib import Path

import h5py
import meshio
import numpy as np
import pytest

from hood_decomp.cli import main
from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble, validation_plan
from hood_decomp.core.fe.hood_preset import build_hood
from hood_decomp.core.fe.model import skin_surface
from hood_decomp.core.fe.solver import build_solver, reduce_model
from hood_decomp.errors import EnsembleError
from hood_decomp.io.ensemble_store import export_member, load_ensemble, load_skin, write_ensemble
from hood_decomp.io.fields import read_field


def test_factorial_plan_has_table_1_ranks() -> None:
    """3^6 = 729 distinct states on {-1, 0, 1}; rank r occurs C(6, r) 2^r times, in rank order."""
    commanded, rank = factorial_plan(-np.ones(6), np.ones(6))
    assert commanded.shape == (729, 6)
    assert len({tuple(row) for row in commanded}) == 729
    assert np.array_equal(rank, (commanded != 0).sum(axis=1))
    assert np.all(np.diff(rank) >= 0)
    assert [int((rank == r).sum()) for r in range(7)] == [comb(6, r) * 2**r for r in range(7)]
    asymmetric, _ = factorial_plan(np.array([-2.0, 0.5]), np.array([1.0, 3.0]))
    assert set(asymmetric[:, 0]) == {-2.0, 0.0, 1.0} and set(asymmetric[:, 1]) == {0.5, 0.0, 3.0}


def test_validation_plan_is_uniform_and_reproducible() -> None:
    a = validation_plan(-np.ones(6), np.ones(6), 4000, seed=5)
    assert np.array_equal(a, validation_plan(-np.ones(6), np.ones(6), 4000, seed=5))
    assert a.min() >= -1 and a.max() <= 1
    assert np.allclose(a.mean(axis=0), 0.0, atol=0.05) and np.allclose(a.var(axis=0), 1 / 3, atol=0.03)


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory):
    model = build_hood("coarse")
    reduced = reduce_model(build_solver(model))
    path = tmp_path_factory.mktemp("ens") / "ensemble.h5"
    summary = write_ensemble(path, reduced, skin_surface(model), model.lower, model.upper, n_validation=40, seed=2)
    return model, reduced, path, summary


def test_store_round_trip_matches_in_memory_members(store) -> None:
    model, reduced, path, summary = store
    training = load_ensemble(path, "training")
    commanded, rank = factorial_plan(model.lower, model.upper)
    expected = simulate_ensemble(reduced, commanded, rank, model.lower, model.upper)
    assert training.names == ("HINGE_X", "HINGE_Y", "LOCK_L", "LOCK_R", "BUFFER_L", "BUFFER_R")
    assert training.n_bilateral == 4 and training.model_id == model.model_id
    assert np.array_equal(training.commanded, expected.commanded) and np.array_equal(training.rank, rank)
    assert np.allclose(training.effective, expected.effective)
    assert np.allclose(training.normal_displacement, expected.normal_displacement, atol=1e-5)
    assert np.allclose(training.displacement, expected.displacement, atol=1e-5)
    assert summary["training"]["members"] == 729
    validation = load_ensemble(path, "validation")
    assert validation.n_members == 40 and np.all(validation.rank == -1)
    assert np.array_equal(validation.commanded, validation_plan(model.lower, model.upper, 40, seed=2))
    skin = load_skin(path)
    assert skin.model_id == model.model_id and skin.n_nodes == training.normal_displacement.shape[1]


def test_store_is_plain_hdf5_without_objects(store) -> None:
    _, _, path, _ = store
    with h5py.File(path, "r") as f:
        assert f.attrs["schema"] == "hood_decomp.ensemble" and int(f.attrs["schema_version"]) == 2
        kinds = []
        f.visititems(lambda name, obj: kinds.append(obj.dtype.kind) if isinstance(obj, h5py.Dataset) else None)
        assert set(kinds) <= {"f", "i", "O"}  # "O" only for the UTF-8 names
        assert f["names"].dtype == h5py.string_dtype()
        assert f["training/displacement"].dtype == np.float32


def test_normal_displacement_is_the_normal_part_of_the_3d_field(store) -> None:
    _, _, path, _ = store
    training = load_ensemble(path, "training", members=slice(100, 110))
    normals = load_skin(path).normals
    assert np.allclose(np.einsum("mnk,nk->mn", training.displacement, normals), training.normal_displacement,
                       atol=1e-5)


def test_incomplete_or_foreign_store_is_refused(tmp_path: Path, store) -> None:
    _, _, path, _ = store
    copy = tmp_path / "copy.h5"
    copy.write_bytes(path.read_bytes())
    with h5py.File(copy, "a") as f:
        f["validation"].attrs["complete"] = False
    with pytest.raises(EnsembleError, match="incomplete"):
        load_ensemble(copy, "validation")
    with h5py.File(copy, "a") as f:
        f.attrs["schema"] = "other"
    with pytest.raises(EnsembleError, match="expected schema"):
        load_ensemble(copy)


def test_member_export_to_vtu(tmp_path: Path, store) -> None:
    _, _, path, _ = store
    out = export_member(path, "training", 17, tmp_path / "member.vtu")
    mesh = meshio.read(out)
    member = load_ensemble(path, "training", members=slice(17, 18))
    assert mesh.point_data["displacement"].shape == (member.displacement.shape[1], 3)
    assert np.allclose(mesh.point_data["normal_displacement"], member.normal_displacement[0])
    field, vectors = read_field(out)
    assert field.model_id == member.model_id and np.allclose(vectors, member.displacement[0], atol=1e-6)
    with pytest.raises(EnsembleError, match=r"members 0\.\.728"):
        export_member(path, "training", 729, tmp_path / "x.vtu")


def test_command_line_model_simulate_ensemble(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    model_dir, field, store_path = tmp_path / "hood", tmp_path / "field.vtu", tmp_path / "e.h5"
    assert main(["model", "--preset", "hood", "--resolution", "coarse", "--out", str(model_dir)]) == 0
    assert (model_dir / "model.yaml").is_file() and (model_dir / "mesh.vtu").is_file()
    assert main(["simulate", "--model", str(model_dir), "--set", "HINGE_Y=1,LOCK_L=-0.5", "--out", str(field)]) == 0
    report = json.loads(capsys.readouterr().out)
    written, vectors = read_field(field)
    normal = written.normal_displacement
    assert report["max_abs_normal_displacement_mm"] == pytest.approx(np.abs(normal).max())
    assert vectors.shape == (len(normal), 3)
    assert main(["ensemble", "--model", str(model_dir), "--out", str(store_path), "--validation", "5"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["training"]["members"] == 729 and summary["validation"]["members"] == 5
    assert main(["simulate", "--model", str(model_dir), "--set", "HINGE_Z=1", "--out", str(field)]) == 2
    assert "unknown setting 'HINGE_Z'" in capsys.readouterr().err
    assert main(["simulate", "--model", str(tmp_path / "nope"), "--set", "HINGE_Y=1", "--out", str(field)]) == 2
