"""Geometric nonlinearity of the facet shell (core/fe/geometric.py) against beam-column theory.

A simply supported strip (1000 x 50 x 5 mm, nu = 0 so the plate strip is an Euler beam, EI = E b t^3 / 12) under an
axial compression P at its free end and its own weight as the lateral load: Euler's buckling load pi^2 EI / L^2 and
Timoshenko's exact midspan deflection of a uniformly loaded beam-column (Theory of Elastic Stability, eq. 1-34),
delta = delta_0 * 12 (2 sec u - 2 - u^2) / (5 u^4), u = (L/2) sqrt(P / EI), are the independent references.
"""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.core.fe.geometric import (
    NonlinearSolver,
    bilinear_force,
    buckling_factor,
    facet_triangles,
    membrane_forces,
    nonlinear_force_parts,
    nonlinear_forces,
    tangent_increment,
)
from hood_decomp.core.fe.model import Boundary, Material, Part, PartModel, Patch
from hood_decomp.core.fe.solver import build_solver
from hood_decomp.errors import SolverError

L, WIDTH, T, E = 1000.0, 50.0, 5.0, 210000.0
EI = E * WIDTH * T**3 / 12.0
P_EULER = np.pi**2 * EI / L**2  # 1080 N


def _strip(axial: float, nx: int = 40, density: float = Material().density) -> PartModel:
    """The strip on nx x 2 quads: x = 0 pinned, x = L held in y and z, ``axial`` N pushing the end at x = L, its
    weight of ``density`` t/mm^3 (steel's, unless told) the lateral load."""
    x, y = np.linspace(0.0, L, nx + 1), np.linspace(0.0, WIDTH, 3)
    nodes = np.array([[a, b, 0.0] for a in x for b in y])
    index = np.arange(len(nodes)).reshape(nx + 1, 3)
    cells = np.stack([index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]], axis=-1).reshape(-1, 4)
    start, end = tuple(int(i) for i in index[0]), tuple(int(i) for i in index[-1])
    boundaries = (Boundary("pin", "fixed", Patch(nodes=start), dofs=("x", "y", "z")),
                  Boundary("roller", "fixed", Patch(nodes=end), dofs=("y", "z")),
                  Boundary("push", "force", Patch(nodes=end), axis=(-1.0, 0.0, 0.0), force=axial))
    return PartModel(name="strip", nodes=nodes, cells=cells, cell_part=np.zeros(len(cells), dtype=np.int64),
                     parts=(Part("strip", T),), material=Material(E=E, nu=0.0, density=density), boundaries=boundaries,
                     parameters=(), skin_part="strip")


def test_euler_buckling_load_of_a_strip() -> None:
    """Fails if the initial-stress stiffness K_G = int G^T N G dA (sign, area, membrane force from the CST) gives a
    critical load of the strip more than 0.5 % from Euler's pi^2 EI / L^2."""
    model = _strip(axial=1.0)
    solver = build_solver(model)
    facets = facet_triangles(model)
    u = solver.load_response() - build_solver(_strip(axial=1e-12)).load_response()  # the push alone
    N = membrane_forces(facets, u.reshape(-1, 6)[:, :3, None], nonlinear=False)[..., 0]
    # the CST carries the push as a uniaxial N = -P / b (facet frames differ: trace and determinant)
    np.testing.assert_allclose((N[:, 0] + N[:, 1]) * WIDTH, -1.0, rtol=1e-6)
    np.testing.assert_allclose(N[:, 0] * N[:, 1] - N[:, 2] ** 2, 0.0, atol=1e-9 / WIDTH**2)
    critical = buckling_factor(solver, u)
    assert critical == pytest.approx(P_EULER, rel=0.005)


@pytest.mark.parametrize("fraction", [0.3, 0.6])
def test_beam_column_amplification(fraction: float) -> None:
    """Fails if the nonlinear member (Green-Lagrange membrane forces, the tangent, the incremental Newton of
    NonlinearSolver) does not amplify the strip's weight deflection as Timoshenko's beam-column within 0.5 %, or if
    it changes the linear deflection without the push (no membrane force: nothing to amplify, within 1e-3)."""
    P = fraction * P_EULER
    linear = build_solver(_strip(axial=1e-12))
    plain = NonlinearSolver(linear, tolerance=1e-9).reference.reshape(-1, 6)[:, 2]
    w0 = linear.load_response().reshape(-1, 6)[:, 2]
    mid = np.argmin(np.abs(linear.model.nodes[:, 0] - L / 2) + np.abs(linear.model.nodes[:, 1] - WIDTH / 2))
    assert abs(plain[mid] / w0[mid] - 1.0) < 1e-3
    pushed = NonlinearSolver(build_solver(_strip(axial=P)), tolerance=1e-9).reference.reshape(-1, 6)[:, 2]
    u = 0.5 * L * np.sqrt(P / EI)
    expected = 12.0 * (2.0 / np.cos(u) - 2.0 - u**2) / (5.0 * u**4)
    assert pushed[mid] / w0[mid] == pytest.approx(expected, rel=0.005)


