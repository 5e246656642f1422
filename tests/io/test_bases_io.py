"""Bases files (HDF5, no pickle), field files (.vtu) and the bases/estimate/decompose command line."""

import json
from dataclasses import replace

import h5py
import numpy as np
import pytest

from hood_decomp.cli import main
from hood_decomp.core.method.bases import build_bases, decompose_field, estimate_field
from hood_decomp.errors import BasisError, FieldError, ModelIdMismatchError
from hood_decomp.io.bases import load_bases, save_bases
from hood_decomp.io.fields import read_field, write_field
from tests.toy_models import field_of, full_factorial, make_ensemble, make_reduced_model, make_skin, random_states


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    skin = make_skin(16, 12)
    model = make_reduced_model(skin, seed=8)
    states, rank = full_factorial(6)
    bases = build_bases(make_ensemble(model, states, rank), skin, model, n_components=10, epsilon=0.01)
    path = tmp_path_factory.mktemp("bases") / "bases.h5"
    save_bases(path, bases)
    return skin, model, bases, path


def test_round_trip_keeps_every_array_and_result(saved):
    skin, model, bases, path = saved
    loaded = load_bases(path)
    assert loaded.model_id == bases.model_id and loaded.names == bases.names
    for name in ("components_", "components_3d_", "component_states_", "mean_state_", "gram_"):
        np.testing.assert_array_equal(getattr(loaded.pca, name), getattr(bases.pca, name))
    for name in ("fields_", "fields_3d_", "effect_fields_", "independent_", "trace_"):
        np.testing.assert_array_equal(getattr(loaded.hierarchical, name), getattr(bases.hierarchical, name))
    assert loaded.hierarchical.effect_names_ == bases.hierarchical.effect_names_
    assert loaded.pca.notes_ == bases.pca.notes_
    np.testing.assert_array_equal(loaded.reduced_model.H, model.H)
    assert loaded.reduced_model.names == model.names
    np.testing.assert_array_equal(loaded.skin.triangles, skin.triangles)
    truth = random_states(model, 1, seed=2)[0]
    values = make_ensemble(model, truth[None]).normal_displacement[0]
    for method in ("contact", "pca"):
        a = estimate_field(bases, field_of(skin, values), method)
        b = estimate_field(loaded, field_of(skin, values), method)
        np.testing.assert_allclose(a.values, b.values, rtol=0, atol=1e-12)
    shares = [e.share for e in decompose_field(loaded, field_of(skin, values)).effects]
    np.testing.assert_allclose(shares, [e.share for e in decompose_field(bases, field_of(skin, values)).effects])



def test_loaded_bases_report_the_id_their_content_has(saved):
    """Fails if the id `estimate` reports for loaded bases (remembered from the load's check, not hashed again) is not
    the file's bases_id and the fingerprint of the content, or if another Bases object (calibrated, replaced) is
    given the remembered id instead of its own."""
    from hood_decomp.io.bases import bases_id, loaded_bases_id

    _, _, bases, path = saved
    loaded = load_bases(path)
    with h5py.File(path, "r") as h5:
        stored = h5.attrs["bases_id"]
    assert loaded_bases_id(loaded) == stored == bases_id(loaded) == bases_id(bases)
    other = replace(loaded, calibration='{"id": "x"}')
    assert loaded_bases_id(other) == bases_id(other) != stored


def test_what_a_scan_reads_is_stored_plain_and_other_indices_packed(saved):
    """Fails if float arrays or the prepared scan skin's integer arrays are gzip-compressed again (inflating them cost
    more than half of a one-off `estimate --scan`'s file reading at paper resolution: the skin's lookup grid and
    kernel indices alone 80 ms of CPU), or if the other integer arrays are stored unpacked."""
    _, _, _, path = saved
    with h5py.File(path, "r") as h5:
        assert h5["pca/components_3d"].compression is None and h5["scan_skin/kernel_data"].compression is None
        assert h5["scan_skin/grid_table"].compression is None
        assert h5["scan_skin/kernel_indices"].compression is None
        assert h5["hierarchical/effect_fields"].compression == "gzip"

def test_file_holds_no_python_objects(saved):
    _, _, _, path = saved
    with h5py.File(path, "r") as h5:
        kinds = []
        h5.visititems(lambda _, item: kinds.append(item.dtype.kind) if isinstance(item, h5py.Dataset) else None)
    assert set(kinds) <= {"f", "i", "b", "O", "u"}  # "O" only as HDF5 variable-length strings
    with h5py.File(path, "r") as h5:
        assert h5["parameters/names"].dtype == h5py.string_dtype()


