"""Synthetic data with a known truth: a structured-light scanner model and the demo's and bags' scenario scans.

May import: ``hood_decomp.core`` and ``hood_decomp.errors``.
"""

from hood_decomp.synthetic.scanner import ScannerConfig, SyntheticScan, synthesize_scan
from hood_decomp.synthetic.scenarios import ScenarioScan, make_scenario_scan

__all__ = ["ScannerConfig", "ScenarioScan", "SyntheticScan", "make_scenario_scan", "synthesize_scan"]
