"""hood_decomp_msgs and sensor_msgs <-> core data. The only place where millimetres (core) become metres (ROS, REP 103).

Per-node arrays are copied once into the message's float32 array (``array.array('f')``), never element by element.
Besides the project messages: the scan cloud in (:func:`scan_to_mm`), the skin clouds out (:class:`SkinClouds`) and
the scan node's cell calibration parameters (:func:`calibration_from_params`, :func:`calibration_to_params`) and its
diagnostic key-values of a stated marker noise's check (:func:`marker_check_values`).
"""

from __future__ import annotations

import array
import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from hood_decomp.core.scan.registration import MarkerNoiseCheck
from hood_decomp.core.types import (
    BoundaryCorrection,
    Decomposition,
    DisplacementField,
    EffectContribution,
    FieldErrorModel,
    ModelCheck,
    MoveVerification,
    ParameterEstimate,
    SkinSurface,
    ViewPoseError,
    ZoneVerdict,
)
from hood_decomp.errors import FieldError
from hood_decomp.ros.pointcloud import cloud_channel, cloud_to_xyz, finite_rows, xyz_to_cloud

MM_PER_M = 1000.0
M_PER_MM = 1.0 / MM_PER_M


def _float32_array(values: np.ndarray, scale: float = 1.0) -> array.array:
    """(N,) values times ``scale`` as the ``array.array('f')`` rclpy keeps for float32[] fields (one copy)."""
    out = array.array("f", bytes(4 * len(values)))
    np.multiply(values, scale, out=np.frombuffer(out, dtype=np.float32), casting="unsafe")
    return out


def _numpy(values: Any, scale: float = 1.0) -> np.ndarray:
    """A message array (array.array, list or numpy) as float64 numpy times ``scale``."""
    return np.asarray(values, dtype=np.float64) * scale


def _flags(values: np.ndarray | None) -> list[bool]:
    """Per-parameter flags for a bool[] field; None (no parameter flagged by its source) is the empty list."""
    return [] if values is None else [bool(v) for v in values]


def _unflag(values: Any) -> np.ndarray | None:
    """A bool[] field back to (P,) bool, or None when empty (a sender without the field, or nothing flagged)."""
    return np.asarray(values, dtype=bool) if len(values) else None


def part_id_of(msg: Any) -> str:
    """The part id a message carries, or one made from its header stamp (``stamp-<sec>.<nanosec>``) when it has none
    (a scan cloud, an older sender, a bag recorded before part ids): every node that sees the same stamp makes the same
    id, so the outputs of one field still agree."""
    given = getattr(msg, "part_id", "")
    if given:
        return given
    stamp = msg.header.stamp
    return f"stamp-{stamp.sec}.{stamp.nanosec:09d}"


def field_to_msg(field: DisplacementField, header: Any, part_id: str) -> Any:
    """core DisplacementField (mm) -> hood_decomp_msgs/DisplacementField (m) of the part ``part_id``, with its error
    model; a fused field's per-view registration errors (``FieldErrorModel.view_poses``) travel as they are
    (``view_weight``, ``view_poses``), so the estimator node propagates them exactly as the fusing process would (V
    views of N nodes add 4 V N + 312 V bytes); a field's 3D displacement travels in ``displacement_3d`` (12 N bytes,
    empty without one)."""
    from hood_decomp_msgs.msg import DisplacementField as Msg

    errors = field.errors
    # the twist covariance [omega rad, t mm] in metres: the translation rows/columns scale by 1e-3
    unit = np.array([1.0, 1.0, 1.0, M_PER_MM, M_PER_MM, M_PER_MM])
    views = errors.view_poses
    return Msg(
        header=header,
        model_id=field.model_id,
        part_id=part_id,
        normal_displacement=_float32_array(field.normal_displacement, M_PER_MM),
        coverage=float(field.coverage),
        noise_rms=float(field.noise_rms) * M_PER_MM,
        error_model=errors.kind,
        node_std=_float32_array(np.asarray(errors.node_std, float), M_PER_MM),
        node_correlation=_float32_array(np.asarray(errors.correlation, float)),
        correlation_length=float(errors.correlation_length_mm) * M_PER_MM,
        pose_covariance=(np.asarray(errors.pose_covariance, float) * np.outer(unit, unit)).ravel().tolist(),
        pose_center=(np.asarray(errors.pose_center, float) * M_PER_MM).tolist(),
        bias_correlation=float(errors.bias_correlation),
        bias_variance_floor=float(errors.bias_variance_floor) * M_PER_MM**2,
        view_weight=_float32_array(np.concatenate([np.asarray(v.weight, float) for v in views]) if views
                                   else np.zeros(0)),
        view_poses=[float(c) for v in views for c in np.concatenate([
            (np.asarray(v.covariance, float) * np.outer(unit, unit)).ravel(), np.asarray(v.center, float) * M_PER_MM])],
        displacement_3d=_float32_array(np.zeros(0) if field.displacement is None
                                       else np.asarray(field.displacement, float).ravel(), M_PER_MM),
    )


