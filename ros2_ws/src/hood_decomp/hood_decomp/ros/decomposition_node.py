"""Decomposition node: hood_decomp/displacement (+ hood_decomp/boundary_state) -> hood_decomp/effects and
hood_decomp/effects_cloud (PointCloud2 of the skin with one contribution channel per effect, for RViz).

Each field is paired with the boundary state of the same stamp and part id (the estimator copies the field's header
and part id), so the hierarchical subset is chosen from the estimate (paper step 3); a state of another model is
refused by name. A field whose state does not come within ``pair_timeout_s`` is decomposed from every effect instead,
and the diagnostic says so: no accepted field is lost. The effects are published transient-local (the latest result).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from typing import Any, NamedTuple

from hood_decomp_msgs.msg import BoundaryState, DisplacementField, EffectFields
from sensor_msgs.msg import PointCloud2

from hood_decomp.errors import HoodDecompError
from hood_decomp.ros import messages
from hood_decomp.ros.node_common import ReferencedNode, declare, spin

MAX_UNPAIRED_STATES = 100  # states are small; one whose field never comes is dropped after this many newer ones


class _Pair(NamedTuple):
    header: Any
    field: DisplacementField
    state: BoundaryState | None


_Key = tuple[int, int, str]


def _key(msg: Any) -> _Key:
    """A field and its boundary state pair by stamp and part id."""
    return msg.header.stamp.sec, msg.header.stamp.nanosec, messages.part_id_of(msg)


class DecompositionNode(ReferencedNode):
    def __init__(self) -> None:
        super().__init__("hood_decomp_decomposition")
        declare(self, "use_boundary_state", True, "choose the hierarchical subset from the estimator's boundary state "
                "of the same stamp (paper step 3)")
        declare(self, "pair_timeout_s", 2.0, "wait this long (s) for the boundary state of a field, then decompose "
                "from every effect", 0.0, 60.0)
        declare(self, "min_coverage", 0.2, "smallest seen fraction of the skin", 0.0, 1.0)
        self.fields: OrderedDict[_Key, tuple[DisplacementField, float]] = OrderedDict()
        self.states: OrderedDict[_Key, BoundaryState] = OrderedDict()
        self.skin_clouds: dict[str, messages.SkinClouds] = {}  # model_id -> the skin of that variant
        self.effects_pub = self.cloud_pub = None
        self.process = self.guarded("decomposition", self.decompose)
        self.refuse_state = self.guarded("boundary state", self.other_model)

    def configure_node(self) -> None:
        super().configure_node()  # the references, read with the new bases
        self.skin_clouds = {bases.model_id: messages.SkinClouds(bases.skin)  # each variant's skin xyz once
                            for bases in self.variant_bases.values()}
        self.effects_pub = self.publisher(EffectFields, "hood_decomp/effects", latest=True)
        self.cloud_pub = self.publisher(PointCloud2, "hood_decomp/effects_cloud")

    def activate_node(self) -> None:
        self.subscription(DisplacementField, "hood_decomp/displacement", self.on_field)
        self.subscription(BoundaryState, "hood_decomp/boundary_state", self.on_state)
        self.timer(0.1, self.flush_unpaired)

    def on_field(self, msg: DisplacementField) -> None:
        key = _key(msg)
        if not self.param("use_boundary_state") or key in self.states:
            self.process(_Pair(msg.header, msg, self.states.pop(key, None)))
            return
        if key in self.fields:  # a second field with the same stamp: the first is not lost, it goes unpaired
            earlier = self.fields.pop(key)[0]
            self.process(_Pair(earlier.header, earlier, None))
        self.fields[key] = (msg, time.monotonic())

    def other_model(self, msg: BoundaryState) -> None:
        """A state of a model this node does not serve is refused by name (ERROR diagnostic), never paired."""
        served = ", ".join(repr(model_id) for model_id in self.skin_clouds)
        raise HoodDecompError(f"boundary state of model_id {msg.model_id!r}, but the bases are of model_id "
                              f"{served}: not used for the field of its stamp")

    def on_state(self, msg: BoundaryState) -> None:
        if msg.model_id not in self.skin_clouds:
            self.refuse_state(msg)
            return
        key = _key(msg)
        if key in self.fields:
            self.process(_Pair(msg.header, self.fields.pop(key)[0], msg))
        elif self.param("use_boundary_state"):
            self.states[key] = msg
            while len(self.states) > MAX_UNPAIRED_STATES:
                self.states.popitem(last=False)

    def flush_unpaired(self) -> None:
        """Fields whose state did not come in time are decomposed without one (oldest first)."""
        deadline = time.monotonic() - self.param("pair_timeout_s")
        while self.fields and next(iter(self.fields.values()))[1] <= deadline:
            _, (field, _) = self.fields.popitem(last=False)
            self.process(_Pair(field.header, field, None))

    def decompose(self, pair: _Pair) -> dict[str, object]:
        from hood_decomp.core.method.bases import decompose_field

        bases, field, reference = self.field_of(pair.field)
        if pair.state is not None and pair.state.model_id != bases.model_id:
            raise HoodDecompError(f"field of model_id {bases.model_id!r} paired with a boundary state of model_id "
                                  f"{pair.state.model_id!r}")
        estimate = messages.msg_to_estimate(pair.state) if pair.state is not None else None
        decomposition = decompose_field(bases, field, estimate, min_coverage=self.param("min_coverage"))
        part_id = messages.part_id_of(pair.field)
        self.effects_pub.publish(messages.decomposition_to_msg(decomposition, pair.header, part_id, reference))
        self.cloud_pub.publish(self.skin_clouds[bases.model_id].effects(decomposition, pair.header))
        # the estimator and this node each hold the references: a part given its own on one of them only is named
        differs = pair.state is not None and pair.state.reference != reference
        return {"part_id": part_id, "reference": reference or "none",
                "warning": f"the boundary state's field was relative to {pair.state.reference or 'no reference'}, "
                f"this one to {reference or 'none'}: give the part's reference to both nodes" if differs else "",
                "effects": ", ".join(effect.name for effect in decomposition.effects),
                "paired_with_boundary_state": pair.state is not None,
                "reconstruction_rms_mm": f"{decomposition.reconstruction_rms:.4f}"}


def main(args: list[str] | None = None) -> int:
    return spin(DecompositionNode, args)
