"""A measured effect is a parameter without a boundary, everywhere an estimate leaves the system: bases rebuilt with
the generator's bump as a measured effect (20 x 20 hood) carry its name through their file, every estimate flags
it, the `estimate` verb and the estimator node (real rclpy + Fast DDS) report its amplitude against the generator's
truth, and no correction ever moves anything for it. The same node writes its live results history (a real SQLite
file) and loses no part to a bad path or a locked database."""

from __future__ import annotations

import functools
import hashlib
import json
import sqlite3
import subprocess
import sys

import h5py
import numpy as np
import pytest

from hood_decomp.core.loop.measured_effects import FoundMode, augmented_bases
from hood_decomp.core.method.bases import estimate_field
from hood_decomp.core.method.correction import plan_correction
from hood_decomp.errors import BasisError
from hood_decomp.io.bases import load_bases, save_bases
from hood_decomp.synthetic.shift import ProcessModel, bump_field, make_part, plan_shift
from tests.hood20 import hood20

NAME = "measured_1"


@functools.cache
def _case():
    """Bases rebuilt with the generator's own bump (its true shape, not a learned one) as a measured effect, and
    parts that carry the bump (amplitudes 0.05-0.2 mm), declared states drawn by the process model."""
    case = hood20()
    process = ProcessModel(candidate_share=0.0, bump_share=1.0, drift_label=None, step_label=None)
    truth = bump_field(case.skin, process.bump_center, process.bump_radius_mm)
    amplitude = np.array([-0.2, 0.1, 0.2])
    mode = FoundMode("measured", NAME, truth, truth / np.linalg.norm(truth), truth, np.ones(3, bool), amplitude,
                     np.full(3, 0.01), 0.0, (), 0.0, 0, 0, np.zeros(3, bool), np.zeros(0), np.zeros(0), np.zeros(0),
                     np.full((3, len(case.bases.names)), np.nan))
    rebuilt = augmented_bases(case.bases, case.ensemble, (mode,))
    plan = plan_shift(case.reduced.names, process, 6, seed=3)
    parts = [make_part(plan, i, case.truth_model, case.skin) for i in range(6)]
    return case, rebuilt, plan, parts


@pytest.fixture(scope="module")
def measured_bases(tmp_path_factory):
    rebuilt = _case()[1]
    path = tmp_path_factory.mktemp("measured") / "bases_measured.h5"
    save_bases(path, rebuilt, scan_skin=False)
    return path


def _check_state(names, values, std, plan, i):
    """The measured effect's amplitude against the generator's truth (3 std + 5 um of basis error)."""
    column = list(names).index(NAME)
    assert abs(values[column] - plan.amplitude[i]) <= 3 * std[column] + 0.005, (values[column], plan.amplitude[i])
    return column


def test_plan_correction_never_moves_a_measured_effect():
    """Fails if the rebuilt bases do not name the measured effect, if an estimate does not flag it (and only it), if
    its amplitude misses the truth, or if plan_correction (the one correction of the nodes, the verbs and the shift)
    moves anything for it or calls it applicable, or stops correcting the boundaries."""
    case, rebuilt, plan, parts = _case()
    assert rebuilt.measured_effects == (NAME,) and NAME in rebuilt.names
    estimate = estimate_field(rebuilt, parts[0].field)
    column = _check_state(estimate.names, estimate.values, estimate.std, plan, 0)
    assert abs(estimate.values[column]) > 0.04  # the bump is there: a correction without the filter would move it
    assert list(estimate.measured_effect) == [name == NAME for name in estimate.names]
    correction = plan_correction(estimate)
    assert correction.corrections[column] == 0.0 and not correction.applicable[column]
    assert correction.measured_effect[column] and f"{NAME} is a measured effect: no boundary to move" in \
        correction.reason
    boundary = estimate.boundary & ~estimate.lifted
    np.testing.assert_array_equal(correction.corrections[boundary], -estimate.values[boundary])
    # bases without a measured effect flag nothing
    assert estimate_field(case.bases, parts[0].field).measured_effect is None


