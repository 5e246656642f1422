"""HierarchicalBasis against a brute-force reference of its greedy loop, its growing orthonormal span, scale
invariance and refused designs.

Written against the survivors of benchmarks/mutation.py. The reference (``greedy_reference``) follows the module
docstring with plain numpy least squares on the member fields (no orthonormal span, no rank-one updates); the
ensembles are random fields on a full-factorial design, so every member is its own effect and the partners are
independent (unlike the linear and bilinear toy models, where most of them are dependent).
"""

from __future__ import annotations

import itertools
import warnings
from dataclasses import replace

import numpy as np
import pytest

from hood_decomp.core.method.hierarchical import DEPENDENT_RTOL, LOADS, HierarchicalBasis, _GreedyBuild
from hood_decomp.core.types import Ensemble
from hood_decomp.errors import BasisError
from tests.toy_models import full_factorial, make_skin, smooth_fields


def random_ensemble(n_params: int, seed: int, loads: bool = True, scale: float = 1.0) -> Ensemble:
    """A full-factorial design over {-1, 0, 1}^P whose members are unrelated smooth random fields (peak ~1 mm)."""
    skin = make_skin(12, 8)
    rng = np.random.default_rng(seed)
    states, rank = full_factorial(n_params)
    m = len(states)
    normal = scale * smooth_fields(skin.points, m, rng)
    if not loads:
        normal[rank == 0] = 0.0
    return Ensemble(model_id=skin.model_id, names=tuple(f"P{i}" for i in range(n_params)), n_bilateral=n_params,
                    lower=-np.ones(n_params), upper=np.ones(n_params), commanded=states, effective=states.copy(),
                    contact_fraction=np.zeros((m, 0)), reactions=np.zeros((m, 0)), rank=rank,
                    normal_displacement=normal, displacement=normal[:, :, None] * skin.normals)


def _outside(vector: np.ndarray, span: list[np.ndarray]) -> np.ndarray:
    if not span:
        return vector
    a = np.array(span)
    return vector - np.linalg.lstsq(a.T, vector, rcond=None)[0] @ a


def factorial_interaction(x: np.ndarray, commanded: np.ndarray, m: int) -> np.ndarray:
    """Sum over the subsets T of member m's non-zero parameters of (-1)^(|S| - |T|) u(a_T), by itertools."""
    used = np.flatnonzero(commanded[m])
    total = np.zeros(x.shape[1])
    for size in range(used.size + 1):
        for subset in itertools.combinations(used, size):
            state = np.zeros_like(commanded[m])
            state[list(subset)] = commanded[m][list(subset)]
            j = int(np.flatnonzero(np.all(commanded == state, axis=1))[0])
            total += (-1.0) ** (used.size - size) * x[j]
    return total


def greedy_reference(ensemble: Ensemble, epsilon: float):
    """The greedy loop of the module docstring done plainly. Returns (effect masks, effect ranks, fields (F, N),
    independent (F,), members (F,), per rank the final worst error)."""
    x, commanded, rank = ensemble.normal_displacement, ensemble.commanded, ensemble.rank
    n_params = commanded.shape[1]
    fields, independent, members, masks, ranks, effect_fields = [], [], [], [], [], []

    def add(vector, member):
        span = [f for f, ind in zip(fields, independent, strict=True) if ind]
        independent.append(bool(np.linalg.norm(_outside(vector, span)) > DEPENDENT_RTOL * np.linalg.norm(vector)))
        fields.append(vector)
        members.append(member)
        return len(fields) - 1

    origin = int(np.flatnonzero(rank == 0)[0])
    if np.abs(x[origin]).max() > 1e-12:
        effect_fields.append([add(x[origin], origin)])
        masks.append(np.zeros(n_params, bool))
        ranks.append(0)
    for p in range(n_params):
        pair = []
        for sign in (1.0, -1.0):
            m = int(np.flatnonzero((rank == 1) & (np.sign(commanded[:, p]) == sign))[0])
            pair.append(add(x[m] - x[origin], m))
        effect_fields.append(pair)
        masks.append(np.arange(n_params) == p)
        ranks.append(1)
    worst_of_rank = np.zeros(int(rank.max()) + 1)
    for r in range(2, int(rank.max()) + 1):
        group = np.flatnonzero(rank == r)
        while True:
            span = [f for f, ind in zip(fields, independent, strict=True) if ind]
            errors = np.array([np.abs(_outside(x[m], span)).max() for m in group])
            worst = int(np.argmax(errors))
            if errors[worst] <= epsilon:
                worst_of_rank[r] = errors[worst]
                break
            m = int(group[worst])
            mask = commanded[m] != 0
            partner = [int(j) for j in group if np.all(commanded[j] == -commanded[m])]
            sub = [fields[i] for e, emask in enumerate(masks) if not np.any(emask & ~mask)
                   for i in effect_fields[e] if independent[i]]
            interactions = {j: factorial_interaction(x, commanded, j) for j in [m, *partner[:1]]}
            effect_fields.append([add(i + _outside(x[j] - i, sub), j) for j, i in interactions.items()])
            masks.append(mask)
            ranks.append(r)
    return np.array(masks), np.array(ranks), np.array(fields), np.array(independent), np.array(members), worst_of_rank


