"""Synthetic data with a known truth: a structured-light scanner model, the demo's and bags' scenario scans, and
shifts of parts drawn from a process model (``shift``).

May import: ``hood_decomp.core`` and ``hood_decomp.errors``.
"""

from hood_decomp.synthetic.scanner import ScannerConfig, SyntheticScan, random_rigid, synthesize_scan
from hood_decomp.synthetic.scenarios import ScenarioScan, make_scenario_scan
from hood_decomp.synthetic.shift import ProcessModel, ShiftPart, ShiftPlan, make_part, plan_shift

__all__ = [
    "ProcessModel", "ScannerConfig", "ScenarioScan", "ShiftPart", "ShiftPlan", "SyntheticScan", "make_part",
    "make_scenario_scan", "plan_shift", "random_rigid", "synthesize_scan",
]