def msg_to_field(msg: Any) -> DisplacementField:
    """hood_decomp_msgs/DisplacementField (m) -> core DisplacementField (mm), with its error model (an empty
    ``error_model`` string, from a sender that predates it, is "none"; empty view arrays, from one view or an older
    sender, leave the one pose of ``pose_covariance``; an empty ``displacement_3d`` is no 3D displacement). View
    arrays of inconsistent lengths and a ``displacement_3d`` of other than 3 N values are a FieldError here; the rest
    of the error model and the 3D displacement are checked where the field is used (a bad one is a FieldError naming
    the problem)."""
    unit = np.array([1.0, 1.0, 1.0, MM_PER_M, MM_PER_M, MM_PER_M])
    kind = msg.error_model or "none"
    errors = FieldErrorModel.none() if kind == "none" else FieldErrorModel(
        kind=kind,
        node_std=_numpy(msg.node_std, MM_PER_M),
        correlation=_numpy(msg.node_correlation),
        correlation_length_mm=float(msg.correlation_length) * MM_PER_M,
        pose_covariance=_numpy(msg.pose_covariance).reshape(6, 6) * np.outer(unit, unit),
        pose_center=_numpy(msg.pose_center, MM_PER_M),
        bias_correlation=float(msg.bias_correlation),
        bias_variance_floor=float(msg.bias_variance_floor) * MM_PER_M**2,
        view_poses=_view_poses(msg, len(msg.normal_displacement), unit),
    )
    n_nodes = len(msg.normal_displacement)
    vectors = msg.displacement_3d
    if len(vectors) not in (0, 3 * n_nodes):
        raise FieldError(f"displacement_3d must hold 3 N values (N = {n_nodes} nodes) or none; got {len(vectors)}")
    return DisplacementField(
        model_id=msg.model_id,
        normal_displacement=_numpy(msg.normal_displacement, MM_PER_M),
        coverage=float(msg.coverage),
        noise_rms=float(msg.noise_rms) * MM_PER_M,
        error_model=errors,
        displacement=_numpy(vectors, MM_PER_M).reshape(n_nodes, 3) if len(vectors) else None,
    )


def _view_poses(msg: Any, n_nodes: int, unit: np.ndarray) -> tuple[ViewPoseError, ...]:
    """The per-view registration errors of a fused field's message (mm), or () when it carries none (one view, an
    older sender: ``pose_covariance`` is the field's). Raises FieldError when the two arrays disagree on the number of
    views V (V x 39 and V x N values)."""
    poses, weight = msg.view_poses, msg.view_weight
    n_views = len(poses) // 39
    if (len(poses), len(weight)) != (39 * n_views, n_views * n_nodes):
        raise FieldError(f"view_poses and view_weight must hold V x 39 and V x N values (N = {n_nodes} nodes); got "
                         f"{len(poses)} and {len(weight)}")
    poses = _numpy(poses).reshape(n_views, 39)
    weights = _numpy(weight).reshape(n_views, n_nodes)
    return tuple(ViewPoseError(p[:36].reshape(6, 6) * np.outer(unit, unit), p[36:] * MM_PER_M, w)
                 for p, w in zip(poses, weights, strict=True))


def estimate_to_msg(estimate: ParameterEstimate, header: Any, part_id: str, reference: str = "") -> Any:
    """core ParameterEstimate (mm) -> hood_decomp_msgs/BoundaryState (m) of the part ``part_id``; ``reference``: the
    reference its field was made relative to ("cell:PATH", "part:PATH"; "" none)."""
    from hood_decomp_msgs.msg import BoundaryState

    return BoundaryState(
        header=header,
        model_id=estimate.model_id,
        part_id=part_id,
        names=list(estimate.names),
        values=(estimate.values * M_PER_MM).tolist(),
        std_dev=(estimate.std * M_PER_MM).tolist(),
        lower=(estimate.lower * M_PER_MM).tolist(),
        upper=(estimate.upper * M_PER_MM).tolist(),
        lifted=[bool(v) for v in estimate.lifted],
        residual_rms=float(estimate.residual_rms) * M_PER_MM,
        residual_max=float(estimate.residual_max) * M_PER_MM,
        coverage=float(estimate.coverage),
        within_model=bool(estimate.within_model),
        covariance=[] if estimate.covariance is None else (estimate.covariance * M_PER_MM**2).ravel().tolist(),
        p_value=float("nan") if estimate.check is None else estimate.check.p_value,
        alpha=float("nan") if estimate.check is None else estimate.check.alpha,
        noise_scale=float("nan") if estimate.check is None else estimate.check.noise_scale,
        noise_source="" if estimate.check is None else estimate.check.noise_source,
        measured_effect=_flags(estimate.measured_effect),
        reference=reference,
    )


