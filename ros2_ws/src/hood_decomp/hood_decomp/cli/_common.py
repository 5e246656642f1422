"""What several verbs share: argument groups, reading their inputs, the ``--set`` syntax and writing JSON.

Verbs import from here, never from each other. Library code (file formats, the method) lives in ``io`` and ``core``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from hood_decomp.errors import FieldError, HoodDecompError, ModelError, OutputError
from hood_decomp.io.json_values import json_ready

if TYPE_CHECKING:  # only for annotations: a verb's --help does not load the method
    from hood_decomp.core.method.bases import Bases
    from hood_decomp.core.scan.fusion import FusedField, ScanView
    from hood_decomp.core.scan.registration import MarkerNoiseCheck
    from hood_decomp.core.types import DisplacementField, SkinSurface

#: what ``args.inputs`` holds: ("field" or "scan", path) in the order given on the command line
Inputs = list[tuple[str, Path]]
#: what ``args.scanner_poses`` holds: index of a --scan in ``args.inputs`` -> its --scanner-pose POSE.json
Poses = dict[int, Path]


class _Inputs(argparse.Action):
    """Append (option kind, path) to ``namespace.inputs`` for every --field and --scan, in the order given."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        namespace.inputs = [*(namespace.inputs or []), (self.dest, Path(values))]


class _ScannerPose(argparse.Action):
    """Attach a --scanner-pose to the --scan just before it (``namespace.scanner_poses``, :data:`Poses`)."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        inputs = namespace.inputs or []
        if not inputs or inputs[-1][0] != "scan":
            parser.error(f"--scanner-pose {values}: must follow the --scan SCAN.ply it belongs to")
        poses = dict(namespace.scanner_poses or {})
        if len(inputs) - 1 in poses:
            parser.error(f"--scan {inputs[-1][1]} has two --scanner-pose options; give one per scan")
        poses[len(inputs) - 1] = Path(values)
        namespace.scanner_poses = poses


class _Input(argparse.Action):
    """Set ``namespace.inputs`` to the one (option kind, path); a repeated option replaces the earlier one."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        namespace.inputs = [(self.dest, Path(values))]


def add_bases(parser: argparse.ArgumentParser) -> None:
    """Required --bases."""
    parser.add_argument("--bases", required=True, type=Path, help="bases file written by `hood-decomp bases`")


def add_inputs(parser: argparse.ArgumentParser, repeatable: bool = False) -> None:
    """--field FIELD.vtu / --scan SCAN.ply into ``args.inputs`` (:data:`Inputs`): one field or the views of one part
    (--scan, repeatable), or with ``repeatable`` any number of either (at least one is checked by
    :func:`read_fields`); each --scan optionally followed by its --scanner-pose POSE.json (``args.scanner_poses``,
    :data:`Poses`); --min-coverage and --marker-std-mm (``args.marker_std_mm``)."""
    pose_help = ("JSON 4 x 4 row-major transform, mm, part <- scanner, of the --scan just before it; with several "
                 "--scan views every view needs one (or a pose stored in its PLY)")
    if repeatable:
        parser.add_argument("--field", action=_Inputs, metavar="FIELD.vtu", help="field file (repeatable)")
        parser.add_argument("--scan", action=_Inputs, metavar="SCAN.ply", help="scan point cloud (repeatable); "
                            "scans with a --scanner-pose are the views of one part, fused into one field")
    else:
        source = parser.add_mutually_exclusive_group(required=True)
        source.add_argument("--field", action=_Input, metavar="FIELD.vtu",
                            help="field file (.vtu with point data normal_displacement)")
        source.add_argument("--scan", action=_Inputs, metavar="SCAN.ply",
                            help="scan point cloud (.ply), converted to a field first; repeat it for several "
                            "views of one part (fused into one field)")
    parser.add_argument("--scanner-pose", action=_ScannerPose, metavar="POSE.json", help=pose_help)
    parser.add_argument("--min-coverage", type=finite(0.0, 1.0), default=0.2,
                        help="smallest fraction of skin nodes the field must cover (default 0.2)")
    parser.add_argument("--marker-std-mm", type=finite(0.0, 10.0, low_open=True), default=None, metavar="MM",
                        help="the scanner's calibrated marker-centre noise (mm per coordinate) for the marker "
                        "registration's pose covariance; default: estimated from the scan's own marker residual (8 "
                        "markers give it 18 degrees of freedom: the stated uncertainties then have Student-t tails)")
    parser.set_defaults(inputs=None, scanner_poses=None)


