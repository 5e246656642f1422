"""The scanner's stated marker-centre noise on the command line (issue 15): `estimate --scan S.ply --marker-std-mm`.
Truth: the marker registration's pose covariance is the marker noise squared times a fixed geometry term, so a
parameter's stated std grows with the stated marker noise where the registration dominates it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hood_decomp.cli import main
from hood_decomp.io.ply import write_scan
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan


@pytest.fixture(scope="module")
def marker_scan(coarse_hood, tmp_path_factory):
    """One scan of the coarse hood at its nominal state (the FE model's) in the scanner frame with its 8 fixture
    markers (0.03 mm centre noise), as a PLY."""
    from hood_decomp.core.fe.ensemble import solve_members

    nominal = solve_members(coarse_hood.reduced, np.zeros((1, len(coarse_hood.reduced.names)))).displacement[0]
    scan = synthesize_scan(coarse_hood.skin, nominal,
                           ScannerConfig(n_points=120_000, noise_mm=0.02, marker_noise_mm=0.03), seed=5)
    path = tmp_path_factory.mktemp("marker_scan") / "scan.ply"
    write_scan(path, scan.points, markers=scan.markers, markers_nominal=scan.markers_nominal)
    return path


def _estimate(coarse_hood, scan, extra, tmp_path, capsys) -> tuple[dict, str]:
    out = tmp_path / "estimate.json"
    code = main(["estimate", "--bases", str(coarse_hood.bases_path), "--scan", str(scan), "--json", str(out), *extra])
    err = capsys.readouterr().err
    assert code == 0, err
    return json.loads(out.read_text()), err


def test_a_stated_marker_noise_replaces_the_estimate(coarse_hood, marker_scan, tmp_path, capsys):
    """Fails if --marker-std-mm does not reach the registration's pose covariance: two statements the marker
    residual accepts (0.7 and 1.6 times the residual's own estimate) must differ in the locks' std (the registration
    is most of them on the coarse hood even in the generalised least-squares fit, which separates a pose error from
    HINGE_X's move by the surface's shape: HINGE_X's std moves by 0.1 %) by at least 1.4 times (the registration term
    alone by 2.29, an ignored statement by 1.0; measured 2.04-2.05 in session 11 and 1.65 since the scan's slide is
    taken out: the other terms of the locks' variance are now about 0.7 of the registration's, 0.16 before), and the
    JSON must report each check as accepted with the stated value used, and the fit as the generalised one."""
    first, _ = _estimate(coarse_hood, marker_scan, ["--marker-std-mm", "0.03"], tmp_path, capsys)
    [check] = first["marker_noise_checks"]
    assert check["accepted"] and check["used_mm"] == 0.03 and check["dof"] == 18, check  # the scanner's truth
    assert first["weighting"] == "generalised"  # a registered scan's field is weighted by its error model
    estimated = check["estimated_mm"]
    runs = [_estimate(coarse_hood, marker_scan, ["--marker-std-mm", f"{factor * estimated:.6f}"], tmp_path, capsys)[0]
            for factor in (0.7, 1.6)]
    for run in runs:
        [check] = run["marker_noise_checks"]
        assert check["accepted"] and check["used_mm"] == check["stated_mm"], check
    for lock in ("LOCK_L", "LOCK_R"):
        low, high = (run["std_mm"][lock] for run in runs)
        print(f"{lock} std {low:.4f} -> {high:.4f} mm ({high / low:.2f} x)")
        assert high > 1.4 * low, (lock, low, high)


def test_a_stated_marker_noise_the_markers_reject_is_named_and_not_used(coarse_hood, marker_scan, tmp_path,
                                                                         capsys):
    """Fails if a stated marker noise ten times below the scan's (0.003 against the synthetic scanner's 0.03 mm) is
    used: the JSON must name the rejection (accepted false, a reason saying "too small", the residual's estimate
    used), stderr must carry it as one warning line, and every std must equal the run without a statement (the
    estimate is what is used then). Without the check HINGE_X's std would shrink several times."""
    unstated, _ = _estimate(coarse_hood, marker_scan, [], tmp_path, capsys)
    assert unstated["marker_noise_checks"] is None
    stated, err = _estimate(coarse_hood, marker_scan, ["--marker-std-mm", "0.003"], tmp_path, capsys)
    [check] = stated["marker_noise_checks"]
    assert not check["accepted"] and "too small" in check["reason"] and check["used_mm"] == check["estimated_mm"]
    assert check["p_value"] < check["alpha"] == 0.001
    warnings = [line for line in err.splitlines() if "stated marker noise 0.003 mm is too small" in line]
    assert len(warnings) == 1, err
    for name, std in unstated["std_mm"].items():
        assert stated["std_mm"][name] == pytest.approx(std, rel=1e-9), name
