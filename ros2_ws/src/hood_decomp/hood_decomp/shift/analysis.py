"""A shift's analysis from its results history, and its report: control charts and run rules per boundary,
capability, correlation, the share of parts outside the model over time, the recurring residual modes (traced to FE
candidates when a model is given, else offered as measured effects), the failed parts by name, and the references and
calibrations the parts were estimated against (a shift mixing references is said to: its values are not comparable).

Writes OUT/index.html (figures in OUT/figures/), OUT/shift.json (the numbers behind the report) and OUT/history.csv.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from hood_decomp.errors import ShiftError
from hood_decomp.io.history import History, HistoryTable
from hood_decomp.shift.spc import (
    RULES,
    Capability,
    ControlChart,
    capability,
    correlation,
    individuals_chart,
    rolling_share,
)

logger = logging.getLogger(__name__)

#: parts in the rolling share of parts outside the model
SHARE_WINDOW = 25
#: most recent parts outside the model whose residuals the recurring-mode search reads
MAX_RECURRING_PARTS = 400


@dataclass(frozen=True)
class ShiftAnalysis:
    """table: the shift's parts (time order). ok: (M,) processed parts. charts: per parameter with enough charted
    parts (a measured effect's chart follows its amplitude: ``table.measured_effect``); capabilities: per boundary
    with a chart (a measured effect has no tolerance range to be capable against). correlation: (P, P). outside:
    (M,) bool; outside_share: (M,) rolling share.
    recurring: a RecurringResult or None (with ``recurring_note`` saying why). alpha: the within-model level."""

    table: HistoryTable
    ok: np.ndarray
    charts: tuple[ControlChart, ...]
    capabilities: tuple[Capability, ...]
    correlation: np.ndarray
    outside: np.ndarray
    outside_share: np.ndarray
    recurring: Any
    recurring_note: str
    alpha: float


@dataclass(frozen=True)
class ReferenceGroup:
    """Processed parts of a shift estimated against one reference with one calibration: ``reference`` ("" none) and
    ``calibration`` (id, "" uncalibrated) as the history records them, ``parts`` their count, ``first`` and ``last``
    the part ids in time order."""

    reference: str
    calibration: str
    parts: int
    first: str
    last: str


def reference_groups(table: HistoryTable, ok: np.ndarray) -> tuple[ReferenceGroup, ...]:
    """The processed (``ok``) parts of ``table`` grouped by (reference, calibration), in order of first appearance."""
    rows: dict[tuple[str, str], list[str]] = {}
    for record, processed in zip(table.records, ok, strict=True):
        if processed:
            rows.setdefault((record.reference, record.calibration), []).append(record.part_id)
    return tuple(ReferenceGroup(reference, calibration, len(ids), ids[0], ids[-1])
                 for (reference, calibration), ids in rows.items())


def mixing_note(groups: tuple[ReferenceGroup, ...]) -> str:
    """What a reader must know when the parts were estimated against more than one reference or calibration ("" when
    all share one): values against different references (or bases calibrated differently) are not comparable."""
    references = list(dict.fromkeys(group.reference or "none" for group in groups))
    calibrations = list(dict.fromkeys(group.calibration or "uncalibrated" for group in groups))
    notes = []
    if len(references) > 1:
        notes.append(f"This shift mixes {len(references)} references ({', '.join(references)}): a part's values are "
                     "relative to its reference's known state, so values across different references are not "
                     "comparable, and the control charts, capability and correlation below pool them as one process.")
    if len(calibrations) > 1:
        notes.append(f"This shift mixes {len(calibrations)} calibrations of the bases ({', '.join(calibrations)}): "
                     "values estimated with differently calibrated bases are not comparable either.")
    return " ".join(notes)


def chart_values(table: HistoryTable, ok: np.ndarray) -> np.ndarray:
    """(M, P) values to chart: NaN for failed parts, for parts outside the model (their estimates carry the missing
    effect; they are charted by the share outside the model and the recurring modes) and for lifted boundaries (a
    position bound, not a state)."""
    values = np.where(table.lifted, np.nan, table.values)
    values[~ok | ~np.array([r.within_model for r in table.records], dtype=bool)] = np.nan
    return values


def analyse_shift(history: History, sources: list[str], bases: Any, baseline: int, alpha: float = 0.01,
                  candidates: Any = None) -> ShiftAnalysis:
    """The analysis (module docstring) of the history's parts from ``sources``; bases: the shift's Bases."""
    from hood_decomp.core.loop.measured_effects import analyse_recurring

    full = history.table()
    keep = np.array([r.source in sources for r in full.records], dtype=bool)
    if not keep.any():
        raise ShiftError(f"the history holds no part of {sources}")
    table = HistoryTable(tuple(r for r, k in zip(full.records, keep, strict=True) if k), full.names,
                         full.values[keep], full.std[keep], full.lifted[keep], full.measured_effect)
    ok = np.array([r.status == "ok" for r in table.records])
    values = chart_values(table, ok)
    names = list(table.names)
    lower = dict(zip(bases.names, bases.pca.lower_, strict=True))
    upper = dict(zip(bases.names, bases.pca.upper_, strict=True))
    charts, capabilities = [], []
    for column, name in enumerate(names):
        charted = int(np.isfinite(values[:, column]).sum())
        size = min(baseline, charted // 2)
        if size < 10:
            logger.info("%s: %d charted parts, too few for a control chart", name, charted)
            continue
        charts.append(individuals_chart(name, values[:, column], size))
        if name in lower and not table.measured_effect[column]:
            capabilities.append(capability(name, values[:, column], lower[name], upper[name]))
    outside = ok & ~np.array([r.within_model for r in table.records])
    rows = np.flatnonzero(outside)[-MAX_RECURRING_PARTS:]
    recurring, note = None, ""
    if bases.reduced_model is None:
        note = "the bases hold no reduced model: recurring residuals cannot be analysed"
    elif rows.size < 10:
        note = f"{rows.size} parts outside the model: too few to look for recurring residual modes"
    else:
        residuals = history.residuals([table.records[i].key for i in rows])
        noise = np.array([table.records[i].noise_mm for i in rows])
        inside = ok & ~outside
        state = np.nanmedian(table.values[inside if inside.any() else ok], axis=0)
        recurring = analyse_recurring(bases, residuals, noise, table.values[rows], state, candidates, alpha=alpha)
        note = recurring.message if candidates is not None else (
            recurring.message + " (no --model given: modes could not be traced to FE candidates)")
    return ShiftAnalysis(table, ok, tuple(charts), tuple(capabilities), correlation(values), outside,
                         rolling_share(outside[ok], SHARE_WINDOW), recurring, note, alpha)


def analysis_json(analysis: ShiftAnalysis, summary: Any) -> dict[str, Any]:
    """The numbers behind the report (mm), JSON-ready through io.json_values."""
    records = analysis.table.records
    rows = np.flatnonzero(analysis.outside)
    measured = dict(zip(analysis.table.names, analysis.table.measured_effect, strict=True))
    groups = reference_groups(analysis.table, analysis.ok)
    out: dict[str, Any] = {
        "parts": len(records), "processed": int(analysis.ok.sum()),
        "failed": [{"source": r.source, "part_id": r.part_id, "error": r.error} for r in records if r.status != "ok"],
        "outside_model": int(analysis.outside.sum()), "alpha": analysis.alpha,
        "batch": {"total": summary.total, "processed": summary.processed, "skipped": summary.skipped,
                  "failed": len(summary.failed), "seconds": summary.seconds, "workers": summary.workers,
                  "parts_per_s": summary.rate},
        "boundaries": {
            chart.name: {"measured_effect": bool(measured[chart.name]), "centre_mm": chart.centre,
                         "sigma_mm": chart.sigma, "sigma_estimate_mm": chart.sigma_estimate,
                         "lcl_mm": chart.lcl, "ucl_mm": chart.ucl,
                         "baseline_parts": chart.baseline_end,
                         "alarms": {rule: [records[i].part_id for i in chart.alarms[rule]] for rule in RULES},
                         "first_alarm": None if chart.first_alarm() is None else
                         {"part_id": records[chart.first_alarm()[0]].part_id, "index": chart.first_alarm()[0],
                          "rule": chart.first_alarm()[1]}}
            for chart in analysis.charts},
        "capability": {c.name: {"cp": c.cp, "cpk": c.cpk, "pp": c.pp, "ppk": c.ppk, "mean_mm": c.mean,
                                "share_outside_range": c.share_outside} for c in analysis.capabilities},
        "correlation": {"names": list(analysis.table.names), "matrix": analysis.correlation},
        "measured_effects": [n for n, flag in measured.items() if flag],
        "references": [{"reference": g.reference, "calibration": g.calibration, "parts": g.parts,
                        "first_part": g.first, "last_part": g.last} for g in groups],
        "references_note": mixing_note(groups),
        "recurring": {"note": analysis.recurring_note, "modes": []},
    }
    if analysis.recurring is not None:
        for mode in analysis.recurring.modes:
            carrying = np.flatnonzero(mode.parts)
            out["recurring"]["modes"].append({
                "kind": mode.kind, "name": mode.name, "parts": [records[rows[i]].part_id for i in carrying],
                "amplitude": mode.amplitude[carrying], "std": mode.std[carrying],
                "candidate_scores": dict(mode.candidate_scores), "explained_by_best_candidate": mode.explained,
                "p_value": mode.p_value, "n_learn": mode.n_learn, "n_judge": mode.n_judge,
                "cross_validated": {"parts": int(mode.judged.sum()),
                                    "residual_rms_before_mm": mode.rms_before, "residual_rms_after_mm": mode.rms_after,
                                    "expected_rms_mm": mode.expected_rms},
                "values_after_mm": {records[rows[i]].part_id: dict(zip(analysis.table.names, mode.values_after[i],
                                                                       strict=True)) for i in carrying},
            })
    return out
