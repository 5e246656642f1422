"""The steps of ``hood-decomp demo`` (see hood_decomp.demo.run), each a plain function over one shared state."""

from __future__ import annotations

import logging
import pathlib
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hood_decomp.core.types import DisplacementField
from hood_decomp.demo import figures as report_plots
from hood_decomp.demo.config import PAPER_TABLE3_S, DemoConfig, Timer, max_abs
from hood_decomp.demo.html import Report
from hood_decomp.plots import method as plots
from hood_decomp.synthetic.scanner import ScannerConfig

logger = logging.getLogger(__name__)

SCAN_TOPIC_OUTPUTS = ("hood_decomp/displacement", "hood_decomp/boundary_state", "hood_decomp/boundary_correction",
                      "hood_decomp/effects")


@dataclass
class DemoState:
    config: DemoConfig
    out: pathlib.Path
    timer: Timer
    data: dict[str, Any] = field(default_factory=dict)
    figures: dict[str, list[tuple[pathlib.Path, str]]] = field(default_factory=dict)

    def figure(self, group: str, path: pathlib.Path, caption: str) -> None:
        self.figures.setdefault(group, []).append((path, caption))


def build_model(state: DemoState) -> None:
    from hood_decomp.core.fe.hood_preset import build_preset
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.io.model_files import save_model

    model = build_preset(state.config.preset, state.config.resolution)
    state.data.update(model=model, skin=skin_surface(model))
    save_model(model, state.out / "model")
    state.figure("model", report_plots.plot_model(model, state.out / "figures" / "model.png"),
                 "The hood model in plan view: parts, and the boundary patches with the parameters acting on them")


def build_solver_and_reduce(state: DemoState) -> None:
    from hood_decomp.core.fe.solver import build_solver, reduce_model

    solver = build_solver(state.data["model"])
    state.data.update(solver=solver, reduced=reduce_model(solver))


def build_ensemble(state: DemoState) -> None:
    from hood_decomp.io.ensemble_store import load_ensemble, write_ensemble

    model, path = state.data["model"], state.out / "ensemble.h5"
    start = time.perf_counter()
    summary = write_ensemble(path, state.data["reduced"], state.data["skin"], model.lower, model.upper,
                             n_validation=state.config.n_validation)
    state.data.update(ensemble_summary=summary, ensemble_seconds=time.perf_counter() - start,
                      training=load_ensemble(path, "training"), validation=load_ensemble(path, "validation"))


def build_bases_step(state: DemoState) -> None:
    from hood_decomp.core.method.bases import Bases, build_bases
    from hood_decomp.io.bases import save_bases

    data = state.data
    start = time.perf_counter()
    bases: Bases = build_bases(data["training"], data["skin"], data["reduced"])
    data["bases_seconds"] = time.perf_counter() - start
    data["bases"] = save_bases(state.out / "bases.h5", bases)
    state.figure("bases", plots.plot_explained_variance(bases.pca.explained_variance_ratio_,
                                                        state.out / "figures" / "explained_variance.png"),
                 "Explained variance of the first ten principal components (paper Fig. 8)")


def interaction_maps(state: DemoState) -> None:
    """The interaction map of both presets (the demo's from its training ensemble; the other's from the same solver
    with its buffers retargeted, rank 0-2 members only: no second factorisation)."""
    from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble
    from hood_decomp.core.fe.hood_preset import PRESETS, build_preset
    from hood_decomp.core.fe.solver import retarget_pads
    from hood_decomp.core.method.interactions import interaction_map

    data, config = state.data, state.config
    maps = {config.preset: interaction_map(data["training"])}
    for preset in PRESETS:
        if preset not in maps:
            model = build_preset(preset, config.resolution)
            reduced = retarget_pads(data["reduced"], model)
            commanded, rank = factorial_plan(model.lower, model.upper)
            keep = rank <= 2
            maps[preset] = interaction_map(simulate_ensemble(reduced, commanded[keep], rank[keep], model.lower,
                                                             model.upper))
    epsilon = data["bases"].hierarchical.epsilon_
    for preset, interactions in maps.items():
        state.figure("interactions", plots.plot_interaction_map(
            interactions, state.out / "figures" / f"interactions_{preset}.png",
            f"{preset}: max |u(a_i + a_j) - u(a_i) - u(a_j) + u0| (mm)", epsilon),
            f"Interaction map of preset {preset} at '{config.resolution}' resolution: every pair and sign")
    data["interaction_maps"] = maps


