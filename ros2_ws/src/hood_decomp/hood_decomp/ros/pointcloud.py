"""sensor_msgs/PointCloud2 <-> numpy, with at most one copy of the point buffer.

Reading accepts any layout a real scanner sends: float32 or float64 x/y/z at any offsets, extra fields and padding
(``point_step`` larger than the xyz triple), row padding (``row_step > width * point_step``), organized clouds
(``height > 1``), NaN points and big-endian data. The buffer is viewed in place with a strided numpy dtype and read
once, converting to native float64 (and scaling, e.g. metres to millimetres) in that same pass.

Both functions are duck-typed on the message: they work with rclpy's ``sensor_msgs.msg.PointCloud2`` (``data`` is an
``array.array('B')``) and with messages decoded by ``rosbags`` (``data`` is a numpy uint8 array).
"""

from __future__ import annotations

import array
import sys
from collections.abc import Mapping
from typing import Any

import numpy as np

from hood_decomp.errors import PointCloudError

# sensor_msgs/PointField datatype constants -> numpy base type.
POINTFIELD_DTYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
POINTFIELD_NAMES: dict[int, str] = {
    1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32", 7: "FLOAT32", 8: "FLOAT64",
}
FLOAT32 = 7
FLOATS = (7, 8)
XYZ = ("x", "y", "z")


def _fields_dtype(cloud: Any, names: tuple[str, ...], kinds: tuple[int, ...]) -> np.dtype:
    """A strided dtype that reads only the fields ``names`` out of one point of ``cloud``."""
    byte_order = ">" if cloud.is_bigendian else "<"
    fields = {field.name: field for field in cloud.fields}
    missing = [name for name in names if name not in fields]
    if missing:
        present = ", ".join(sorted(fields)) or "none"
        raise PointCloudError(f"PointCloud2 has no field(s) {', '.join(missing)}; fields present: {present}")
    formats = []
    for name in names:
        field = fields[name]
        if field.datatype not in kinds:
            kind = POINTFIELD_NAMES.get(field.datatype, f"unknown datatype {field.datatype}")
            expected = " or ".join(POINTFIELD_NAMES[k] for k in kinds)
            raise PointCloudError(f"PointCloud2 field '{name}' has datatype {kind}; expected {expected}")
        if field.count != 1:
            raise PointCloudError(f"PointCloud2 field '{name}' has count {field.count}; expected 1")
        base = np.dtype(byte_order + POINTFIELD_DTYPES[field.datatype])
        if field.offset < 0 or field.offset + base.itemsize > cloud.point_step:
            raise PointCloudError(
                f"PointCloud2 field '{name}' at offset {field.offset} ({base.itemsize} bytes) does not fit in "
                f"point_step {cloud.point_step}"
            )
        formats.append(base)
    return np.dtype({
        "names": list(names),
        "formats": formats,
        "offsets": [fields[name].offset for name in names],
        "itemsize": cloud.point_step,
    })


def _points_view(cloud: Any, names: tuple[str, ...], kinds: tuple[int, ...]) -> np.ndarray:
    """Zero-copy (height, width) view of the fields ``names``, after checking the sizes of the cloud."""
    height, width = int(cloud.height), int(cloud.width)
    point_step, row_step = int(cloud.point_step), int(cloud.row_step)
    n_bytes = len(cloud.data)
    if n_bytes != row_step * height:
        raise PointCloudError(
            f"PointCloud2 data has {n_bytes} bytes; expected row_step * height = {row_step} * {height} = "
            f"{row_step * height}"
        )
    dtype = _fields_dtype(cloud, names, kinds)
    if row_step < width * point_step:
        raise PointCloudError(
            f"PointCloud2 row_step {row_step} is smaller than width * point_step = {width} * {point_step}"
        )
    # (height, row_step) bytes -> drop row padding -> (height, width) points of the strided dtype.
    raw = np.frombuffer(cloud.data, dtype=np.uint8).reshape(height, row_step)[:, : width * point_step]
    return raw.view(dtype)


def _xyz_view(cloud: Any, points: np.ndarray) -> np.ndarray | None:
    """(height, width, 3) view of x, y, z in the cloud's buffer when they are one datatype, adjacent and in order
    (the usual layout), so that one strided copy reads all three; None otherwise."""
    fields = points.dtype.fields
    base = fields["x"][0]
    offset = fields["x"][1]
    if any(fields[name][0] != base or fields[name][1] != offset + k * base.itemsize for k, name in enumerate(XYZ)):
        return None
    height, width = points.shape
    return np.ndarray((height, width, 3), dtype=base, buffer=memoryview(cloud.data).cast("B"), offset=offset,
                      strides=(int(cloud.row_step), int(cloud.point_step), base.itemsize))  # fmt: skip


