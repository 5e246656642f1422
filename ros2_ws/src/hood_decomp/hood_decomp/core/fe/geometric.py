"""Geometric nonlinearity of the facet shell: Green-Lagrange membrane strains, solved by incremental Newton.

The linear solver (:mod:`.solver`) keeps the small-strain membrane strain eps = sym(grad u). Here each facet triangle
of the mesh (the same four half-weight triangles per quad as :func:`.shell.quad_stiffness`) gets the total-Lagrangian
membrane strain

    eps = sym(grad u_loc) + 1/2 J^T J,     J = d u / d(x, y)   (3 x 2, all three translations, facet frame),

whose membrane force N = t D eps does work on the displacement gradients: the internal force beyond the linear one is

    f_nl(u) = sum_facets A [ B_m^T N_q + G^T N G u ],      N_q = t D (1/2 J^T J),  N = t D eps,

i.e. the initial-stress (geometric) stiffness K_G(N) = int G^T N G dA of the member's own membrane forces (stress
stiffening and softening, the P-delta of the gas springs' in-plane push) plus the membrane stretching of large
deflection. Bending stays the linear DKT (rotations of 1e-3 rad here). A member solves K u + f_nl(u) = F + P f with
the pad contact re-solved exactly (:func:`.contact.solve_lcp`) in every iteration, so load, contact and geometry are
consistent at convergence (:class:`NonlinearSolver`: tangents K + d f_nl/du shared between members). The iteration
with the linear K alone diverges on the hood (the gas spring patches' local membrane action). Opt-in: the linear
path (:func:`.solver.reduce_model`, :func:`.ensemble.solve_members`) does not use this module.

Checked against Euler's buckling load and Timoshenko's beam-column (tests/core/fe/test_geometric.py) and CalculiX
NLGEOM on the coarse hood (benchmarks/bench_nlgeom.py).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from hood_decomp.core.fe.contact import solve_lcp
from hood_decomp.core.fe.ensemble import MemberBlock, contact_summary
from hood_decomp.core.fe.model import PartModel, skin_surface
from hood_decomp.core.fe.shell import QUAD_SPLITS, local_frames
from hood_decomp.core.fe.solver import ShellSolver
from hood_decomp.core.types import Ensemble
from hood_decomp.errors import SolverError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FacetTriangles:
    """The facet triangles of a mesh for the nonlinear membrane terms.

    nodes: (T, 3) node indices. frame: (T, 3, 3) rows (e1, e2, n). grad: (T, 2, 3) 1/mm, d(shape function i)/d(x, y)
    in the facet frame. thickness: (T,) mm. area: (T,) mm^2, the triangle's area x 1/2 (each quad is both diagonal
    splits at half weight). D: (3, 3) MPa, plane-stress elasticity on (xx, yy, 2xy). n_nodes: the mesh's nodes.
    """

    nodes: np.ndarray
    frame: np.ndarray
    grad: np.ndarray
    thickness: np.ndarray
    area: np.ndarray
    D: np.ndarray
    n_nodes: int

    def rows(self, start: int, stop: int) -> FacetTriangles:
        """The facets start:stop (a chunk of the sums over facets)."""
        return FacetTriangles(self.nodes[start:stop], self.frame[start:stop], self.grad[start:stop],
                              self.thickness[start:stop], self.area[start:stop], self.D, self.n_nodes)

    def select(self, index: np.ndarray, weight: np.ndarray) -> FacetTriangles:
        """The facets ``index`` (k,) with their areas scaled by ``weight`` (k,) >= 0: a weighted subset whose sums
        stand for all facets' (hyper-reduction)."""
        return FacetTriangles(self.nodes[index], self.frame[index], self.grad[index], self.thickness[index],
                              self.area[index] * weight, self.D, self.n_nodes)

    @cached_property
    def operator(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """(9T, 3n) CSR on nodal translations (node-major, 3n) and its transpose: rows k T + t, k = 0-5 the
        gradient J (J_x of the 3 global components, then J_y), k = 6-8 the linear membrane strain (xx, yy, 2xy,
        facet frame). One sparse product gathers every facet quantity f_nl needs (component-major: each a contiguous
        (T, m) block) and the transpose scatters the forces back (5x faster than the per-facet gathers for one
        column on the coarse hood)."""
        T, b, c = len(self.nodes), self.grad[:, 0], self.grad[:, 1]  # b, c: (T, 3) over the facet's nodes
        e1, e2 = self.frame[:, 0], self.frame[:, 1]  # (T, 3) over the global components
        both = (3 * self.nodes[:, :, None] + np.arange(3)).reshape(T, 9)  # (node, component) columns

        def outer(g: np.ndarray, e: np.ndarray) -> np.ndarray:
            return (g[:, :, None] * e[:, None]).reshape(T, 9)

        entries = [(3 * a + k, 3 * self.nodes + k, g) for a, g in enumerate((b, c)) for k in range(3)]
        entries += [(6, both, outer(b, e1)), (7, both, outer(c, e2)), (8, both, outer(c, e1) + outer(b, e2))]
        rows = np.concatenate([np.broadcast_to(k * T + np.arange(T)[:, None], col.shape).ravel()
                               for k, col, _ in entries])
        columns = np.concatenate([col.ravel() for _, col, _ in entries])
        values = np.concatenate([value.ravel() for *_, value in entries])
        operator = sp.csr_matrix((values, (rows, columns)), shape=(9 * T, 3 * self.n_nodes))
        return operator, operator.T.tocsr()


def facet_triangles(model: PartModel) -> FacetTriangles:
    """The four half-weight triangles of every quad of ``model`` (as the linear stiffness splits them)."""
    nodes = model.cells[:, QUAD_SPLITS].reshape(-1, 3)
    thickness = np.repeat(np.array([p.thickness for p in model.parts])[model.cell_part], len(QUAD_SPLITS))
    frame, xy = local_frames(model.nodes[nodes])
    x, y = xy[..., 0], xy[..., 1]
    area2 = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    b = np.stack([y[:, 1] - y[:, 2], y[:, 2] - y[:, 0], y[:, 0] - y[:, 1]], axis=1) / area2[:, None]
    c = np.stack([x[:, 2] - x[:, 1], x[:, 0] - x[:, 2], x[:, 1] - x[:, 0]], axis=1) / area2[:, None]
    E, nu = model.material.E, model.material.nu
    D = E / (1 - nu**2) * np.array([[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]])
    return FacetTriangles(nodes, frame, np.stack([b, c], axis=1), thickness, 0.25 * area2, D, len(model.nodes))


def gradients(facets: FacetTriangles, translations: np.ndarray) -> np.ndarray:
    """J (T, 3, 2, m): d(global translation component)/d(facet x, y) of nodal translations (n, 3, m)."""
    return np.einsum("tai,ticm->tcam", facets.grad, translations[facets.nodes], optimize=True)


def _quadratic(J: np.ndarray) -> np.ndarray:
    """1/2 J^T J on (xx, yy, 2xy), (T, 3, m)."""
    return np.stack([0.5 * (J[:, :, 0] ** 2).sum(1), 0.5 * (J[:, :, 1] ** 2).sum(1),
                     (J[:, :, 0] * J[:, :, 1]).sum(1)], axis=1)


def linear_strain(facets: FacetTriangles, J: np.ndarray) -> np.ndarray:
    """The linear membrane strain sym(grad u_loc) (T, 3, m) on (xx, yy, 2xy) of gradients J (T, 3, 2, m)."""
    local = np.einsum("tdc,tcam->tdam", facets.frame[:, :2], J)  # in-plane components' gradients
    return np.stack([local[:, 0, 0], local[:, 1, 1], local[:, 0, 1] + local[:, 1, 0]], axis=1)


def membrane_forces(facets: FacetTriangles, translations: np.ndarray, nonlinear: bool = True) -> np.ndarray:
    """Membrane forces (T, 3, m) N/mm (Nxx, Nyy, Nxy in each facet frame) of nodal translations (n, 3, m) mm;
    ``nonlinear`` adds the Green-Lagrange term 1/2 J^T J to the strain."""
    J = gradients(facets, translations)
    eps = linear_strain(facets, J) + _quadratic(J) if nonlinear else linear_strain(facets, J)
    return facets.thickness[:, None, None] * np.einsum("ij,tjm->tim", facets.D, eps)


def _gather(facets: FacetTriangles, translations: np.ndarray) -> np.ndarray:
    """(9, T, m): J_x (3 components), J_y, the linear strain (xx, yy, 2xy) of nodal translations (n, 3, m)."""
    m = translations.shape[2]
    return (facets.operator[0] @ translations.reshape(-1, m)).reshape(9, len(facets.nodes), m)


def _strain_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The symmetric bilinear Green-Lagrange term (3, T, m) of two gathered fields (9, T, m): 1/2 J_a^T J_b
    symmetrised on (xx, yy, 2xy); with a = b the strain's quadratic part 1/2 J^T J."""
    def dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.einsum("ctm,ctm->tm", x, y)

    if a is b:
        return np.stack([0.5 * dot(a[:3], a[:3]), 0.5 * dot(a[3:6], a[3:6]), dot(a[:3], a[3:6])])
    return 0.5 * np.stack([dot(a[:3], b[:3]), dot(a[3:6], b[3:6]), dot(a[:3], b[3:6]) + dot(a[3:6], b[:3])])


def _stress(facets: FacetTriangles, strain: np.ndarray) -> np.ndarray:
    """A t D strain (3, T, m) N mm of a strain (3, T, m)."""
    return (facets.D @ strain.reshape(3, -1)).reshape(strain.shape) * (facets.area * facets.thickness)[:, None]


def _scatter(facets: FacetTriangles, terms: list[tuple[np.ndarray, np.ndarray]], membrane: np.ndarray | None
             ) -> np.ndarray:
    """(n, 3, m) N: the sum over the facets of G^T (stress) G u over the terms (stress (3, T, m) N mm, u's gathered
    (9, T, m)) plus B_m^T membrane (3, T, m) N mm (None: zero)."""
    _, T, m = terms[0][1].shape
    out = np.zeros((9, T, m))
    for stress, gathered in terms:
        Jx, Jy = gathered[:3], gathered[3:6]
        out[:3] += stress[0] * Jx + stress[2] * Jy  # A (Nxx J_x + Nxy J_y)
        out[3:6] += stress[2] * Jx + stress[1] * Jy  # A (Nxy J_x + Nyy J_y)
    if membrane is not None:
        out[6:] = membrane
    return (facets.operator[1] @ out.reshape(9 * T, m)).reshape(-1, 3, m)


def nonlinear_forces(facets: FacetTriangles, translations: np.ndarray) -> np.ndarray:
    """f_nl (n, 3, m) N: the internal force of nodal translations (n, 3, m) mm beyond the linear stiffness's,
    sum over the facets of A [B_m^T N_q + G^T N G u] (module docstring), through :attr:`FacetTriangles.operator`."""
    u = _gather(facets, translations)
    quadratic = _stress(facets, _strain_product(u, u))  # A N_q
    return _scatter(facets, [(_stress(facets, u[6:]) + quadratic, u)], quadratic)


def nonlinear_force_parts(facets: FacetTriangles, translations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """f_nl's quadratic and cubic parts f2(u, u), f3(u, u, u) (n, 3, m) N of nodal translations (n, 3, m) mm
    (f_nl = f2 + f3 exactly): A [B_m^T N_q + G^T N_L G u] and A G^T N_q G u."""
    u = _gather(facets, translations)
    quadratic = _stress(facets, _strain_product(u, u))
    return _scatter(facets, [(_stress(facets, u[6:]), u)], quadratic), _scatter(facets, [(quadratic, u)], None)


def bilinear_force(facets: FacetTriangles, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """f2(a, b) (n, 3, m) N, the symmetric bilinear form of f_nl's quadratic part (f2(u, u) of
    :func:`nonlinear_force_parts`), column by column of nodal translations a, b (n, 3, m) mm:
    A [B_m^T t D (1/2 J_a^T J_b)_sym + 1/2 G^T (N_L(a) G b + N_L(b) G a)]."""
    a, b = _gather(facets, first), _gather(facets, second)
    return _scatter(facets, [(0.5 * _stress(facets, a[6:]), b), (0.5 * _stress(facets, b[6:]), a)],
                    _stress(facets, _strain_product(a, b)))


def nonlinear_force_vector(facets: FacetTriangles, u: np.ndarray, chunk_bytes: float = 200e6) -> np.ndarray:
    """f_nl (6n, m) N of displacements (6n, m) mm (rotations: zero force, ignored), ``chunk_bytes`` of facet
    temporaries at a time (:func:`on_displacements`)."""
    return on_displacements(nonlinear_forces, facets, u, chunk_bytes=chunk_bytes)[0]


def on_displacements(forces: Callable[..., np.ndarray | tuple[np.ndarray, ...]], facets: FacetTriangles,
                     *displacements: np.ndarray, chunk_bytes: float = 200e6) -> tuple[np.ndarray, ...]:
    """A facet force function of nodal translations (``forces(facets, *translations)``, each (n, 3, m) mm, returning
    one or a tuple of (n, 3, m) N) applied to displacements (6n, m) mm (rotations ignored) in column chunks of
    ``chunk_bytes`` of facet temporaries (about 30 values per facet and column): its forces (6n, m) N, a tuple,
    zero on the rotations."""
    n, m = displacements[0].shape[0] // 6, displacements[0].shape[1]
    translation = (np.arange(6 * n) % 6) < 3
    chunk = max(1, int(chunk_bytes / (8 * 30 * len(facets.nodes) * len(displacements))))
    outs: list[np.ndarray] = []
    for start in range(0, m, chunk):
        parts = forces(facets, *(u[translation, start:start + chunk].reshape(n, 3, -1) for u in displacements))
        for k, part in enumerate(parts if isinstance(parts, tuple) else (parts,)):
            if k == len(outs):
                outs.append(np.zeros((6 * n, m)))
            outs[k][translation, start:start + chunk] = part.reshape(3 * n, -1)
    return tuple(outs)


def tangent_increment(facets: FacetTriangles, translations: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """d f_nl / du at nodal translations (n, 3) mm: (6n, 6n) CSR on the translation DOFs, N/mm.

    Per facet A [B(u)^T t D B(u) - B_0^T t D B_0] + K_G(N(u)): B(u) is the membrane strain's derivative with the
    facet axes e_x + J_x, e_y + J_y (B_0: e_x, e_y, the linear membrane already in K), K_G = int G^T N G dA x I_3.
    """
    J = gradients(facets, translations[:, :, None])[..., 0]  # (T, 3, 2)
    N = membrane_forces(facets, translations[:, :, None])[..., 0]  # (T, 3)
    g = facets.grad  # (T, 2, 3)
    tD = facets.thickness[:, None, None] * facets.D

    def strain_matrix(ax: np.ndarray, ay: np.ndarray) -> np.ndarray:
        """(T, 3, 9): rows xx, yy, 2xy; columns (node, component) for axes ax, ay (T, 3)."""
        B = np.stack([g[:, 0, :, None] * ax[:, None, :], g[:, 1, :, None] * ay[:, None, :],
                      g[:, 1, :, None] * ax[:, None, :] + g[:, 0, :, None] * ay[:, None, :]], axis=1)
        return B.reshape(-1, 3, 9)

    e1, e2 = facets.frame[:, 0], facets.frame[:, 1]
    B0, B = strain_matrix(e1, e2), strain_matrix(e1 + J[:, :, 0], e2 + J[:, :, 1])
    area = facets.area[:, None, None]
    local = area * (np.einsum("tia,tij,tjb->tab", B, tD, B) - np.einsum("tia,tij,tjb->tab", B0, tD, B0))
    local += _geometric_blocks(facets, N)
    return _assemble(facets, local, n_nodes)


def geometric_stiffness(facets: FacetTriangles, membrane: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """Initial-stress stiffness K_G = int G^T N G dA x I_3, (6n, 6n) CSR on the translation DOFs, N/mm, of membrane
    forces (T, 3) N/mm (:func:`membrane_forces`, facet frames): linear in N (a buckling eigenproblem's matrix)."""
    return _assemble(facets, _geometric_blocks(facets, membrane), n_nodes)


def buckling_factor(solver: ShellSolver, displacement: np.ndarray, modes: int = 3) -> float:
    """Linear buckling: the smallest positive lambda at which K + lambda K_G(N(u)) turns singular, for a
    displacement u (6n,) mm (the membrane forces of u scaled by lambda; its loads or boundary motions scaled alike).

    Solved as the largest eigenvalue mu of -K^-1 K_G (ARPACK, ``modes`` eigenvalues), lambda = 1 / mu; inf when no
    membrane force of u softens the structure.
    """
    import scipy.sparse.linalg as sla

    model = solver.model
    facets = facet_triangles(model)
    N = membrane_forces(facets, displacement.reshape(-1, 6)[:, :3, None], nonlinear=False)[..., 0]
    KG = geometric_stiffness(facets, N, len(model.nodes))[solver.free][:, solver.free]
    size = len(solver.free)
    operator = sla.LinearOperator((size, size), matvec=lambda v: -solver.solve_free(KG @ v))
    mu = sla.eigs(operator, k=modes, which="LR", return_eigenvectors=False, tol=1e-8).real.max()
    return float(1.0 / mu) if mu > 0 else float("inf")


def _geometric_blocks(facets: FacetTriangles, N: np.ndarray) -> np.ndarray:
    """(T, 9, 9) per-facet K_G on (node, global component) of membrane forces N (T, 3)."""
    g = facets.grad
    Nmat = np.stack([np.stack([N[:, 0], N[:, 2]], -1), np.stack([N[:, 2], N[:, 1]], -1)], -2)  # (T, 2, 2)
    scalar = facets.area[:, None, None] * np.einsum("tai,tab,tbj->tij", g, Nmat, g)  # (T, 3, 3) node x node
    return np.einsum("tij,cd->ticjd", scalar, np.eye(3)).reshape(-1, 9, 9)


def _assemble(facets: FacetTriangles, local: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """(6n, 6n) CSR of per-facet (T, 9, 9) blocks on the facets' nodes' translations."""
    dofs = (6 * facets.nodes[:, :, None] + np.arange(3)).reshape(-1, 9)
    rows = np.broadcast_to(dofs[:, :, None], local.shape).ravel()
    cols = np.broadcast_to(dofs[:, None, :], local.shape).ravel()
    return sp.coo_matrix((local.ravel(), (rows, cols)), shape=(6 * n_nodes, 6 * n_nodes)).tocsr()


@dataclass(frozen=True)
class NonlinearMembers:
    """Geometrically nonlinear members (m of them).

    translations: (m, n, 3) mm, every node. pad_forces: (m, S) N. pad_displacement: (m, S) mm, the pad springs' mean
    axial displacement z. iterations: (m,) iterations to convergence (all tangents together).
    """

    translations: np.ndarray
    pad_forces: np.ndarray
    pad_displacement: np.ndarray
    iterations: np.ndarray


@dataclass(frozen=True)
class _Tangent:
    """One factorised tangent K_T = K + increment and its linear responses (load + unit bilateral motions, unit pad
    spring forces) and LCP matrix M = H + diag(1/k)."""

    solver: ShellSolver
    increment: sp.csr_matrix
    linear: np.ndarray
    pad_fields: np.ndarray
    M: np.ndarray


class _Mixing:
    """Anderson mixing of a fixed-point iteration x -> x + r(x) over the last ``history`` iterates: a secant update
    (the contact's kinks make the map only piecewise smooth)."""

    def __init__(self, history: int) -> None:
        self.history = history
        self.xs: list[np.ndarray] = []
        self.rs: list[np.ndarray] = []

    def next(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """The next iterate after x with the fixed-point residual r = T(x) - x."""
        self.xs, self.rs = [*self.xs, x][-self.history - 1:], [*self.rs, r][-self.history - 1:]
        if len(self.rs) == 1:
            return x + r
        dR = np.stack([self.rs[i + 1] - self.rs[i] for i in range(len(self.rs) - 1)], axis=1)
        dX = np.stack([self.xs[i + 1] - self.xs[i] for i in range(len(self.xs) - 1)], axis=1)
        gamma = np.linalg.lstsq(dR, r, rcond=None)[0]
        return x + r - (dX + dR) @ gamma


class NonlinearSolver:
    """Geometrically nonlinear members of a factorised :class:`~.solver.ShellSolver` (same loads, boundaries and
    pads): an incremental Newton method whose tangents are shared between members.

    With a tangent K_T (factorised at a solved state), a member iterates K_T u = F(a) + P f - g(u),
    g(u) = f_nl(u) - (K_T - K) u, from K_T's own linear responses, with the pad contact re-solved exactly (LCP on
    K_T's compliance) in every iteration; at convergence K u + f_nl(u) = F(a) + P f with the contact conditions,
    whichever tangent was used. A member starts from the solved state nearest to it (the reference state, all
    parameters 0, is solved first: modified Newton steps with Anderson mixing, a new tangent only when a step grows
    past 1/``contraction`` x the smallest so far) and walks to its own state in increments: when an increment's change
    grows past 1/``contraction`` x its smallest so far (the second iteration, Anderson's first, past
    1/contraction^2: a tangent too soft for the member makes the plain step grow, and the mixing's first secant
    cures it), a new tangent is factorised at the last solved increment (kept for the members after it), and then
    the increment is halved. An iteration that reaches its cap still contracting steadily is not abandoned: from the
    cap on it goes on while the rate fitted to its last ``window`` changes is at most ``steady`` and the iterations
    that rate predicts to the tolerance fit in ``extension`` more, whatever one iteration's growth (the whole-way
    increments of the hood at default resolution contract at ~0.85 to the cap and converge in 42 iterations with
    single growths of 3x past it; abandoning them costs a walk with a new tangent). A walk's first increment (from
    the nearest solved state) that converges only past the cap leaves a new tangent where the walk would have:
    half-way, solved with the start's tangent (kept for the members after it, whom the far tangent serves badly; at
    the member itself it serves the next greedy pass's guesses worse, and after later increments it is not where
    the walk would have put one: RESULTS.md, issue 21).

    tolerance: mm, largest change of any translation between iterations at convergence; min_step: the smallest
    increment (fraction of the way) before SolverError (near or beyond a buckling load); newton_steps: the reference
    state's iterations at most; facets: the model's :func:`facet_triangles` when the caller has them (their sparse
    operator is ~200 MB at default resolution), else built here; max_iter: an iteration's cap; steady, window,
    extension: the largest rate (per iteration), the changes it is fitted to and the iterations past the cap a
    steadily contracting iteration gets.
    ``factorisations`` and ``failed_iterations`` (the iterations of increments and guesses that did not converge)
    count the solver's work so far.
    """

    def __init__(self, solver: ShellSolver, tolerance: float = 1e-6, contraction: float = 0.5,
                 min_step: float = 1.0 / 64, newton_steps: int = 30, facets: FacetTriangles | None = None,
                 max_iter: int = 30, steady: float = 0.9, window: int = 10, extension: int = 30) -> None:
        self.solver = solver
        self.tolerance = tolerance
        self.contraction = contraction
        if not (max_iter >= 1 and 0 < steady < 1 and window >= 2 and extension >= 0):
            raise SolverError(f"expected max_iter >= 1, 0 < steady < 1, window >= 2 and extension >= 0, got "
                              f"{max_iter}, {steady}, {window} and {extension}")
        self.max_iter, self.steady, self.window, self.extension = max_iter, steady, window, extension
        self.min_step = min_step
        model = solver.model
        n = len(model.nodes)
        self.facets = facet_triangles(model) if facets is None else facets
        self._translation = (np.arange(6 * n) % 6) < 3
        self._pad_loads = solver.pads.loads.tocsr()
        self._solved: list[tuple[np.ndarray, np.ndarray, _Tangent]] = []  # (state, displacement, its tangent)
        self.factorisations = 0
        self.failed_iterations = 0
        u, tangent = solver.load_response(), None
        for iteration in range(1, newton_steps + 1):
            if tangent is None:
                tangent = solver.with_stiffness((solver.K + self._increment(u)).tocsr())
                mixing, best = _Mixing(6), np.inf
                self.factorisations += 1
            correction = tangent.solve(solver.load - solver.K @ u - self._f_nl(u[:, None])[:, 0])
            size = float(np.abs(correction).max())
            if size < tolerance:
                u = u + correction
                logger.info("reference state solved in %d iterations with %d tangents", iteration, self.factorisations)
                break
            if size > best / contraction:  # a new tangent only when the mixed iteration stops contracting
                tangent = None
                continue
            best = min(best, size)
            u = mixing.next(u, correction)
        else:
            raise SolverError(f"the reference state did not converge in {newton_steps} iterations")
        self.reference = u
        self._new_tangent(np.zeros(len(model.names)), u)

    def _f_nl(self, u: np.ndarray) -> np.ndarray:
        """f_nl (6n, m) N of displacements (6n, m) mm (zero on rotations)."""
        return nonlinear_force_vector(self.facets, u)

    def _increment(self, u: np.ndarray) -> sp.csr_matrix:
        n = len(self.solver.model.nodes)
        return tangent_increment(self.facets, u.reshape(n, 6)[:, :3], n)

    def _new_tangent(self, state: np.ndarray, u: np.ndarray) -> _Tangent:
        """Factorise the tangent at a solved (state, displacement) and keep it."""
        model, n = self.solver.model, len(self.solver.model.nodes)
        increment = self._increment(u)
        tangent = self.solver.with_stiffness((self.solver.K + increment).tocsr())
        self.factorisations += 1
        columns = [tangent.load_response()] + [tangent.boundary_response(p.boundary, p.direction)
                                                for p in model.bilateral]
        pads = self.solver.pads
        pad_fields = tangent.solve(pads.loads.toarray()) if len(pads.k) else np.zeros((6 * n, 0))
        H = np.asarray(self._pad_loads.T @ pad_fields)
        out = _Tangent(tangent, increment, np.stack(columns, axis=1), pad_fields,
                       0.5 * (H + H.T) + np.diag(1.0 / pads.k))
        self._solved.append((state.copy(), u.copy(), out))
        return out

    def _iterate(self, tangent: _Tangent, states: np.ndarray, u: np.ndarray, history: int = 6
                 ) -> list[tuple[np.ndarray, np.ndarray, int] | None]:
        """Members (m of them) of ``states`` (m, P) from displacements u (6n, m), iterated together (one
        back-substitution of all the columns still iterating per iteration: several times cheaper a column than
        one at a time): for each, converged (displacement (6n,), pad forces (S,), iterations), or None when its
        change grows past 1/contraction x the smallest so far (1/contraction^2 at the second iteration) before
        ``max_iter``, or from ``max_iter`` on when it is not contracting steadily (:meth:`_steady`: the trend of its
        last changes, not one iteration's growth; at most ``extension`` iterations more).

        Each member's fixed point x = T(x) of the correction x = -K_T^-1 g(u(x)) is accelerated by Anderson mixing
        over its last ``history`` iterates (:class:`_Mixing`). Iterations of members that fail add to
        ``failed_iterations``."""
        B = len(self.solver.model.bilateral)
        pads = self.solver.pads
        target = states[:, B:][:, pads.pad_of] + pads.preload  # (m, S)
        base = tangent.linear @ np.concatenate([np.ones((1, len(states))), states[:, :B].T])  # (6n, m)

        def correction(u: np.ndarray) -> np.ndarray:
            return tangent.solver.solve(tangent.increment @ u - self._f_nl(u))

        x = correction(u)
        mixing = [_Mixing(history) for _ in states]
        best = np.full(len(states), np.inf)
        changes: list[list[float]] = [[] for _ in states]
        out: list[tuple[np.ndarray, np.ndarray, int] | None] = [None] * len(states)
        active = np.arange(len(states))
        max_iter, cap = self.max_iter, self.max_iter + self.extension
        for iteration in range(1, cap + 1):
            if not len(active):
                break
            z = np.asarray(self._pad_loads.T @ (base[:, active] + x[:, active]))
            f = np.stack([solve_lcp(tangent.M, z[:, i] - target[j]) for i, j in enumerate(active)], axis=1)
            u = base[:, active] + x[:, active] + tangent.pad_fields @ f
            r = correction(u) - x[:, active]
            change = np.abs(r).max(axis=0)
            going = []
            for i, j in enumerate(active):
                if change[i] < self.tolerance:
                    out[j] = (u[:, i], f[:, i], iteration)
                    continue
                changes[j].append(float(change[i]))
                # before the cap one iteration's growth ends it (the second, Anderson's first, may grow up to
                # 1/contraction^2 x); from the cap on the trend does (single growths are common there: the zigzag)
                going_on = np.isfinite(change[i]) and (
                    change[i] <= best[j] / self.contraction ** (2 if iteration == 2 else 1) if iteration < max_iter
                    else self._steady(changes[j], cap - iteration))
                if going_on:
                    best[j] = min(best[j], change[i])
                    x[:, j] = mixing[j].next(x[:, j].copy(), r[:, i].copy())  # (copies: x changes in place)
                    going.append(j)
                else:
                    self.failed_iterations += iteration
            active = np.array(going, dtype=np.int64)  # (none left after the cap: _steady has no iterations left)
        return out

    def _steady(self, changes: list[float], left: int) -> bool:
        """Whether an iteration whose changes (mm, one per iteration so far) are ``changes`` contracts steadily enough
        to reach the tolerance in ``left`` more iterations: the rate rho fitted to the last ``window`` changes (least
        squares on their logarithms: Anderson's changes zigzag) is at most ``steady`` and log(tolerance / change) /
        log(rho) <= left."""
        if len(changes) < self.window or left <= 0:
            return False
        rho = np.exp(np.polyfit(np.arange(self.window), np.log(changes[-self.window:]), 1)[0])
        return bool(rho <= self.steady and np.log(self.tolerance / changes[-1]) / np.log(rho) <= left)

    def _nearest(self, state: np.ndarray) -> int:
        """The index of the solved state nearest to ``state`` (1-norm)."""
        return int(np.argmin([np.abs(solved[0] - state).sum() for solved in self._solved]))

    def solve_displacement(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """One member: displacement (6n,) mm, pad forces (S,) N, iterations."""
        start, u, tangent = self._solved[self._nearest(state)]
        done, step, fresh, iterations, f = 0.0, 1.0, True, 0, None
        while done < 1.0:
            trial = min(1.0, done + step)
            result = self._iterate(tangent, (start + trial * (state - start))[None], u[:, None])[0]
            if result is not None:
                if result[2] > self.max_iter and done == 0:  # the start's tangent is poor here: one half-way for
                    # the members after it (its iterations are the solver's, not the member's: not in ``iterations``)
                    middle = start + trial / 2 * (state - start)
                    solved = self._iterate(tangent, middle[None], u[:, None])[0]
                    if solved is not None:
                        self._new_tangent(middle, solved[0])
                u, f, count = result
                iterations += count
                done, fresh = trial, False
                continue
            if not fresh:  # a Newton step: the tangent at the last solved increment
                tangent, fresh = self._new_tangent(start + done * (state - start), u), True
                continue
            step /= 2
            if step < self.min_step:
                raise SolverError(f"geometrically nonlinear member {state.tolist()} stalls at {done:.3f} of the way "
                                  "from the nearest solved state: the loads are near a buckling load")
        if f is None:  # the member is a solved state itself
            f = solve_lcp(tangent.M, self._pad_loads.T @ u - state[len(self.solver.model.bilateral):][
                self.solver.pads.pad_of] - self.solver.pads.preload)
        return u, f, iterations

    def solve_displacements(self, states: np.ndarray, guesses: np.ndarray
                            ) -> list[tuple[np.ndarray, np.ndarray, int]]:
        """Members (m, P) mm from displacements near them, guesses (6n, m) mm (e.g. a reduced model's members): each
        iterated from its guess the whole way at once with its nearest solved state's tangent, those sharing a
        tangent together (:meth:`_iterate`). Those that do not converge, one after the other: from the nearest
        member converged so far when it is nearer than the nearest solved state (the same tangent), else (or when
        that fails) walking (:meth:`solve_displacement`). For each, displacement (6n,) mm, pad forces (S,) N,
        iterations."""
        states = np.atleast_2d(np.asarray(states, dtype=float))
        nearest = np.array([self._nearest(state) for state in states], dtype=np.int64)
        out: list[tuple[np.ndarray, np.ndarray, int] | None] = [None] * len(states)
        for k in np.unique(nearest):
            members = np.flatnonzero(nearest == k)
            for j, result in zip(members, self._iterate(self._solved[k][2], states[members], guesses[:, members]),
                                 strict=True):
                out[j] = result
        for j, state in enumerate(states):
            if out[j] is not None:
                continue
            done = [i for i, result in enumerate(out) if result is not None]
            distance = [np.abs(states[i] - state).sum() for i in done]
            k = self._nearest(state)
            if done and min(distance) < np.abs(self._solved[k][0] - state).sum():
                neighbour = out[done[int(np.argmin(distance))]][0]  # (a converged member is a better start)
                out[j] = self._iterate(self._solved[k][2], state[None], neighbour[:, None])[0]
            if out[j] is None:
                out[j] = self.solve_displacement(state)
        return out

    def solve(self, commanded: np.ndarray) -> NonlinearMembers:
        """Members with commanded states (m, P) mm (model.names order), one after the other."""
        model = self.solver.model
        commanded = np.atleast_2d(np.asarray(commanded, dtype=float))
        if commanded.ndim != 2 or commanded.shape[1] != len(model.names) or not np.all(np.isfinite(commanded)):
            raise SolverError(f"expected finite parameter states (m, {len(model.names)}), got {commanded.shape}")
        n, m = len(model.nodes), len(commanded)
        u = np.zeros((6 * n, m))
        forces = np.zeros((m, len(self.solver.pads.k)))
        iterations = np.zeros(m, dtype=np.int64)
        for member, state in enumerate(commanded):
            u[:, member], forces[member], iterations[member] = self.solve_displacement(state)
            if (member + 1) % 50 == 0:
                logger.info("nonlinear member %d/%d, %d tangents so far", member + 1, m, self.factorisations)
        z = np.asarray(self._pad_loads.T @ u).T
        translations = u[self._translation].reshape(n, 3, m).transpose(2, 0, 1)
        return NonlinearMembers(translations, forces, z, iterations)

    def members(self, commanded: np.ndarray) -> MemberBlock:
        """Members (m, P) mm as the linear ensemble's :func:`.ensemble.solve_members` reports them (skin fields)."""
        model = self.solver.model
        solved = self.solve(commanded)
        commanded = np.atleast_2d(np.asarray(commanded, dtype=float))
        pads = self.solver.pads
        B = len(model.bilateral)
        effective, fraction, reactions = contact_summary(commanded, solved.pad_forces, solved.pad_displacement,
                                                         pads.pad_of, pads.preload, B, model.parameter_states)
        skin = solved.translations[:, model.skin_nodes]
        normal = np.einsum("mna,na->mn", skin, skin_surface(model).normals)
        compression = commanded[:, B:][:, pads.pad_of] + pads.preload - solved.pad_displacement
        return MemberBlock(effective, fraction, reactions, normal, skin, solved.pad_forces, compression)


def nonlinear_ensemble(solver: NonlinearSolver, commanded: np.ndarray, rank: np.ndarray, lower: np.ndarray,
                       upper: np.ndarray) -> Ensemble:
    """An in-memory Ensemble of geometrically nonlinear members (as :func:`.ensemble.simulate_ensemble`)."""
    block = solver.members(commanded)
    return Ensemble(
        model_id=solver.solver.model.model_id, names=solver.solver.model.names,
        n_bilateral=len(solver.solver.model.bilateral), lower=np.asarray(lower, dtype=float),
        upper=np.asarray(upper, dtype=float), commanded=np.asarray(commanded, dtype=float),
        effective=block.effective, contact_fraction=block.contact_fraction, reactions=block.reactions,
        rank=np.asarray(rank, dtype=np.int64), normal_displacement=block.normal_displacement,
        displacement=block.displacement)
