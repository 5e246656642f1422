"""The prepared scan skin stored in a bases file: used instead of a rebuild, equal to a fresh preparation, and an
altered or forged one refused; version 2 files (without it) still load."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest

from hood_decomp.core.method.bases import build_bases
from hood_decomp.core.scan import scan_field
from hood_decomp.core.scan.scan_field import ScanFieldEstimator, field_from_scan
from hood_decomp.errors import BasisError, ScanError
from hood_decomp.io.bases import bases_id, load_bases, prepared_id, save_bases
from tests.toy_models import full_factorial, make_ensemble, make_reduced_model, make_skin


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    skin = make_skin(24, 16)
    model = make_reduced_model(skin, seed=8)
    states, rank = full_factorial(6)
    bases = build_bases(make_ensemble(model, states, rank), skin, model, n_components=10, epsilon=0.01)
    path = tmp_path_factory.mktemp("bases") / "bases.h5"
    save_bases(path, bases)
    return bases, path


@pytest.fixture(scope="module")
def points():
    """A scan of the toy skin's nominal surface (0.05 mm noise), part frame."""
    rng = np.random.default_rng(3)
    x, y = rng.uniform(0.0, 1500.0, 150_000), rng.uniform(0.0, 1000.0, 150_000)
    z = 40.0 * np.sin(np.pi * y / 1000.0) + 0.01 * x + rng.normal(0.0, 0.05, x.size)
    return np.column_stack([x, y, z])


@pytest.fixture()
def fresh_cache(monkeypatch):
    """No prepared estimator or stored preparation from other tests."""
    monkeypatch.setattr(scan_field, "_PREPARED", {})
    monkeypatch.setattr(scan_field, "_STORED", {})


def _rewritten(path, target, edit):
    """A copy of the bases file ``path`` at ``target`` whose /scan_skin ``edit(h5)`` changed, its prepared_id
    recomputed over what is left (a file written before a dataset existed, or a forger's)."""
    shutil.copy(path, target)
    with h5py.File(target, "r+") as h5:
        edit(h5)
        arrays = {name: h5[f"scan_skin/{name}"][()] for name in h5["scan_skin"]}
        h5["scan_skin"].attrs["prepared_id"] = prepared_id(h5.attrs["bases_id"], arrays)
    return target


def _no_rebuild(monkeypatch):
    def refuse(*_args, **_kwargs):
        raise AssertionError("the prepared skin was rebuilt")

    monkeypatch.setattr(ScanFieldEstimator, "_build_grid", refuse)
    monkeypatch.setattr(ScanFieldEstimator, "_fit_quadrics", refuse)


def test_stored_scan_skin_is_used_and_equals_a_fresh_preparation(saved, points, fresh_cache, monkeypatch):
    """Fails if a scan of a loaded bases rebuilds the grid or quadrics instead of reading them from the file, or if
    the stored preparation gives another field than a fresh ScanFieldEstimator().fit (1e-12 mm)."""
    bases, path = saved
    expected = ScanFieldEstimator().fit(bases.skin).field(points)
    loaded = load_bases(path)
    _no_rebuild(monkeypatch)
    field, _ = field_from_scan(loaded.skin, points)
    assert field.coverage > 0.9
    np.testing.assert_array_equal(np.isnan(field.normal_displacement), np.isnan(expected.normal_displacement))
    np.testing.assert_allclose(field.normal_displacement, expected.normal_displacement, rtol=0, atol=1e-12)
    np.testing.assert_allclose(field.error_model.node_std, expected.error_model.node_std, rtol=1e-12)


def test_altered_scan_skin_is_refused(saved, points, fresh_cache, tmp_path):
    """Fails if an edited lookup-grid entry of the stored preparation reaches a field (it must fail its
    prepared_id on first use)."""
    bases, path = saved
    altered = tmp_path / "altered.h5"
    shutil.copy(path, altered)
    with h5py.File(altered, "r+") as h5:
        table = h5["scan_skin/grid_table"]
        table[0] = (table[0] + 1) % bases.skin.n_nodes  # still a valid node: only the fingerprint tells
    loaded = load_bases(altered)  # bases_id does not cover the derived preparation: the bases load
    with pytest.raises(BasisError, match="prepared_id"):
        field_from_scan(loaded.skin, points)


def test_forged_scan_skin_with_a_recomputed_id_is_range_checked(saved, points, fresh_cache, tmp_path):
    """Fails if a forger who recomputes prepared_id can put a node index out of range into the kernel (a crash or
    a wrong read instead of a named refusal)."""
    bases, path = saved
    forged = tmp_path / "forged.h5"
    shutil.copy(path, forged)
    with h5py.File(forged, "r+") as h5:
        h5["scan_skin/kernel_indices"][3] = 10**6
        arrays = {name: h5[f"scan_skin/{name}"][()] for name in scan_field.PREPARED_SKIN}
        h5["scan_skin"].attrs["prepared_id"] = prepared_id(bases_id(bases), arrays)
    loaded = load_bases(forged)
    with pytest.raises(ScanError, match="out-of-range kernel_indices"):
        field_from_scan(loaded.skin, points)


