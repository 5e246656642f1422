"""The hood-paper preset: the paper's boundary physics (rigid unilateral buffers, commanded states) on the same hood."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from hood_decomp.cli import main
from hood_decomp.core.fe.ensemble import factorial_plan, solve_members
from hood_decomp.core.fe.hood_preset import RIGID_PAD_STIFFNESS, build_hood, build_hood_paper
from hood_decomp.core.fe.solver import retarget_pads
from hood_decomp.errors import ModelError
from hood_decomp.io.bases import load_bases
from hood_decomp.io.model_files import load_model


def test_same_hood_other_boundary_physics() -> None:
    """Fails if hood-paper is not the same mesh as the default hood, or if either preset's buffers or state convention
    are not what they claim (the default must stay preloaded rubber pads with effective states)."""
    paper, default = build_hood_paper("coarse"), build_hood("coarse")
    assert paper.model_id == default.model_id and paper.name == "hood-paper-coarse"
    assert paper.parameter_states == "commanded" and default.parameter_states == "effective"
    buffers = {b.name: b for b in paper.boundaries if b.kind == "unilateral"}
    assert set(buffers) == {"buffer_L", "buffer_R"}
    assert all(b.stiffness == RIGID_PAD_STIFFNESS and b.preload == 0.0 for b in buffers.values())
    assert all(b.stiffness == 600.0 and b.preload == 0.15 for b in default.boundaries if b.kind == "unilateral")
    kinds = {b.name: (b.kind, b.dofs) for b in paper.boundaries}
    assert kinds["lock_L"] == ("prescribed", ("z",)) and kinds["lock_R"] == ("prescribed", ("z",))
    assert [b.force for b in paper.boundaries if b.kind == "force"] == [580.0, 580.0]


def test_buffers_are_rigid_converged_in_stiffness(coarse_hood_paper) -> None:
    """Fails if the buffer stiffness is not high enough to be rigid: making it 1000 times stiffer (1/k -> ~0, the
    rigid unilateral constraint of the LCP) must move no member of the 729 by more than 2e-6 mm nor change which pad
    springs touch."""
    reduced = coarse_hood_paper.reduced
    commanded, _ = factorial_plan(coarse_hood_paper.model.lower, coarse_hood_paper.model.upper)
    rigid = solve_members(reduced, commanded)
    stiffer = solve_members(replace(reduced, k=reduced.k * 1e3), commanded)
    assert np.abs(stiffer.normal_displacement - rigid.normal_displacement).max() < 2e-6
    assert np.array_equal(stiffer.pad_forces > 0, rigid.pad_forces > 0)
    # and the buffers do act: some members press a buffer with more than 500 N, others lift it off
    assert rigid.reactions.max() > 500.0 and (rigid.contact_fraction == 0).any()


def test_contact_solution_against_a_direct_solve(coarse_hood_paper) -> None:
    """Fails if a member is not the FE solution with the buffers as rigid unilateral displacement boundaries: for
    members that press, lift and tilt the buffers, the reaction forces applied to a direct solve of the full model
    (not the reduced model's superposition) must reproduce the member's skin field, leave no spring penetrating its
    buffer (gap >= -1e-5 mm), pull on none (f >= 0), and every loaded spring must touch (gap <= 1e-5 mm)."""
    case = coarse_hood_paper
    solver, reduced, model = case.solver, case.reduced, case.model
    names = list(model.names)
    settings = [{}, {"BUFFER_L": 1.0}, {"LOCK_L": -1.0, "LOCK_R": -1.0}, {"HINGE_Y": -1.0, "BUFFER_R": 1.0},
                {"LOCK_L": 1.0, "BUFFER_L": -1.0, "BUFFER_R": 1.0}]
    skin = model.skin_nodes
    normals = case.skin.normals
    for setting in settings:
        state = np.array([setting.get(n, 0.0) for n in names])
        member = solve_members(reduced, state[None, :])
        forces = member.pad_forces[0]
        prescribed = np.zeros(len(solver.constrained))
        for p, parameter in enumerate(model.bilateral):
            prescribed[np.isin(solver.constrained, solver.boundary_dofs(parameter.boundary, parameter.direction))] = \
                state[p]
        u = solver.solve(solver.load + solver.pads.loads @ forces, prescribed)
        translations = u.reshape(-1, 6)[:, :3]
        normal = np.einsum("na,na->n", translations[skin], normals)
        assert np.abs(normal - member.normal_displacement[0]).max() < 1e-6, setting
        gap = solver.pads.loads.T @ u - state[reduced.n_bilateral:][solver.pads.pad_of]
        assert gap.min() > -1e-5 and forces.min() >= 0.0, setting
        assert np.all(gap[forces > 0] < 1e-5), setting
    # no preload: at the nominal state the loads lift the front off both buffers, so the rank-0 member is the loads'
    # response with no buffer at all
    assert np.allclose(case.ensemble.normal_displacement[0], reduced.w0, atol=1e-12)
    assert case.ensemble.contact_fraction[0].tolist() == [0.0, 0.0]


def test_held_buffers_are_bilateral_displacement_boundaries(coarse_hood_paper) -> None:
    """Fails if ``buffers="held"`` is not each buffer as a bilateral displacement boundary at its commanded position
    (bench_paper's no-contact control): every pad spring must sit at the commanded position (within 1e-5 mm: the
    rigid spring's 1/k), some must pull, and the members must be affine in the state (superposition: the second
    difference u(a + b) - u(a) - u(b) + u(0) below 1e-6 mm) for a lock-buffer pair whose unilateral members interact by
    more than 0.1 mm (contact). Bad ``buffers`` values are refused."""
    from hood_decomp.core.fe.contact import contact_state
    from hood_decomp.errors import EnsembleError

    reduced = coarse_hood_paper.reduced
    names = list(reduced.names)
    B = reduced.n_bilateral
    a, b = np.zeros(len(names)), np.zeros(len(names))
    a[names.index("LOCK_L")], b[names.index("BUFFER_L")] = -1.0, 1.0
    states = np.array([a + b, a, b, np.zeros(len(names))])
    for state in states:
        held = contact_state(reduced, state[:B], state[B:], held=True)
        assert np.abs(held.z - state[B:][reduced.pad_of]).max() < 1e-5
    held = solve_members(reduced, states, buffers="held")
    assert (held.pad_forces < 0).any()
    second = np.array([1.0, -1.0, -1.0, 1.0]) @ held.normal_displacement
    assert np.abs(second).max() < 1e-6
    unilateral = np.array([1.0, -1.0, -1.0, 1.0]) @ solve_members(reduced, states).normal_displacement
    assert np.abs(unilateral).max() > 0.1
    with pytest.raises(EnsembleError, match="buffers"):
        solve_members(reduced, states, buffers="glued")


def test_retargeted_pads_equal_a_fresh_reduction(coarse_hood, coarse_hood_paper) -> None:
    """Fails if retarget_pads (hood-paper's reduced model from the default hood's, no solve) differs from a full
    reduction of hood-paper, or accepts a model whose pads are laid out otherwise."""
    retargeted = retarget_pads(coarse_hood.reduced, coarse_hood_paper.model)
    fresh = coarse_hood_paper.reduced
    assert retargeted.parameter_states == "commanded" and np.array_equal(retargeted.k, fresh.k)
    assert np.array_equal(retargeted.preload, fresh.preload) and np.allclose(retargeted.G, fresh.G, atol=1e-12)
    with pytest.raises(ModelError, match="another layout"):
        retarget_pads(coarse_hood.reduced, coarse_hood_paper.model, pad_lattice=3)


def test_states_are_commanded_with_the_lifted_flag_kept(coarse_hood_paper, coarse_hood) -> None:
    """Fails if hood-paper's ensemble records a lifted buffer's state as the part's position (the default hood's
    convention) instead of the commanded one, or loses the lifted flag; or if the default hood's convention changed."""
    paper = coarse_hood_paper.ensemble
    assert np.array_equal(paper.effective, paper.commanded)
    lifted = paper.contact_fraction == 0
    assert lifted.any() and (~lifted).any()
    lowered = np.flatnonzero((paper.rank == 1) & (paper.commanded[:, 4] == -1.0))
    assert lowered.size == 1 and lifted[lowered[0], 0]  # the lowered left buffer alone does not touch the hood
    default = coarse_hood.ensemble
    lifted_default = default.contact_fraction == 0
    assert np.all(default.effective[:, 4:][lifted_default] > default.commanded[:, 4:][lifted_default])