def msg_to_estimate(msg: Any) -> ParameterEstimate:
    """hood_decomp_msgs/BoundaryState (m) -> core ParameterEstimate (mm).

    The message carries no per-node arrays, so ``reconstruction`` and ``residual`` are empty (shape (0,)), and the
    estimator is unknown (``method`` is "message"). The test's p-value, alpha and noise level come back in a
    :class:`ModelCheck` whose statistic and degrees of freedom are unknown (NaN, 0).
    """
    empty = np.empty(0)
    n = len(msg.names)
    covariance = _numpy(msg.covariance, MM_PER_M**2).reshape(n, n) if len(msg.covariance) == n * n else None
    check = None if not msg.noise_source else ModelCheck(
        float("nan"), 0, float("nan"), float(msg.p_value), float(msg.alpha), bool(msg.within_model),
        float(msg.noise_scale), msg.noise_source, float("nan"))
    return ParameterEstimate(
        model_id=msg.model_id,
        names=tuple(msg.names),
        values=_numpy(msg.values, MM_PER_M),
        std=_numpy(msg.std_dev, MM_PER_M),
        lower=_numpy(msg.lower, MM_PER_M),
        upper=_numpy(msg.upper, MM_PER_M),
        lifted=np.asarray(msg.lifted, dtype=bool),
        reconstruction=empty,
        residual=empty,
        residual_rms=float(msg.residual_rms) * MM_PER_M,
        residual_max=float(msg.residual_max) * MM_PER_M,
        coverage=float(msg.coverage),
        within_model=bool(msg.within_model),
        method="message",
        covariance=covariance,
        check=check,
        measured_effect=_unflag(msg.measured_effect),
    )


def correction_to_msg(correction: BoundaryCorrection, header: Any, part_id: str) -> Any:
    """core BoundaryCorrection (mm) -> hood_decomp_msgs/BoundaryCorrection (m) of the part ``part_id``."""
    from hood_decomp_msgs.msg import BoundaryCorrection as Msg

    return Msg(
        header=header,
        model_id=correction.model_id,
        part_id=part_id,
        names=list(correction.names),
        corrections=(correction.corrections * M_PER_MM).tolist(),
        safe_to_apply=bool(correction.safe_to_apply),
        reason=correction.reason,
        std_dev=[] if correction.std is None else (np.asarray(correction.std) * M_PER_MM).tolist(),
        # always one per boundary: an empty float64[] after a float64[] is padded differently by Fast CDR and rosbags
        remaining=(np.zeros(len(correction.names)) if correction.remaining is None
                   else np.asarray(correction.remaining, float) * M_PER_MM).tolist(),
        applicable=[] if correction.applicable is None else [bool(v) for v in correction.applicable],
        measured_effect=_flags(correction.measured_effect),
    )


def msg_to_correction(msg: Any) -> BoundaryCorrection:
    """hood_decomp_msgs/BoundaryCorrection (m) -> core BoundaryCorrection (mm)."""
    return BoundaryCorrection(
        model_id=msg.model_id,
        names=tuple(msg.names),
        corrections=_numpy(msg.corrections, MM_PER_M),
        safe_to_apply=bool(msg.safe_to_apply),
        reason=msg.reason,
        std=_numpy(msg.std_dev, MM_PER_M) if len(msg.std_dev) else None,
        applicable=np.asarray(msg.applicable, dtype=bool) if len(msg.applicable) else None,
        remaining=_numpy(msg.remaining, MM_PER_M) if len(msg.remaining) else None,
        measured_effect=_unflag(msg.measured_effect),
    )


