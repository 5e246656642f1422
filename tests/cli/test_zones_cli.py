"""Tolerance zones on the command line: model.yaml -> `hood-decomp bases --model` -> `hood-decomp estimate --json`,
judged against the field file read here with meshio and the zone's nodes picked here from the skin coordinates."""

from __future__ import annotations

import json
import shutil

import meshio
import numpy as np

from hood_decomp.cli import main
from hood_decomp.io.bases import load_bases

ZONES = """tolerance_zones:
  - name: lock_side
    box: {min: [900.0, -800.0, -50.0], max: [1300.0, 800.0, 400.0]}
    lower_mm: -0.05
    upper_mm: 0.05
  - name: everywhere
    sphere: {center: [600.0, 0.0, 100.0], radius: 5000.0}
    lower_mm: -10.0
    upper_mm: 10.0
"""


def test_zones_from_model_yaml_reach_the_estimate_json(tiny_workspace, tmp_path, capsys):
    """Fails if `bases --model` does not carry model.yaml's zones into the bases file, or if `estimate --json` does
    not judge them on the field: the out-of-tolerance zone NOK with the worst deviation and node computed here from
    the field file, the wide zone OK, zones_ok false."""
    model = tmp_path / "model"
    shutil.copytree(tiny_workspace.model, model)
    (model / "model.yaml").write_text((model / "model.yaml").read_text() + ZONES)
    bases = tmp_path / "zoned.h5"
    assert main(["bases", "--ensemble", str(tiny_workspace.ensemble), "--model", str(model),
                 "--out", str(bases)]) == 0
    assert "2 tolerance zone(s)" in capsys.readouterr().out
    loaded = load_bases(bases)
    assert [zone.name for zone in loaded.tolerance_zones] == ["lock_side", "everywhere"]
    out = tmp_path / "estimate.json"
    assert main(["estimate", "--bases", str(bases), "--field", str(tiny_workspace.field), "--json", str(out)]) == 0
    payload = json.loads(out.read_text())

    field = meshio.read(tiny_workspace.field)
    values = np.asarray(field.point_data["normal_displacement"], dtype=float)
    points = loaded.skin.points
    inside = np.flatnonzero((points[:, 0] >= 900.0) & (points[:, 0] <= 1300.0))
    excess = np.maximum(-0.05 - values[inside], values[inside] - 0.05)
    worst = int(np.argmax(excess))
    lock_side, everywhere = payload["zones"]
    assert lock_side["name"] == "lock_side" and not lock_side["ok"] and excess[worst] > 0
    assert lock_side["worst_node"] == int(inside[worst])
    assert abs(lock_side["worst_deviation_mm"] - values[inside][worst]) < 1e-9
    assert lock_side["outside"] == int(np.count_nonzero(excess > 0)) and lock_side["coverage"] == 1.0
    assert everywhere["ok"] and not payload["zones_ok"]
