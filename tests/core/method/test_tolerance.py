"""Tolerance zones on a displacement field (core.method.tolerance), against verdicts worked out here by hand on a
planted field: which nodes a box and a sphere select, which node is worst, what is seen."""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.core.method.tolerance import zone_nodes, zone_verdicts
from hood_decomp.core.types import DisplacementField, ToleranceZone
from hood_decomp.errors import FieldError

#: a 21 x 11 grid, 10 mm apart, in the z = 5 plane: node i*11 + j sits at (10 i, 10 j, 5)
POINTS = np.array([(10.0 * i, 10.0 * j, 5.0) for i in range(21) for j in range(11)])


def _node(i: int, j: int) -> int:
    return i * 11 + j


def _zone(nodes: list[int], lower: float = -0.3, upper: float = 0.3, min_coverage: float = 0.5) -> ToleranceZone:
    return ToleranceZone("edge", np.array(sorted(nodes), dtype=np.int64), lower, upper, min_coverage, "{}")


def _field(values: np.ndarray) -> DisplacementField:
    return DisplacementField("toy", values, float(np.isfinite(values).mean()), 0.01)


def test_box_and_sphere_select_the_nodes_inside_both():
    """Fails if the box is not inclusive of its bounds, if the sphere is not, or if box and sphere together are not
    their intersection (the grid nodes listed here by their coordinates)."""
    box = ((20.0, 0.0, 0.0), (50.0, 30.0, 10.0))  # i 2..5, j 0..3
    assert zone_nodes(POINTS, box=box).tolist() == sorted(_node(i, j) for i in range(2, 6) for j in range(4))
    sphere = ((100.0, 50.0, 5.0), 10.0)  # the centre node and its four neighbours at exactly 10 mm
    assert zone_nodes(POINTS, sphere=sphere).tolist() == sorted(
        [_node(10, 5), _node(9, 5), _node(11, 5), _node(10, 4), _node(10, 6)])
    both = zone_nodes(POINTS, box=((100.0, 0.0, 0.0), (200.0, 100.0, 10.0)), sphere=sphere)
    assert both.tolist() == sorted([_node(10, 5), _node(11, 5), _node(10, 4), _node(10, 6)])
    with pytest.raises(ValueError, match="box or a sphere"):
        zone_nodes(POINTS)


def test_worst_node_is_the_seen_one_farthest_outside():
    """Fails if an unseen node (NaN) counts, if the worst node is not the seen one farthest outside the limits (a
    value below the lower limit by more beats one above the upper by less), if its value, index, the count outside
    or the coverage are wrong, or if the verdict is OK."""
    nodes = [_node(i, j) for i in range(4) for j in range(5)]  # 20 nodes
    values = np.zeros(len(POINTS))
    values[nodes] = 0.1
    values[_node(1, 1)] = 0.45    # 0.15 above
    values[_node(2, 3)] = -0.55   # 0.25 below: the worst
    values[[_node(3, 4), _node(0, 0)]] = np.nan  # not seen
    (verdict,) = zone_verdicts(_field(values), [_zone(nodes)])
    assert not verdict.ok
    assert verdict.worst_node == _node(2, 3) and verdict.worst_deviation_mm == pytest.approx(-0.55)
    assert verdict.outside == 2 and verdict.coverage == pytest.approx(18 / 20)
    assert "2 seen node(s) outside" in verdict.reason


def test_a_part_within_limits_is_ok_and_names_the_node_nearest_a_limit():
    """Fails if a zone whose seen nodes all lie within the limits is not OK, or if its worst node is not the one
    nearest to a limit (0.25 of upper 0.3 beats -0.2 of lower -0.3)."""
    nodes = [_node(5, j) for j in range(11)]
    values = np.full(len(POINTS), 7.0)  # outside the zone: ignored
    values[nodes] = np.linspace(-0.2, 0.25, len(nodes))
    (verdict,) = zone_verdicts(_field(values), [_zone(nodes)])
    assert verdict.ok and verdict.reason == "" and verdict.outside == 0
    assert verdict.worst_node == _node(5, 10) and verdict.worst_deviation_mm == pytest.approx(0.25)


def test_a_zone_seen_too_little_or_not_at_all_is_not_ok():
    """Fails if a zone seen on less than its min_coverage is judged OK from the few nodes seen, or if an unseen zone
    gives a verdict other than NOK with no worst node; or if zones of another skin (a node beyond the field) are
    judged instead of refused."""
    nodes = [_node(8, j) for j in range(10)]
    values = np.full(len(POINTS), np.nan)
    values[nodes[:4]] = 0.0
    (partial,) = zone_verdicts(_field(values), [_zone(nodes, min_coverage=0.5)])
    assert not partial.ok and partial.coverage == pytest.approx(0.4) and "40 % of the zone seen" in partial.reason
    values[nodes[:4]] = np.nan
    (unseen,) = zone_verdicts(_field(values), [_zone(nodes)])
    assert not unseen.ok and unseen.worst_node == -1 and np.isnan(unseen.worst_deviation_mm)
    with pytest.raises(FieldError, match="another skin"):
        zone_verdicts(_field(np.zeros(10)), [_zone(nodes)])
