"""Calibration to the real part (issue 16): uncalibrated, reference-relative and calibrated bases on stand-in parts.

Stand-in parts (hood_decomp.synthetic.standin): CalculiX S8R responses of the coarse hood with per-family physics
(E +-3 %, thickness +-5 %, pad stiffness +-30 %, preload +-50 %, gas spring +-5 %) and per-part thickness +-0.5 %,
exact pad contact, white field noise of 0.02 mm (stated error model). For each family: 13 calibration entries (the
reference and +-0.8 mm of each parameter alone) and, for the first families, 25 (plus +-0.4 mm); parts at uniform
random states; an undeclared hinge_R.z move of 0.05 mm on a subset (its response from the embedded solver) for the
detection rate. Also the issue's table: nominal physics, no noise, 40 parts, embedded bases.

    scripts/with-env python benchmarks/bench_calibration.py [--families 5] [--parts 40] [--families-25 2]
    scripts/with-env python benchmarks/bench_calibration.py --default-ccx CCX.npz [--families 5] [--parts 20]
        (the default hood instead: CalculiX load, gas and unit responses at the three thickness scales, the embedded
        solver's pad responses at each (68 pad jobs of ~7.7 GB are out of reach); no reference-relative and no
        25-entry variant; CCX.npz is made when missing: 18 CalculiX jobs of ~7.7 GB and 130-1000 s, one at a time
        under the flock ccx_default.lock beside it, each job kept in CCX.jobs/ so an interrupted run resumes, e.g.
        /work/scratch/cache/standin_ccx_default_nopads.npz, whose 6 nominal jobs session 14 made)
    [--part-spread 0.005]: the per-part thickness variation (0: none, the same parts and noise draws)

Prints tables (per parameter: max and median error, median stated std, coverage of the stated 95 % interval, max
|error|/std; per variant: the within-model rate, its complement the false-alarm rate, and the hinge_R.z detection
rate; the calibrations' model discrepancy is logged; coverage per family, coverage with the model std, and the
position error of truly lifted pads) and writes benchmarks/out/bench_calibration.json.
The CalculiX responses are cached in benchmarks/out/standin_ccx_coarse.npz or ``--ccx-cache`` (47 jobs; 44 min at
load 15, 24 min at load 6-15 on 2026-11-24; /work/scratch/cache/standin_ccx_coarse.npz outlives a worktree).

Per parameter the errors are also split by what the estimate says: over estimates not flagged lifted (a touching
pad's commanded position, observable) and over estimates flagged lifted (the part's position at the pad; a pad that
touches with a light force the field cannot show is flagged lifted too, while its truth is its commanded position,
up to the touch's compression above the part: not observable). The buffer errors above 0.05 mm are counted by the
truth's pad reaction. A last table gives, per bilateral parameter and per buffer and category (the truth's pad
reaction >= 20 N, 0-20 N or lifted, times the estimate's lifted flag), n, max, 99th and 95th percentile of |error|,
the count above 0.02 mm and the coverage; a truly lifted pad flagged lifted is measured against the part's position
(what it reports), the other categories against the truth's state; then the worst buffer cases.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble, solve_members, validation_plan
from hood_decomp.core.fe.hood_preset import build_hood
from hood_decomp.core.fe.model import PartModel, skin_surface
from hood_decomp.core.fe.solver import (
    build_solver,
    physical_responses,
    project,
    reduce_model,
    thermal_moves,
    thickness_sensitivities,
)
from hood_decomp.core.loop.calibration import (
    CalibrationEntry,
    PhysicalResponses,
    calibrate,
    one_at_a_time,
    rebuild_bases,
    relative_field,
)
from hood_decomp.core.method.bases import build_bases, estimate_field
from hood_decomp.core.types import DisplacementField, FieldErrorModel
from hood_decomp.synthetic.standin import (
    PART_THICKNESS_SPREAD,
    Family,
    StandIn,
    calculix_responses,
    serial_responses,
)

OUT = Path(__file__).parent / "out"
NOISE_MM = 0.02
HINGE_R_Z_MM = 0.05

logger = logging.getLogger("bench_calibration")


def field(model_id: str, values: np.ndarray, rng: np.random.Generator | None) -> DisplacementField:
    if rng is None:
        return DisplacementField(model_id, values, 1.0, np.nan)
    return DisplacementField(model_id, values + rng.normal(0.0, NOISE_MM, values.shape), 1.0, NOISE_MM,
                             FieldErrorModel.stated(NOISE_MM, values.size))


def summarise(errors: list, stds: list, within: list, names: tuple[str, ...], lifted: list | None = None,
              reactions: list | None = None, families: list | None = None, model_stds: list | None = None) -> dict:
    errors, stds = np.abs(np.array(errors)), np.array(stds)
    inside = errors <= 1.96 * stds
    z = errors / stds
    extra = {}
    if families is not None:
        # the coverage is measured over few calibrations: per family it is one calibration's, and its spread over
        # the families is what the pooled figure is uncertain by (a cluster sample, not 1,000 independent ones)
        families = np.array(families)
        per_family = np.array([inside[families == g].mean(axis=0) for g in np.unique(families)])
        extra["coverage_95_per_family"] = per_family.tolist()
        extra["coverage_95_per_parameter_family_se"] = dict(zip(
            names, (per_family.std(axis=0, ddof=1) / np.sqrt(len(per_family))).tolist(), strict=True))
    if model_stds is not None:
        total = np.hypot(stds, np.array(model_stds))
        extra["coverage_95_per_parameter_with_model_std"] = dict(zip(
            names, (errors <= 1.96 * total).mean(axis=0).tolist(), strict=True))
        extra["median_model_std_mm"] = dict(zip(names, np.median(np.array(model_stds), axis=0).tolist(), strict=True))
    split: dict = {}
    if lifted is not None and reactions is not None:
        flagged, reactions = np.array(lifted, bool), np.array(reactions)
        pads = errors[:, -reactions.shape[1]:]
        flagged_pads = flagged[:, -reactions.shape[1]:]
        large = pads > 0.05
        split = {
            "max_error_not_lifted_mm": dict(zip(names, np.where(flagged, 0.0, errors).max(axis=0).tolist(),
                                                strict=True)),
            "max_error_lifted_mm": dict(zip(names, np.where(flagged, errors, 0.0).max(axis=0).tolist(), strict=True)),
            "coverage_95_not_lifted": float(inside[~flagged].mean()),
            "flagged_lifted_rate": dict(zip(names, flagged.mean(axis=0).tolist(), strict=True)),
            "buffer_errors_above_0.05mm": {
                "count": int(large.sum()),
                "truth_lifted": int((large & (reactions <= 0)).sum()),
                "truth_touch_below_20N": int((large & (reactions > 0) & (reactions < 20)).sum()),
                "truth_touch_above_20N": int((large & (reactions >= 20)).sum()),
                "flagged_lifted": int((large & flagged_pads).sum()),
                "inside_95": int((large & inside[:, -reactions.shape[1]:]).sum()),
            },
        }
    return {
        "parts": len(errors),
        "max_error_mm": dict(zip(names, errors.max(axis=0).tolist(), strict=True)),
        "median_error_mm": dict(zip(names, np.median(errors, axis=0).tolist(), strict=True)),
        "median_std_mm": dict(zip(names, np.median(stds, axis=0).tolist(), strict=True)),
        "coverage_95": float(inside.mean()),
        "coverage_95_per_parameter": dict(zip(names, inside.mean(axis=0).tolist(), strict=True)),
        "max_abs_z": dict(zip(names, z.max(axis=0).tolist(), strict=True)),
        "within_model_rate": float(np.mean(within)),
        "false_alarm_rate": 1.0 - float(np.mean(within)),
        **split,
        **extra,
    }


def table(title: str, summary: dict) -> str:
    rows = [f"{title}: {summary['parts']} parts, coverage of the 95 % intervals {100 * summary['coverage_95']:.1f} %, "
            f"within model {100 * summary['within_model_rate']:.1f} %",
            "| parameter | max error (mm) | median error (mm) | median stated std (mm) | coverage | max abs(err)/std |",
            "|---|---|---|---|---|---|"]
    for name in summary["max_error_mm"]:
        coverage = 100 * summary["coverage_95_per_parameter"][name]
        rows.append(f"| {name} | {summary['max_error_mm'][name]:.4f} | {summary['median_error_mm'][name]:.4f} | "
                    f"{summary['median_std_mm'][name]:.4f} | {coverage:.1f} % | {summary['max_abs_z'][name]:.1f} |")
    return "\n".join(rows)


def split_table(summary: dict) -> str:
    """The errors split by the estimate's lifted flag, and the large buffer errors by the truth's reaction."""
    rows = [f"coverage over estimates not flagged lifted {100 * summary['coverage_95_not_lifted']:.1f} %",
            "| parameter | flagged lifted | max error not lifted (mm) | max error lifted (mm) |", "|---|---|---|---|"]
    for name in summary["max_error_mm"]:
        rows.append(f"| {name} | {100 * summary['flagged_lifted_rate'][name]:.1f} % | "
                    f"{summary['max_error_not_lifted_mm'][name]:.4f} | {summary['max_error_lifted_mm'][name]:.4f} |")
    rows.append(f"buffer errors > 0.05 mm: {summary['buffer_errors_above_0.05mm']}")
    rows.append("coverage with the model std (the calibration's factors): " + ", ".join(
        f"{k} {100 * v:.1f}" for k, v in summary["coverage_95_per_parameter_with_model_std"].items()))
    rows.append("coverage per family (%): " + "; ".join(
        " ".join(f"{100 * v:.0f}" for v in row) for row in summary["coverage_95_per_family"])
                + " (standard error over the families: " + ", ".join(
        f"{k} {100 * v:.1f}" for k, v in summary["coverage_95_per_parameter_family_se"].items()) + ")")
    if "lifted_pad_position" in summary:
        rows.append(f"truly lifted pads flagged lifted, position error: {summary['lifted_pad_position']}")
    reported = summary["against_what_is_reported"]
    rows.append("against what is reported (a lifted flag: the part's position at the pad): max error "
                + ", ".join(f"{k} {v:.4f}" for k, v in reported["max_error_mm"].items())
                + f"; coverage {100 * reported['coverage_95']:.1f} % ("
                + ", ".join(f"{k} {100 * v:.1f}" for k, v in reported["coverage_95_per_parameter"].items()) + ")")
    return "\n".join(rows)


#: a pad seated with at least this reaction (N) is observable at 0.02 mm noise (a lighter touch on a few springs is not)
SEATED_N = 20.0
#: the buffer categories: (key, description, mask of the pad's truth reaction r (m,) N, its lifted flag f (m,) and
#: whether every pad of the part is truly lifted (m,): the hood then hangs on its bilateral boundaries alone)
CATEGORIES = (
    ("seated_touching", "truth >= 20 N, estimated touching", lambda r, f, a: (r >= SEATED_N) & ~f),
    ("seated_lifted", "truth >= 20 N, flagged lifted", lambda r, f, a: (r >= SEATED_N) & f),
    ("light_touching", "truth 0-20 N (light touch), estimated touching",
     lambda r, f, a: (r > 0) & (r < SEATED_N) & ~f),
    ("light_lifted", "truth 0-20 N (light touch), flagged lifted", lambda r, f, a: (r > 0) & (r < SEATED_N) & f),
    ("lifted_lifted", "truly lifted, flagged lifted (the part's position)", lambda r, f, a: (r <= 0) & f),
    ("lifted_lifted_other_touching", "  of which another pad touches", lambda r, f, a: (r <= 0) & f & ~a),
    ("lifted_lifted_all_lifted", "  of which every pad is lifted", lambda r, f, a: (r <= 0) & f & a),
    ("lifted_touching", "truly lifted, estimated touching (wrong contact decision)", lambda r, f, a: (r <= 0) & ~f),
)


def collection() -> dict[str, list]:
    """Per-part records of one variant's estimates (:func:`record`)."""
    return {k: [] for k in ("errors", "stds", "within", "detected", "lifted", "reactions", "reported", "family",
                            "model_std", "pad_position", "gap")}


