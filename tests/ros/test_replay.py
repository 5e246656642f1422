"""Every bag of bags/ replayed with `hood-decomp replay --bases` through the three real nodes (separate processes,
Fast DDS on loopback), the recorded output decoded with rosbags and checked against the bag's sidecar truth."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest

from tests.required import require_import

require_import("hood_decomp_msgs.msg", "colcon build", "run inside scripts/with-env after scripts/setup.sh")
from hood_decomp.cli import main
from hood_decomp.core.method.decomposition import DEFAULT_ZERO_TOL_MM
from hood_decomp.io.bags import read_bag, read_sidecar, typestore

pytestmark = pytest.mark.ros

BAGS = pathlib.Path(__file__).parents[2] / "bags"
# Largest error (mm) of an estimated boundary in contact, per scenario. The scan-derived field carries a spatially
# correlated smoothing error (about 0.0015 mm RMS at default resolution) that the weakly observable HINGE_X turns
# into up to ~0.035 mm on clean scans; the stated std does not cover it (see the issue notes).
TOLERANCE_MM = {"clean": 0.05, "noisy_occluded": 0.1, "malformed": 0.05}


def decoded(record_dir: pathlib.Path, topic: str) -> list:
    store = typestore()
    return [store.deserialize_cdr(r.data, r.msgtype) for r in read_bag(record_dir, topics=[topic])]


def stamp(msg) -> str:
    return f"{msg.header.stamp.sec}.{msg.header.stamp.nanosec:09d}"


@pytest.mark.parametrize("name", ["clean", "noisy_occluded", "undeclared", "malformed"])
def test_replay_bag(name, default_hood, tmp_path):
    bag = BAGS / name
    sidecar = read_sidecar(bag)
    assert sidecar["model"]["model_id"] == default_hood.model.model_id, \
        "bags/ are stale for the current hood model: rebuild them with scripts/make_bags.py"
    # Through the command line as a user runs it: the nodes take the cell calibration from the bag's sidecar (the
    # issue: without it all three clean scans were refused, and replay exited 0). Pairing must never time out here:
    # an unpaired field skips paper step 3 (checked below).
    params = tmp_path / "params.yaml"
    params.write_text("hood_decomp_decomposition:\n  ros__parameters:\n    pair_timeout_s: 30.0\n")
    status = main(["replay", str(bag), "--bases", str(default_hood.bases_path), "--params", str(params),
                   "--record", str(tmp_path / "out"), "--json", str(tmp_path / "summary.json")])
    result = json.loads((tmp_path / "summary.json").read_text())
    scans = sidecar["scans"]
    good = [s for s in scans if s["kind"] == "good"]
    bad = [s for s in scans if s["kind"] != "good"]
    assert result["scans"] == len(scans) and not result["unanswered"]
    assert status == (1 if bad else 0)  # a refused scan is a non-zero exit
    assert set(result["refused"]) == {s["stamp"] for s in bad}, result["refused"]

    # Count in equals count out: one boundary state, one correction and one effect set per good scan.
    states = {stamp(m): m for m in decoded(tmp_path / "out", "hood_decomp/boundary_state")}
    effects = {stamp(m): m for m in decoded(tmp_path / "out", "hood_decomp/effects")}
    corrections = {stamp(m): m for m in decoded(tmp_path / "out", "hood_decomp/boundary_correction")}
    expected = {s["stamp"] for s in good}
    assert set(states) == expected and set(effects) == expected and set(corrections) == expected
    assert len(decoded(tmp_path / "out", "hood_decomp/boundary_state")) == len(good)

    # Each malformed cloud is answered on /diagnostics with its stamp and a message naming the problem.
    refused = result["refused"]
    words = {"no_xyz": "no field", "size_mismatch": "row_step * height", "int16_x": "INT16", "empty": "empty",
             "all_nan": "NaN", "metres_as_mm": "in metres"}
    for scan in bad:
        assert any(words[scan["kind"]] in message for message in refused[scan["stamp"]]), \
            (scan["kind"], refused[scan["stamp"]])

    # Boundary states against the truth that made the scans; the table goes to the test output.
    rows, problems = [], []
    for scan in good:
        state, correction = states[scan["stamp"]], corrections[scan["stamp"]]
        values = dict(zip(state.names, 1000.0 * np.asarray(state.values), strict=True))
        std = dict(zip(state.names, 1000.0 * np.asarray(state.std_dev), strict=True))
        lifted = dict(zip(state.names, state.lifted, strict=True))
        for label, truth in scan["truth_mm"].items():
            rows.append((scan["name"], label, truth, values[label], std[label], bool(lifted[label]),
                         scan["lifted"].get(label, False)))
        if scan["undeclared_mm"]:
            if state.within_model:
                problems.append(f"{scan['name']}: the undeclared effect went unnoticed")
            if correction.safe_to_apply or "lacks an effect" not in correction.reason:
                problems.append(f"{scan['name']}: correction not held back: {correction.reason!r}")
            continue
        if not state.within_model:
            problems.append(f"{scan['name']}: residual {1000 * state.residual_rms:.4f} mm RMS called outside the model")
        for label, truth in scan["truth_mm"].items():
            # A buffer reported lifted (truly lifted, or touching too lightly to tell) is reported with the highest
            # commanded position the field allows: the truth must not lie above it.
            if lifted[label]:
                if truth > values[label] + 0.05:
                    problems.append(f"{scan['name']}: {label} reported lifted at {values[label]:.4f} mm, but the "
                                    f"commanded {truth} mm lies above")
            elif scan["lifted"].get(label, False):
                problems.append(f"{scan['name']}: {label} lifted in truth, reported in contact at {values[label]:.4f}")
            elif abs(values[label] - truth) > TOLERANCE_MM[name]:
                problems.append(f"{scan['name']}: {label} estimated {values[label]:.4f} mm, truth {truth:.4f} mm")
    # Effects against the truth and the state of the same stamp (paper step 3): every boundary set by at least 0.3 mm
    # and in contact has its effect; a boundary its state calls zero has none; every field met its state.
    paired = [kv.value for array in decoded(tmp_path / "out", "/diagnostics") for s in array.status
              if s.name == "hood_decomp/hood_decomp_decomposition" for kv in s.values
              if kv.key == "paired_with_boundary_state"]
    assert paired == ["True"] * len(good), paired
    for scan in good:
        state, names = states[scan["stamp"]], {e.name for e in effects[scan["stamp"]].effects}
        present = {label for label, truth in scan["truth_mm"].items()
                   if abs(truth) >= 0.3 and not scan["lifted"].get(label, False)}
        zero = {label for label, value, std, lifted in zip(state.names, state.values, state.std_dev, state.lifted,
                                                           strict=True)
                if not lifted and abs(1000.0 * value) <= max(DEFAULT_ZERO_TOL_MM, 3000.0 * std)}
        if not {"LOADS"} | present <= names:
            problems.append(f"{scan['name']}: effects {sorted(names)} lack {sorted({'LOADS'} | present - names)}")
        if names & zero:
            problems.append(f"{scan['name']}: effects {sorted(names & zero)} kept though their state is zero")
    print(f"\n{name}: scan, parameter, truth mm, estimate mm, std mm, reported lifted, lifted in truth")
    for row in rows:
        print(f"  {row[0]:18s} {row[1]:9s} {row[2]:8.4f} {row[3]:9.4f} {row[4]:8.4f} {row[5]!s:6s} {row[6]}")
    assert not problems, "\n".join(problems)