def validate(state: DemoState) -> None:
    """Fig. 9/10 on the validation set: estimation errors of every observable state, both estimators, with and
    without 0.02 mm noise, and the hierarchical basis' maximum reconstruction error per member."""
    from hood_decomp.core.method.bases import estimate_field
    from hood_decomp.core.method.decomposition import reconstruct_members

    bases, val = state.data["bases"], state.data["validation"]
    rng = np.random.default_rng(0)
    observable = np.ones_like(val.effective, dtype=bool)
    observable[:, val.n_bilateral:] = val.contact_fraction > 0
    results: dict[str, np.ndarray] = {}
    lifted_ok = []
    for label, method, noise in (("PCA, noise-free", "pca", 0.0), ("contact-aware, noise-free", "contact", 0.0),
                                 ("contact-aware, 0.02 mm noise", "contact", 0.02)):
        errors = np.full(val.effective.shape, np.nan)
        for i in range(val.n_members):
            values = val.normal_displacement[i] + (rng.normal(0.0, noise, val.normal_displacement.shape[1])
                                                   if noise else 0.0)
            field_i = DisplacementField(bases.model_id, values, 1.0, noise if noise else float("nan"))
            estimate = estimate_field(bases, field_i, method=method)
            errors[i] = np.where(observable[i], estimate.values - val.effective[i], np.nan)
            if method == "contact" and not noise:
                lifted = ~observable[i, val.n_bilateral:]
                reported = estimate.lifted[val.n_bilateral:]
                commanded = val.commanded[i, val.n_bilateral:]
                lifted_ok.append(np.all(reported[lifted]) and np.all(
                    commanded[lifted] <= estimate.values[val.n_bilateral:][lifted] + 0.01))
        results[label] = errors
        slug = label.split(",")[0].split()[0].lower() + ("_noisy" if noise else "")
        state.figure("validation", plots.plot_error_boxplot(
            val.names, np.nan_to_num(errors), state.out / "figures" / f"validation_{slug}.png",
            f"{label}: estimation error over {val.n_members} validation members"), f"{label} (paper Fig. 9)")
    reconstruction = reconstruct_members(bases.hierarchical, val.normal_displacement)
    per_member = np.abs(reconstruction - val.normal_displacement).max(axis=1)
    state.figure("validation", plots.plot_error_histogram(
        per_member, state.out / "figures" / "hierarchical_max_error.png",
        f"Hierarchical basis ({len(bases.hierarchical.effect_names_)} effects): worst node per member"),
        "Maximum reconstruction error per validation member with the hierarchical basis (paper Fig. 10)")
    state.data.update(validation_errors=results, lifted_ok=float(np.mean(lifted_ok)) if lifted_ok else float("nan"),
                      hierarchical_max_error=per_member)


@dataclass(frozen=True)
class DemoScan:
    name: str
    settings: dict[str, float]
    config: ScannerConfig
    what: str


