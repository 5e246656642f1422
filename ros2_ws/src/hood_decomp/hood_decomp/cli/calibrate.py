"""`hood-decomp calibrate`: bases calibrated to the real part from fields or scans in known settings (issue 16)."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from hood_decomp.cli._common import check_output, finite, model_inputs, written_whole

HELP = "calibrate bases to the real part from fields or scans with known settings"

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bases", required=True, type=Path, help="bases file to calibrate (with its reduced model)")
    parser.add_argument("--model", required=True, type=Path,
                        help="model directory of the bases (the gas-spring, thermal and thickness responses come from "
                        "it when the bases file does not hold them)")
    parser.add_argument("--cal", required=True, type=Path, metavar="CAL.json",
                        help='calibration entries: a JSON list of {"field": F.vtu, "setting": {LABEL: mm}} or '
                        '{"scans": [S.ply], "setting": {...}}; files relative to CAL.json (docs/calibration.md)')
    parser.add_argument("--out", required=True, type=Path, help="calibrated bases file to write (HDF5)")
    parser.add_argument("--min-coverage", type=finite(0.0, 1.0), default=0.2,
                        help="smallest fraction of skin nodes a scan entry must cover (default 0.2)")


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.loop.calibration import CalibrationEntry, calibrate, model_physics, rebuild_bases
    from hood_decomp.core.loop.scan_skin import with_reading_bias
    from hood_decomp.errors import CalibrationError
    from hood_decomp.io.bases import bases_id, load_bases, save_bases
    from hood_decomp.io.calibration_files import read_entries
    from hood_decomp.io.model_files import load_model

    out = check_output(args.out, [args.bases, args.cal, *model_inputs(args.model)])
    bases = load_bases(args.bases)
    if bases.reduced_model is None:
        raise CalibrationError(f"{args.bases} holds no reduced model (build the bases with --model)")
    model = load_model(args.model)
    if model.model_id != bases.model_id:
        raise CalibrationError(f"model {args.model} (model_id {model.model_id}) is not the bases' ({bases.model_id})")
    read = read_entries(args.cal, bases.skin, args.min_coverage)
    entries = [CalibrationEntry(e.name, e.field, e.setting_vector(bases.names)) for e in read]
    if bases.physics is not None:  # written by `bases --model`: as the model gives them, checked on reading
        logger.info("calibrate: %d entries; the model's physical responses from the bases file", len(entries))
        physics = bases.physics.with_3d()
    else:
        logger.info("calibrate: %d entries; the model's gas-spring, thermal and thickness responses (one "
                    "factorisation and one per sheet group)", len(entries))
        physics = model_physics(model, bases.reduced_model)
    # scanned entries lose the scan step's bias inside the basis as the calibrated bases' scans will (a file written
    # before it was stored measures it now: else the calibration would learn it and the estimator take it out again)
    scanned = any(entry.field.errors.kind == "scan" for entry in entries)
    reading = with_reading_bias(bases).reading() if scanned else None
    reduced, calibration = calibrate(bases.reduced_model, physics, entries, bases.skin,
                                     (bases.pca.lower_, bases.pca.upper_), reading)
    record = calibration.record()
    record["settings_mm"] = {e.name: e.setting for e in read}
    record["from_bases_id"] = bases_id(bases)
    calibrated = rebuild_bases(bases, reduced, json.dumps(record, sort_keys=True), physics, **calibration.error_terms())
    with written_whole(out) as temporary:
        save_bases(temporary, calibrated)
    print(f"wrote {out}: calibration {record['id']} from {len(entries)} entries, leave-one-out RMS "
          f"{record['loo_rms_mm']:.4f} mm (noise {record['noise_mm']:.4f} mm), correction rank {record['rank']}, "
          f"model discrepancy rank {record['discrepancy']['rank']} RMS {record['discrepancy']['rms_mm']:.4f} mm, "
          f"bases_id {bases_id(calibrated)}")
    return 0
