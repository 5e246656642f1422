"""The part model: shell mesh, parts with thicknesses, mechanical boundaries and adjustable parameters.

A :class:`PartModel` is what ``model.yaml`` plus the mesh file describe (see :mod:`hood_decomp.io.model_files`).
Geometry is a quadrilateral shell mesh: ``nodes`` (n, 3) mm and ``cells`` (E, 4) node indices, each cell belonging to
one :class:`Part` (a sheet with a thickness). The visible skin is the set of nodes of the skin part's cells, in
ascending node index order: that order is the node order of every per-node array of the method.

Boundaries act on node patches (position + radius, or an explicit node set):
- ``fixed``: the listed translations of every patch node are held at 0.
- ``prescribed``: the listed translations are held at a commanded value (0 unless a parameter or a setting moves them).
- ``unilateral``: a rubber pad, compression-only springs along ``axis`` spread over the patch (area weighted), total
  stiffness ``stiffness`` N/mm and ``preload`` mm; its commanded position is an adjustable parameter.
- ``force``: a total force ``force`` N along ``axis`` spread over the patch (area weighted), e.g. a gas spring.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hood_decomp.core.types import SkinSurface, fingerprint
from hood_decomp.errors import ModelError

BOUNDARY_KINDS = ("fixed", "prescribed", "unilateral", "force")
#: how a lifted unilateral boundary's parameter state is reported (types.Ensemble.effective): "effective" (the part's
#: position there, this project's default) or "commanded" (the commanded position, the paper's convention, section 4)
PARAMETER_STATES = ("effective", "commanded")
AXES = {"x": 0, "y": 1, "z": 2}
#: gravity of a model that states none, mm/s^2 (-Z)
GRAVITY = (0.0, 0.0, -9810.0)


@dataclass(frozen=True)
class Material:
    """Linear elastic isotropic material. E, MPa; nu; density, t/mm^3 (so that mass x mm/s^2 gives N). The defaults
    are steel, the material of a model that states none."""

    E: float = 210000.0
    nu: float = 0.3
    density: float = 7.85e-9


@dataclass(frozen=True)
class Part:
    """One sheet of the assembly: a name and a shell thickness (mm)."""

    name: str
    thickness: float


@dataclass(frozen=True)
class Patch:
    """Node selection of a boundary.

    Either ``nodes`` (explicit node indices) or ``center`` (3,) mm + ``radius`` mm (3D distance). ``parts`` restricts
    the selection to nodes of those parts' cells (empty: all parts); ``exclude_parts`` removes nodes that also belong
    to those parts (e.g. the skin, so that a boundary on the inner structure never grabs a hem node).
    """

    center: tuple[float, float, float] | None = None
    radius: float = 0.0
    nodes: tuple[int, ...] = ()
    parts: tuple[str, ...] = ()
    exclude_parts: tuple[str, ...] = ()


@dataclass(frozen=True)
class Boundary:
    """A mechanical boundary.

    kind: one of ``fixed``, ``prescribed``, ``unilateral``, ``force``.
    dofs: constrained translations for fixed/prescribed, a subset of ("x", "y", "z").
    axis: (3,) unit vector for unilateral (the direction the pad pushes the part) and force boundaries.
    force: total force, N (force boundaries). stiffness: total pad stiffness, N/mm; preload: pad preload, mm.
    """

    name: str
    kind: str
    patch: Patch
    dofs: tuple[str, ...] = ()
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    force: float = 0.0
    stiffness: float = 0.0
    preload: float = 0.0


@dataclass(frozen=True)
class Parameter:
    """An adjustable parameter a_i in [lower, upper] mm (paper eq. 1): a boundary and a direction ("x", "y", "z")."""

    label: str
    boundary: str
    direction: str
    lower: float
    upper: float


@dataclass(frozen=True)
class PartModel:
    """A complete part model.

    nodes: (n, 3) float64 mm. cells: (E, 4) int64 quads (counter-clockwise seen from the skin's outside for the skin).
    cell_part: (E,) int64 index into ``parts``. gravity: (3,) mm/s^2. skin_part: name of the visible outer skin part.
    Parameters are stored bilateral (prescribed boundaries) first, then unilateral ones. parameter_states: one of
    ``PARAMETER_STATES``, the state an ensemble records for a lifted unilateral boundary (its lifted flag is kept
    either way).
    """

    name: str
    nodes: np.ndarray
    cells: np.ndarray
    cell_part: np.ndarray
    parts: tuple[Part, ...]
    material: Material
    boundaries: tuple[Boundary, ...]
    parameters: tuple[Parameter, ...]
    skin_part: str
    gravity: np.ndarray = field(default_factory=lambda: np.array(GRAVITY))
    parameter_states: str = "effective"

    def part_index(self, name: str) -> int:
        for index, part in enumerate(self.parts):
            if part.name == name:
                return index
        raise ModelError(f"unknown part {name!r}; the model has {[p.name for p in self.parts]}")

    def boundary(self, name: str) -> Boundary:
        for boundary in self.boundaries:
            if boundary.name == name:
                return boundary
        raise ModelError(f"unknown boundary {name!r}; the model has {[b.name for b in self.boundaries]}")

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter labels, bilateral first then unilateral (the order of ReducedModel and Ensemble)."""
        return tuple(p.label for p in self.parameters)

    @property
    def bilateral(self) -> tuple[Parameter, ...]:
        return tuple(p for p in self.parameters if self.boundary(p.boundary).kind != "unilateral")

    @property
    def unilateral(self) -> tuple[Parameter, ...]:
        return tuple(p for p in self.parameters if self.boundary(p.boundary).kind == "unilateral")

    @property
    def lower(self) -> np.ndarray:
        return np.array([p.lower for p in self.parameters], dtype=float)

    @property
    def upper(self) -> np.ndarray:
        return np.array([p.upper for p in self.parameters], dtype=float)

    @property
    def skin_nodes(self) -> np.ndarray:
        """(N,) int64 node indices of the visible skin, ascending: the method's node order."""
        skin_cells = self.cells[self.cell_part == self.part_index(self.skin_part)]
        return np.unique(skin_cells)

    @property
    def model_id(self) -> str:
        """Fingerprint of the mesh and the skin node order."""
        return fingerprint(self.nodes, self.cells, self.skin_nodes)


def nodal_areas(nodes: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Tributary area per node, (n,) mm^2: a quarter of each adjacent quad's area."""
    p = nodes[cells]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1]), axis=1)
    out = np.zeros(len(nodes))
    np.add.at(out, cells.ravel(), np.repeat(area / 4.0, 4))
    return out


