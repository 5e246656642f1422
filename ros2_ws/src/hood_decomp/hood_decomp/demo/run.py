"""The main job: the whole system on the built-in hood, ending in ``DIR/index.html``.

Steps (each timed and shown on the terminal): hood model (preset hood or hood-paper) -> solver and ensemble (729
training + validation members) -> PCA and hierarchical bases -> the interaction maps of both presets -> validation on
the validation set -> synthetic scans with known truth (clean, noisy, occluded, one with an undeclared effect)
written as a bag -> bag replayed through the three ROS nodes running as separate processes, their output recorded ->
close the loop on the undeclared scan -> the report. Progress goes to the ``hood_decomp`` loggers (``hood-decomp
demo`` prints it).
"""

from __future__ import annotations

import json
import logging
import pathlib

from hood_decomp.demo import steps
from hood_decomp.demo.config import DemoConfig, Timer

logger = logging.getLogger(__name__)


def run_demo(config: DemoConfig) -> pathlib.Path:
    """Run every step; returns the path of the report."""
    out = config.out
    out.mkdir(parents=True, exist_ok=True)
    timer = Timer()
    state = steps.DemoState(config=config, out=out, timer=timer)
    for title, step in (
        ("hood model", steps.build_model),
        ("solver: assembly and one factorisation", steps.build_solver_and_reduce),
        ("ensemble: 729 training + validation members", steps.build_ensemble),
        ("bases: PCA and hierarchical", steps.build_bases_step),
        ("interaction maps of both presets", steps.interaction_maps),
        ("validation of the estimators on the validation set", steps.validate),
        ("synthetic scans and scenario bag", steps.make_scans),
        ("replay through the three ROS nodes", steps.replay),
        ("per-scan results and contribution plots", steps.analyse_scans),
        ("close the loop on the scan with an undeclared effect", steps.close_loop),
    ):
        with timer.step(title):
            step(state)
    with timer.step("report"):
        path = steps.write_report(state)
    (out / "timings.json").write_text(json.dumps({k: round(v, 3) for k, v in timer.seconds.items()}, indent=2))
    logger.info("report: %s", path.resolve())
    return path
