"""The embedded linear shell solver: assembly, one factorisation, responses, and the reduced model.

The part is linear except for the unilateral pads, so the stiffness K (6 DOF per node) is assembled once from
:mod:`hood_decomp.core.fe.shell`, the constrained translations (fixed and prescribed boundaries) are eliminated, K_ff is
factorised once (CHOLMOD when ``sksparse`` is importable, else SuperLU), and every response the method needs is a
pair of triangular solves with that factor:

- the load response (gravity + force boundaries, all prescribed values 0),
- the response to a unit (1 mm) motion of any boundary DOF (elimination for constrained DOFs; for a direction the
  boundary does not constrain, the patch force that moves the patch rigidly by 1 mm),
- the response to a unit (1 N) pad spring force.

:func:`reduce_model` condenses these to a :class:`~hood_decomp.core.types.ReducedModel` (skin normal and 3D responses
plus pad compliances); each ensemble member is then a small complementarity problem (:mod:`.contact`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from hood_decomp.core.fe.model import AXES, PartModel, patch_nodes, patch_weights, skin_surface, validate_model
from hood_decomp.core.fe.shell import quad_stiffness
from hood_decomp.core.types import SENSITIVE_ARRAYS, ReducedModel
from hood_decomp.errors import ModelError, SolverError

logger = logging.getLogger(__name__)
#: quads per vectorised element chunk (bounds the (4 x CHUNK, 18, 18) triangle temporaries to ~100 MB each)
CHUNK = 10000
#: pad springs per side of the square lattice that groups a pad's nodes into springs
PAD_LATTICE = 6


def assemble_stiffness(model: PartModel, stiffness_factor: np.ndarray | None = None) -> sp.csr_matrix:
    """Global stiffness (6n, 6n) CSR, N/mm (translations) and N mm/rad (rotations), DOF 6*node + (ux..rz).

    The (Q, 24, 24) quad matrices are computed ``CHUNK`` quads at a time into one COO array, which is converted to CSR
    once (shared entries summed). At the paper's resolution (~300k quads) the COO holds 171M values: 1.4 GB of data
    plus 1.4 GB of int32 indices; with the CSR being formed the assembly peaks near 5 GB, below the factorisation's.
    stiffness_factor: (E,) factor on each quad's matrix, i.e. on its Young's modulus (membrane, bending and drilling
    stiffness are all proportional to E); None: 1 everywhere.
    """
    cells = model.cells
    thickness = np.array([p.thickness for p in model.parts])[model.cell_part]
    factor = np.ones(len(cells)) if stiffness_factor is None else np.asarray(stiffness_factor, dtype=float)
    if factor.shape != (len(cells),) or not np.all(np.isfinite(factor) & (factor > 0)):
        raise ModelError(f"stiffness_factor must hold {len(cells)} positive numbers (one per quad), got {factor.shape}")
    data = np.empty((len(cells), 24, 24))
    for start in range(0, len(cells), CHUNK):
        chunk = slice(start, start + CHUNK)
        data[chunk] = quad_stiffness(model.nodes[cells[chunk]], thickness[chunk], model.material.E, model.material.nu)
        data[chunk] *= factor[chunk, None, None]
        logger.info("assembly %d/%d triangles", 4 * min(start + CHUNK, len(cells)), 4 * len(cells))
    n_dof = 6 * len(model.nodes)
    dofs = (6 * cells[:, :, None] + np.arange(6)).reshape(len(cells), 24).astype(np.int32)
    rows = np.broadcast_to(dofs[:, :, None], data.shape).ravel()
    cols = np.broadcast_to(dofs[:, None, :], data.shape).ravel()
    K = sp.coo_matrix((data.ravel(), (rows, cols)), shape=(n_dof, n_dof)).tocsr()
    del data, rows, cols
    K.eliminate_zeros()  # couplings that cancel exactly
    # tocsr leaves K's arrays as views of buffers sized for the COO (1.8 times nnz here): copy them out.
    return K.copy()


def load_vector(model: PartModel) -> np.ndarray:
    """Gravity (lumped nodal masses) plus force boundaries, (6n,) N."""
    p = model.nodes[model.cells]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1]), axis=1)
    thickness = np.array([part.thickness for part in model.parts])[model.cell_part]
    mass = np.zeros(len(model.nodes))
    np.add.at(mass, model.cells.ravel(), np.repeat(area * thickness * model.material.density / 4.0, 4))
    F = np.zeros((len(model.nodes), 6))
    F[:, :3] = mass[:, None] * np.asarray(model.gravity, dtype=float) + force_boundary_loads(model)
    return F.ravel()


def force_boundary_loads(model: PartModel) -> np.ndarray:
    """Nodal forces (n, 3) N of the force boundaries (gas springs) alone, at their stated force."""
    forces = np.zeros((len(model.nodes), 3))
    for boundary in model.boundaries:
        if boundary.kind == "force":
            nodes = patch_nodes(model, boundary)
            forces[nodes] += boundary.force * patch_weights(model, nodes)[:, None] * np.asarray(boundary.axis)
    return forces


def rigid_body_check(model: PartModel, constrained: np.ndarray) -> None:
    """Raise ModelError naming the free rigid-body motion when the constrained translations do not fix the part.

    constrained: (C,) global DOF indices held by fixed/prescribed boundaries (unilateral pads do not count: they can
    lift off).
    """
    nodes = model.nodes
    center = nodes.mean(axis=0)
    node, axis = np.divmod(constrained, 6)
    if np.any(axis > 2):
        raise ModelError("only translations can be constrained")
    # rigid mode (t, w): u = t + w x (x - c); row of the constrained DOF along axis
    rel = nodes[node] - center
    modes = np.zeros((len(constrained), 6))
    modes[np.arange(len(constrained)), axis] = 1.0
    unit = np.eye(3)[axis]
    scale = max(np.ptp(nodes, axis=0).max(), 1.0)
    modes[:, 3:] = np.cross(rel, unit) / scale  # e_axis . (w x r) = w . (r x e_axis); scaled to mm like translations
    s_full = np.zeros(6)
    if len(constrained):
        _, s, vt = np.linalg.svd(modes, full_matrices=True)
        s_full[: len(s)] = s
    else:
        vt = np.eye(6)
    free = vt[s_full < 1e-8 * max(s_full.max(), 1.0)]
    if len(free) == 0:
        return
    # rotate the free basis so that pure translations come out as such: SVD of its rotation part
    u_rot, s_rot, _ = np.linalg.svd(free[:, 3:], full_matrices=True)
    s_rot = np.concatenate([s_rot, np.zeros(len(free) - len(s_rot))])
    free = u_rot.T @ free
    motions = [_describe_motion(vector[:3], vector[3:] / scale, center, rotation=s > 1e-6)
               for vector, s in zip(free, s_rot, strict=True)]
    raise ModelError(
        f"under-constrained part: the fixed and prescribed boundaries leave {len(free)} free rigid-body motion(s): "
        f"{'; '.join(motions)}; add or extend a fixed/prescribed boundary"
    )


def _describe_motion(t: np.ndarray, w: np.ndarray, center: np.ndarray, rotation: bool) -> str:
    """Readable rigid motion u = t + w x (x - center): a translation or a rotation about an axis line."""
    names = "XYZ"
    if not rotation:
        d = t / np.linalg.norm(t)
        return f"translation along {names[int(np.argmax(np.abs(d)))]} ({d[0]:.2f}, {d[1]:.2f}, {d[2]:.2f})"
    d = w / np.linalg.norm(w)
    point = center + np.cross(w, t) / np.dot(w, w)
    return (f"rotation about {names[int(np.argmax(np.abs(d)))]} (axis ({d[0]:.2f}, {d[1]:.2f}, {d[2]:.2f}) through "
            f"({point[0]:.0f}, {point[1]:.0f}, {point[2]:.0f}) mm)")


@dataclass(frozen=True)
class PadSprings:
    """Pad springs of all unilateral parameters.

    loads: (6n, S) sparse, column s spreads a unit (1 N) spring force over its nodes along the pad axis; its transpose
    maps a displacement to the spring's mean axial displacement z_s (mm). k: (S,) N/mm. preload: (S,) mm.
    pad_of: (S,) index into the unilateral parameters.
    """

    loads: sp.csc_matrix
    k: np.ndarray
    preload: np.ndarray
    pad_of: np.ndarray


def pad_springs(model: PartModel, lattice: int = PAD_LATTICE) -> PadSprings:
    """Group each pad's patch into springs on a ``lattice`` x ``lattice`` grid across the pad axis (1: one spring).

    Each spring acts on the area-weighted mean axial displacement of its nodes and spreads its force with the same
    weights, so the spring set is the same at every mesh resolution once the mesh is finer than the lattice.
    """
    rows, cols, vals, k, preload, pad_of = [], [], [], [], [], []
    for u, parameter in enumerate(model.unilateral):
        boundary = model.boundary(parameter.boundary)
        nodes = patch_nodes(model, boundary)
        weights = patch_weights(model, nodes)
        axis = np.asarray(boundary.axis, dtype=float)
        e1 = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        rel = model.nodes[nodes] - model.nodes[nodes].mean(axis=0)
        extent = max(np.abs(rel @ e1).max(), np.abs(rel @ e2).max(), 1e-9)
        cell = np.floor((np.stack([rel @ e1, rel @ e2], axis=1) / extent + 1.0) * lattice / 2.0001).astype(int)
        _, group = np.unique(cell[:, 0] * (lattice + 1) + cell[:, 1], return_inverse=True)
        for g in range(group.max() + 1):
            members = nodes[group == g]
            w = weights[group == g]
            column = len(k)
            for a in range(3):
                rows.append(6 * members + a)
                cols.append(np.full(len(members), column))
                vals.append(w / w.sum() * axis[a])
            k.append(boundary.stiffness * w.sum())
            preload.append(boundary.preload)
            pad_of.append(u)
    n_dof = 6 * len(model.nodes)
    loads = sp.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_dof, len(k))
    ) if k else sp.csc_matrix((n_dof, 0))
    return PadSprings(loads=loads, k=np.array(k), preload=np.array(preload), pad_of=np.array(pad_of, dtype=np.int64))


class ShellSolver:
    """The factorised embedded solver of one part model. Build it with :func:`build_solver`.

    Attributes: model, K (6n, 6n) CSR, constrained (C,) DOF indices (ascending), free (6n - C,), backend
    ("cholmod" or "splu"), load (6n,) N, pads (PadSprings), timings (dict of seconds).
    """

    def __init__(self, model: PartModel, K: sp.csr_matrix, constrained: np.ndarray, factor, backend: str,
                 timings: dict[str, float], pad_lattice: int = PAD_LATTICE) -> None:
        self.model = model
        self.pad_lattice = pad_lattice
        self.K = K
        self.constrained = constrained
        n_dof = K.shape[0]
        mask = np.ones(n_dof, dtype=bool)
        mask[constrained] = False
        self.free = np.flatnonzero(mask)
        self._factor = factor
        self.backend = backend
        self.load = load_vector(model)
        self.pads = pad_springs(model, pad_lattice)
        self.timings = timings
        self._K_fc = K[self.free][:, constrained].tocsc()
        self._position = np.full(n_dof, -1, dtype=np.int64)
        self._position[constrained] = np.arange(len(constrained))

    @property
    def n_dof(self) -> int:
        return int(self.K.shape[0])

    def solve(self, forces: np.ndarray, prescribed: np.ndarray | None = None) -> np.ndarray:
        """Displacements (6n, k) for nodal forces (6n, k) N and constrained-DOF values (C, k) mm (None: zero)."""
        forces = np.asarray(forces, dtype=float)
        squeeze = forces.ndim == 1
        forces = forces.reshape(self.n_dof, -1)
        rhs = forces[self.free]
        u = np.zeros_like(forces)
        if prescribed is not None:
            prescribed = np.asarray(prescribed, dtype=float).reshape(len(self.constrained), -1)
            rhs = rhs - self._K_fc @ prescribed
            u[self.constrained] = prescribed
        u[self.free] = self.solve_free(rhs)
        return u[:, 0] if squeeze else u

    def solve_free(self, rhs: np.ndarray) -> np.ndarray:
        """K_ff^-1 rhs on the free DOFs, (F,) or (F, k)."""
        out = self._factor(np.ascontiguousarray(rhs))
        if not np.all(np.isfinite(out)):
            raise SolverError("the factorised stiffness gave non-finite displacements (singular structure)")
        return out

    def with_stiffness(self, K: sp.csr_matrix) -> ShellSolver:
        """The same part, boundaries and pads with another stiffness K (6n, 6n), factorised (e.g. a tangent)."""
        start = time.perf_counter()
        factor, backend = _factorise(K[self.free][:, self.free])
        timings = {"factorisation_s": time.perf_counter() - start}
        return ShellSolver(self.model, K, self.constrained, factor, backend, timings, self.pad_lattice)

    def boundary_dofs(self, boundary: str, direction: str) -> np.ndarray:
        """Global DOF indices (translation ``direction`` of every patch node) of a boundary."""
        if direction not in AXES:
            raise ModelError(f"direction must be x, y or z, got {direction!r}")
        nodes = patch_nodes(self.model, self.model.boundary(boundary))
        return 6 * nodes + AXES[direction]

    def boundary_response(self, boundary: str, direction: str) -> np.ndarray:
        """Displacement (6n,) mm for a unit (1 mm) motion of a boundary patch along ``direction``, no loads.

        For a constrained direction (fixed or prescribed boundary) the patch DOFs are moved by elimination. For a
        direction the boundary does not constrain (e.g. a lock's X), the patch is moved rigidly by 1 mm by the patch
        forces that do so (one solve per patch node, Schur complement on the patch), with everything else unchanged.
        """
        dofs = self.boundary_dofs(boundary, direction)
        position = self._position[dofs]
        if np.all(position >= 0):
            prescribed = np.zeros(len(self.constrained))
            prescribed[position] = 1.0
            return self.solve(np.zeros(self.n_dof), prescribed)
        if np.any(position >= 0):
            raise ModelError(f"boundary {boundary!r} direction {direction!r} is only partly constrained")
        unit_loads = sp.csc_matrix((np.ones(len(dofs)), (dofs, np.arange(len(dofs)))), shape=(self.n_dof, len(dofs)))
        U = self.solve(unit_loads.toarray())
        lam = np.linalg.solve(U[dofs], np.ones(len(dofs)))
        return U @ lam

    def force_response(self, boundary: str, direction: str) -> np.ndarray:
        """Displacement (6n,) mm for a unit total force (1 N) spread area-weighted over a boundary patch."""
        nodes = patch_nodes(self.model, self.model.boundary(boundary))
        F = np.zeros((len(self.model.nodes), 6))
        F[nodes, AXES[direction]] = patch_weights(self.model, nodes)
        return self.solve(F.ravel())

    def load_response(self) -> np.ndarray:
        """Displacement (6n,) mm under gravity and the force boundaries, all prescribed values 0, no pad force."""
        return self.solve(self.load)

    def pad_responses(self, block: int = 16) -> np.ndarray:
        """Nodal translations (n, 3, S) mm for a unit (1 N) force of each pad spring (solved ``block`` at a time)."""
        S = self.pads.loads.shape[1]
        out = np.zeros((len(self.model.nodes), 3, S))
        for start in range(0, S, block):
            u = self.solve(self.pads.loads[:, start : start + block].toarray())
            out[:, :, start : start + block] = u.reshape(len(self.model.nodes), 6, -1)[:, :3]
        return out


def constrained_dofs(model: PartModel) -> np.ndarray:
    """Global DOF indices held by fixed and prescribed boundaries, plus all DOFs of nodes no cell uses."""
    held = []
    for boundary in model.boundaries:
        if boundary.kind in ("fixed", "prescribed"):
            nodes = patch_nodes(model, boundary)
            held.extend(6 * nodes + AXES[d] for d in boundary.dofs)
    unused = np.setdiff1d(np.arange(len(model.nodes)), np.unique(model.cells))
    held.append((6 * unused[:, None] + np.arange(6)).ravel())
    return np.unique(np.concatenate(held)) if held else np.zeros(0, dtype=np.int64)


def _factorise(K_ff: sp.spmatrix) -> tuple[Callable[[np.ndarray], np.ndarray], str]:
    try:
        from sksparse.cholmod import CholmodNotPositiveDefiniteError, cholesky
    except ImportError:
        cholesky = None
    if cholesky is not None:
        try:
            factor = cholesky(K_ff.tocsc())
        except CholmodNotPositiveDefiniteError as error:
            raise SolverError(f"stiffness is not positive definite (a mechanism or free part): {error}") from error
        return factor, "cholmod"
    from scipy.sparse.linalg import splu

    try:
        lu = splu(K_ff.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
    except RuntimeError as error:
        raise SolverError(f"stiffness is singular (a mechanism or free part): {error}") from error
    return lu.solve, "splu"


def build_solver(model: PartModel, validate: bool = True, pad_lattice: int = PAD_LATTICE,
                 stiffness_factor: np.ndarray | None = None) -> ShellSolver:
    """Validate the model, assemble K, eliminate constrained DOFs and factorise K_ff once.

    pad_lattice: springs per side of each pad's spring lattice (1 makes every pad a single point spring).
    stiffness_factor: (E,) factor on each quad's Young's modulus (a region of another stiffness); None: 1.
    """
    timings = {}
    start = time.perf_counter()
    if validate:
        validate_model(model)
    constrained = constrained_dofs(model)
    rigid_body_check(model, constrained[constrained % 6 < 3])
    K = assemble_stiffness(model, stiffness_factor)
    timings["assembly_s"] = time.perf_counter() - start
    mask = np.ones(K.shape[0], dtype=bool)
    mask[constrained] = False
    start = time.perf_counter()
    logger.info("factorising %d free DOF", mask.sum())
    factor, backend = _factorise(K[mask][:, mask])
    timings["factorisation_s"] = time.perf_counter() - start
    logger.info("factorised with %s in %.1f s", backend, timings["factorisation_s"])
    return ShellSolver(model, K, constrained, factor, backend, timings, pad_lattice)


def project(model: PartModel, pads: PadSprings, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the reduced model keeps of nodal translations (n, 3, k) mm: the skin normal displacement (N, k), the pad
    springs' mean axial displacement (S, k) and the skin translations (N, 3, k)."""
    skin = model.skin_nodes
    normals = skin_surface(model).normals
    n = len(model.nodes)
    rows = np.arange(6 * n)
    translation = sp.csr_matrix((np.ones(3 * n), (np.arange(3 * n), rows[rows % 6 < 3])), shape=(3 * n, 6 * n))
    loads = (translation @ pads.loads).tocsc()  # (3n, S): spring weights x axis on the translations
    z = np.asarray(loads.T @ columns.reshape(3 * n, -1))
    w3 = columns[skin]
    return np.einsum("nak,na->nk", w3, normals), z, w3


def condense(model: PartModel, pads: PadSprings, columns: np.ndarray, pad_columns: np.ndarray,
             names: tuple[str, ...], n_bilateral: int) -> ReducedModel:
    """Build the ReducedModel from nodal translations (solver independent: embedded or CalculiX).

    columns: (n, 3, 1 + B) mm, the load response then one unit response per bilateral input; pad_columns: (n, 3, S)
    mm, one unit pad spring force response per spring; names: (B + U,) labels; n_bilateral: B.
    """
    return assemble(model, pads, project(model, pads, columns), project(model, pads, pad_columns), names, n_bilateral)


def assemble(model: PartModel, pads: PadSprings, projected: tuple[np.ndarray, np.ndarray, np.ndarray],
             pad_projected: tuple[np.ndarray, np.ndarray, np.ndarray], names: tuple[str, ...],
             n_bilateral: int) -> ReducedModel:
    """The ReducedModel from :func:`project` of the load and unit responses (1 + B columns) and of the pad spring
    responses (S columns): :func:`condense` once the projections are made (they are linear in the translations, so a
    caller may combine projections instead of translations)."""
    w, z, w3 = projected
    g, H, g3 = pad_projected
    return ReducedModel(
        model_id=model.model_id,
        names=tuple(names),
        n_bilateral=n_bilateral,
        w0=w[:, 0].copy(),
        R=w[:, 1:].copy(),
        G=g,
        z0=z[:, 0].copy(),
        Sa=z[:, 1:].copy(),
        H=0.5 * (H + H.T),
        k=pads.k.copy(),
        preload=pads.preload.copy(),
        pad_of=pads.pad_of.copy(),
        w0_3d=w3[:, :, 0].copy(),
        R_3d=w3[:, :, 1:].copy(),
        G_3d=g3.copy(),
        parameter_states=model.parameter_states,
    )


def reduce_model(solver: ShellSolver, extra: Sequence[tuple[str, str]] = ()) -> ReducedModel:
    """Condense the solver to a ReducedModel (see types.ReducedModel for the equations).

    extra: additional bilateral inputs (boundary, direction), e.g. ("hinge_R", "z"), appended after the declared
    bilateral parameters and named "boundary.direction"; each is a unit boundary motion (:meth:`boundary_response`).
    """
    model = solver.model
    columns = [solver.load_response()]
    for parameter in model.bilateral:
        columns.append(solver.boundary_response(parameter.boundary, parameter.direction))
    for boundary, direction in extra:
        columns.append(solver.boundary_response(boundary, direction))
    logger.info("%d load/boundary responses solved", len(columns))
    n = len(model.nodes)
    U = np.stack(columns, axis=1).reshape(n, 6, -1)[:, :3]
    P = solver.pad_responses()
    logger.info("%d pad spring responses solved", P.shape[2])
    names = tuple(p.label for p in model.bilateral) + tuple(f"{b}.{d}" for b, d in extra) + tuple(
        p.label for p in model.unilateral
    )
    return condense(model, solver.pads, U, P, names, len(model.bilateral) + len(extra))


def retarget_pads(reduced: ReducedModel, model: PartModel, pad_lattice: int = PAD_LATTICE) -> ReducedModel:
    """The reduced model of ``model`` from that of a model that differs from it only in its pads' stiffness and
    preload and in ``parameter_states`` (e.g. preset hood-paper from hood): the responses w0, R, G, z0, Sa, H do not
    depend on those, so no solve is needed. The mesh (model_id), parameters and pad spring layout must match; the
    patches themselves are not compared (a moved pad patch needs :func:`reduce_model`). Raises ModelError."""
    if model.model_id != reduced.model_id or model.names != tuple(reduced.names):
        raise ModelError(f"model {model.name!r} (model_id {model.model_id}, parameters {model.names}) is not the mesh "
                         f"and parameters of the reduced model ({reduced.model_id}, {reduced.names})")
    pads = pad_springs(model, pad_lattice)
    if not np.array_equal(pads.pad_of, reduced.pad_of):
        raise ModelError(f"model {model.name!r} has {len(pads.k)} pad springs, the reduced model {len(reduced.k)} "
                         "with another layout: use reduce_model")
    return replace(reduced, k=pads.k, preload=pads.preload, parameter_states=model.parameter_states)


#: linear thermal expansion coefficient of steel, 1/K (the default part material)
STEEL_EXPANSION = 1.2e-5


def physical_responses(solver: ShellSolver, expansion: float = STEEL_EXPANSION) -> dict[str, tuple]:
    """Responses behind the physical factors of a calibration, from the solver's one factorisation (no refactorisation).

    Returns name -> (skin normal (N,), pad spring axial (S,), skin translations (N, 3)) mm:
    - "gas_spring": the force boundaries (gas springs) alone at their stated force (a part of the load response);
    - "thermal": a uniform temperature rise of 1 K. A free part expands by ``expansion`` (x - c) (stress free for the
      shell: uniform in-plane strain, no curvature); the held translations cannot follow, so the response is that
      free expansion plus the response to moving the held DOFs back by it (no other loads).
    """
    model = solver.model
    n = len(model.nodes)
    F = np.zeros((n, 6))
    F[:, :3] = force_boundary_loads(model)
    gas = solver.solve(F.ravel()).reshape(n, 6)[:, :3]
    free = np.zeros((n, 6))
    free[:, :3] = expansion * (model.nodes - model.nodes.mean(axis=0))
    held = solver.solve(np.zeros(solver.n_dof), -free.ravel()[solver.constrained]).reshape(n, 6)[:, :3]
    columns = np.stack([gas, free[:, :3] + held], axis=2)
    w, z, w3 = project(model, solver.pads, columns)
    return {name: (w[:, i], z[:, i], w3[:, :, i]) for i, name in enumerate(("gas_spring", "thermal"))}


def thermal_moves(model: PartModel, expansion: float = STEEL_EXPANSION) -> np.ndarray:
    """The bilateral parameter moves (B,) mm per K that make up the held part of the thermal response.

    Uniform expansion about the centroid is stress free; what deforms the part is that its held patches cannot follow.
    Take the rigid motion (least squares, smallest) that brings the expansion back to zero at the patch centres of
    the held directions that are no parameter (hinge R in x, y, z and hinge L in z on the hood); the expansion plus
    that rigid motion is still stress free, and at the parameters' patch centres it is what the held patches hold
    back: the thermal response is (expansion + rigid motion) - sum_i m_i (unit response of parameter i) plus the
    response to the patches' own small expansion. Returns m (the moves the unit responses take, mm per K; 0 for a
    parameter whose direction is not held). Pure kinematics: any solver's thermal response splits so (on the coarse
    hood the embedded solver's and CalculiX's keep 98 % and 99 % of their RMS in the first two terms), so a calibration
    that corrects the unit responses corrects the thermal response by sum_i m_i (its correction of unit response i).
    """
    centre = model.nodes.mean(axis=0)
    parameters = {(p.boundary, p.direction): i for i, p in enumerate(model.bilateral)}
    fixed_rows, fixed_rhs, moved_rows = [], [], []
    for boundary in model.boundaries:
        if boundary.kind not in ("fixed", "prescribed"):
            continue
        nodes = patch_nodes(model, boundary)
        at = patch_weights(model, nodes) @ model.nodes[nodes] - centre
        for direction in boundary.dofs:
            axis = np.eye(3)[AXES[direction]]
            row = np.concatenate([axis, np.cross(at, axis)])  # rigid (t, omega) -> (t + omega x at)[axis]
            if (boundary.name, direction) in parameters:
                moved_rows.append((parameters[(boundary.name, direction)], row, expansion * at[AXES[direction]]))
            else:
                fixed_rows.append(row)
                fixed_rhs.append(-expansion * at[AXES[direction]])
    rigid = (np.linalg.lstsq(np.array(fixed_rows), np.array(fixed_rhs), rcond=None)[0] if fixed_rows
             else np.zeros(6))
    moves = np.zeros(len(model.bilateral))
    for i, row, free in moved_rows:
        moves[i] = -(free + row @ rigid)
    return moves


#: relative thickness step of the finite-difference thickness sensitivities
THICKNESS_STEP = 0.02


def thickness_groups(model: PartModel) -> dict[str, tuple[str, ...]]:
    """The sheet groups whose thickness a calibration scales together: parts by the name before the first "_"
    (outer_skin, inner_panel, and the four reinf_* together on the hood)."""
    groups: dict[str, list[str]] = {}
    for part in model.parts:
        groups.setdefault(part.name.split("_")[0], []).append(part.name)
    return {name: tuple(members) for name, members in groups.items()}


def thickness_sensitivities(model: PartModel, base: ReducedModel, step: float = THICKNESS_STEP,
                            pad_lattice: int = PAD_LATTICE) -> dict[str, ReducedModel]:
    """Finite-difference sensitivities of the reduced model to each thickness group's scale
    (:func:`thickness_groups`): group -> ReducedModel whose arrays are d(array)/d(log thickness) (one assembly and
    factorisation per group, logged). ``base``: the reduced model of ``model`` itself."""
    out = {}
    for index, (group, members) in enumerate(thickness_groups(model).items(), start=1):
        parts = tuple(replace(p, thickness=p.thickness * (1.0 + step)) if p.name in members else p
                      for p in model.parts)
        logger.info("thickness sensitivity %d/%d: %s (%s)", index, len(thickness_groups(model)), group,
                    ", ".join(members))
        shifted = reduce_model(build_solver(replace(model, parts=parts), validate=False, pad_lattice=pad_lattice))
        scale = 1.0 / np.log1p(step)
        out[group] = replace(base, **{name: (getattr(shifted, name) - getattr(base, name)) * scale
                                      for name in SENSITIVE_ARRAYS})
    return out