def test_nonlinear_force_is_the_gradient_of_the_green_lagrange_energy() -> None:
    """Fails if f_nl is not the derivative of the membrane energy 1/2 int N . eps (Green-Lagrange eps) beyond the
    linear membrane, or if the tangent is not the derivative of f_nl (central differences on random motions)."""
    model = _strip(axial=1.0, nx=6)
    facets = facet_triangles(model)
    rng = np.random.default_rng(3)
    u, v = rng.normal(size=(2, len(model.nodes), 3, 1)) * np.array([0.3, 1.0])[:, None, None, None]
    compliance = np.linalg.inv(facets.D)

    def energy(w: np.ndarray) -> float:
        N = membrane_forces(facets, w)[..., 0]
        return 0.5 * float(np.sum(facets.area * np.einsum("ti,ij,tj->t", N, compliance, N) / facets.thickness))

    def linear_work(w: np.ndarray, dw: np.ndarray) -> float:
        strain = np.einsum("ij,tjm->tim", compliance, membrane_forces(facets, dw, nonlinear=False))[..., 0]
        return float(np.sum(facets.area * np.einsum("ti,ti->t", membrane_forces(facets, w, nonlinear=False)[..., 0],
                                                    strain) / facets.thickness))

    h = 1e-6
    derivative = (energy(u + h * v) - energy(u - h * v)) / (2 * h)
    assert derivative == pytest.approx(linear_work(u, v) + float(np.sum(nonlinear_forces(facets, u) * v)), rel=1e-6)
    step = (nonlinear_forces(facets, u + h * v) - nonlinear_forces(facets, u - h * v))[..., 0] / (2 * h)
    v6 = np.zeros((len(model.nodes), 6))
    v6[:, :3] = v[..., 0]
    tangent = (tangent_increment(facets, u[..., 0], len(model.nodes)) @ v6.ravel()).reshape(-1, 6)
    np.testing.assert_allclose(tangent[:, :3], step, atol=1e-6 * np.abs(step).max())


def test_force_parts_and_bilinear_form_are_those_of_f_nl() -> None:
    """Fails if nonlinear_force_parts' f2, f3 are not the quadratic and cubic terms of nonlinear_forces (f_nl(s u) =
    s^2 f2 + s^3 f3 at two scales), or if bilinear_force is not the polarisation of f_nl's even part,
    2 f2(u, v) = E(u + v) - E(u) - E(v) with E(w) = [f_nl(w) + f_nl(-w)] / 2, in either order."""
    model = _strip(axial=1.0, nx=6)
    facets = facet_triangles(model)
    u, v = np.random.default_rng(5).normal(size=(2, len(model.nodes), 3, 2))
    f2, f3 = nonlinear_force_parts(facets, u)
    scale = np.abs(nonlinear_forces(facets, u)).max()
    for s in (0.5, 2.0):
        np.testing.assert_allclose(nonlinear_forces(facets, s * u), s**2 * f2 + s**3 * f3, atol=1e-12 * scale * s**3)

    def even(w: np.ndarray) -> np.ndarray:
        return 0.5 * (nonlinear_forces(facets, w) + nonlinear_forces(facets, -w))

    polarised = 0.5 * (even(u + v) - even(u) - even(v))
    for a, b in ((u, v), (v, u)):
        np.testing.assert_allclose(bilinear_force(facets, a, b), polarised, atol=1e-12 * scale)


