"""Candidate effects on the smallest hood the preset builds (20 x 20 skin nodes, a fraction of a second): what is
enumerated and how it is described, the parsing of user candidates, the responses and the augmented model.

Written against the survivors of benchmarks/mutation.py. References are independent of candidates.py: the hood's
declared boundaries and parameters (the module docstring's rule), ``reduce_model(solver, extra=...)`` for motion
columns, a model whose gas spring pushes harder (factorised anew) for a force column, and the solver's own
per-axis force responses for an oblique force.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from hood_decomp.core.fe.hood_preset import build_hood
from hood_decomp.core.fe.model import skin_surface
from hood_decomp.core.fe.solver import build_solver, reduce_model
from hood_decomp.core.loop import candidates as cd
from hood_decomp.core.loop.candidates import (
    Candidate,
    CandidateFields,
    augment_reduced,
    candidate_fields,
    candidate_response,
    candidates_from_document,
    enumerate_candidates,
    force,
    motion,
)
from hood_decomp.errors import ModelError

ENUMERATED = (
    "hinge_R.x", "hinge_R.y", "hinge_R.z", "hinge_L.z", "lock_L.x", "lock_L.y", "lock_R.x", "lock_R.y",
    "buffer_L.x", "buffer_L.y", "buffer_L.stick", "buffer_R.x", "buffer_R.y", "buffer_R.stick",
    "gas_spring_L.force", "gas_spring_R.force",
)


@pytest.fixture(scope="module")
def tiny():
    model = build_hood("coarse", grid=(20, 20))
    solver = build_solver(model)
    return model, solver, reduce_model(solver)


@pytest.fixture(scope="module")
def fields(tiny):
    model, solver, _ = tiny
    return candidate_fields(solver, enumerate_candidates(model))


def test_enumerated_candidates_and_their_order(tiny):
    """Fails if the candidates are not every undeclared boundary translation, every pad's stick force and every
    force boundary's force, in the model's boundary order (x, y, z within a boundary)."""
    model, _, _ = tiny
    found = enumerate_candidates(model)
    assert tuple(c.name for c in found) == ENUMERATED
    kinds = {c.name: c.kind for c in found}
    assert {n for n, k in kinds.items() if k == "force"} == {"buffer_L.stick", "buffer_R.stick",
                                                             "gas_spring_L.force", "gas_spring_R.force"}
    by_name = {c.name: c for c in found}
    assert by_name["hinge_R.z"].description == "hinge_R moves along z (held)"
    assert by_name["lock_L.x"].description == "lock_L moves along x (in-plane, not constrained)"
    assert by_name["buffer_L.y"].description == "pad buffer_L drags the part along y"
    assert by_name["buffer_R.stick"].description.startswith("extra force of pad buffer_R along its axis")
    assert by_name["gas_spring_L.force"].description == "force of gas_spring_L changes"
    gas = next(b for b in model.boundaries if b.name == "gas_spring_L")
    assert by_name["gas_spring_L.force"].axis == pytest.approx(gas.axis)
    assert by_name["buffer_L.stick"].axis == pytest.approx((0.0, 0.0, 1.0))
    assert all(c.boundary == c.name.split(".")[0] for c in found)


def test_user_candidates_replace_by_name_and_need_a_boundary(tiny):
    """Fails if a user candidate does not replace the enumerated one of the same name (in its place) or is not
    appended, or if one on an unknown boundary is accepted."""
    model, _, _ = tiny
    mine = motion("lock_L", "x", "mine")
    extra = force("lock_R", (0.0, 1.0, 0.0), "lock_R.push", "push")
    found = enumerate_candidates(model, [mine, extra])
    assert tuple(c.name for c in found) == (*ENUMERATED, "lock_R.push")
    assert found[ENUMERATED.index("lock_L.x")].description == "mine"
    with pytest.raises(ModelError):
        enumerate_candidates(model, [motion("nowhere", "x")])


def test_candidate_properties():
    """Fails if a candidate's unit or coordinate direction is wrong, or motion/force do not build what they say."""
    for direction, axis in (("x", (1.0, 0.0, 0.0)), ("y", (0.0, 1.0, 0.0)), ("z", (0.0, 0.0, 1.0))):
        c = motion("b", direction)
        assert (c.name, c.kind, c.axis, c.unit, c.direction) == (f"b.{direction}", "motion", axis, "mm", direction)
        assert c.description == f"b moves along {direction}"
    f = force("b", [0.0, -3.0, 4.0], "b.f", "d")
    assert f.axis == pytest.approx((0.0, -0.6, 0.8)) and f.unit == "N" and f.direction == "z"
    assert force("b", [-5.0, 1.0, 0.0], "b.f", "d").direction == "x"
    assert (cd.KINDS, cd.UNITS) == (("motion", "force"), {"motion": "mm", "force": "N"})