def test_version_2_file_loads_and_scans_with_a_rebuilt_skin(saved, points, fresh_cache, tmp_path):
    """Fails if a schema-2 bases file (no prepared skin) is refused, or if the prepared skin enters bases_id (the
    same bases must keep the same id with and without it)."""
    bases, path = saved
    old = tmp_path / "v2.h5"
    save_bases(old, bases, scan_skin=False)
    with h5py.File(old, "r+") as h5:
        h5.attrs["schema_version"] = 2
        stored = h5.attrs["bases_id"]
    with h5py.File(path, "r") as h5:
        assert h5.attrs["bases_id"] == stored and "scan_skin" in h5
    loaded = load_bases(old)
    field, _ = field_from_scan(loaded.skin, points)
    assert field.coverage > 0.9


def test_mapped_load_views_the_file_and_still_checks_it(saved, points, fresh_cache, tmp_path):
    """Fails if ``load_bases(mapped=True)`` copies the plainly stored arrays instead of viewing the mapped file (a
    writeable array), reads another offset or dtype than h5py does (another field than a copying load, bit for bit),
    or lets an edited float of the mapped file through (its bases_id must still be checked)."""
    _, path = saved
    copied = field_from_scan(load_bases(path).skin, points)[0]
    mapped = load_bases(path, mapped=True)
    assert not mapped.pca.components_.flags.writeable and not mapped.skin.points.flags.writeable
    with h5py.File(path, "r") as h5:
        np.testing.assert_array_equal(mapped.pca.components_, h5["pca/components"][()])
    field = field_from_scan(mapped.skin, points)[0]
    np.testing.assert_array_equal(field.normal_displacement, copied.normal_displacement)
    altered = tmp_path / "altered.h5"
    shutil.copy(path, altered)
    with h5py.File(altered, "r+") as h5:
        h5["pca/components"][0, 0] += 1e-9
    with pytest.raises(BasisError, match="bases_id"):
        load_bases(altered, mapped=True)


def test_twicing_variance_is_stored_and_files_without_it_still_scan(saved, points, fresh_cache, tmp_path, monkeypatch):
    """Fails if the twiced fit's variance ratio is not stored with the prepared skin (a one-off scan then rebuilds it
    from the kernel's two-ring product, 0.1 s on the default hood), if a stored one is not used, or if a file written
    before it existed (no /scan_skin/twicing_variance, its prepared_id over the other arrays) no longer scans or
    gives another node std."""
    _, path = saved
    with h5py.File(path, "r") as h5:
        assert "scan_skin/twicing_variance" in h5
    expected = field_from_scan(load_bases(path).skin, points)[0]
    older = _rewritten(path, tmp_path / "older.h5", lambda h5: h5.__delitem__("scan_skin/twicing_variance"))
    monkeypatch.setattr(scan_field, "_PREPARED", {})
    again = field_from_scan(load_bases(older).skin, points)[0]
    np.testing.assert_allclose(again.error_model.node_std, expected.error_model.node_std, rtol=1e-12)
    monkeypatch.setattr(scan_field, "_PREPARED", {})

    def refuse(_self):
        raise AssertionError("the stored twicing variance was rebuilt")

    monkeypatch.setattr(ScanFieldEstimator, "_twicing_variance", refuse)
    stored = field_from_scan(load_bases(path).skin, points)[0]
    np.testing.assert_array_equal(stored.error_model.node_std, expected.error_model.node_std)


def test_bias_correlation_is_stored_and_files_without_it_measure_it(saved, points, fresh_cache, tmp_path,
                                                                     monkeypatch):
    """Fails if the scan step's bias correlation measured on the part (core.loop.scan_skin) is not stored with the
    prepared skin or not carried by a scanned field's error model (the area fallback instead), or if a file written
    before it existed (no /scan_skin/bias_correlation, its prepared_id over the other arrays) does not measure the
    same value from its bases at the first scan."""
    bases, path = saved
    with h5py.File(path, "r") as h5:
        stored = float(h5["scan_skin/bias_correlation"][0])
    fallback = scan_field.smoothing_bias_correlation(bases.skin)
    assert np.isfinite(stored) and stored > 0 and abs(stored - fallback) > 1e-6 * fallback
    assert field_from_scan(load_bases(path).skin, points)[0].error_model.bias_correlation == stored
    older = _rewritten(path, tmp_path / "older.h5", lambda h5: h5.__delitem__("scan_skin/bias_correlation"))
    monkeypatch.setattr(scan_field, "_PREPARED", {})
    loaded = load_bases(older)
    again = field_from_scan(loaded.skin, points)[0]
    assert again.error_model.bias_correlation == pytest.approx(stored, rel=1e-9)


