"""The shift report (OUT/index.html with OUT/figures/, OUT/shift.json, OUT/history.csv), built with the demo's static
page builder: what a quality engineer reads after a shift."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from hood_decomp.demo.html import Report
from hood_decomp.io.history import History
from hood_decomp.io.json_values import json_ready
from hood_decomp.plots.method import plot_skin_field
from hood_decomp.shift import figures
from hood_decomp.shift.analysis import (
    SHARE_WINDOW,
    ShiftAnalysis,
    analyse_shift,
    analysis_json,
    mixing_note,
    reference_groups,
)
from hood_decomp.shift.spc import RULES

logger = logging.getLogger(__name__)


def _f(value: float, digits: int = 4) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def build_report(analysis: ShiftAnalysis, bases: Any, summary: Any, out: Path) -> Report:
    """The page (not yet written); figures are written to ``out/figures``."""
    fig_dir = out / "figures"
    records = analysis.table.records
    report = Report("hood_decomp: shift report",
                    f"{len(records)} parts, {int(analysis.ok.sum())} processed, {len(records) - int(analysis.ok.sum())}"
                    f" failed, {int(analysis.outside.sum())} outside the model. Lengths in mm.")
    section = report.section("Summary")
    section.table(["quantity", "value"], [
        ("parts in the inputs", summary.total), ("processed in this run", summary.processed),
        ("already in the history (not processed again)", summary.skipped), ("failed", len(summary.failed)),
        ("outside the model (chi-square test at alpha)", int(analysis.outside.sum())),
        ("Dask workers", summary.workers), ("wall time (s)", _f(summary.seconds, 1)),
        ("parts per second", _f(summary.rate, 2))])
    groups = reference_groups(analysis.table, analysis.ok)
    section.table(["reference", "calibration", "processed parts", "first part", "last part"],
                  [(g.reference or "none", g.calibration or "uncalibrated", g.parts, g.first, g.last) for g in groups],
                  "What the processed parts were estimated against (history columns reference, calibration)")
    note = mixing_note(groups)
    if note:
        section.text(note, "bad")
    failed = [r for r in records if r.status != "ok"]
    if failed:
        section.text("Failed parts (the batch went on without them):", "bad")
        section.table(["source", "part", "error"], [(r.source, r.part_id, r.error) for r in failed])
    else:
        section.text("No part failed.", "good")

    section = report.section("Control charts per boundary")
    section.text("Individuals charts with limits from a baseline period (centre, 1/2/3 sigma; sigma the larger of the "
                 "moving-range and the sample estimate of the baseline, times its 90 % upper-confidence allowance for "
                 "a baseline of that length), the Western Electric rules (the run rule with Nelson's 9 points) and "
                 "an EWMA (lambda 0.2, L 2.86) for slow drifts. Lifted buffers (a position bound, not a state), "
                 "failed parts and parts outside the model (their estimates carry the missing effect) are left out. "
                 "A measured effect (a parameter without a boundary, learned from recurring residuals) is charted by "
                 "its amplitude: a trend there is the incoming parts changing, with nothing to adjust.")
    measured = dict(zip(analysis.table.names, analysis.table.measured_effect, strict=True))
    rows = []
    for chart in analysis.charts:
        first = chart.first_alarm()
        rows.append((chart.name, "measured effect" if measured[chart.name] else "boundary", _f(chart.centre),
                     _f(chart.sigma), _f(chart.lcl), _f(chart.ucl), chart.baseline_end,
                     *[int(chart.alarms[rule].size) for rule in RULES],
                     "-" if first is None else f"{records[first[0]].part_id} ({first[1]})"))
    if rows:
        section.table(["parameter", "kind", "centre", "sigma", "LCL", "UCL", "monitored from part", *RULES,
                       "first alarm"], rows)
    else:
        section.text("Too few parts within the model for a control chart (at least 20 charted parts per boundary).",
                     "note")
    section.figures([(figures.plot_control_chart(chart, fig_dir / f"chart_{chart.name}.png"),
                      f"{chart.name} (measured effect)" if measured[chart.name] else chart.name)
                     for chart in analysis.charts], out)

    section = report.section("Capability against the parameter ranges")
    images = []
    if analysis.table.measured_effect.any():
        section.text("Measured effects (" + ", ".join(n for n, flag in measured.items() if flag) + ") have no "
                     "boundary and so no tolerance range: no capability for them.", "note")
    if not analysis.capabilities:
        section.text("No capability without a control chart.", "note")
    else:
        section.table(["boundary", "range (mm)", "mean", "sigma within", "sigma overall", "Cp", "Cpk", "Pp", "Ppk",
                       "outside range (%)"],
                      [(c.name, f"[{c.lower:g}, {c.upper:g}]", _f(c.mean), _f(c.sigma_within), _f(c.sigma_overall),
                        _f(c.cp, 2), _f(c.cpk, 2), _f(c.pp, 2), _f(c.ppk, 2), _f(100 * c.share_outside, 1))
                       for c in analysis.capabilities])
        images.append((figures.plot_capability(analysis.capabilities, fig_dir / "capability.png"), "Cpk and Ppk"))
    images.append((figures.plot_correlation(analysis.table.names, analysis.correlation, fig_dir / "correlation.png"),
                   "correlation between boundaries"))
    section.figures(images, out)

    section = report.section("Parts outside the model over time")
    section.text(f"Share of the last {SHARE_WINDOW} processed parts whose residual the within-model test rejects; "
                 f"without a missing effect it stays near alpha = {analysis.alpha:g}.")
    section.figures([(figures.plot_outside_share(analysis.outside_share, analysis.alpha, SHARE_WINDOW,
                                                 fig_dir / "outside_share.png"), "share outside the model")], out)

    section = report.section("Recurring residuals and measured effects")
    section.text(analysis.recurring_note)
    result = analysis.recurring
    if result is not None and result.modes:
        outside_rows = np.flatnonzero(analysis.outside)
        table_rows, images = [], []
        for mode in result.modes:
            carrying = mode.parts
            unit = "mm"
            table_rows.append((mode.name, mode.kind, int(carrying.sum()), _f(np.nanmean(mode.amplitude[carrying])),
                               _f(np.nanmean(mode.std[carrying])), _f(mode.explained, 3), f"{mode.p_value:.2g}",
                               _f(float(np.mean(mode.rms_before)) if mode.rms_before.size else np.nan),
                               _f(float(np.mean(mode.rms_after)) if mode.rms_after.size else np.nan),
                               _f(float(np.mean(mode.expected_rms)) if mode.expected_rms.size else np.nan)))
            images.append((plot_skin_field(bases.skin, mode.field, fig_dir / f"mode_{mode.name}.png",
                                           f"{mode.name} ({mode.kind}): basis field per unit", "mm / unit",
                                           cmap="RdBu_r"), f"map of {mode.name}"))
            images.append((figures.plot_amplitudes(mode.name, outside_rows[carrying], mode.amplitude[carrying],
                                                   mode.std[carrying], unit, fig_dir / f"amplitude_{mode.name}.png"),
                           f"{mode.name}: amplitude per part"))
        section.table(["mode", "kind", "parts", "mean amplitude", "mean std", "best candidate explains",
                       "p (cross-validated)", "residual RMS before", "after (judging half)", "expected"], table_rows,
                      "Before/after: the mode learned on one half of the parts, judged on the other half")
        section.figures(images, out)
    return report


def write_measured_bases(bases: Any, measured: tuple, path: Path) -> Path:
    """Bases rebuilt with the measured effects (core/loop/measured_effects.augmented_bases), saved to ``path``."""
    from hood_decomp.core.loop.close_loop import training_ensemble
    from hood_decomp.core.loop.measured_effects import augmented_bases
    from hood_decomp.io.bases import save_bases

    logger.info("shift: rebuilding the bases with %s", ", ".join(mode.name for mode in measured))
    save_bases(path, augmented_bases(bases, training_ensemble(bases), measured))
    return path


def analyse_and_report(history: History, sources: list[str], bases: Any, out: Path, summary: Any,
                       baseline: int, alpha: float = 0.01, model_path: Path | None = None) -> Path:
    """Analyse the history's parts from ``sources`` with the shift's ``bases`` and write the report, shift.json and
    history.csv into ``out``."""
    candidates = None
    if model_path is not None:
        from hood_decomp.core.fe.solver import build_solver
        from hood_decomp.core.loop.candidates import candidate_fields, enumerate_candidates
        from hood_decomp.io.model_files import load_model_with_candidates

        model, user = load_model_with_candidates(model_path)
        candidates = candidate_fields(build_solver(model), enumerate_candidates(model, user))
    analysis = analyse_shift(history, sources, bases, baseline, alpha, candidates)
    numbers = analysis_json(analysis, summary)
    rebuilt = None
    if analysis.recurring is not None and analysis.recurring.measured:
        rebuilt = write_measured_bases(bases, analysis.recurring.measured, out / "bases_measured.h5")
        numbers["recurring"]["bases_measured"] = str(rebuilt)
    (out / "shift.json").write_text(json.dumps(json_ready(numbers), indent=2, allow_nan=False) + "\n")
    history.export_csv(out / "history.csv")
    report = build_report(analysis, bases, summary, out)
    if rebuilt is not None:
        report.sections[-1].text(f"Bases rebuilt with the measured effects as parameters without a boundary (the "
                                 f"estimator reports their amplitudes; corrections never move a boundary for them): "
                                 f"{rebuilt.name}. Candidate effects found above are not in them: add those with "
                                 "hood-decomp close-loop.")
    path = report.write(out / "index.html")
    logger.info("shift: report written to %s", path)
    return path
