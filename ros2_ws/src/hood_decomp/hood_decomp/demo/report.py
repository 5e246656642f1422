"""The demo's report: what a quality engineer reads, built from the demo state (hood_decomp.demo.steps)."""

from __future__ import annotations

from typing import Any

import numpy as np

from hood_decomp.demo.figures import plot_timings
from hood_decomp.demo.html import Report


def _fmt(value: float, digits: int = 4) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def build_report(state: Any, paper_seconds: dict[str, float]) -> Report:
    data, config = state.data, state.config
    model, bases = data["model"], data["bases"]
    report = Report(
        "hood_decomp: scanned deviations of the hood, decomposed",
        f"Built-in preset '{config.preset}' at '{config.resolution}' resolution, {len(model.skin_nodes):,} visible "
        "skin nodes; "
        f"generated {state.timer.seconds and 'in ' + format(sum(state.timer.seconds.values()), '.0f') + ' s'} "
        "by hood-decomp demo. Lengths in mm.",
    )
    _summary(report, state)
    section = report.section("The part model and its boundaries")
    section.text("The hood is held by a fixed right hinge, an adjustable left hinge (X, Y), two locks (Z, push and "
                 "pull), two rubber buffers (Z, compression only: they can lose contact) and two gas springs. "
                 "The six adjustable boundaries are the parameters whose states hood_decomp estimates.")
    section.figures(state.figures.get("model", []), state.out)
    section.table(["parameter", "boundary", "direction", "range (mm)"],
                  [(p.label, p.boundary, p.direction, f"[{p.lower:g}, {p.upper:g}]") for p in model.parameters])
    section.table(["boundary", "kind", "constrained / axis", "force (N)", "pad stiffness (N/mm)", "preload (mm)"],
                  [(b.name, b.kind, ", ".join(b.dofs) or "axis (" + ", ".join(f"{a:.3g}" for a in b.axis) + ")",
                    b.force or "", b.stiffness or "", b.preload or "") for b in model.boundaries])

    summary = data["ensemble_summary"]
    section = report.section("Simulation ensemble")
    section.text(f"Full factorial over {{min, 0, max}} of the six parameters (729 members, ranks as in the paper's "
                 f"Table 1) and {config.n_validation} uniform random validation members, solved with the embedded "
                 f"shell solver: one factorisation, then an exact contact solve per member, in "
                 f"{data['ensemble_seconds']:.1f} s.")
    section.table(["set", "members", "buffer lifted", "partly in contact", "fully in contact"],
                  [(group, info["members"], info["pad_contact"]["lifted"], info["pad_contact"]["partial"],
                    info["pad_contact"]["full"]) for group, info in summary.items() if isinstance(info, dict)],
                  "Buffer contact states over (member, buffer) pairs: the contact is a genuine nonlinearity")

    section = report.section("Bases")
    pca, hierarchical = bases.pca, bases.hierarchical
    section.text(f"PCA basis: {pca.n_components_} components, cumulative explained variance "
                 f"{100 * pca.cumulative_explained_variance_[pca.n_components_ - 1]:.6f} %. "
                 f"Hierarchical basis at epsilon = {hierarchical.epsilon_:g} mm: "
                 f"{len(hierarchical.effect_names_)} effects.")
    for note in pca.notes_:
        section.text(note, "note")
    section.figures(state.figures.get("bases", []), state.out)
    section.table(["effect", "parameters", "rank"],
                  [(name, ", ".join(np.asarray(hierarchical.names_)[mask]) or "loads only", int(rank))
                   for name, mask, rank in zip(hierarchical.effect_names_, hierarchical.effect_mask_,
                                               hierarchical.effect_rank_, strict=True)],
                  "Effects of the hierarchical basis, in the order the greedy algorithm found them")

    section = report.section("Where the parameters interact")
    section.text("For every pair of parameters and every sign: the largest |u(a_i + a_j) - u(a_i) - u(a_j) + u0| "
                 "over the skin, from the rank 0-2 members (zero for a part that responds additively). The "
                 "hierarchical basis adds an interaction effect only where a rank-2 member is farther than epsilon "
                 "from the span of the effects found so far; a large interaction whose shape the single effects "
                 "already carry (a buffer's reaction, for instance) adds none.")
    section.figures(state.figures.get("interactions", []), state.out)
    maps = data["interaction_maps"]
    top = {preset: m.rows()[:8] for preset, m in maps.items()}
    section.table(["preset", "pair (sign: + max, - min)", "max |interaction| (mm)"],
                  [(preset, f"{a}{sa} & {b}{sb}", _fmt(peak)) for preset, rows in top.items()
                   for a, sa, b, sb, peak in rows],
                  "The eight largest interactions of each preset")

    section = report.section("How accurate the estimates are (validation set)")
    rows = []
    for label, errors in data["validation_errors"].items():
        rows.append((label, *[_fmt(np.nanmax(np.abs(errors[:, j]))) for j in range(errors.shape[1])]))
    section.table(["estimator", *data["validation"].names], rows,
                  "Largest absolute error (mm) of every observable state over the validation set (buffers only "
                  "where in contact). The paper reports 0.004 mm for its PCA estimator.")
    section.text(f"Lifted buffers reported as lifted, with the commanded position at most 0.01 mm above the "
                 f"reported part position: {100 * data['lifted_ok']:.1f} % of validation members.")
    section.text(f"Hierarchical reconstruction: worst node error over all validation members "
                 f"{_fmt(float(np.max(data['hierarchical_max_error'])))} mm (paper: below 0.025 mm).")
    section.figures(state.figures.get("validation", []), state.out)

    _scans(report, state)
    _close_loop(report, state)
    _timings(report, state, paper_seconds)
    return report