def finite_rows(points: np.ndarray) -> np.ndarray | None:
    """Rows (N, 3) with all coordinates finite as an (N,) bool mask, or None when every row is (one flat pass; the
    mask, three column passes, only when a point is NaN or infinite)."""
    if np.isfinite(points.reshape(-1)).all():
        return None
    check = points[:, 0] + points[:, 1]
    check += points[:, 2]  # any NaN or inf coordinate makes the sum non-finite (float32 data cannot overflow it)
    return np.isfinite(check)


def cloud_to_xyz(cloud: Any, *, scale: float = 1.0, drop_nan: bool = True) -> np.ndarray:
    """Read the points of a PointCloud2.

    cloud: a sensor_msgs/PointCloud2 (rclpy or rosbags message).
    scale: factor applied while copying, e.g. 1000.0 for metres (the message) to millimetres (the core).
    drop_nan: drop points with a non-finite coordinate (the scanner's "no return"); keep them with False, which keeps
        an organized cloud's row-major pixel order.
    Returns: (N, 3) float64, N = height * width (minus dropped points), in the cloud's frame, times ``scale``.
    Raises PointCloudError naming the problem: missing x/y/z, unsupported datatype, a field outside point_step,
    row_step < width * point_step, or len(data) != row_step * height.
    """
    points = _points_view(cloud, XYZ, FLOATS)
    out = np.empty((points.size, 3), dtype=np.float64)
    xyz = _xyz_view(cloud, points) if points.size else None
    # The one copy: strided (possibly big-endian, float32) -> native float64; then scaled in place, in float64.
    if xyz is not None:
        out.reshape(*points.shape, 3)[...] = xyz
    else:  # x, y, z apart or of different types: one strided copy per coordinate
        for axis, name in enumerate(XYZ):
            out.reshape(*points.shape, 3)[:, :, axis] = points[name]
    if scale != 1.0:
        out *= scale
    if drop_nan:
        finite = finite_rows(out)
        if finite is not None:
            out = np.compress(finite, out, axis=0)  # 3x faster than boolean indexing of (N, 3) rows
    return out


def cloud_channel(cloud: Any, name: str) -> np.ndarray:
    """One numeric per-point field (any datatype) as (height * width,) float64, in the cloud's point order
    (``cloud_to_xyz(..., drop_nan=False)`` order). Raises PointCloudError like :func:`cloud_to_xyz`."""
    view = _points_view(cloud, (name,), tuple(POINTFIELD_DTYPES))
    return view[name].astype(np.float64).ravel()


def xyz_to_cloud(
    points: np.ndarray,
    header: Any,
    *,
    channels: Mapping[str, np.ndarray] | None = None,
    scale: float = 1.0,
) -> Any:
    """Build an unorganized float32 PointCloud2 with fields x, y, z and one float32 field per channel.

    points: (N, 3) array; written as ``points * scale`` (e.g. 0.001 for millimetres to metres).
    channels: name -> (N,) array of extra per-point values (e.g. a displacement in metres, a contribution 0..1),
        written unscaled.
    The buffer is allocated once as the message's own ``array.array('B')`` and filled in place through a numpy view.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PointCloudError(f"points must have shape (N, 3); got {points.shape}")
    channels = dict(channels or {})
    for name, values in channels.items():
        if np.shape(values) != (points.shape[0],):
            raise PointCloudError(f"channel '{name}' must have shape ({points.shape[0]},); got {np.shape(values)}")
        if name in XYZ:
            raise PointCloudError(f"channel name '{name}' clashes with a coordinate field")
    from sensor_msgs.msg import PointCloud2, PointField

    names = [*XYZ, *channels]
    n_points, point_step = points.shape[0], 4 * len(names)
    buffer = array.array("B", bytes(n_points * point_step))
    view = np.frombuffer(buffer, dtype=np.float32).reshape(n_points, len(names))
    np.multiply(points, scale, out=view[:, :3], casting="unsafe")
    for column, values in enumerate(channels.values(), start=3):
        view[:, column] = values
    cloud = PointCloud2()
    cloud.header = header
    cloud.height, cloud.width = 1, n_points
    cloud.fields = [PointField(name=name, offset=4 * i, datatype=FLOAT32, count=1) for i, name in enumerate(names)]
    cloud.is_bigendian = sys.byteorder == "big"
    cloud.point_step, cloud.row_step = point_step, point_step * n_points
    cloud.is_dense = bool(np.isfinite(view).all())
    cloud.data = buffer
    return cloud
