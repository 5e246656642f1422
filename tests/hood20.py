"""A 20 x 20 built-in hood (400 skin nodes) with its bases and a truth model holding the candidate input hinge_R.z:
fast enough (about 2 s, built once a session) for the shift tests, which process hundreds of parts."""

from __future__ import annotations

import dataclasses
import functools
import pathlib
import tempfile
from typing import Any


@dataclasses.dataclass(frozen=True)
class Hood20:
    model: Any
    skin: Any
    solver: Any
    reduced: Any
    truth_model: Any
    ensemble: Any
    bases: Any
    bases_path: pathlib.Path


@functools.cache
def hood20() -> Hood20:
    from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble
    from hood_decomp.core.fe.hood_preset import build_hood
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver, reduce_model
    from hood_decomp.core.method.bases import build_bases
    from hood_decomp.io.bases import save_bases

    model = build_hood("coarse", grid=(20, 20))
    skin = skin_surface(model)
    solver = build_solver(model)
    reduced = reduce_model(solver)
    truth_model = reduce_model(solver, extra=[("hinge_R", "z")])
    commanded, rank = factorial_plan(model.lower, model.upper)
    ensemble = simulate_ensemble(reduced, commanded, rank, model.lower, model.upper)
    bases = build_bases(ensemble, skin, reduced)
    path = pathlib.Path(tempfile.mkdtemp(prefix="hood20_")) / "bases.h5"
    save_bases(path, bases)
    return Hood20(model, skin, solver, reduced, truth_model, ensemble, bases, path)
