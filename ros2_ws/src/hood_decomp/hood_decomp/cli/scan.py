"""`hood-decomp scan`: synthesise a structured-light scan of a displaced part.

One forward FE solve of the boundary setting, then the synthetic scanner (synthetic/scanner.py) looks at the displaced
visible skin in its fixture: about a million points in the scanner frame with range noise, dropouts, occlusion,
outliers and the fixture markers, written as SCAN.ply (io/ply.py) with a sidecar SCAN.json stating the truth (setting,
noise, scanner and part transforms). The other verbs read such a file with ``--scan`` (io/scans.py).
"""

from __future__ import annotations

import argparse
import logging

import numpy as np

from hood_decomp.cli._common import (
    add_setting,
    check_output,
    emit_json,
    finite,
    model_inputs,
    parse_settings,
    write_json,
    written_whole,
)
from hood_decomp.errors import ScanError

HELP = "synthesise a structured-light scan of a displaced part -> SCAN.ply (+ SCAN.json with the truth)"
LOG_FORMAT = "hood-decomp scan: %(message)s"

logger = logging.getLogger(__name__)
#: most points a synthetic scan may have: a real structured-light scan of a hood has 1-20 million; each point costs
#: about 200 bytes on the way (ray, hit, noise, PLY record), so 50 million is about 10 GB
MAX_POINTS = 50_000_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, help="model directory or its model.yaml")
    add_setting(parser)
    parser.add_argument("--out", required=True, help="output scan (.ply, points in the scanner frame, mm)")
    parser.add_argument("--noise-mm", type=finite(0.0, 10.0), default=0.02,
                        help="range noise along the ray, mm (default 0.02; at most 10)")
    parser.add_argument("--seed", type=finite(0, 2**32 - 1, integer=True), default=0,
                        help="random seed (noise, dropouts, pose error)")
    parser.add_argument("--points", type=finite(1000, MAX_POINTS, integer=True), default=1_000_000,
                        help=f"points on the skin (default 1,000,000; 1000 to {MAX_POINTS:,})")
    parser.add_argument("--misplacement", default="0,0,0,0,0,0", metavar="RX,RY,RZ,TX,TY,TZ",
                        help="part misplacement in the fixture: rotation vector in degrees, translation in mm "
                        "(default none)")  # fmt: skip
    parser.add_argument("--no-fixture", action="store_true", help="no fixture (no background, clamp or markers)")


def _misplacement(text: str) -> tuple[float, float, float, float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 6 or not all(np.isfinite(values)):
        raise ScanError(f"--misplacement {text[:80]!r}: expected six finite numbers RX,RY,RZ (deg),TX,TY,TZ (mm)")
    return values  # type: ignore[return-value]


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.fe.ensemble import simulate_setting
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver
    from hood_decomp.io.model_files import load_model
    from hood_decomp.io.ply import write_scan
    from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan

    out = check_output(args.out, model_inputs(args.model))
    if out.suffix.lower() == ".json":
        raise ScanError(f"--out {out}: a scan is a .ply file; its truth goes to the .json sidecar beside it")
    sidecar = check_output(out.with_suffix(".json"), model_inputs(args.model), "--out (its .json sidecar)")
    config = ScannerConfig(n_points=args.points, noise_mm=args.noise_mm, fixture=not args.no_fixture,
                           misplacement=_misplacement(args.misplacement))  # fmt: skip
    settings = parse_settings(args.settings)
    model = load_model(args.model)
    skin = skin_surface(model)
    logger.info("solving %s on %d skin nodes", settings or "the nominal setting", skin.n_nodes)
    result = simulate_setting(build_solver(model), settings)
    logger.info("scanning about %d points", args.points)
    scan = synthesize_scan(skin, result.displacement, config, seed=args.seed)
    with written_whole(out) as temporary:
        write_scan(temporary, scan.points, scanner_pose=scan.scanner_pose, markers=scan.markers,
                   marker_ids=scan.marker_ids, markers_nominal=scan.markers_nominal,
                   comments=(f"hood_decomp model_id {skin.model_id}",))
    truth = {
        "model_id": skin.model_id,
        "settings_mm": settings,
        "noise_mm": args.noise_mm,
        "seed": args.seed,
        "n_points": int(scan.points.shape[0]),
        "n_skin_points": scan.n_skin_points,
        "n_outliers": scan.n_outliers,
        "n_markers": int(scan.markers.shape[0]),
        "misplacement_deg_mm": list(config.misplacement),
        "true_transform": scan.true_transform.tolist(),
        "scanner_pose_nominal": scan.scanner_pose.tolist(),
        "max_abs_normal_displacement_mm": float(np.abs(result.normal_displacement).max()),
    }
    write_json(sidecar, truth)
    emit_json({"out": str(out), "truth": str(sidecar), "n_points": truth["n_points"], "n_markers": truth["n_markers"]})
    return 0
