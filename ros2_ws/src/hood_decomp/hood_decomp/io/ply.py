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
from hood_decomp.io.small_files import open_regular

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


#: a PLY header is a few hundred bytes; a line or header longer than this is not one
_MAX_HEADER_LINE = 4096
_MAX_HEADER_LINES = 10_000


def _parse_header(handle, path) -> tuple[str, list[tuple[str, int, list[tuple[str, str, str | None]]]], list[str]]:
    """Format, elements (name, count, properties (name, type, list count type or None)) and comments of a PLY
    header; ScanError naming the line for anything else (unknown type, a count that is not a whole number >= 0, a
    missing word, no end_header)."""
    if handle.readline(_MAX_HEADER_LINE).strip() != b"ply":
        raise ScanError(f"{path}: not a PLY file (first line is not 'ply')")
    fmt, elements, comments = "", [], []
    for number in range(2, _MAX_HEADER_LINES):
        line = handle.readline(_MAX_HEADER_LINE)
        if not line:
            raise ScanError(f"{path}: PLY header has no end_header")
        if not line.endswith(b"\n") and len(line) == _MAX_HEADER_LINE:
            raise ScanError(f"{path}: PLY header line {number} is longer than {_MAX_HEADER_LINE} bytes")
        text = line.decode("ascii", errors="replace").strip()
        words = text.split()
        if not words:
            continue
        if words[0] == "end_header":
            break
        if words[0] in ("comment", "obj_info"):
            comments.append(text.split(" ", 1)[-1] if len(words) > 1 else "")
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            if not words[2].isdigit():
                raise ScanError(f"{path}: PLY header line {number}: element {words[1][:40]!r} count "
                                f"{words[2][:40]!r} is not a whole number >= 0")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            names = [words[-1]]
            if len(words) == 5 and words[1] == "list":
                types = [words[2], words[3]]
            elif len(words) == 3:
                types = [words[1]]
            else:
                raise ScanError(f"{path}: PLY header line {number}: expected 'property TYPE NAME' or 'property list "
                                f"COUNT_TYPE TYPE NAME', got {text[:80]!r}")
            unknown = [t for t in types if t not in _TYPES]
            if unknown:
                raise ScanError(f"{path}: PLY header line {number}: unknown property type {unknown[0][:40]!r} "
                                f"(known: {sorted(_TYPES)})")
            if names[0] in {p[0] for p in elements[-1][2]}:
                raise ScanError(f"{path}: PLY header line {number}: property {names[0][:40]!r} declared twice")
            if len(types) == 2:
                elements[-1][2].append((names[0], _TYPES[types[1]], _TYPES[types[0]]))
            else:
                elements[-1][2].append((names[0], _TYPES[types[0]], None))
        else:
            raise ScanError(f"{path}: PLY header line {number}: cannot read {text[:80]!r}")
    else:
        raise ScanError(f"{path}: PLY header has no end_header within {_MAX_HEADER_LINES} lines")
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise ScanError(f"{path}: unsupported PLY format {fmt[:40]!r}")
    if len({name for name, _, _ in elements}) != len(elements):
        raise ScanError(f"{path}: PLY header declares an element twice")
    empty = [name for name, _, props in elements if not props]
    if empty:
        raise ScanError(f"{path}: PLY element {empty[0][:40]!r} has no properties")
    return fmt, elements, comments


def _record_dtype(props: list[tuple[str, str, str | None]], endian: str) -> np.dtype:
    """One binary record of an element: its properties in order, or a triangle list (count, 3 indices)."""
    listed = [p for p in props if p[2] is not None]
    if listed:
        return np.dtype([("n", endian + listed[0][2]), ("i", endian + listed[0][1], (3,))])
    return np.dtype([(p[0], endian + p[1]) for p in props])


def _ascii_numbers(tokens: list[bytes], start: int, count: int, path, name: str) -> np.ndarray:
    """``count`` numbers of an ASCII PLY body from token ``start``; ScanError when fewer are left or one is text."""
    if start + count > len(tokens):
        raise ScanError(f"{path}: PLY file is truncated in element {name!r} (the header promises "
                        f"{count} more numbers, {len(tokens) - start} are left)")
    try:
        return np.array(tokens[start : start + count], dtype=np.float64)
    except ValueError:
        bad = next(t for t in tokens[start : start + count] if not _is_number(t))
        raise ScanError(f"{path}: PLY element {name!r} holds the text {bad[:40].decode(errors='replace')!r} where a "
                        "number belongs") from None


