"""What the demo's modules share: its configuration, the step timer, the paper's Table 3 and one number helper."""

from __future__ import annotations

import logging
import pathlib
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

logger = logging.getLogger(__name__)

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
    """out: report directory; preset: built-in model (hood | hood-paper); resolution: hood mesh; n_validation:
    validation members; scan_points: per scan."""

    out: pathlib.Path
    preset: str = "hood"
    resolution: str = "default"
    n_validation: int = 1400
    scan_points: int = 1_000_000


@dataclass
class Timer:
    """Wall times of the demo's steps (s, by step name), logged as each starts and finishes."""

    seconds: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def step(self, name: str) -> Iterator[None]:
        logger.info("%s ...", name)
        start = time.perf_counter()
        yield
        self.seconds[name] = time.perf_counter() - start
        logger.info("%s: done in %.1f s", name, self.seconds[name])


def max_abs(values: np.ndarray) -> float:
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    return float(np.abs(finite).max()) if finite.size else float("nan")
