"""Issue 16 on the nodes, as real processes on the real middleware (Fast DDS, loopback, a per-run domain): a reference
per cell (the ``reference`` parameter) and per part (the ``set_reference`` service) on the estimator and the
decomposition node, refused references that leave the node serving, and calibrated bases (made by
``hood-decomp calibrate``) swapped in through lifecycle transitions, reported on /diagnostics; bases without the
reduced model a reference needs refuse one.

The "real part" has a static model error the FE model lacks: a smooth springback-like shape added to the model's own
field (made by the FE model at the part's state, not by the code under test). A reference of the part at a known
state cancels it. One set of two node processes serves the module; each test continues from the state the previous
one left, in file order."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace

import h5py
import numpy as np
import pytest

from tests.required import require_import

require_import("hood_decomp_msgs.msg", "colcon build", "run inside scripts/with-env after scripts/setup.sh")
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from hood_decomp_msgs.msg import BoundaryState, DisplacementField, EffectFields, MoveVerification
from hood_decomp_msgs.srv import SetReference
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.parameter import Parameter
from std_msgs.msg import Header

from hood_decomp.core.fe.ensemble import solve_members
from hood_decomp.core.loop.calibration import one_at_a_time
from hood_decomp.core.types import DisplacementField as CoreField
from hood_decomp.io.fields import write_field
from hood_decomp.ros import messages
from hood_decomp.ros.launcher import NODE_NAMES, start_nodes, stop_nodes
from hood_decomp.ros.participant import Participant, latest_heartbeat

pytestmark = pytest.mark.ros

NODES = ("estimator_node", "decomposition_node")
STATE = np.array([0.4, -0.3, 0.5, -0.2, 0.3, 0.6])  # mm, inside the ranges, between the sample points
REFERENCE_SETTING = {"HINGE_X": 0.3}  # the reference part's known state (other parameters 0 mm)
FOREIGN_MODEL = "0123456789abcdef"


def static_errors(skin) -> tuple[np.ndarray, np.ndarray]:
    """Two smooth static model errors (N,) mm (what a springback shape or a load case the model gets wrong leaves),
    from the skin's node coordinates: the cell's and one part's own."""
    unit = (skin.points - skin.points.min(axis=0)) / np.ptp(skin.points, axis=0)
    cell = 0.1 * np.sin(np.pi * unit[:, 0]) * np.cos(np.pi * unit[:, 1])
    part = 0.08 * np.cos(np.pi * unit[:, 0]) * np.sin(2.0 * np.pi * unit[:, 1])
    return cell, part


def write_reference(directory, skin, values: np.ndarray, name: str, model_id: str) -> str:
    """A REF.json in ``directory`` naming a field file of ``values`` (N,) mm at REFERENCE_SETTING."""
    directory.mkdir(parents=True, exist_ok=True)
    write_field(directory / f"{name}.vtu", skin, CoreField(model_id, values, 1.0, np.nan))
    (directory / f"{name}.json").write_text(json.dumps({"field": f"{name}.vtu", "setting": REFERENCE_SETTING}))
    return str(directory / f"{name}.json")


def write_calibration(directory, coarse_hood, truth) -> None:
    """13 entries (the reference and +-0.8 mm of each parameter alone) of the part ``truth`` (a reduced model with
    other physics than the bases') with 0.005 mm noise, the model directory and CAL.json for `hood-decomp calibrate`."""
    from hood_decomp.io.model_files import save_model

    save_model(coarse_hood.model, directory / "model")
    names = coarse_hood.reduced.names
    settings = one_at_a_time(len(names))
    fields = solve_members(truth, settings).normal_displacement
    rng = np.random.default_rng(16)
    entries = []
    for j, setting in enumerate(settings):
        values = fields[j] + rng.normal(0.0, 0.005, fields[j].shape)
        write_field(directory / f"entry{j}.vtu", coarse_hood.skin,
                    CoreField(coarse_hood.reduced.model_id, values, 1.0, 0.005))
        entries.append({"field": f"entry{j}.vtu", "setting": dict(zip(names, map(float, setting), strict=True))})
    (directory / "cal.json").write_text(json.dumps(entries))