def _summary(report: Report, state: Any) -> None:
    data = state.data
    section = report.section("Summary")
    replay = data["replay"]
    section.text(f"{replay.scans} synthetic structured-light scans with known truth were replayed through the three "
                 f"ROS 2 nodes (scan, estimator, decomposition) as separate processes: {replay.answered} answered, "
                 f"{len(replay.refused)} refused, {len(replay.unanswered)} unanswered; {replay.recorded} messages "
                 "recorded.")
    rows = []
    for row in data["scan_rows"]:
        scan = row["scan"]
        if "estimate" not in row:
            rows.append((scan.name, ("no answer", "bad"), "", "", ""))
            continue
        estimate, correction = row["estimate"], row["correction"]
        observable = [n for n in estimate.names if not scan.lifted.get(n, False)]
        worst = max(abs(estimate.values[list(estimate.names).index(n)] - scan.truth_mm[n]) for n in observable)
        rows.append((scan.name, ("within model", "good") if estimate.within_model else ("model lacks an effect", "bad"),
                     worst, ("yes", "good") if correction.safe_to_apply else ("no", "bad"),
                     correction.reason or ""))
    section.table(["scan", "verdict", "worst error of a boundary in contact (mm)", "correction safe to apply",
                   "reason"], rows)


def _scans(report: Report, state: Any) -> None:
    specs = state.data["scan_specs"]
    for row in state.data["scan_rows"]:
        scan = row["scan"]
        section = report.section(f"Scan '{scan.name}'")
        section.text(specs[scan.name].what + (f"; undeclared: {scan.undeclared_mm}" if scan.undeclared_mm else ""))
        if "estimate" not in row:
            section.text("The nodes did not answer this scan; see the logs in the output directory.", "bad")
            continue
        estimate, correction = row["estimate"], row["correction"]
        names = list(estimate.names)
        section.table(
            ["parameter", "true (mm)", "estimated (mm)", "std (mm)", "error (mm)", "contact", "correction (mm)"],
            [(name, scan.truth_mm[name], float(estimate.values[i]), float(estimate.std[i]),
              ("part position; commanded at or below" if estimate.lifted[i] else
               float(estimate.values[i] - scan.truth_mm[name])),
              "lifted" if estimate.lifted[i] else "in contact", float(correction.corrections[i]))
             for i, name in enumerate(names)],
            f"Residual RMS {estimate.residual_rms:.4f} mm, max {estimate.residual_max:.4f} mm, coverage "
            f"{estimate.coverage:.1%}. Correction for the adjustment robot: "
            f"{'safe to apply' if correction.safe_to_apply else 'NOT safe to apply: ' + correction.reason}")
        section.table(["effect", "parameters", "share of the field"],
                      [(e.name, ", ".join(e.parameters), f"{100 * e.share:.1f} %")
                       for e in row["decomposition"].effects],
                      "Effects kept by the decomposition (paper steps 3-6)")
        section.figures(state.figures.get(scan.name, []), state.out)


def _close_loop(report: Report, state: Any) -> None:
    section = report.section("Closing the loop")
    result = state.data.get("close_loop")
    if result is None:
        section.text("Not run.", "bad")
        return
    section.table(result["headers"], result["rows"], result["caption"])
    for line in result["text"]:
        section.text(line)
    section.figures(state.figures.get("close_loop", []), state.out)


def _timings(report: Report, state: Any, paper: dict[str, float]) -> None:
    data, seconds = state.data, state.timer.seconds
    members = data["ensemble_summary"]
    n_train = members["training"]["members"]
    n_val = members.get("validation", {}).get("members", 0)
    share = data["ensemble_seconds"] / max(n_train + n_val, 1)
    ours = {
        "training ensemble (729 runs)": share * n_train,
        "validation ensemble (1400 runs)": share * n_val,
        "PCA basis": None,
        "hierarchical basis": None,
        "parameter estimation (one field)": data["estimate_seconds"],
        "decomposition + contribution plots (one field)": data["decompose_seconds"],
    }
    section = report.section("Run times next to the paper's Table 3")
    section.text(f"This machine: the demo's steps took {sum(seconds.values()):.0f} s in all. The ensemble figures "
                 "are the measured ensemble time split by member count; both bases are built in one step "
                 f"({data['bases_seconds']:.1f} s). Estimation is the contact-aware estimator (the paper's PCA "
                 f"estimator: {1000 * data['estimate_pca_seconds']:.2f} ms).")
    rows = [(task, "" if ours[task] is None else float(ours[task]), float(paper[task]),
             "" if not ours[task] else f"{paper[task] / ours[task]:,.0f}x") for task in paper]
    rows.append(("both bases (PCA + hierarchical)", float(data["bases_seconds"]),
                 float(paper["PCA basis"] + paper["hierarchical basis"]),
                 f"{(paper['PCA basis'] + paper['hierarchical basis']) / data['bases_seconds']:,.0f}x"))
    section.table(["task", "hood_decomp (s)", "paper (s)", "speed-up"], rows)
    chart = [(task, float(ours[task]), paper[task]) for task in paper if ours[task]]
    chart.append(("both bases", float(data["bases_seconds"]), paper["PCA basis"] + paper["hierarchical basis"]))
    section.figures([(plot_timings(chart, state.out / "figures" / "timings.png"), "Run times, log scale")],
                    state.out)
    section.table(["demo step", "seconds"], [(name, float(value)) for name, value in seconds.items()])
