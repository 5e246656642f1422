"""A reduced geometrically nonlinear model: members of :mod:`.geometric`'s physics in milliseconds.

A member of the full nonlinear model (:class:`.geometric.NonlinearSolver`) solves K u + f_nl(u) = F + P f with the
pad contact. Its exact solution is u = u_lin(a, f) + c with the linear member u_lin = u0 + W a + G f (load response,
unit bilateral responses, unit pad spring responses; exact contact) and the correction c = -K^-1 f_nl(u) on the free
DOFs. Here the correction is sought in a small space, c = Psi q (r modes, zero on the constrained DOFs), by Galerkin
projection in K's inner product,

    Psi^T K Psi q + Psi^T f_nl(u) = 0,     f = LCP(M, z0 + Sa a + Zq q - b[pad_of] - preload)       (1)

with the pad contact solved exactly on the linear compliance M = H + diag(1/k) (Zq = P^T Psi: the correction moves
the pads). f_nl is the gradient of the Green-Lagrange membrane energy beyond the linear one (cubic + quartic in u), so
with u written in reduced coordinates y = (1, a, phi, q), u = u0 + W a + G Bf phi + Psi q, the projected force is a
cubic polynomial in y whose tensors are computed once from the facet triangles:

    E(y) = T3 . y^3 + T4 . y^4,   Psi^T f_nl = dE/dq = 3 T3(y, y, .) + 4 T4(y, y, y, .)                    (2)

The pad forces enter f_nl only through phi = Bf^T H f, their projection on the p pad force shapes (Bf, H-orthonormal)
that the linear members use (H-weighted POD of their forces); the linear part keeps every spring exactly. A member is
a semi-smooth Newton method on q (r unknowns) with the LCP re-solved in every step and its active set's derivative in
the Jacobian: milliseconds, whatever the mesh.

Psi is trained on the training states (ranks 0-2 of the factorial and the 2^P corners of the ranges, 137 for six
parameters) in one of two ways (:func:`build_reduced_geometric`, ``training``):

- ``"states"`` (the default): the K-weighted POD of the exact corrections u - u_lin of all training states, each
  solved once by the full nonlinear model (coarse hood-paper, HINGE_Y +-0.5 mm: 0.0077 mm from the full members;
  the 137 solves are most of the build, 36.5 of 43.5 CPU s).
- ``"derivatives"``: static derivatives instead of most full solves. f_nl = f2(u, u) + f3(u, u, u) exactly; f2's
  bilinear form and f3 evaluated as such (no step size) and back-substitutions with the factorised K give the
  second-order terms -K^-1 f2(v_i, v_j) of the linear fields (u0, W a, G Bf phi at their reach) and the second- and
  third-order terms along each training state's linear member; their POD gives modes - passes x added modes. Then
  greedy passes: the reduced training members' residuals through K^-1 rank them, the worst few are solved by the
  full model from the reduced members, a pass's members together (:meth:`.geometric.NonlinearSolver.
  solve_displacements`, to GREEDY_TOLERANCE), and their corrections add modes (24 full solves instead of 137 by
  default). Not as accurate: 0.012 mm on the same members, 0.019 mm at default resolution (a low-order expansion
  leaves about half of the correction at the lock-twist and lock-buffer corners, where the nonlinearity is strong;
  the greedy full solves carry the accuracy there). The build: ~32 CPU s on the coarse hood (71-74 before session
  18; session 21: 1.22x fewer, 1.16x at default), default resolution in benchmarks/RESULTS.md ("The nonlinear
  build's hot paths" and "... round 2"). Each greedy pass sums only
  the tensor terms with a new coordinate (:func:`energy_sums` with the previous sums; the same sums, 75 % of a
  fresh sum's CPU at d = 49 on coarse).

The tensors are sums over all facets (O(facets x d^4 / 4); the quartic part in single precision, relative ~1e-7:
one sum at d = 49 is ~4 CPU s on the coarse hood, 6.7 before session 21, ~35 s at default resolution before).
``hyper`` (opt-in) sums them over a weighted subset instead (ECSW, :func:`hyper_facets`: non-negative facet
weights fitted so that the subset reproduces the reduced forces at HYPER_ROWS // r training states; 384 of 189,744
facets at default). It is not accurate enough to be the default: on the coarse hood's 39 bench members the reduced
members move 1.9-2.3x (derivatives, 0.023-0.027 mm) and 3.5x (states, 0.028 mm) farther from the full solve, at
tolerance 1e-3 or 1e-4 alike, and at default 0.030 against 0.019 mm: 11-16 snapshots are too few, and more rows
make the NNLS cost grow with their cube. Nor does it save time (coarse: a fit costs more CPU than the sum it
replaces; default: a 496 CPU s build against the exact update's 461; benchmarks/RESULTS.md, "Energy tensors of a
grown basis, and hyper-reduced").

The reduced model is valid inside the parameter ranges it was built for; a range that passes a buckling load
(HINGE_Y +1 mm on the hood) stalls the full solves of the training states or shows as a reduced tangent that is not
positive definite (SolverError).
Checked member by member against the full nonlinear solver (tests/core/fe/test_reduced_geometric.py,
benchmarks/bench_nlgeom_rom.py).
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.linalg.blas import ssyrk

from hood_decomp.core.fe.contact import solve_lcp
from hood_decomp.core.fe.ensemble import MemberBlock, contact_summary, factorial_plan, validation_plan
from hood_decomp.core.fe.geometric import (
    FacetTriangles,
    NonlinearSolver,
    bilinear_force,
    facet_triangles,
    gradients,
    linear_strain,
    nonlinear_force_parts,
    nonlinear_force_vector,
    on_displacements,
)
from hood_decomp.core.fe.model import skin_surface
from hood_decomp.core.fe.solver import ShellSolver
from hood_decomp.errors import SolverError

logger = logging.getLogger(__name__)
#: relative H-weighted singular value below which a pad force shape is dropped
PAD_TOLERANCE = 3e-3
#: bytes of facet temporaries per chunk when the energy tensors are summed
CHUNK_BYTES = 200e6
#: rows (modes x snapshots) the hyper-reduction's facet weights fit: its NNLS costs grow with their cube (384 rows:
#: 2 CPU s, 768: 14 s on coarse hood-paper), so the snapshots are HYPER_ROWS // modes evenly spaced training states
#: (the test's members at tolerance 1e-3: 400 rows 0.027 mm from the full solve, 800 rows 0.013 mm; at 1e-4 and 400
#: rows 0.0073 mm, all facets 0.007-0.009 mm: the tolerance matters more than the rows)
HYPER_ROWS = 400
#: mm, the largest change between iterations at which the build's own full solves stop: the corrections they train
#: are 0.1-0.8 mm and the model is 0.01-0.02 mm from the full solve, so 1e-4 is ample (coarse hood-paper: the same
#: members to 2e-5 mm as with NonlinearSolver's 1e-6, and 32 % fewer iterations)
TRAINING_TOLERANCE = 1e-4
#: mm, the same for the derivative training's greedy full solves: their corrections add 4 modes each pass to a model
#: 0.012-0.019 mm from the full solve, so 1e-3 is still a twelfth of that (coarse hood-paper, session 21: 308
#: iterations instead of 392, the bench's members 0.0118 mm from the full solve instead of 0.0119)
GREEDY_TOLERANCE = 1e-3
#: how the correction modes are trained (:func:`build_reduced_geometric`)
TRAININGS = ("derivatives", "states")


@dataclass(frozen=True)
class ReducedGeometricModel:
    """The reduced nonlinear model of one part, pad set and parameter range (see the module docstring).

    names: (P,) labels, bilateral first. n_bilateral: B. lower, upper: (P,) mm, the ranges it was built for.
    w0, w0_3d: (N,), (N, 3) skin normal / 3D load response, mm. R, R_3d: (N, B), (N, 3, B) per mm.
    G, G_3d: (N, S), (N, 3, S) per N. Psi, Psi_3d: (N, r), (N, 3, r) mm, the correction modes on the skin.
    z0: (S,), Sa: (S, B), H: (S, S), Zq: (S, r): pad spring displacements, mm. k, preload, pad_of: (S,).
    Bf: (S, p) pad force shapes, H-orthonormal. Kq: (r, r) N/mm, Psi^T K Psi.
    T3q: (r, d, d), T4q: (r, d, d, d): the rows of the symmetrised energy tensors for q, d = 1 + B + p + r.
    residual: mm, the training members' difference from the full solve or their one-step correction (see
    :func:`build_reduced_geometric`). build_s, build_cpu_s: wall and CPU seconds of the build's parts.
    """

    model_id: str
    names: tuple[str, ...]
    n_bilateral: int
    parameter_states: str
    lower: np.ndarray
    upper: np.ndarray
    w0: np.ndarray
    R: np.ndarray
    G: np.ndarray
    Psi: np.ndarray
    w0_3d: np.ndarray
    R_3d: np.ndarray
    G_3d: np.ndarray
    Psi_3d: np.ndarray
    z0: np.ndarray
    Sa: np.ndarray
    H: np.ndarray
    Zq: np.ndarray
    k: np.ndarray
    preload: np.ndarray
    pad_of: np.ndarray
    Bf: np.ndarray
    Kq: np.ndarray
    T3q: np.ndarray
    T4q: np.ndarray
    residual: float
    build_s: dict[str, float] = field(default_factory=dict)
    build_cpu_s: dict[str, float] = field(default_factory=dict)

    @property
    def modes(self) -> int:
        return int(self.Kq.shape[0])

    def coordinates(self, state: np.ndarray, f: np.ndarray, q: np.ndarray) -> np.ndarray:
        """y (d,) of a state (P,) mm, pad forces (S,) N and correction coordinates (r,)."""
        return np.concatenate([[1.0], state[:self.n_bilateral], self.Bf.T @ (self.H @ f), q])

    def force(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Psi^T f_nl (r,) N (generalised forces on the unit-peak modes, eq. 2) and d/dy (r, d) at y (d,)."""
        t4y = self.T4q @ y  # (r, d, d)
        t4yy = t4y @ y
        t3y = self.T3q @ y
        return 3 * t3y @ y + 4 * t4yy @ y, 6 * t3y + 12 * t4yy

    def solve(self, state: np.ndarray, max_iter: int = 40, tolerance: float = 1e-9
              ) -> tuple[np.ndarray, np.ndarray, int]:
        """One member (eq. 1): pad forces f (S,) N, correction coordinates q (r,), Newton iterations.

        Newton from q = 0 (the linear member); when it does not converge, continuation in the nonlinear force's
        scale (1/4, 1/2, 3/4, 1). SolverError when that fails too or the reduced tangent is not positive definite at
        the solution (beyond a buckling load)."""
        for scales in ((1.0,), (0.25, 0.5, 0.75, 1.0)):
            q = np.zeros(self.modes)
            iterations = 0
            for scale in scales:
                result = self._newton(state, q, scale, max_iter, tolerance)
                if result is None:
                    break
                f, q, count, tangent = result
                iterations += count
            else:
                if np.linalg.eigvalsh(0.5 * (tangent + tangent.T)).min() <= 0:
                    raise SolverError(f"reduced nonlinear member {np.round(state, 4).tolist()}: the tangent is not "
                                      "positive definite (beyond a buckling load; narrow the parameter ranges)")
                return f, q, iterations
        raise SolverError(f"reduced nonlinear member {np.round(state, 4).tolist()} did not converge: the loads are "
                          "near a buckling load or outside the ranges the model was built for "
                          f"({self.lower.tolist()} .. {self.upper.tolist()})")

    def _newton(self, state: np.ndarray, q: np.ndarray, scale: float, max_iter: int, tolerance: float
                ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray] | None:
        B, r = self.n_bilateral, self.modes
        offset = self.z0 + self.Sa @ state[:B] - state[B:][self.pad_of] - self.preload
        M = self.H + np.diag(1.0 / self.k)
        phi = slice(1 + B, 1 + B + self.Bf.shape[1])
        for iteration in range(1, max_iter + 1):
            f = solve_lcp(M, offset + self.Zq @ q)
            force, derivative = self.force(self.coordinates(state, f, q))
            residual = self.Kq @ q + scale * force
            tangent = self.Kq + scale * derivative[:, -r:]
            active = f > 0
            if active.any():  # df_A/dq = -M_AA^-1 Zq_A: the contact follows the correction
                df = np.linalg.solve(M[np.ix_(active, active)], -self.Zq[active])
                tangent = tangent + scale * derivative[:, phi] @ (self.Bf.T @ self.H[:, active]) @ df
            step = np.linalg.solve(tangent, -residual)
            if not np.all(np.isfinite(step)):
                return None
            q = q + step
            if np.abs(step).max() < tolerance:
                return solve_lcp(M, offset + self.Zq @ q), q, iteration, tangent
        return None

    def solve_all(self, commanded: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pad forces (m, S) N and correction coordinates (m, r) of members (m, P) mm (:meth:`solve`)."""
        commanded = np.atleast_2d(np.asarray(commanded, dtype=float))
        if commanded.ndim != 2 or commanded.shape[1] != len(self.names) or not np.all(np.isfinite(commanded)):
            raise SolverError(f"expected finite parameter states (m, {len(self.names)}), got {commanded.shape}")
        forces = np.zeros((len(commanded), len(self.k)))
        q = np.zeros((len(commanded), self.modes))
        for i, state in enumerate(commanded):
            forces[i], q[i], _ = self.solve(state)
        return forces, q

    def members(self, commanded: np.ndarray) -> MemberBlock:
        """Members (m, P) mm as :func:`.ensemble.solve_members` reports them (skin fields, contact summary)."""
        forces, q = self.solve_all(commanded)
        commanded = np.atleast_2d(np.asarray(commanded, dtype=float))
        B = self.n_bilateral
        a = commanded[:, :B]
        z = (self.z0[None] + a @ self.Sa.T + forces @ self.H.T + q @ self.Zq.T)
        effective, fraction, reactions = contact_summary(commanded, forces, z, self.pad_of, self.preload, B,
                                                         self.parameter_states)
        normal = self.w0[None] + a @ self.R.T + forces @ self.G.T + q @ self.Psi.T
        vectors = (self.w0_3d[None] + np.einsum("nab,mb->mna", self.R_3d, a)
                   + np.einsum("nas,ms->mna", self.G_3d, forces) + np.einsum("nar,mr->mna", self.Psi_3d, q))
        compression = commanded[:, B:][:, self.pad_of] + self.preload - z
        return MemberBlock(effective, fraction, reactions, normal, vectors, forces, compression)


@dataclass(frozen=True)
class EnergySums:
    """The facet sums of the membrane energy beyond the linear one (:func:`energy_sums`), kept in pair form so that a
    grown basis sums only the terms with a new coordinate.

    basis: (n, 3, d) mm, the nodal translations they were summed for. T3: (d, pairs), T4: (pairs, pairs) symmetric,
    pairs = d (d + 1) / 2 products y_a y_b (a <= b, np.triu_indices(d) order): E(y) = sum_c y_c (T3 z)_c + z^T T4 z
    with z the pair products. index: the facets summed when a weighted subset (hyper-reduction), else None.
    """

    basis: np.ndarray
    T3: np.ndarray
    T4: np.ndarray
    index: np.ndarray | None = None

    def tensors(self) -> tuple[np.ndarray, np.ndarray]:
        """The symmetric tensors T3 (d, d, d), T4 (d, d, d, d): E(y) = T3 . y^3 + T4 . y^4."""
        d = self.basis.shape[2]
        first, second = np.triu_indices(d)
        full3 = np.zeros((d, d, d))
        full3[:, first, second] = self.T3  # a <= b only: the sum over all indices is then z-space's
        full4 = np.zeros((d, d, d, d))
        full4[first[:, None], second[:, None], first[None], second[None]] = self.T4
        full3 = sum(full3.transpose(p) for p in itertools.permutations(range(3))) / 6
        full4 = sum(full4.transpose(p) for p in itertools.permutations(range(4))) / 24
        return full3, full4


def energy_sums(facets: FacetTriangles, basis: np.ndarray, previous: EnergySums | None = None) -> EnergySums:
    """The Green-Lagrange membrane energy beyond the linear one of u = basis @ y summed over the facets
    (:class:`EnergySums`); basis: nodal translations (n, 3, d) mm. With ``previous``, the sums of a basis that is
    ``basis``'s first d0 columns, only the terms with a coordinate >= d0 are summed (the rest are taken from it: the
    same sums; a greedy pass adding 4 coordinates to 45 costs 75 % of a fresh sum's CPU on coarse). T4 is summed in
    single precision (each chunk's sum added in double: relative ~1e-7 of a double sum), T3 in double.

    Per facet, eps_L = L y and eps_Q = (y^T S_k y)_k (k = xx, yy, 2xy); E = sum A [eps_L^T tD eps_Q + 1/2 eps_Q^T
    tD eps_Q] (the energy whose gradient is :func:`.geometric.nonlinear_forces`), summed in the products y_a y_b."""
    d = basis.shape[2]
    d0 = 0 if previous is None else previous.basis.shape[2]
    if previous is not None and (d0 > d or not np.array_equal(previous.basis, basis[:, :, :d0])):
        raise SolverError(f"previous energy sums: expected those of the first columns of the basis {basis.shape}, "
                          f"got a basis {previous.basis.shape} that is not")
    first, second = np.triu_indices(d)
    pairs = len(first)
    flat, mirror, diagonal = first * d + second, second * d + first, np.flatnonzero(first == second)
    new, old = np.flatnonzero(second >= d0), np.flatnonzero(second < d0)
    T3 = np.zeros((d, pairs))
    T4new = np.zeros((pairs, len(new)))  # the columns of the new pairs (fresh: the upper triangle, by ssyrk)
    root = np.linalg.cholesky(facets.D)  # D = root root^T: S^T (A t D) S = X^T X, X = sqrt(A t) root^T S
    size = len(facets.nodes)
    chunk = max(1, int(CHUNK_BYTES / (8 * 9 * max(d * d, pairs))))
    for start in range(0, size, chunk):
        part = facets.rows(start, start + chunk)
        t = len(part.nodes)
        J = gradients(part, basis)  # (t, 3, 2, d)
        L = linear_strain(part, J)  # (t, 3, d)
        root_scale = np.sqrt(part.area * part.thickness)  # (A t)^1/2: in S (through J) and in ell, A t in T3
        J *= np.sqrt(root_scale)[:, None, None, None]
        xt, yt = J[:, :, 0].transpose(0, 2, 1), J[:, :, 1].transpose(0, 2, 1)
        S = np.empty((t, 3, pairs))  # eps_Q's pair coefficients: y^T S_k y = sum over a <= b of S_k,ab y_a y_b
        for k, product in enumerate((xt @ J[:, :, 0], yt @ J[:, :, 1], xt @ J[:, :, 1])):  # batched matmul
            np.take(product.reshape(t, -1), flat, axis=1, out=S[:, k])  # (flat, no stack: 1.4x a 2-D index)
        S[:, 2] += np.take(product.reshape(t, -1), mirror, axis=1)  # 2xy: Jx_a . Jy_b + Jx_b . Jy_a
        S[:, :, diagonal] *= 0.5
        ell = (np.einsum("tka,kl->tla", L, facets.D) * root_scale[:, None, None]).reshape(-1, d)
        S = S.reshape(-1, pairs)
        T3[d0:] += ell[:, d0:].T @ S  # (rows of new coordinates, then the new pairs of the old: no copy of S)
        if d0:
            T3[:d0, new] += ell[:, :d0].T @ S[:, new]
        # X = root^T S in single precision (the quartic sums' BLAS 2.2x faster, the bulk of a sum at default
        # resolution; each chunk's sum added in double: relative error ~1e-7); root is lower triangular
        S3, X = S.reshape(t, 3, pairs), np.empty((t, 3, pairs), dtype=np.float32)
        for k in range(3):
            X[:, k] = sum(root[row, k] * S3[:, row] for row in range(k, 3) if root[row, k])
        X = X.reshape(-1, pairs)
        if d0:  # all pairs x the new ones in one GEMM (no copy of X's old columns)
            T4new += 0.5 * (X.T @ X[:, new])
        else:
            T4new += ssyrk(0.5, X.T, trans=0, lower=0)  # half a GEMM
    if d0:
        T4 = np.zeros((pairs, pairs))
        T4[:, new] = T4new
        T4[new] = T4new.T
        T4[np.ix_(new, new)] = 0.5 * (T4new[new] + T4new[new].T)
    else:
        T4 = np.triu(T4new) + np.triu(T4new, 1).T
    if previous is not None:
        # the old pairs' positions in the previous (d0) triu order: a d0 - a (a - 1) / 2 + b - a
        index = first[old] * (2 * d0 - first[old] + 1) // 2 + second[old] - first[old]
        T3[:d0, old] = previous.T3[:, index]
        T4[np.ix_(old, old)] = previous.T4[np.ix_(index, index)]
    return EnergySums(basis, T3, T4)


def facet_reduced_forces(facets: FacetTriangles, basis: np.ndarray, Y: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Each facet's share of the reduced nonlinear force dE/dy_c (the rows c of eq. 2) at coordinates Y (d, m):
    (T, len(rows), m) N, for u = basis @ y, basis (n, 3, d) mm. Summed over the facets it is the projection of
    :func:`.geometric.nonlinear_forces` on the basis columns ``rows``.

    dE/dy_c = A [L_c^T tD eps_Q + N^T d eps_Q/dy_c], N = tD (eps_L + eps_Q); d eps_Q/dy_c = (Jx_c . Jx, Jy_c . Jy,
    Jx_c . Jy + Jy_c . Jx) with Jx, Jy the gradients of u."""
    J = gradients(facets, basis)  # (T, 3, 2, d)
    L = linear_strain(facets, J)  # (T, 3, d)
    Ju = J @ Y  # (T, 3, 2, m)
    Jx, Jy = Ju[:, :, 0], Ju[:, :, 1]
    quadratic = np.stack([0.5 * (Jx * Jx).sum(1), 0.5 * (Jy * Jy).sum(1), (Jx * Jy).sum(1)], axis=1)
    tD = (facets.area * facets.thickness)[:, None, None] * facets.D
    stress_q = tD @ quadratic  # (T, 3, m)
    stress = tD @ (L @ Y) + stress_q
    Vx = stress[:, None, 0] * Jx + stress[:, None, 2] * Jy  # (T, 3, m)
    Vy = stress[:, None, 2] * Jx + stress[:, None, 1] * Jy
    Jc = J[:, :, :, rows]  # (T, 3, 2, c)
    return (L[:, :, rows].transpose(0, 2, 1) @ stress_q + Jc[:, :, 0].transpose(0, 2, 1) @ Vx
            + Jc[:, :, 1].transpose(0, 2, 1) @ Vy)


def hyper_facets(facets: FacetTriangles, basis: np.ndarray, Y: np.ndarray, rows: np.ndarray, tolerance: float,
                 initial: np.ndarray | None = None, max_rounds: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """A weighted subset of the facets whose reduced nonlinear forces (:func:`facet_reduced_forces`, rows ``rows``)
    at the snapshot coordinates Y (d, m) are all facets' within ``tolerance`` (relative, each snapshot scaled to a
    unit force): energy-conserving sampling and weighting (ECSW, Farhat et al. 2014), w >= 0 by a greedy
    non-negative least squares (the facets whose columns correlate most with the residual join a pool in growing
    batches, scipy's NNLS over the pool; its zero weights are left out at the end; ``initial``: facets the pool starts
    with, e.g. those of a smaller basis). Returns the facets (k,) and their weights (k,) (:meth:`.geometric.
    FacetTriangles.select`). SolverError when ``max_rounds`` do not reach the tolerance."""
    from scipy.optimize import nnls

    size, width = len(facets.nodes), len(rows) * Y.shape[1]
    C = np.zeros((width, size), dtype=np.float32)  # float32: enough for fits to 1e-4, half the memory
    chunk = max(1, int(CHUNK_BYTES / (8 * 9 * max(basis.shape[2], width))))
    for start in range(0, size, chunk):
        part = facet_reduced_forces(facets.rows(start, start + chunk), basis, Y, rows)
        C[:, start:start + chunk] = part.reshape(len(part), -1).T
    total = C.sum(axis=1, dtype=np.float64).reshape(len(rows), -1)
    scale = 1.0 / np.maximum(np.linalg.norm(total, axis=0), 1e-300)  # each snapshot counts alike
    C *= np.tile(scale, len(rows)).astype(np.float32)[:, None]
    b = (total * scale).ravel()
    pool = np.zeros(0, dtype=np.int64) if initial is None else np.asarray(initial, dtype=np.int64)
    weight = np.zeros(len(pool))
    if len(pool):
        A = C[:, pool].astype(np.float64)
        weight, _ = nnls(A, b, maxiter=20 * len(pool))
    residual = b - C[:, pool].astype(np.float64) @ weight
    for _ in range(max_rounds):
        if np.linalg.norm(residual) <= tolerance * np.linalg.norm(b):
            chosen = weight > 0
            logger.info("hyper-reduction: %d of %d facets, relative force error %.1e", chosen.sum(), size,
                        np.linalg.norm(residual) / np.linalg.norm(b))
            return pool[chosen], weight[chosen]
        score = C.T @ residual.astype(np.float32)
        score[pool] = -np.inf  # the pool only grows: the NNLS over it can only improve
        batch = max(32, len(pool) // 2) if len(pool) else len(b)  # about as many facets as rows are needed
        add = np.argpartition(-score, batch)[:batch]
        pool = np.concatenate([pool, add[score[add] > 0]])
        A = C[:, pool].astype(np.float64)
        weight, _ = nnls(A, b, maxiter=20 * len(pool))
        residual = b - A @ weight
    raise SolverError(f"hyper-reduction: expected a relative force error <= {tolerance} in {max_rounds} rounds, got "
                      f"{np.linalg.norm(residual) / np.linalg.norm(b):.2e} with {int((weight > 0).sum())} facets")


def training_states(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """States (m, P) mm the correction modes are built from: ranks 0-2 of the factorial and the 2^P corners (137 for
    six parameters; without rank 2, 77, the coarse hood's random members were 0.014 mm from the full solve, with it
    0.008 mm)."""
    commanded, rank = factorial_plan(lower, upper)
    corners = np.array(list(itertools.product(*zip(lower, upper, strict=True))), dtype=float)
    return np.concatenate([commanded[rank <= 2], corners])


def derivative_snapshots(solver: ShellSolver, facets: FacetTriangles, fields: np.ndarray, lines: np.ndarray
                         ) -> np.ndarray:
    """Static derivatives of the correction c = -K^-1 f_nl(u_lin + c) about the unloaded state, (6n, k) mm, zero
    on the constrained DOFs: the second-order terms of the linear fields v (6n, m) mm, s_ii = -K^-1 f2(v_i, v_i),
    s_ij = -2 K^-1 f2(v_i, v_j) (i < j), so that c = sum_{i <= j} y_i y_j s_ij + O(|y|^3) for u_lin = sum y_i v_i;
    and along each linear member e1 of ``lines`` (6n, l) mm its second- and third-order terms
    e2 = -K^-1 f2(e1, e1), e3 = -K^-1 [2 f2(e1, e2) + f3(e1, e1, e1)]. k = m (m + 1) / 2 + 2 l.

    f_nl is f2(u, u) + f3(u, u, u), nothing else (:func:`.geometric.nonlinear_forces`); f2's bilinear form and f3
    are evaluated as such (:func:`.geometric.bilinear_force`, :func:`.geometric.nonlinear_force_parts`): exact, no
    step size."""
    first, second = np.triu_indices(fields.shape[1])
    quadratic = on_displacements(bilinear_force, facets, fields[:, first], fields[:, second])[0]
    quadratic[:, first != second] *= 2
    even, odd = on_displacements(nonlinear_force_parts, facets, lines)
    e2 = -solver.solve(even)
    mixed = 2 * on_displacements(bilinear_force, facets, lines, e2)[0] + odd
    e3 = -solver.solve(mixed)
    return np.concatenate([-solver.solve(quadratic), e2, e3], axis=1)


def build_reduced_geometric(solver: ShellSolver, lower: np.ndarray, upper: np.ndarray, modes: int = 36,
                            pad_samples: int = 1400, seed: int = 1, full: NonlinearSolver | None = None,
                            training: str = "states", passes: int = 3, solves: int = 8, added: int = 4,
                            hyper: float | None = None, enough: float | None = None) -> ReducedGeometricModel:
    """The reduced nonlinear model of a factorised linear solver over the ranges [lower, upper] (P,) mm.

    The correction modes (``modes`` of them at most) are trained on the training states (:func:`training_states`)
    in one of two ways (``training``):

    - ``"states"``: the K-weighted POD of the exact corrections u - u_lin of all training states, each solved by the
      full nonlinear model (``full``, or a new :class:`.geometric.NonlinearSolver` of ``solver`` converged to
      TRAINING_TOLERANCE); ``residual`` is the largest difference of the reduced model's training members from
      those (any skin translation).
    - ``"derivatives"``: ``modes - passes x added`` modes from the K-weighted POD of static derivatives
      (:func:`derivative_snapshots`: the second-order terms of the linear fields u0, W a, G Bf phi scaled to their
      reach in the ranges, and the second- and third-order terms along the training states' linear members), then
      ``passes`` greedy passes: the reduced training members' residuals r = K u + f_nl(u) - F - P f through K^-1 rank
      them, the ``solves`` largest (not solved before) are solved by the full nonlinear model (to GREEDY_TOLERANCE),
      and the K-weighted POD of their corrections K-orthogonal to the modes so far adds ``added`` modes.
      ``residual`` is the largest |K^-1 r| of the final model's training members on the skin (an error indicator,
      not a difference from the full solve). ``passes x solves`` full solves instead of 137; with ``enough`` (mm),
      fewer: the passes end once the largest indicator of the training members not yet solved is below it, and the
      model has fewer modes (an estimate, not a bound: on coarse hood-paper the members' largest distance from the
      full solve was 0.3-0.8x the final indicator; benchmarks/RESULTS.md, session 18).

    pad_samples: random states whose linear pad forces (with the factorial's) give the pad force shapes.
    hyper: None (the energy tensors summed over all facets) or the relative tolerance of a hyper-reduction: the
    tensors summed over a weighted subset of the facets (:func:`hyper_facets`) fitted to the reduced forces at
    HYPER_ROWS // modes training states, their coordinates q the K-projection of their correction estimates (the
    static derivatives' e2 + e3 along their rays, or the full solve where there is one) on the modes; re-fitted
    whenever the modes grow (opt-in: not exact).
    ``build_s``, ``build_cpu_s``: wall and CPU seconds (this process) of the build's parts (pads, derivatives, full
    solves, tensors, indicator or check).
    """
    if training not in TRAININGS:
        raise SolverError(f"training: expected one of {TRAININGS}, got {training!r}")
    if enough is not None and not enough > 0:
        raise SolverError(f"enough: expected None or an indicator in mm > 0, got {enough!r}")
    if hyper is not None and not 0 < hyper < 1:
        raise SolverError(f"hyper: expected None or a relative tolerance in (0, 1), got {hyper!r}")
    start = time.perf_counter()
    clock, cpu = {"start": start}, {"start": time.process_time()}

    def lap(name: str) -> None:
        for timer, now in ((clock, time.perf_counter()), (cpu, time.process_time())):
            timer[name] = timer.get(name, 0.0) + now - timer["start"]
            timer["start"] = now

    model = solver.model
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    n, B = len(model.nodes), len(model.bilateral)
    pads = solver.pads
    P = pads.loads.tocsr()
    u0 = solver.load_response()
    W = np.stack([solver.boundary_response(p.boundary, p.direction) for p in model.bilateral], axis=1)
    G = solver.solve(pads.loads.toarray())
    H = np.asarray(P.T @ G)
    H = 0.5 * (H + H.T)
    z0, Sa = P.T @ u0, np.asarray(P.T @ W)
    M = H + np.diag(1.0 / pads.k)

    def linear_forces(commanded: np.ndarray) -> np.ndarray:
        return np.array([solve_lcp(M, z0 + Sa @ s[:B] - s[B:][pads.pad_of] - pads.preload) for s in commanded])

    def corrections(commanded: np.ndarray, guesses: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Full nonlinear members (6n, m) and their corrections u - u_lin (6n, m), zero on the constrained DOFs;
        guesses: (6n, m) displacements near them to start from (the reduced members), or None."""
        nonlocal full
        tolerance = TRAINING_TOLERANCE if training == "states" else GREEDY_TOLERANCE
        full = NonlinearSolver(solver, tolerance=tolerance, facets=facets) if full is None else full
        exact, f = np.zeros((6 * n, len(commanded))), np.zeros((len(commanded), len(pads.k)))
        began, failed = time.process_time(), full.failed_iterations
        solved = ([full.solve_displacement(state) for state in commanded] if guesses is None
                  else full.solve_displacements(commanded, guesses))
        iterations = 0
        for i, (u, forces, count) in enumerate(solved):
            exact[:, i], f[i] = u, forces
            iterations += count
        logger.info("%d full solves: %d iterations (+%d in failed increments), %d factorisations so far (%.1f CPU s)",
                    len(commanded), iterations, full.failed_iterations - failed, full.factorisations,
                    time.process_time() - began)
        return exact, exact - u0[:, None] - W @ commanded[:, :B].T - G @ f.T

    # pad force shapes: H-weighted POD of the linear members' forces
    factorial, _ = factorial_plan(lower, upper)
    forces = linear_forces(np.concatenate([factorial, validation_plan(lower, upper, pad_samples, seed)]))
    values, vectors = np.linalg.eigh(H)
    root = vectors * np.sqrt(np.maximum(values, 0))  # H = root root^T
    _, sigma, vt = np.linalg.svd(forces @ root, full_matrices=False)
    p = int((sigma > PAD_TOLERANCE * sigma[0]).sum())
    Bf = (vectors / np.sqrt(np.maximum(values, values.max() * 1e-14))) @ vt[:p].T  # root^-T V: H-orthonormal
    logger.info("%d pad force shapes of %d springs (%.1f s)", p, len(pads.k), time.perf_counter() - start)
    lap("pads")

    states = training_states(lower, upper)
    if training == "derivatives" and not (0 < passes * added < modes and 0 < passes * solves <= len(states)):
        raise SolverError(f"expected 0 < passes x added < modes and 0 < passes x solves <= {len(states)} (the "
                          f"training states), got {passes} x {added}, {modes} and {passes} x {solves}")
    facets = facet_triangles(model)
    linear = linear_forces(states)
    if training == "states":
        exact, snapshots = corrections(states)
        estimate = snapshots
        logger.info("%d training members solved by the full nonlinear model (%.1f s)", len(states),
                    time.perf_counter() - start)
        lap("full solves")
        Psi = _pod(solver.K, snapshots, modes)
    else:
        reach = np.concatenate([[1.0], np.maximum(np.abs(lower[:B]), np.abs(upper[:B])),
                                np.abs(forces @ H @ Bf).max(axis=0)])
        snapshots = derivative_snapshots(solver, facets, np.concatenate([u0[:, None], W, G @ Bf], axis=1) * reach,
                                         u0[:, None] + W @ states[:, :B].T + G @ linear.T)
        logger.info("%d static derivatives (%.1f s)", snapshots.shape[1], time.perf_counter() - start)
        lap("derivatives")
        Psi = _pod(solver.K, snapshots, modes - passes * added)
        estimate = snapshots[:, -2 * len(states):-len(states)] + snapshots[:, -len(states):]  # e2 + e3
    fixed = np.concatenate([np.ones((1, len(states))), states[:, :B].T, Bf.T @ H @ linear.T])  # y without q

    def assemble(Psi: np.ndarray, sums: EnergySums | None) -> tuple[ReducedGeometricModel, EnergySums]:
        if hyper is None:
            return _assemble(solver, Psi, u0, W, G, H, z0, Sa, Bf, lower, upper, facets, sums)
        return _assemble(solver, Psi, u0, W, G, H, z0, Sa, Bf, lower, upper, facets,
                         hyper=(fixed, estimate, hyper, None if sums is None else sums.index))

    rom, sums = assemble(Psi, None)
    lap("tensors")
    solved = np.zeros(len(states), dtype=bool)
    for sweep in range(passes + 1 if training == "derivatives" else 0):
        f, q = rom.solve_all(states)
        reduced = u0[:, None] + W @ states[:, :B].T + G @ f.T + Psi @ q.T
        # K^-1 (K u + f_nl(u) - F - P f) with the linear member's part exact (K_ff of u0, W a, G f is F, 0, P f
        # on the free DOFs): Psi q + K^-1 f_nl(u), without the full-order K u
        step = (Psi @ q.T + solver.solve(nonlinear_force_vector(facets, reduced))).reshape(n, 6, -1)
        lap("indicator")
        size = np.where(solved, -1.0, np.abs(step[:, :3]).max(axis=(0, 1)))
        if sweep == passes or (enough is not None and size.max() < enough):
            if sweep < passes:
                logger.info("greedy passes end after %d: largest indicator %.4f mm < %.4f mm", sweep, size.max(),
                            enough)
            residual = float(np.abs(step[model.skin_nodes, :3]).max())
            break
        chosen = np.argsort(size)[::-1][:solves]
        solved[chosen] = True
        new = corrections(states[chosen], reduced[:, chosen])[1]
        estimate[:, chosen] = new
        logger.info("pass %d: %d full solves, largest indicator %.4f mm (%.1f s)", sweep + 1, len(chosen),
                    size.max(), time.perf_counter() - start)
        lap("full solves")
        new = new - Psi @ np.linalg.solve(Psi.T @ (solver.K @ Psi), Psi.T @ (solver.K @ new))
        Psi = np.concatenate([Psi, _pod(solver.K, new, added)], axis=1)
        rom, sums = assemble(Psi, sums)
        lap("tensors")
    if training == "states":
        f, q = rom.solve_all(states)
        difference = (u0[:, None] + W @ states[:, :B].T + G @ f.T + Psi @ q.T - exact).reshape(n, 6, -1)
        residual = float(np.abs(difference[model.skin_nodes, :3]).max())
        lap("check")
    clock.pop("start")
    cpu.pop("start")
    logger.info("reduced nonlinear model (%s): %d modes, %d pad force shapes; residual %.4f mm (%.1f s)",
                training, rom.modes, p, residual, time.perf_counter() - start)
    return replace(rom, residual=residual, build_s=clock, build_cpu_s=cpu)


def _pod(K: np.ndarray, snapshots: np.ndarray, modes: int) -> np.ndarray:
    """The K-weighted POD of snapshots (6n, k): at most ``modes`` modes (6n, r), each scaled to a unit peak."""
    gram = snapshots.T @ (K @ snapshots)
    values, vectors = np.linalg.eigh(0.5 * (gram + gram.T))
    order = np.argsort(values)[::-1][:modes]
    order = order[values[order] > 1e-12 * values[order[0]]]
    Psi = snapshots @ vectors[:, order]
    return Psi / np.abs(Psi).max(axis=0)


def _assemble(solver: ShellSolver, Psi: np.ndarray, u0: np.ndarray, W: np.ndarray, G: np.ndarray, H: np.ndarray,
              z0: np.ndarray, Sa: np.ndarray, Bf: np.ndarray, lower: np.ndarray, upper: np.ndarray,
              facets: FacetTriangles | None = None, previous: EnergySums | None = None,
              hyper: tuple[np.ndarray, np.ndarray, float, np.ndarray | None] | None = None
              ) -> tuple[ReducedGeometricModel, EnergySums]:
    """The reduced model of the correction modes Psi (6n, r) (residual not yet measured: NaN) and its energy sums;
    ``previous``: those of Psi's first columns (:func:`energy_sums`). ``hyper``: (y without q (1 + B + p, m),
    correction estimates (6n, m) mm, tolerance, facets to start from or None): the sums over a weighted subset of the
    facets fitted to the reduced forces at HYPER_ROWS // r of those m snapshots, evenly spaced (:func:`hyper_facets`;
    ``previous`` must then be None; the subset's facet indices are the sums' ``index``)."""
    model = solver.model
    n, r = len(model.nodes), Psi.shape[1]
    basis = np.concatenate([u0[:, None], W, G @ Bf, Psi], axis=1).reshape(n, 6, -1)[:, :3]
    Kq = Psi.T @ (solver.K @ Psi)
    facets = facet_triangles(model) if facets is None else facets
    if hyper is not None:
        assert previous is None, "the sums of another facet subset"
        fixed, estimate, tolerance, begin = hyper
        sample = np.unique(np.linspace(0, fixed.shape[1] - 1, max(2, HYPER_ROWS // r)).round().astype(int))
        q = np.linalg.solve(Kq, Psi.T @ (solver.K @ estimate[:, sample]))  # (r, m): the estimates' K-projection
        d = basis.shape[2]
        index, weight = hyper_facets(facets, basis, np.concatenate([fixed[:, sample], q]), np.arange(d - r, d),
                                     tolerance, begin)
        sums = replace(energy_sums(facets.select(index, weight), basis), index=index)
    else:
        sums = energy_sums(facets, basis, previous)
    T3, T4 = sums.tensors()
    skin, normals = model.skin_nodes, skin_surface(model).normals

    def on_skin(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = u.reshape(n, 6, -1)[skin, :3]
        return np.einsum("nak,na->nk", t, normals), t

    w, w3 = on_skin(np.concatenate([u0[:, None], W], axis=1))
    g, g3 = on_skin(G)
    psi, psi3 = on_skin(Psi)
    pads = solver.pads
    return ReducedGeometricModel(
        model_id=model.model_id, names=tuple(model.names), n_bilateral=len(model.bilateral),
        parameter_states=model.parameter_states, lower=lower.copy(), upper=upper.copy(), w0=w[:, 0], R=w[:, 1:],
        G=g, Psi=psi, w0_3d=w3[:, :, 0], R_3d=w3[:, :, 1:], G_3d=g3, Psi_3d=psi3, z0=z0, Sa=Sa, H=H,
        Zq=np.asarray(pads.loads.T @ Psi), k=pads.k.copy(), preload=pads.preload.copy(), pad_of=pads.pad_of.copy(),
        Bf=Bf, Kq=Kq, T3q=T3[-r:].copy(), T4q=T4[-r:].copy(), residual=float("nan")), sums