def test_wrong_files_and_fields_are_refused(saved, tmp_path):
    skin, model, bases, _ = saved
    with pytest.raises(BasisError, match="does not exist"):
        load_bases(tmp_path / "missing.h5")
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as h5:
        h5.attrs["format"] = "something else"
    with pytest.raises(BasisError, match="not a hood_decomp bases file"):
        load_bases(other)
    foreign = replace(field_of(skin, model.w0), model_id="ffffffffffffffff")
    with pytest.raises(ModelIdMismatchError):
        estimate_field(bases, foreign)
    with pytest.raises(ModelIdMismatchError):
        decompose_field(bases, foreign)
    with pytest.raises(BasisError, match="unknown estimation method"):
        estimate_field(bases, field_of(skin, model.w0), "magic")


def test_field_file_round_trip_and_missing_model_id(saved, tmp_path):
    skin, model, _, _ = saved
    values = model.w0.copy()
    values[:10] = np.nan
    path = tmp_path / "field.vtu"
    write_field(path, skin, field_of(skin, values, 0.02))
    field, vectors = read_field(path)
    assert field.model_id == skin.model_id and field.noise_rms == 0.02
    np.testing.assert_array_equal(field.normal_displacement, values)
    assert field.coverage == pytest.approx(1 - 10 / skin.n_nodes)
    np.testing.assert_allclose(vectors[10:], skin.normals[10:] * values[10:, None])
    import meshio

    plain = tmp_path / "plain.vtu"  # meshio drops VTU field data: no model_id in this file
    meshio.write(plain, meshio.Mesh(skin.points, [("triangle", skin.triangles)],
                                    point_data={"normal_displacement": values}))
    with pytest.raises(FieldError, match="no field data 'model_id'"):
        read_field(plain)
    assert read_field(plain, skin)[0].model_id == skin.model_id
    moved = replace(skin, points=skin.points + 1.0)
    with pytest.raises(FieldError, match="not the bases' skin nodes"):
        read_field(plain, moved)


def test_field_file_carries_a_3d_displacement_only_when_the_field_has_one(saved, tmp_path):
    """A field's 3D displacement (issue 21) is written and read back as it was; a field without one, or a file
    written before the flag (its ``displacement`` is normal x value, a picture), reads without one; a file cannot
    state one it does not hold, one that is not the field's, or a flag that is not 0 or 1."""
    skin, model, _, _ = saved
    values, vectors = model.w0.copy(), model.w0_3d.copy()  # the toy model's 3D field has its w0 as normal part
    values[:10] = np.nan
    vectors[:10] = np.nan
    path = tmp_path / "field3.vtu"
    write_field(path, skin, replace(field_of(skin, values), displacement=vectors))
    field, picture = read_field(path, skin)
    np.testing.assert_array_equal(field.displacement, vectors)
    np.testing.assert_array_equal(field.normal_displacement, values)
    np.testing.assert_array_equal(picture, vectors)
    assert np.abs(vectors[10:] - skin.normals[10:] * values[10:, None]).max() > 0.1  # not the normal picture

    plain = tmp_path / "normal.vtu"
    write_field(plain, skin, field_of(skin, values))
    assert read_field(plain, skin)[0].displacement is None
    text = path.read_text()
    flag = '<DataArray type="UInt8" Name="displacement_3d" NumberOfTuples="1" format="ascii">1</DataArray>\n'
    assert flag in text
    old = tmp_path / "old.vtu"  # as written before the flag: its displacement is not read as the field's
    old.write_text(text.replace(flag, ""))
    assert read_field(old, skin)[0].displacement is None
    for bad, message in ((flag.replace(">1<", ">2<"), "0 or 1"), (flag.replace(">1<", ">nan<"), "0 or 1")):
        wrong = tmp_path / "wrong.vtu"
        wrong.write_text(text.replace(flag, bad.replace("UInt8", "Float64") if "nan" in bad else bad))
        with pytest.raises(FieldError, match=message):
            read_field(wrong, skin)
    with pytest.raises(FieldError, match="normal part differs"):
        write_field(tmp_path / "x.vtu", skin, replace(field_of(skin, values), displacement=vectors + skin.normals))
    # a file whose 3D field is not its normal one on this skin: written against other normals
    tilted = np.cross(skin.normals, [1.0, 0.0, 0.0]) * 0.3 + skin.normals
    other = replace(skin, normals=tilted / np.linalg.norm(tilted, axis=1, keepdims=True))
    forged = replace(field_of(skin, np.einsum("na,na->n", vectors, other.normals)), displacement=vectors)
    write_field(tmp_path / "forged.vtu", other, forged)
    with pytest.raises(FieldError, match="normal part differs"):
        read_field(tmp_path / "forged.vtu", skin)
    read_field(tmp_path / "forged.vtu")  # without the skin the normal part is not checked (the estimator does)


