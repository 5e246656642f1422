"""Tolerance zones from model.yaml to the bases file and back: the nodes a zone selects (worked out here from the
skin's coordinates), the validation of every entry, and the optional /tolerance_zones group outside bases_id with
its own fingerprint."""

from __future__ import annotations

import dataclasses
import math
import re

import h5py
import numpy as np
import pytest

from hood_decomp.core.fe.hood_preset import build_hood
from hood_decomp.core.fe.model import skin_surface
from hood_decomp.core.method.bases import build_bases
from hood_decomp.core.types import ToleranceZone
from hood_decomp.errors import BasisError, ModelError
from hood_decomp.io.bases import bases_id, load_bases, save_bases
from hood_decomp.io.model_files import load_model, load_model_with_zones, save_model
from tests.toy_models import full_factorial, make_ensemble, make_reduced_model, make_skin

ZONES = """tolerance_zones:
  - name: front_edge
    box: {min: [1100.0, -800.0, -10.0], max: [1300.0, 800.0, 400.0]}
    lower_mm: -0.3
    upper_mm: 0.5
  - name: centre
    sphere: {center: [600.0, 0.0, 190.0], radius: 250.0}
    box: {min: [0.0, 0.0, -10.0], max: [2000.0, 1000.0, 400.0]}
    lower_mm: -1.0
    upper_mm: 1.0
    min_coverage: 0.8
"""


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    directory = tmp_path_factory.mktemp("zoned_model")
    save_model(build_hood(grid=(20, 20)), directory)
    return directory


def _with(model_dir, tmp_path, text: str):
    """A copy of the model whose model.yaml ends with ``text``."""
    (tmp_path / "mesh.vtu").write_bytes((model_dir / "mesh.vtu").read_bytes())
    (tmp_path / "model.yaml").write_text((model_dir / "model.yaml").read_text() + text)
    return tmp_path


def test_zones_select_the_skin_nodes_of_their_region(model_dir, tmp_path):
    """Fails if a zone's nodes are not the skin nodes inside its box (and sphere) as computed here from the skin's
    coordinates, if limits or min_coverage (default 0.5) are lost, or if zones change the model (model_id)."""
    model, zones = load_model_with_zones(_with(model_dir, tmp_path, ZONES))
    points = skin_surface(model).points
    front = [i for i, (x, _, _) in enumerate(points) if 1100.0 <= x <= 1300.0]
    centre = [i for i, (x, y, z) in enumerate(points)
              if y >= 0.0 and math.dist((x, y, z), (600.0, 0.0, 190.0)) <= 250.0]
    assert [z.name for z in zones] == ["front_edge", "centre"]
    assert zones[0].nodes.tolist() == front and zones[1].nodes.tolist() == centre and len(centre) > 3
    assert (zones[0].lower_mm, zones[0].upper_mm, zones[0].min_coverage) == (-0.3, 0.5, 0.5)
    assert zones[1].min_coverage == 0.8
    assert model.model_id == load_model(model_dir).model_id


@pytest.mark.parametrize(("entry", "message"), [
    ("{name: a, box: {min: [0, 0, 0], max: [9000, 9000, 9000]}, lower_mm: -1, uper_mm: 1}", "did you mean 'upper_mm'"),
    ("{name: a, box: {min: [0, 0, 0], max: [9000, 9000, 9000]}, lower_mm: 1, upper_mm: 1}", "lower_mm < upper_mm"),
    ("{name: a, box: {min: [0, 0, 0], max: [9000, 9000, 9000]}, lower_mm: .nan, upper_mm: 1}", "finite"),
    ("{name: a, box: {min: [0, 0, 0], max: [9000, 9000, 9000]}, lower_mm: -1, upper_mm: 1, min_coverage: 2}", "0..1"),
    ("{name: a, box: {min: [0, 0, 0], max: [9000.0, 9000.0]}, lower_mm: -1, upper_mm: 1}", "list of 3 numbers"),
    ("{name: a, sphere: {center: [0, 0, 0], radius: -5}, lower_mm: -1, upper_mm: 1}", "radius: expected > 0"),
    ("{name: a, lower_mm: -1, upper_mm: 1}", "'box' and/or 'sphere'"),
    ("{name: far_away, sphere: {center: [0, 0, 5000], radius: 10}, lower_mm: -1, upper_mm: 1}",
     "'far_away': its region holds no node of the visible skin"),
    ("{name: a, sphere: {centre: [0, 0, 0], radius: 10}, lower_mm: -1, upper_mm: 1}", "did you mean 'center'"),
])
def test_a_bad_zone_is_refused_naming_it(model_dir, tmp_path, entry, message):
    """Fails if a zone entry with a misspelt key, limits out of order, a non-finite number, a coverage beyond 1, a
    short coordinate list, a negative radius, no region, or a region that holds no skin node is accepted, or refused
    without naming the problem (a typo must not make a zone that is always OK)."""
    with pytest.raises(ModelError, match=re.escape(message)):
        load_model(_with(model_dir, tmp_path, f"tolerance_zones:\n  - {entry}\n"))


