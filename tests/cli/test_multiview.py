"""Several views of one part on the command line (issue 17): `estimate`, `decompose` and `close-loop` with repeated
--scan, each followed by its --scanner-pose POSE.json. Truth: the FE state the synthetic scanner scanned, and the
scanner's true poses (written to the POSE.json files; the PLY files hold no pose and no markers, so the pose files
are the only registration)."""

from __future__ import annotations

import json

import pytest

from hood_decomp.cli import main
from hood_decomp.io.ply import write_scan
from tests.multiview import scanned_part

STATE = {"HINGE_Y": -0.3, "LOCK_L": 0.4}


@pytest.fixture(scope="module")
def views(coarse_hood, tmp_path_factory):
    """Three partial views (PLY without pose or markers) and their true poses as POSE.json (nested 4 x 4 lists)."""
    directory = tmp_path_factory.mktemp("views")
    member, scans = scanned_part(coarse_hood, STATE, 7, n_holes=0, fixture=False)
    files = []
    for k, scan in enumerate(scans):
        ply, pose = directory / f"view{k + 1}.ply", directory / f"view{k + 1}_pose.json"
        write_scan(ply, scan.points)
        pose.write_text(json.dumps(scan.true_transform.tolist()))
        files.append((ply, pose))
    return member, files


def _estimate(coarse_hood, argv_scans, tmp_path, capsys) -> dict:
    out = tmp_path / "estimate.json"
    assert main(["estimate", "--bases", str(coarse_hood.bases_path), *argv_scans, "--json", str(out)]) == 0, \
        capsys.readouterr().err
    return json.loads(out.read_text())


def test_estimate_fuses_the_views_of_one_part(coarse_hood, views, tmp_path, capsys):
    """Fails if the views are not fused (the fused coverage must exceed every single view's by 10 points and stay
    below their sum), if a view's pose file is ignored (a view in the scanner frame would not overlap the part) or the
    fused estimate misses the scanned truth by more than 4 stated stds or 0.05 mm on a parameter."""
    member, files = views
    single = [_estimate(coarse_hood, ["--scan", str(p), "--scanner-pose", str(q)], tmp_path, capsys) for p, q in files]
    argv = [a for p, q in files for a in ("--scan", str(p), "--scanner-pose", str(q))]
    fused = _estimate(coarse_hood, argv, tmp_path, capsys)
    coverages = [s["coverage"] for s in single]
    assert max(coverages) + 0.1 < fused["coverage"] <= sum(coverages), (coverages, fused["coverage"])
    truth = dict(zip(coarse_hood.reduced.names, member.effective[0], strict=True))
    for label, value in fused["parameters_mm"].items():
        if fused["lifted"].get(label):
            continue
        error = abs(value - truth[label])
        assert error <= max(4 * fused["std_mm"][label], 0.005) and error < 0.05, (label, value, truth[label])


def test_decompose_and_close_loop_take_the_views_too(coarse_hood, views, tmp_path, capsys):
    """Fails if decompose or close-loop refuse posed views or treat them as separate parts (close-loop must report
    one field for three posed scans), or if close-loop names an effect on a part its model explains."""
    _, files = views
    argv = [a for p, q in files for a in ("--scan", str(p), "--scanner-pose", str(q))]
    out = tmp_path / "decompose.json"
    assert main(["decompose", "--bases", str(coarse_hood.bases_path), *argv, "--json", str(out)]) == 0
    assert json.loads(out.read_text())["effects"]
    from hood_decomp.io.model_files import save_model

    save_model(coarse_hood.model, tmp_path / "model")
    assert main(["close-loop", "--model", str(tmp_path / "model"), "--bases", str(coarse_hood.bases_path), *argv,
                 "--out", str(tmp_path / "loop")]) == 0, capsys.readouterr().err
    report = json.loads((tmp_path / "loop" / "close_loop.json").read_text())
    assert len(report["residual_rms_before_mm"]) == 1
    assert report["status"] == "within_model", report["status"]
