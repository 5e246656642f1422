"""The flat shell element against rigid-body motion, exact membrane states and the classical plate solution."""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.core.fe.model import Boundary, Material, Part, PartModel, Patch
from hood_decomp.core.fe.shell import QUAD_SPLITS, quad_stiffness, triangle_stiffness
from hood_decomp.core.fe.solver import build_solver

E, NU, T = 210000.0, 0.3, 0.7


def _rigid_motions(xyz: np.ndarray) -> list[np.ndarray]:
    """Six rigid motions (18,) of one triangle: three translations, three rotations about the origin."""
    motions = []
    for axis in np.eye(3):
        u = np.zeros((3, 6))
        u[:, :3] = axis
        motions.append(u.ravel())
        u = np.zeros((3, 6))
        u[:, :3] = np.cross(axis, xyz)
        u[:, 3:] = axis
        motions.append(u.ravel())
    return motions


def test_element_has_exactly_six_rigid_modes_and_they_cost_nothing() -> None:
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(20, 3, 3)) * 50.0
    K = triangle_stiffness(xyz, np.full(20, T), E, NU)
    assert np.allclose(K, K.transpose(0, 2, 1), atol=1e-9 * np.abs(K).max())
    for k, x in zip(K, xyz, strict=True):
        eig = np.linalg.eigvalsh(k)
        assert eig.min() > -1e-10 * eig.max()
        assert np.sum(eig < 1e-9 * eig.max()) == 6
        for u in _rigid_motions(x):
            assert np.linalg.norm(k @ u) < 1e-9 * np.linalg.norm(k) * np.linalg.norm(u)



def test_quad_is_both_diagonal_splits_at_half_weight() -> None:
    """A quad's (24, 24) stiffness is the four triangles of both diagonals, each counted half, placed on its corners."""
    rng = np.random.default_rng(2)
    xyz = np.array([[0.0, 0, 0], [30, 0, 0], [32, 25, 0], [-1, 28, 0]]) + rng.normal(size=(5, 4, 3))
    thickness = np.linspace(0.7, 2.0, 5)
    K = quad_stiffness(xyz, thickness, E, NU)
    for quad, t, k in zip(xyz, thickness, K, strict=True):
        expected = np.zeros((24, 24))
        for corners in QUAD_SPLITS:
            dofs = (6 * corners[:, None] + np.arange(6)).ravel()
            expected[np.ix_(dofs, dofs)] += 0.5 * triangle_stiffness(quad[corners][None], np.array([t]), E, NU)[0]
        np.testing.assert_allclose(k, expected, rtol=0, atol=1e-12 * np.abs(expected).max())
        eig = np.linalg.eigvalsh(k)
        assert np.sum(eig < 1e-9 * eig.max()) == 6

def _plate(n: int, size: float) -> tuple[np.ndarray, np.ndarray]:
    g = np.linspace(0.0, size, n + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    idx = np.arange(X.size).reshape(n + 1, n + 1)
    cells = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], axis=-1).reshape(-1, 4)
    return nodes, cells


def _plate_model(nodes: np.ndarray, cells: np.ndarray, boundaries: tuple[Boundary, ...]) -> PartModel:
    return PartModel(
        name="plate", nodes=nodes, cells=cells, cell_part=np.zeros(len(cells), dtype=np.int64),
        parts=(Part("sheet", T),), material=Material(E, NU, 0.0), boundaries=boundaries,
        parameters=(), skin_part="sheet", gravity=np.zeros(3),
    )


def test_membrane_uniform_tension_is_exact() -> None:
    """A square sheet pulled by a uniform edge traction: u_x = F L / (E t W), contraction -nu F / (E t) exactly."""
    size, force = 200.0, 1000.0
    nodes, cells = _plate(6, size)
    rng = np.random.default_rng(3)
    # distorted interior (a patch test); the quads along the loaded edge stay regular so that area-weighted nodal
    # forces there are the consistent loads of a uniform traction
    inner = (nodes[:, 0] > 0) & (nodes[:, 0] < size * 4 / 6 + 1) & (nodes[:, 1] > 0) & (nodes[:, 1] < size)
    nodes[inner, :2] += rng.uniform(-8, 8, size=(inner.sum(), 2))
    left = tuple(np.flatnonzero(nodes[:, 0] == 0).tolist())
    right = tuple(np.flatnonzero(nodes[:, 0] == size).tolist())
    corner = (int(np.flatnonzero((nodes[:, 0] == 0) & (nodes[:, 1] == 0))[0]),)
    model = _plate_model(nodes, cells, (
        Boundary("left", "fixed", Patch(nodes=left), dofs=("x",)),
        Boundary("flat", "fixed", Patch(nodes=tuple(range(len(nodes)))), dofs=("z",)),
        Boundary("corner", "fixed", Patch(nodes=corner), dofs=("y",)),
        Boundary("pull", "force", Patch(nodes=right), axis=(1.0, 0.0, 0.0), force=force),
    ))
    solver = build_solver(model)
    u = solver.load_response().reshape(-1, 6)
    strain = force / (E * T * size)
    assert np.allclose(u[:, 0], strain * nodes[:, 0], atol=1e-9)
    assert np.allclose(u[:, 1], -NU * strain * nodes[:, 1], atol=1e-9)


def navier_center_deflection(load: float, size: float, D: float, terms: int = 4001) -> float:
    """Simply supported square plate, central point load (Timoshenko & Woinowsky-Krieger, Navier double series):
    w = 4 P a^2 / (pi^4 D) sum_{m,n odd} 1 / (m^2 + n^2)^2."""
    odd = np.arange(1, terms + 1, 2, dtype=float)
    m, n = np.meshgrid(odd, odd)
    return 4 * load * size**2 / (np.pi**4 * D) * float(np.sum(1.0 / (m**2 + n**2) ** 2))


@pytest.mark.parametrize("n", [24])
def test_simply_supported_plate_center_load_matches_series(n: int) -> None:
    """24 x 24 quads (each split both ways): centre deflection within 2 % of the series (alpha = 0.0116)."""
    size, load = 500.0, 10.0
    nodes, cells = _plate(n, size)
    edge = (nodes[:, 0] == 0) | (nodes[:, 0] == size) | (nodes[:, 1] == 0) | (nodes[:, 1] == size)
    center = int(np.argmin(np.linalg.norm(nodes[:, :2] - size / 2, axis=1)))
    c0 = int(np.flatnonzero((nodes[:, 0] == 0) & (nodes[:, 1] == 0))[0])
    c1 = int(np.flatnonzero((nodes[:, 0] == size) & (nodes[:, 1] == 0))[0])
    model = _plate_model(nodes, cells, (
        Boundary("edges", "fixed", Patch(nodes=tuple(np.flatnonzero(edge).tolist())), dofs=("z",)),
        Boundary("pin", "fixed", Patch(nodes=(c0,)), dofs=("x", "y")),
        Boundary("roller", "fixed", Patch(nodes=(c1,)), dofs=("y",)),
        Boundary("load", "force", Patch(nodes=(center,)), axis=(0.0, 0.0, -1.0), force=load),
    ))
    w = -build_solver(model).load_response().reshape(-1, 6)[center, 2]
    D = E * T**3 / (12 * (1 - NU**2))
    exact = navier_center_deflection(load, size, D)
    assert exact == pytest.approx(0.0116 * load * size**2 / D, rel=2e-3)  # the tabulated coefficient
    assert w == pytest.approx(exact, rel=0.02)