def verification_to_msg(verification: MoveVerification, header: Any, part_id: str, corrected_stamp: Any) -> Any:
    """core MoveVerification (mm) -> hood_decomp_msgs/MoveVerification (m) of the part ``part_id``; the outcome codes
    are the message's constants."""
    from hood_decomp_msgs.msg import MoveVerification as Msg

    return Msg(
        header=header,
        model_id=verification.model_id,
        part_id=part_id,
        corrected_stamp=corrected_stamp,
        names=list(verification.names),
        predicted=(verification.predicted * M_PER_MM).tolist(),
        measured=(verification.measured * M_PER_MM).tolist(),
        std_dev=(verification.std * M_PER_MM).tolist(),
        fraction=np.asarray(verification.fraction, float).tolist(),
        outcome=[int(code) for code in verification.outcome],
        all_achieved=verification.all_achieved,
        summary=verification.summary,
    )


def zone_verdicts_to_msg(verdicts: Sequence[ZoneVerdict]) -> list[Any]:
    """core ZoneVerdicts (mm) -> hood_decomp_msgs/ZoneVerdict[] (m); a zone nobody saw has worst_node 0 and a NaN
    worst_deviation (the message's index is unsigned)."""
    from hood_decomp_msgs.msg import ZoneVerdict as Msg

    return [Msg(name=v.name, ok=v.ok, lower=v.lower_mm * M_PER_MM, upper=v.upper_mm * M_PER_MM,
                worst_deviation=v.worst_deviation_mm * M_PER_MM, worst_node=max(v.worst_node, 0),
                coverage=float(v.coverage)) for v in verdicts]


def decomposition_to_msg(decomposition: Decomposition, header: Any, part_id: str, reference: str = "") -> Any:
    """core Decomposition (mm) -> hood_decomp_msgs/EffectFields (m; contributions stay 0..1) of the part
    ``part_id``; ``reference`` as :func:`estimate_to_msg`'s."""
    from hood_decomp_msgs.msg import EffectField, EffectFields

    return EffectFields(
        header=header,
        model_id=decomposition.model_id,
        part_id=part_id,
        effects=[
            EffectField(
                name=effect.name,
                parameters=list(effect.parameters),
                contribution=_float32_array(effect.contribution),
                share=float(effect.share),
            )
            for effect in decomposition.effects
        ],
        reconstruction=_float32_array(decomposition.reconstruction, M_PER_MM),
        residual=_float32_array(decomposition.residual, M_PER_MM),
        reconstruction_rms=float(decomposition.reconstruction_rms) * M_PER_MM,
        reference=reference,
    )


def msg_to_decomposition(msg: Any) -> Decomposition:
    """hood_decomp_msgs/EffectFields (m) -> core Decomposition (mm).

    The message carries the contributions d_i / D but not the partial displacements d_i, so each effect's
    ``partial_displacement`` is empty (shape (0,)) rather than a guess.
    """
    return Decomposition(
        model_id=msg.model_id,
        effects=tuple(
            EffectContribution(
                name=effect.name,
                parameters=tuple(effect.parameters),
                partial_displacement=np.empty(0),
                contribution=_numpy(effect.contribution),
                share=float(effect.share),
            )
            for effect in msg.effects
        ),
        reconstruction=_numpy(msg.reconstruction, MM_PER_M),
        residual=_numpy(msg.residual, MM_PER_M),
        reconstruction_rms=float(msg.reconstruction_rms) * MM_PER_M,
    )