@pytest.fixture(scope="module")
def cell(coarse_hood, tmp_path_factory):
    """The estimator and decomposition nodes on the uncalibrated coarse bases, no reference; the files the tests give
    them; a peer that hears their outputs and /diagnostics and publishes fields."""
    root = tmp_path_factory.mktemp("references")
    skin, reduced, model_id = coarse_hood.skin, coarse_hood.reduced, coarse_hood.bases.model_id
    cell_error, part_error = static_errors(skin)
    setting = np.array([REFERENCE_SETTING.get(name, 0.0) for name in reduced.names])
    at_reference = solve_members(reduced, setting[None]).normal_displacement[0]
    files = {
        "cell": write_reference(root / "cell", skin, at_reference + cell_error, "ref", model_id),
        "part": write_reference(root / "part", skin, at_reference + part_error, "ref", model_id),
        # a reference of another part model (another model_id on the same mesh)
        "foreign": write_reference(root / "foreign", replace(skin, model_id=FOREIGN_MODEL), at_reference, "ref",
                                   FOREIGN_MODEL),
    }
    (root / "secret.vtu").write_bytes((root / "cell" / "ref.vtu").read_bytes())
    (root / "cell" / "escape.json").write_text(json.dumps({"field": "../secret.vtu", "setting": {}}))
    files["escape"] = str(root / "cell" / "escape.json")
    os.mkfifo(root / "fifo.json")  # no writer ever: a reader that opens it blocks
    files["fifo"], files["zero"] = str(root / "fifo.json"), "/dev/zero"
    files["relative"], files["long"] = "cell/ref.json", "/" + "x" * 1100
    logs = root / "logs"
    logs.mkdir()
    processes = start_nodes(coarse_hood.bases_path, nodes=NODES, extra_params=["pair_timeout_s:=30.0"], log_dir=logs)
    peer = Participant("test_references", depth=1000)
    received = {topic: peer.collect(topic, cls) for topic, cls in (
        ("hood_decomp/boundary_state", BoundaryState), ("hood_decomp/effects", EffectFields),
        ("hood_decomp/move_verification", MoveVerification), ("/diagnostics", DiagnosticArray))}
    peer.publisher("hood_decomp/displacement", DisplacementField)
    connected = peer.connected(["hood_decomp/displacement"], ["hood_decomp/boundary_state", "hood_decomp/effects"],
                               60.0, subscribers=2) and peer.wait(lambda: all(
        int(latest_heartbeat(received["/diagnostics"], NODE_NAMES[node]).get("publishers /hood_decomp/displacement",
                                                                              0)) >= 1 for node in NODES), 30.0)
    assert connected, f"nodes did not come up; logs in {logs}"
    yield {"peer": peer, "received": received, "processes": processes, "files": files, "root": root, "logs": logs,
           "cell_error": cell_error, "part_error": part_error}
    peer.close()
    stop_nodes(processes)


def set_parameter(peer: Participant, node: str, name: str, value) -> tuple[bool, str]:
    request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
    result = peer.call(f"/{NODE_NAMES[node]}/set_parameters", SetParameters, request, 30.0).results[0]
    return result.successful, result.reason


def string_parameter(peer: Participant, node: str, name: str) -> str:
    response = peer.call(f"/{NODE_NAMES[node]}/get_parameters", GetParameters, GetParameters.Request(names=[name]),
                         30.0)
    return response.values[0].string_value


def set_reference(peer: Participant, node: str, part_id: str, path: str) -> tuple[bool, str]:
    request = SetReference.Request(part_id=part_id, variant="", path=path)
    response = peer.call(f"/{NODE_NAMES[node]}/set_reference", SetReference, request, 30.0)
    return response.accepted, response.message


def transition(peer: Participant, node: str, transition_id: int) -> bool:
    request = ChangeState.Request(transition=Transition(id=transition_id))
    return peer.call(f"/{NODE_NAMES[node]}/change_state", ChangeState, request, 90.0).success