def add_reference(parser: argparse.ArgumentParser) -> None:
    """--reference REF.json (reference-relative estimation) into ``args.reference``; :func:`apply_reference`."""
    parser.add_argument("--reference", type=Path, default=None, metavar="REF.json",
                        help='a part in a known state: {"field": F.vtu or "scans": [S.ply], "setting": {LABEL: mm}} '
                        "(file relative to REF.json); each field becomes measured - reference + the model's field "
                        "for that state, so a static model error cancels (docs/calibration.md)")


def apply_reference(args: argparse.Namespace, bases: Bases, fields: list[DisplacementField]
                    ) -> list[DisplacementField]:
    """The fields made reference-relative when --reference was given (:func:`add_reference`), else unchanged
    (io.calibration_files.read_reference, as the nodes' ``reference`` parameter)."""
    if getattr(args, "reference", None) is None:
        return fields
    from hood_decomp.io.calibration_files import read_reference

    reference = read_reference(args.reference, bases, args.min_coverage)
    return [reference.relative(field, bases) for field in fields]


def add_json(parser: argparse.ArgumentParser) -> None:
    """--json OUT; :func:`emit_json` prints to stdout without it."""
    parser.add_argument("--json", type=Path, default=None, help="write the result as JSON here (default: stdout)")


def add_setting(parser: argparse.ArgumentParser) -> None:
    """--set LABEL=VALUE[,...] into ``args.settings`` (text; :func:`parse_settings` reads it)."""
    parser.add_argument("--set", dest="settings", default="", metavar="LABEL=VALUE[,LABEL=VALUE...]",
                        help="mm; LABEL is a parameter label (HINGE_X) or BOUNDARY.DIRECTION (hinge_R.z, lock_L.x); "
                        "unset parameters are 0")


def parse_settings(text: str) -> dict[str, float]:
    """'A=1,B=-0.5' -> {'A': 1.0, 'B': -0.5}; ModelError on a malformed item or a value that is not finite or beyond
    the plausible field bound (io.fields.MAX_ABS_MM)."""
    from hood_decomp.io.fields import MAX_ABS_MM

    settings: dict[str, float] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        label, sep, value = item.partition("=")
        try:
            settings[label.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not label.strip():
            raise ModelError(f"--set item {item[:80]!r}: expected LABEL=VALUE with VALUE in mm")
        if not math.isfinite(settings[label.strip()]):
            raise ModelError(f"--set item {item[:80]!r}: the value must be a finite number of mm")
        if abs(settings[label.strip()]) > MAX_ABS_MM:
            raise ModelError(f"--set item {item[:80]!r}: at most {MAX_ABS_MM:g} mm (a boundary setting beyond that "
                             "makes a field no reader accepts)")
    return settings


def finite(low: float = -math.inf, high: float = math.inf, *, integer: bool = False, low_open: bool = False,
           why: str = "") -> Callable[[str], float | int]:
    """An argparse ``type``: a finite number (``integer``: a whole one, "1e6" allowed) in [low, high] (``low_open``:
    > low), else a one-line usage error naming the option, before any work; ``why`` says where a bound comes from.
    NaN and inf never reach a computation through a command-line number."""

    def parse(text: str) -> float | int:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if (math.isfinite(value) and (value > low or (value == low and not low_open)) and value <= high
                and (not integer or value == int(value))):
            return int(value) if integer else value
        bound = f"{'(' if low_open else '['}{low:g}, {high:g}]"
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a finite {'whole number' if integer else 'number'} in {bound}{why}")

    parse.__name__ = "integer" if integer else "number"  # argparse names the type in its message
    return parse


# --- outputs: checked before any work, never an input, written whole or not at all -------------------------------
def check_output(path: Path | str, inputs: Iterable[Path | str], option: str = "--out", *, directory: bool = False,
                 writes: Iterable[str] = (), parents: bool = False) -> Path:
    """Check an output before any work; return it as a Path. OutputError when its directory (for ``directory``
    outputs: its parent, or itself when it exists) is missing or not writable (tried by creating and removing a file
    there, so it holds for root and read-only mounts too), when it is a directory where a file is wanted or a file
    where a directory is, or when it (or a file ``writes`` names inside a directory output) is one of ``inputs``:
    same resolved path or same file (hard links, ``os.path.samefile``). ``parents``: a directory output whose
    missing parents the verb creates (then the nearest existing ancestor must be writable)."""
    wants_directory = str(path).endswith(("/", os.sep))
    path = Path(path)
    if directory:
        if path.exists() and not path.is_dir():
            raise OutputError(f"{option} {path} is a file; expected a directory")
        targets = [path / name for name in writes]
        place = path if path.is_dir() else path.parent
        while parents and not place.exists() and place != place.parent:
            place = place.parent
    else:
        if path.is_dir() or wants_directory:
            raise OutputError(f"{option} {path} is a directory; expected a file name")
        targets, place = [path], path.parent
    if not place.is_dir():
        raise OutputError(f"{option} {path}: directory {place} does not exist")
    try:
        handle, probe = tempfile.mkstemp(prefix=".hood_decomp_probe_", dir=place)
        os.close(handle)
        os.unlink(probe)
    except OSError as error:
        raise OutputError(f"{option} {path}: cannot write in {place}: {error.strerror}") from error
    for source in inputs:
        source = Path(source)
        for target in targets:
            if target.resolve() == source.resolve() or (target.exists() and source.exists()
                                                         and os.path.samefile(target, source)):
                raise OutputError(f"{option} {path} would overwrite the input {source}; choose another output")
    return path


@contextmanager
def written_whole(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix) to write to; on success it replaces ``path`` in one
    rename, on failure it is removed: a failed verb never leaves a half file or a clobbered old one."""
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(handle)
    try:
        yield Path(temporary)
        os.chmod(temporary, _file_mode(path))  # mkstemp makes 0600; the output gets what a plain write would give
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _file_mode(path: Path) -> int:
    """The mode of the file at ``path`` if there is one, else what a new file gets under the process's umask."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


@contextmanager
def written_whole_directory(path: Path) -> Iterator[Path]:
    """Yield a temporary directory beside ``path`` to write files into; on success each file moves into ``path``
    (created when missing) by rename, on failure the temporary directory is removed."""
    parent = path if path.is_dir() else path.parent
    temporary = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=parent))
    try:
        yield temporary
        path.mkdir(exist_ok=True)
        for item in sorted(temporary.rglob("*")):
            target = path / item.relative_to(temporary)
            if item.is_dir():
                target.mkdir(exist_ok=True)
            else:
                os.replace(item, target)
    finally:
        shutil.rmtree(temporary, ignore_errors=True)