def test_bias_variance_floor_is_stored_and_files_without_it_measure_it(saved, points, fresh_cache, tmp_path,
                                                                        monkeypatch):
    """Fails if the scan step's bias variance floor measured on the part (core.loop.scan_skin, beside the
    correlation) is not stored with the prepared skin or not carried by a scanned field's error model, or if a file
    written before it (no /scan_skin/bias_variance_floor) does not measure the same value at the first scan while
    keeping the correlation it stores (here one altered to tell it from a re-measured one)."""
    _, path = saved
    with h5py.File(path, "r") as h5:
        stored = float(h5["scan_skin/bias_variance_floor"][0])
    assert np.isfinite(stored) and stored > 0
    assert field_from_scan(load_bases(path).skin, points)[0].error_model.bias_variance_floor == stored

    def older_file(h5):
        del h5["scan_skin/bias_variance_floor"]
        h5["scan_skin/bias_correlation"][0] = 33.0

    older = _rewritten(path, tmp_path / "older.h5", older_file)
    monkeypatch.setattr(scan_field, "_PREPARED", {})
    loaded = load_bases(older)  # held: the measurement needs the bases alive
    again = field_from_scan(loaded.skin, points)[0].error_model
    assert again.bias_variance_floor == pytest.approx(stored, rel=1e-9) and again.bias_correlation == 33.0


@pytest.mark.parametrize("value", [-1e-6, float("nan")])
def test_a_prepared_skin_with_a_bad_bias_variance_floor_is_refused_by_name(saved, value):
    """Fails if a prepared skin whose bias variance floor is negative (an indefinite bias term) or NaN is taken
    instead of refused naming it."""
    bases, _ = saved
    arrays = ScanFieldEstimator().fit(bases.skin).prepared_skin() | {"bias_variance_floor": np.array([value])}
    with pytest.raises(ScanError, match="bias_variance_floor"):
        ScanFieldEstimator().fit(bases.skin, prepared=arrays)


@pytest.mark.parametrize("value", [-3.0, 0.0, float("nan")])
def test_a_prepared_skin_with_a_bad_bias_correlation_is_refused_by_name(saved, points, fresh_cache, tmp_path, value):
    """Fails if a prepared skin whose bias correlation is negative, zero or NaN reaches a field (a negative one
    would make the within-model test's covariance indefinite, zero drop the bias allowance so every scan alarms)
    instead of a named refusal: ScanError from the arrays themselves, and from a file whose prepared_id was
    recomputed by a forger (the reader refuses a NaN by name first)."""
    bases, path = saved
    arrays = ScanFieldEstimator().fit(bases.skin).prepared_skin() | {"bias_correlation": np.array([value])}
    with pytest.raises(ScanError, match="bias_correlation"):
        ScanFieldEstimator().fit(bases.skin, prepared=arrays)
    def forge(h5):
        h5["scan_skin/bias_correlation"][0] = value

    forged = _rewritten(path, tmp_path / "forged.h5", forge)
    with pytest.raises((ScanError, BasisError), match="bias_correlation"):
        field_from_scan(load_bases(forged).skin, points)


def test_scan_skin_stored_before_the_bricks_loads_and_scans_the_same(saved, points, fresh_cache, tmp_path,
                                                                      monkeypatch):
    """Fails if a prepared skin written before the lookup table was laid out in bricks (no grid_brick, the table in
    plain C order, a grid of any shape) is refused, rebuilt, or gives another field than a fresh preparation
    (1e-12 mm): its table must be laid out in bricks at load, its last cells repeated to whole bricks."""
    bases, path = saved

    def plain_order(h5):
        brick = h5["scan_skin/grid_brick"][()]
        shape = h5["scan_skin/grid_shape"][()]
        outer = shape // brick
        table = h5["scan_skin/grid_table"][()].reshape(*outer, *brick).transpose(0, 3, 1, 4, 2, 5).reshape(shape)
        table = table[: shape[0] - 1, : shape[1] - 1, : shape[2] - 1]  # no longer whole bricks
        for name in ("grid_brick", "grid_table", "grid_shape"):
            del h5[f"scan_skin/{name}"]
        h5["scan_skin"].create_dataset("grid_table", data=table.ravel())
        h5["scan_skin"].create_dataset("grid_shape", data=np.array(table.shape, np.int64))

    old = _rewritten(path, tmp_path / "plain.h5", plain_order)
    expected = ScanFieldEstimator().fit(bases.skin).field(points)
    _no_rebuild(monkeypatch)
    field, _ = field_from_scan(load_bases(old).skin, points)
    assert field.coverage > 0.9
    np.testing.assert_array_equal(np.isnan(field.normal_displacement), np.isnan(expected.normal_displacement))
    np.testing.assert_allclose(field.normal_displacement, expected.normal_displacement, rtol=0, atol=1e-12)


