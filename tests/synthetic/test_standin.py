"""The stand-in's part positions at the pads, its cache of serially run CalculiX responses and its embedded pads
(hood_decomp.synthetic.standin) against independent paths: the contact summary's lifted states, a counting stand-in
for CalculiX and the embedded solver's reduced model at a scaled thickness."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

from hood_decomp.core.fe.ensemble import solve_members, validation_plan
from hood_decomp.core.fe.solver import build_solver, force_boundary_loads, project, reduce_model
from hood_decomp.errors import SolverError
from hood_decomp.synthetic import standin
from tests.hood20 import hood20


def test_pad_positions_are_the_lifted_states_and_lie_below_a_touching_pad():
    """Fails if the part's position at a pad is not where a lifted pad's state is (the contact summary's z - preload,
    another path), or if a touching pad's position is not below its commanded position by its largest spring
    compression (pads swapped, wrong columns, max for min)."""
    case = hood20()
    model, reduced = case.model, case.reduced
    states = validation_plan(model.lower, model.upper, 40, seed=5)
    block = solve_members(reduced, states)
    position = standin.pad_positions(states, block.compression, reduced.pad_of)
    B = reduced.n_bilateral
    lifted = block.reactions <= 0
    assert lifted.any() and (~lifted).any()
    np.testing.assert_allclose(position[lifted], block.effective[:, B:][lifted], atol=1e-9)
    for u in range(position.shape[1]):
        largest = block.compression[:, reduced.pad_of == u].max(axis=1)
        touching = ~lifted[:, u]
        np.testing.assert_allclose(position[touching, u], states[touching, B + u] - largest[touching], atol=1e-9)
        assert (largest[touching] > 0).all()


def test_serial_responses_run_each_job_once_resume_complete_a_nominal_cache_and_check_the_model(tmp_path,
                                                                                                 monkeypatch):
    """Fails if a job stored by an interrupted run is run again, if a job runs at the wrong thickness or is stored
    under the wrong scale, if the cache lacks a job or holds a pad job, if session 14's nominal-only cache (no
    "scales"; jobs in <cache>.jobs/<model_id>/) is not completed from its jobs without rerunning them, if a complete
    cache is not read back without any job, if a cache lacking a scale is not completed, or if a cache of another model
    is used."""
    model = hood20().model
    thickness = model.parts[0].thickness
    runs: list[tuple[str, float]] = []

    def fake_run(scaled, case, constrained, timeout):
        scale = round(scaled.parts[0].thickness / thickness, 6)
        runs.append((case.name, scale))
        if case.name == "unit_LOCK_L" and scale == 1.05 and runs.count(runs[-1]) == 1:
            raise SolverError("interrupted")
        # a value naming the job and its scale: what the cache must hand back where
        return np.full((len(scaled.nodes), 3), len(case.name) + 100.0 * scale)

    monkeypatch.setattr(standin, "run_case", fake_run)
    names = {"load", "gas", *(f"unit_{p.label}" for p in model.bilateral)}
    cache = tmp_path / "responses.npz"
    # session 14's cache: the nominal jobs stored, the .npz without "scales"
    nominal = standin.serial_responses(model, cache, lock=tmp_path / "lock", scales=(1.0,))
    assert sorted(runs) == sorted((name, 1.0) for name in names) and cache.exists()
    np.savez(cache, model_id=np.array(model.model_id), **nominal[1.0])
    runs.clear()
    with pytest.raises(SolverError, match="interrupted"):
        standin.serial_responses(model, cache, lock=tmp_path / "lock")
    first = list(runs)
    out = standin.serial_responses(model, cache, lock=tmp_path / "lock")
    second = runs[len(first):]
    expected = {(name, s) for name in names for s in (0.95, 1.05)}
    assert set(second).isdisjoint(first[:-1]) and sorted(first[:-1] + second) == sorted(expected)
    assert set(out) == {0.95, 1.0, 1.05} and all(set(columns) == names for columns in out.values())
    for scale, columns in out.items():
        np.testing.assert_array_equal(columns["gas"], 3.0 + 100.0 * scale)
    done = len(runs)
    again = standin.serial_responses(model, cache)
    assert len(runs) == done and all(np.array_equal(again[s][n], out[s][n]) for s in out for n in names)
    # a cache with "scales" but not every scale asked for is completed (here from no jobs: all run)
    fewer = tmp_path / "fewer.npz"
    np.savez(fewer, model_id=np.array(model.model_id), scales=np.array([1.0]),
             **{f"1.0|{name}": value for name, value in again[1.0].items()})
    standin.serial_responses(model, fewer, scales=(1.0, 1.05))
    assert sorted(runs[done:]) == sorted((name, s) for name in names for s in (1.0, 1.05))
    other = tmp_path / "other.npz"
    np.savez(other, model_id=np.array("another"), **again[1.0])
    with pytest.raises(SolverError, match="model_id"):
        standin.serial_responses(model, other)


def test_stand_in_with_embedded_pads_is_the_embedded_solver_at_every_thickness():
    """Fails if the stand-in on embedded responses with the embedded solver's pads (embedded_pads) is not the
    embedded solver's reduced model at a scaled thickness (the interpolation's nodes exactly, a thickness between them
    to the interpolation's error), if a family's E, gas-spring force, pad stiffness or preload act wrongly, or if pad
    responses are mixed up with embedded_pads."""
    model = hood20().model
    responses = standin.embedded_responses(model)
    without_pads = {s: {k: v for k, v in columns.items() if not k.startswith("pad_")}
                    for s, columns in responses.items()}
    stand_in = standin.StandIn(model, without_pads, embedded_pads=True)
    with pytest.raises(SolverError, match="embedded_pads"):
        standin.StandIn(model, responses, embedded_pads=True)
    with pytest.raises(SolverError, match="embedded_pads=True"):
        standin.StandIn(model, without_pads)
    fields = ("w0", "R", "G", "z0", "Sa", "H", "w0_3d", "R_3d", "G_3d")
    for scale, rtol in ((0.95, 1e-9), (1.05, 1e-9), (0.98, 1e-3)):
        direct = reduce_model(build_solver(standin.scaled_thickness(model, scale), validate=False))
        part = stand_in.reduced(standin.Family(thickness=scale))
        for name in fields:
            expected = getattr(direct, name)
            np.testing.assert_allclose(getattr(part, name), expected, rtol=0, atol=rtol * np.abs(expected).max(),
                                       err_msg=f"{name} at thickness {scale}")
    nominal = reduce_model(build_solver(model, validate=False))
    gas = stand_in.reduced(standin.Family(gas_spring=1.1)).w0 - stand_in.reduced(standin.Family()).w0
    family = standin.Family(E=1.2, gas_spring=1.1, pad_stiffness=0.8, preload=1.5)
    part = stand_in.reduced(family)
    np.testing.assert_allclose(part.w0, (nominal.w0 + gas) / 1.2, atol=1e-9 * np.abs(nominal.w0).max())
    np.testing.assert_allclose(part.R, nominal.R, atol=1e-9 * np.abs(nominal.R).max())
    np.testing.assert_allclose(part.H, nominal.H / 1.2, atol=1e-9 * np.abs(nominal.H).max())
    np.testing.assert_allclose(part.k, nominal.k * 0.8)
    np.testing.assert_allclose(part.preload, nominal.preload * 1.5)
    # the gas springs' share: their force response on the nominal model (another path: the solver's own solve)
    solver = build_solver(model, validate=False)
    loads = np.zeros((len(model.nodes), 6))
    loads[:, :3] = force_boundary_loads(model)
    expected_gas = 0.1 * project(model, solver.pads, solver.solve(loads.ravel()).reshape(-1, 6)[:, :3, None])[0][:, 0]
    np.testing.assert_allclose(gas, expected_gas, atol=1e-9 * np.abs(expected_gas).max() + 1e-15)


def test_serial_responses_skip_a_job_another_process_finished_while_waiting_for_the_lock(tmp_path, monkeypatch):
    """Fails if a job stored by another process while this one waited for the lock is run again."""
    model = hood20().model
    runs: list[str] = []
    jobs = tmp_path / "responses.jobs" / model.model_id

    @contextlib.contextmanager
    def other_process_first(lock):
        # the other process held the lock and stored "load" at nominal thickness
        if not (jobs / "load.npy").exists():
            np.save(jobs / "load.npy", np.full((len(model.nodes), 3), 7.0))
        yield

    monkeypatch.setattr(standin, "holding", other_process_first)
    monkeypatch.setattr(standin, "run_case", lambda scaled, case, constrained, timeout: (
        runs.append(case.name) or np.zeros((len(scaled.nodes), 3))))
    out = standin.serial_responses(model, tmp_path / "responses.npz", lock=tmp_path / "lock", scales=(1.0,))
    assert "load" not in runs and len(runs) == len(out[1.0]) - 1
    np.testing.assert_array_equal(out[1.0]["load"], 7.0)
