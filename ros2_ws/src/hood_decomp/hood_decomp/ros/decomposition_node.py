"""Decomposition node: hood_decomp/displacement (+ hood_decomp/boundary_state) -> hood_decomp/effects and
hood_decomp/effects_cloud (PointCloud2 of the skin with one contribution channel per effect, for RViz).

Each field is paired with the boundary state of the same stamp (the estimator copies the field's header), so the
hierarchical subset is chosen from the estimate (paper step 3). A field whose state does not come within
``pair_timeout_s`` is decomposed from every effect instead, and the diagnostic says so: no accepted field is lost.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from typing import Any, NamedTuple

from hood_decomp_msgs.msg import BoundaryState, DisplacementField, EffectFields
from sensor_msgs.msg import PointCloud2

from hood_decomp.ros import messages
from hood_decomp.ros.node_common import HoodNode, declare, spin

MAX_UNPAIRED_STATES = 100  # states are small; one whose field never comes is dropped after this many newer ones


class _Pair(NamedTuple):
    header: Any
    field: DisplacementField
    state: BoundaryState | None


def _key(header: Any) -> tuple[int, int]:
    return header.stamp.sec, header.stamp.nanosec


class DecompositionNode(HoodNode):
    def __init__(self) -> None:
        super().__init__("hood_decomp_decomposition")
        self.use_state = declare(self, "use_boundary_state", True, "choose the hierarchical subset from the "
                                 "estimator's boundary state of the same stamp (paper step 3)")
        self.pair_timeout = declare(self, "pair_timeout_s", 2.0, "wait this long (s) for the boundary state of a "
                                    "field, then decompose from every effect", 0.0, 60.0)
        self.min_coverage = declare(self, "min_coverage", 0.2, "smallest seen fraction of the skin", 0.0, 1.0)
        self.fields: OrderedDict[tuple[int, int], tuple[DisplacementField, float]] = OrderedDict()
        self.states: OrderedDict[tuple[int, int], BoundaryState] = OrderedDict()
        self.skin_clouds = messages.SkinClouds(self.bases.skin) if self.bases is not None else None  # xyz once
        self.process = self.guarded("decomposition", self.decompose)
        self.effects_pub = self.publisher(EffectFields, "hood_decomp/effects")
        self.cloud_pub = self.publisher(PointCloud2, "hood_decomp/effects_cloud")
        self.subscription(DisplacementField, "hood_decomp/displacement", self.on_field)
        self.subscription(BoundaryState, "hood_decomp/boundary_state", self.on_state)
        self.create_timer(0.1, self.flush_unpaired)

    def on_field(self, msg: DisplacementField) -> None:
        key = _key(msg.header)
        if not self.use_state or key in self.states:
            self.process(_Pair(msg.header, msg, self.states.pop(key, None)))
            return
        if key in self.fields:  # a second field with the same stamp: the first is not lost, it goes unpaired
            earlier = self.fields.pop(key)[0]
            self.process(_Pair(earlier.header, earlier, None))
        self.fields[key] = (msg, time.monotonic())

    def on_state(self, msg: BoundaryState) -> None:
        key = _key(msg.header)
        if key in self.fields:
            self.process(_Pair(msg.header, self.fields.pop(key)[0], msg))
        elif self.use_state:
            self.states[key] = msg
            while len(self.states) > MAX_UNPAIRED_STATES:
                self.states.popitem(last=False)

    def flush_unpaired(self) -> None:
        """Fields whose state did not come in time are decomposed without one (oldest first)."""
        deadline = time.monotonic() - self.pair_timeout
        while self.fields and next(iter(self.fields.values()))[1] <= deadline:
            _, (field, _) = self.fields.popitem(last=False)
            self.process(_Pair(field.header, field, None))

    def decompose(self, pair: _Pair) -> dict[str, object]:
        from hood_decomp.core.method.bases import decompose_field

        bases = self.require_bases()
        estimate = messages.msg_to_estimate(pair.state) if pair.state is not None else None
        decomposition = decompose_field(bases, messages.msg_to_field(pair.field), estimate,
                                        min_coverage=self.min_coverage)
        part_id = messages.part_id_of(pair.field)
        self.effects_pub.publish(messages.decomposition_to_msg(decomposition, pair.header, part_id))
        self.cloud_pub.publish(self.skin_clouds.effects(decomposition, pair.header))
        return {"part_id": part_id, "effects": ", ".join(effect.name for effect in decomposition.effects),
                "paired_with_boundary_state": pair.state is not None,
                "reconstruction_rms_mm": f"{decomposition.reconstruction_rms:.4f}"}


def main(args: list[str] | None = None) -> int:
    return spin(DecompositionNode, args)
