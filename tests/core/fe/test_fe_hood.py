"""The embedded solver on the hood: exact contact, physical admissibility, nonlinearity, convergence, any-boundary
responses."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from hood_decomp.core.fe.contact import contact_state, solve_lcp
from hood_decomp.core.fe.ensemble import (
    contact_counts,
    factorial_plan,
    simulate_ensemble,
    simulate_setting,
    solve_members,
    validation_plan,
)
from hood_decomp.core.fe.hood_preset import build_hood
from hood_decomp.core.fe.model import patch_nodes
from hood_decomp.core.fe.solver import build_solver, reduce_model


@pytest.fixture(scope="module")
def coarse():
    model = build_hood("coarse")
    solver = build_solver(model)
    return model, solver, reduce_model(solver)


@pytest.fixture(scope="module")
def coarse_ensemble(coarse):
    model, _, reduced = coarse
    commanded, rank = factorial_plan(model.lower, model.upper)
    return simulate_ensemble(reduced, commanded, rank, model.lower, model.upper)


def _direct_solve(solver, reduced, state: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Independent linear solve with the pad springs of ``active`` added to K (fresh SuperLU factorisation)."""
    model = solver.model
    B = reduced.n_bilateral
    L = solver.pads.loads[:, np.flatnonzero(active)]
    k = reduced.k[active]
    K = (solver.K + L @ sp.diags(k) @ L.T).tocsr()
    target = (state[B:][reduced.pad_of] + reduced.preload)[active]
    F = solver.load + L @ (k * target)
    u = np.zeros(solver.n_dof)
    for parameter, value in zip(model.bilateral, state[:B], strict=True):
        u[solver.boundary_dofs(parameter.boundary, parameter.direction)] = value
    free = solver.free
    K_ff = K[free][:, free].tocsc()
    u[free] = splu(K_ff).solve(F[free] - K[free][:, solver.constrained] @ u[solver.constrained])
    return u.reshape(-1, 6)[model.skin_nodes, :3]


def test_complementarity_equals_direct_solve_with_same_active_set(coarse) -> None:
    model, solver, reduced = coarse
    commanded, _ = factorial_plan(model.lower, model.upper)
    block = solve_members(reduced, commanded)
    partial = np.flatnonzero(((block.contact_fraction > 0) & (block.contact_fraction < 1)).any(axis=1))
    assert len(partial) > 0
    for member in partial[:3]:
        active = block.pad_forces[member] > 0
        direct = _direct_solve(solver, reduced, commanded[member], active)
        error = np.abs(direct - block.displacement[member]).max()
        assert error < 1e-8 * np.abs(direct).max()


