"""PLY files for scans and meshes, in plain numpy (binary little/big endian and ASCII; no pickle, no open3d).

A scan file written here holds the raw points in the scanner frame (``vertex`` x, y, z as doubles, mm), the scanner's
nominal pose as a header comment ``hood_decomp scanner_pose`` with 16 numbers (row-major 4x4, x_part = T x_scan) and,
when the scanner reported fixture markers, an element ``marker`` with ``id``, the measured centre ``x y z`` (scanner
frame) and the nominal centre ``fx fy fz`` (part frame). Other programs (CloudCompare, MeshLab) read the vertices and
ignore the rest.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from hood_decomp.core.types import SkinSurface
from hood_decomp.errors import ScanError

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip
_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint", "f4": "float",
          "f8": "double"}  # fmt: skip
_POSE_TAG = "hood_decomp scanner_pose"


@dataclass(frozen=True)
class PlyData:
    """Contents of a PLY file.

    points: (N, 3) float64 vertex positions. triangles: (T, 3) int64, or None when the file has no faces.
    vertex_fields: other per-vertex properties by name, (N,) each (e.g. CloudCompare's distance scalar field).
    elements: further elements by name, each a dict of property name to (K,) array.
    comments: header comments in order.
    """

    points: np.ndarray
    triangles: np.ndarray | None = None
    vertex_fields: dict[str, np.ndarray] = field(default_factory=dict)
    elements: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    comments: tuple[str, ...] = ()


@dataclass(frozen=True)
class ScanFile:
    """A scan as stored: points (M, 3) mm scanner frame; scanner_pose (4, 4) or None; markers (K, 3) measured
    (scanner frame), marker_ids (K,), markers_nominal (K, 3) part frame (K = 0 without markers)."""

    points: np.ndarray
    scanner_pose: np.ndarray | None
    markers: np.ndarray
    marker_ids: np.ndarray
    markers_nominal: np.ndarray


def write_ply(
    path: str | os.PathLike,
    points: np.ndarray,
    *,
    triangles: np.ndarray | None = None,
    vertex_fields: dict[str, np.ndarray] | None = None,
    elements: dict[str, dict[str, np.ndarray]] | None = None,
    comments: tuple[str, ...] = (),
    precision: str = "double",
) -> None:
    """Write a binary little-endian PLY: vertices (N, 3) as ``precision`` ("double" or "float"), optional
    triangles (T, 3), per-vertex scalar fields (N,) as float32, further elements and header comments."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ScanError(f"PLY points must be (N, 3); got {points.shape}")
    n = points.shape[0]
    coord = "f8" if precision == "double" else "f4"
    vertex_cols: dict[str, np.ndarray] = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}
    vertex_types = dict.fromkeys(vertex_cols, coord)
    for name, values in (vertex_fields or {}).items():
        values = np.asarray(values)
        if values.shape != (n,):
            raise ScanError(f"vertex field {name!r} must have shape ({n},); got {values.shape}")
        vertex_cols[name], vertex_types[name] = values, "f4"
    blocks = [("vertex", n, vertex_cols, vertex_types)]
    if triangles is not None:
        tri = np.asarray(triangles)
        faces = {"count": np.full(tri.shape[0], 3), "v0": tri[:, 0], "v1": tri[:, 1], "v2": tri[:, 2]}
        blocks.append(("face", tri.shape[0], faces, {"count": "u1", "v0": "i4", "v1": "i4", "v2": "i4"}))
    for name, props in (elements or {}).items():
        sizes = {np.asarray(v).shape[0] for v in props.values()}
        if len(sizes) != 1:
            raise ScanError(f"element {name!r}: properties of different lengths {sorted(sizes)}")
        types = {k: np.asarray(v).dtype.str[1:] for k, v in props.items()}
        types = {k: (t if t in _NAMES else "f8") for k, t in types.items()}  # anything else is written as double
        blocks.append((name, sizes.pop(), props, types))

    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments)]
    for name, count, cols, types in blocks:
        header.append(f"element {name} {count}")
        if name == "face":
            header.append("property list uchar int vertex_indices")
        else:
            header.extend(f"property {_NAMES[types[k]]} {k}" for k in cols)
    header.append("end_header")
    with open(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        for _, count, cols, types in blocks:
            record = np.empty(count, dtype=[(k, "<" + types[k]) for k in cols])
            for k, values in cols.items():
                record[k] = values
            handle.write(record.tobytes())


def _parse_header(handle) -> tuple[str, list[tuple[str, int, list[tuple[str, str, str | None]]]], list[str]]:
    if handle.readline().strip() != b"ply":
        raise ScanError(f"{handle.name}: not a PLY file (first line is not 'ply')")
    fmt, elements, comments = "", [], []
    while True:
        line = handle.readline()
        if not line:
            raise ScanError(f"{handle.name}: PLY header has no end_header")
        words = line.decode("ascii", errors="replace").split()
        if not words:
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1]
        elif words[0] in ("comment", "obj_info"):
            comments.append(line.decode("ascii", errors="replace").strip().split(" ", 1)[-1])
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise ScanError(f"{handle.name}: PLY property before any element")
            if words[1] == "list":
                elements[-1][2].append((words[4], _TYPES[words[3]], _TYPES[words[2]]))
            else:
                elements[-1][2].append((words[2], _TYPES[words[1]], None))
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise ScanError(f"{handle.name}: unsupported PLY format {fmt!r}")
    return fmt, elements, comments


