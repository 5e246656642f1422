"""Field files: a displacement field as a ``.vtu`` on the visible skin.

Layout: points = skin node positions (N, 3) mm, triangle cells = skin triangles, point data ``normal_displacement``
(N,) mm (NaN where unknown) and ``displacement`` (N, 3) mm. ``displacement`` is the field's own 3D displacement
(:attr:`DisplacementField.displacement`, what a ``components="xyz"`` fit reads) only when FieldData
``displacement_3d`` is 1 (UInt8); without it (0, or a file written before it) it is normal x value, a picture for
ParaView, and the field read has no 3D displacement. VTK FieldData carries ``model_id`` (UInt8
ASCII codes), ``coverage`` and ``noise_rms`` (mm, NaN when unknown), and the field's error model (FieldData
``error_model`` (kind, ASCII codes; "none" for a simulated field), ``error_correlation_length_mm``,
``error_pose_covariance`` (36, row-major 6 x 6, [rad, mm]^2 about ``error_pose_center_mm`` (3)),
``error_bias_correlation`` and ``error_bias_variance_floor_mm2`` (mm^2 per node; absent in files written before
it: 0); point data ``error_std`` (N,) mm and ``error_correlation`` (N,)). meshio reads FieldData
but does not write it, so the writer adds the FieldData element to the XML meshio wrote; ParaView shows it as field
data.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hood_decomp.core.types import DisplacementField, FieldErrorModel, SkinSurface
from hood_decomp.errors import FieldError, HoodDecompError
from hood_decomp.io.small_files import descriptor_path, open_regular

if TYPE_CHECKING:  # meshio is imported where a .vtu is read or written: a scan's verb never loads it
    import meshio


def _ascii_codes(text: str) -> np.ndarray:
    return np.frombuffer(text.encode("ascii"), dtype=np.uint8)


def _field_data_xml(items: dict[str, np.ndarray]) -> str:
    """VTK FieldData with one DataArray per item (uint8 arrays as UInt8 ASCII codes, the rest as Float64)."""
    rows = []
    for name, values in items.items():
        kind = "UInt8" if values.dtype == np.uint8 else "Float64"
        text = " ".join(str(int(v)) if kind == "UInt8" else repr(float(v)) for v in values.ravel())
        rows.append(f'<DataArray type="{kind}" Name="{name}" NumberOfTuples="{values.size}" format="ascii">{text}'
                    "</DataArray>\n")
    return "<FieldData>\n" + "".join(rows) + "</FieldData>\n"


def _error_model_items(errors: FieldErrorModel) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(point data, field data) that carry an error model; the kind "none" is written too, so it is stated."""
    field_data = {"error_model": _ascii_codes(errors.kind)}
    if errors.kind == "none":
        return {}, field_data
    field_data.update(
        error_correlation_length_mm=np.array([errors.correlation_length_mm]),
        error_pose_covariance=np.asarray(errors.pose_covariance, float).ravel(),
        error_pose_center_mm=np.asarray(errors.pose_center, float),
        error_bias_correlation=np.array([errors.bias_correlation]),
        error_bias_variance_floor_mm2=np.array([errors.bias_variance_floor]),
    )
    return {"error_std": np.asarray(errors.node_std, float),
            "error_correlation": np.asarray(errors.correlation, float)}, field_data


def _read_error_model(mesh: meshio.Mesh, path: Path, n_nodes: int) -> FieldErrorModel | None:
    """The error model a field file carries (None for a file written before error models); validated."""
    data = mesh.field_data
    if "error_model" not in data:
        return None
    kind = bytes(np.asarray(data["error_model"], dtype=np.uint8).reshape(-1)).decode("ascii", errors="replace")
    if kind == "none":
        return FieldErrorModel.none()

    def item(name: str, where: dict, size: int | None = None) -> np.ndarray:
        if name not in where:
            raise FieldError(f"{path} states an error model {kind!r} but has no {name!r}")
        values = np.asarray(where[name], dtype=float).reshape(-1)
        if size is not None and values.size != size:
            raise FieldError(f"{path}: {name} has {values.size} values, expected {size}")
        return values

    errors = FieldErrorModel(
        kind=kind, node_std=item("error_std", mesh.point_data), correlation=item("error_correlation", mesh.point_data),
        correlation_length_mm=float(item("error_correlation_length_mm", data, 1)[0]),
        pose_covariance=item("error_pose_covariance", data, 36).reshape(6, 6),
        pose_center=item("error_pose_center_mm", data, 3),
        bias_correlation=float(item("error_bias_correlation", data, 1)[0]),
        bias_variance_floor=float(item("error_bias_variance_floor_mm2", data, 1)[0])
        if "error_bias_variance_floor_mm2" in data else 0.0,  # a file written before the floor states none
    )
    try:
        errors.validate(n_nodes)
    except FieldError as error:
        raise FieldError(f"{path}: {error}") from None
    return errors