def test_cli_estimate_and_decompose(saved, tmp_path, capsys):
    skin, model, _, path = saved
    truth = np.array([0.3, -0.6, 0.5, 0.2, 0.4, -1.0])
    member = make_ensemble(model, truth[None])
    field_path = tmp_path / "f.vtu"
    write_field(field_path, skin, field_of(skin, member.normal_displacement[0]))
    out = tmp_path / "e.json"
    assert main(["estimate", "--bases", str(path), "--field", str(field_path), "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert set(result) >= {"parameters_mm", "std_mm", "lifted", "residual_rms_mm", "residual_max_mm", "coverage"}
    assert set(result["lifted"]) == {"BUFFER_R", "BUFFER_L"}
    assert result["lifted"]["BUFFER_L"] == bool(member.contact_fraction[0, 1] == 0)
    for i, name in enumerate(model.names):
        assert result["parameters_mm"][name] == pytest.approx(member.effective[0, i], abs=1e-9)
    # issue 15: the full covariance (symmetric, its diagonal the std^2) and the one test behind within_model; a
    # simulated field states no error model, so its noise level is estimated from the residual and says so
    cov = result["covariance_mm2"]
    for a in model.names:
        assert cov[a][a] == pytest.approx(result["std_mm"][a] ** 2, rel=1e-9, abs=1e-30)
        for b in model.names:
            assert cov[a][b] == pytest.approx(cov[b][a], rel=1e-9, abs=1e-30)
    assert result["within_model_test"]["noise_source"] == "residual"
    # the uncalibrated model's physical factors, apart from the measurement std: model_std^2 is the sum of the
    # factors' squared effects and the model covariance's diagonal; the pad factors move the touching buffer
    model_cov, factors = result["model_covariance_mm2"], result["model_factors_mm"]
    assert set(factors) == {"compliance (Young's modulus)", "pad stiffness", "pad preload"}
    for a in model.names:
        total = sum(effect[a] ** 2 for effect in factors.values())
        assert result["model_std_mm"][a] ** 2 == pytest.approx(total, rel=1e-9, abs=1e-30)
        assert model_cov[a][a] == pytest.approx(total, rel=1e-9, abs=1e-30)
    assert abs(factors["pad preload"]["BUFFER_R"]) > 1e-4
    assert result["within_model"] == (result["within_model_test"]["p_value"] >= result["within_model_test"]["alpha"])
    plots = tmp_path / "plots"
    out = tmp_path / "d.json"
    assert main(["decompose", "--bases", str(path), "--field", str(field_path), "--json", str(out),
                 "--plots", str(plots)]) == 0
    result = json.loads(out.read_text())
    assert result["reconstruction_rms_mm"] < 0.01
    assert sum(e["share"] for e in result["effects"]) == pytest.approx(1.0)
    assert all(set(e) >= {"name", "parameters", "share"} for e in result["effects"])
    assert len(list(plots.glob("contribution_*.png"))) == len(result["effects"])
    assert (plots / "reconstruction_error.png").stat().st_size > 1000


def test_cli_errors_are_one_line(saved, tmp_path, capsys):
    _, _, _, path = saved
    assert main(["estimate", "--bases", str(tmp_path / "nope.h5"), "--field", "x.vtu"]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["estimate", "--bases", str(path), "--field", str(tmp_path / "nope.vtu")]) == 2
    assert "field file" in capsys.readouterr().err
    assert main(["estimate", "--bases", str(path), "--scan", str(tmp_path / "s.ply")]) == 2
    assert "s.ply" in capsys.readouterr().err  # missing scan file (or missing scan-to-field code) named
