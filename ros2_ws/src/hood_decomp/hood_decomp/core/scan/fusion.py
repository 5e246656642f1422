"""Several views of one part fused into one displacement field (DESIGN.md "Robotic cell", issue 17).

A robot takes several partial views of one part, each from its own pose (part <- scanner, from the robot, TF, a pose
topic or a file). Each view is registered on its own (its fixture markers, three or more, refine the pose: the
marker fit replaces it, and the difference is reported) and turned into a field by the one scan-to-field step
(:func:`hood_decomp.core.scan.scan_field.field_from_scan`). The fused field is, per skin node i,

    a_i = sum_v w_v(i) a_v(i),   w_v(i) = e_v(i)^-2 / sum_u e_u(i)^-2   (views that saw node i)

the inverse-variance weighted mean of the views' values, e_v(i)^2 = s_v(i)^2 + |U_v(i)|^2 the view's node variance
from its error model: node noise s_v plus what its registration error does at the node (a view with a poor pose
counts less where its pose error reaches far). Its error model follows from the views' being independent (their
point noise and their registrations are):

- node std s_i = (sum_v w_v(i)^2 s_v(i)^2)^1/2 (noise only: the registration part is in U below);
- correlation sum g_i = sum_v w_v(i)^2 s_v(i)^2 g_v(i) / s_i^2 (with the weights and stds locally constant over a
  correlation length, sum_k Cov_ik / (s_i s_k) over the views' independent noise);
- one registration error per view, reaching the nodes through the view's weight: U = [w_1 U_1, ..., w_V U_V] (N, 6V)
  (:class:`hood_decomp.core.types.ViewPoseError`), correlated over all nodes of one view and independent between
  views; the DisplacementField message carries them as they are. A single-pose summary (the sum of the views' pose
  covariances about a common centre, never smaller on any node) goes where only one pose fits (field files).

A node no view saw stays NaN; so the fused coverage is the union of the views' coverages.
Units: mm, rad; transforms (4, 4) map scanner points to the part frame, x_part = R x_scan + t.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hood_decomp.core.scan.registration import RegistrationResult
from hood_decomp.core.scan.scan_field import ScanFieldEstimator, field_from_scan
from hood_decomp.core.types import DisplacementField, FieldErrorModel, SkinSurface, ViewPoseError
from hood_decomp.errors import ScanError

logger = logging.getLogger(__name__)

#: largest deviation of a rotation block from orthonormal (max |R^T R - I|) a pose may carry: a 4x4 written with
#: six decimals is orthonormal to ~1e-6; beyond this the matrix scales or shears the scan
ROTATION_TOLERANCE = 1e-4
#: a marker fit that moves a view further than this from its given pose means a wrong pose or mismatched markers
MAX_POSE_CORRECTION_MM = 50.0
MAX_POSE_CORRECTION_DEG = 5.0


def check_pose(pose: object, what: str = "scanner pose") -> np.ndarray:
    """A rigid (4, 4) transform (part <- scanner, mm) from ``pose`` (a 4x4 or 16 numbers, row-major), checked.

    Raises ScanError naming ``what`` and the problem: not 16 numbers, not finite, a rotation block that is not
    orthonormal within :data:`ROTATION_TOLERANCE` or that mirrors (det < 0), a last row other than [0, 0, 0, 1].
    """
    try:
        matrix = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ScanError(f"{what} must be 16 numbers (a 4 x 4 row-major transform): {error}") from None
    if matrix.size != 16 or matrix.ndim not in (1, 2) or (matrix.ndim == 2 and matrix.shape != (4, 4)):
        raise ScanError(f"{what} must be a 4 x 4 transform (16 numbers, row-major); got shape {matrix.shape}")
    matrix = matrix.reshape(4, 4)
    if not np.all(np.isfinite(matrix)):
        raise ScanError(f"{what} has non-finite entries (NaN or inf)")
    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
        raise ScanError(f"{what}: the last row must be [0, 0, 0, 1]; got {matrix[3].tolist()}")
    rotation = matrix[:3, :3]
    off = float(np.max(np.abs(rotation.T @ rotation - np.eye(3))))
    if off > ROTATION_TOLERANCE:
        raise ScanError(f"{what}: the rotation block is not orthonormal (max |R^T R - I| = {off:.3g}, tolerance "
                        f"{ROTATION_TOLERANCE:g}); a rigid transform in mm was expected")
    if np.linalg.det(rotation) < 0:
        raise ScanError(f"{what}: the rotation block mirrors (determinant < 0); a proper rotation was expected")
    return matrix


def pose_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """How far apart two rigid transforms (4, 4) are: translation (mm) and rotation angle (deg) of a b^-1."""
    delta = a @ np.linalg.inv(b)
    cos = np.clip((np.trace(delta[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(delta[:3, 3])), float(np.degrees(np.arccos(cos)))


@dataclass(frozen=True)
class ScanView:
    """One view of a part: a raw cloud and where it was taken from.

    points_mm: (M, 3) scanner frame. scanner_pose: (4, 4) part <- scanner, mm (None: the points are in the part frame
    already, or the markers register them). markers_mm / markers_nominal_mm: (K, 3) measured (scanner frame) and
    nominal (part frame) fixture markers, row by row; three or more register the view, replacing the pose.
    name: names the view in errors and reports. pose_source: where the pose came from ("file", "tf", "scan/pose",
    "parameter", ...; "none" without one). A pose states no error of its own: a view registered by its pose alone
    carries no registration error in its field's error model (markers give one).
    """

    points_mm: np.ndarray
    scanner_pose: np.ndarray | None = None
    markers_mm: np.ndarray | None = None
    markers_nominal_mm: np.ndarray | None = None
    name: str = "view"
    pose_source: str = "none"

    @property
    def n_markers(self) -> int:
        return 0 if self.markers_mm is None else int(np.asarray(self.markers_mm).reshape(-1, 3).shape[0])


@dataclass(frozen=True)
class ViewResult:
    """What one view gave: its field and registration, and how it agrees with its pose and with the other views.

    field: the view's own DisplacementField (N,) mm. registration: its RegistrationResult (method "markers" when three
    or more markers registered it, else "pose" or "identity"). pose_correction_mm / pose_correction_deg: how far the
    marker fit moved the view from its given pose (NaN without both). overlap_nodes: skin nodes this view shares with
    the others; overlap_rms_mm: RMS difference of its values there from the other views' fused values (NaN without
    overlap): views that disagree far beyond their stds point at a wrong pose.
    """

    name: str
    pose_source: str
    field: DisplacementField
    registration: RegistrationResult
    pose_correction_mm: float
    pose_correction_deg: float
    overlap_nodes: int = 0
    overlap_rms_mm: float = float("nan")


@dataclass(frozen=True)
class FusedField:
    """A part's fused field and the views behind it (in the order given)."""

    field: DisplacementField
    views: tuple[ViewResult, ...]


