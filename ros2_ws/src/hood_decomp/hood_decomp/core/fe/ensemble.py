"""The simulation ensemble (paper section 3.1.1): sampling plans and the member solutions.

Training members are the full factorial over {min, 0, max} per parameter (3^P members, 729 for the hood), ordered by
rank as in Table 1 (rank = number of non-zero parameters); validation members are uniform random parameter states
(1400 in the paper, section 4.1). Each member is solved exactly from the reduced model: the pad contact LCP
(:mod:`hood_decomp.core.fe.contact`) and superposition w = w0 + R a + G f.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from hood_decomp.core.fe.contact import contact_state
from hood_decomp.core.fe.solver import ShellSolver, reduce_model
from hood_decomp.core.types import Ensemble, ReducedModel
from hood_decomp.errors import EnsembleError, ModelError


def factorial_plan(lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Full factorial over {min, 0, max}: commanded states (3^P, P) mm and ranks (3^P,), ordered by rank (Table 1).

    Within a rank, members follow itertools order over (0, min, max) per parameter, so the file order is stable.
    """
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    if np.any(lower > upper):
        raise EnsembleError(f"ranges need min <= max, got lower {lower} upper {upper}")
    levels = np.array(list(itertools.product((0, 1, 2), repeat=len(lower))), dtype=np.int64)
    values = np.stack([np.zeros_like(lower), lower, upper], axis=0)  # (3, P)
    commanded = values[levels, np.arange(len(lower))]
    rank = (levels != 0).sum(axis=1)
    order = np.argsort(rank, kind="stable")
    return commanded[order], rank[order]