def test_span_buffer_stays_orthonormal_and_grows_by_doubling():
    """Fails if the private span Q of the greedy build loses orthonormality, counts its rows wrongly or does not
    double its buffer exactly when it is full (1 parameter: room for 4 rows at first)."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(9, 40))
    build = _GreedyBuild(x, n_params=1)
    assert build.q.shape == (4, 40) and build.k == 0
    for i in range(9):
        build.add(x[i], build.eye[i], i)
        assert build.k == i + 1
        assert build.q.shape[0] == (4 if i < 4 else 8 if i < 8 else 16)
        q = build.q[: build.k]
        np.testing.assert_allclose(q @ q.T, np.eye(build.k), atol=1e-13)
    np.testing.assert_allclose(build.q[build.k:], 0.0)
    # the span of Q is the span of the members added
    np.testing.assert_allclose(x - (x @ build.q[:9].T) @ build.q[:9], 0.0, atol=1e-12)


def test_nearly_dependent_fields_are_orthogonalised_twice():
    """Fails if Q stops being orthonormal to 1e-14 when each new field lies within 1e-4 of the current span (one
    Gram-Schmidt pass loses orthogonality in proportion to that ratio; the second pass restores it)."""
    rng = np.random.default_rng(1)
    vectors = list(rng.normal(size=(3, 200)))
    for _ in range(6):
        inside = rng.normal(size=len(vectors)) @ np.array(vectors)
        vectors.append(inside + 1e-4 * np.linalg.norm(inside) / np.sqrt(200) * rng.normal(size=200))
    build = _GreedyBuild(np.array(vectors), n_params=4)
    for i, vector in enumerate(vectors):
        build.add(vector, build.eye[i], i)
    q = build.q[: build.k]
    assert build.k == len(vectors)
    assert np.abs(q @ q.T - np.eye(build.k)).max() < 1e-14


def test_a_field_is_dependent_relative_to_its_own_size():
    """Fails if the dependence test is not relative to the field's norm: a 1e-9 mm field outside the span is a new
    direction, however small."""
    x = np.array([[1e-9, 0.0, 0.0], [0.0, 1e-9, 0.0], [1e-9, 1e-9 * (1 + 1e-3), 0.0]])
    build = _GreedyBuild(x, n_params=1)
    for i in range(3):
        build.add(x[i], build.eye[i], i)
    assert build.independent == [True, True, False]
    build.add(np.array([0.0, 0.0, 1e-12]), np.zeros(3), 0)
    assert build.independent[-1] and build.k == 3


@pytest.mark.parametrize("n_params, seed", [(2, 3), (3, 4)])
def test_matches_the_brute_force_greedy_loop(n_params, seed):
    """Fails if any effect, its rank, its basis fields (values and defining members), their independence or the
    per-rank errors differ from a plain least-squares run of the greedy loop, or if the fit warns."""
    ensemble = random_ensemble(n_params, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        basis = HierarchicalBasis(epsilon=1e-6).fit(ensemble)
    masks, ranks, fields, independent, members, worst = greedy_reference(ensemble, 1e-6)
    np.testing.assert_array_equal(basis.effect_mask_, masks)
    np.testing.assert_array_equal(basis.effect_rank_, ranks)
    np.testing.assert_array_equal(basis.independent_, independent)
    np.testing.assert_array_equal(basis.field_member_, members)
    np.testing.assert_allclose(basis.fields_, fields, atol=1e-9)
    np.testing.assert_allclose(basis.rank_max_error_, worst, atol=1e-9)
    assert basis.rank_max_error_.shape == (n_params + 1,)
    assert basis.rank_max_error_[0] == 0.0 and basis.rank_max_error_[1] == 0.0
    # every member of a random design is its own direction
    assert int(basis.independent_.sum()) == 3**n_params
    # the trace covers the ranks >= 2 only, one row per step plus the closing one of each rank
    assert set(basis.trace_[:, 0].astype(int)) == set(range(2, n_params + 1))
    assert len(basis.trace_) == int(np.sum(ranks >= 2)) + n_params - 1


def test_effects_pair_a_member_with_its_negation():
    """Fails if an effect's second field is not defined by the member with the negated parameter state."""
    ensemble = random_ensemble(3, 5)
    basis = HierarchicalBasis(epsilon=1e-6).fit(ensemble)
    for e in np.flatnonzero(basis.effect_rank_ >= 1):
        first, second = basis.effect_fields_[e]
        assert second >= 0
        c1 = ensemble.commanded[basis.field_member_[first]]
        c2 = ensemble.commanded[basis.field_member_[second]]
        np.testing.assert_array_equal(c2, -c1)
        np.testing.assert_array_equal(c1 != 0, basis.effect_mask_[e])


