"""PointCloud2 <-> numpy: exact round trips over every layout a scanner may send, and clear errors for bad clouds.

The reference encoder below writes each point with ``struct.pack_into``, independently of the numpy code under test.
"""

from __future__ import annotations

import array
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.required import require_import

require_import("sensor_msgs.msg", "colcon build", "the ROS 2 environment: run inside scripts/with-env")
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from hood_decomp.errors import PointCloudError
from hood_decomp.ros.pointcloud import cloud_channel, cloud_to_xyz, finite_rows, xyz_to_cloud

STRUCT = {7: "f", 8: "d", 2: "B", 4: "H", 6: "I"}
SIZE = {7: 4, 8: 8, 2: 1, 4: 2, 6: 4}


def encode(points: np.ndarray, *, height: int, xyz_types: tuple[int, int, int], extra: list[int], big: bool,
           gap: int, row_pad: int, order: list[int]) -> PointCloud2:
    """Reference encoder: fields in ``order`` (0-2 = x, y, z; 3+ = extras), ``gap`` padding bytes after each field,
    ``row_pad`` bytes after each row; values written point by point with struct."""
    names = ["x", "y", "z"] + [f"extra{i}" for i in range(len(extra))]
    types = list(xyz_types) + extra
    offsets, offset = {}, 0
    for index in order:
        offsets[index] = offset
        offset += SIZE[types[index]] + gap
    point_step = offset
    width = points.shape[0] // height
    row_step = width * point_step + row_pad
    data = bytearray(row_step * height)
    prefix = ">" if big else "<"
    for i, point in enumerate(points):
        row, col = divmod(i, width)
        base = row * row_step + col * point_step
        for index in range(len(types)):
            value = point[index] if index < 3 else 7
            struct.pack_into(prefix + STRUCT[types[index]], data, base + offsets[index], value)
    cloud = PointCloud2()
    cloud.header = Header(frame_id="scanner")
    cloud.height, cloud.width = height, width
    cloud.fields = [PointField(name=names[i], offset=offsets[i], datatype=types[i], count=1) for i in order]
    cloud.is_bigendian = big
    cloud.point_step, cloud.row_step = point_step, row_step
    cloud.is_dense = bool(np.isfinite(points).all())
    cloud.data = array.array("B", bytes(data))
    return cloud


@st.composite
def layouts(draw):
    height = draw(st.integers(1, 4))
    width = draw(st.integers(0, 12))
    xyz_types = tuple(draw(st.sampled_from([7, 8])) for _ in range(3))
    extra = draw(st.lists(st.sampled_from([2, 4, 6, 7, 8]), max_size=3))
    order = draw(st.permutations(list(range(3 + len(extra)))))
    values = draw(st.lists(
        st.one_of(st.floats(-1e4, 1e4, width=32), st.just(float("nan"))),
        min_size=3 * height * width, max_size=3 * height * width,
    ))
    return dict(
        points=np.array(values, dtype=np.float64).reshape(height * width, 3),
        height=height, xyz_types=xyz_types, extra=extra, order=order,
        big=draw(st.booleans()), gap=draw(st.integers(0, 5)), row_pad=draw(st.integers(0, 9)),
    )


@settings(max_examples=200, deadline=None)
@given(layouts())
def test_reads_every_layout_exactly(layout):
    points = layout.pop("points")
    cloud = encode(points, **layout)
    kept = cloud_to_xyz(cloud, drop_nan=False)
    np.testing.assert_array_equal(kept, points)  # float32 values survive float64 exactly; NaN == NaN here
    dropped = cloud_to_xyz(cloud)
    np.testing.assert_array_equal(dropped, points[np.isfinite(points).all(axis=1)])
    for i in range(len(layout["extra"])):  # any numeric extra field reads back in point order
        np.testing.assert_array_equal(cloud_channel(cloud, f"extra{i}"), np.full(points.shape[0], 7.0))