@pytest.mark.parametrize(("fraction", "converges"), [(0.7, True), (0.9, False)])
def test_mixing_gets_one_iteration_of_growth_and_no_more(fraction: float, converges: bool) -> None:
    """A member iterated with a tangent too soft for it (NonlinearSolver._iterate): the strip's weight (1000x lighter
    than steel, so its membrane stretching is negligible and the member is the linear one, 2.3e-3 mm) with the
    tangent of a push of ``fraction`` x Euler's load. The modified Newton step then multiplies the error of the first
    bending mode by mu = 1 - 1 / (1 - fraction) per iteration (Euler: that mode's stiffness times 1 - fraction), so the
    second iteration's change is |mu| x the first (-7/3 at 0.7, measured 2.33; -9 at 0.9). Fails if the member at
    0.7 is not converged by Anderson's mixing to the linear solver's member (the second iteration is Anderson's first:
    it may grow up to 4x; measured 7 iterations), or if the member at 0.9 is not abandoned after its second
    iteration."""
    light = 7.85e-12
    linear = build_solver(_strip(axial=1e-12, density=light))
    push = build_solver(_strip(axial=1.0, density=light)).load_response() - linear.load_response()  # per N
    full = NonlinearSolver(linear, tolerance=1e-12)
    tangent = full._new_tangent(np.zeros(0), fraction * P_EULER * push)
    result = full._iterate(tangent, np.zeros((1, 0)), np.zeros((len(push), 1)))[0]
    if converges:
        assert result is not None and result[2] <= 8
        # the deflection is the linear solver's; all of it (the axial shortening 1/2 w'^2 too, 1.3e-8 mm) the
        # member the reference iteration of the true tangent converges to
        expected = linear.load_response().reshape(-1, 6)[:, 2]
        assert np.abs(result[0].reshape(-1, 6)[:, 2] - expected).max() < 1e-6 * np.abs(expected).max()
        assert np.abs(result[0] - full.reference).max() < 1e-11
        assert full.failed_iterations == 0
    else:
        assert result is None and full.failed_iterations == 2


@pytest.mark.parametrize(("rate", "converges"), [(0.85, True), (0.95, False)])
def test_a_steadily_contracting_iteration_goes_past_the_cap(rate: float, converges: bool) -> None:
    """A member iterated past the cap (NonlinearSolver._iterate, 30 iterations, the default 30 more when steady): the
    light strip's weight (the linear member, 2.3e-3 mm, as above) with the tangent of a pull of f = rate / (1 - rate)
    x Euler's load and plain modified Newton steps (history 0: no mixing). Each step multiplies the first bending
    mode's error by mu = 1 - 1 / (1 + f) = ``rate`` (Euler: that mode's stiffness times 1 + f; the higher modes' by
    f / (n^2 + f), faster). The first step is K_T^-1 F, (1 - mu) of the deflection w, so the first change is
    c1 = mu (1 - mu) max |w| and the change falls below the tolerance 3e-7 mm at iteration
    1 + ceil(log(3e-7 / c1) / log(mu)): 44 at 0.85 (measured: ratios 0.850, c1 2.91e-4 mm). Fails if the member at
    0.85 is abandoned at the cap or is not the linear solver's member (and the reference iteration's with its own
    tangent) within the error mu / (1 - mu) x the last change leaves, or if the member at 0.95 (above the bound 0.9)
    is not abandoned at the cap as without the extension."""
    light, tolerance = 7.85e-12, 3e-7
    linear = build_solver(_strip(axial=1e-12, density=light))
    push = build_solver(_strip(axial=1.0, density=light)).load_response() - linear.load_response()  # per N
    full = NonlinearSolver(linear, tolerance=tolerance)
    tangent = full._new_tangent(np.zeros(0), -rate / (1 - rate) * P_EULER * push)
    result = full._iterate(tangent, np.zeros((1, 0)), np.zeros((len(push), 1)), history=0)[0]
    if converges:
        expected = linear.load_response()
        first = rate * (1 - rate) * np.abs(expected.reshape(-1, 6)[:, 2]).max()
        assert result is not None and 30 < result[2] == 1 + int(np.ceil(np.log(tolerance / first) / np.log(rate)))
        bound = 2 * tolerance * rate / (1 - rate)  # 3.4e-6 mm, 0.15 % of the deflection
        assert np.abs(result[0] - expected).max() < bound
        assert np.abs(result[0] - NonlinearSolver(linear, tolerance=1e-12).reference).max() < bound
        assert full.failed_iterations == 0
    else:
        assert result is None and full.failed_iterations == 30


def test_the_extension_past_the_cap_is_checked() -> None:
    """A rate bound outside (0, 1) is refused, naming what was expected."""
    with pytest.raises(SolverError, match="expected max_iter >= 1, 0 < steady < 1"):
        NonlinearSolver(build_solver(_strip(axial=1.0, nx=6)), steady=1.2)
