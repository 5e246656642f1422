"""Harness (ii), model discrepancy (issue 15): does the system *say* when the part is not its model?

Truth from another model than the bases (the default hood's, built at ``--resolution``: coarse for counts, default
for a spot check where the gate can open):
- ``physics_*``: the same hood and mesh with perturbed physics, the bases' own embedded solver through
  :class:`~hood_decomp.synthetic.standin.StandIn` (:func:`~hood_decomp.synthetic.standin.embedded_responses`):
  Young's modulus x (1 +- 3 %), skin and all sheet thicknesses x (1 +- 5 %), pad stiffness x (1 +- 30 %), gas-spring
  force x (1 +- 5 %), one factor at a time (uniform in its range) and ``physics_all`` (all four at once);
- ``mesh_default``: the hood solved on the default mesh (30,107 skin nodes) against coarse bases (4,736);
- ``ccx_nominal`` / ``ccx_family``: CalculiX S8R responses (cached npz of :func:`calculix_responses`, never run here)
  at nominal physics and with a drawn :class:`Family` (E, thickness, pads, preload, gas springs).
Each part: random commanded states in the declared ranges, solved with exact pad contact; scanned by the synthetic
scanner (120k points, 0.02 mm range noise, 3 holes, scanner 0.5 deg / 5 mm off, 8 fixture markers with 0.02 mm centre
noise) and turned into a field by the scan step with its error model; estimated through the path users take
(``estimate_field``: contact-aware estimate, covariance from the field's error model, the one within-model test) and
gated by ``plan_correction`` (the estimator node's ``BoundaryCorrection``). The same truth is also judged as a field
with 0.02 mm white node noise stated as its error model (``field`` rows: no scan step, so no registration std: the
only place where the gate can open and the safety count means something).

"Moved": the discrepancy's own shift of the estimate, measured noise-free: the estimate of the exact truth field
(on the scan's seen nodes, with the scan's error model) minus the truth, in units of the stated std of the scanned
estimate; a part is moved when any parameter is shifted by more than 2 std. Caught: the test alarms or
``safe_to_apply`` is false; "said model": the reason says the model does not explain the part (the alarm) rather
than naming a boundary's uncertainty or range. Unsafe: ``safe_to_apply`` true with an applicable correction wrong by
more than 0.02 mm; "appl>0.02": parts where a boundary the correction states ``applicable`` (what the robot may
still apply when the whole is not safe) is wrong by more than 0.02 mm; "w/o": the same with the gate ignoring the
model's physical factors (``model_std``, core/method/model_spread.py), as it was before them. "3x": the alarm rate
with the node noise stated 3 times too large.

The bases carry the FE model's responses to gas springs and thickness, so the gate's model std counts all five
factors (``--without-physics``: compliance, pads and preload only, as bases files without ``/physics`` do;
``--through-file``: the bases written by ``save_bases`` as ``bases --model`` writes them and read back by
``load_bases``, the path a bases file's user takes). ``--own-parts``: harness (i)
parts (truth from the bases' own reduced model) through the same path. ``--calibrate ccx|embedded``: the bases are
first calibrated (core.loop.calibration, 13 one-at-a-time entries with 0.02 mm noise) to a family drawn from the seed,
made by CalculiX (coarse cache) or by the embedded solver re-solved with the family's physics; ``calibrated_family``
parts are of that family (harness (ii) on the calibrated bases); ``--scanned-entries``: the entries are scans of the
family taken as the parts' are (a cell calibrates with its own scanner), not white-noise fields;
``--entry-moves 0.8 0.4`` (25 entries) and ``--entry-repeats K`` (each setting K times) make larger calibrations;
``--harness-markers``: every scan with harness (i)'s marker noise (0.02-0.05 mm drawn per scan, stated) and 0-8 holes.
Besides the gate,
a table per boundary of error / sqrt(std^2 + model_std^2) (is each error inside its total stated uncertainty).

Prints a table per kind and writes benchmarks/out/discrepancy.json (rewritten as it goes). From the repository root:
    scripts/with-env nice python benchmarks/bench_discrepancy.py [--parts N] [--mesh-parts N] [--ccx-parts N]
        [--own-parts N] [--calibrate ccx|embedded [--scanned-entries] [--entry-moves MM ...] [--entry-repeats K]]
        [--harness-markers]
        [--without-physics] [--through-file] [--kinds ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.interpolate import LinearNDInterpolator

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_uncertainty import judge, start_run  # noqa: E402

from hood_decomp.core.fe.ensemble import solve_members  # noqa: E402
from hood_decomp.core.fe.hood_preset import build_preset  # noqa: E402
from hood_decomp.core.fe.model import skin_surface  # noqa: E402
from hood_decomp.core.fe.solver import (  # noqa: E402
    build_solver,
    reduce_model,
)
from hood_decomp.core.loop.calibration import (  # noqa: E402
    CalibrationEntry,
    calibrate,
    model_physics,
    one_at_a_time,
    rebuild_bases,
)
from hood_decomp.core.loop.scan_skin import with_reading_bias  # noqa: E402
from hood_decomp.core.method.bases import estimate_field  # noqa: E402
from hood_decomp.core.method.correction import plan_correction  # noqa: E402
from hood_decomp.core.method.model_spread import PhysicalResponses  # noqa: E402
from hood_decomp.core.scan.scan_field import field_from_scan, prepared_estimator  # noqa: E402
from hood_decomp.core.types import DisplacementField, FieldErrorModel  # noqa: E402
from hood_decomp.io.bases import load_bases, save_bases  # noqa: E402
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan  # noqa: E402
from hood_decomp.synthetic.standin import (  # noqa: E402
    FAMILY_SPREAD,
    Family,
    StandIn,
    calculix_responses,
    embedded_responses,
)
from tests.core.method.test_truth_elsewhere import _grid_coordinates  # noqa: E402

OUT = ROOT / "benchmarks" / "out" / "discrepancy.json"
CCX_CACHE = ROOT / "benchmarks" / "out" / "standin_ccx_coarse.npz"  # as bench_calibration's
NOISE_MM = 0.02
MOVED_STD = 2.0
UNSAFE_MM = 0.02
PHYSICS = {"physics_E": ("E",), "physics_thickness": ("thickness",), "physics_pad": ("pad_stiffness",),
           "physics_gas": ("gas_spring",), "physics_all": ("E", "thickness", "pad_stiffness", "gas_spring")}


def log(line: str) -> None:
    print(f"[bench_discrepancy {time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


def inflated(field: DisplacementField, factor: float = 3.0) -> DisplacementField:
    """The field with its node noise stated ``factor`` times too large."""
    errors = field.errors
    return dataclasses.replace(field, noise_rms=factor * field.noise_rms,
                               error_model=dataclasses.replace(errors, node_std=factor * errors.node_std))


def verdict(bases, field: DisplacementField, truth_field: np.ndarray, member, names) -> dict:
    """One part judged: ``judge``'s row, the noise-free shift in stated std, caught, said model, 3x alarm."""
    estimate = estimate_field(bases, field)
    row = judge(estimate, member, names)
    clean = np.where(np.isfinite(field.normal_displacement), truth_field, np.nan)
    # the truth's node displacement through the same estimator and error model (not estimate_field: it would add a
    # slide to it as to a scan's reading, up to 2 std of a default-hood scan's estimate)
    noise_free = dataclasses.replace(field, normal_displacement=clean)
    shift = bases.contact_estimator().estimate(noise_free).values - member.effective[0]
    row["shift_z"] = [float(v) for v in shift / estimate.std]
    row["moved"] = bool(np.max(np.abs(shift / estimate.std)) > MOVED_STD)
    row["caught"] = (not row["within"]) or (not row["safe"])
    row["said_model"] = "model" in row["reasons"]
    row["reason"] = plan_correction(estimate).reason  # judge's row has what the robot may apply, before and after
    row["within_3x"] = bool(estimate_field(bases, inflated(field)).within_model)
    row["max_abs_error_mm"] = float(np.max(np.abs(estimate.values - member.effective[0])))
    return row