def validation_plan(lower: np.ndarray, upper: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Uniform random parameter states (n, P) mm in [lower, upper], reproducible from ``seed``."""
    if n < 0:
        raise EnsembleError(f"validation size must be >= 0, got {n}")
    rng = np.random.default_rng(seed)
    return rng.uniform(np.asarray(lower, float), np.asarray(upper, float), size=(n, len(lower)))


@dataclass(frozen=True)
class MemberBlock:
    """Solutions of a block of members (m of them).

    effective: (m, P) mm; contact_fraction, reactions: (m, U); normal_displacement: (m, N) mm;
    displacement: (m, N, 3) mm; pad_forces: (m, S) N; compression: (m, S) mm (pad spring b + preload - z).
    """

    effective: np.ndarray
    contact_fraction: np.ndarray
    reactions: np.ndarray
    normal_displacement: np.ndarray
    displacement: np.ndarray
    pad_forces: np.ndarray
    compression: np.ndarray


def solve_members(reduced: ReducedModel, commanded: np.ndarray, buffers: str = "unilateral") -> MemberBlock:
    """Solve members with commanded states (m, P) mm (names order of ``reduced``): exact contact + superposition.

    buffers: "unilateral" (the model's contact) or "held": every pad spring kept active, pulling as well as pushing,
    i.e. each buffer a bilateral displacement boundary at its commanded position (the paper's Table 2 read as plain
    displacement boundaries; CalculiX's ``buffers="held"`` decks). Held members are affine in the state.
    """
    commanded = np.atleast_2d(np.asarray(commanded, dtype=float))
    n_params = len(reduced.names)
    if commanded.shape[1] != n_params:
        raise EnsembleError(f"expected {n_params} parameter columns {reduced.names}, got {commanded.shape[1]}")
    if buffers not in ("unilateral", "held"):
        raise EnsembleError(f"buffers must be 'unilateral' or 'held', got {buffers!r}")
    B = reduced.n_bilateral
    m, S = len(commanded), len(reduced.k)
    forces = np.zeros((m, S))
    compression = np.zeros((m, S))
    z = np.zeros((m, S))
    for i, state in enumerate(commanded):
        contact = contact_state(reduced, state[:B], state[B:], held=buffers == "held")
        forces[i] = contact.f
        compression[i] = contact.compression
        z[i] = contact.z
    effective, contact_fraction, reactions = contact_summary(commanded, forces, z, reduced.pad_of, reduced.preload,
                                                             B, reduced.parameter_states)
    a = commanded[:, :B]
    normal = reduced.w0[None, :] + a @ reduced.R.T + forces @ reduced.G.T
    n = len(reduced.w0)
    vectors = (
        reduced.w0_3d.ravel()[None, :]
        + a @ reduced.R_3d.reshape(3 * n, B).T
        + forces @ reduced.G_3d.reshape(3 * n, S).T
    ).reshape(m, n, 3)
    return MemberBlock(effective, contact_fraction, reactions, normal, vectors, forces, compression)


def contact_summary(commanded: np.ndarray, forces: np.ndarray, z: np.ndarray, pad_of: np.ndarray,
                    preload: np.ndarray, n_bilateral: int, parameter_states: str
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per member and pad: the recorded state, the fraction of springs in contact and the total reaction.

    commanded: (m, P) mm; forces, z: (m, S) pad spring forces N and axial displacements mm; pad_of, preload: (S,).
    Returns effective (m, P) mm (a lifted pad's state is the part's position there when ``parameter_states`` is
    "effective", types.Ensemble), contact_fraction (m, U) and reactions (m, U) N.
    """
    U = commanded.shape[1] - n_bilateral
    effective = commanded.copy()
    contact_fraction = np.zeros((len(commanded), U))
    reactions = np.zeros((len(commanded), U))
    for u in range(U):
        springs = pad_of == u
        touching = forces[:, springs] > 0
        contact_fraction[:, u] = touching.mean(axis=1)
        reactions[:, u] = forces[:, springs].sum(axis=1)
        if parameter_states == "effective":
            # lifted: the part's position at the pad, where the pad would just touch
            lifted = ~touching.any(axis=1)
            effective[lifted, n_bilateral + u] = np.min(z[lifted][:, springs] - preload[springs], axis=1)
    return effective, contact_fraction, reactions


def iter_members(reduced: ReducedModel, commanded: np.ndarray, block: int = 128,
                 solve: Callable[[np.ndarray], MemberBlock] | None = None) -> Iterator[tuple[slice, MemberBlock]]:
    """Solve members (m, P) mm block by block (bounded memory for large skins): (rows, solutions) per block.

    solve: another solver of a block of members (e.g. the reduced nonlinear model's ``members``); None: the linear
    :func:`solve_members` of ``reduced``."""
    total = len(commanded)
    for start in range(0, total, block):
        rows = slice(start, min(start + block, total))
        yield rows, solve_members(reduced, commanded[rows]) if solve is None else solve(commanded[rows])


def simulate_ensemble(reduced: ReducedModel, commanded: np.ndarray, rank: np.ndarray, lower: np.ndarray,
                      upper: np.ndarray, buffers: str = "unilateral") -> Ensemble:
    """An in-memory Ensemble of the given members (use the store for large ones); buffers: see solve_members."""
    solved = solve_members(reduced, commanded, buffers)
    return Ensemble(
        model_id=reduced.model_id,
        names=tuple(reduced.names),
        n_bilateral=reduced.n_bilateral,
        lower=np.asarray(lower, dtype=float),
        upper=np.asarray(upper, dtype=float),
        commanded=np.asarray(commanded, dtype=float),
        effective=solved.effective,
        contact_fraction=solved.contact_fraction,
        reactions=solved.reactions,
        rank=np.asarray(rank, dtype=np.int64),
        normal_displacement=solved.normal_displacement,
        displacement=solved.displacement,
    )


def contact_counts(contact_fraction: np.ndarray) -> dict[str, int]:
    """How many (member, pad) pairs are lifted (0), partly (0..1) and fully (1) in contact."""
    return {
        "lifted": int((contact_fraction == 0).sum()),
        "partial": int(((contact_fraction > 0) & (contact_fraction < 1)).sum()),
        "full": int((contact_fraction == 1).sum()),
    }


@dataclass(frozen=True)
class Setting:
    """One forward solve. normal_displacement (N,) mm, displacement (N, 3) mm, contact_fraction and reactions: pad
    label -> fraction of springs in contact / total force N, names: the inputs in reduced-model order, values (mm)."""

    names: tuple[str, ...]
    values: np.ndarray
    normal_displacement: np.ndarray
    displacement: np.ndarray
    contact_fraction: dict[str, float]
    reactions: dict[str, float]


def simulate_setting(solver: ShellSolver, settings: dict[str, float]) -> Setting:
    """Solve any setting of any boundary: keys are parameter labels or "boundary.direction" (mm); others are 0.

    A "boundary.direction" key that matches a declared parameter is that parameter; any other becomes an extra
    bilateral input (unit boundary response from the same factorisation, see ShellSolver.boundary_response).
    """
    model = solver.model
    by_dof = {f"{p.boundary}.{p.direction}": p.label for p in model.parameters}
    labels = set(model.names)
    extra: list[tuple[str, str]] = []
    resolved: dict[str, float] = {}
    for key, value in settings.items():
        key_label = by_dof.get(key, key)
        if key_label in labels:
            resolved[key_label] = float(value)
            continue
        boundary, _, direction = key.partition(".")
        if not direction:
            raise ModelError(
                f"unknown setting {key!r}: expected a parameter label {sorted(labels)} or BOUNDARY.DIRECTION with a "
                f"boundary among {[b.name for b in model.boundaries]}"
            )
        model.boundary(boundary)
        extra.append((boundary, direction.lower()))
        resolved[f"{boundary}.{direction.lower()}"] = float(value)
    reduced = reduce_model(solver, extra=extra)
    values = np.array([resolved.get(name, 0.0) for name in reduced.names])
    block = solve_members(reduced, values[None, :])
    unilateral = reduced.names[reduced.n_bilateral:]
    return Setting(
        names=reduced.names,
        values=values,
        normal_displacement=block.normal_displacement[0],
        displacement=block.displacement[0],
        contact_fraction={name: float(block.contact_fraction[0, u]) for u, name in enumerate(unilateral)},
        reactions={name: float(block.reactions[0, u]) for u, name in enumerate(unilateral)},
    )