def _is_number(token: bytes) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_ply(path: str | os.PathLike) -> PlyData:
    """Read a PLY file (binary or ASCII). Faces must be triangles (a polygon list of 3 indices each). Raises
    ScanError naming the problem for anything a PLY file should not hold; sizes the header claims are checked
    against the file's size before anything is allocated."""
    try:  # judged on the open descriptor: a FIFO swapped in after a caller's is_file() check is refused, not waited on
        handle = open_regular(path, ScanError, "PLY file")
    except OSError as error:
        raise ScanError(f"cannot open PLY file {path}: {error.strerror}") from error
    with handle:
        fmt, elements, comments = _parse_header(handle, path)
        body_size = os.fstat(handle.fileno()).st_size - handle.tell()
        endian = ">" if fmt == "binary_big_endian" else "<"
        if fmt != "ascii":  # the header's promise against the file's size, before reading or allocating
            needed = sum(_record_dtype(props, endian).itemsize * count for _, count, props in elements)
            if needed > body_size:
                raise ScanError(f"{path}: the PLY header promises {needed} bytes of data, the file holds "
                                f"{body_size} (truncated, or a count that lies)")
        elif sum(count * max(len(props), 1) for _, count, props in elements) > body_size:
            raise ScanError(f"{path}: the PLY header promises more numbers than the {body_size}-byte body can hold")
        if fmt == "ascii":
            body = handle.read()
        else:  # straight into one array (a bytes object took twice its size in page faults: 50 MB at 1M points)
            body = np.empty(body_size, np.uint8)
            body = body[: handle.readinto(memoryview(body))]
    tokens = body.split() if fmt == "ascii" else None
    offset, data = 0, {}
    for name, count, props in elements:
        lists = [p for p in props if p[2] is not None]
        if lists and (len(props) != 1 or name != "face"):
            raise ScanError(f"{path}: only a face element may hold a list property (element {name!r})")
        if lists:
            dtype = _record_dtype(props, endian)
            if tokens is not None:
                rows = _ascii_numbers(tokens, offset, 4 * count, path, name).reshape(count, 4)
                offset += 4 * count
                counts, indices = rows[:, 0], rows[:, 1:]
            else:
                record = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
                offset += dtype.itemsize * count
                counts, indices = record["n"], record["i"]
            if count and np.any(counts != 3):
                shown = sorted(set(counts.tolist()))[:5]
                raise ScanError(f"{path}: faces must be triangles; found polygons of {shown}")
            if count and not np.all(np.isfinite(indices) & (indices == np.round(indices))):
                raise ScanError(f"{path}: face vertex indices must be whole numbers")
            data[name] = {"vertex_indices": indices.astype(np.int64)}
            continue
        if tokens is not None:
            width = len(props)
            rows = _ascii_numbers(tokens, offset, width * count, path, name).reshape(count, width)
            offset += width * count
            data[name] = {p[0]: rows[:, k] for k, p in enumerate(props)}
        else:
            dtype = _record_dtype(props, endian)
            record = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
            offset += dtype.itemsize * count
            data[name] = {p[0]: record[p[0]] for p in props}
    vertex = data.pop("vertex", None)
    if vertex is None or not {"x", "y", "z"} <= vertex.keys():
        raise ScanError(f"{path}: PLY file has no vertex element with x, y, z")
    # one copy into the final (M, 3) float64 array (per-column casts and a stack made three: 0.1 s at 5M points)
    points = np.empty((len(vertex["x"]), 3))
    for k, axis in enumerate("xyz"):
        points[:, k] = vertex.pop(axis)
    face = data.pop("face", None)
    triangles = face["vertex_indices"] if face is not None else None
    if triangles is not None and triangles.size and (triangles.min() < 0 or triangles.max() >= len(points)):
        raise ScanError(f"{path}: faces index vertices {triangles.min()}..{triangles.max()}, the file has "
                        f"0..{len(points) - 1}")
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
            words = comment[len(_POSE_TAG) :].split()
            values = np.array([float(w) if _is_number(w.encode()) else np.nan for w in words], dtype=np.float64)
            if values.size != 16 or not np.all(np.isfinite(values)):
                raise ScanError(f"{path}: scanner_pose comment must hold 16 finite numbers; found "
                                f"{comment[len(_POSE_TAG):][:80].strip()!r}")
            pose = values.reshape(4, 4)
    marker = ply.elements.get("marker")
    if marker is not None and not {"id", "x", "y", "z", "fx", "fy", "fz"} <= marker.keys():
        raise ScanError(f"{path}: element marker needs id, x, y, z, fx, fy, fz; found {sorted(marker)[:10]}")
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
