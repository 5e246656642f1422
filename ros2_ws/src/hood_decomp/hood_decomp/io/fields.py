"""Field files: a displacement field as a ``.vtu`` on the visible skin.

Layout: points = skin node positions (N, 3) mm, triangle cells = skin triangles, point data ``normal_displacement``
(N,) mm (NaN where unknown) and, when known, ``displacement`` (N, 3) mm. VTK FieldData carries ``model_id`` (UInt8
ASCII codes), ``coverage`` and ``noise_rms`` (mm, NaN when unknown). meshio reads FieldData but does not write it,
so the writer adds the FieldData element to the XML meshio wrote; ParaView shows it as field data.
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import escape

import meshio
import numpy as np

from hood_decomp.core.types import DisplacementField, SkinSurface
from hood_decomp.errors import FieldError, HoodDecompError


def _field_data_xml(model_id: str, coverage: float, noise_rms: float) -> str:
    codes = " ".join(str(b) for b in model_id.encode("ascii"))
    return (
        "<FieldData>\n"
        f'<DataArray type="UInt8" Name="model_id" NumberOfTuples="{len(model_id)}" format="ascii">{codes}</DataArray>\n'
        f'<DataArray type="Float64" Name="coverage" NumberOfTuples="1" format="ascii">{coverage!r}</DataArray>\n'
        f'<DataArray type="Float64" Name="noise_rms" NumberOfTuples="1" format="ascii">{noise_rms!r}</DataArray>\n'
        "</FieldData>\n"
    )


def write_field(
    path: str | Path, skin: SkinSurface, field: DisplacementField, displacement: np.ndarray | None = None
) -> None:
    """Write ``field`` on ``skin`` to ``path`` (.vtu). displacement: optional (N, 3) mm; default normal x value."""
    if field.model_id != skin.model_id:
        raise FieldError(f"field model_id {field.model_id!r} differs from the skin's {skin.model_id!r}")
    values = np.asarray(field.normal_displacement, dtype=float)
    if values.shape != (skin.n_nodes,):
        raise FieldError(f"field has shape {values.shape}, expected ({skin.n_nodes},)")
    vectors = field.vectors(skin.normals) if displacement is None else np.asarray(displacement, dtype=float)
    if vectors.shape != (skin.n_nodes, 3):
        raise FieldError(f"displacement has shape {vectors.shape}, expected ({skin.n_nodes}, 3)")
    mesh = meshio.Mesh(
        skin.points,
        [("triangle", np.asarray(skin.triangles))],
        point_data={"normal_displacement": values, "displacement": vectors},
    )
    path = Path(path)
    meshio.write(path, mesh, file_format="vtu")
    text = path.read_text()
    marker = "<UnstructuredGrid>\n"
    extra = _field_data_xml(escape(field.model_id), float(field.coverage), float(field.noise_rms))
    path.write_text(text.replace(marker, marker + extra, 1))


def read_field(path: str | Path, skin: SkinSurface | None = None) -> tuple[DisplacementField, np.ndarray | None]:
    """Read a field file; return ``(DisplacementField, displacement (N, 3) mm or None)``.

    A file without ``model_id`` (e.g. written by a plain ``meshio.write``, which drops VTU FieldData) is accepted only
    when ``skin`` is given and the file's points are the skin's nodes in the skin's order (within 1e-6 mm); it then
    gets the skin's model_id. Raises FieldError when the file is missing or unreadable, has no
    ``normal_displacement``, or has no ``model_id`` and no matching skin. Coverage is recomputed from the values; a
    missing ``noise_rms`` is NaN.
    """
    path = Path(path)
    if not path.is_file():
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
    field = DisplacementField(model_id=model_id, normal_displacement=values, coverage=coverage, noise_rms=noise_rms)
    return field, vectors


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
    try:
        return meshio.vtu.read(str(path))
    except (Exception, SystemExit) as failure:  # any failure of a foreign reader means a bad file
        text = " ".join(str(failure).split())[:200] or type(failure).__name__
        raise error(f"cannot read {path} as a .vtu file: {text}") from failure
