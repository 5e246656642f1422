"""The contact-aware estimator on parts whose buffers touch on only some of their pad springs (issue 21's fault).

Truth from the FE solver: the pad reactions of the member's contact solution applied to a direct solve of the full
shell model (not the reduced model's superposition the estimator works in), with the contact conditions checked on
that solution. On hood-paper (rigid buffers, 7e8 N/mm per spring) a buffer carrying 60 N is compressed by 1e-7 mm;
a fixed 1e-7 mm compression floor reported such buffers lifted and the bilateral states took their reaction (HINGE_X
0.09 mm off on a noise-free member of the estimator's own model).
"""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.core.fe.ensemble import solve_members, validation_plan
from hood_decomp.core.method.bases import estimate_field
from hood_decomp.core.types import DisplacementField

# a noise-free field made by the FE solver differs from the reduced model's member by round-off of the two solves
# (below 1e-9 mm here); the estimate may amplify it by the design's condition, not to 1e-6 mm
EXACT_MM = 1e-6


def fe_member(case, state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(skin normal displacement (N,) mm, pad forces (S,) N, skin 3D displacement (N, 3) mm) of ``state`` (P,) mm from
    a direct FE solve with the member's pad reactions; asserts that the reactions push (f >= 0), that every loaded
    spring touches its buffer and that no free spring penetrates it, on the FE solution."""
    solver, reduced, model = case.solver, case.reduced, case.model
    forces = solve_members(reduced, state[None, :]).pad_forces[0]
    prescribed = np.zeros(len(solver.constrained))
    for p, parameter in enumerate(model.bilateral):
        prescribed[np.isin(solver.constrained, solver.boundary_dofs(parameter.boundary, parameter.direction))] = \
            state[p]
    u = solver.solve(solver.load + solver.pads.loads @ forces, prescribed)
    gap = solver.pads.loads.T @ u - (state[reduced.n_bilateral:][reduced.pad_of] + reduced.preload)
    scale = 1e-9 * (1.0 + np.abs(u).max())
    assert forces.min() >= 0.0
    assert np.all(gap[forces == 0] >= -scale)
    np.testing.assert_allclose(-gap[forces > 0], forces[forces > 0] / reduced.k[forces > 0], atol=scale)
    vectors = u.reshape(-1, 6)[model.skin_nodes, :3]
    return np.einsum("na,na->n", vectors, case.skin.normals), forces, vectors


def partial_contact_members(case, n: int, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(state, pad forces) of the first ``count`` of ``n`` random members with a buffer touching on 1-3 of its
    springs."""
    reduced = case.reduced
    plan = validation_plan(case.model.lower, case.model.upper, n, seed=3)
    block = solve_members(reduced, plan)
    pads = len(reduced.names) - reduced.n_bilateral
    touching = np.array([[(block.pad_forces[i][reduced.pad_of == u] > 0).sum() for u in range(pads)]
                         for i in range(n)])
    chosen = np.flatnonzero(((touching >= 1) & (touching <= 3)).any(axis=1))[:count]
    assert len(chosen) == count, f"only {len(chosen)} partial-contact members among {n}"
    return [(plan[i], block.pad_forces[i]) for i in chosen]


def observable(case, state: np.ndarray, forces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(values (P,) mm, lifted (P,) bool) the estimator can recover: the state, with a lifted buffer's value the
    part's position there (the commanded position at which it would just touch), from the reduced contact solution's
    spring displacements."""
    reduced = case.reduced
    B = reduced.n_bilateral
    values, lifted = state.copy(), np.zeros(state.size, dtype=bool)
    z = reduced.z0 + reduced.Sa @ state[:B] + reduced.H @ forces
    for u in range(state.size - B):
        springs = reduced.pad_of == u
        if not (forces[springs] > 0).any():
            lifted[B + u] = True
            values[B + u] = np.min(z[springs] - reduced.preload[springs])
    return values, lifted


@pytest.mark.parametrize("preset", ["coarse_hood_paper", "coarse_hood"])
def test_noise_free_partial_contact_is_estimated_exactly(preset, request) -> None:
    """Fails if a noise-free member of the estimator's own model (made by the FE solver) whose buffer touches on 1-3 of
    its 14 springs is not estimated within 1e-6 mm with the right lifted flags: a buffer reported lifted although it
    carries load (its reaction then lands on the bilateral states), on hood-paper's rigid buffers (where main's fixed
    1e-7 mm compression floor did so up to 50 N) and on the default hood's rubber pads."""
    case = request.getfixturevalue(preset)
    worst = 0.0
    for state, forces in partial_contact_members(case, 300, 5):
        normal, _, _ = fe_member(case, state)
        estimate = estimate_field(case.bases, DisplacementField(case.model.model_id, normal, 1.0, float("nan")))
        values, lifted = observable(case, state, forces)
        np.testing.assert_array_equal(estimate.lifted, lifted)
        worst = max(worst, float(np.abs(estimate.values - values).max()))
    assert worst < EXACT_MM, worst


def test_noisy_light_touch_bilateral_states_within_their_std(coarse_hood) -> None:
    """Fails if the bilateral states of noisy parts with a light-touch buffer (1-3 of 14 springs, 1-5 N in all, the
    RESULTS "light-touch pad" case) stray outside their stated uncertainty: per state, the RMS of error / std over 5
    parts x 30 noise draws (0.02 mm white noise, stated) must stay below 1.2 and no |error| / std above 4. The pad's
    commanded position is not observable there (it may be reported lifted), but its reaction must not land on the
    bilateral states unstated: when the best contact state has the pad lifted, the touching state's own (larger)
    covariance counts. Before (main 45b5b9a): LOCK_R RMS 1.27, max 4.3, 86.7 % inside its 95 % interval; after
    1.09, 2.9, 92.7 % (benchmarks/RESULTS.md, issue 21: the contact-aware estimator on partial contact)."""
    case = coarse_hood
    reduced = case.reduced
    B = reduced.n_bilateral
    plan = validation_plan(case.model.lower, case.model.upper, 200, seed=0)
    block = solve_members(reduced, plan)
    parts = []
    for i in range(len(plan)):
        for u in range(len(reduced.names) - B):
            springs = reduced.pad_of == u
            touching, force = (block.pad_forces[i][springs] > 0).sum(), block.pad_forces[i][springs].sum()
            if 1 <= touching <= 3 and 1.0 <= force <= 5.0:
                parts.append(plan[i])
                break
    assert len(parts) == 5
    rng = np.random.default_rng(5)
    z = []
    for state in parts:
        normal, _, _ = fe_member(case, state)
        for _ in range(30):
            noisy = normal + rng.normal(0.0, 0.02, normal.size)
            estimate = estimate_field(case.bases, DisplacementField(case.model.model_id, noisy, 1.0, 0.02))
            z.append((estimate.values[:B] - state[:B]) / estimate.std[:B])
    z = np.array(z)
    rms = np.sqrt(np.mean(z**2, axis=0))
    assert np.all(rms < 1.2) and np.abs(z).max() < 4.0, (rms, np.abs(z).max(axis=0))