def test_without_loads_there_is_no_loads_effect():
    """Fails if a zero loads field (rank-0 member exactly 0) still gets a LOADS effect, or a non-zero one does not."""
    assert LOADS not in HierarchicalBasis(1e-6).fit(random_ensemble(2, 6, loads=False)).effect_names_
    assert HierarchicalBasis(1e-6).fit(random_ensemble(2, 6)).effect_names_[0] == LOADS


def test_the_basis_does_not_depend_on_the_units():
    """Fails if an ensemble in metres (1e-3 x, every field well below 1 mm, 1e-9 m fields) gives other effects than
    the same ensemble in millimetres, with epsilon scaled alike."""
    mm = HierarchicalBasis(epsilon=1e-3).fit(random_ensemble(3, 7))
    for scale in (1e-3, 1e-9):
        small = HierarchicalBasis(epsilon=scale * 1e-3).fit(random_ensemble(3, 7, scale=scale))
        assert small.effect_names_ == mm.effect_names_
        np.testing.assert_allclose(small.fields_, scale * mm.fields_, atol=scale * 1e-9)
        np.testing.assert_array_equal(small.independent_, mm.independent_)


def test_zero_parameter_ensemble_is_the_loads_alone():
    """Fails if an ensemble without parameters (one member: the loads) does not give the single LOADS effect."""
    one = random_ensemble(1, 8)
    keep = one.rank == 0
    bare = replace(one, names=(), n_bilateral=0, lower=np.zeros(0), upper=np.zeros(0),
                   commanded=np.zeros((1, 0)), effective=np.zeros((1, 0)), rank=one.rank[keep],
                   normal_displacement=one.normal_displacement[keep], displacement=one.displacement[keep])
    basis = HierarchicalBasis().fit(bare)
    assert basis.effect_names_ == (LOADS,)
    np.testing.assert_array_equal(basis.fields_, bare.normal_displacement)
    assert basis.effect_mask_.shape == (1, 0)


def _drop_duplicate(ensemble: Ensemble, member: int) -> Ensemble:
    """``ensemble`` with ``member`` appearing twice."""
    idx = np.r_[np.arange(ensemble.n_members), member]
    return replace(ensemble, commanded=ensemble.commanded[idx], effective=ensemble.effective[idx],
                   contact_fraction=ensemble.contact_fraction[idx], reactions=ensemble.reactions[idx],
                   rank=ensemble.rank[idx], normal_displacement=ensemble.normal_displacement[idx],
                   displacement=ensemble.displacement[idx])


def test_duplicated_rank0_or_rank1_members_are_refused():
    """Fails if a design with two rank-0 members, or two rank-1 members for one parameter sign, is accepted."""
    ensemble = random_ensemble(2, 9)
    with pytest.raises(BasisError, match="exactly one rank-0 member, found 2"):
        HierarchicalBasis().fit(_drop_duplicate(ensemble, int(np.flatnonzero(ensemble.rank == 0)[0])))
    with pytest.raises(BasisError, match="one rank-1 member with P0 at its max, found 2"):
        HierarchicalBasis().fit(_drop_duplicate(ensemble, int(np.flatnonzero(ensemble.commanded[:, 0] == 1.0)[0])))


def test_missing_minimum_member_is_named():
    """Fails if a design without the rank-1 member at a parameter's minimum is not reported as such."""
    ensemble = random_ensemble(2, 10)
    keep = ~((ensemble.rank == 1) & (ensemble.commanded[:, 1] == -1.0))
    cut = replace(ensemble, commanded=ensemble.commanded[keep], rank=ensemble.rank[keep],
                  normal_displacement=ensemble.normal_displacement[keep])
    with pytest.raises(BasisError, match="one rank-1 member with P1 at its min, found 0"):
        HierarchicalBasis().fit(cut)


def test_repeated_effect_names_are_numbered():
    """Fails if an effect found twice (here: one-member design, the second member added for a second pass) does not
    get a "#2" suffix."""
    build = _GreedyBuild(np.eye(3), n_params=1)
    for _ in range(3):
        build.add_effect("A & B", np.array([True]), 2, [0])
    assert build.names == ["A & B", "A & B #2", "A & B #3"]
    assert build.effect_fields == [[0, -1]] * 3