def test_two_zones_of_one_name_are_refused(model_dir, tmp_path):
    """Fails if two zones share a name (their verdicts could not be told apart)."""
    entry = "  - {name: a, sphere: {center: [600, 0, 190], radius: 300}, lower_mm: -1, upper_mm: 1}\n"
    with pytest.raises(ModelError, match="unique"):
        load_model(_with(model_dir, tmp_path, "tolerance_zones:\n" + entry + entry))


@pytest.fixture(scope="module")
def toy_bases():
    skin = make_skin(12, 8)
    model = make_reduced_model(skin, seed=2)
    states, rank = full_factorial(6)
    return build_bases(make_ensemble(model, states, rank), skin, model, n_components=6, epsilon=0.05)


def test_zones_round_trip_outside_bases_id_and_an_edit_is_refused(toy_bases, tmp_path):
    """Fails if the zones do not come back as written, if they change bases_id (they are acceptance criteria, not
    the model: a history keyed by bases_id must not split), if a file with zones is readable as version 3 (an older
    reader would ignore its zones), or if an edited limit or a zone taken from other bases loads."""
    zones = (ToleranceZone("left", np.array([0, 3, 5]), -0.2, 0.4, 0.5, '{"box": {}}'),
             ToleranceZone("right", np.array([90, 95]), -1.0, 1.0, 1.0, '{"sphere": {}}'))
    zoned = dataclasses.replace(toy_bases, tolerance_zones=zones)
    path = tmp_path / "zoned.h5"
    save_bases(path, zoned, scan_skin=False)
    loaded = load_bases(path)
    assert bases_id(loaded) == bases_id(toy_bases)
    assert [(z.name, z.nodes.tolist(), z.lower_mm, z.upper_mm, z.min_coverage, z.region)
            for z in loaded.tolerance_zones] == [(z.name, z.nodes.tolist(), z.lower_mm, z.upper_mm, z.min_coverage,
                                                  z.region) for z in zones]
    with h5py.File(path) as h5:
        assert h5.attrs["schema_version"] == 4
    plain = tmp_path / "plain.h5"
    save_bases(plain, toy_bases, scan_skin=False)
    assert load_bases(plain).tolerance_zones == ()

    with h5py.File(path, "r+") as h5:
        h5["tolerance_zones/upper_mm"][0] = 4.0
    with pytest.raises(BasisError, match="zones_id"):
        load_bases(path)

    other = dataclasses.replace(toy_bases, calibration='{"id": "x"}')  # another bases_id
    save_bases(path, dataclasses.replace(other, tolerance_zones=zones), scan_skin=False)
    with h5py.File(path, "r") as source, h5py.File(plain, "r+") as target:
        source.copy("tolerance_zones", target)
    with pytest.raises(BasisError, match="zones_id"):
        load_bases(plain)


def test_calibration_keeps_the_zones(toy_bases):
    """Fails if bases rebuilt by calibration (`hood-decomp calibrate`) drop the tolerance zones of the bases they
    were made from (a calibrated cell would silently stop judging its acceptance criteria)."""
    from hood_decomp.core.loop.calibration import rebuild_bases

    zones = (ToleranceZone("left", np.array([0, 3, 5]), -0.2, 0.4, 0.5, "{}"),)
    rebuilt = rebuild_bases(dataclasses.replace(toy_bases, tolerance_zones=zones), toy_bases.reduced_model, '{"id": 1}')
    assert [z.name for z in rebuilt.tolerance_zones] == ["left"]
    assert rebuilt.tolerance_zones[0].nodes.tolist() == [0, 3, 5]
