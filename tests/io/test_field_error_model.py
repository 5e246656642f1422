"""The field error model in the field file: round trip, the "none" statement, and bad error models refused by name."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hood_decomp.core.types import DisplacementField, FieldErrorModel
from hood_decomp.errors import FieldError
from hood_decomp.io.fields import read_field, write_field
from tests.toy_models import make_skin

SKIN = make_skin(12, 8)


def _scan_like(n: int) -> FieldErrorModel:
    rng = np.random.default_rng(0)
    root = rng.normal(size=(6, 6)) * 1e-3
    std = rng.uniform(0.001, 0.003, n)
    std[:5] = np.nan
    return FieldErrorModel("scan", std, rng.uniform(1.0, 20.0, n), 12.5, root @ root.T, np.array([1.0, 2.0, 3.0]),
                           300.0, bias_variance_floor=2.5e-6)


def test_error_model_round_trip_and_none_is_stated(tmp_path):
    """Fails if any part of the error model (node std with its NaN, correlation, pose covariance and centre, lengths)
    does not survive the file, or a simulated field's "none" is not written and read back as "none"."""
    values = np.linspace(-0.2, 0.3, SKIN.n_nodes)
    values[:5] = np.nan
    errors = _scan_like(SKIN.n_nodes)
    write_field(tmp_path / "f.vtu", SKIN, DisplacementField(SKIN.model_id, values, 0.9, 0.02, errors))
    back = read_field(tmp_path / "f.vtu")[0].error_model
    assert back.kind == "scan" and back.correlation_length_mm == 12.5 and back.bias_correlation == 300.0
    assert back.bias_variance_floor == 2.5e-6
    np.testing.assert_array_equal(back.node_std, errors.node_std)
    np.testing.assert_array_equal(back.correlation, errors.correlation)
    np.testing.assert_array_equal(back.pose_covariance, errors.pose_covariance)
    np.testing.assert_array_equal(back.pose_center, errors.pose_center)
    write_field(tmp_path / "g.vtu", SKIN, DisplacementField(SKIN.model_id, values, 0.9, float("nan")))
    assert read_field(tmp_path / "g.vtu")[0].error_model.kind == "none"


@pytest.mark.parametrize(("change", "message"), [
    (dict(node_std=np.ones(3)), "node_std has shape"),
    (dict(correlation=np.ones(3)), "correlation has shape"),
    (dict(node_std=-np.ones(SKIN.n_nodes)), "finite and >= 0"),
    (dict(node_std=np.full(SKIN.n_nodes, np.inf)), "finite and >= 0"),
    (dict(correlation=np.full(SKIN.n_nodes, np.nan)), "correlation"),
    (dict(pose_covariance=np.triu(np.ones((6, 6)))), "not symmetric"),
    (dict(pose_covariance=-np.eye(6)), "not positive semi-definite"),
    (dict(pose_covariance=np.full((6, 6), np.nan)), "finite \\(6, 6\\)"),
    (dict(pose_covariance=np.eye(5)), "finite \\(6, 6\\)"),
    (dict(kind="guess"), "kind"),
    (dict(bias_correlation=-1.0), "bias_correlation"),
    (dict(bias_variance_floor=-1e-6), "bias_variance_floor must be a finite number >= 0"),
    (dict(bias_variance_floor=np.nan), "bias_variance_floor must be a finite number >= 0"),
])
def test_bad_error_models_are_named(tmp_path, change, message):
    """Fails if an error model of the wrong shape, with negative, infinite or NaN variances (on seen nodes), or a pose
    covariance that is not a symmetric positive semi-definite 6 x 6 matrix is accepted by the writer, or by the
    reader when it comes in a file (the estimator checks it through check_field the same way)."""
    from hood_decomp.core.method.estimation import check_field

    bad = dataclasses.replace(_scan_like(SKIN.n_nodes), **change)
    field = DisplacementField(SKIN.model_id, np.zeros(SKIN.n_nodes), 1.0, 0.02, bad)
    with pytest.raises(FieldError, match=message):
        write_field(tmp_path / "bad.vtu", SKIN, field)
    with pytest.raises(FieldError, match=message):
        check_field(field, SKIN.model_id, SKIN.n_nodes)
    # the same model written by hand into a file is refused on reading, naming the file
    good = DisplacementField(SKIN.model_id, np.zeros(SKIN.n_nodes), 1.0, 0.02, _scan_like(SKIN.n_nodes))
    write_field(tmp_path / "ok.vtu", SKIN, good)
    if "pose_covariance" in change and np.shape(change["pose_covariance"]) == (6, 6):
        text = (tmp_path / "ok.vtu").read_text()
        start = text.index('Name="error_pose_covariance"')
        start = text.index(">", start) + 1
        end = text.index("</DataArray>", start)
        numbers = " ".join(repr(float(v)) for v in np.asarray(change["pose_covariance"]).ravel())
        (tmp_path / "ok.vtu").write_text(text[:start] + numbers + text[end:])
        with pytest.raises(FieldError, match=f"ok.vtu: .*{message}"):
            read_field(tmp_path / "ok.vtu")


def test_a_field_file_written_before_the_bias_floor_reads_as_none(tmp_path):
    """Fails if a field file without ``error_bias_variance_floor_mm2`` (written before issue 15 run 17) is refused
    or reads as anything but no floor, or if the key is not where the file states the floor."""
    field = DisplacementField(SKIN.model_id, np.zeros(SKIN.n_nodes), 1.0, 0.02, _scan_like(SKIN.n_nodes))
    write_field(tmp_path / "f.vtu", SKIN, field)
    text = (tmp_path / "f.vtu").read_text()
    start = text.rindex("<DataArray", 0, text.index('Name="error_bias_variance_floor_mm2"'))
    end = text.index("</DataArray>", start) + len("</DataArray>")
    (tmp_path / "f.vtu").write_text(text[:start] + text[end:])
    back = read_field(tmp_path / "f.vtu")[0].error_model
    assert back.bias_variance_floor == 0.0 and back.bias_correlation == 300.0


def test_an_error_model_checked_for_one_node_count_is_checked_again_for_another_and_lands_unchecked():
    """Fails if the memo of FieldErrorModel.validate (an estimate asks four times) lets a model checked for N nodes
    pass for another count, or if a pickled model (a dask task, a process pool) carries the memo and its cached
    variances with it instead of making them again where it lands."""
    import pickle

    errors = _scan_like(SKIN.n_nodes)
    errors.validate(SKIN.n_nodes)
    variance, _ = errors.node_variance(SKIN.n_nodes)
    with pytest.raises(FieldError, match="node_std has shape"):
        errors.validate(SKIN.n_nodes + 1)
    landed = pickle.loads(pickle.dumps(errors))
    assert not any(name.startswith("_") for name in vars(landed))
    np.testing.assert_array_equal(landed.node_variance(SKIN.n_nodes)[0], variance)