def record(data: dict[str, list], e, commanded: np.ndarray, effective: np.ndarray, reactions: np.ndarray,
           position: np.ndarray, family: int, n_bilateral: int) -> None:
    """Record estimate ``e`` of one part: commanded (P,) mm its settings, effective (P,) mm the truth's states,
    reactions (U,) N its pad reactions, position (U,) mm the part's position at each pad
    (:func:`~hood_decomp.synthetic.standin.pad_positions`)."""
    B = n_bilateral
    data["gap"].append(commanded[B:] - position)
    data["errors"].append(e.values - effective)
    data["stds"].append(e.std)
    data["within"].append(e.within_model)
    data["lifted"].append(e.lifted)
    data["reactions"].append(reactions)
    data["family"].append(family)
    data["model_std"].append(np.zeros(len(e.values)) if e.model_std is None else e.model_std)
    # a truly lifted pad flagged lifted: its value is the part's position there
    for u in np.flatnonzero((reactions <= 0) & e.lifted[B:]):
        data["pad_position"].append((float(e.values[B + u] - position[u]), float(e.std[B + u]),
                                     float(0.0 if e.model_std is None else e.model_std[B + u]), family, u))
    # what a lifted flag reports: the part's position at the pad (a light touch's commanded position lies above it
    # and is not observable)
    data["reported"].append(e.values - np.concatenate([effective[:B], np.where(e.lifted[B:], position,
                                                                               effective[B:])]))