def model_inputs(model: Path | str) -> list[Path]:
    """The files a --model argument reads (model.yaml and its mesh), for :func:`check_output`."""
    from hood_decomp.io.model_files import model_files

    return model_files(model)


def input_paths(args: argparse.Namespace) -> list[Path]:
    """Every file --field, --scan and --scanner-pose name (for :func:`check_output`)."""
    return [*(path for _, path in args.inputs or []), *(args.scanner_poses or {}).values()]


def _scan_inputs(inputs: Inputs, poses: Poses) -> list[tuple[Path, Path | None]]:
    """The --scan paths of ``inputs`` in their order, each with its --scanner-pose (keyed by input index) or None."""
    return [(path, poses.get(i)) for i, (kind, path) in enumerate(inputs) if kind == "scan"]


def read_fields(inputs: Inputs | None, skin: SkinSurface, min_coverage: float,
                poses: Poses | None = None, one_part: bool = False,
                views: Sequence[ScanView] | None = None, marker_std_mm: float | None = None,
                marker_checks: list[dict] | None = None) -> list[DisplacementField]:
    """The displacement fields of --field and --scan inputs, in their order; FieldError when there is none.

    The scans are the views of one part, fused into one field in the place of the first (each with its
    --scanner-pose from ``poses``, else the pose its PLY stores), when ``one_part`` (a verb that reads one part) or
    when any scan has a --scanner-pose; otherwise every scan is a field of its own. ``views``: those fused scans'
    views when the caller read them already (:func:`read_bases_and_field`). ``marker_std_mm``: --marker-std-mm;
    ``marker_checks``: a list that receives :func:`marker_check_payload` of every scan view registered by markers
    with it (what the JSON reports; a rejected value is also a warning line on stderr).
    """
    from hood_decomp.io.fields import read_field
    from hood_decomp.io.scans import fused_field_from_scan_files

    if not inputs:
        raise FieldError("give at least one --field FIELD.vtu or --scan SCAN.ply")
    poses = poses or {}
    scans = _scan_inputs(inputs, poses)
    fields: list[DisplacementField] = []
    fused_done = False

    def field_of(fused: FusedField) -> DisplacementField:
        if marker_checks is not None:
            marker_checks.extend(marker_check_payload(view.name, view.registration.marker_noise)
                                 for view in fused.views if view.registration.marker_noise is not None)
        return fused.field

    for kind, path in inputs:
        if kind == "field":
            fields.append(read_field(path, skin)[0])
        elif one_part or poses:
            if not fused_done:
                fields.append(field_of(fused_field_from_scan_files(skin, scans, min_coverage, views, marker_std_mm)))
                fused_done = True
        else:
            fields.append(field_of(fused_field_from_scan_files(skin, [(path, None)], min_coverage,
                                                               marker_std_mm=marker_std_mm)))
    return fields