@pytest.mark.parametrize("axis", [[0.0, 0.0, 0.0], [1.0, 2.0], [np.inf, 0.0, 0.0], [np.nan, 1.0, 0.0]])
def test_force_axis_must_be_a_finite_nonzero_3_vector(axis):
    """Fails if a zero, short or non-finite force axis is accepted."""
    with pytest.raises(ModelError, match="non-zero 3-vector"):
        force("b", axis, "b.f", "d")


def test_motion_direction_must_be_an_axis():
    """Fails if a motion along anything but x, y, z is accepted."""
    with pytest.raises(ModelError, match="must be x, y or z"):
        motion("b", "w")


def test_candidates_from_document():
    """Fails if model.yaml's candidates list is not parsed as documented (names, axes, units, descriptions)."""
    assert candidates_from_document(None) == ()
    parsed = candidates_from_document([
        {"boundary": "lock_L", "kind": "force", "direction": "Y"},
        {"boundary": "hinge_L", "kind": "force", "axis": [0, 3, 4], "description": "oblique"},
        {"boundary": "lock_R", "kind": "motion", "direction": "x", "name": "lock_R.slide"},
        {"boundary": "hinge_R", "kind": "force", "axis": (1.5, 0, 0)},
    ])
    assert [c.name for c in parsed] == ["lock_L.force_y", "hinge_L.force[0,3,4]", "lock_R.slide",
                                        "hinge_R.force[1.5,0,0]"]
    assert [c.kind for c in parsed] == ["force", "force", "motion", "force"]
    assert parsed[0].axis == (0.0, 1.0, 0.0) and parsed[0].description == "force on lock_L along y"
    assert parsed[1].axis == pytest.approx((0.0, 0.6, 0.8)) and parsed[1].description == "oblique"
    assert parsed[2].description == "lock_R moves along x" and parsed[2].axis == (1.0, 0.0, 0.0)
    assert parsed[3].description == "force on hinge_R" and parsed[3].axis == (1.0, 0.0, 0.0)


@pytest.mark.parametrize("entries, message", [
    ({"boundary": "a"}, "must be a list, got dict"),
    (["lock_L"], "entry #0"),
    ([{"kind": "force", "direction": "x"}], "entry #0"),
    ([{"boundary": "a", "kind": "motion", "direction": "x"}, {"boundary": "a", "kind": "push"}], "entry #1"),
    ([{"boundary": "a", "kind": "force", "axis": [1, 0]}], "axis must be 3 numbers"),
    ([{"boundary": "a", "kind": "force", "axis": "x"}], "axis must be 3 numbers"),
    ([{"boundary": "a", "kind": "force", "direction": "w"}], "needs 'direction'"),
    ([{"boundary": "a", "kind": "force"}], "needs 'direction'"),
])
def test_bad_candidate_entries_are_named(entries, message):
    """Fails if a malformed candidates entry is accepted or the error does not name it."""
    with pytest.raises(ModelError, match=message):
        candidates_from_document(entries)


def test_motion_columns_are_the_ones_reduce_model_builds(tiny, fields):
    """Fails if a motion candidate's skin, 3D and pad columns differ from reduce_model(extra=...)'s."""
    model, solver, reduced = tiny
    extra = [("hinge_R", "z"), ("lock_L", "x"), ("buffer_L", "y")]
    reference = reduce_model(solver, extra=extra)
    augmented = augment_reduced(reduced, fields, [f"{b}.{d}" for b, d in extra])
    assert augmented.names == reference.names and augmented.n_bilateral == reference.n_bilateral
    for name in ("R", "Sa", "R_3d", "G", "H", "w0", "z0"):
        np.testing.assert_allclose(getattr(augmented, name), getattr(reference, name), rtol=0, atol=1e-12)
    skin = skin_surface(model)
    column = fields.index("hinge_R.z")
    np.testing.assert_allclose(np.einsum("na,na->n", fields.vectors[:, :, column], skin.normals),
                               fields.normal[:, column], atol=1e-12)