def quantiles(errors: np.ndarray, stds: np.ndarray, model_stds: np.ndarray) -> dict:
    """n, max, 99th and 95th percentile of |error| (mm), the count above 0.02 mm (and of those inside the stated 95 %
    interval) and the coverage of the stated 95 % interval (and with the model std) of errors, stds, model_stds
    (n,)."""
    errors = np.abs(errors)
    if not len(errors):
        return {"n": 0}
    return {"n": len(errors), "max_mm": float(errors.max()), "q99_mm": float(np.quantile(errors, 0.99)),
            "q95_mm": float(np.quantile(errors, 0.95)), "above_0.02mm": int((errors > 0.02).sum()),
            # of those, how many the stated 95 % interval announces (a large error with a large std)
            "above_0.02mm_inside_95": int(((errors > 0.02) & (errors <= 1.96 * stds)).sum()),
            "coverage_95": float(np.mean(errors <= 1.96 * stds)),
            "coverage_95_with_model_std": float(np.mean(errors <= 1.96 * np.hypot(stds, model_stds)))}


def summarise_collection(data: dict[str, list], names: tuple[str, ...], n_bilateral: int) -> dict:
    """:func:`summarise` of a variant's records with the lifted split, the truly lifted pads' position error, the
    errors against what is reported, the bilateral parameters' and the buffer categories' quantiles and the worst
    buffer cases."""
    B = n_bilateral
    summary = summarise(data["errors"], data["stds"], data["within"], names, data["lifted"], data["reactions"],
                        data["family"], data["model_std"])
    if data["pad_position"]:
        error, std, model_std, families, pads = np.array(data["pad_position"]).T
        total = np.hypot(std, model_std)
        summary["lifted_pad_position"] = {
            "pads": len(error), "max_error_mm": float(np.abs(error).max()),
            "rms_error_mm": float(np.sqrt(np.mean(error**2))),
            "max_abs_z_std": float(np.max(np.abs(error) / std)),
            "max_abs_z_with_model_std": float(np.max(np.abs(error) / total)),
            "coverage_95_std": float(np.mean(np.abs(error) <= 1.96 * std)),
            "coverage_95_with_model_std": float(np.mean(np.abs(error) <= 1.96 * total)),
            "median_std_mm": float(np.median(std)), "median_model_std_mm": float(np.median(model_std)),
            # per family and pad: a shared offset (the calibrated pad springs' error) against the scatter
            "mean_error_mm_per_family_pad": [[float(error[(families == g) & (pads == u)].mean())
                                              if ((families == g) & (pads == u)).any() else None
                                              for u in range(len(names) - B)] for g in np.unique(data["family"])]}
    reported = summarise(data["reported"], data["stds"], data["within"], names)
    summary["against_what_is_reported"] = {key: reported[key] for key in
                                           ("max_error_mm", "coverage_95", "coverage_95_per_parameter")}
    errors, reported = np.array(data["errors"]), np.array(data["reported"])
    stds, model_stds = np.array(data["stds"]), np.array(data["model_std"])
    flags, reactions = np.array(data["lifted"], bool)[:, B:], np.array(data["reactions"])
    summary["bilateral"] = {name: quantiles(errors[:, j], stds[:, j], model_stds[:, j])
                            for j, name in enumerate(names[:B])}
    # a truly lifted pad flagged lifted is measured against the part's position (what it reports; its truth's
    # effective state is that position too), the other categories against the truth's state
    summary["buffer_categories"] = {}
    for u, name in enumerate(names[B:]):
        summary["buffer_categories"][name] = {}
        for key, text, category in CATEGORIES:
            mask, j = category(reactions[:, u], flags[:, u], (reactions <= 0).all(axis=1)), B + u
            summary["buffer_categories"][name][key] = {
                "description": text,
                **quantiles((reported if key.startswith("lifted_lifted") else errors)[mask, j], stds[mask, j],
                            model_stds[mask, j]),
                "max_against_reported_mm": float(np.abs(reported[mask, j]).max()) if mask.any() else None}
    gap = np.array(data["gap"])

    def cases(order: np.ndarray) -> list[dict]:
        return [{"part": int(i), "family": int(data["family"][i]), "buffer": names[B + u],
                 "truth_reaction_n": float(reactions[i, u]), "gap_mm": float(gap[i, u]),
                 "flagged_lifted": bool(flags[i, u]), "error_mm": float(errors[i, B + u]),
                 "error_against_reported_mm": float(reported[i, B + u]), "std_mm": float(stds[i, B + u]),
                 "model_std_mm": float(model_stds[i, B + u])}
                for i, u in (divmod(int(k), len(names) - B) for k in order)]

    summary["worst_buffer_cases"] = cases(np.argsort(np.abs(errors[:, B:]).ravel())[::-1][:8])
    # by |what is reported - its truth| / std: the cases the stated interval misses most
    summary["worst_buffer_z_cases"] = cases(np.argsort((np.abs(reported) / stds)[:, B:].ravel())[::-1][:6])
    summary["hinge_R_z_0.05mm_detected"] = float(np.mean(data["detected"])) if data["detected"] else None
    summary["hinge_R_z_parts"] = len(data["detected"])
    return summary