def summary(rows: list[dict], names: tuple[str, ...]) -> dict:
    if not rows:
        return {"n": 0}
    moved = [r for r in rows if r["moved"]]
    kinds = [kind for r in rows for kind in r["reasons"]]
    return {
        "n": len(rows),
        "alarm_rate": float(np.mean([not r["within"] for r in rows])),
        "alarm_rate_noise_stated_3x": float(np.mean([not r["within_3x"] for r in rows])),
        "gate_open_rate": float(np.mean([r["safe"] for r in rows])),
        "moved": len(moved),
        "moved_caught": sum(r["caught"] for r in moved),
        "moved_alarmed": sum(not r["within"] for r in moved),
        "alarms_without_model_message": sum(not r["within"] and not r["said_model"] for r in rows),
        "moved_caught_rate": float(np.mean([r["caught"] for r in moved])) if moved else None,
        "moved_alarm_rate": float(np.mean([not r["within"] for r in moved])) if moved else None,
        "median_max_shift_z": float(np.median([np.max(np.abs(r["shift_z"])) for r in rows])),
        "unsafe": sum(r["safe"] and r["applied_error_mm"] > UNSAFE_MM for r in rows),
        "unsafe_before": sum(r["safe_before"] and r["applicable_error_before_mm"] > UNSAFE_MM for r in rows),
        "applicable_wrong_before": sum(r["applicable_error_before_mm"] > UNSAFE_MM for r in rows),
        "max_applicable_error_before_mm": float(max(r["applicable_error_before_mm"] for r in rows)),
        "applicable_boundaries_before": {name: sum(name in r["applicable_before"] for r in rows) for name in names},
        "applicable_wrong": sum(r["applicable_error_mm"] > UNSAFE_MM for r in rows),
        "max_applicable_error_mm": float(max(r["applicable_error_mm"] for r in rows)),
        "applicable_boundaries": {name: sum(name in r["applicable"] for r in rows) for name in names},
        "max_applied_error_mm": float(max(r["applied_error_mm"] for r in rows)),
        "gate_closed_by": {kind: kinds.count(kind) for kind in sorted(set(kinds))},
        "z_total": z_table(rows, names),
    }