def patch_nodes(model: PartModel, boundary: Boundary) -> np.ndarray:
    """Node indices (ascending) selected by a boundary's patch. Raises ModelError when the patch selects nothing."""
    patch = boundary.patch
    n = len(model.nodes)
    allowed = np.ones(n, dtype=bool)
    if patch.parts:
        allowed[:] = False
        for name in patch.parts:
            allowed[model.cells[model.cell_part == model.part_index(name)].ravel()] = True
    for name in patch.exclude_parts:
        allowed[model.cells[model.cell_part == model.part_index(name)].ravel()] = False
    if patch.nodes:
        chosen = np.asarray(patch.nodes, dtype=np.int64)
        if chosen.min() < 0 or chosen.max() >= n:
            raise ModelError(f"boundary {boundary.name!r}: node set has indices outside 0..{n - 1}")
        selected = chosen[allowed[chosen]]
    elif patch.center is not None:
        distance = np.linalg.norm(model.nodes - np.asarray(patch.center, dtype=float), axis=1)
        selected = np.flatnonzero((distance <= patch.radius) & allowed)
    else:
        raise ModelError(f"boundary {boundary.name!r}: patch needs 'center' + 'radius' or 'nodes'")
    if selected.size == 0:
        where = f"center {patch.center} radius {patch.radius} mm" if patch.center is not None else "its node set"
        raise ModelError(
            f"boundary {boundary.name!r}: patch selects no nodes ({where}, parts {list(patch.parts) or 'all'})"
        )
    return np.unique(selected)


def patch_weights(model: PartModel, nodes: np.ndarray) -> np.ndarray:
    """Area weights (summing to 1) of patch nodes, used to spread pad stiffness and forces."""
    area = nodal_areas(model.nodes, model.cells)[nodes]
    return area / area.sum()