def test_lcp_matches_brute_force_enumeration() -> None:
    """On small random SPD problems the pivoting solution is the one active set that satisfies complementarity."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        A = rng.normal(size=(6, 6))
        M = A @ A.T + 0.5 * np.eye(6)
        q = rng.normal(size=6)
        f = solve_lcp(M, q)
        found = 0
        for mask in range(64):
            active = np.array([(mask >> i) & 1 for i in range(6)], dtype=bool)
            g = np.zeros(6)
            g[active] = np.linalg.solve(M[np.ix_(active, active)], -q[active]) if active.any() else []
            s = M @ g + q
            if np.all(g >= -1e-12) and np.all(s[~active] >= -1e-12):
                found += 1
                assert np.allclose(f, g, atol=1e-10)
        assert found == 1


def test_no_penetration_and_no_tension_in_any_member(coarse) -> None:
    model, _, reduced = coarse
    training, _ = factorial_plan(model.lower, model.upper)
    commanded = np.concatenate([training, validation_plan(model.lower, model.upper, 300, seed=3)])
    block = solve_members(reduced, commanded)
    scale = np.abs(block.compression).max()
    assert np.all(block.pad_forces >= 0)  # no spring in tension
    off = block.pad_forces == 0
    assert np.all(block.compression[off] <= 1e-10 * scale)  # a spring without force is not compressed (no overlap)
    on = ~off
    k = np.broadcast_to(reduced.k, block.pad_forces.shape)
    assert np.allclose(block.pad_forces[on], k[on] * block.compression[on], rtol=1e-9)
    lifted = block.contact_fraction == 0
    B = reduced.n_bilateral
    assert np.all(block.effective[:, B:][lifted] >= commanded[:, B:][lifted] - 1e-12)
    assert np.array_equal(block.effective[:, :B], commanded[:, :B])


def test_ensemble_is_nonlinear(coarse, coarse_ensemble) -> None:
    """Pads lift off entirely, partly and sit fully, and the fields need more than the 7 linear responses that point
    buffers would give."""
    model = coarse[0]
    for u in range(2):
        counts = contact_counts(coarse_ensemble.contact_fraction[:, u])
        assert counts["lifted"] > 20 and counts["partial"] > 20 and counts["full"] > 20, counts
    fields = coarse_ensemble.normal_displacement
    s_pads = np.linalg.svd(fields, compute_uv=False)
    # the same hood with each pad a single point spring: every member combines w0, 4 boundary and 2 pad responses
    point = reduce_model(build_solver(model, pad_lattice=1))
    commanded, rank = factorial_plan(model.lower, model.upper)
    s_point = np.linalg.svd(simulate_ensemble(point, commanded, rank, model.lower, model.upper).normal_displacement,
                            compute_uv=False)
    assert s_point[7] < 1e-10 * s_point[0]
    assert s_pads[7] > 1e-5 * s_pads[0]


def test_setting_any_boundary_moves_the_part_rigidly_when_all_supports_move(coarse) -> None:
    """All Z supports up by 1 mm (the fixed hinge's Z too) = the part lifted rigidly by 1 mm."""
    _, solver, _ = coarse
    base = simulate_setting(solver, {})
    lifted = simulate_setting(solver, {"hinge_R.z": 1.0, "hinge_L.z": 1.0, "LOCK_L": 1.0, "LOCK_R": 1.0,
                                       "BUFFER_L": 1.0, "BUFFER_R": 1.0})
    assert np.allclose(lifted.displacement - base.displacement, [0.0, 0.0, 1.0], atol=1e-9)


def test_free_direction_response_moves_the_patch_by_one_mm(coarse) -> None:
    model, solver, _ = coarse
    u = solver.boundary_response("lock_L", "x").reshape(-1, 6)
    nodes = patch_nodes(model, model.boundary("lock_L"))
    assert np.allclose(u[nodes, 0], 1.0, atol=1e-9)
    assert np.allclose(u[nodes, 2], 0.0, atol=1e-9)  # the lock still holds Z
    held = solver.boundary_response("hinge_L", "y").reshape(-1, 6)
    assert np.allclose(held[patch_nodes(model, model.boundary("hinge_L")), 1], 1.0)


def test_contact_state_agrees_with_member_solution(coarse) -> None:
    _, _, reduced = coarse
    state = np.array([0.3, -0.4, 0.2, -0.8, 0.1, -0.6])
    contact = contact_state(reduced, state[:4], state[4:])
    block = solve_members(reduced, state[None])
    assert np.allclose(block.pad_forces[0], contact.f)


@pytest.mark.slow
def test_hood_mesh_convergence() -> None:
    """RMS skin responses to the loads and to the four bilateral parameters, and the pad reaction with both buffers
    raised 1 mm (fully seated), settle as the mesh is refined (same geometry, bond lines and patch positions at every
    grid): the largest relative change shrinks and the last refinement (13 -> 10 mm elements) changes no quantity by
    more than 2 %."""
    values = []
    seated = np.array([[0.0, 0.0, 0.0, 0.0, 1.0, 1.0]])
    for grid in [(64, 74), (96, 112), (128, 149)]:
        reduced = reduce_model(build_solver(build_hood("coarse", grid=grid)))
        rms = np.sqrt((np.column_stack([reduced.w0, reduced.R]) ** 2).mean(axis=0))
        block = solve_members(reduced, seated)
        assert np.all(block.contact_fraction == 1.0)
        values.append(np.append(rms, block.reactions.sum()))
    values = np.array(values)
    change = np.abs(np.diff(values, axis=0)) / np.abs(values[1:])
    assert change[1].max() < change[0].max()
    assert change[1].max() < 0.02
