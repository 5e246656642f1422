"""Test-session setup shared by all tests.

ROS 2 discovery stays on loopback and each test run gets its own domain, so parallel runs never see each other and no
discovery traffic leaves the machine. This must happen before any rclpy.init().
"""

import dataclasses
import os
import pathlib
from typing import Any

import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
os.environ.setdefault("MPLBACKEND", "Agg")


@dataclasses.dataclass(frozen=True)
class CoarseHood:
    """The built-in hood at coarse resolution with its full-factorial ensemble and saved bases (built once)."""

    model: Any
    skin: Any
    solver: Any
    reduced: Any
    ensemble: Any
    bases: Any
    bases_path: pathlib.Path


@pytest.fixture(scope="session")
def coarse_hood(tmp_path_factory: pytest.TempPathFactory) -> CoarseHood:
    from hood_decomp.core.ensemble import factorial_plan, simulate_ensemble
    from hood_decomp.core.fe import build_solver, reduce_model
    from hood_decomp.core.hood_preset import build_hood
    from hood_decomp.core.model import skin_surface
    from hood_decomp.io.bases import build_bases, save_bases

    model = build_hood("coarse")
    skin = skin_surface(model)
    solver = build_solver(model)
    reduced = reduce_model(solver)
    commanded, rank = factorial_plan(model.lower, model.upper)
    ensemble = simulate_ensemble(reduced, commanded, rank, model.lower, model.upper)
    bases = build_bases(ensemble, skin, reduced)
    path = tmp_path_factory.mktemp("coarse_hood") / "bases.h5"
    save_bases(path, bases)
    return CoarseHood(model, skin, solver, reduced, ensemble, bases, path)
