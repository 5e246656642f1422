"""Hierarchical basis (paper section 3.1.2, Fig. 5): effects discovered rank by rank.

Rank 0 and rank 1 first: the rank-0 member is the effect of the loads alone ("LOADS"); each parameter's effect is the
pair (u(max e_p) - u0, u(min e_p) - u0). Subtracting u0 spans the same space as the paper's raw members but keeps the
loads out of every single-parameter effect, so a contribution plot shows what the parameter itself does. Then, rank by
rank, every member is approximated by least squares; the worst difference field above epsilon (max abs over nodes,
normal displacement, mm) and the difference field of its inverse partner (the member with the negated parameter
state) are added as a new effect named by the parameters the member involves (e.g. ``LOCK_L & LOCK_R``), until
every member of the rank is within epsilon.

What an interaction effect's field holds (a deviation from the paper in the partition only, not in the span): the
paper adds the member's least-squares difference field itself, so an interaction's part that looks like a single
effect (a lock pair pressing the hood onto a buffer: the buffer's own field) is fitted to the single effects and the
effect's partial displacement is only what lies outside their span (0.044 mm against a factorial interaction of
0.151 mm in Fig. 11's lock pair on the nonlinear coarse hood-paper, RESULTS.md). Here the field is the member's
factorial interaction (the Moebius difference over its sub-states, for a pair u(a_i + a_j) - u(a_i) - u(a_j) + u0,
section 3.1.1's grid) plus the difference field of what is left, u_S - I_S (zero for a pair; for rank 3 the rank-2
sub-members' parts outside the span, each within epsilon). Its part outside the span equals the paper's difference
field exactly, so the greedy adds the same directions, finds the same effects and reconstructs every field the same;
a decomposition gives the interaction effect the factorial interaction, which a user can check with four solves.

Which span a member is measured against (``span``): the paper's Fig. 5 fits it with every effect found so far
("whole", the default). Step 3 of the workflow then fits a field that moves only some parameters with the effects of
those parameters alone, where the other effects that absorbed part of an interaction are gone: on the nonlinear
coarse hood-paper the LOCK_L & LOCK_R members are 0.033 mm from the whole span but 0.157 mm from their own effects'
(lock-buffer pairs 0.061 and 0.215 mm). "subset" measures each member against the effects its own parameters span
(``subset_fields``), so every member is within epsilon of the basis step 3 leaves for it. A subset difference field
that lies in the whole span (an interaction shaped exactly like an unmoved parameter's field) adds no direction to
the whole basis and is refused (BasisError), as the decomposition fits with independent fields only.

Speed: the paper refits every member from scratch after each addition (3 h 21 min at 188k nodes x 729 members). Here
an orthonormal basis Q of the span grows by Gram-Schmidt (with one re-orthogonalisation), and the difference fields
of the current rank are updated by one rank-one projection per added direction: E <- E - (E q) q^T. Every basis
field is kept as a combination of ensemble members, so its 3D field and parameter state follow by the same weights.
"""

from __future__ import annotations

import logging

import numpy as np

from hood_decomp.core.types import Ensemble
from hood_decomp.errors import BasisError

logger = logging.getLogger(__name__)

LOADS = "LOADS"
# A field whose part orthogonal to the current span is below this fraction of its norm adds no direction: it is
# kept in its effect (eq. 6 needs the pair) but not fitted, so the least-squares problem stays well posed. Ensemble
# stores hold float32 (relative rounding 6e-8 per value): at the paper's 188k nodes the inverse partner of a nearly
# linear parameter differed from its negated field by 5e-7 and made the normal matrix singular on partial fields.
DEPENDENT_RTOL = 1e-5
#: which span a member is measured against in the greedy loop: "whole", the paper's Fig. 5 (every effect found so
#: far), or "subset", the effects its own parameters span (what step 3 of the workflow leaves for such a field)
SPANS = ("whole", "subset")


