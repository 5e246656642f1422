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
from hood_decomp.errors import FieldError


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
    try:
        mesh = meshio.read(path, file_format="vtu")
    except Exception as error:  # meshio raises many types for a corrupt file
        raise FieldError(f"cannot read field file {path}: {error}") from error
    if "normal_displacement" not in mesh.point_data:
        raise FieldError(f"{path} has no point data 'normal_displacement' (found {sorted(mesh.point_data)})")
    values = np.asarray(mesh.point_data["normal_displacement"], dtype=float).reshape(-1)
    if "model_id" in mesh.field_data:
        model_id = bytes(np.asarray(mesh.field_data["model_id"], dtype=np.uint8).reshape(-1)).decode("ascii")
    elif skin is not None and mesh.points.shape == skin.points.shape and np.allclose(
        mesh.points, skin.points, rtol=0.0, atol=1e-6
    ):
        model_id = skin.model_id
    else:
        raise FieldError(f"{path} has no field data 'model_id' and its points are not the bases' skin nodes; "
                         "write fields with hood_decomp.io.fields.write_field")
    noise = mesh.field_data.get("noise_rms")
    noise_rms = float(np.asarray(noise).reshape(-1)[0]) if noise is not None else float("nan")
    coverage = float(np.isfinite(values).mean()) if values.size else 0.0
    vectors = mesh.point_data.get("displacement")
    field = DisplacementField(model_id=model_id, normal_displacement=values, coverage=coverage, noise_rms=noise_rms)
    return field, None if vectors is None else np.asarray(vectors, dtype=float)