def scan_to_mm(cloud: Any, marker_field: str, markers_nominal_mm: Mapping[int, np.ndarray]
               ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A scan (sensor_msgs/PointCloud2, metres, scanner frame) as the core's inputs in mm.

    Returns the surface points (M, 3) mm, and the measured marker centres (K, 3) mm (scanner frame) with their nominal
    positions (K, 3) mm for the markers ``markers_nominal_mm`` (id -> (3,) mm, part frame) knows; both None when the
    cloud has no ``marker_field`` channel, reports no known marker, or no marker is configured. In ``marker_field`` a
    surface point has a negative id. Points without a return (NaN) are dropped in the same selection that takes the
    markers out; when no surface point is finite the surface rows are passed on whole, so the core names the all-NaN
    (or empty) scan.
    """
    points = cloud_to_xyz(cloud, scale=MM_PER_M, drop_nan=False)
    finite = finite_rows(points)
    finite = np.ones(len(points), dtype=bool) if finite is None else finite
    surface = np.ones(len(points), dtype=bool)
    markers = nominal = None
    if markers_nominal_mm and marker_field in {field.name for field in cloud.fields}:
        ids = cloud_channel(cloud, marker_field)
        surface = ids < 0
        known = np.isin(ids, np.fromiter(markers_nominal_mm, dtype=float)) & finite
        if known.any():
            markers = points[known]
            nominal = np.array([markers_nominal_mm[int(i)] for i in ids[known]])
    keep = surface & finite
    if not keep.any():
        keep = surface
    return (points if keep.all() else np.compress(keep, points, axis=0)), markers, nominal


def points_to_cloud(points_mm: np.ndarray, header: Any, channels: Mapping[str, np.ndarray] | None = None) -> Any:
    """Points (M, 3) mm as a sensor_msgs/PointCloud2 in metres (float32), with per-point ``channels`` (M,) unscaled."""
    return xyz_to_cloud(points_mm, header, channels=channels, scale=M_PER_MM)


def channel_name(effect_name: str) -> str:
    """A PointCloud2 field name for an effect: 'LOCK_L & LOCK_R' -> 'LOCK_L__LOCK_R'."""
    return re.sub(r"\W+", "_", effect_name.replace(" & ", "__"))


class SkinClouds:
    """Per-node results over the skin as sensor_msgs/PointCloud2 (metres, for RViz).

    The skin's node positions (N, 3) mm are converted to float32 metres once; each cloud only adds its channels.
    """

    def __init__(self, skin: SkinSurface) -> None:
        self._xyz_m = (np.asarray(skin.points, dtype=np.float64) * M_PER_MM).astype(np.float32)

    def displacement(self, field: DisplacementField, header: Any) -> Any:
        """The skin with a ``normal_displacement`` channel (N,) in metres (NaN where unseen)."""
        return xyz_to_cloud(self._xyz_m, header, channels={"normal_displacement": field.normal_displacement * M_PER_MM})

    def effects(self, decomposition: Decomposition, header: Any) -> Any:
        """The skin with one contribution channel (N,) per effect (0..1), named by :func:`channel_name`."""
        return xyz_to_cloud(self._xyz_m, header, channels={channel_name(effect.name): effect.contribution
                                                           for effect in decomposition.effects})


def calibration_from_params(pose: Sequence[float], markers: Sequence[float]
                            ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """The scan node's cell calibration parameters (metres) in mm.

    pose: 16 numbers, the row-major (4, 4) scanner-to-part transform with its translation in metres; markers: id, x,
    y, z (metres, part frame) per reference marker. Returns the (4, 4) transform with its translation in mm and
    marker id -> nominal centre (3,) mm.
    """
    scanner_pose = np.array(pose, dtype=float).reshape(4, 4)
    scanner_pose[:3, 3] *= MM_PER_M
    table = np.asarray(markers, dtype=float).reshape(-1, 4)
    return scanner_pose, {int(row[0]): row[1:] * MM_PER_M for row in table}


def calibration_to_params(pose_mm: np.ndarray, markers_mm: Mapping[int | str, Sequence[float]]
                          ) -> tuple[list[float], list[float]]:
    """The inverse of :func:`calibration_from_params`: the (4, 4) transform (translation mm) and marker id -> centre
    (3,) mm as the parameter values (16 numbers; id, x, y, z per marker; metres)."""
    pose = np.array(pose_mm, dtype=float).reshape(4, 4)
    pose[:3, 3] *= M_PER_MM
    markers = [value for marker_id, position in markers_mm.items()
               for value in (float(marker_id), *(np.asarray(position, dtype=float) * M_PER_MM))]
    return pose.ravel().tolist(), markers


def marker_check_values(pooled: MarkerNoiseCheck | None, own: MarkerNoiseCheck | None) -> dict[str, str]:
    """The scan node's diagnostic key-values of a stated marker noise's check
    (:func:`hood_decomp.core.scan.registration.check_marker_noise`), the pooled one over the scanner's recent clouds
    when it rejected the statement, else the cloud's own: stated, estimated and used noise (mm), the chi-square with
    its dof and p-value, and ``warning`` (the reason) when it was rejected, which makes the diagnostic a WARN
    (:func:`hood_decomp.ros.node_common.guarded`). Empty without a check."""
    check = pooled if pooled is not None and not pooled.accepted else own
    if check is None:
        return {}
    values = {"marker_std_stated_mm": f"{check.stated_mm:.4g}", "marker_std_estimated_mm": f"{check.estimated_mm:.4g}",
              "marker_std_used_mm": f"{check.used_mm:.4g}", "marker_chi2": f"{check.chi2:.2f} ({check.dof} dof)",
              "marker_p_value": f"{check.p_value:.2g}", "marker_clouds": str(check.clouds)}
    return {**values, "warning": check.reason} if check.reason else values