def test_bases_file_keeps_the_measured_effect(measured_bases, tmp_path):
    """Fails if the bases file loses the measured effect's name, is written with a schema version an older reader
    would accept (it would correct the effect), or if a file whose measured effects were stripped or renamed is
    read."""
    assert load_bases(measured_bases).measured_effects == (NAME,)
    with h5py.File(measured_bases) as h5:
        assert h5.attrs["schema_version"] == 4
    assert load_bases(hood20().bases_path).measured_effects == ()
    stripped = tmp_path / "stripped.h5"
    stripped.write_bytes(measured_bases.read_bytes())
    with h5py.File(stripped, "r+") as h5:
        del h5["parameters/measured_effects"]
        h5.attrs["schema_version"] = 3
    with pytest.raises(BasisError, match="bases_id"):
        load_bases(stripped)
    renamed = tmp_path / "renamed.h5"
    renamed.write_bytes(measured_bases.read_bytes())
    with h5py.File(renamed, "r+") as h5:
        del h5["parameters/measured_effects"]
        h5.create_dataset("parameters/measured_effects", data=np.array(["BUFFER_L"], dtype=object),
                          dtype=h5py.string_dtype())
    with pytest.raises(BasisError, match="measured_effects"):
        load_bases(renamed)


def test_estimate_verb_reports_the_amplitude_and_no_move(measured_bases, tmp_path):
    """Fails if `hood-decomp estimate` on the rebuilt bases does not list the measured effect, misses its amplitude,
    or its correction block moves it or calls it applicable."""
    from hood_decomp.io.fields import write_field

    case, _, plan, parts = _case()
    write_field(tmp_path / "part.vtu", case.skin, parts[1].field)
    out = tmp_path / "estimate.json"
    run = subprocess.run([sys.executable, "-m", "hood_decomp.cli", "estimate", "--bases", str(measured_bases),
                          "--field", str(tmp_path / "part.vtu"), "--json", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    payload = json.loads(out.read_text())
    assert payload["measured_effects"] == [NAME]
    names = list(payload["parameters_mm"])
    _check_state(names, [payload["parameters_mm"][n] for n in names], [payload["std_mm"][n] for n in names],
                 plan, 1)
    assert payload["correction"]["corrections_mm"][NAME] == 0.0
    assert payload["correction"]["applicable"][NAME] is False
    assert f"{NAME} is a measured effect" in payload["correction"]["reason"]


# --- the estimator node ------------------------------------------------------------------------------------------
def test_history_and_shift_report_show_the_measured_effect(tmp_path):
    """Fails if parts estimated with the rebuilt bases (every part carrying the bump) lose the measured effect's
    flag on their way into a real SQLite history (the shift's and the node's one record path, inspection_record), if
    a boundary is flagged, or if the shift analysis and report do not chart the effect's amplitude as a measured
    effect (JSON flag, table kind, caption) while giving it a capability against a tolerance range it does not
    have, or stop doing so for the boundaries."""
    from hood_decomp.io.history import History, PartRecord, inspection_record
    from hood_decomp.shift.analysis import analyse_shift, analysis_json
    from hood_decomp.shift.part import Options, inspect_field
    from hood_decomp.shift.report import build_report
    from hood_decomp.shift.runner import BatchSummary

    case, rebuilt, _, _ = _case()
    process = ProcessModel(candidate_share=0.0, bump_share=1.0, drift_label=None, step_label=None)
    n = 30
    plan = plan_shift(case.reduced.names, process, n, seed=11)
    with History(tmp_path / "h.sqlite") as history:
        for i in range(n):
            estimate, analysis, correction, decomposition = inspect_field(
                rebuilt, make_part(plan, i, case.truth_model, case.skin).field, Options())
            history.add(inspection_record(
                PartRecord(source="shift", part_id=f"P{i}", message=i, stamp_ns=i), estimate, analysis, correction,
                tuple((e.name, float(e.share)) for e in decomposition.effects), keep_residual=False))
        analysis = analyse_shift(history, ["shift"], rebuilt, baseline=10)
    with sqlite3.connect(tmp_path / "h.sqlite") as db:
        flagged = db.execute("SELECT DISTINCT name, COUNT(*) FROM parameters WHERE measured_effect = 1").fetchall()
    assert flagged == [(NAME, n)]
    assert analysis.table.measured_effect.tolist() == [name == NAME for name in analysis.table.names]
    charted = {chart.name for chart in analysis.charts}
    assert NAME in charted and len(charted) >= 4, charted
    assert {c.name for c in analysis.capabilities} == charted - {NAME}
    numbers = analysis_json(analysis, BatchSummary(n, 0, n, (), 1.0, 1))
    assert numbers["measured_effects"] == [NAME]
    assert {name: b["measured_effect"] for name, b in numbers["boundaries"].items()} == {
        name: name == NAME for name in charted}
    page = build_report(analysis, rebuilt, BatchSummary(n, 0, n, (), 1.0, 1), tmp_path).write(tmp_path / "i.html")
    text = page.read_text()
    assert f"<td>{NAME}</td><td>measured effect</td>" in text and f"{NAME} (measured effect)" in text
    assert "<td>HINGE_Y</td><td>boundary</td>" in text or "HINGE_Y" not in charted
    assert f"Measured effects ({NAME}) have no boundary" in text


@pytest.fixture(scope="module")
def node(measured_bases, tmp_path_factory):
    from tests.required import require_import

    require_import("hood_decomp_msgs.msg", "colcon build", "run inside scripts/with-env after scripts/setup.sh")
    from diagnostic_msgs.msg import DiagnosticArray
    from hood_decomp_msgs.msg import BoundaryCorrection, BoundaryState, DisplacementField

    from hood_decomp.ros.launcher import start_nodes, stop_nodes
    from hood_decomp.ros.participant import Participant, latest_heartbeat

    root = tmp_path_factory.mktemp("live")
    bad = root / "a_directory.sqlite"
    bad.mkdir()  # a path that is no file: the history cannot be opened
    processes = start_nodes(measured_bases, nodes=("estimator_node",), extra_params=[f"history:={bad}"],
                            log_dir=root)
    peer = Participant("test_measured_node")
    received = {topic: peer.collect(topic, cls) for topic, cls in (
        ("hood_decomp/boundary_state", BoundaryState), ("hood_decomp/boundary_correction", BoundaryCorrection),
        ("/diagnostics", DiagnosticArray))}
    peer.publisher("hood_decomp/displacement", DisplacementField)
    connected = peer.connected(["hood_decomp/displacement"], ["hood_decomp/boundary_state"], 60.0) and peer.wait(
        lambda: int(latest_heartbeat(received["/diagnostics"], "hood_decomp_estimator").get(
            "publishers /hood_decomp/displacement", 0)) >= 1, 30.0)
    yield peer, received, processes, connected, root, measured_bases
    peer.close()
    stop_nodes(processes)


def _send(peer, i: int) -> None:
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header

    from hood_decomp.ros import messages

    _, _, _, parts = _case()
    header = Header(frame_id="hood", stamp=Time(sec=100 + i, nanosec=0))
    peer.publishers["hood_decomp/displacement"].publish(messages.field_to_msg(parts[i].field, header, f"P-{i}"))


def _history_errors(received) -> list[str]:
    from diagnostic_msgs.msg import DiagnosticStatus

    return [s.message for array in received["/diagnostics"] for s in array.status
            if s.level == DiagnosticStatus.ERROR and "history" in s.message]


def _rows(path) -> dict[str, dict[str, tuple[float, float, int]]]:
    """part_id -> parameter -> (value_mm, correction_mm, measured_effect) of the history at ``path``."""
    db = sqlite3.connect(path, timeout=5)
    try:
        rows = db.execute("SELECT p.part_id, q.name, q.value_mm, q.correction_mm, q.measured_effect FROM parts p "
                          "JOIN parameters q ON q.part = p.id").fetchall()
    finally:
        db.close()
    out: dict[str, dict[str, tuple[float, float, int]]] = {}
    for part, name, value, correction, measured in rows:
        out.setdefault(part, {})[name] = (value, correction, measured)
    return out


@pytest.mark.ros
def test_node_flags_the_measured_effect_and_never_moves_it(node):
    """Fails if the estimator node's BoundaryState does not flag the measured effect or misses its amplitude, if its
    BoundaryCorrection moves it, calls it applicable or does not flag it, or if a history path that cannot be opened
    loses the boundary state (the robot's answer must not wait for the history) or goes unreported on
    /diagnostics."""
    peer, received, processes, connected, root, _ = node
    assert connected, f"node did not come up; logs in {root}"
    _, _, plan, _ = _case()
    _send(peer, 2)
    states, corrections = received["hood_decomp/boundary_state"], received["hood_decomp/boundary_correction"]
    assert peer.wait(lambda: states and corrections and _history_errors(received), 60.0), \
        (len(states), len(corrections), _history_errors(received))
    state, correction = states[-1], corrections[-1]
    assert list(state.measured_effect) == [name == NAME for name in state.names]
    values_mm, std_mm = np.array(state.values) * 1e3, np.array(state.std_dev) * 1e3
    column = _check_state(state.names, values_mm, std_mm, plan, 2)
    assert list(correction.names) == list(state.names) and correction.measured_effect[column]
    assert correction.corrections[column] == 0.0 and not correction.applicable[column]
    moved = np.array(correction.corrections) != 0.0
    assert moved.sum() >= 3  # the boundaries are still corrected
    assert "not a file" in _history_errors(received)[-1] and "1 parts pending" in _history_errors(received)[-1]
    assert all(p.poll() is None for p in processes), "the node died"


@pytest.mark.ros
def test_live_history_survives_a_bad_path_and_a_lock(node):
    """Fails if the node does not write its estimates to the SQLite history named by its parameter (values and the
    zero move of the measured effect as published, the bases file's fingerprint), if the part that arrived while
    the path was bad is lost once a good path is set, or if a locked database loses a part (or the boundary state
    of it) instead of reporting it and writing it when the lock is gone, or if the history does not flag the
    measured effect (and only it) as one."""
    from tests.ros.test_lifecycle import set_parameter

    peer, received, processes, connected, root, bases_path = node
    assert connected, f"node did not come up; logs in {root}"
    states = received["hood_decomp/boundary_state"]
    db = root / "live.sqlite"
    assert set_parameter(peer, "estimator_node", "history", str(db)) == (True, "")
    _send(peer, 3)
    assert peer.wait(lambda: db.exists() and set(_rows(db)) == {"P-2", "P-3"}, 60.0), _rows(db) if db.exists() \
        else "no database"
    rows = _rows(db)
    last = next(s for s in states if s.part_id == "P-3")
    for name, value in zip(last.names, last.values, strict=True):
        assert rows["P-3"][name][0] == pytest.approx(value * 1e3, abs=1e-9)
    assert rows["P-2"][NAME][1] == 0.0 and rows["P-3"][NAME][1] == 0.0
    assert {name: row[2] for name, row in rows["P-3"].items()} == {name: int(name == NAME) for name in last.names}
    fingerprint = hashlib.sha256(bases_path.read_bytes()).hexdigest()[:16]
    with sqlite3.connect(db) as check:
        assert {r[0] for r in check.execute("SELECT bases_id FROM parts")} == {fingerprint}

    errors_before = len(_history_errors(received))
    lock = sqlite3.connect(db, timeout=5, isolation_level=None)
    lock.execute("BEGIN EXCLUSIVE")
    try:
        _send(peer, 4)
        assert peer.wait(lambda: any(s.part_id == "P-4" for s in states)
                         and len(_history_errors(received)) > errors_before, 60.0)
        assert "locked" in _history_errors(received)[-1]
    finally:
        lock.execute("COMMIT")
        lock.close()
    _send(peer, 5)
    assert peer.wait(lambda: set(_rows(db)) == {"P-2", "P-3", "P-4", "P-5"}, 60.0), sorted(_rows(db))
    assert all(p.poll() is None for p in processes), "the node died"