def write_field(path: str | Path, skin: SkinSurface, field: DisplacementField) -> None:
    """Write ``field`` on ``skin`` to ``path`` (.vtu): point data ``displacement`` is the field's 3D displacement
    (validated against the skin, :meth:`DisplacementField.checked_displacement`) when it has one, else normal x value
    (module docstring)."""
    if field.model_id != skin.model_id:
        raise FieldError(f"field model_id {field.model_id!r} differs from the skin's {skin.model_id!r}")
    values = np.asarray(field.normal_displacement, dtype=float)
    if values.shape != (skin.n_nodes,):
        raise FieldError(f"field has shape {values.shape}, expected ({skin.n_nodes},)")
    has_3d = field.displacement is not None
    vectors = field.checked_displacement(skin.normals) if has_3d else field.vectors(skin.normals)
    field.errors.validate(skin.n_nodes)
    error_points, error_data = _error_model_items(field.errors)
    from xml.sax.saxutils import escape  # writing only: it loads urllib and http (30 ms of a reader's start)

    import meshio

    mesh = meshio.Mesh(
        skin.points,
        [("triangle", np.asarray(skin.triangles))],
        point_data={"normal_displacement": values, "displacement": vectors, **error_points},
    )
    path = Path(path)
    meshio.write(path, mesh, file_format="vtu")
    text = path.read_text()
    marker = "<UnstructuredGrid>\n"
    extra = _field_data_xml({"model_id": _ascii_codes(escape(field.model_id)),
                             "coverage": np.array([float(field.coverage)]),
                             "noise_rms": np.array([float(field.noise_rms)]),
                             "displacement_3d": np.array([int(has_3d)], np.uint8), **error_data})
    path.write_text(text.replace(marker, marker + extra, 1))


def read_field(path: str | Path, skin: SkinSurface | None = None) -> tuple[DisplacementField, np.ndarray | None]:
    """Read a field file; return ``(DisplacementField, displacement (N, 3) mm or None)``.

    A file without ``model_id`` (e.g. written by a plain ``meshio.write``, which drops VTU FieldData) is accepted only
    when ``skin`` is given and the file's points are the skin's nodes in the skin's order (within 1e-6 mm); it then
    gets the skin's model_id. Raises FieldError when the file is missing or unreadable, has no
    ``normal_displacement``, or has no ``model_id`` and no matching skin. Coverage is recomputed from the values; a
    missing ``noise_rms`` is NaN. The field has a 3D displacement when the file states one (module docstring),
    validated (:meth:`DisplacementField.checked_displacement`; its normal part only given ``skin``); the second value
    returned is the file's point data ``displacement`` whatever it is.
    """
    path = Path(path)
    if not path.exists():  # anything else that is not a regular file is named by read_vtu
        raise FieldError(f"field file {path} does not exist")
    mesh = read_vtu(path, FieldError)
    if "normal_displacement" not in mesh.point_data:
        raise FieldError(f"{path} has no point data 'normal_displacement' (found {sorted(mesh.point_data)[:10]})")
    values = _plausible(mesh.point_data["normal_displacement"], path, "normal_displacement").reshape(-1)
    if len(values) != len(mesh.points):
        raise FieldError(f"{path}: normal_displacement has {len(values)} values for {len(mesh.points)} points")
    if "model_id" in mesh.field_data:
        codes = np.asarray(mesh.field_data["model_id"]).reshape(-1)
        if codes.dtype.kind not in "iu" or codes.size > 64 or np.any((codes < 32) | (codes > 126)):
            raise FieldError(f"{path}: field data model_id is not a short ASCII text")
        model_id = bytes(codes.astype(np.uint8)).decode("ascii")
    elif skin is not None and mesh.points.shape == skin.points.shape and np.allclose(
        mesh.points, skin.points, rtol=0.0, atol=1e-6
    ):
        model_id = skin.model_id
    else:
        raise FieldError(f"{path} has no field data 'model_id' and its points are not the bases' skin nodes; "
                         "write fields with hood_decomp.io.fields.write_field")
    noise = mesh.field_data.get("noise_rms")
    noise_rms = float("nan")
    if noise is not None:
        noise = np.asarray(noise).reshape(-1)
        if noise.size != 1 or noise.dtype.kind not in "fiu" or np.isinf(noise[0]) or noise[0] < 0:
            raise FieldError(f"{path}: field data noise_rms must be one number >= 0 mm (or NaN: unknown)")
        noise_rms = float(noise[0])
    coverage = float(np.isfinite(values).mean()) if values.size else 0.0
    vectors = mesh.point_data.get("displacement")
    if vectors is not None:
        vectors = _plausible(vectors, path, "displacement")
        if vectors.shape != (len(values), 3):
            raise FieldError(f"{path}: displacement has shape {vectors.shape}, expected ({len(values)}, 3)")
    field = DisplacementField(model_id=model_id, normal_displacement=values, coverage=coverage, noise_rms=noise_rms,
                              error_model=_read_error_model(mesh, path, values.size),
                              displacement=vectors if _states_3d(mesh, path, vectors) else None)
    if field.displacement is not None:
        try:
            field.checked_displacement(None if skin is None else skin.normals)
        except FieldError as error:
            raise FieldError(f"{path}: {error}") from None
    return field, vectors


