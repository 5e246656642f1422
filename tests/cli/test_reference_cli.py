"""`--reference REF.json` on the command line (issue 16): the reference state is honoured, and a reference file cannot
name a file outside its directory or a parameter the bases lack."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest


def _estimate(workspace, reference, out):
    command = [sys.executable, "-m", "hood_decomp.cli", "estimate", "--bases", str(workspace.bases), "--field",
               str(workspace.field), "--reference", str(reference), "--json", str(out)]
    return subprocess.run(command, capture_output=True, text=True, timeout=300)


def test_reference_state_is_what_the_reference_itself_estimates_to(tiny_workspace, tmp_path):
    """Fails if --reference is ignored or its setting misread: the field measured as its own reference (LOCK_L at
    0.4 mm) becomes the model's field for the reference's stated setting, so LOCK_L must come out at that setting
    (0.25 mm, not the field's 0.4 mm), and the JSON must name the reference and the (uncalibrated) bases."""
    lock_l = 0.25
    shutil.copy(tiny_workspace.field, tmp_path / "ref.vtu")
    (tmp_path / "ref.json").write_text(json.dumps({"field": "ref.vtu", "setting": {"LOCK_L": lock_l}}))
    run = _estimate(tiny_workspace, tmp_path / "ref.json", tmp_path / "out.json")
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads((tmp_path / "out.json").read_text())
    assert abs(result["parameters_mm"]["LOCK_L"] - lock_l) < 1e-3, result["parameters_mm"]
    assert result["reference"].endswith("ref.json") and result["calibration"] is None and result["bases_id"]


@pytest.mark.parametrize(("entry", "message"), [
    ({"field": "../decoys/secret.txt", "setting": {}}, "leaves the calibration file's directory"),
    ({"field": "ref.vtu", "setting": {"LOCK_Z": 0.1}}, "unknown parameter 'LOCK_Z'"),
    ({"field": "ref.vtu", "scans": ["a.ply"], "setting": {}}, "exactly one of 'field' and 'scans'"),
])
def test_bad_reference_is_one_line_and_exit_2(tiny_workspace, tmp_path, entry, message):
    """Fails if a reference file naming a file outside its directory, an unknown parameter or both a field and scans
    is accepted, or refused other than by one line with exit status 2."""
    root = tmp_path / "cell"
    root.mkdir()
    (tmp_path / "decoys").mkdir()
    (tmp_path / "decoys" / "secret.txt").write_text("secret\n")
    shutil.copy(tiny_workspace.field, root / "ref.vtu")
    (root / "ref.json").write_text(json.dumps(entry))
    run = _estimate(tiny_workspace, root / "ref.json", tmp_path / "out.json")
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], run.stderr
    assert not (tmp_path / "out.json").exists()