def demo_scans(labels: tuple[str, ...], points: int) -> list[DemoScan]:
    """Four measurements with known truth: clean, noisy, occluded, and one with an effect the model lacks."""
    clean = ScannerConfig(n_points=points, noise_mm=0.02)
    return [
        DemoScan("clean", dict(zip(labels, (0.6, -0.4, 0.5, -0.7, 0.3, 0.4), strict=True)), clean,
                 "0.02 mm noise; the scanner 0.5 deg / 5 mm off its calibrated pose, recovered from the markers"),
        DemoScan("noisy", dict(zip(labels, (-0.5, 0.8, -0.3, 0.6, 0.5, -0.2), strict=True)),
                 ScannerConfig(n_points=points, noise_mm=0.05), "0.05 mm noise"),
        DemoScan("occluded", dict(zip(labels, (0.2, 0.3, 0.9, 0.4, -1.0, 0.6), strict=True)),
                 ScannerConfig(n_points=points, noise_mm=0.02, n_holes=8, hole_radius_mm=90.0,
                               dropout_fraction=0.1), "holes and dropouts; BUFFER_L lowered by 1 mm"),
        DemoScan("undeclared", {**dict(zip(labels, (0.3, -0.2, -0.4, 0.5, 0.4, 0.3), strict=True)),
                                "hinge_R.z": 0.5}, clean,
                 "the fixed right hinge moved 0.5 mm in Z: an effect the model does not declare"),
    ]


def make_scans(state: DemoState) -> None:
    from hood_decomp.ros.scan_bag import write_scenario_bag
    from hood_decomp.synthetic.scenarios import make_scenario_scan

    data = state.data
    scans, specs = [], demo_scans(data["reduced"].names, state.config.scan_points)
    for seed, spec in enumerate(specs, start=1):
        logger.info("scan '%s': %s", spec.name, spec.what)
        scans.append(make_scenario_scan(spec.name, data["solver"], data["reduced"], data["skin"], spec.settings,
                                        spec.config, seed))
    bag = state.out / "bags" / "scans"
    if bag.exists():
        import shutil

        shutil.rmtree(bag)
    bag.parent.mkdir(parents=True, exist_ok=True)
    write_scenario_bag(bag, scans, model_id=data["model"].model_id, resolution=state.config.resolution,
                       description="hood-decomp demo scans")
    data.update(scans=scans, scan_specs={s.name: s for s in specs}, bag=bag)


def replay(state: DemoState) -> None:
    import shutil

    from hood_decomp.io.bags import read_sidecar
    from hood_decomp.ros.launcher import start_nodes, stop_nodes
    from hood_decomp.ros.replay import replay_bag
    from hood_decomp.ros.scan_bag import write_node_params

    bag, record = state.data["bag"], state.out / "bags" / "nodes_output"
    if record.exists():
        shutil.rmtree(record)
    logs = state.out / "logs"
    logs.mkdir(exist_ok=True)
    params = write_node_params(state.out / "node_params.yaml", read_sidecar(bag))
    processes = start_nodes((state.out / "bases.h5").resolve(), params_file=params, log_dir=logs)
    try:
        result = replay_bag(bag, record=record)
    finally:
        stop_nodes(processes)
    state.data.update(replay=result, record=record)


