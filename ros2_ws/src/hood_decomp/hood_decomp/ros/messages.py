"""hood_decomp_msgs <-> core dataclasses. The only place where millimetres (core) become metres (ROS, REP 103).

Per-node arrays are copied once into the message's float32 array (``array.array('f')``), never element by element.
"""

from __future__ import annotations

import array
from typing import Any

import numpy as np

from hood_decomp.core.types import (
    BoundaryCorrection,
    Decomposition,
    DisplacementField,
    EffectContribution,
    ParameterEstimate,
)

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


def field_to_msg(field: DisplacementField, header: Any) -> Any:
    """core DisplacementField (mm) -> hood_decomp_msgs/DisplacementField (m)."""
    from hood_decomp_msgs.msg import DisplacementField as Msg

    return Msg(
        header=header,
        model_id=field.model_id,
        normal_displacement=_float32_array(field.normal_displacement, M_PER_MM),
        coverage=float(field.coverage),
        noise_rms=float(field.noise_rms) * M_PER_MM,
    )


def msg_to_field(msg: Any) -> DisplacementField:
    """hood_decomp_msgs/DisplacementField (m) -> core DisplacementField (mm)."""
    return DisplacementField(
        model_id=msg.model_id,
        normal_displacement=_numpy(msg.normal_displacement, MM_PER_M),
        coverage=float(msg.coverage),
        noise_rms=float(msg.noise_rms) * MM_PER_M,
    )


def estimate_to_msg(estimate: ParameterEstimate, header: Any) -> Any:
    """core ParameterEstimate (mm) -> hood_decomp_msgs/BoundaryState (m)."""
    from hood_decomp_msgs.msg import BoundaryState

    return BoundaryState(
        header=header,
        model_id=estimate.model_id,
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
    )


def msg_to_estimate(msg: Any) -> ParameterEstimate:
    """hood_decomp_msgs/BoundaryState (m) -> core ParameterEstimate (mm).

    The message carries no per-node arrays, so ``reconstruction`` and ``residual`` are empty (shape (0,)), and the
    estimator is unknown (``method`` is "message").
    """
    empty = np.empty(0)
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
    )


def correction_to_msg(correction: BoundaryCorrection, header: Any) -> Any:
    """core BoundaryCorrection (mm) -> hood_decomp_msgs/BoundaryCorrection (m)."""
    from hood_decomp_msgs.msg import BoundaryCorrection as Msg

    return Msg(
        header=header,
        model_id=correction.model_id,
        names=list(correction.names),
        corrections=(correction.corrections * M_PER_MM).tolist(),
        safe_to_apply=bool(correction.safe_to_apply),
        reason=correction.reason,
    )


def msg_to_correction(msg: Any) -> BoundaryCorrection:
    """hood_decomp_msgs/BoundaryCorrection (m) -> core BoundaryCorrection (mm)."""
    return BoundaryCorrection(
        model_id=msg.model_id,
        names=tuple(msg.names),
        corrections=_numpy(msg.corrections, MM_PER_M),
        safe_to_apply=bool(msg.safe_to_apply),
        reason=msg.reason,
    )


def decomposition_to_msg(decomposition: Decomposition, header: Any) -> Any:
    """core Decomposition (mm) -> hood_decomp_msgs/EffectFields (m; contributions stay 0..1)."""
    from hood_decomp_msgs.msg import EffectField, EffectFields

    return EffectFields(
        header=header,
        model_id=decomposition.model_id,
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