def category_table(summary: dict) -> str:
    """The bilateral parameters' and each buffer's errors by category (truth reaction x the estimate's lifted
    flag), and the worst buffer cases."""
    rows = ["| parameter | category | n | max (mm) | q99 (mm) | q95 (mm) | > 0.02 mm (inside the 95 % interval) | "
            "coverage (with model std) | "
            "max against reported (mm) |", "|---|---|---|---|---|---|---|---|---|"]
    cells = [(name, "bilateral", q) for name, q in summary["bilateral"].items()]
    cells += [(name, q["description"], q) for name, categories in summary["buffer_categories"].items()
              for q in categories.values()]
    for name, text, q in cells:
        if q["n"]:
            rows.append(f"| {name} | {text} | {q['n']} | {q['max_mm']:.4f} | {q['q99_mm']:.4f} | {q['q95_mm']:.4f} | "
                        f"{q['above_0.02mm']} ({q['above_0.02mm_inside_95']}) | {100 * q['coverage_95']:.1f} % "
                        f"({100 * q['coverage_95_with_model_std']:.1f} %) | "
                        f"{q.get('max_against_reported_mm', q['max_mm']):.4f} |")
    for key, title in (("worst_buffer_cases", "worst buffer cases by |error|"),
                       ("worst_buffer_z_cases", "worst buffer cases by |error against what is reported| / std")):
        rows.append(f"{title} (error against the truth's state; against what is reported; gap: commanded minus the "
                    "part's position at the pad, < 0 a lifted pad's clearance, > 0 the largest spring compression):")
        rows += [f"  part {w['part']} family {w['family']} {w['buffer']}: truth reaction {w['truth_reaction_n']:.1f} "
                 f"N, gap {w['gap_mm']:+.4f} mm, flagged lifted {w['flagged_lifted']}, error {w['error_mm']:+.4f} "
                 f"({w['error_against_reported_mm']:+.4f}) mm, std {w['std_mm']:.4f}, model std "
                 f"{w['model_std_mm']:.4f}" for w in summary[key]]
    return "\n".join(rows)


