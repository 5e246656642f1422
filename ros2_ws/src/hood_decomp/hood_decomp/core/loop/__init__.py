"""Closing the loop: candidate effects the FE model can compute, tracing a residual to them, adding the effect and
rebuilding the bases, the error before and after; recurring residuals over many parts traced to candidates or
offered as measured effects (``measured_effects``); the prepared scan skin of a set of bases with the scan step's bias
measured on the part's own states (``scan_skin``).

May import: ``hood_decomp.core.fe``, ``hood_decomp.core.method``, ``hood_decomp.core.scan``, ``hood_decomp.core.types``
and ``hood_decomp.errors``.
"""

from hood_decomp.core.loop.candidates import Candidate, candidate_fields, enumerate_candidates
from hood_decomp.core.loop.close_loop import CloseLoopResult, close_loop, trace_effect
from hood_decomp.core.loop.measured_effects import FoundMode, RecurringResult, analyse_recurring, augmented_bases
from hood_decomp.core.loop.scan_skin import prepared_scan_skin

__all__ = [
    "Candidate", "CloseLoopResult", "FoundMode", "RecurringResult", "analyse_recurring", "augmented_bases",
    "candidate_fields", "close_loop", "enumerate_candidates", "prepared_scan_skin", "trace_effect",
]
