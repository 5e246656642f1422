"""Synthetic measurement scenarios with known truth: a boundary setting, its FE solution and a structured-light scan.

Used by the bag generator (scripts/make_bags.py), the demo and the tests. A setting may include boundary motions that
are not declared parameters (``"hinge_R.z": 0.4``): the undeclared effects the close-the-loop step must find.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hood_decomp.core.fe.ensemble import simulate_setting, solve_members
from hood_decomp.core.fe.solver import ShellSolver
from hood_decomp.core.types import ReducedModel, SkinSurface
from hood_decomp.synthetic.scanner import ScannerConfig, SyntheticScan, synthesize_scan


@dataclass(frozen=True)
class ScenarioScan:
    """One synthetic measurement.

    settings: what was set, mm (declared labels and "boundary.direction" keys).
    truth_mm: declared parameter label -> commanded state, mm (a lifted buffer's commanded position lies at or below
        the part's position there, which is all a field can reveal).
    lifted: declared unilateral label -> True when the buffer lost contact in the true solution.
    undeclared_mm: the settings that are not declared parameters (the effects the model lacks).
    normal_displacement: (N,) mm, the true field; scan: the synthetic scan of it.
    """

    name: str
    settings: dict[str, float]
    truth_mm: dict[str, float]
    lifted: dict[str, bool]
    undeclared_mm: dict[str, float]
    normal_displacement: np.ndarray
    scan: SyntheticScan
    config: ScannerConfig = field(repr=False)


def make_scenario_scan(name: str, solver: ShellSolver, reduced: ReducedModel, skin: SkinSurface,
                       settings: dict[str, float], config: ScannerConfig, seed: int) -> ScenarioScan:
    """Solve ``settings`` exactly (contact included) and scan the displaced skin with ``config``."""
    names = reduced.names
    undeclared = {key: float(value) for key, value in settings.items() if key not in names}
    truth = {label: float(settings.get(label, 0.0)) for label in names}
    unilateral = names[reduced.n_bilateral:]
    if undeclared:
        setting = simulate_setting(solver, settings)
        normal, displacement = setting.normal_displacement, setting.displacement
        lifted = {label: bool(setting.contact_fraction[label] == 0.0) for label in unilateral}
    else:
        member = solve_members(reduced, np.array([[truth[label] for label in names]]))
        normal, displacement = member.normal_displacement[0], member.displacement[0]
        lifted = {label: bool(member.contact_fraction[0, i] == 0.0) for i, label in enumerate(unilateral)}
    return ScenarioScan(name, dict(settings), truth, lifted, undeclared, np.asarray(normal),
                        synthesize_scan(skin, np.asarray(displacement), config, seed=seed), config)
