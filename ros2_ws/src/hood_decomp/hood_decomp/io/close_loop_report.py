"""The JSON report of closing the loop (``close_loop.json``, fields in docs/close_loop.md): residual before/after,
the effect found and its magnitude, the candidates' ranking and, where the truth is known, every parameter's error."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from hood_decomp.core.loop.close_loop import CloseLoopResult
from hood_decomp.core.method.residual import ResidualAnalysis
from hood_decomp.core.types import ParameterEstimate
from hood_decomp.errors import FieldError
from hood_decomp.io.json_values import json_ready


def _estimate_entry(estimate: ParameterEstimate, truth: Mapping[str, float]) -> dict:
    params = {}
    for name, value, std, lifted in zip(estimate.names, estimate.values, estimate.std, estimate.lifted, strict=True):
        entry = {"value": value, "std": std, "lifted": lifted}
        if name in truth:
            entry["truth"] = float(truth[name])
            # a lifted pad's value is the part's position there, not its commanded position: no error to state
            entry["error"] = None if lifted else value - truth[name]
        params[name] = entry
    return params


def _analysis_entry(analysis: ResidualAnalysis, max_regions: int = 5) -> dict:
    return {
        "residual_rms_mm": analysis.rms_mm, "residual_max_mm": analysis.max_mm, "residual_mean_mm": analysis.mean_mm,
        "noise_mm": analysis.noise_mm, "noise_source": analysis.noise_source, "chi2": analysis.chi2,
        "dof": analysis.dof, "p_value": analysis.p_value, "within_model": analysis.within_model,
        "regions": [{"centroid_mm": r.centroid, "peak_mm": r.peak_mm, "peak_point_mm": r.peak_point,
                     "area_mm2": r.area_mm2, "rms_mm": r.rms_mm, "n_nodes": r.nodes.size}
                    for r in analysis.regions[:max_regions]],
    }


def _named(result: CloseLoopResult) -> list[dict]:
    """A partial outcome's named candidate (not added): its magnitude per field and the residual RMS with it."""
    if result.status != "partial":
        return []
    best = result.traces[0].best
    return [{"name": best.name, "kind": best.kind, "unit": best.unit, "description": best.description,
             "magnitude": best.values, "std": best.std, "explained": best.explained,
             "residual_rms_with_it_mm": [float(np.sqrt(rss / a.n_seen))
                                         for rss, a in zip(best.rss_mm2, result.analyses_before, strict=True)]}]


def close_loop_report(result: CloseLoopResult, truth: Sequence[Mapping[str, float]] | None = None,
                      top: int = 5) -> dict:
    """The JSON-ready report of :func:`hood_decomp.core.loop.close_loop.close_loop` (non-finite numbers are null).

    truth: per field, label -> true value (mm, or N for a force effect); parameters without truth get no error.
    top: candidates listed per trace step. Raises FieldError when ``truth`` has not one entry per field.
    """
    truth = list(truth) if truth is not None else [{} for _ in result.before]
    if len(truth) != len(result.before):
        raise FieldError(f"truth has {len(truth)} entries, expected one per field ({len(result.before)})")
    fields = []
    for i, estimate in enumerate(result.before):
        entry = {"before": {"parameters": _estimate_entry(estimate, truth[i]),
                            **_analysis_entry(result.analyses_before[i])}}
        if result.after:
            entry["after"] = {"parameters": _estimate_entry(result.after[i], truth[i]),
                              **_analysis_entry(result.analyses_after[i])}
        fields.append(entry)
    traces = [{
        "ranking": [{"name": s.name, "kind": s.kind, "unit": s.unit, "description": s.description,
                     "explained": s.explained, "f_statistic": s.f_statistic, "p_adjusted": s.p_adjusted,
                     "magnitude": s.values, "std": s.std} for s in trace.scores[:top]],
        "pairs": [{"names": list(p.names), "explained": p.explained, "f_statistic": p.f_statistic,
                   "p_adjusted": p.p_adjusted, "within_model": p.within_after, "magnitude": p.values, "std": p.std}
                  for p in trace.pairs[:top]],
        "significant": trace.significant, "decisive": trace.decisive, "within_model_with_best": trace.within_after,
        "outcome": trace.outcome, "named": list(trace.named), "likelihood_ratio_to_runner_up": trace.decisiveness,
        "reason": trace.reason,
    } for trace in result.traces]
    return json_ready({
        "status": result.status,
        "message": result.message,
        "within_model_before": result.within_model_before,
        "p_value_before": result.p_value_before,
        "within_model_after": result.within_model_after,
        "p_value_after": result.p_value_after,
        "residual_rms_before_mm": [a.rms_mm for a in result.analyses_before],
        "residual_max_before_mm": [a.max_mm for a in result.analyses_before],
        "residual_rms_after_mm": [a.rms_mm for a in result.analyses_after],
        "residual_max_after_mm": [a.max_mm for a in result.analyses_after],
        "effects_found": [{"name": a.name, "kind": a.kind, "unit": a.unit, "boundary": a.boundary,
                           "description": a.description, "magnitude": a.values, "std": a.std,
                           "range": [a.lower, a.upper]} for a in result.added],
        "effects_named": _named(result),
        "traces": traces,
        "fields": fields,
        "timings_s": result.timings,
    })