def skin_surface(model: PartModel) -> SkinSurface:
    """The visible skin: points, outward (+Z-ish) unit normals, triangles (each skin quad split in two)."""
    skin = model.skin_nodes
    local = np.full(len(model.nodes), -1, dtype=np.int64)
    local[skin] = np.arange(len(skin))
    quads = local[model.cells[model.cell_part == model.part_index(model.skin_part)]]
    triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    points = model.nodes[skin]
    p = points[quads]
    quad_normal = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])  # length = 2 x area: area weighting
    normals = np.zeros_like(points)
    for corner in range(4):
        np.add.at(normals, quads[:, corner], quad_normal)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    if normals[:, 2].mean() < 0:  # outward means towards the scanner above the part
        normals = -normals
        triangles = triangles[:, ::-1]
    return SkinSurface(points=points, normals=normals, triangles=triangles.astype(np.int64), model_id=model.model_id)


def validate_model(model: PartModel) -> None:
    """Check a model and raise ModelError naming the problem (expected vs found).

    Checks: mesh shapes, cell indices, degenerate cells, thicknesses, material, boundary kinds and patches, parameter
    references and ranges, one connected structure. Rigid-body freedom is checked by the solver assembly
    (:func:`hood_decomp.core.fe.solver.rigid_body_check`), which knows the constrained DOFs.
    """
    nodes, cells = model.nodes, model.cells
    if nodes.ndim != 2 or nodes.shape[1] != 3 or not np.all(np.isfinite(nodes)):
        raise ModelError(f"nodes must be a finite (n, 3) array, got shape {nodes.shape}")
    if cells.ndim != 2 or cells.shape[1] != 4:
        raise ModelError(f"cells must be an (E, 4) quad array, got shape {cells.shape}")
    if cells.size and (cells.min() < 0 or cells.max() >= len(nodes)):
        raise ModelError(f"cells reference nodes outside 0..{len(nodes) - 1}")
    if model.cell_part.shape != (len(cells),) or (
        len(cells) and (model.cell_part.min() < 0 or model.cell_part.max() >= len(model.parts))
    ):
        raise ModelError(f"cell_part must be ({len(cells)},) indices into {len(model.parts)} parts")
    for part in model.parts:
        if part.thickness is None or not np.isfinite(part.thickness) or part.thickness <= 0:
            raise ModelError(f"part {part.name!r}: thickness must be a positive number of mm, got {part.thickness}")
    model.part_index(model.skin_part)
    if model.parameter_states not in PARAMETER_STATES:
        raise ModelError(f"parameter_states must be one of {PARAMETER_STATES}, got {model.parameter_states!r}")
    material = model.material
    if not (material.E > 0 and -1.0 < material.nu < 0.5 and material.density >= 0):
        raise ModelError(f"material must have E > 0, -1 < nu < 0.5, density >= 0, got {material}")
    _check_cells(nodes, cells)
    _check_connected(model)
    names = set()
    for boundary in model.boundaries:
        if boundary.name in names:
            raise ModelError(f"boundary name {boundary.name!r} used twice")
        names.add(boundary.name)
        if boundary.kind not in BOUNDARY_KINDS:
            raise ModelError(f"boundary {boundary.name!r}: kind must be one of {BOUNDARY_KINDS}, got {boundary.kind!r}")
        bad = [d for d in boundary.dofs if d not in AXES]
        if bad:
            raise ModelError(f"boundary {boundary.name!r}: dofs must be among x, y, z, got {bad}")
        if boundary.kind in ("fixed", "prescribed") and not boundary.dofs:
            raise ModelError(f"boundary {boundary.name!r}: a {boundary.kind} boundary needs dofs (x, y and/or z)")
        if boundary.kind in ("unilateral", "force") and not np.isclose(np.linalg.norm(boundary.axis), 1.0, atol=1e-6):
            raise ModelError(f"boundary {boundary.name!r}: axis must be a unit vector, got {boundary.axis}")
        if boundary.kind == "unilateral" and not boundary.stiffness > 0:
            raise ModelError(f"boundary {boundary.name!r}: pad stiffness must be > 0 N/mm, got {boundary.stiffness}")
        for part in boundary.patch.parts + boundary.patch.exclude_parts:
            model.part_index(part)
        patch_nodes(model, boundary)
    labels = set()
    for parameter in model.parameters:
        if parameter.label in labels:
            raise ModelError(f"parameter label {parameter.label!r} used twice")
        labels.add(parameter.label)
        if parameter.boundary not in names:
            raise ModelError(
                f"parameter {parameter.label!r}: unknown boundary {parameter.boundary!r}; known: {sorted(names)}"
            )
        boundary = model.boundary(parameter.boundary)
        if parameter.direction not in AXES:
            raise ModelError(f"parameter {parameter.label!r}: direction must be x, y or z, got {parameter.direction!r}")
        if boundary.kind == "prescribed" and parameter.direction not in boundary.dofs:
            raise ModelError(
                f"parameter {parameter.label!r}: direction {parameter.direction!r} is not a dof of boundary "
                f"{boundary.name!r} (dofs {list(boundary.dofs)})"
            )
        if boundary.kind not in ("prescribed", "unilateral"):
            raise ModelError(
                f"parameter {parameter.label!r}: boundary {boundary.name!r} is {boundary.kind}; "
                "a parameter needs a prescribed or unilateral boundary"
            )
        if not (np.isfinite(parameter.lower) and np.isfinite(parameter.upper)) or parameter.lower > parameter.upper:
            raise ModelError(
                f"parameter {parameter.label!r}: range needs min <= max, got [{parameter.lower}, {parameter.upper}]"
            )
    for boundary in model.boundaries:
        count = sum(p.boundary == boundary.name for p in model.parameters)
        if boundary.kind == "unilateral" and count != 1:
            raise ModelError(
                f"boundary {boundary.name!r}: a unilateral pad needs exactly one parameter (its commanded position), "
                f"found {count}"
            )
    kinds = [model.boundary(p.boundary).kind == "unilateral" for p in model.parameters]
    if kinds != sorted(kinds):
        raise ModelError(f"parameters must list bilateral ones before unilateral ones, got {list(model.names)}")