def view_field(
    skin: SkinSurface,
    view: ScanView,
    *,
    estimator: ScanFieldEstimator | None = None,
    min_coverage: float = 0.02,
    datum_mask: np.ndarray | None = None,
    marker_std_mm: float | None = None,
    check_correction: bool = True,
) -> ViewResult:
    """Register one view with its own pose (refined by its markers) and turn it into its field.

    min_coverage: smallest fraction of the skin one view must see (a partial view sees little of it).
    check_correction: refuse a view whose markers contradict its pose by more than :data:`MAX_POSE_CORRECTION_MM` /
    :data:`MAX_POSE_CORRECTION_DEG` (a lone scan's stored nominal pose is only a fallback, and is not checked).
    Raises ScanError prefixed with the view's name (bad pose, markers that do not fit or contradict the pose, no
    overlap, too little coverage).
    """
    pose = None if view.scanner_pose is None else check_pose(view.scanner_pose, f"{view.name}: scanner pose")
    use_markers = view.n_markers >= 3 and view.markers_nominal_mm is not None
    try:
        field, registration = field_from_scan(
            skin, view.points_mm, scanner_pose=pose,
            markers_mm=view.markers_mm if use_markers else None,
            markers_nominal_mm=view.markers_nominal_mm if use_markers else None,
            datum_mask=datum_mask, min_coverage=min_coverage, estimator=estimator, marker_std_mm=marker_std_mm)
    except ScanError as error:
        raise ScanError(f"{view.name}: {error}") from None
    shift_mm = angle_deg = float("nan")
    if use_markers and pose is not None:
        shift_mm, angle_deg = pose_difference(registration.transform, pose)
        if check_correction and (shift_mm > MAX_POSE_CORRECTION_MM or angle_deg > MAX_POSE_CORRECTION_DEG):
            raise ScanError(
                f"{view.name}: its markers place it {shift_mm:.1f} mm / {angle_deg:.2f} deg from its "
                f"{view.pose_source} pose (at most {MAX_POSE_CORRECTION_MM:g} mm / {MAX_POSE_CORRECTION_DEG:g} deg "
                "expected): a wrong pose or mismatched markers")
    logger.info("%s: registered by %s (%s pose), coverage %.1f%%", view.name, registration.method,
                view.pose_source, 100.0 * field.coverage)
    return ViewResult(view.name, view.pose_source, field, registration, shift_mm, angle_deg)


