"""One part through the same core path as the nodes: field (from a bag's PointCloud2, a scan file or a field file)
-> reference-relative when the shift has a reference -> estimate -> correction -> decomposition -> the within-model
test, as one :class:`~hood_decomp.io.history.PartRecord` naming the reference and the bases' calibration it used.

:func:`process_task` is what a Dask worker runs. It never raises for a bad part: any error becomes a record with
status "failed" naming it, so one bad part never stops a batch. Each worker process loads a bases file once
(:func:`worker_bases`) and keeps it with its fitted estimators, and the shift's reference once for them
(:func:`worker_reference`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hood_decomp.core.method.bases import Bases, analyse_estimate, decompose_field, estimate_field
from hood_decomp.core.method.correction import CorrectionPolicy, plan_correction
from hood_decomp.core.method.residual import DEFAULT_ALPHA, ResidualAnalysis
from hood_decomp.core.types import DisplacementField, ParameterEstimate
from hood_decomp.errors import BagError
from hood_decomp.io.history import PartRecord, bases_file_id, inspection_record

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PartTask:
    """One part to process. kind: "cloud" (``data``: a serialised sensor_msgs/PointCloud2 from a bag, with the cell
    calibration ``scanner_pose_mm`` (4x4) and ``markers_mm`` (id -> (3,) mm) of its sidecar), "field" (a .vtu at
    ``path``), "scan" (a .ply at ``path``) or "multiview" (a bag at ``path`` holding one part in several views: not
    fused here, recorded as failed with the reason). source, part_id, message, stamp_ns: as the history keeps
    them."""

    source: str
    part_id: str
    message: int
    stamp_ns: int
    kind: str
    path: str
    data: bytes | None = None
    scanner_pose_mm: tuple[float, ...] | None = None
    markers_mm: tuple[tuple[int, float, float, float], ...] = ()

    @property
    def key(self) -> tuple[str, str]:
        return (self.source, self.part_id)


@dataclass(frozen=True)
class Options:
    """How every part is processed: estimator ``method``, ``min_coverage`` of a field, the correction ``policy``,
    the within-model test's ``alpha``, ``shift`` label, ``keep_residual`` (store the residual field in the history),
    ``reference``: a REF.json (absolute path) every part's field is made relative to, as the nodes' cell reference
    (io.calibration_files.read_reference); "" none."""

    method: str = "contact"
    min_coverage: float = 0.2
    policy: CorrectionPolicy = dataclasses.field(default_factory=CorrectionPolicy)
    alpha: float = DEFAULT_ALPHA
    shift: str = ""
    keep_residual: bool = True
    reference: str = ""


_BASES: dict[tuple[str, int, int], tuple[Bases, str]] = {}


def worker_bases(path: str) -> tuple[Bases, str]:
    """The bases at ``path`` and their id, loaded once per process (keyed by path, size and modification time)."""
    from hood_decomp.io.bases import load_bases

    stat = Path(path).stat()
    key = (str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns)
    if key not in _BASES:
        _BASES.clear()
        _BASES[key] = (load_bases(path), bases_file_id(path))
    return _BASES[key]


_REFERENCE: dict[tuple[str, str, float], Any] = {}


def worker_reference(path: str, bases: Bases, min_coverage: float) -> Any:
    """The REF.json at ``path`` read for ``bases`` (io.calibration_files.Reference), once per process while neither
    changes (its files unchanged: Reference.reads); None for ``path`` "". CalibrationError when it does not serve."""
    from hood_decomp.io.bases import loaded_bases_id
    from hood_decomp.io.calibration_files import file_key, read_reference

    if not path:
        return None
    key = (path, loaded_bases_id(bases), min_coverage)
    held = _REFERENCE.get(key)
    if held is None or not held.reads(file_key(path)):
        _REFERENCE.clear()
        _REFERENCE[key] = held = read_reference(path, bases, min_coverage)
    return held


def read_task_field(bases: Bases, task: PartTask, min_coverage: float) -> DisplacementField:
    """The displacement field of a task's part, by the path the scan node (clouds) or the CLI (files) takes."""
    if task.kind == "field":
        from hood_decomp.io.fields import read_field

        return read_field(task.path, bases.skin)[0]
    if task.kind == "scan":
        from hood_decomp.io.scans import field_from_scan_file

        return field_from_scan_file(bases.skin, task.path, min_coverage)
    if task.kind == "multiview":  # its views are not parts of their own, and their poses are in the bag's TF
        raise BagError(f"bag {task.path} holds part {task.part_id} in several views (sidecar expected_views): the "
                       "shift does not fuse views; inspect it through the nodes (hood-decomp replay BAG --bases B)")
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    from hood_decomp.core.scan.scan_field import field_from_scan, prepared_estimator
    from hood_decomp.ros import messages

    cloud = deserialize_message(task.data, PointCloud2)
    markers = {int(m[0]): np.array(m[1:], dtype=float) for m in task.markers_mm}
    points, measured, nominal = messages.scan_to_mm(cloud, "marker_id", markers)
    pose = None if task.scanner_pose_mm is None else np.asarray(task.scanner_pose_mm, float).reshape(4, 4)
    field, _ = field_from_scan(bases.skin, points, scanner_pose=pose, markers_mm=measured,
                               markers_nominal_mm=nominal, min_coverage=min_coverage,
                               estimator=prepared_estimator(bases.skin))
    return field


def inspect_field(bases: Bases, field: DisplacementField, options: Options
                  ) -> tuple[ParameterEstimate, ResidualAnalysis, Any, Any]:
    """Estimate, within-model test, correction and decomposition of one field (the nodes' path). The correction's
    safety follows the within-model test's verdict."""
    from hood_decomp.core.method.residual import noise_level

    estimate = estimate_field(bases, field, options.method, options.min_coverage)
    analysis = analyse_estimate(bases, estimate, noise_level(field.noise_rms)[0], options.alpha)
    estimate = dataclasses.replace(estimate, within_model=analysis.within_model)
    correction = plan_correction(estimate, options.policy)
    decomposition = decompose_field(bases, field, estimate)
    return estimate, analysis, correction, decomposition


def process_task(task: PartTask, bases_path: str, options: Options) -> PartRecord:
    """Process one part; a failure of the part (bad file, bad cloud, too little coverage, ...) becomes a "failed"
    record naming the error. Runs in a Dask worker."""
    from hood_decomp.io.bases import calibration_id

    base = PartRecord(source=task.source, part_id=task.part_id, message=task.message, stamp_ns=task.stamp_ns,
                      shift=options.shift, method=options.method)
    try:
        bases, identity = worker_bases(bases_path)
        base = dataclasses.replace(base, model_id=bases.model_id, bases_id=identity, calibration=calibration_id(bases))
        reference = worker_reference(options.reference, bases, options.min_coverage)
        field = read_task_field(bases, task, options.min_coverage)
        if reference is not None:
            field = reference.relative(field, bases)
            base = dataclasses.replace(base, reference=reference.label("cell"))
        estimate, analysis, correction, decomposition = inspect_field(bases, field, options)
    except Exception as error:  # a bad part is recorded, never fatal to the batch
        logger.warning("part %s of %s failed: %s", task.part_id, task.source, error)
        return dataclasses.replace(base, status="failed", error=f"{type(error).__name__}: {error}".splitlines()[0])
    return inspection_record(base, estimate, analysis, correction,
                             tuple((e.name, float(e.share)) for e in decomposition.effects), options.keep_residual)
