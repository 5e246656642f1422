"""Small input files other than references (a scanner pose, a model.yaml) are read as a reference is
(io.small_files.read_small_file): from a regular file only, never more than their bound. A FIFO is refused at once by
name (it would block the reader), and a file over the bound is refused without being read whole. The scan (.ply) and
field (.vtu) readers judge the file they opened, not the path a caller checked before (io.small_files.open_regular):
a FIFO swapped in between is refused, not waited on."""

from __future__ import annotations

import json
import os
import shutil

import pytest

from hood_decomp.errors import CalibrationError, FieldError, ModelError, ScanError
from hood_decomp.io.model_files import load_model
from hood_decomp.io.poses import MAX_POSE_FILE_BYTES, read_pose_file
from tests.bad_inputs import outcome_without_blocking


@pytest.mark.parametrize(("reader", "error", "name"), [
    (read_pose_file, ScanError, "pose.json"),
    (load_model, ModelError, "model.yaml"),
])
def test_a_fifo_is_refused_by_name_without_blocking(tmp_path, reader, error, name):
    """Fails if the reader opens the FIFO blocking (the test would hang: no writer ever comes; run it with a timeout
    to see it red) or reads it instead of refusing it with a one-line error naming the kind of file."""
    os.mkfifo(tmp_path / name)
    with pytest.raises(error, match=f"{name} is a FIFO, not a regular file$"):
        reader(tmp_path / name)


def test_a_pose_file_over_its_bound_is_refused(tmp_path):
    """Fails if a pose file of more than MAX_POSE_FILE_BYTES (a list of 16 numbers padded with spaces: valid JSON)
    is read and accepted instead of refused naming the bound."""
    path = tmp_path / "pose.json"
    numbers = "[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]"
    path.write_text(numbers + " " * MAX_POSE_FILE_BYTES)
    with pytest.raises(ScanError, match=f"larger than {MAX_POSE_FILE_BYTES} bytes"):
        read_pose_file(path)
    path.write_text(numbers)
    assert read_pose_file(path).shape == (4, 4)


@pytest.mark.parametrize("kind", ["scans", "field"])
def test_a_reference_scan_or_field_swapped_for_a_fifo_after_its_check_is_refused(tiny_workspace, tmp_path,
                                                                                 monkeypatch, kind):
    """Fails if the file a REF.json names (a .ply scan or a .vtu field), checked to be a regular file and then
    replaced by a FIFO before its reader opens it, blocks the reader (it would wait for a writer forever) or is read
    instead of refused with a one-line CalibrationError naming the file as a FIFO. The swap happens at the last look
    read_entries takes at the file (its file_key) before the reader."""
    from hood_decomp.io import calibration_files
    from hood_decomp.io.bases import load_bases

    source = tiny_workspace.scan if kind == "scans" else tiny_workspace.field
    named = tmp_path / f"ref{source.suffix}"
    shutil.copy(source, named)
    entry = {kind: [named.name] if kind == "scans" else named.name, "setting": {}}
    (tmp_path / "ref.json").write_text(json.dumps(entry))
    original = calibration_files.file_key

    def swapping_file_key(path):
        key = original(path)
        if os.fspath(path) == os.fspath(named):
            named.unlink()
            os.mkfifo(named)
        return key

    monkeypatch.setattr(calibration_files, "file_key", swapping_file_key)
    bases = load_bases(tiny_workspace.bases)
    error = outcome_without_blocking(lambda: calibration_files.read_reference(tmp_path / "ref.json", bases), named)
    assert named.is_fifo(), "the swap did not happen: the test proves nothing"
    assert isinstance(error, CalibrationError) and f"{named} is a FIFO, not a regular file" in str(error), error
    assert "\n" not in str(error)


@pytest.mark.parametrize(("suffix", "error"), [(".ply", ScanError), (".vtu", FieldError)])
def test_the_scan_and_field_readers_refuse_a_fifo_and_a_device(tmp_path, suffix, error):
    """Fails if read_scan (.ply) or read_field (.vtu) given a FIFO blocks or reads it, or given /dev/zero (endless)
    reads it, instead of refusing either at once by the kind of file."""
    from hood_decomp.io.fields import read_field
    from hood_decomp.io.ply import read_scan

    reader = read_scan if suffix == ".ply" else read_field
    fifo = tmp_path / f"part{suffix}"
    os.mkfifo(fifo)
    outcome = outcome_without_blocking(lambda: reader(fifo), fifo)
    assert isinstance(outcome, error) and "is a FIFO, not a regular file" in str(outcome), outcome
    with pytest.raises(error, match="/dev/zero is a character device, not a regular file"):
        reader("/dev/zero")


@pytest.mark.parametrize(("kind", "error"), [("bases", "BasisError"), ("ensemble", "EnsembleError"),
                                             ("deck", "MeshError")])
def test_the_hdf5_and_deck_readers_refuse_a_fifo(tmp_path, kind, error):
    """Fails if load_bases, load_ensemble (HDF5, opened by name inside h5py) or read_inp_mesh (a CalculiX deck) given a
    FIFO blocks or is refused other than by one line naming the kind of file (before: "does not exist" for a FIFO at
    the path, and a FIFO swapped in after that check was waited on). Run in a child process stopped after 60 s: h5py
    waits on the FIFO holding the interpreter's lock, so a thread could not be timed out."""
    import subprocess
    import sys

    reader = {"bases": "hood_decomp.io.bases import load_bases as read",
              "ensemble": "hood_decomp.io.ensemble_store import load_ensemble as read",
              "deck": "hood_decomp.io.mesh import read_inp_mesh as read"}[kind]
    fifo = tmp_path / f"{kind}.h5"
    os.mkfifo(fifo)
    code = f"from {reader}\ntry:\n    read({str(fifo)!r})\nexcept Exception as e:\n    print(type(e).__name__, e)"
    try:
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the {kind} reader blocked on the FIFO {fifo}")
    assert run.stdout.startswith(f"{error} ") and run.stdout.count("\n") == 1, run.stdout + run.stderr[-2000:]
    assert run.stdout.endswith(f"{fifo} is a FIFO, not a regular file\n"), run.stdout