class _GreedyBuild:
    """Scratch state of one greedy build: the basis fields and effects found so far and the orthonormal span Q.

    x: (M, N) mm member normal fields. Every basis field is kept with its member weights (M,), so its 3D field and
    parameter state follow by the same weights. While a rank is worked on, ``diff`` (R, N) holds its members' parts
    outside the span.
    """

    def __init__(self, x: np.ndarray, n_params: int, commanded: np.ndarray | None = None) -> None:
        self.x = x
        self.eye = np.eye(len(x))
        # commanded states (M, P) and the member index by state, for the factorial interaction's sub-states
        self.commanded = np.zeros((len(x), n_params)) if commanded is None else commanded
        self.state_index = {tuple(row.tolist()): m for m, row in enumerate(self.commanded)}  # tuples: -0.0 == 0.0
        self.q = np.zeros((2 * n_params + 2, x.shape[1]))  # rows 0..k-1 span the basis; grows by doubling
        self.k = 0
        self.combos: list[np.ndarray] = []  # per basis field: member weights (M,)
        self.normal: list[np.ndarray] = []  # per basis field: normal values (N,) mm
        self.members: list[int] = []  # per basis field: the member that defined it
        self.independent: list[bool] = []  # per basis field: brought a new direction
        self.names: list[str] = []  # per effect
        self.masks: list[np.ndarray] = []  # per effect: (P,) parameters involved
        self.ranks: list[int] = []  # per effect
        self.effect_fields: list[list[int]] = []  # per effect: indices of B_i and B_i^-1 (-1: none)
        self.diff: np.ndarray | None = None

    def add(self, vector: np.ndarray, combination: np.ndarray, member: int) -> None:
        """Add one basis field (normal values (N,), member weights (M,)); extend Q if it brings a new direction."""
        self.combos.append(combination)
        self.normal.append(vector)
        self.members.append(member)
        if self.k == self.q.shape[0]:
            self.q = np.vstack([self.q, np.zeros_like(self.q)])
        q = self.q[: self.k]
        h = q @ vector
        rest = vector - h @ q
        h2 = q @ rest
        rest -= h2 @ q
        h += h2
        norm = float(np.linalg.norm(rest))
        if norm <= DEPENDENT_RTOL * max(float(np.linalg.norm(vector)), 1e-300):
            self.independent.append(False)
            return
        self.independent.append(True)
        direction = rest / norm
        self.q[self.k] = direction
        self.k += 1
        if self.diff is not None:
            self.diff -= np.outer(self.diff @ direction, direction)

    def add_effect(self, name: str, mask: np.ndarray, rank: int, fields: list[int]) -> None:
        """Record an effect over the basis fields ``fields``; a repeated name gets a ``#2``, ``#3`` ... suffix."""
        base, count = name, 2
        while name in self.names:
            name = f"{base} #{count}"
            count += 1
        self.names.append(name)
        self.masks.append(mask)
        self.ranks.append(rank)
        self.effect_fields.append([*fields, -1][:2])

    def subset_fields(self, mask: np.ndarray) -> list[int]:
        """Independent basis fields of the effects whose parameters lie within ``mask`` (P,) bool (LOADS included):
        what step 3 of the workflow leaves for a field that moves exactly those parameters."""
        return [i for e, m in enumerate(self.masks) if not np.any(m & ~mask)
                for i in self.effect_fields[e] if i >= 0 and self.independent[i]]

    def subset_errors(self, members: np.ndarray) -> np.ndarray:
        """(R,) mm: each member's largest distance from the span of its own subset of effects (``subset_fields``)."""
        masks = self.commanded[members] != 0
        errors = np.zeros(len(members))
        for mask in np.unique(masks, axis=0):
            rows = np.flatnonzero(np.all(masks == mask, axis=1))
            q = np.linalg.qr(np.array([self.normal[i] for i in self.subset_fields(mask)]).T)[0]
            block = self.x[members[rows]]
            errors[rows] = np.abs(block - (block @ q) @ q.T).max(axis=1)
        return errors

    def difference(self, weights: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Difference field (N,) of the member combination ``weights`` (M,) and its member weights (M,): the
        combination minus its least-squares fit with the effects whose parameters it involves (LOADS included)."""
        fields = self.subset_fields(mask)
        sub = np.array([self.normal[i] for i in fields])
        target = weights @ self.x
        coeff = np.linalg.lstsq(sub.T, target, rcond=None)[0]
        combo = weights - coeff @ np.array([self.combos[i] for i in fields])
        return target - coeff @ sub, combo

    def interaction(self, member: int) -> np.ndarray:
        """Member weights (M,) of the factorial interaction of ``member``: sum over the subsets T of its non-zero
        parameters of (-1)^(|S| - |T|) u(a_T), a_T its state with the parameters outside T at 0."""
        state = self.commanded[member]
        used = np.flatnonzero(state != 0)
        weights = np.zeros(len(self.x))
        for bits in range(1 << used.size):
            keep = np.zeros(state.size, dtype=bool)
            keep[used[[(bits >> b) & 1 == 1 for b in range(used.size)]]] = True
            sub = tuple(np.where(keep, state, 0.0).tolist())
            if sub not in self.state_index:
                raise BasisError(f"the factorial interaction of member {member} needs the member {sub}")
            weights[self.state_index[sub]] += (-1.0) ** (used.size - int(keep.sum()))
        return weights

    def effect_field(self, member: int, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """An interaction effect's field (N,) and its member weights (M,) for ``member``: its factorial interaction
        I_S plus the difference field of u_S - I_S (module docstring); outside the span it is the member's
        difference field."""
        weights = self.interaction(member)
        rest, combo = self.difference(self.eye[member] - weights, mask)
        return weights @ self.x + rest, weights + combo

    def grow_rank(self, rank: int, members: np.ndarray, commanded: np.ndarray, names: tuple[str, ...],
                  epsilon: float, trace: list[tuple[int, int, float]], span: str = "whole") -> float:
        """Add effects until every member of ``rank`` (indices ``members``) is within ``epsilon`` mm of the span
        (``span`` "whole": of all effects found so far; "subset": of its own subset, ``subset_errors``); one trace
        row per step. Returns the rank's final worst member error (mm)."""
        x = self.x
        q = self.q[: self.k]
        self.diff = x[members] - (x[members] @ q.T) @ q
        while True:
            errors = np.abs(self.diff).max(axis=1) if span == "whole" else self.subset_errors(members)
            worst = int(np.argmax(errors))
            trace.append((rank, len(self.names), float(errors[worst])))
            if errors[worst] <= epsilon:
                self.diff = None
                return float(errors[worst])
            m = int(members[worst])
            partner = np.flatnonzero(np.all(commanded[members] == -commanded[m], axis=1))
            mask = commanded[m] != 0
            group = [m] + [int(members[i]) for i in partner[:1]]
            diffs = [(*self.effect_field(j, mask), j) for j in group]
            k_before = self.k
            fields = []
            for diff, combo, j in diffs:
                fields.append(len(self.combos))
                self.add(diff, combo, j)
            if self.k == k_before:
                raise BasisError(f"rank {rank}: the worst member ({errors[worst]:.3g} mm) adds no new direction")
            self.add_effect(" & ".join(n for n, used in zip(names, mask, strict=True) if used), mask, rank, fields)
            logger.info("hierarchical: rank %d, max error %.4g mm -> %d effects", rank, errors[worst], len(self.names))


class HierarchicalBasis:
    """Greedy hierarchical basis of effects (Fig. 5).

    Parameters: epsilon (mm), the largest allowed max-abs difference of any member; span (SPANS), the span a member
    is measured against: "whole" (the paper's Fig. 5) or "subset" (module docstring). Progress is logged (INFO).

    Fitted attributes (F basis fields, E effects, N nodes, P parameters):
    model_id_, names_, n_bilateral_, epsilon_.
    fields_ (F, N) mm normal basis fields; fields_3d_ (F, N, 3) mm; field_states_ (F, P) mm, the effective parameter
    states combined with the same weights; field_member_ (F,) index of the ensemble member that defined each field;
    independent_ (F,) bool, False for a field already in the span of the ones before it (coefficient fixed to 0).
    effect_names_ (E,) str; effect_mask_ (E, P) bool, parameters involved; effect_fields_ (E, 2) int, indices of
    B_i and B_i^-1 into fields_ (-1 where an effect has a single field); effect_rank_ (E,).
    trace_ (T, 3): per greedy step [rank, number of effects after the step, max error before the step (mm)].
    rank_max_error_ (R,) mm: the final worst member error of each rank; gram_ (F, F) over all nodes.
    """

    def __init__(self, epsilon: float = 0.1, span: str = "whole") -> None:
        self.epsilon = epsilon
        self.span = span

    def fit(self, ensemble: Ensemble) -> HierarchicalBasis:
        """Build the basis from a full-factorial ensemble (ranks >= 0, both signs of every sample present)."""
        x = np.asarray(ensemble.normal_displacement, dtype=float)
        commanded = np.asarray(ensemble.commanded, dtype=float)
        rank = np.asarray(ensemble.rank)
        names = tuple(ensemble.names)
        if self.epsilon <= 0:
            raise BasisError(f"epsilon must be > 0 mm, got {self.epsilon}")
        if self.span not in SPANS:
            raise BasisError(f"span must be one of {SPANS}, got {self.span!r}")
        if not np.all(np.isfinite(x)):
            raise BasisError("ensemble normal displacement holds NaN or inf values")
        if np.any(rank < 0):
            raise BasisError("the hierarchical basis needs a full-factorial ensemble (ranks >= 0), got random members")
        rank0 = np.flatnonzero(rank == 0)
        if rank0.size != 1:
            raise BasisError(f"expected exactly one rank-0 member, found {rank0.size}")

        build = _GreedyBuild(x, len(names), commanded)
        origin = int(rank0[0])
        if np.abs(x[origin]).max() > 1e-12:
            build.add(x[origin], build.eye[origin], origin)
            build.add_effect(LOADS, np.zeros(len(names), dtype=bool), 0, [0])
        for p, label in enumerate(names):
            pair = []
            for sign in (1.0, -1.0):
                hit = np.flatnonzero((rank == 1) & (np.sign(commanded[:, p]) == sign))
                if hit.size != 1:
                    raise BasisError(f"expected one rank-1 member with {label} at its {'max' if sign > 0 else 'min'}, "
                                     f"found {hit.size}")
                m = int(hit[0])
                pair.append(len(build.combos))
                build.add(x[m] - x[origin], build.eye[m] - build.eye[origin], m)
            build.add_effect(label, np.arange(len(names)) == p, 1, pair)
        logger.info("hierarchical: rank 0-1 basis, %d effects", len(build.names))

        trace: list[tuple[int, int, float]] = []
        rank_error = np.zeros(int(rank.max()) + 1)
        for r in range(2, len(rank_error)):
            rank_error[r] = build.grow_rank(r, np.flatnonzero(rank == r), commanded, names, self.epsilon, trace,
                                            self.span)

        combos = np.array(build.combos)
        self.model_id_ = ensemble.model_id
        self.names_ = names
        self.n_bilateral_ = int(ensemble.n_bilateral)
        self.epsilon_ = float(self.epsilon)
        self.fields_ = combos @ x
        self.fields_3d_ = np.tensordot(combos, np.asarray(ensemble.displacement, dtype=float), axes=1)
        self.field_states_ = combos @ np.asarray(ensemble.effective, dtype=float)
        self.field_member_ = np.array(build.members, dtype=np.int64)
        self.independent_ = np.array(build.independent, dtype=bool)
        self.effect_names_ = tuple(build.names)
        self.effect_mask_ = np.array(build.masks, dtype=bool).reshape(len(build.names), len(names))
        self.effect_fields_ = np.array(build.effect_fields, dtype=np.int64).reshape(len(build.names), 2)
        self.effect_rank_ = np.array(build.ranks, dtype=np.int64)
        self.trace_ = np.array(trace, dtype=float).reshape(len(trace), 3)
        self.rank_max_error_ = rank_error
        self.gram_ = self.fields_ @ self.fields_.T
        return self

    def effect_parameters(self, index: int) -> tuple[str, ...]:
        """Labels of the parameters effect ``index`` involves."""
        return tuple(n for n, used in zip(self.names_, self.effect_mask_[index], strict=True) if used)


# Attribute names that make up a fitted HierarchicalBasis (used by the HDF5 writer/reader).
HIERARCHICAL_FITTED_ARRAYS = (
    "fields_",
    "fields_3d_",
    "field_states_",
    "field_member_",
    "independent_",
    "effect_mask_",
    "effect_fields_",
    "effect_rank_",
    "trace_",
    "rank_max_error_",
    "gram_",
)