def test_a_forged_brick_is_refused(saved, points, fresh_cache, tmp_path):
    """Fails if a grid_brick that is no power of two, or does not divide the grid's shape, reaches the lookup (a
    read out of the table) instead of a named refusal."""
    _, path = saved
    for k, value in enumerate(([3, 4, 1], [8, 8, 8])):
        def edit(h5, value=value):
            h5["scan_skin/grid_brick"][...] = value

        forged = _rewritten(path, tmp_path / f"brick{k}.h5", edit)
        scan_field._PREPARED.clear()
        scan_field._STORED.clear()
        with pytest.raises(ScanError, match="out-of-range grid_brick"):
            field_from_scan(load_bases(forged).skin, points)


def _with_reading_bias(bases, seed):
    """``bases`` with a stated scan reading bias (small: gain inside the basis about 0.05; the toy skin's own
    measured one is too large to take out and is not stored, core.loop.scan_skin.reading_bias)."""
    import dataclasses

    from hood_decomp.core.method.surface_reading import ScanReadingBias

    rng = np.random.default_rng(seed)
    k = bases.pca.n_components_
    components = 0.05 * rng.normal(size=(k, k)) @ bases.pca.components_ / np.sqrt(k)
    bias = ScanReadingBias(4.0, rng.normal(0.0, 1e-3, bases.skin.n_nodes), components)
    return dataclasses.replace(bases, scan_reading_bias=bias)


def test_the_scan_reading_bias_is_stored_checked_and_refused_when_altered(saved, tmp_path):
    """Fails if the bases' scan reading bias is not written to its own group and read back unchanged (not part of
    the bases' value: the bases_id stays the bases'), if the toy skin's own measured one (gain inside the basis
    2.8, far beyond a one-step correction) is stored, if an edited value or one taken from other bases passes its
    reading_id, or if a forged one of the wrong shape or not finite is not refused by name."""
    bases, path = saved
    assert load_bases(path).scan_reading_bias is None
    stated = _with_reading_bias(bases, 1)
    path = tmp_path / "stated.h5"
    assert save_bases(path, stated, scan_skin=False) is stated
    loaded = load_bases(path)
    bias = loaded.scan_reading_bias
    np.testing.assert_array_equal(bias.components, stated.scan_reading_bias.components)
    np.testing.assert_array_equal(bias.mean, stated.scan_reading_bias.mean)
    assert bias.radius_mm == 4.0 and bases_id(loaded) == bases_id(bases)

    def altered(name, edit):
        target = tmp_path / f"{name}.h5"
        shutil.copy(path, target)
        with h5py.File(target, "r+") as h5:
            edit(h5)
        return target

    def nudge(h5):
        h5["scan_reading_bias/mean"][0] += 1e-6

    with pytest.raises(BasisError, match="reading_id"):
        load_bases(altered("nudged", nudge))
    with pytest.raises(BasisError, match="reading_id"):
        load_bases(altered("radius", lambda h5: h5["scan_reading_bias"].attrs.modify("radius_mm", 9.0)))

    def short(h5):
        del h5["scan_reading_bias/components"]
        h5["scan_reading_bias"].create_dataset("components", data=np.zeros((3, bases.skin.n_nodes)))

    with pytest.raises(BasisError, match="components"):
        load_bases(altered("short", short))

    def nan(h5):
        h5["scan_reading_bias/mean"][0] = np.nan

    with pytest.raises(BasisError, match="mean"):
        load_bases(altered("nan", nan))

    other = tmp_path / "other.h5"  # other bases' own reading bias, well formed: it must not pass here
    model = make_reduced_model(bases.skin, seed=9)
    others = build_bases(make_ensemble(model, *full_factorial(6)), bases.skin, model, n_components=10, epsilon=0.01)
    assert others.pca.n_components_ == bases.pca.n_components_ and bases_id(others) != bases_id(bases)
    save_bases(other, _with_reading_bias(others, 2), scan_skin=False)

    def foreign(h5):
        del h5["scan_reading_bias"]
        with h5py.File(other, "r") as source:
            source.copy(source["scan_reading_bias"], h5, "scan_reading_bias")

    with pytest.raises(BasisError, match="reading_id"):
        load_bases(altered("foreign", foreign))
