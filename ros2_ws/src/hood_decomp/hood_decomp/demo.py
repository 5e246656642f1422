"""The main job: the whole system on the built-in hood, ending in ``DIR/index.html``.

Steps (each timed and shown on the terminal): hood model -> solver and ensemble (729 training + validation members)
-> PCA and hierarchical bases, validated on the validation set -> synthetic scans with known truth (clean, noisy,
occluded, one with an undeclared effect) written as a bag -> bag replayed through the three ROS nodes running as
separate processes, their output recorded -> close the loop on the undeclared scan -> the report.
"""

from __future__ import annotations

import json
import pathlib
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

# The paper's Table 3, seconds (ABAQUS on an i7-5820K; PCA with scikit-learn; scipy least squares).
PAPER_TABLE3_S = {
    "training ensemble (729 runs)": 729 * 187.0,
    "validation ensemble (1400 runs)": 1400 * 187.0,
    "PCA basis": 41.0,
    "hierarchical basis": 3 * 3600 + 21 * 60.0,
    "parameter estimation (one field)": 1.84,
    "decomposition + contribution plots (one field)": 19.77,
}


@dataclass(frozen=True)
class DemoConfig:
    """out: report directory; resolution: hood mesh; n_validation: validation members; scan_points: per scan."""

    out: pathlib.Path
    resolution: str = "default"
    n_validation: int = 1400
    scan_points: int = 1_000_000


@dataclass
class Timer:
    """Wall times of the demo's steps, shown as they finish."""

    progress: Callable[[str], None]
    seconds: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def step(self, name: str) -> Iterator[None]:
        self.progress(f"{name} ...")
        start = time.perf_counter()
        yield
        self.seconds[name] = time.perf_counter() - start
        self.progress(f"{name}: done in {self.seconds[name]:.1f} s")


def _print(line: str) -> None:
    print(f"[demo {time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


def run_demo(config: DemoConfig, progress: Callable[[str], None] = _print) -> pathlib.Path:
    """Run every step; returns the path of the report."""
    from hood_decomp import demo_steps as steps

    out = config.out
    out.mkdir(parents=True, exist_ok=True)
    timer = Timer(progress)
    state = steps.DemoState(config=config, out=out, timer=timer)
    for title, step in (
        ("hood model", steps.build_model),
        ("solver: assembly and one factorisation", steps.build_solver_and_reduce),
        ("ensemble: 729 training + validation members", steps.build_ensemble),
        ("bases: PCA and hierarchical", steps.build_bases_step),
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
    progress(f"report: {path.resolve()}")
    return path


def max_abs(values: np.ndarray) -> float:
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    return float(np.abs(finite).max()) if finite.size else float("nan")
