"""The project messages: built, importable from the sourced environment, serialisable by rclpy and decodable by an
independent CDR implementation (rosbags), and converted to and from the core dataclasses with mm <-> m."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from tests.required import require_import

require_import("hood_decomp_msgs.msg", "colcon build", "run inside scripts/with-env after scripts/setup.sh")
from hood_decomp_msgs import msg as hd_msg
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from std_msgs.msg import Header

from hood_decomp.core.types import (
    BoundaryCorrection,
    Decomposition,
    DisplacementField,
    EffectContribution,
    ParameterEstimate,
)
from hood_decomp.ros import messages

MSG_DIR = pathlib.Path(__file__).parents[2] / "ros2_ws/src/hood_decomp_msgs/msg"
NAMES = ["DisplacementField", "BoundaryState", "BoundaryCorrection", "EffectField", "EffectFields"]


@pytest.fixture(scope="module")
def typestore():
    store = get_typestore(Stores.ROS2_KILTED)
    types = {}
    for name in NAMES:
        types.update(get_types_from_msg((MSG_DIR / f"{name}.msg").read_text(), f"hood_decomp_msgs/msg/{name}"))
    store.register(types)
    return store


def rosbags_decode(typestore, message) -> object:
    """Serialise with rclpy (Fast CDR) and decode with rosbags' own CDR reader."""
    name = f"hood_decomp_msgs/msg/{type(message).__name__}"
    return typestore.deserialize_cdr(bytes(serialize_message(message)), name)


def test_every_message_is_generated():
    for name in NAMES:
        cls = getattr(hd_msg, name)
        assert deserialize_message(serialize_message(cls()), cls) == cls()


def test_displacement_field_mm_to_m(typestore):
    values = np.array([1.5, -0.25, np.nan, 0.0])
    field = DisplacementField(model_id="abc123", normal_displacement=values, coverage=0.75, noise_rms=0.02)
    msg = messages.field_to_msg(field, Header(frame_id="part"))
    decoded = rosbags_decode(typestore, msg)
    np.testing.assert_allclose(decoded.normal_displacement, [0.0015, -0.00025, np.nan, 0.0], rtol=1e-7)
    assert decoded.model_id == "abc123" and decoded.header.frame_id == "part"
    assert decoded.noise_rms == pytest.approx(2e-5)
    back = messages.msg_to_field(msg)
    np.testing.assert_allclose(back.normal_displacement, values, rtol=1e-7, atol=1e-9)
    assert back.coverage == 0.75 and back.noise_rms == pytest.approx(0.02)


def _estimate() -> ParameterEstimate:
    return ParameterEstimate(
        model_id="m1", names=("HINGE_X", "BUFFER_L"), values=np.array([0.5, -0.2]), std=np.array([0.001, 0.002]),
        lower=np.array([-1.0, -1.0]), upper=np.array([1.0, 1.0]), lifted=np.array([False, True]),
        reconstruction=np.zeros(3), residual=np.zeros(3), residual_rms=0.01, residual_max=0.05, coverage=0.9,
        within_model=True, method="contact",
    )


def test_boundary_state_mm_to_m(typestore):
    msg = messages.estimate_to_msg(_estimate(), Header())
    decoded = rosbags_decode(typestore, msg)
    np.testing.assert_allclose(decoded.values, [0.0005, -0.0002])
    np.testing.assert_allclose(decoded.std_dev, [1e-6, 2e-6])
    assert list(decoded.lifted) == [False, True] and decoded.residual_max == pytest.approx(5e-5)
    back = messages.msg_to_estimate(msg)
    np.testing.assert_allclose(back.values, [0.5, -0.2])
    np.testing.assert_allclose(back.upper, [1.0, 1.0])
    assert back.names == ("HINGE_X", "BUFFER_L") and back.reconstruction.shape == (0,)


def test_boundary_correction_mm_to_m(typestore):
    correction = BoundaryCorrection(model_id="m1", names=("LOCK_L",), corrections=np.array([-0.8]),
                                    safe_to_apply=False, reason="coverage 0.30 below 0.60")
    decoded = rosbags_decode(typestore, messages.correction_to_msg(correction, Header()))
    assert list(decoded.corrections) == pytest.approx([-0.0008]) and decoded.reason == "coverage 0.30 below 0.60"
    back = messages.msg_to_correction(messages.correction_to_msg(correction, Header()))
    assert back.corrections == pytest.approx([-0.8]) and not back.safe_to_apply


def test_effect_fields_mm_to_m(typestore):
    effects = (
        EffectContribution("LOCK_L", ("LOCK_L",), np.array([1.0, 0.0]), np.array([1.0, 0.0]), 0.6),
        EffectContribution("LOCK_L & LOCK_R", ("LOCK_L", "LOCK_R"), np.array([0.0, 2.0]), np.array([0.0, 1.0]), 0.4),
    )
    decomposition = Decomposition("m1", effects, np.array([1.0, 2.0]), np.array([0.001, np.nan]), 0.0007)
    msg = messages.decomposition_to_msg(decomposition, Header())
    decoded = rosbags_decode(typestore, msg)
    assert [e.name for e in decoded.effects] == ["LOCK_L", "LOCK_L & LOCK_R"]
    assert list(decoded.effects[1].parameters) == ["LOCK_L", "LOCK_R"]
    np.testing.assert_allclose(decoded.reconstruction, [0.001, 0.002], rtol=1e-7)
    back = messages.msg_to_decomposition(msg)
    np.testing.assert_allclose(back.effects[1].contribution, [0.0, 1.0])
    np.testing.assert_allclose(back.residual, [0.001, np.nan], rtol=1e-6)
    assert back.reconstruction_rms == pytest.approx(0.0007)