def marker_checks_or_none(args: argparse.Namespace, checks: list[dict]) -> list[dict] | None:
    """The JSON's ``marker_noise_checks``: null without --marker-std-mm (nothing stated, nothing checked), else one
    :func:`marker_check_payload` per scan view registered by markers."""
    return None if args.marker_std_mm is None else checks


def marker_check_payload(view: str, check: MarkerNoiseCheck) -> dict:
    """The check of a stated marker noise (core.scan.registration.check_marker_noise) as the JSON reports it:
    ``view``, ``stated_mm``, ``estimated_mm``, ``used_mm`` (what the pose covariance used), ``chi2``, ``dof``,
    ``p_value`` (two-sided), ``alpha``, ``accepted`` and ``reason`` ("" when accepted)."""
    return {"view": view, "stated_mm": check.stated_mm, "estimated_mm": check.estimated_mm,
            "used_mm": check.used_mm, "chi2": check.chi2, "dof": check.dof, "p_value": check.p_value,
            "alpha": check.alpha, "accepted": check.accepted, "reason": check.reason}


def read_bases_and_field(args: argparse.Namespace, meanwhile: Callable[[Bases], object] | None = None,
                         marker_checks: list[dict] | None = None) -> tuple[Bases, DisplacementField]:
    """The bases of --bases and the one field of --field or of the --scan views of one part (:func:`add_bases`,
    :func:`add_inputs`). The scan files are read in a second thread while the bases load (neither needs the other;
    a bad bases file still fails first, by its own error). ``meanwhile(bases)``: work that needs only the bases, run
    in a second thread while the field is made (a scan: its prepared skin and scan path), finished before this
    returns; a HoodDecompError there is left to the caller's own call of that work, which raises it again.
    ``marker_checks``: as :func:`read_fields`."""
    from hood_decomp.io.bases import load_bases
    from hood_decomp.io.scans import scan_file_views

    inputs = args.inputs or []
    scans = _scan_inputs(inputs, args.scanner_poses or {})
    with ThreadPoolExecutor(2) as pool:
        early = pool.submit(scan_file_views, scans) if scans and len(scans) == len(inputs) else None
        bases = load_bases(args.bases, mapped=True)  # a verb's process ends soon: the file's pages as they are
        pending = None if meanwhile is None else pool.submit(meanwhile, bases)
        fields = read_fields(args.inputs, bases.skin, args.min_coverage, args.scanner_poses, one_part=True,
                             views=None if early is None else early.result(), marker_std_mm=args.marker_std_mm,
                             marker_checks=marker_checks)
        if pending is not None:
            with contextlib.suppress(HoodDecompError):
                pending.result()
    return bases, apply_reference(args, bases, fields[:1])[0]


def write_json(path: Path, payload: object) -> None:
    """``payload`` as indented JSON in ``path`` (whole or not at all), non-finite numbers as null."""
    text = _dumps(payload) + "\n"
    with written_whole(Path(path)) as temporary:
        temporary.write_text(text)


def check_json(args: argparse.Namespace) -> list[Path]:
    """Check --json (when given) against the inputs of --bases, --field and --scan before any work (:func:`add_json`);
    return those inputs."""
    inputs = [args.bases, *input_paths(args)]
    if getattr(args, "reference", None) is not None:
        inputs.append(args.reference)
    if args.json is not None:
        check_output(args.json, inputs, "--json")
    return inputs


def emit_json(payload: object, path: Path | None = None) -> None:
    """``payload`` as indented JSON, non-finite numbers as null: on stdout, or into ``path`` (then named on stderr)."""
    if path is None:
        print(_dumps(payload))
    else:
        write_json(path, payload)
        print(f"wrote {path}", file=sys.stderr)


def _dumps(payload: object) -> str:
    return json.dumps(json_ready(payload), indent=2, allow_nan=False)