def report(title: str, summary: dict) -> str:
    """Every table of a variant: per parameter, the lifted split, the categories."""
    detected = "" if summary["hinge_R_z_0.05mm_detected"] is None else (
        f"\nhinge_R.z 0.05 mm detected in {100 * summary['hinge_R_z_0.05mm_detected']:.1f} % of "
        f"{summary['hinge_R_z_parts']} parts")
    return "\n".join([table(title, summary) + detected, split_table(summary), category_table(summary)])


def calibration_record(calibration, calibrated, truth, seconds: float) -> dict:
    """A calibration's record for the JSON: seconds, rank, leave-one-out RMS, factors and their std, the pads'
    z0 - preload calibrated minus the family's truth (its reduced model; mm, mean per pad) and the discrepancy."""
    offset = (calibrated.z0 - calibrated.preload) - (truth.z0 - truth.preload)
    return {"seconds": seconds, "rank": calibration.rank, "loo_rms_mm": calibration.loo_rms_mm.tolist(),
            "factors": calibration.factors, "factor_std": calibration.factor_std,
            "pad_offset_error_mm": [float(offset[truth.pad_of == u].mean()) for u in range(truth.pad_of.max() + 1)],
            "discrepancy": calibration.record()["discrepancy"]}


def hood_setup(model: PartModel) -> tuple:
    """The hood ``model``: model, skin, solver, reduced model, embedded bases (full factorial) and the FE responses
    behind the physical factors."""
    skin = skin_surface(model)
    solver = build_solver(model)
    reduced = reduce_model(solver)
    commanded, rank = factorial_plan(model.lower, model.upper)
    bases = build_bases(simulate_ensemble(reduced, commanded, rank, model.lower, model.upper), skin, reduced)
    physics = PhysicalResponses.from_solver(physical_responses(solver), thickness_sensitivities(model, reduced),
                                            thermal_moves(model))
    return model, skin, solver, reduced, bases, physics