def analyse_scans(state: DemoState) -> None:
    """Decode what the nodes published, compare with the truth, and draw each scan's fields and contributions."""
    from hood_decomp.core.method.bases import decompose_field, estimate_field
    from hood_decomp.io.bags import read_bag, typestore
    from hood_decomp.ros import messages

    data, store = state.data, typestore()
    by_stamp: dict[str, dict[str, Any]] = {}
    for record in read_bag(data["record"], topics=SCAN_TOPIC_OUTPUTS):
        msg = store.deserialize_cdr(record.data, record.msgtype)
        stamp = f"{msg.header.stamp.sec}.{msg.header.stamp.nanosec:09d}"
        by_stamp.setdefault(stamp, {})[record.topic] = msg
    skin, bases = data["skin"], data["bases"]
    rows = []
    for index, scan in enumerate(data["scans"]):
        sec, nanosec = divmod(1_000_000_000_000 + index * 1_000_000_000, 1_000_000_000)
        outputs = by_stamp.get(f"{sec}.{nanosec:09d}", {})
        entry: dict[str, Any] = {"scan": scan, "outputs": outputs}
        rows.append(entry)
        if "hood_decomp/effects" not in outputs:
            continue
        field_msg = outputs["hood_decomp/displacement"]
        measured = messages.msg_to_field(field_msg)
        decomposition = messages.msg_to_decomposition(outputs["hood_decomp/effects"])
        entry.update(field=measured, decomposition=decomposition,
                     estimate=messages.msg_to_estimate(outputs["hood_decomp/boundary_state"]),
                     correction=messages.msg_to_correction(outputs["hood_decomp/boundary_correction"]))
        directory = state.out / "figures" / scan.name
        truth_err = measured.normal_displacement - scan.normal_displacement
        limit = max(max_abs(scan.normal_displacement), 1e-6)
        levels = np.linspace(-limit, limit, 11)
        for name, values, title, kwargs in (
            ("true_field", scan.normal_displacement, "True normal displacement (simulation)", dict(levels=levels,
                                                                                                   cmap="coolwarm")),
            ("input_field", measured.normal_displacement, f"Measured from the scan (coverage {measured.coverage:.0%}, "
             f"noise {measured.noise_rms:.3f} mm)", dict(levels=levels, cmap="coolwarm")),
            ("reconstruction", decomposition.reconstruction, "Reconstruction with the hierarchical basis",
             dict(levels=levels, cmap="coolwarm")),
            ("scan_error", truth_err, f"Scan-to-field error against the truth, RMS "
             f"{np.sqrt(np.nanmean(truth_err ** 2)):.4f} mm", dict(cmap="coolwarm")),
        ):
            state.figure(scan.name, plots.plot_skin_field(skin, values, directory / f"{name}.png", title, "mm",
                                                          **kwargs), title)
        for path in plots.plot_contributions(skin, decomposition, directory):
            state.figure(scan.name, path, path.stem.replace("_", " "))
        estimate = entry["estimate"]
        names = list(estimate.names)
        state.figure(scan.name, report_plots.plot_estimate_bars(
            names, [scan.truth_mm[n] for n in names], estimate.values, estimate.std,
            directory / "estimate.png", f"{scan.name}: true and estimated parameter states"),
            "True and estimated parameter states (a lifted buffer shows the part's position there)")
    # Execution times next to Table 3, measured here on the first good field.
    first = next(r for r in rows if "field" in r)
    data["estimate_seconds"] = _best_time(lambda: estimate_field(bases, first["field"]))
    data["estimate_pca_seconds"] = _best_time(lambda: estimate_field(bases, first["field"], method="pca"))
    start = time.perf_counter()
    decomposition = decompose_field(bases, first["field"], estimate_field(bases, first["field"]))
    plots.plot_contributions(skin, decomposition, state.out / "figures" / "timing_run")
    data["decompose_seconds"] = time.perf_counter() - start
    data["scan_rows"] = rows


