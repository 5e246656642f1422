"""Exact solution of the pad contact problem: a linear complementarity problem (LCP) on the pad springs.

With the reduced model (types.ReducedModel) the pad spring compression is c = b[pad_of] + preload - z and
z = z0 + Sa a + H f. A compression-only spring carries f = k max(0, c). Writing s = f / k - c gives the LCP

    find f >= 0 with s = M f + q >= 0 and f . s = 0,   M = H + diag(1 / k),   q = z0 + Sa a - b[pad_of] - preload,

where M is symmetric positive definite (H is a compliance, 1/k > 0), so the solution is unique. It is found exactly by
principal pivoting on the active set (block pivoting of Judice & Pires, falling back to Murty's single least-index
pivot, which terminates for any P-matrix): the final f solves M_AA f_A = -q_A on the active set A directly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hood_decomp.core.types import ReducedModel
from hood_decomp.errors import SolverError


def solve_lcp(M: np.ndarray, q: np.ndarray, max_iter: int = 1000) -> np.ndarray:
    """Solve the LCP f >= 0, M f + q >= 0, f . (M f + q) = 0 for symmetric positive definite M (S, S); f (S,)."""
    n = len(q)
    if n == 0:
        return np.zeros(0)
    tol = 1e-12 * max(np.abs(q).max(), 1e-300)
    active = q < 0
    best, chances = n + 1, 3
    for _ in range(max_iter):
        f = np.zeros(n)
        if active.any():
            f[active] = np.linalg.solve(M[np.ix_(active, active)], -q[active])
        s = M @ f + q
        violated = (active & (f < 0)) | (~active & (s < -tol))
        count = int(violated.sum())
        if count == 0:
            return np.maximum(f, 0.0)
        if count < best:
            best, chances = count, 3
            active ^= violated
        elif chances > 0:
            chances -= 1
            active ^= violated
        else:
            last = np.flatnonzero(violated)[-1]
            active[last] = ~active[last]
    raise SolverError(f"pad contact (LCP of {n} springs) did not converge in {max_iter} pivots")


@dataclass(frozen=True)
class ContactState:
    """Pad contact solution of one parameter state.

    f: (S,) spring forces N (>= 0). z: (S,) pad spring axial displacement, mm. compression: (S,) mm, b + preload - z.
    """

    f: np.ndarray
    z: np.ndarray
    compression: np.ndarray


def contact_state(reduced: ReducedModel, bilateral: np.ndarray, unilateral: np.ndarray,
                  held: bool = False) -> ContactState:
    """Solve the pad contact for bilateral states a (B,) mm and commanded pad positions b (U,) mm.

    held: keep every spring active (M f = -q, f of either sign): the buffers as bilateral boundaries, no contact."""
    bilateral = np.asarray(bilateral, dtype=float)
    unilateral = np.asarray(unilateral, dtype=float)
    if bilateral.shape != (reduced.n_bilateral,):
        raise SolverError(f"expected {reduced.n_bilateral} bilateral values, got shape {bilateral.shape}")
    n_unilateral = len(reduced.names) - reduced.n_bilateral
    if unilateral.shape != (n_unilateral,):
        raise SolverError(f"expected {n_unilateral} unilateral values, got shape {unilateral.shape}")
    target = unilateral[reduced.pad_of] + reduced.preload if len(reduced.k) else np.zeros(0)
    z_free = reduced.z0 + reduced.Sa @ bilateral if len(reduced.k) else np.zeros(0)
    M = reduced.H + np.diag(1.0 / reduced.k)
    f = np.linalg.solve(M, target - z_free) if held and len(reduced.k) else solve_lcp(M, z_free - target)
    z = z_free + reduced.H @ f
    return ContactState(f=f, z=z, compression=target - z)
