"""A directory of synthetic part fields (.vtu) of the 20 x 20 hood, written once per test module that asks."""

from __future__ import annotations

import pathlib

from hood_decomp.io.fields import write_field
from hood_decomp.synthetic.shift import ProcessModel, make_part, plan_shift
from tests.hood20 import hood20


def write_fields(directory: pathlib.Path, n: int, seed: int = 1, **process: float) -> pathlib.Path:
    """n part fields (a stable process unless ``process`` says otherwise) in ``directory``; returns it."""
    case = hood20()
    directory.mkdir(parents=True, exist_ok=True)
    options = {"drift_label": None, "step_label": None, **process}
    plan = plan_shift(case.reduced.names, ProcessModel(**options), n, seed=seed)
    for i in range(n):
        part = make_part(plan, i, case.truth_model, case.skin)
        write_field(directory / f"{part.part_id}.vtu", case.skin, part.field)
    return directory