def send(cell, coarse_hood, values: np.ndarray, sec: int, part_id: str) -> tuple[BoundaryState, EffectFields]:
    """Publish a field (N,) mm of ``part_id`` with stamp ``sec``; its boundary state and effects."""
    peer, received = cell["peer"], cell["received"]
    field = CoreField(coarse_hood.bases.model_id, values, 1.0, 0.0)
    peer.publishers["hood_decomp/displacement"].publish(
        messages.field_to_msg(field, Header(frame_id="hood", stamp=Time(sec=sec)), part_id))
    states, effects = received["hood_decomp/boundary_state"], received["hood_decomp/effects"]
    answered = peer.wait(lambda: any(s.header.stamp.sec == sec for s in states)
                         and any(e.header.stamp.sec == sec for e in effects), 60.0)
    assert answered, (f"field {sec} not answered; logs in {cell['logs']}",
                      [s.message for a in received["/diagnostics"][-20:] for s in a.status
                       if s.level == DiagnosticStatus.ERROR])
    return (next(s for s in states if s.header.stamp.sec == sec), next(e for e in effects if e.header.stamp.sec == sec))


def error_mm(state: BoundaryState, names, truth_mm: np.ndarray) -> np.ndarray:
    """|estimate - truth| (P,) mm in ``names`` order."""
    index = [list(state.names).index(name) for name in names]
    return np.abs(np.array(state.values)[index] * 1000.0 - truth_mm)