def _moved_covariance(covariance: np.ndarray, center: np.ndarray, to: np.ndarray) -> np.ndarray:
    """A twist covariance (6, 6) [omega, t] about ``center`` expressed about ``to``: the same motion of every point,
    omega x (x - c) + t = omega x (x - c') + t + omega x (c' - c)."""
    d = np.asarray(to, float) - np.asarray(center, float)
    adjoint = np.eye(6)
    adjoint[3:, :3] = -np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])  # t' = t - d x omega
    return adjoint @ covariance @ adjoint.T


def fuse_fields(fields: Sequence[DisplacementField], skin: SkinSurface | None = None) -> DisplacementField:
    """One field (N,) mm from several fields of the same part (see the module docstring for the weights and the
    error model). One field is returned as it is. With ``skin`` the weights take each view's registration error at
    the node into account (without it, the node noise alone). Fields without a scan's node std ("none" or "stated")
    are averaged with equal weights per node, and the fused field then states no error model.

    Raises ScanError for no fields or fields of different models or node counts.
    """
    if not fields:
        raise ScanError("nothing to fuse: no view gave a field")
    if len(fields) == 1:
        return fields[0]
    model_id, n = fields[0].model_id, fields[0].normal_displacement.shape[0]
    for k, other in enumerate(fields[1:], start=2):
        if other.model_id != model_id or other.normal_displacement.shape != (n,):
            raise ScanError(f"view {k} is of another model ({other.model_id}, {other.normal_displacement.shape[0]} "
                            f"nodes) than view 1 ({model_id}, {n} nodes)")
    values = np.array([np.asarray(f.normal_displacement, float) for f in fields])  # (V, N)
    seen = np.isfinite(values)
    scan_models = all(f.errors.kind == "scan" for f in fields)
    if scan_models:
        noise_var = np.array([np.asarray(f.errors.node_std, float) ** 2 for f in fields])
        seen &= np.isfinite(noise_var) & (noise_var > 0)
        noise_var = np.where(seen, noise_var, 1.0)
        pose_var = np.zeros_like(noise_var)
        if skin is not None:
            for v, f in enumerate(fields):
                if f.errors.has_pose:
                    pose_var[v] = np.sum(f.errors.registration_modes(skin.points, skin.normals) ** 2, axis=1)
        precision = np.where(seen, 1.0 / (noise_var + pose_var), 0.0)
    else:
        precision = seen.astype(float)
    total = precision.sum(axis=0)
    any_seen = total > 0
    weight = np.where(any_seen, precision / np.where(any_seen, total, 1.0), 0.0)  # (V, N)
    fused = np.where(any_seen, np.sum(weight * np.where(seen, values, 0.0), axis=0), np.nan)
    noise = np.array([f.noise_rms for f in fields], float)
    noise_rms = float(np.sqrt(np.mean(noise[np.isfinite(noise)] ** 2))) if np.isfinite(noise).any() else np.nan
    errors = FieldErrorModel.none()
    if scan_models:
        models = [f.errors for f in fields]
        correlation = np.array([np.asarray(m.correlation, float) for m in models])
        # independent view noise: Var = sum_v w_v^2 s_v^2; correlation sum g = sum_v w_v^2 s_v^2 g_v / Var
        variance = np.sum(weight**2 * noise_var, axis=0)
        node_std = np.where(any_seen, np.sqrt(variance), np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            fused_correlation = np.sum(weight**2 * noise_var * correlation, axis=0) / variance
        views = tuple(view for m, w in zip(models, weight, strict=True) for view in _view_poses(m, w))
        center = np.mean([v.center for v in views if v.has_pose] or [np.zeros(3)], axis=0)
        summary = sum((_moved_covariance(v.covariance, v.center, center) for v in views if v.has_pose),
                      np.zeros((6, 6)))
        errors = FieldErrorModel(
            "scan", node_std, np.where(any_seen, np.maximum(fused_correlation, 1.0), 1.0),
            max(m.correlation_length_mm for m in models), pose_covariance=summary, pose_center=center,
            bias_correlation=max(m.bias_correlation for m in models), view_poses=views,
            bias_variance_floor=max(m.bias_variance_floor for m in models))
        errors.validate(n)
    return DisplacementField(model_id, fused, float(any_seen.mean()), noise_rms, errors)


def _view_poses(errors: FieldErrorModel, weight: np.ndarray) -> tuple[ViewPoseError, ...]:
    """The registration errors of one fused-in field with its fusion weight (N,): its own pose, or the views of a
    field that was itself fused (their weights multiplied), so fusing in stages stays exact."""
    if errors.view_poses:
        return tuple(ViewPoseError(v.covariance, v.center, v.weight * weight) for v in errors.view_poses)
    return (ViewPoseError(np.asarray(errors.pose_covariance, float), np.asarray(errors.pose_center, float), weight),)


def fuse_views(
    skin: SkinSurface,
    views: Sequence[ScanView],
    *,
    estimator: ScanFieldEstimator | None = None,
    min_coverage: float = 0.2,
    min_view_coverage: float = 0.02,
    datum_mask: np.ndarray | None = None,
    marker_std_mm: float | None = None,
) -> FusedField:
    """Register and fuse the views of one part (module docstring).

    A lone view without a pose is taken in the part frame (or registered by its markers), as a single scan always
    was; with more than one view every view needs a pose, and one without is refused by name (ScanError), markers or
    not: the robot program placed it, and a view the cell cannot place is not part of this inspection.
    min_coverage: smallest fused coverage; min_view_coverage: smallest coverage of one view.
    """
    if not views:
        raise ScanError("an inspection needs at least one view")
    names = [view.name for view in views]
    if len(set(names)) != len(names):
        raise ScanError(f"view names must be unique; got {names}")
    if len(views) > 1:
        missing = [view.name for view in views if view.scanner_pose is None]
        if missing:
            raise ScanError(f"{', '.join(missing)}: no scanner pose; every view of a multi-view part needs one "
                            "(robot, TF, pose topic or file)")
    results = [view_field(skin, view, estimator=estimator, min_coverage=min_view_coverage, datum_mask=datum_mask,
                          marker_std_mm=marker_std_mm, check_correction=len(views) > 1) for view in views]
    fused = fuse_fields([r.field for r in results], skin)
    if fused.coverage < min_coverage:
        raise ScanError(f"fused coverage too low: {fused.coverage:.1%} of {skin.n_nodes} skin nodes seen by "
                        f"{len(views)} view(s) (minimum {min_coverage:.0%})")
    if len(results) > 1:
        results = [_with_overlap(r, [o.field for o in results if o is not r], skin) for r in results]
    return FusedField(fused, tuple(results))


def _with_overlap(result: ViewResult, others: list[DisplacementField], skin: SkinSurface) -> ViewResult:
    """``result`` with its overlap with the other views' fused field (nodes shared, RMS difference)."""
    rest = fuse_fields(others, skin)
    own = result.field.normal_displacement
    shared = np.isfinite(own) & np.isfinite(rest.normal_displacement)
    rms = float(np.sqrt(np.mean((own[shared] - rest.normal_displacement[shared]) ** 2))) if shared.any() else np.nan
    return dataclasses.replace(result, overlap_nodes=int(shared.sum()), overlap_rms_mm=rms)