def test_non_finite_points_are_dropped_in_any_coordinate():
    """Fails if the one-pass finiteness test misses a NaN, +inf or -inf in any coordinate of the adjacent-xyz read, or
    drops a finite point (against numpy's per-element test)."""
    rng = np.random.default_rng(5)
    points = rng.uniform(-2.0, 2.0, (300, 3))
    for row, (axis, bad) in enumerate([(a, b) for a in range(3) for b in (np.nan, np.inf, -np.inf)]):
        points[17 * row + 3, axis] = bad
    expected = np.isfinite(points).all(axis=1)
    np.testing.assert_array_equal(finite_rows(points), expected)
    assert finite_rows(points[expected]) is None
    cloud = encode(points, height=3, xyz_types=(7, 7, 7), extra=[2], big=False, gap=0, row_pad=2, order=[0, 1, 2, 3])
    np.testing.assert_array_equal(cloud_to_xyz(cloud, scale=1000.0),
                                  points[expected].astype(np.float32).astype(np.float64) * 1000.0)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 50), st.integers(0, 3), st.floats(1e-3, 1e3))
def test_write_then_read_round_trips(n_points, n_channels, scale):
    rng = np.random.default_rng(n_points)
    points = rng.uniform(-2000, 2000, (n_points, 3)).astype(np.float32).astype(np.float64)
    channels = {f"c{i}": rng.normal(size=n_points) for i in range(n_channels)}
    cloud = xyz_to_cloud(points, Header(frame_id="part"), channels=channels)
    assert [f.name for f in cloud.fields] == ["x", "y", "z", *channels]
    np.testing.assert_array_equal(cloud_to_xyz(cloud), points)
    # Scaling is applied on the way out and undone on the way in (the mm <-> m use).
    scaled = xyz_to_cloud(points, Header(), scale=1.0 / scale)
    np.testing.assert_allclose(cloud_to_xyz(scaled, scale=scale), points, rtol=2e-7, atol=1e-9)
    # Channels are readable by an independent decoder.
    if n_channels and n_points:
        raw = bytes(cloud.data)
        last = struct.unpack_from("<f", raw, (n_points - 1) * cloud.point_step + 4 * (2 + n_channels))[0]
        assert last == pytest.approx(channels[f"c{n_channels - 1}"][-1], rel=1e-6)


def test_scales_metres_to_millimetres_in_one_pass():
    points = np.array([[0.5, -0.25, 1.0]])
    cloud = encode(points, height=1, xyz_types=(7, 7, 7), extra=[], big=False, gap=0, row_pad=0, order=[0, 1, 2])
    np.testing.assert_array_equal(cloud_to_xyz(cloud, scale=1000.0), [[500.0, -250.0, 1000.0]])


def _good_cloud() -> PointCloud2:
    return encode(np.ones((6, 3)), height=2, xyz_types=(7, 7, 7), extra=[7], big=False, gap=0, row_pad=0,
                  order=[0, 1, 2, 3])


def test_missing_xyz_is_named():
    cloud = _good_cloud()
    cloud.fields = [f for f in cloud.fields if f.name != "z"]
    with pytest.raises(PointCloudError, match=r"no field.*z.*present: extra0, x, y"):
        cloud_to_xyz(cloud)


def test_inconsistent_size_is_named():
    cloud = _good_cloud()
    cloud.data = cloud.data[:-4]
    with pytest.raises(PointCloudError, match=r"data has 92 bytes; expected row_step \* height = 48 \* 2 = 96"):
        cloud_to_xyz(cloud)


def test_row_step_smaller_than_row_is_named():
    cloud = _good_cloud()
    cloud.row_step, cloud.height = 8, 12
    with pytest.raises(PointCloudError, match="row_step 8 is smaller than width"):
        cloud_to_xyz(cloud)


@pytest.mark.parametrize("datatype, name", [(5, "INT32"), (3, "INT16"), (42, "unknown datatype 42")])
def test_unsupported_datatype_is_named(datatype, name):
    cloud = _good_cloud()
    cloud.fields[1].datatype = datatype
    with pytest.raises(PointCloudError, match=f"field 'y' has datatype {name}; expected FLOAT32 or FLOAT64"):
        cloud_to_xyz(cloud)


def test_field_outside_point_step_is_named():
    cloud = _good_cloud()
    cloud.fields[2].offset = 14
    with pytest.raises(PointCloudError, match=r"'z' at offset 14 .* point_step 16"):
        cloud_to_xyz(cloud)


def test_count_other_than_one_is_refused():
    cloud = _good_cloud()
    cloud.fields[0].count = 3
    with pytest.raises(PointCloudError, match="'x' has count 3"):
        cloud_to_xyz(cloud)


def test_bad_points_shape_is_named():
    with pytest.raises(PointCloudError, match=r"shape \(N, 3\); got \(4, 2\)"):
        xyz_to_cloud(np.zeros((4, 2)), Header())