def check(setup: tuple, standin: StandIn, families: int, parts: int, detect: int, families_25: int, reference: bool,
          part_spread: float, title: str) -> tuple[dict, dict[str, dict[str, list]]]:
    """The check on ``standin``'s parts (both hoods): the issue's table (nominal physics, no noise, 40 parts, embedded
    bases); then per family (seeds 1000 + f) 13 calibration entries (and 25 for the first ``families_25``), ``parts``
    parts at 0.02 mm white field noise (states: seeds 2000 + f), each part with its own thickness factor (1 +-
    ``part_spread``), estimated with the uncalibrated, (``reference``) reference-relative and calibrated bases; the
    first ``detect`` parts per family also with an undeclared 0.05 mm hinge_R.z move (embedded response). Prints the
    tables; returns the results for the JSON and each variant's per-part records (:func:`record`)."""
    start = time.perf_counter()
    model, skin, solver, reduced, bases, physics = setup
    moved = solver.boundary_response("hinge_R", "z").reshape(-1, 6)[:, :3, None]
    hinge_r_z = project(model, solver.pads, moved)[0][:, 0]
    names, mid, B = model.names, model.model_id, len(model.bilateral)
    results: dict = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                     "machine": "2 cores shared by the lead and helpers", "load_at_start": os.getloadavg()[0],
                     "noise_mm": NOISE_MM, "part_spread": part_spread}

    states = validation_plan(model.lower, model.upper, 40, seed=16)
    block = solve_members(standin.reduced(Family()), states)
    nominal = [estimate_field(bases, field(mid, block.normal_displacement[i], None)) for i in range(len(states))]
    results["uncalibrated_nominal_noise_free"] = summarise(
        [e.values - block.effective[i] for i, e in enumerate(nominal)], [e.std for e in nominal],
        [e.within_model for e in nominal], names)
    print(table(f"uncalibrated, nominal stand-in parts, no noise, {title}", results["uncalibrated_nominal_noise_free"]))

    collected = {label: collection() for label in ("uncalibrated", "reference", "calibrated_13", "calibrated_25")}
    family_records = []
    for f in range(families):
        rng = np.random.default_rng(1000 + f)
        family = Family.draw(rng)
        logger.info("family %d: %s", f, family)
        variants = {"uncalibrated": bases}
        family_record = {"family": family.__dict__}
        for label, moves in (("calibrated_13", (0.8,)), ("calibrated_25", (0.8, 0.4))):
            if label == "calibrated_25" and f >= families_25:
                continue
            settings = one_at_a_time(len(names), moves)
            values = standin.fields(family, settings, rng, part_spread).normal_displacement
            entries = [CalibrationEntry(f"entry {j}", field(mid, values[j], rng), settings[j])
                       for j in range(len(settings))]
            tic = time.perf_counter()
            calibrated, calibration = calibrate(reduced, physics, entries, skin, (model.lower, model.upper))
            variants[label] = rebuild_bases(bases, calibrated, json.dumps(calibration.record()), physics,
                                            **calibration.error_terms())
            family_record[label] = calibration_record(calibration, calibrated, standin.reduced(family),
                                                      time.perf_counter() - tic)
            logger.info("family %d %s: discrepancy %s", f, label, family_record[label]["discrepancy"])
            if label == "calibrated_13":
                reference_entry = entries[0]
        states = validation_plan(model.lower, model.upper, parts, seed=2000 + f)
        block = standin.fields(family, states, rng, part_spread)
        for i in range(len(states)):
            measured = field(mid, block.normal_displacement[i], rng)
            fields = {label: measured for label in variants}
            if reference:
                fields["reference"] = relative_field(reduced, measured, reference_entry.field,
                                                     reference_entry.setting)
            for label, part_field in fields.items():
                b = variants.get(label, bases)
                record(collected[label], estimate_field(b, part_field), states[i], block.effective[i],
                       block.reactions[i], block.position[i], f, B)
                if i < detect:
                    moved = field(mid, block.normal_displacement[i] + HINGE_R_Z_MM * hinge_r_z, rng)
                    if label == "reference":
                        moved = relative_field(reduced, moved, reference_entry.field, reference_entry.setting)
                    collected[label]["detected"].append(not estimate_field(b, moved).within_model)
        family_records.append(family_record)
        logger.info("family %d done at %.0f s (load %.1f)", f, time.perf_counter() - start, os.getloadavg()[0])
    results["families"] = family_records
    for label, data in collected.items():
        if data["errors"]:
            results[label] = summarise_collection(data, names, B)
            print(report(f"{label}, {title} ({families} families x {parts} parts, 0.02 mm noise)", results[label]))
    lifted = results["calibrated_13"].get("lifted_pad_position", {}).get("mean_error_mm_per_family_pad")

    def mm(values: list) -> str:
        return " / ".join("-" if v is None else f"{v:+.4f}" for v in values)

    for f, family_record in enumerate(family_records):
        print(f"family {f}: pad offset z0 - preload, calibrated minus the truth's, "
              f"{mm(family_record['calibrated_13']['pad_offset_error_mm'])} mm; truly lifted pads flagged lifted: "
              f"mean position error {mm(lifted[f]) if lifted else '-'} mm")
    results["seconds"] = time.perf_counter() - start
    results["load_at_end"] = os.getloadavg()[0]
    return results, collected


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", type=int, default=5)
    parser.add_argument("--families-25", type=int, default=2, help="families also calibrated from 25 entries (coarse)")
    parser.add_argument("--parts", type=int, default=40, help="parts per family")
    parser.add_argument("--detect", type=int, default=20, help="parts per family with the hinge_R.z move")
    parser.add_argument("--part-spread", type=float, default=PART_THICKNESS_SPREAD,
                        help="half-width of the per-part thickness factor (0: the family's thickness only)")
    parser.add_argument("--json", default="bench_calibration.json", help="file name in benchmarks/out/")
    parser.add_argument("--ccx-cache", type=Path, default=OUT / "standin_ccx_coarse.npz",
                        help="the stand-in's CalculiX responses (.npz), read when present, else made and written")
    parser.add_argument("--default-ccx", type=Path, default=None,
                        help="the default hood instead, on these CalculiX responses (.npz; made when missing: 18 jobs "
                             "of ~7.7 GB one at a time, resumable)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    for name in ("distributed", "hood_decomp.core.method", "hood_decomp.core.fe.solver"):
        logging.getLogger(name).setLevel(logging.WARNING)
    start = time.perf_counter()
    if args.default_ccx is not None:
        model = build_hood("default")
        # the CalculiX jobs first: made without the bases' set-up in memory (a job takes ~7.7 GB)
        responses = serial_responses(model, args.default_ccx, lock=args.default_ccx.parent / "ccx_default.lock")
        setup = hood_setup(model)
        standin = StandIn(model, responses, embedded_pads=True)
        logger.info("default hood set up in %.0f s", time.perf_counter() - start)
        results, collected = check(setup, standin, args.families, args.parts, args.detect, 0, False,
                                   args.part_spread, "DEFAULT hood")
        results["note"] = ("default hood, CalculiX load/gas/unit responses at thickness 0.95/1/1.05, the embedded "
                           "solver's pad responses at each")
    else:
        setup = hood_setup(build_hood("coarse"))
        standin = StandIn(setup[0], calculix_responses(setup[0], cache=args.ccx_cache))
        results, collected = check(setup, standin, args.families, args.parts, args.detect, args.families_25, True,
                                   args.part_spread, "coarse hood")
    results["seconds_with_set_up"] = time.perf_counter() - start
    OUT.mkdir(exist_ok=True)
    (OUT / args.json).write_text(json.dumps(results, indent=1))
    # the per-part records beside it ("<variant>|<key>"): subsets (some families, another run's same parts) are
    # summarised afterwards with summarise_collection
    np.savez_compressed(OUT / Path(args.json).with_suffix(".npz").name,
                        **{f"{label}|{key}": np.array(values) for label, data in collected.items()
                           for key, values in data.items() if values})
    print(f"wrote {OUT / args.json} in {results['seconds_with_set_up']:.0f} s")


if __name__ == "__main__":
    main()
