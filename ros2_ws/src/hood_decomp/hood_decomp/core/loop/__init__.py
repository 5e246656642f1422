"""Closing the loop: candidate effects the FE model can compute, tracing a residual to them, adding the effect and
rebuilding the bases, the error before and after.

May import: ``hood_decomp.core.fe``, ``hood_decomp.core.method``, ``hood_decomp.core.types`` and ``hood_decomp.errors``.
"""

from hood_decomp.core.loop.candidates import Candidate, candidate_fields, enumerate_candidates
from hood_decomp.core.loop.close_loop import CloseLoopResult, close_loop, trace_effect

__all__ = ["Candidate", "CloseLoopResult", "candidate_fields", "close_loop", "enumerate_candidates", "trace_effect"]
