"""The main job end to end: `hood-decomp demo` (default hood, a small validation set) as a user runs it, its report
rendered in headless Chromium: every image loads, every table is filled, no error text; and the numbers behind the
report agree with the truth the scans were made from."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.browser import check_rendered_report

pytestmark = [pytest.mark.ros, pytest.mark.slow]


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    command = [sys.executable, "-m", "hood_decomp.cli", "demo", "--resolution", "default", "--validation", "40",
               "--scan-points", "150000", "--out", str(out)]
    run = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    assert f"report written to {(out / 'index.html').resolve()}" in run.stderr
    return out


def test_report_renders_completely(demo_dir, tmp_path):
    check_rendered_report(demo_dir / "index.html", tmp_path / "profile", 20, 10,
                          ("Traceback", "Error", "NaN", " nan ", "Not run"))


def test_report_numbers_agree_with_truth(demo_dir):
    results = json.loads((demo_dir / "results.json").read_text())
    scans = {scan["name"]: scan for scan in results["scans"]}
    assert set(scans) == {"clean", "noisy", "occluded", "undeclared"}
    tolerance = {"clean": 0.05, "noisy": 0.1, "occluded": 0.05}  # as tests/test_replay.py, same reasons
    for name in ("clean", "noisy", "occluded"):
        scan = scans[name]
        assert scan["within_model"], f"{name}: a scan without undeclared effect reported outside the model"
        for label, truth in scan["truth_mm"].items():
            if scan["lifted"][label]:  # an upper bound of the commanded position
                assert truth <= scan["estimate_mm"][label] + 0.05, (name, label)
            else:
                assert not scan["lifted_truth"].get(label, False), (name, label, "lifted in truth")
                assert abs(scan["estimate_mm"][label] - truth) <= tolerance[name], (name, label)
    undeclared = scans["undeclared"]
    assert not undeclared["within_model"] and not undeclared["safe_to_apply"]
    assert results["close_loop"]["effect"] == "hinge_R.z"
    assert results["close_loop"]["residual_rms_after_mm"] < results["close_loop"]["residual_rms_before_mm"] / 3
