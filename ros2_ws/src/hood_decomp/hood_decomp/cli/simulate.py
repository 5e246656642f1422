"""`hood-decomp simulate`: one forward FE solve of a boundary setting, written as a field file (.vtu)."""

from __future__ import annotations

import argparse
import json
import sys

from hood_decomp.errors import ModelError

HELP = "one forward FE solve of a boundary setting (any boundary, declared parameter or not) -> FIELD.vtu"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, help="model directory or its model.yaml")
    parser.add_argument("--set", dest="settings", default="", metavar="LABEL=VALUE[,LABEL=VALUE...]",
                        help="mm; LABEL is a parameter label (HINGE_X) or BOUNDARY.DIRECTION (hinge_R.z, lock_L.x); "
                        "unset parameters are 0")
    parser.add_argument("--out", required=True, help="output field file (.vtu, skin point data displacement and "
                        "normal_displacement in mm)")


def parse_settings(text: str) -> dict[str, float]:
    """'A=1,B=-0.5' -> {'A': 1.0, 'B': -0.5}; ModelError on a malformed item."""
    settings: dict[str, float] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        label, sep, value = item.partition("=")
        try:
            settings[label.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not label.strip():
            raise ModelError(f"--set item {item!r}: expected LABEL=VALUE with VALUE in mm")
    return settings


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.fe.ensemble import simulate_setting
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver
    from hood_decomp.core.types import DisplacementField
    from hood_decomp.io.fields import write_field
    from hood_decomp.io.model_files import load_model

    model = load_model(args.model)
    settings = parse_settings(args.settings)
    result = simulate_setting(build_solver(model), settings)
    field = DisplacementField(model_id=model.model_id, normal_displacement=result.normal_displacement, coverage=1.0,
                              noise_rms=float("nan"))
    write_field(args.out, skin_surface(model), field, result.displacement)
    print(json.dumps({"out": args.out, "settings_mm": settings, "max_abs_normal_displacement_mm":
                      float(abs(result.normal_displacement).max()), "pad_contact_fraction": result.contact_fraction,
                      "pad_reaction_n": result.reactions}), file=sys.stdout)
    return 0
