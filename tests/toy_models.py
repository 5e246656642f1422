"""Synthetic ensembles with known truth for the method's tests (not the code under test).

A flat-ish rectangular skin, smooth random response fields, and a tiny hand-made ReducedModel with compression-only
pad springs. The forward contact problem is solved here by brute-force enumeration of all contact states (exact, and
independent of the estimator's active-set search). Optional interaction terms (a field times the product of some
parameters) give ensembles whose hierarchical basis must contain exactly those effects.
"""

from __future__ import annotations

import itertools

import numpy as np

from hood_decomp.core.types import DisplacementField, Ensemble, ReducedModel, SkinSurface, fingerprint

BILATERAL = ("HINGE_X", "HINGE_Y", "LOCK_L", "LOCK_R")
UNILATERAL = ("BUFFER_R", "BUFFER_L")


def make_skin(nx: int = 24, ny: int = 16) -> SkinSurface:
    """A gently curved 1500 x 1000 mm skin on an nx x ny grid, normals pointing up (+z)."""
    x, y = np.meshgrid(np.linspace(0.0, 1500.0, nx), np.linspace(0.0, 1000.0, ny), indexing="ij")
    z = 40.0 * np.sin(np.pi * y / 1000.0) + 0.01 * x
    points = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    dzdx = np.full(x.shape, 0.01)
    dzdy = 40.0 * np.pi / 1000.0 * np.cos(np.pi * y / 1000.0)
    normals = np.column_stack([-dzdx.ravel(), -dzdy.ravel(), np.ones(x.size)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    tri = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            p = i * ny + j
            tri += [(p, p + ny, p + ny + 1), (p, p + ny + 1, p + 1)]
    triangles = np.array(tri, dtype=np.int64)
    return SkinSurface(points, normals, triangles, fingerprint(points, normals, triangles))


def smooth_fields(points: np.ndarray, count: int, rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    """(count, N) smooth random fields: a few Gaussian bumps plus a plane, peak about ``scale``."""
    xy = points[:, :2] / 1000.0
    out = np.empty((count, points.shape[0]))
    for i in range(count):
        field = rng.normal() * xy[:, 0] + rng.normal() * xy[:, 1]
        for _ in range(3):
            centre = rng.uniform([0.0, 0.0], [1.5, 1.0])
            width = rng.uniform(0.2, 0.5)
            field += rng.normal() * np.exp(-np.sum((xy - centre) ** 2, axis=1) / width**2)
        out[i] = scale * field / np.abs(field).max()
    return out


def _to_3d(skin: SkinSurface, normal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(count, N) normal components -> (count, N, 3): normal part plus a smooth in-plane part."""
    count = normal.shape[0]
    tangential = smooth_fields(skin.points, 3 * count, rng, 0.3).reshape(count, 3, -1).transpose(0, 2, 1)
    tangential -= np.sum(tangential * skin.normals, axis=2, keepdims=True) * skin.normals
    return normal[:, :, None] * skin.normals + tangential


def make_reduced_model(
    skin: SkinSurface, seed: int = 0, n_bilateral: int = 4, n_pads: int = 2, springs_per_pad: int = 2
) -> ReducedModel:
    """A hand-made ReducedModel: pads sag onto their springs at a = 0 (in contact at b = 0, lifted at b = -1)."""
    rng = np.random.default_rng(seed)
    n_springs = n_pads * springs_per_pad
    names = BILATERAL[:n_bilateral] + UNILATERAL[:n_pads]
    w0 = smooth_fields(skin.points, 1, rng, 1.5)[0]
    r = smooth_fields(skin.points, n_bilateral, rng, 1.0).T
    g = smooth_fields(skin.points, n_springs, rng, 0.004).T
    base = rng.normal(size=(n_springs, n_springs))
    h = 0.001 * (base @ base.T / n_springs + np.eye(n_springs))
    fields3 = _to_3d(skin, np.vstack([w0[None], r.T, g.T]), rng)
    return ReducedModel(
        model_id=skin.model_id,
        names=names,
        n_bilateral=n_bilateral,
        w0=w0,
        R=r,
        G=g,
        z0=np.full(n_springs, -0.3) + rng.uniform(-0.05, 0.05, n_springs),
        Sa=rng.uniform(-0.3, 0.3, (n_springs, n_bilateral)),
        H=h,
        k=np.full(n_springs, 800.0),
        preload=rng.uniform(0.0, 0.05, n_springs),
        pad_of=np.repeat(np.arange(n_pads), springs_per_pad),
        w0_3d=fields3[0],
        R_3d=fields3[1 : 1 + n_bilateral].transpose(1, 2, 0),
        G_3d=fields3[1 + n_bilateral :].transpose(1, 2, 0),
    )


def solve_contact_exact(model: ReducedModel, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pad forces f (S,) >= 0 by enumerating every contact state (the LCP matrix is P, so exactly one fits)."""
    n_s = model.k.size
    for active in itertools.product((False, True), repeat=n_s):
        idx = np.flatnonzero(active)
        f = np.zeros(n_s)
        if idx.size:
            m = np.diag(1.0 / model.k[idx]) + model.H[np.ix_(idx, idx)]
            f[idx] = np.linalg.solve(m, b[model.pad_of[idx]] + model.preload[idx] - model.z0[idx] - model.Sa[idx] @ a)
        z = model.z0 + model.Sa @ a + model.H @ f
        gap = b[model.pad_of] + model.preload - z
        if np.all(f[idx] >= -1e-12) and np.all(gap[np.setdiff1d(np.arange(n_s), idx)] <= 1e-12):
            return f
    raise AssertionError("no contact state solves the LCP")


def simulate(model: ReducedModel, state: np.ndarray) -> dict[str, np.ndarray]:
    """Truth for one commanded state (B + U,): w (N,), w3 (N, 3), f (S,), effective state, contact, reactions."""
    n_b = model.n_bilateral
    a, b = state[:n_b], state[n_b:]
    f = solve_contact_exact(model, a, b)
    z = model.z0 + model.Sa @ a + model.H @ f
    effective = np.array(state, dtype=float)
    n_pads = b.size
    contact = np.zeros(n_pads)
    reactions = np.zeros(n_pads)
    for pad in range(n_pads):
        springs = model.pad_of == pad
        contact[pad] = np.mean(f[springs] > 0)
        reactions[pad] = f[springs].sum()
        if not np.any(f[springs] > 0):
            effective[n_b + pad] = np.min(z[springs] - model.preload[springs])
    return {
        "w": model.w0 + model.R @ a + model.G @ f,
        "w3": model.w0_3d + model.R_3d @ a + model.G_3d @ f,
        "f": f,
        "effective": effective,
        "contact": contact,
        "reactions": reactions,
    }


def full_factorial(n_params: int, low: float = -1.0, high: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(3^P, P) states over {low, 0, high} and their ranks (number of non-zero entries), sorted by rank."""
    states = np.array(list(itertools.product((0.0, high, low), repeat=n_params)))
    rank = np.count_nonzero(states, axis=1)
    order = np.argsort(rank, kind="stable")
    return states[order], rank[order]


def make_ensemble(
    model: ReducedModel,
    states: np.ndarray,
    rank: np.ndarray | None = None,
    interactions: tuple[tuple[tuple[int, ...], np.ndarray, np.ndarray], ...] = (),
) -> Ensemble:
    """Simulate every commanded state; each interaction (param indices, field (N,), field3 (N, 3)) adds
    field * prod(state[indices]) to the member."""
    sims = [simulate(model, s) for s in states]
    w = np.array([s["w"] for s in sims])
    w3 = np.array([s["w3"] for s in sims])
    for indices, field, field3 in interactions:
        factor = np.prod(states[:, list(indices)], axis=1)
        w += factor[:, None] * field
        w3 += factor[:, None, None] * field3
    n = len(model.names)
    return Ensemble(
        model_id=model.model_id,
        names=tuple(model.names),
        n_bilateral=model.n_bilateral,
        lower=np.full(n, -1.0),
        upper=np.full(n, 1.0),
        commanded=np.array(states, dtype=float),
        effective=np.array([s["effective"] for s in sims]),
        contact_fraction=np.array([s["contact"] for s in sims]).reshape(len(sims), -1),
        reactions=np.array([s["reactions"] for s in sims]).reshape(len(sims), -1),
        rank=np.full(len(states), -1) if rank is None else np.asarray(rank),
        normal_displacement=w,
        displacement=w3,
    )


def interaction_term(skin: SkinSurface, indices: tuple[int, ...], seed: int, scale: float = 0.5):
    """One interaction (indices, field (N,), field3 (N, 3)) of peak ``scale`` mm."""
    rng = np.random.default_rng(seed)
    field = smooth_fields(skin.points, 1, rng, scale)
    return indices, field[0], _to_3d(skin, field, rng)[0]


def random_states(model: ReducedModel, count: int, seed: int) -> np.ndarray:
    """(count, B + U) uniform random commanded states in [-1, 1] (a validation set)."""
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (count, len(model.names)))


def field_of(skin: SkinSurface, values: np.ndarray, noise_rms: float = float("nan")) -> DisplacementField:
    """A DisplacementField of the skin's model from (N,) values (NaN where unseen)."""
    return DisplacementField(skin.model_id, values, float(np.isfinite(values).mean()), noise_rms)


def interacting_ensemble(skin: SkinSurface, seed: int = 3):
    """Bilateral-only model (4 parameters) with LOCK_L & LOCK_R and HINGE_X & HINGE_Y & LOCK_L interactions.

    Returns (model, full-factorial ensemble, interaction terms)."""
    model = make_reduced_model(skin, seed=seed, n_pads=0)
    states, rank = full_factorial(4)
    terms = (interaction_term(skin, (2, 3), seed + 10, 0.5), interaction_term(skin, (0, 1, 2), seed + 11, 0.3))
    return model, make_ensemble(model, states, rank, terms), terms


def plain_hierarchical(
    x: np.ndarray, commanded: np.ndarray, rank: np.ndarray, names: tuple[str, ...], epsilon: float,
    time_cap_s: float = float("inf"),
) -> tuple[list[str], int]:
    """The paper's greedy loop done plainly (reference, and the benchmark's "paper stack"): after every addition all
    members of the rank are refitted from scratch with scipy.linalg.lstsq on the raw member fields.

    Returns (effect names in order of discovery, number of refits done); stops early after ``time_cap_s``.
    """
    import time

    from scipy.linalg import lstsq

    start = time.perf_counter()
    origin = int(np.flatnonzero(rank == 0)[0])
    basis = [x[origin]] + [x[i] for i in np.flatnonzero(rank == 1)]
    found = list(names)
    refits = 0
    for r in range(2, int(rank.max()) + 1):
        members = np.flatnonzero(rank == r)
        while time.perf_counter() - start < time_cap_s:
            b = np.array(basis).T
            diffs = []
            for m in members:
                coeff = lstsq(b, x[m], cond=1e-10)[0]
                diffs.append(x[m] - b @ coeff)
                refits += 1
            errors = np.abs(np.array(diffs)).max(axis=1)
            worst = int(np.argmax(errors))
            if errors[worst] <= epsilon:
                break
            m = members[worst]
            partner = np.flatnonzero(np.all(commanded[members] == -commanded[m], axis=1))
            basis.append(diffs[worst])
            if partner.size:
                basis.append(diffs[int(partner[0])])
            found.append(" & ".join(n for n, s in zip(names, commanded[m], strict=True) if s != 0))
    return found, refits


def smoothed_noise(skin: SkinSurface, passes: int) -> tuple[object, np.ndarray, np.ndarray]:
    """Node noise smoothed as a scan's is, with its error model known exactly (not the scan step's): white noise
    averaged over each node's one ring ``passes`` times (>= 1). Returns (S (N, N) sparse, the smoothing; std (N,), the
    per-node std of S e for unit white e; correlation (N,), each node's sum of correlation coefficients with all
    nodes): ``level * (S @ e) / std`` has node std ``level`` and those correlation sums."""
    from hood_decomp.core.method.residual import ring_incidence

    rings = ring_incidence(skin).astype(float)
    average = rings.multiply(1.0 / rings.sum(axis=1)).tocsr()
    smoothing = average
    for _ in range(passes - 1):
        smoothing = (average @ smoothing).tocsr()
    std = np.sqrt(np.asarray(smoothing.multiply(smoothing).sum(axis=1)).ravel())
    covariance = (smoothing @ smoothing.T).tocsr()
    correlation = np.asarray(covariance.multiply(1.0 / std[:, None]).multiply(1.0 / std[None, :]).sum(axis=1)).ravel()
    return smoothing, std, correlation