def test_force_column_is_the_field_of_a_changed_load(tiny, fields):
    """Fails if a force candidate's skin or pad column is not the change of the load response per newton (a model
    whose gas spring pushes 50 N harder, factorised anew)."""
    model, _, reduced = tiny
    boundaries = tuple(dataclasses.replace(b, force=b.force + 50.0) if b.name == "gas_spring_L" else b
                       for b in model.boundaries)
    changed = reduce_model(build_solver(dataclasses.replace(model, boundaries=boundaries)))
    column = fields.index("gas_spring_L.force")
    scale = np.abs(fields.normal[:, column]).max()
    np.testing.assert_allclose((changed.w0 - reduced.w0) / 50.0, fields.normal[:, column], atol=1e-9 * scale)
    np.testing.assert_allclose((changed.z0 - reduced.z0) / 50.0, fields.pad[:, column],
                               atol=1e-9 * np.abs(fields.pad[:, column]).max())


def test_oblique_force_combines_the_coordinate_responses(tiny):
    """Fails if a force along (0.6, 0, 0.8) is not 0.6 x the x response + 0.8 x the z response of the solver (and a
    zero component contributes nothing, not even a solve)."""
    _, solver, _ = tiny
    oblique = force("lock_R", (3.0, 0.0, 4.0), "lock_R.f", "d")
    expected = 0.6 * solver.force_response("lock_R", "x") + 0.8 * solver.force_response("lock_R", "z")
    np.testing.assert_allclose(candidate_response(solver, oblique), expected, atol=1e-12 * np.abs(expected).max())
    calls = []
    original = solver.force_response

    class Spy:
        def __getattr__(self, name):
            return getattr(solver, name)

        def force_response(self, boundary, direction):
            calls.append(direction)
            return original(boundary, direction)

    candidate_response(Spy(), force("lock_R", (0.0, 0.0, 2.0), "lock_R.z", "d"))
    assert calls == ["z"]
    np.testing.assert_allclose(candidate_response(solver, motion("lock_R", "x")),
                               solver.boundary_response("lock_R", "x"))


def test_candidates_that_move_nothing_are_dropped(tiny, caplog):
    """Fails if a candidate without any skin response (a force on a boundary that holds every direction) is kept,
    or one that moves the skin is dropped; or if the solves are not logged one by one."""
    model, solver, _ = tiny
    held = force("hinge_R", (0.0, 0.0, 1.0), "hinge_R.push", "d")
    chosen = [motion("lock_L", "x"), held, force("gas_spring_R", (0.0, 0.0, 1.0), "gas_spring_R.z", "d")]
    with caplog.at_level(logging.INFO, logger="hood_decomp.core.loop.candidates"):
        result = candidate_fields(solver, chosen)
    assert result.names == ("lock_L.x", "gas_spring_R.z") and result.dropped == ("hinge_R.push",)
    assert result.normal.shape == (len(model.skin_nodes), 2) and result.vectors.shape == (len(model.skin_nodes), 3, 2)
    assert result.pad.shape[1] == 2
    messages = [r.getMessage() for r in caplog.records]
    assert messages == ["candidate 1/3 lock_L.x solved", "candidate 2/3 hinge_R.push solved",
                        "candidate 3/3 gas_spring_R.z solved"]
    with pytest.raises(ModelError, match="no candidate effects"):
        candidate_fields(solver, [])
    assert cd.NEGLIGIBLE_RTOL == 1e-9


def test_negligible_is_relative_to_the_largest_candidate(tiny):
    """Fails if a candidate is dropped unless its largest response is below NEGLIGIBLE_RTOL of the largest one's:
    scaled copies of one response 1e-8 and 1e-10 times smaller are kept and dropped."""
    _, solver, _ = tiny
    base = force("lock_R", (1.0, 0.0, 0.0), "big", "d")  # lock_R holds z only
    result = candidate_fields(solver, [base, force("lock_R", (1.0, 0.0, 0.0), "same", "d")])
    assert result.names == ("big", "same")

    class Scaled:
        def __getattr__(self, name):
            return getattr(solver, name)

        def force_response(self, boundary, direction):
            return scale[0] * solver.force_response(boundary, direction)

    scale = [1.0]
    responses = []
    for factor in (1.0, 1e-8, 1e-10):
        scale[0] = factor
        responses.append(candidate_response(Scaled(), base))

    class Fixed:
        def __getattr__(self, name):
            return getattr(solver, name)

        def force_response(self, boundary, direction):
            return responses[int(boundary[-1])]

    fixed = [force(f"lock_{i}", (1.0, 0.0, 0.0), f"c{i}", "d") for i in range(3)]
    result = candidate_fields(Fixed(), fixed)
    assert result.names == ("c0", "c1") and result.dropped == ("c2",)


