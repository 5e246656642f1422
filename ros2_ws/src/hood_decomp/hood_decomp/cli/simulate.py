"""`hood-decomp simulate`: one forward FE solve of a boundary setting, written as a field file (.vtu)."""

from __future__ import annotations

import argparse

from hood_decomp.cli._common import add_setting, check_output, emit_json, model_inputs, parse_settings, written_whole

HELP = "one forward FE solve of a boundary setting (any boundary, declared parameter or not) -> FIELD.vtu"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, help="model directory or its model.yaml")
    add_setting(parser)
    parser.add_argument("--out", required=True, help="output field file (.vtu, skin point data displacement (the "
                        "3D field, estimate --components xyz fits it) and normal_displacement in mm)")


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.fe.ensemble import simulate_setting
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver
    from hood_decomp.core.types import DisplacementField
    from hood_decomp.io.fields import write_field
    from hood_decomp.io.model_files import load_model

    settings = parse_settings(args.settings)
    out = check_output(args.out, model_inputs(args.model))
    model = load_model(args.model)
    result = simulate_setting(build_solver(model), settings)
    field = DisplacementField(model_id=model.model_id, normal_displacement=result.normal_displacement, coverage=1.0,
                              noise_rms=float("nan"), displacement=result.displacement)
    with written_whole(out) as temporary:
        write_field(temporary, skin_surface(model), field)
    emit_json({"out": args.out, "settings_mm": settings,
               "max_abs_normal_displacement_mm": float(abs(result.normal_displacement).max()),
               "pad_contact_fraction": result.contact_fraction, "pad_reaction_n": result.reactions})
    return 0
