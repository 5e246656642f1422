"""Model mesh files: .vtu via meshio, and the shell mesh of an ABAQUS/CalculiX .inp deck.

A .vtu model mesh has points (n, 3) mm, quad cells and cell data ``part`` (int, index into the model.yaml part list).
Field files (skin displacement fields) are :mod:`hood_decomp.io.fields`.
"""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np

from hood_decomp.errors import MeshError
from hood_decomp.io.fields import read_vtu
from hood_decomp.io.small_files import open_regular

#: shell element types of an .inp deck and their node counts; the first 4 nodes are the corners
INP_SHELLS = {"S4": 4, "S4R": 4, "S4R5": 4, "M3D4": 4, "S8": 8, "S8R": 8, "M3D8": 8, "M3D8R": 8}


def write_mesh(path: str | Path, nodes: np.ndarray, cells: np.ndarray, cell_part: np.ndarray) -> None:
    """Write a quad shell mesh: nodes (n, 3) mm, cells (E, 4), cell_part (E,) int."""
    mesh = meshio.Mesh(
        points=np.asarray(nodes, dtype=float),
        cells=[("quad", np.asarray(cells, dtype=np.int64))],
        cell_data={"part": [np.asarray(cell_part, dtype=np.int32)]},
    )
    mesh.write(str(path), binary=True)


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a quad shell mesh: nodes (n, 3) mm, cells (E, 4) int64, cell_part (E,) int64. Raises MeshError."""
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"mesh file {path} does not exist")
    if path.suffix.lower() != ".vtu":
        raise MeshError(f"mesh {path}: expected a .vtu mesh (or an .inp deck), found {path.suffix or 'no suffix'!r}")
    mesh = read_vtu(path, MeshError)
    blocks = [block for block in mesh.cells if block.type == "quad"]
    others = sorted({block.type for block in mesh.cells} - {"quad"})
    if not blocks or others:
        raise MeshError(f"mesh {path}: expected quad cells only, found {[b.type for b in mesh.cells]}")
    if "part" not in mesh.cell_data:
        raise MeshError(f"mesh {path}: cell data 'part' (part index per cell) is missing")
    cells = np.concatenate([block.data for block in blocks]).astype(np.int64)
    part = np.concatenate(
        [data for data, block in zip(mesh.cell_data["part"], mesh.cells, strict=True) if block.type == "quad"]
    ).astype(np.int64).ravel()
    nodes = np.asarray(mesh.points, dtype=float)
    if nodes.shape[1] == 2:
        nodes = np.column_stack([nodes, np.zeros(len(nodes))])
    return nodes, cells, part


def read_inp_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Read the shell mesh of an ABAQUS/CalculiX deck: ``*NODE`` lines and 4- or 8-node shell ``*ELEMENT`` blocks
    (:data:`INP_SHELLS`) with ``ELSET=`` naming the part.

    The cells are the elements' corners (first 4 nodes); nodes used only as mid-side nodes of 8-node shells (as in
    the decks :func:`hood_decomp.core.fe.calculix.write_deck` writes) are not mesh nodes. Returns nodes (n, 3) mm in
    node-id order, cells (E, 4) 0-based in element-id order, and the ELSET name per cell. Other keywords are ignored.
    Raises MeshError.
    """
    path = Path(path)
    if not path.exists():  # anything else that is not a regular file is named by open_regular
        raise MeshError(f"mesh file {path} does not exist")
    try:
        with open_regular(path, MeshError, "mesh file") as handle:
            text = handle.read().decode("utf-8")
    except OSError as error:
        raise MeshError(f"cannot read mesh file {path}: {error.strerror}") from error
    except UnicodeDecodeError as error:
        raise MeshError(f"{path}: not a text deck (byte {error.start} is not UTF-8)") from error
    node_ids, coords, elements, midside = [], [], [], set()
    block, elset, size = None, "", 0
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("**"):
            continue
        if line.startswith("*"):
            options = {k.strip().upper(): v.strip() for k, _, v in (o.partition("=") for o in line.split(",")[1:])}
            keyword = line.split(",")[0].strip().upper()
            block = None
            if keyword == "*NODE":
                block = "node"
            elif keyword == "*ELEMENT":
                kind = options.get("TYPE", "").upper()
                if kind not in INP_SHELLS:
                    raise MeshError(f"{path}:{number}: element type {kind!r} not supported (expected one of "
                                    f"{sorted(INP_SHELLS)})")
                block, elset, size = "element", options.get("ELSET", ""), INP_SHELLS[kind]
                if not elset:
                    raise MeshError(f"{path}:{number}: *ELEMENT needs ELSET= naming the part")
            continue
        values = [v for v in line.split(",") if v.strip()]
        try:
            if block == "node":
                node_ids.append(int(values[0]))
                coords.append([float(v) for v in values[1:4]] + [0.0] * (4 - len(values)))
            elif block == "element":
                if len(values) < 1 + size:
                    raise MeshError(f"{path}:{number}: expected an element id and {size} nodes, got {line!r}")
                elements.append((int(values[0]), [int(v) for v in values[1:5]], elset))
                midside.update(int(v) for v in values[5:1 + size])
        except (ValueError, IndexError) as error:
            raise MeshError(f"{path}:{number}: cannot read {line!r}: {error}") from error
    if not node_ids or not elements:
        raise MeshError(f"{path}: expected *NODE and *ELEMENT blocks, found {len(node_ids)} nodes, "
                        f"{len(elements)} elements")
    elements.sort(key=lambda item: item[0])
    connectivity = np.asarray([e[1] for e in elements])
    only_midside = np.setdiff1d(np.fromiter(midside, dtype=np.int64, count=len(midside)), connectivity)
    order = np.argsort(node_ids)
    order = order[~np.isin(np.asarray(node_ids)[order], only_midside)]
    ids = np.asarray(node_ids)[order]
    nodes = np.asarray(coords, dtype=float)[order]
    cells = np.searchsorted(ids, connectivity)
    if np.any(cells >= len(ids)) or np.any(ids[np.minimum(cells, len(ids) - 1)] != connectivity):
        raise MeshError(f"{path}: elements reference undefined nodes")
    return nodes, cells.astype(np.int64), [e[2] for e in elements]