def _best_time(function, repeats: int = 5) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def close_loop(state: DemoState) -> None:
    """Trace the undeclared scan's residual to a candidate effect, add it, rebuild the bases, estimate again."""
    from hood_decomp.core.loop.candidates import candidate_fields, enumerate_candidates
    from hood_decomp.core.loop.close_loop import close_loop as run_close_loop
    from hood_decomp.io.close_loop_report import close_loop_report
    from hood_decomp.plots.close_loop import plot_before_after, plot_residual_maps

    data = state.data
    row = next(r for r in data["scan_rows"] if r["scan"].undeclared_mm and "field" in r)
    scan = row["scan"]
    candidates = candidate_fields(data["solver"], enumerate_candidates(data["model"]))
    result = run_close_loop(data["bases"], [row["field"]], candidates, ensemble=data["training"])
    truth = [{**scan.truth_mm, **scan.undeclared_mm}]
    summary = close_loop_report(result, truth)
    directory = state.out / "figures" / "close_loop"
    for path in plot_residual_maps(data["skin"], result, directory):
        state.figure("close_loop", path, path.stem.replace("_", " "))
    state.figure("close_loop", plot_before_after(result, directory / "before_after.png", truth),
                 "Residual and parameter errors before and after adding the effect found")
    before, after = result.before[0], result.after[0] if result.after else None
    rows = []
    for i, name in enumerate(before.names):
        true = scan.truth_mm[name]
        row_after = (float(after.values[list(after.names).index(name)]),
                     float(after.values[list(after.names).index(name)] - true)) if after else ("", "")
        rows.append((name, true, float(before.values[i]), row_after[0], float(before.values[i] - true), row_after[1]))
    for effect in result.added:
        true = scan.undeclared_mm.get(effect.name, float("nan"))
        rows.append((f"{effect.name} (added, {effect.unit})", true, "", float(effect.values[0]), "",
                     float(effect.values[0] - true)))
    added = ", ".join(f"{a.name} = {a.values[0]:.4f} {a.unit} (std {a.std[0]:.4f})" for a in result.added)
    data["close_loop"] = {
        "headers": ["parameter", "true", "before", "after", "error before", "error after"],
        "rows": rows,
        "caption": "Estimates (mm) on the scan with the undeclared effect, before and after adding the effect found",
        "text": [result.message,
                 f"Residual RMS {result.analyses_before[0].rms_mm:.4f} mm before, "
                 + (f"{result.analyses_after[0].rms_mm:.4f} mm after adding {added}." if result.added else
                    "nothing added.")],
    }
    data["close_loop_summary"] = {
        "status": result.status, "effect": result.added[0].name if result.added else None,
        "magnitude": float(result.added[0].values[0]) if result.added else None,
        "residual_rms_before_mm": result.analyses_before[0].rms_mm,
        "residual_rms_after_mm": result.analyses_after[0].rms_mm if result.analyses_after else None,
        "report": summary,
    }


def write_report(state: DemoState) -> pathlib.Path:
    """index.html, and results.json with the numbers behind it (mm, seconds)."""
    import json

    from hood_decomp.demo.report import build_report

    data = state.data
    scans = []
    for row in data["scan_rows"]:
        scan = row["scan"]
        entry = {"name": scan.name, "truth_mm": scan.truth_mm, "lifted_truth": scan.lifted,
                 "undeclared_mm": scan.undeclared_mm}
        if "estimate" in row:
            estimate, correction = row["estimate"], row["correction"]
            entry.update(
                estimate_mm=dict(zip(estimate.names, estimate.values.tolist(), strict=True)),
                std_mm=dict(zip(estimate.names, estimate.std.tolist(), strict=True)),
                lifted=dict(zip(estimate.names, estimate.lifted.tolist(), strict=True)),
                within_model=estimate.within_model, residual_rms_mm=estimate.residual_rms,
                safe_to_apply=correction.safe_to_apply, reason=correction.reason,
                effects=[{"name": e.name, "share": e.share} for e in row["decomposition"].effects])
        scans.append(entry)
    validation = {label: np.nanmax(np.abs(errors), axis=0).tolist()
                  for label, errors in data["validation_errors"].items()}
    results = {"resolution": state.config.resolution, "parameters": list(data["reduced"].names),
               "validation_max_abs_error_mm": validation, "lifted_reported_ok": data["lifted_ok"],
               "preset": state.config.preset,
               "hierarchical_effects": list(data["bases"].hierarchical.effect_names_),
               "interaction_peak_mm": {preset: {f"{a}{sa} & {b}{sb}": peak for a, sa, b, sb, peak in m.rows()}
                                       for preset, m in data["interaction_maps"].items()},
               "hierarchical_max_error_mm": float(np.max(data["hierarchical_max_error"])),
               "scans": scans, "close_loop": data.get("close_loop_summary"),
               "timings_s": state.timer.seconds}
    (state.out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    report: Report = build_report(state, PAPER_TABLE3_S)
    return report.write(state.out / "index.html")