def read_ply(path: str | os.PathLike) -> PlyData:
    """Read a PLY file (binary or ASCII). Faces must be triangles (a polygon list of 3 indices each)."""
    try:
        handle = open(path, "rb")
    except OSError as error:
        raise ScanError(f"cannot open PLY file {path}: {error.strerror}") from error
    with handle:
        fmt, elements, comments = _parse_header(handle)
        body = handle.read()
    endian = ">" if fmt == "binary_big_endian" else "<"
    tokens = body.split() if fmt == "ascii" else None
    offset, data = 0, {}
    for name, count, props in elements:
        lists = [p for p in props if p[2] is not None]
        if lists and (len(props) != 1 or name != "face"):
            raise ScanError(f"{path}: only a face element may hold a list property (element {name!r})")
        if lists:
            _, index_type, count_type = lists[0]
            dtype = np.dtype([("n", endian + count_type), ("i", endian + index_type, (3,))])
            if tokens is not None:
                rows = np.array(tokens[offset : offset + 4 * count], dtype=np.float64).reshape(count, 4)
                offset += 4 * count
                counts, indices = rows[:, 0], rows[:, 1:].astype(np.int64)
            else:
                record = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
                offset += dtype.itemsize * count
                counts, indices = record["n"], record["i"].astype(np.int64)
            if count and np.any(counts != 3):
                raise ScanError(f"{path}: faces must be triangles; found polygons of {sorted(set(counts.tolist()))}")
            data[name] = {"vertex_indices": indices}
            continue
        if tokens is not None:
            width = len(props)
            rows = np.array(tokens[offset : offset + width * count], dtype=np.float64).reshape(count, width)
            offset += width * count
            data[name] = {p[0]: rows[:, k] for k, p in enumerate(props)}
        else:
            dtype = np.dtype([(p[0], endian + p[1]) for p in props])
            if offset + dtype.itemsize * count > len(body):
                raise ScanError(f"{path}: PLY file is truncated in element {name!r}")
            record = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
            offset += dtype.itemsize * count
            data[name] = {p[0]: record[p[0]] for p in props}
    vertex = data.pop("vertex", None)
    if vertex is None or not {"x", "y", "z"} <= vertex.keys():
        raise ScanError(f"{path}: PLY file has no vertex element with x, y, z")
    points = np.column_stack([vertex.pop(k).astype(np.float64) for k in ("x", "y", "z")])
    face = data.pop("face", None)
    triangles = face["vertex_indices"] if face is not None else None
    fields = {k: np.asarray(v, dtype=np.float64) for k, v in vertex.items()}
    return PlyData(points, triangles, fields, data, tuple(comments))


def write_scan(
    path: str | os.PathLike,
    points: np.ndarray,
    *,
    scanner_pose: np.ndarray | None = None,
    markers: np.ndarray | None = None,
    marker_ids: np.ndarray | None = None,
    markers_nominal: np.ndarray | None = None,
    comments: tuple[str, ...] = (),
) -> None:
    """Write a scan (see the module docstring): points (M, 3) mm scanner frame, optional pose and markers."""
    header = ["hood_decomp units mm", *comments]
    if scanner_pose is not None:
        header.append(_POSE_TAG + " " + " ".join(repr(float(v)) for v in np.asarray(scanner_pose).ravel()))
    elements = None
    if markers is not None and len(markers):
        measured, nominal = np.asarray(markers, dtype=np.float64), np.asarray(markers_nominal, dtype=np.float64)
        ids = np.arange(len(measured)) if marker_ids is None else np.asarray(marker_ids)
        elements = {
            "marker": {
                "id": ids.astype(np.int32),
                "x": measured[:, 0], "y": measured[:, 1], "z": measured[:, 2],
                "fx": nominal[:, 0], "fy": nominal[:, 1], "fz": nominal[:, 2],
            }
        }  # fmt: skip
    write_ply(path, points, elements=elements, comments=tuple(header))


def read_scan(path: str | os.PathLike) -> ScanFile:
    """Read a scan written by :func:`write_scan` (or any PLY point cloud: then no pose and no markers)."""
    ply = read_ply(path)
    pose = None
    for comment in ply.comments:
        if comment.startswith(_POSE_TAG):
            values = np.array(comment[len(_POSE_TAG) :].split(), dtype=np.float64)
            if values.size != 16:
                raise ScanError(f"{path}: scanner_pose comment must hold 16 numbers; found {values.size}")
            pose = values.reshape(4, 4)
    marker = ply.elements.get("marker")
    if marker is None:
        return ScanFile(ply.points, pose, np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3)))
    measured = np.column_stack([marker[k] for k in ("x", "y", "z")]).astype(np.float64)
    nominal = np.column_stack([marker[k] for k in ("fx", "fy", "fz")]).astype(np.float64)
    return ScanFile(ply.points, pose, measured, marker["id"].astype(np.int64), nominal)


def write_skin_mesh(
    path: str | os.PathLike, skin: SkinSurface, vertex_fields: dict[str, np.ndarray] | None = None
) -> None:
    """Write the skin as a triangle mesh whose winding agrees with the node normals (right-hand rule), so programs
    that sign distances by the face normal (CloudCompare) sign them like hood_decomp does."""
    tri = np.asarray(skin.triangles, dtype=np.int64)
    p = skin.points
    face = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])
    flip = np.einsum("td,td->t", face, skin.normals[tri].sum(axis=1)) < 0
    tri = np.where(flip[:, None], tri[:, ::-1], tri)
    write_ply(path, p, triangles=tri, vertex_fields=vertex_fields, comments=(f"hood_decomp skin {skin.model_id}",))
