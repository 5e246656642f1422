"""The part and its finite-element model: model description, the built-in hood preset, the flat-facet shell element,
the embedded solver and its reduced model, exact pad contact, CalculiX decks and jobs, and the simulation ensemble.

May import: ``hood_decomp.core.types`` and ``hood_decomp.errors`` only (never ``method``, ``scan`` or ``loop``).
"""

from hood_decomp.core.fe.calculix import ccx_executable, reduce_model_calculix
from hood_decomp.core.fe.contact import contact_state, solve_lcp
from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble, simulate_setting, validation_plan
from hood_decomp.core.fe.geometric import NonlinearSolver, buckling_factor, nonlinear_ensemble
from hood_decomp.core.fe.hood_preset import PRESETS, build_hood, build_hood_paper, build_preset
from hood_decomp.core.fe.model import Boundary, Material, Parameter, Part, PartModel, Patch, patch_nodes, skin_surface
from hood_decomp.core.fe.solver import ShellSolver, build_solver, reduce_model

__all__ = [
    "PRESETS", "Boundary", "Material", "NonlinearSolver", "Parameter", "Part", "PartModel", "Patch", "ShellSolver",
    "buckling_factor", "build_hood",
    "build_hood_paper", "build_preset", "build_solver",
    "ccx_executable", "contact_state", "factorial_plan", "nonlinear_ensemble", "patch_nodes", "reduce_model",
    "reduce_model_calculix",
    "simulate_ensemble", "simulate_setting", "skin_surface", "solve_lcp", "validation_plan",
]
