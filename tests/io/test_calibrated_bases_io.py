"""Calibrated bases on disk (issue 16): the calibration record, the thermal response and the model discrepancy
round-trip, change the bases_id (the model_id stays), and an edited record or discrepancy is refused."""

from __future__ import annotations

import json
from dataclasses import replace

import h5py
import numpy as np
import pytest

from hood_decomp.errors import BasisError
from hood_decomp.io.bases import bases_id, load_bases, save_bases


def test_calibration_and_thermal_round_trip_and_are_fingerprinted(coarse_hood, tmp_path):
    """Fails if the calibration record, the thermal response, the discrepancy modes, its per-node local part, its
    rows' noise or the correction's own noise (session 11) are lost or altered on the way through the file, if a file
    without the last two does not read as before, if calibrated bases keep the uncalibrated bases_id or change the
    model_id, or if an edited record, discrepancy, local part or noise term is accepted."""
    bases = coarse_hood.bases
    n, s = bases.skin.n_nodes, len(bases.reduced_model.k)
    rng = np.random.default_rng(0)
    thermal = (rng.normal(size=n), rng.normal(size=s), rng.normal(size=(n, 3)))
    record = json.dumps({"id": "abc", "entries": [{"name": "ref.vtu", "loo_rms_mm": 0.02}], "loo_rms_mm": 0.02})
    discrepancy = 0.01 * rng.normal(size=(n, 3))
    local = 1e-5 * rng.uniform(size=n)
    noise, own = 0.005 * rng.normal(size=(n, 7)), 0.001 * rng.normal(size=(n, 2))
    calibrated = replace(bases, calibration=record, thermal=thermal, discrepancy=discrepancy, discrepancy_local=local,
                         discrepancy_noise=noise, calibration_noise=own)
    path = tmp_path / "calibrated.h5"
    save_bases(path, calibrated)
    loaded = load_bases(path)
    assert loaded.calibration == record
    for a, b in zip(loaded.thermal, thermal, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(loaded.discrepancy, discrepancy)
    np.testing.assert_array_equal(loaded.discrepancy_local, local)
    np.testing.assert_array_equal(loaded.discrepancy_noise, noise)
    np.testing.assert_array_equal(loaded.calibration_noise, own)
    # a file calibrated before session 11 (no noise terms) reads as before: D D^T counted as it is
    older = replace(calibrated, discrepancy_noise=None, calibration_noise=None)
    save_bases(path, older)
    assert load_bases(path).discrepancy_noise is None and load_bases(path).calibration_noise is None
    assert bases_id(older) != bases_id(calibrated)
    save_bases(path, calibrated)
    with h5py.File(path, "r+") as h5:
        h5["discrepancy_noise"][0, 0] = 0.0
    with pytest.raises(BasisError, match="bases_id"):
        load_bases(path)
    save_bases(path, calibrated)
    assert load_bases(coarse_hood.bases_path).discrepancy is None
    assert loaded.model_id == bases.model_id
    assert bases_id(loaded) != bases_id(bases)
    assert load_bases(coarse_hood.bases_path).calibration == ""
    with h5py.File(path, "r+") as h5:
        h5["discrepancy"][0, 0] = 0.0
    with pytest.raises(BasisError, match="bases_id"):
        load_bases(path)
    save_bases(path, calibrated)
    with h5py.File(path, "r+") as h5:
        h5["discrepancy_local"][0] = 2e-5
    with pytest.raises(BasisError, match="bases_id"):
        load_bases(path)
    save_bases(path, calibrated)
    with h5py.File(path, "r+") as h5:
        h5.attrs["calibration"] = record.replace("0.02", "0.01")
    with pytest.raises(BasisError, match="bases_id"):
        load_bases(path)