def test_command_line_on_hood_paper(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Fails if `model --preset hood-paper` does not write the paper physics to model.yaml, or if a verb downstream
    (simulate, ensemble, bases, estimate, decompose) does not run on it unchanged; the estimate of a simulated field
    must recover its bilateral states and flag the lowered buffer as lifted."""
    model_dir = tmp_path / "paper"
    assert main(["model", "--preset", "hood-paper", "--resolution", "coarse", "--out", str(model_dir)]) == 0
    document = yaml.safe_load((model_dir / "model.yaml").read_text())
    assert document["parameter_states"] == "commanded"
    assert load_model(model_dir).parameter_states == "commanded"
    field, store, bases = tmp_path / "f.vtu", tmp_path / "e.h5", tmp_path / "b.h5"
    setting = "HINGE_Y=0.4,LOCK_L=-0.7,LOCK_R=-0.5,BUFFER_L=-0.9,BUFFER_R=0.3"
    assert main(["simulate", "--model", str(model_dir), "--set", setting, "--out", str(field)]) == 0
    assert main(["ensemble", "--model", str(model_dir), "--out", str(store), "--validation", "3"]) == 0
    assert main(["bases", "--ensemble", str(store), "--model", str(model_dir), "--out", str(bases)]) == 0
    assert load_bases(bases).reduced_model.parameter_states == "commanded"
    capsys.readouterr()
    assert main(["estimate", "--bases", str(bases), "--field", str(field)]) == 0
    estimate = json.loads(capsys.readouterr().out)
    values = estimate["parameters_mm"]
    for label, truth in (("HINGE_X", 0.0), ("HINGE_Y", 0.4), ("LOCK_L", -0.7), ("LOCK_R", -0.5), ("BUFFER_R", 0.3)):
        assert values[label] == pytest.approx(truth, abs=1e-3), label
    assert estimate["lifted"]["BUFFER_L"] is True and values["BUFFER_L"] > -0.9 + 1e-3
    assert main(["decompose", "--bases", str(bases), "--field", str(field)]) == 0
    decomposition = json.loads(capsys.readouterr().out)
    assert decomposition["reconstruction_rms_mm"] < 0.01


@pytest.fixture(scope="module")
def ccx_rank0(coarse_hood_paper):
    """CalculiX's rank-0 member of the coarse hood-paper (both buffers lifted, nothing held): one ccx job."""
    from hood_decomp.core.fe.calculix import check_contact_set
    from tests.required import ensure_ccx

    ensure_ccx()
    case = coarse_hood_paper
    names = list(case.model.names)
    members = solve_members(case.reduced, np.zeros((1, len(names))))
    return check_contact_set(case.model, np.zeros(len(names)), members.pad_forces[0], case.skin.normals)


def test_rigid_buffer_member_against_calculix(coarse_hood_paper, ccx_rank0) -> None:
    """Fails if a hood-paper member whose left buffer pushes (BUFFER_L = +1 mm) is not CalculiX's contact solution
    too: CalculiX (S8R, linear) holding exactly the pad springs (here one node each) the LCP says push must find them
    pushing (no pull beyond 2 % of the buffer load) and every other pad node clear of its buffer (no sinking beyond
    2e-3 mm: the contact edge's node, 0.2 % of the 1 mm motion; a wrong contact edge sinks by 0.01 mm or more), with
    the buffer's total reaction within 4 % and the member's response (member minus the rank-0 member, both from
    CalculiX) within 5 % of its peak at every node and within 1.5 % in RMS (a global difference, not one at the lock
    reinforcement's edge, would fail it), its 3D translations consistent with the normal field. Measured: reaction
    250 vs 256 N, held springs' smallest reaction -0.07 N, a free edge node 0.0014 mm below the buffer (springs held
    by *EQUATION; 0.003 mm above it when the nodes were held by *BOUNDARY: ccx ties a shell node's expanded nodes
    differently for the two), response 3.9 % at the worst node (2 mm outside
    the lock reinforcement), 0.93 % RMS (the issue's 3 % is not met on this member's coarse grid: 2.6 % on 101 x
    117, RESULTS.md)."""
    from hood_decomp.core.fe.calculix import check_contact_set

    case = coarse_hood_paper
    names = list(case.model.names)
    state = np.zeros(len(names))
    state[names.index("BUFFER_L")] = 1.0
    members = solve_members(case.reduced, np.stack([np.zeros(len(names)), state]))
    base = ccx_rank0
    pushed = check_contact_set(case.model, state, members.pad_forces[1], case.skin.normals)
    assert not any(t.any() for t in base.touching) and pushed.touching[0].any() and not pushed.touching[1].any()
    load = members.reactions[1, 0]
    assert load > 100.0 and pushed.certified(0.02 * load, 2e-3)
    assert pushed.reaction[0] == pytest.approx(load, rel=0.04)
    ours = members.normal_displacement[1] - members.normal_displacement[0]
    theirs = pushed.normal - base.normal
    assert np.abs(theirs - ours).max() < 0.05 * np.abs(ours).max()
    assert np.sqrt(np.mean((theirs - ours) ** 2)) < 0.015 * np.abs(ours).max()
    assert np.allclose(np.einsum("na,na->n", pushed.skin_displacement, case.skin.normals), pushed.normal)


def test_held_spring_is_the_weighted_mean_of_its_nodes_in_calculix(coarse_hood_paper, ccx_rank0) -> None:
    """Fails if CalculiX's held pad spring is not the embedded solver's rigid spring where a spring averages several
    nodes (the finer meshes' case; here one spring per buffer over all 14 coarse pad nodes, pad_lattice 1): its
    *EQUATION must hold the area-weighted mean of the nodes at the commanded position (wrong weights, an unnormalised
    sum, or the reference held elsewhere would move the patch), and the spring's reaction read back from the pad
    nodes' element forces must be ours within 4 % and push (a sign or a node-set error fails), with the response
    (member minus rank 0) within 5 % of its peak and 1.5 % in RMS, as the one-node springs of the test above.
    Measured: 163.3 vs 162.0 N, response 3.4 % of its 0.69 mm peak, 1.0 % RMS."""
    from hood_decomp.core.fe.calculix import check_contact_set
    from hood_decomp.core.fe.solver import build_solver, reduce_model

    case = coarse_hood_paper
    names = list(case.model.names)
    state = np.zeros(len(names))
    state[names.index("BUFFER_L")] = 1.0
    reduced = reduce_model(build_solver(case.model, pad_lattice=1))
    members = solve_members(reduced, np.stack([np.zeros(len(names)), state]))
    assert members.pad_forces.shape == (2, 2) and members.pad_forces[1, 0] > 100.0 and members.pad_forces[1, 1] == 0
    pushed = check_contact_set(case.model, state, members.pad_forces[1], case.skin.normals, pad_lattice=1)
    assert pushed.touching[0].sum() > 10 and not pushed.touching[1].any()
    assert pushed.spring_reaction[0] == pytest.approx(members.pad_forces[1, 0], rel=0.04)
    assert pushed.certified(0.02 * members.pad_forces[1, 0])
    ours = members.normal_displacement[1] - members.normal_displacement[0]
    theirs = pushed.normal - ccx_rank0.normal
    assert np.abs(theirs - ours).max() < 0.05 * np.abs(ours).max()
    assert np.sqrt(np.mean((theirs - ours) ** 2)) < 0.015 * np.abs(ours).max()