def z_table(rows: list[dict], names: tuple[str, ...]) -> dict:
    """Per boundary, the errors against the total uncertainty sqrt(std^2 + model_std^2) (where the estimate's contact
    state is the truth's): count, largest |z|, fractions within 2 and 3."""
    out = {}
    for i, name in enumerate(names):
        z = np.abs([r["z_total"][i] for r in rows if r["z_total"][i] is not None])
        out[name] = {"n": int(z.size), "max": float(z.max(initial=0.0)),
                     "within_2": float(np.mean(z <= 2.0)) if z.size else None,
                     "within_3": float(np.mean(z <= 3.0)) if z.size else None}
    return out


def calibrated_bases(bases, physics: PhysicalResponses, truth, rng: np.random.Generator, scan=None,
                     moves: tuple[float, ...] = (0.8,), repeats: int = 1):
    """``bases`` calibrated (core.loop.calibration, as ``hood-decomp calibrate``) from the one-at-a-time plan's
    entries of the part model ``truth`` (exact pad contact; 13 with one move, each setting taken ``repeats`` times):
    fields with 0.02 mm white noise stated as the error model, or, with ``scan`` (a member's 3D displacement (n, 3)
    -> scanned field), scans of the part as a cell would take them (the scanner, the marker registration and the scan
    step of the parts)."""
    settings = np.repeat(one_at_a_time(len(bases.names), moves), repeats, axis=0)
    members = solve_members(truth, settings)
    n = bases.skin.n_nodes

    def entry_field(j: int) -> DisplacementField:
        if scan is not None:
            return scan(members.displacement[j])
        return DisplacementField(bases.model_id, members.normal_displacement[j] + rng.normal(0.0, NOISE_MM, n), 1.0,
                                 NOISE_MM, FieldErrorModel.stated(NOISE_MM, n))

    entries = [CalibrationEntry(f"entry {j}", entry_field(j), settings[j]) for j in range(len(settings))]
    reduced, calibration = calibrate(bases.reduced_model, physics, entries, bases.skin,
                                     (bases.pca.lower_, bases.pca.upper_), with_reading_bias(bases).reading())
    # as `hood-decomp calibrate` writes them: the rebuilt basis with its own scan reading bias
    return with_reading_bias(rebuild_bases(bases, reduced, json.dumps(calibration.record(), sort_keys=True), physics,
                                           **calibration.error_terms()))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=int, default=60, help="parts per physics_* kind")
    parser.add_argument("--mesh-parts", type=int, default=60, help="parts of mesh_default (0: skip)")
    parser.add_argument("--ccx-parts", type=int, default=60, help="parts per ccx_* kind (0: skip)")
    parser.add_argument("--ccx-cache", type=Path, default=CCX_CACHE, help="CalculiX responses (never computed here)")
    parser.add_argument("--resolution", choices=("coarse", "default"), default="coarse",
                        help="the bases' (and the physics_* and ccx_* truths') resolution; mesh_default needs coarse")
    parser.add_argument("--points", type=int, default=None,
                        help="scan points on the skin (default: 120,000 at coarse, 500,000 at default resolution)")
    parser.add_argument("--kinds", nargs="+", default=None, help="only these kinds")
    parser.add_argument("--without-physics", action="store_true",
                        help="bases without the responses to thickness and gas springs (model_std without them)")
    parser.add_argument("--through-file", action="store_true",
                        help="the bases written to a file (with /physics unless --without-physics) and read back "
                             "(load_bases, mapped as the command line reads it)")
    parser.add_argument("--own-parts", type=int, default=0,
                        help="parts of own_model: harness (i), truth from the bases' own reduced model (0: skip)")
    parser.add_argument("--calibrate", choices=("ccx", "embedded"), default=None,
                        help="first calibrate the bases (13 entries unless said, 0.02 mm noise) to a family drawn "
                             "from the seed, made by CalculiX (coarse, needs --ccx-cache) or by the embedded solver "
                             "re-solved with that family's physics (any resolution); calibrated_family: parts of that "
                             "family")
    parser.add_argument("--scanned-entries", action="store_true",
                        help="with --calibrate: the calibration entries are scans of the family (as the parts'), "
                             "not fields with 0.02 mm white node noise")
    parser.add_argument("--entry-moves", type=float, nargs="+", default=(0.8,),
                        help="with --calibrate: the one-at-a-time moves, mm (0.8: 13 entries; 0.8 0.4: 25)")
    parser.add_argument("--entry-repeats", type=int, default=1,
                        help="with --calibrate: each calibration setting taken this many times (3: 39 entries)")
    parser.add_argument("--harness-markers", action="store_true",
                        help="scans with harness (i)'s marker noise, 0.02-0.05 mm drawn per scan and stated, and 0-8 "
                             "holes (default: 0.02 mm markers estimated from their residual, 3 holes)")
    parser.add_argument("--seed", type=int, default=152)
    parser.add_argument("--out", type=Path, default=OUT, help="JSON written as the run goes")
    args = parser.parse_args()
    case, rng, results, save = start_run(args, log, kinds={})
    skin, model = case.skin, case.model
    log("the FE model's responses to gas springs and sheet thickness (the model's factors, model_spread)")
    physics = model_physics(model, case.reduced, case.solver)
    # --without-physics: the gate as before thickness and gas springs were considered (for the comparison)
    bases = dataclasses.replace(case.bases, physics=None if args.without_physics else physics)
    held = tempfile.TemporaryDirectory()  # the file stays while the run reads it (mapped)
    if args.through_file:
        save_bases(Path(held.name) / "bases.h5", bases)
        bases = load_bases(Path(held.name) / "bases.h5", mapped=True)
    names = bases.names
    lo, hi = bases.pca.lower_, bases.pca.upper_
    est = prepared_estimator(skin)
    ccx = StandIn(model, calculix_responses(model, cache=args.ccx_cache)) \
        if args.ccx_cache.exists() and args.resolution == "coarse" else None

    def scan_field(truth_skin, displacement) -> DisplacementField:
        # --harness-markers: harness (i)'s marker noise (0.02-0.05 mm, stated by the scanner) and holes (0-8)
        markers, holes = ((float(rng.uniform(0.02, 0.05)), int(rng.integers(0, 9))) if args.harness_markers
                          else (NOISE_MM, 3))
        config = ScannerConfig(n_points=args.points, noise_mm=NOISE_MM, marker_noise_mm=markers, n_holes=holes)
        synthetic = synthesize_scan(truth_skin, displacement, config, seed=int(rng.integers(1 << 30)))
        field, _ = field_from_scan(skin, synthetic.points, markers_mm=synthetic.markers,
                                   markers_nominal_mm=synthetic.markers_nominal, estimator=est,
                                   marker_std_mm=markers if args.harness_markers else None)
        return field

    if args.calibrate == "embedded":
        log("the embedded solver's responses at three thickness scales (the calibration's stand-in)")
        ccx = StandIn(model, embedded_responses(model))
    elif args.calibrate and ccx is None:
        raise SystemExit(f"--calibrate ccx needs the coarse CalculiX cache ({args.ccx_cache})")
    if args.calibrate:
        family = Family.draw(rng)
        bases = calibrated_bases(bases, physics, ccx.reduced(family), rng,
                                 (lambda u: scan_field(skin, u)) if args.scanned_entries else None,
                                 tuple(args.entry_moves), args.entry_repeats)
        results["calibrated_to"] = dataclasses.asdict(family) | {"by": args.calibrate,
                                                                 "record": json.loads(bases.calibration)}
        log(f"calibrated to the CalculiX family {family}")

    def noisy_field(truth: np.ndarray) -> DisplacementField:
        values = truth + rng.normal(0.0, NOISE_MM, truth.size)
        return DisplacementField(skin.model_id, values, 1.0, NOISE_MM, FieldErrorModel.stated(NOISE_MM, truth.size))

    def run(kind: str, n: int, draw) -> None:
        """draw() -> (member, truth skin, truth normal field on the bases' skin nodes, description)."""
        if (args.kinds and kind not in args.kinds) or n <= 0:
            return
        rows: dict[str, list[dict]] = {"scan": [], "field": []}
        start = time.time()
        for k in range(n):
            member, truth_skin, truth_normal, about = draw()
            row = verdict(bases, scan_field(truth_skin, member.displacement[0]), truth_normal, member, names)
            rows["scan"].append(row | about)
            rows["field"].append(verdict(bases, noisy_field(truth_normal), truth_normal, member, names) | about)
            if (k + 1) % 10 == 0 or k + 1 == n:
                results["kinds"][kind] = {way: {"summary": summary(r, names), "parts": r} for way, r in rows.items()}
                save()
                s = results["kinds"][kind]["scan"]["summary"]
                log(f"{kind} {k + 1}/{n}: {(time.time() - start) / (k + 1):.1f} s per part, scan alarms "
                    f"{s['alarm_rate']:.2f}, moved {s['moved']}, caught {s['moved_caught']}, unsafe {s['unsafe']}")

    if args.own_parts and (not args.kinds or "own_model" in args.kinds):
        def draw_own():  # harness (i): the bases' own model, measured
            member = solve_members(bases.reduced_model, rng.uniform(lo, hi)[None])
            return member, skin, member.normal_displacement[0], {}
        run("own_model", args.own_parts, draw_own)
    if args.calibrate and args.ccx_parts:
        def draw_family():  # harness (ii) on the calibrated bases: the family they were calibrated to
            member = solve_members(ccx.reduced(family), rng.uniform(lo, hi)[None])
            return member, skin, member.normal_displacement[0], {}
        run("calibrated_family", args.ccx_parts, draw_family)

    perturbed = [kind for kind in PHYSICS if not args.kinds or kind in args.kinds] if args.parts else []
    if perturbed:
        log("the embedded solver's responses at three thickness scales (perturbed physics)")
        standin = StandIn(model, embedded_responses(model))
    for kind in perturbed:
        factors = PHYSICS[kind]
        def draw_physics(factors=factors):
            family = Family(**{key: float(1.0 + rng.uniform(-FAMILY_SPREAD[key], FAMILY_SPREAD[key]))
                               for key in factors})
            member = solve_members(standin.reduced(family), rng.uniform(lo, hi)[None])
            about = {key: getattr(family, key) for key in factors}
            return member, skin, member.normal_displacement[0], about
        run(kind, args.parts, draw_physics)

    if args.mesh_parts and args.resolution == "coarse" and (not args.kinds or "mesh_default" in args.kinds):
        log("the default-resolution hood (truth on a finer mesh than the coarse bases)")
        fine = build_preset("hood", "default")
        fine_skin = skin_surface(fine)
        fine_reduced = reduce_model(build_solver(fine))
        source, target = _grid_coordinates(fine_skin.points), _grid_coordinates(skin.points)

        def draw_mesh():  # the noise-free truth on the coarse nodes: linear in the skin's grid coordinates
            member = solve_members(fine_reduced, rng.uniform(lo, hi)[None])
            return member, fine_skin, LinearNDInterpolator(source, member.normal_displacement[0])(target), {}
        run("mesh_default", args.mesh_parts, draw_mesh)

    if args.ccx_parts and args.resolution != "coarse" and not args.calibrate:
        results["ccx"] = "not run: the CalculiX cache is the coarse hood's"
    elif args.ccx_parts and ccx is not None and not args.calibrate:
        log(f"CalculiX S8R responses from {args.ccx_cache}")
        for kind, family_of in (("ccx_nominal", lambda: Family()), ("ccx_family", lambda: Family.draw(rng))):
            def draw_ccx(family_of=family_of):
                family = family_of()
                member = solve_members(ccx.reduced(family), rng.uniform(lo, hi)[None])
                return member, skin, member.normal_displacement[0], dataclasses.asdict(family)
            run(kind, args.ccx_parts, draw_ccx)
    elif args.ccx_parts and not args.calibrate:
        log(f"no CalculiX cache at {args.ccx_cache}: the ccx kinds are not run")
        results["ccx"] = f"not run: no cache at {args.ccx_cache}"
    save()

    print(f"{'kind':<18} {'way':<6} {'n':>4} {'alarm':>6} {'3x':>5} {'open':>5} {'moved':>6} {'caught':>7} "
          f"{'alarmed':>8} {'unsafe':>6} {'max applied':>11} {'appl>0.02':>9} {'max appl':>8} "
          f"{'unsafe w/o model std':>20} {'appl>0.02 w/o':>13} {'max appl w/o':>12}")
    for kind, ways in results["kinds"].items():
        for way, block in ways.items():
            s = block["summary"]
            print(f"{kind:<18} {way:<6} {s['n']:>4} {s['alarm_rate']:>6.2f} {s['alarm_rate_noise_stated_3x']:>5.2f} "
                  f"{s['gate_open_rate']:>5.2f} {s['moved']:>6} {s['moved_caught']:>7} {s['moved_alarmed']:>8} "
                  f"{s['unsafe']:>6} {s['max_applied_error_mm']:>11.4f} {s['applicable_wrong']:>9} "
                  f"{s['max_applicable_error_mm']:>8.4f} {s['unsafe_before']:>20} {s['applicable_wrong_before']:>13} "
                  f"{s['max_applicable_error_before_mm']:>12.4f}")
    print("\nerror / sqrt(std^2 + model_std^2) per boundary (contact state as the truth's): max |z|, "
          "fraction within 2 and 3")
    print(f"{'kind':<18} {'way':<6} " + " ".join(f"{name:>20}" for name in names))
    for kind, ways in results["kinds"].items():
        for way, block in ways.items():
            cells = [f"{c['max']:6.2f} {c['within_2'] or 0:5.2f} {c['within_3'] or 0:5.2f}"
                     for c in block["summary"]["z_total"].values()]
            print(f"{kind:<18} {way:<6} " + " ".join(f"{cell:>20}" for cell in cells))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
