"""What several verbs share: argument groups, reading their inputs, the ``--set`` syntax and writing JSON.

Verbs import from here, never from each other. Library code (file formats, the method) lives in ``io`` and ``core``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from hood_decomp.errors import FieldError, ModelError
from hood_decomp.io.json_values import json_ready

if TYPE_CHECKING:  # only for annotations: a verb's --help does not load the method
    from hood_decomp.core.method.bases import Bases
    from hood_decomp.core.types import DisplacementField, SkinSurface

#: what ``args.inputs`` holds: ("field" or "scan", path) in the order given on the command line
Inputs = list[tuple[str, Path]]


class _Inputs(argparse.Action):
    """Append (option kind, path) to ``namespace.inputs`` for every --field and --scan, in the order given."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        namespace.inputs = [*(namespace.inputs or []), (self.dest, Path(values))]


class _Input(argparse.Action):
    """Set ``namespace.inputs`` to the one (option kind, path); a repeated option replaces the earlier one."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        namespace.inputs = [(self.dest, Path(values))]


def add_bases(parser: argparse.ArgumentParser) -> None:
    """Required --bases."""
    parser.add_argument("--bases", required=True, type=Path, help="bases file written by `hood-decomp bases`")


def add_inputs(parser: argparse.ArgumentParser, repeatable: bool = False) -> None:
    """--field FIELD.vtu / --scan SCAN.ply into ``args.inputs`` (:data:`Inputs`): exactly one of them, or with
    ``repeatable`` any number of either (at least one is checked by :func:`read_fields`); and --min-coverage."""
    if repeatable:
        parser.add_argument("--field", action=_Inputs, metavar="FIELD.vtu", help="field file (repeatable)")
        parser.add_argument("--scan", action=_Inputs, metavar="SCAN.ply", help="scan point cloud (repeatable)")
    else:
        source = parser.add_mutually_exclusive_group(required=True)
        source.add_argument("--field", action=_Input, metavar="FIELD.vtu",
                            help="field file (.vtu with point data normal_displacement)")
        source.add_argument("--scan", action=_Input, metavar="SCAN.ply",
                            help="scan point cloud (.ply), converted to a field first")
    parser.add_argument("--min-coverage", type=float, default=0.2,
                        help="smallest fraction of skin nodes the field must cover (default 0.2)")
    parser.set_defaults(inputs=None)


def add_json(parser: argparse.ArgumentParser) -> None:
    """--json OUT; :func:`emit_json` prints to stdout without it."""
    parser.add_argument("--json", type=Path, default=None, help="write the result as JSON here (default: stdout)")


def add_setting(parser: argparse.ArgumentParser) -> None:
    """--set LABEL=VALUE[,...] into ``args.settings`` (text; :func:`parse_settings` reads it)."""
    parser.add_argument("--set", dest="settings", default="", metavar="LABEL=VALUE[,LABEL=VALUE...]",
                        help="mm; LABEL is a parameter label (HINGE_X) or BOUNDARY.DIRECTION (hinge_R.z, lock_L.x); "
                        "unset parameters are 0")


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


def read_fields(inputs: Inputs | None, skin: SkinSurface, min_coverage: float) -> list[DisplacementField]:
    """The displacement fields of --field and --scan inputs, in their order; FieldError when there is none."""
    from hood_decomp.io.fields import read_field
    from hood_decomp.io.scans import field_from_scan_file

    if not inputs:
        raise FieldError("give at least one --field FIELD.vtu or --scan SCAN.ply")
    return [read_field(path, skin)[0] if kind == "field" else field_from_scan_file(skin, path, min_coverage)
            for kind, path in inputs]


def read_bases_and_field(args: argparse.Namespace) -> tuple[Bases, DisplacementField]:
    """The bases of --bases and the one field of --field or --scan (:func:`add_bases`, :func:`add_inputs`)."""
    from hood_decomp.io.bases import load_bases

    bases = load_bases(args.bases)
    return bases, read_fields(args.inputs, bases.skin, args.min_coverage)[0]


def write_json(path: Path, payload: object) -> None:
    """``payload`` as indented JSON in ``path``, non-finite numbers as null."""
    path.write_text(_dumps(payload) + "\n")


def emit_json(payload: object, path: Path | None = None) -> None:
    """``payload`` as indented JSON, non-finite numbers as null: on stdout, or into ``path`` (then named on stderr)."""
    if path is None:
        print(_dumps(payload))
    else:
        write_json(path, payload)
        print(f"wrote {path}", file=sys.stderr)


def _dumps(payload: object) -> str:
    return json.dumps(json_ready(payload), indent=2, allow_nan=False)