def test_names_and_index(fields):
    """Fails if CandidateFields does not name its candidates in order or does not refuse an unknown one."""
    assert fields.names == ENUMERATED
    assert fields.index("lock_L.x") == ENUMERATED.index("lock_L.x")
    assert fields.index("gas_spring_R.force") == len(ENUMERATED) - 1
    with pytest.raises(ModelError, match="unknown candidate 'nope'"):
        fields.index("nope")
    assert isinstance(fields, CandidateFields) and all(isinstance(c, Candidate) for c in fields.candidates)


def test_augmented_model_puts_new_inputs_after_the_bilateral_ones(tiny, fields):
    """Fails if augment_reduced does not insert the candidates (in the given order) between the bilateral and the
    unilateral inputs with their columns, or accepts one already in the model or unknown."""
    _, _, reduced = tiny
    names = ["gas_spring_R.force", "hinge_R.x"]
    augmented = augment_reduced(reduced, fields, names)
    b = reduced.n_bilateral
    assert augmented.names == (*reduced.names[:b], *names, *reduced.names[b:])
    assert augmented.n_bilateral == b + 2
    columns = [fields.index(n) for n in names]
    np.testing.assert_array_equal(augmented.R, np.hstack([reduced.R, fields.normal[:, columns]]))
    np.testing.assert_array_equal(augmented.Sa, np.hstack([reduced.Sa, fields.pad[:, columns]]))
    np.testing.assert_array_equal(augmented.R_3d[:, :, b:], fields.vectors[:, :, columns])
    np.testing.assert_array_equal(augmented.G, reduced.G)
    with pytest.raises(ModelError, match="already inputs of the model"):
        augment_reduced(augmented, fields, ["hinge_R.x"])
    with pytest.raises(ModelError, match="unknown candidate"):
        augment_reduced(reduced, fields, ["nope"])


def test_candidates_are_frozen():
    """Fails if a candidate can be changed after it was made (or is not hashable)."""
    c = motion("b", "x")
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.name = "other"
    assert hash(c) == hash(motion("b", "x"))


@pytest.mark.parametrize("axis", [[1.0, 0.0, 0.0, 0.0], [[1.0], [0.0], [0.0]]])
def test_force_axis_must_have_shape_3(axis):
    """Fails if a 4-vector or a 3 x 1 column is accepted as a force axis."""
    with pytest.raises(ModelError, match="non-zero 3-vector"):
        force("b", axis, "b.f", "d")


def test_only_candidates_that_move_nothing_are_all_dropped(tiny):
    """Fails if candidates whose skin response is zero are kept when no candidate moves anything."""
    _, solver, _ = tiny
    held = force("hinge_R", (0.0, 0.0, 1.0), "hinge_R.push_z", "pushes a held direction")
    fields = candidate_fields(solver, [held])
    assert fields.dropped == ("hinge_R.push_z",) and fields.candidates == ()


def test_augmenting_with_a_declared_name_names_it(tiny):
    """Fails if the error for candidates already in the model does not name exactly those."""
    model, solver, reduced = tiny
    fields = candidate_fields(solver, enumerate_candidates(model))
    with pytest.raises(ModelError, match=r"candidates \['HINGE_X'\] are already inputs"):
        augment_reduced(reduced, fields, ["hinge_R.z", "HINGE_X"])


def test_a_model_without_pads_has_no_pad_rows(tiny):
    """Fails if candidate responses of a model without unilateral boundaries do not have zero pad rows."""
    model, _, _ = tiny
    pads = {b.name for b in model.boundaries if b.kind == "unilateral"}
    padless = dataclasses.replace(model, boundaries=tuple(b for b in model.boundaries if b.name not in pads),
                                  parameters=tuple(p for p in model.parameters if p.boundary not in pads))
    fields = candidate_fields(build_solver(padless), [motion("hinge_R", "z")])
    assert fields.pad.shape == (0, 1) and fields.normal.shape[1] == 1