def part_field(coarse_hood, error: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The part at STATE with a static model error (N,) mm: its field and its true effective states (P,) mm."""
    member = solve_members(coarse_hood.reduced, STATE[None])
    return member.normal_displacement[0] + error, member.effective[0]


def test_a_cell_reference_cancels_a_static_model_error(cell, coarse_hood):
    """Fails if the ``reference`` parameter is not used by both nodes from the next field on, or does not cancel a
    static model error: without it the part's estimate is off by more than 0.1 mm (the static error is real), with
    it every parameter must come out within 1e-4 mm of the FE truth (the reference is noise-free: what is left is
    round-off and the messages' float32), and both outputs must name the reference they used."""
    peer, names = cell["peer"], coarse_hood.reduced.names
    values, truth = part_field(coarse_hood, cell["cell_error"])
    state, effects = send(cell, coarse_hood, values, 1, "A-1")
    assert state.reference == "" and effects.reference == ""
    assert error_mm(state, names, truth).max() > 0.1, error_mm(state, names, truth)
    residual_before = np.sqrt(np.nanmean(np.square(effects.residual)))
    for node in NODES:
        assert set_parameter(peer, node, "reference", cell["files"]["cell"]) == (True, "")
    state, effects = send(cell, coarse_hood, values, 2, "A-2")
    assert error_mm(state, names, truth).max() < 1e-4, error_mm(state, names, truth)
    assert state.reference == effects.reference == f"cell:{cell['files']['cell']}"
    # the decomposition node made the field relative too: the static error is gone from its residual
    residual_after = np.sqrt(np.nanmean(np.square(effects.residual)))
    assert residual_after < 0.01 * residual_before, (residual_after, residual_before)
    beats = {node: latest_heartbeat(cell["received"]["/diagnostics"], NODE_NAMES[node]) for node in NODES}
    assert peer.wait(lambda: all(latest_heartbeat(cell["received"]["/diagnostics"], NODE_NAMES[node]).get(
        "reference") == f"cell:{cell['files']['cell']}" for node in NODES), 5.0), beats


def test_a_part_reference_overrides_the_cells_for_that_part_only(cell, coarse_hood):
    """Fails if a part given its own reference (set_reference) is not made relative to it while another part keeps the
    cell's, if an empty path does not give the part the cell's again, or if more parts than ``remembered_references``
    are kept (the oldest must be forgotten, and the answer must say so; a lower bound forgets at once, with a WARN
    naming the parts; more than 1000 is refused), if two parts naming the same unchanged file do not share one read, or
    if the decomposition node does not warn when its reference for a part differs from the estimator's, or if a move is
    verified across a change of the part's reference (estimates relative to different references) or not verified when
    the reference stayed. The part's own static error differs from the cell's: with the cell's reference it is off by
    more than 0.05 mm."""
    peer, names, files = cell["peer"], coarse_hood.reduced.names, cell["files"]
    own, truth = part_field(coarse_hood, cell["part_error"])
    other, _ = part_field(coarse_hood, cell["cell_error"])
    state, _ = send(cell, coarse_hood, own, 10, "P")
    assert state.reference.startswith("cell:") and error_mm(state, names, truth).max() > 0.05
    for node in NODES:
        accepted, message = set_reference(peer, node, "P", files["part"])
        assert accepted and "part P" in message, message
    state, effects = send(cell, coarse_hood, own, 11, "P")
    assert error_mm(state, names, truth).max() < 1e-4, error_mm(state, names, truth)
    assert state.reference == effects.reference == f"part:{files['part']}"
    # P's correction of field 10 was made relative to the cell's reference, field 11 to its own: the two estimates
    # differ by the references' difference, so the move is not verified (no MoveVerification), and the report says so
    assert peer.wait(lambda: any(
        s.level == DiagnosticStatus.WARN and s.name == "hood_decomp/hood_decomp_estimator"
        and "reference changed between inspections" in s.message
        and ("stamp", "11.000000000") in [(kv.key, kv.value) for kv in s.values]
        for a in cell["received"]["/diagnostics"] for s in a.status), 10.0)
    assert not any(v.header.stamp.sec == 11 for v in cell["received"]["hood_decomp/move_verification"])
    state, effects = send(cell, coarse_hood, other, 12, "Q")
    assert error_mm(state, names, truth).max() < 1e-4
    assert state.reference == effects.reference == f"cell:{files['cell']}"
    for node in NODES:
        assert set_reference(peer, node, "P", "") == (True, f"part P forgot its reference {files['part']}")
    state, _ = send(cell, coarse_hood, own, 13, "P")
    assert state.reference == f"cell:{files['cell']}"
    # bounded: at most remembered_references parts, the oldest forgotten first and said so
    assert set_parameter(peer, "estimator_node", "remembered_references", 2) == (True, "")
    for part_id in ("R1", "R2"):
        assert set_reference(peer, "estimator_node", part_id, files["part"])[0]
    accepted, message = set_reference(peer, "estimator_node", "R3", files["part"])
    assert accepted and "part R1's reference forgotten" in message, message
    # R2 and R3 name the same unchanged file: one read serves both (3 MB a file at paper resolution)
    diagnostics = cell["received"]["/diagnostics"]
    start = len(diagnostics)
    assert peer.wait(lambda: latest_heartbeat(diagnostics[start:], NODE_NAMES["estimator_node"]).get(
        "part_reference_files") == "1", 5.0), latest_heartbeat(diagnostics[start:], NODE_NAMES["estimator_node"])
    assert latest_heartbeat(diagnostics[start:], NODE_NAMES["estimator_node"])["part_references"] == "2"
    ok, reason = set_parameter(peer, "estimator_node", "remembered_references", 1001)  # at most 1000 (3 GB)
    assert not ok, reason
    state, _ = send(cell, coarse_hood, own, 14, "R1")
    assert state.reference == f"cell:{files['cell']}"
    state, effects = send(cell, coarse_hood, own, 15, "R3")
    assert state.reference == f"part:{files['part']}" and effects.reference == f"cell:{files['cell']}"
    # R3's reference was given to the estimator only: the decomposition node says so
    assert cell["peer"].wait(lambda: any(
        s.level == DiagnosticStatus.WARN and s.name == "hood_decomp/hood_decomp_decomposition"
        and "both nodes" in s.message and ("stamp", "15.000000000") in [(kv.key, kv.value) for kv in s.values]
        for a in cell["received"]["/diagnostics"] for s in a.status), 10.0)
    # a lower bound forgets at once (R2, the older), not at the next part's reference
    assert set_parameter(peer, "estimator_node", "remembered_references", 1) == (True, "")
    assert peer.wait(lambda: any(  # and says so, naming the part
        s.level == DiagnosticStatus.WARN and s.name == "hood_decomp/hood_decomp_estimator"
        and s.message == "remembered_references 1: part reference(s) forgotten: R2"
        for a in cell["received"]["/diagnostics"] for s in a.status), 10.0)
    state, _ = send(cell, coarse_hood, own, 16, "R2")
    assert state.reference == f"cell:{files['cell']}"
    # Q's two inspections (12, 17) were both relative to the cell's reference: its move is verified
    send(cell, coarse_hood, other, 17, "Q")
    assert peer.wait(lambda: any(v.header.stamp.sec == 17 and v.part_id == "Q"
                                 for v in cell["received"]["hood_decomp/move_verification"]), 10.0)
    assert set_reference(peer, "estimator_node", "R3", "") == (True, f"part R3 forgot its reference {files['part']}")


def _history_rows(path, query: str = "SELECT part_id, reference, calibration FROM parts") -> list[tuple]:
    """The rows of ``query`` on the results history at ``path`` ([] while it does not exist or is being created)."""
    import sqlite3

    if not path.exists():
        return []
    db = sqlite3.connect(path, timeout=5)
    try:
        return db.execute(query).fetchall()
    except sqlite3.OperationalError:  # being created
        return []
    finally:
        db.close()


def test_the_live_history_records_the_reference_and_calibration_each_part_used(cell, coarse_hood):
    """Fails if the estimator's live history row of a part does not name the reference its estimate used, exactly as
    its BoundaryState does (the part's own for a part given one, the cell's or none for another), or not the bases'
    calibration as the node's heartbeat reports it ("none" there, "" in the history, for uncalibrated bases)."""
    peer, files = cell["peer"], cell["files"]
    path = cell["root"] / "live.sqlite"
    assert set_parameter(peer, "estimator_node", "history", str(path)) == (True, "")
    try:
        accepted, message = set_reference(peer, "estimator_node", "H-own", files["part"])
        assert accepted, message
        values, _ = part_field(coarse_hood, cell["part_error"])
        own, _ = send(cell, coarse_hood, values, 900, "H-own")
        other, _ = send(cell, coarse_hood, values, 901, "H-other")
        assert peer.wait(lambda: len(_history_rows(path)) == 2, 10.0), _history_rows(path)
    finally:
        set_parameter(peer, "estimator_node", "history", "")
        set_reference(peer, "estimator_node", "H-own", "")
    calibration = latest_heartbeat(cell["received"]["/diagnostics"], NODE_NAMES["estimator_node"])["calibration"]
    calibration = "" if calibration == "none" else calibration
    assert own.reference == f"part:{files['part']}" and own.reference != other.reference
    assert sorted(_history_rows(path)) == [("H-other", other.reference, calibration),
                                           ("H-own", own.reference, calibration)]


@pytest.mark.parametrize(("which", "named"), [
    ("missing", "cannot be read"),
    ("foreign", FOREIGN_MODEL),
    ("escape", "leaves the calibration file's directory"),
    ("fifo", "is a FIFO, not a regular file"),
    ("zero", "/dev/zero is a character device, not a regular file"),
    ("relative", "'cell/ref.json' is a relative path: give it absolute"),
    ("long", "reference path of 1101 bytes: at most 1024"),
])
def test_a_bad_reference_is_refused_and_the_node_keeps_serving(cell, coarse_hood, which, named):
    """Fails if a reference file that does not read, a reference of another model_id, one naming a file outside its
    directory, a FIFO (blocks a reader that opens it), /dev/zero (endless: read, it eats the node's memory), a relative
    path (the node's working directory is not the caller's) or a path over 1 KB is accepted (parameter or service),
    refused without a one-line reason naming the problem, or if the node then loses its reference or stops serving: the
    parameter keeps its value, the part keeps none of its own, and the next field is still made relative to the cell's
    reference."""
    peer, files, names = cell["peer"], cell["files"], coarse_hood.reduced.names
    path = str(cell["root"] / "missing.json") if which == "missing" else files[which]
    for node in NODES:
        ok, reason = set_parameter(peer, node, "reference", path)
        assert not ok and named in reason and "\n" not in reason and f"keeps cell:{files['cell']}" in reason, reason
        assert string_parameter(peer, node, "reference") == files["cell"]
        accepted, message = set_reference(peer, node, "B", path)
        assert not accepted and named in message and "\n" not in message, message
    values, truth = part_field(coarse_hood, cell["cell_error"])
    sec = 20 + ("missing", "foreign", "escape", "fifo", "zero", "relative", "long").index(which)
    state, effects = send(cell, coarse_hood, values, sec, "B")
    assert state.reference == effects.reference == f"cell:{files['cell']}"
    assert error_mm(state, names, truth).max() < 1e-4
    assert all(p.poll() is None for p in cell["processes"]), "a node died"


def test_a_part_id_is_taken_as_sent_and_a_long_one_refused(cell, coarse_hood):
    """Fails if set_reference strips the part_id (a field's part_id is matched as sent: the reference of " W" would
    serve the fields of "W") or takes a part_id over 1 KB."""
    peer, files = cell["peer"], cell["files"]
    own, _ = part_field(coarse_hood, cell["part_error"])
    for node in NODES:
        assert set_reference(peer, node, " W", files["part"])[0]
        accepted, message = set_reference(peer, node, "W" * 1025, files["part"])
        assert not accepted and message == "part_id of 1025 bytes: at most 1024", message
    state, effects = send(cell, coarse_hood, own, 27, "W")
    assert state.reference == effects.reference == f"cell:{files['cell']}"
    state, effects = send(cell, coarse_hood, own, 28, " W")
    assert state.reference == effects.reference == f"part:{files['part']}"
    for node in NODES:
        assert set_reference(peer, node, " W", "")[0]


def test_two_spellings_of_one_reference_file_are_one_reference(cell, coarse_hood):
    """Fails if the part's reference given to the estimator as ``DIR/./ref.json`` and to the decomposition node as
    ``DIR/ref.json`` is not named alike by both (the file's resolved path) or makes the decomposition node warn that
    the two nodes used different references."""
    peer, files, diagnostics = cell["peer"], cell["files"], cell["received"]["/diagnostics"]
    spelled = files["part"].replace("/ref.json", "/./ref.json")
    assert spelled != files["part"]
    assert set_reference(peer, "estimator_node", "S", spelled)[0]
    assert set_reference(peer, "decomposition_node", "S", files["part"])[0]
    own, _ = part_field(coarse_hood, cell["part_error"])
    state, effects = send(cell, coarse_hood, own, 29, "S")
    assert state.reference == effects.reference == f"part:{files['part']}"
    assert peer.wait(lambda: any(
        s.name == "hood_decomp/hood_decomp_decomposition" and ("stamp", "29.000000000") in [(kv.key, kv.value)
                                                                                          for kv in s.values]
        for a in diagnostics for s in a.status), 10.0)
    assert not any(s.name == "hood_decomp/hood_decomp_decomposition" and "both nodes" in s.message
                   and ("stamp", "29.000000000") in [(kv.key, kv.value) for kv in s.values]
                   for a in diagnostics for s in a.status)
    for node in NODES:
        assert set_reference(peer, node, "S", "")[0]


def test_calibrated_bases_swap_in_through_lifecycle_transitions(cell, coarse_hood):
    """Fails if deactivate -> cleanup -> set ``bases`` -> configure -> activate does not swap in calibrated bases
    (made by `hood-decomp calibrate` from 13 entries of a part whose pads are 25 % stiffer, preloaded 40 % more and
    whose load response is 2 % smaller than the model's), if /diagnostics does not report the calibration (id from
    the file, 13 entries, its leave-one-out RMS and physical factors) where it reported none, if the estimate does not
    change (uncalibrated off by more than 0.05 mm, calibrated within 0.01 mm), if the live history's rows of the part
    do not name the calibration that served each inspection ("" before, the file's id after), or if a bad cell
    reference does not fail the configure transition, saying why, while the node stays alive."""
    peer, root, diagnostics = cell["peer"], cell["root"], cell["received"]["/diagnostics"]
    reduced = coarse_hood.reduced
    truth = replace(reduced, k=reduced.k * 1.25, preload=reduced.preload * 1.4, w0=reduced.w0 / 1.02,
                    w0_3d=reduced.w0_3d / 1.02)
    write_calibration(root / "calibration", coarse_hood, truth)
    calibrated = root / "calibrated.h5"
    run = subprocess.run([sys.executable, "-m", "hood_decomp.cli", "calibrate", "--bases", str(coarse_hood.bases_path),
                          "--model", str(root / "calibration" / "model"), "--cal",
                          str(root / "calibration" / "cal.json"), "--out", str(calibrated)],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    with h5py.File(calibrated, "r") as h5:
        record = json.loads(h5.attrs["calibration"])
    member = solve_members(truth, STATE[None])
    values, effective = member.normal_displacement[0], member.effective[0]
    for node in NODES:  # the part's fields as measured: no reference
        assert set_parameter(peer, node, "reference", "") == (True, "")
    history = root / "calibration_live.sqlite"
    assert set_parameter(peer, "estimator_node", "history", str(history)) == (True, "")
    before, _ = send(cell, coarse_hood, values, 30, "C")
    beat = latest_heartbeat(diagnostics, NODE_NAMES["estimator_node"])
    assert beat["calibration"] == "none" and json.loads(beat["bases_provenance"])["calibration"] is None
    assert error_mm(before, reduced.names, effective).max() > 0.05, error_mm(before, reduced.names, effective)
    for node in NODES:
        assert transition(peer, node, Transition.TRANSITION_DEACTIVATE)
        assert transition(peer, node, Transition.TRANSITION_CLEANUP)
        assert set_parameter(peer, node, "bases", str(calibrated)) == (True, "")
        # a bad cell reference fails the configure transition, naming it; fixed, the node configures
        assert set_parameter(peer, node, "reference", cell["files"]["foreign"]) == (True, "")
        assert not transition(peer, node, Transition.TRANSITION_CONFIGURE)
        assert peer.wait(lambda n=node: any(
            s.name == f"hood_decomp/{NODE_NAMES[n]}" and "configure failed" in s.message and FOREIGN_MODEL in s.message
            for a in diagnostics for s in a.status), 10.0), (node, [s.message for a in diagnostics[-20:]
                                                                    for s in a.status])
        assert set_parameter(peer, node, "reference", "") == (True, "")
        assert transition(peer, node, Transition.TRANSITION_CONFIGURE)
        assert transition(peer, node, Transition.TRANSITION_ACTIVATE)
    start = len(diagnostics)
    assert peer.wait(lambda: all(latest_heartbeat(diagnostics[start:], NODE_NAMES[node]).get("calibration")
                                 == record["id"] for node in NODES), 10.0)
    for node in NODES:
        provenance = json.loads(latest_heartbeat(diagnostics[start:], NODE_NAMES[node])["bases_provenance"])
        calibration = provenance["calibration"]
        assert len(calibration["entries"]) == 13 and calibration["loo_rms_mm"] == pytest.approx(record["loo_rms_mm"])
        assert calibration["factors"] == record["factors"] and calibration["factor_std"] == record["factor_std"]
    peer.wait(lambda: peer.publishers["hood_decomp/displacement"].get_subscription_count() >= 2, 30.0)
    assert peer.wait(lambda: all(int(latest_heartbeat(diagnostics[start:], NODE_NAMES[node]).get(
        "publishers /hood_decomp/displacement", 0)) >= 1 for node in NODES), 30.0)
    after, effects = send(cell, coarse_hood, values, 31, "C")
    assert error_mm(after, reduced.names, effective).max() < 0.01, error_mm(after, reduced.names, effective)
    assert after.reference == effects.reference == ""
    assert all(p.poll() is None for p in cell["processes"]), "a node died"

    def calibrations() -> list[tuple[int, str, str]]:
        rows = _history_rows(history, "SELECT stamp_ns, calibration, reference FROM parts WHERE part_id = 'C'")
        return sorted(rows)

    assert peer.wait(lambda: len(calibrations()) == 2, 10.0), calibrations()
    assert set_parameter(peer, "estimator_node", "history", "") == (True, "")
    assert calibrations() == [(30 * 10**9, "", ""), (31 * 10**9, record["id"], "")]


def test_bases_without_a_reduced_model_refuse_a_reference(cell, coarse_hood):
    """Fails if a node whose bases hold no reduced model (the model's field at the reference's state cannot be made)
    takes a reference (at configure, as a parameter or by the service) instead of refusing it with the reason, or
    stops serving its fields as measured (the estimator with the paper's PCA method, which needs no reduced model)."""
    from hood_decomp.io.bases import save_bases

    peer, root, diagnostics, files = cell["peer"], cell["root"], cell["received"]["/diagnostics"], cell["files"]
    bare = root / "bare.h5"
    save_bases(bare, replace(coarse_hood.bases, reduced_model=None))
    assert set_parameter(peer, "estimator_node", "method", "pca") == (True, "")
    for node in NODES:
        assert transition(peer, node, Transition.TRANSITION_DEACTIVATE)
        assert transition(peer, node, Transition.TRANSITION_CLEANUP)
        assert set_parameter(peer, node, "bases", str(bare)) == (True, "")
        assert set_parameter(peer, node, "reference", files["cell"]) == (True, "")  # read at configure
        assert not transition(peer, node, Transition.TRANSITION_CONFIGURE)
        assert peer.wait(lambda n=node: any(
            s.name == f"hood_decomp/{NODE_NAMES[n]}" and "configure failed" in s.message
            and "no reduced model" in s.message for a in diagnostics for s in a.status), 10.0), node
        assert set_parameter(peer, node, "reference", "") == (True, "")
        assert transition(peer, node, Transition.TRANSITION_CONFIGURE)
        assert transition(peer, node, Transition.TRANSITION_ACTIVATE)
        ok, reason = set_parameter(peer, node, "reference", files["cell"])
        assert not ok and "no reduced model" in reason and "keeps none" in reason, reason
        accepted, message = set_reference(peer, node, "D", files["cell"])
        assert not accepted and "no reduced model" in message, message
    start = len(diagnostics)
    assert peer.wait(lambda: all(int(latest_heartbeat(diagnostics[start:], NODE_NAMES[node]).get(
        "publishers /hood_decomp/displacement", 0)) >= 1 for node in NODES), 30.0)
    values, _ = part_field(coarse_hood, np.zeros(coarse_hood.skin.n_nodes))
    state, effects = send(cell, coarse_hood, values, 40, "D")
    assert state.reference == effects.reference == ""
    assert all(p.poll() is None for p in cell["processes"]), "a node died"


FAILED_CONFIGURE_SCRIPT = """
import json, sys
import rclpy
from rclpy.parameter import Parameter
from hood_decomp.ros.estimator_node import EstimatorNode
rclpy.init()
node = EstimatorNode()
node.set_parameters([Parameter("bases", value=sys.argv[1]), Parameter("reference", value=sys.argv[2])])
node.trigger_configure()
node._set_reference("P", "", sys.argv[3])
before = node.part_references["P"][1]
node.trigger_cleanup()
publisher = node.publisher
def broken(*args, **kwargs):
    raise RuntimeError("no publisher")
node.publisher = broken  # fails the configure after the references were read
node.trigger_configure()
after_failure = {"cell": node.reference_label(node.cell_reference, "cell"), "heartbeat": node.heartbeat_values()[
    "reference"], "part_kept": node.part_references["P"][1] is before, "state": node.state}
node.publisher = publisher
node.trigger_configure()
print("CONFIGURE", json.dumps({"after_failure": after_failure, "state": node.state,
                               "cell": node.reference_label(node.cell_reference, "cell"),
                               "part_read_again": node.part_references["P"][1] is not before}))
node.destroy_node()
rclpy.shutdown()
"""


def test_a_failed_configure_keeps_no_reference_of_the_bases_it_dropped(coarse_hood, tmp_path):
    """Fails if a configure that fails after the references were read leaves the cell's reference (read for bases
    the failure dropped; the heartbeat would name it) or the parts' references half read again, or if the next
    configure does not read them all again."""
    import pathlib

    skin, reduced = coarse_hood.skin, coarse_hood.reduced
    setting = np.array([REFERENCE_SETTING.get(name, 0.0) for name in reduced.names])
    at_reference = solve_members(reduced, setting[None]).normal_displacement[0]
    cell_path = write_reference(tmp_path / "cell", skin, at_reference, "ref", coarse_hood.bases.model_id)
    part_path = write_reference(tmp_path / "part", skin, at_reference, "ref", coarse_hood.bases.model_id)
    root = pathlib.Path(__file__).resolve().parents[2]
    done = subprocess.run([sys.executable, "-c", FAILED_CONFIGURE_SCRIPT, str(coarse_hood.bases_path), cell_path,
                           part_path], cwd=root, capture_output=True, text=True, timeout=120, env=os.environ.copy())
    line = next((row for row in done.stdout.splitlines() if row.startswith("CONFIGURE ")), None)
    assert line is not None, done.stderr[-3000:]
    found = json.loads(line[len("CONFIGURE "):])
    assert "no publisher" in done.stdout + done.stderr
    assert found["after_failure"] == {"cell": "", "heartbeat": "none", "part_kept": True, "state": "unconfigured"}, (
        found)
    assert found["state"] == "inactive" and found["cell"] == f"cell:{cell_path}" and found["part_read_again"], found