def _check_cells(nodes: np.ndarray, cells: np.ndarray) -> None:
    repeated = (np.sort(cells, axis=1)[:, 1:] == np.sort(cells, axis=1)[:, :-1]).any(axis=1)
    p = nodes[cells]
    edges = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2)
    area = 0.5 * np.linalg.norm(np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1]), axis=1)
    scale = np.maximum(edges.max(axis=1), 1e-300)
    # the two triangles of each split must both have area, else a diagonal split degenerates
    tri_a = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    tri_b = 0.5 * np.linalg.norm(np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]), axis=1)
    tri_c = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 3] - p[:, 0]), axis=1)
    tri_d = 0.5 * np.linalg.norm(np.cross(p[:, 2] - p[:, 1], p[:, 3] - p[:, 1]), axis=1)
    smallest = np.min([tri_a, tri_b, tri_c, tri_d], axis=0)
    bad = np.flatnonzero(repeated | (area <= 1e-6 * scale**2) | (smallest <= 1e-4 * scale**2))
    if bad.size:
        raise ModelError(
            f"degenerate element(s) {bad[:5].tolist()} (repeated nodes or near-zero area; expected a proper quad)"
        )


def _check_connected(model: PartModel) -> None:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    cells = model.cells
    used = np.unique(cells)
    rows = np.concatenate([cells[:, i] for i in range(4)])
    cols = np.concatenate([cells[:, (i + 1) % 4] for i in range(4)])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(model.nodes),) * 2)
    _, labels = connected_components(graph, directed=False)
    components = np.unique(labels[used])
    if len(components) > 1:
        main = np.bincount(labels[used]).argmax()
        loose_cells = np.flatnonzero(labels[cells[:, 0]] != main)
        loose_parts = sorted({model.parts[i].name for i in model.cell_part[loose_cells]})
        raise ModelError(
            f"the mesh is {len(components)} unconnected pieces, expected one joined structure; "
            f"parts not joined to the rest: {loose_parts}"
        )