def _states_3d(mesh: meshio.Mesh, path: Path, vectors: np.ndarray | None) -> bool:
    """Whether the file states its point data ``displacement`` is the field's own 3D displacement (FieldData
    ``displacement_3d``: one value, 0 or 1; absent in files written before it: no)."""
    flag = mesh.field_data.get("displacement_3d")
    if flag is None:
        return False
    flag = np.asarray(flag).reshape(-1)
    if flag.size != 1 or flag.dtype.kind not in "fiu" or flag[0] not in (0, 1):
        raise FieldError(f"{path}: field data displacement_3d must be one value, 0 or 1")
    if flag[0] == 1 and vectors is None:
        raise FieldError(f"{path} states a 3D displacement (displacement_3d 1) but has no point data 'displacement'")
    return bool(flag[0] == 1)


#: largest displacement (mm) a field may hold: the method models sheet-metal deviations of a few millimetres (the
#: hood's parameter ranges are +-1 mm; its largest response over the full factorial, gravity included, is 4.05 mm on
#: the coarse hood); 100 mm is 25 times that, and anything beyond is not a deviation of the part but a unit error, a
#: wrong file or a broken registration
MAX_ABS_MM = 100.0


def _plausible(values: object, path: Path, name: str) -> np.ndarray:
    """Point data ``name`` as floats: numbers, finite or NaN (unknown), at most :data:`MAX_ABS_MM` in magnitude."""
    array = np.asarray(values)
    if array.dtype.kind not in "fiu":
        raise FieldError(f"{path}: point data {name!r} holds {array.dtype}, expected numbers")
    array = array.astype(float)
    if np.any(np.isinf(array)):
        raise FieldError(f"{path}: point data {name!r} holds infinite values (NaN marks unknown nodes)")
    largest = float(np.nanmax(np.abs(array))) if np.any(np.isfinite(array)) else 0.0
    if largest > MAX_ABS_MM:
        raise FieldError(f"{path}: point data {name!r} reaches {largest:.3g} mm; a field beyond {MAX_ABS_MM:g} mm is "
                         "not a deviation of the part (unit error, wrong file?)")
    return array


def read_vtu(path: Path, error: type[HoodDecompError]) -> meshio.Mesh:
    """meshio's .vtu reader with every failure as ``error`` naming the file. Its format reader is called directly:
    ``meshio.read`` prints the reader's error on stdout and ends the process with ``sys.exit(1)`` for a file it
    cannot read, which would bypass the command line's one-line errors."""
    import meshio

    try:  # meshio takes a name: it gets the descriptor's, so it reads the file checked here (never a FIFO)
        handle = open_regular(path, error, ".vtu file")
    except OSError as failure:
        raise error(f"cannot open {path}: {failure.strerror}") from failure
    with handle:
        try:
            return meshio.vtu.read(descriptor_path(handle, path))
        except (Exception, SystemExit) as failure:  # any failure of a foreign reader means a bad file
            text = " ".join(str(failure).split())[:200] or type(failure).__name__
            raise error(f"cannot read {path} as a .vtu file: {text}") from failure
