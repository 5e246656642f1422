"""The stand-in's part positions at the pads and its cache of nominal CalculiX responses (hood_decomp.synthetic.standin)
against independent paths: the contact summary's lifted states, and a counting stand-in for CalculiX."""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.core.fe.ensemble import solve_members, validation_plan
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


def test_nominal_responses_run_each_job_once_resume_and_check_the_model(tmp_path, monkeypatch):
    """Fails if a job stored by an interrupted run is run again, if the cache lacks a job or holds a pad job, if a
    complete cache is not read back without any job, or if a cache of another model is used."""
    model = hood20().model
    runs: list[str] = []

    def fake_run(scaled, case, constrained, timeout):
        runs.append(case.name)
        if case.name == "unit_LOCK_L" and runs.count(case.name) == 1:
            raise SolverError("interrupted")
        return np.full((len(scaled.nodes), 3), float(len(case.name)))

    monkeypatch.setattr(standin, "run_case", fake_run)
    cache = tmp_path / "nominal.npz"
    with pytest.raises(SolverError, match="interrupted"):
        standin.nominal_responses(model, cache, lock=tmp_path / "lock")
    assert not cache.exists()
    first = list(runs)
    out = standin.nominal_responses(model, cache, lock=tmp_path / "lock")
    expected = {"load", "gas", *(f"unit_{p.label}" for p in model.bilateral)}
    assert set(out) == expected and cache.exists()
    second = runs[len(first):]
    assert set(second).isdisjoint(first[:-1]) and sorted(first[:-1] + second) == sorted(expected)
    np.testing.assert_array_equal(out["gas"], 3.0)
    done = len(runs)
    again = standin.nominal_responses(model, cache)
    assert len(runs) == done and set(again) == expected
    other = tmp_path / "other.npz"
    np.savez(other, model_id=np.array("another"), **again)
    with pytest.raises(SolverError, match="model_id"):
        standin.nominal_responses(model, other)
