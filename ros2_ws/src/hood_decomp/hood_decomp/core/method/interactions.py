"""The interaction map of an ensemble: how far the part is from additive in each pair of parameters.

For parameters i, j and signs s_i, s_j the interaction field is the second difference of the rank-2 member over the
factorial grid (section 3.1.1, Table 1):

    I_ij(s_i, s_j) = u(s_i a_i + s_j a_j) - u(s_i a_i) - u(s_j a_j) + u0          (N,) mm, normal displacement

with a_i the parameter's max (s = +1) or min (s = -1). It is zero for a linear part. The hierarchical basis (Fig. 5)
adds an interaction effect of a pair when its rank-2 member's least-squares residual on the span found so far (the
loads, the single effects, earlier interactions) exceeds epsilon in max norm. The member minus I_ij lies in that span,
so the residual is at most I_ij in 2-norm (not strictly in max norm): pairs whose peak is well below epsilon do not
become effects, pairs well above it do, unless other effects of the span already explain them. All four members come
from a full-factorial ensemble, so the map costs no solve.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hood_decomp.core.types import Ensemble
from hood_decomp.errors import BasisError

#: sign pairs (s_i, s_j) in the order of InteractionMap.peak_mm's last two axes: index 0 = +1 (max), 1 = -1 (min)
SIGNS = (1.0, -1.0)


@dataclass(frozen=True)
class InteractionMap:
    """Largest interaction of every parameter pair and sign (see the module docstring).

    names: (P,) parameter labels. peak_mm: (P, P, 2, 2) mm, max over the skin of |I_ij(s_i, s_j)|, s index 0 = max,
    1 = min (SIGNS); symmetric in (i, j) with the sign axes swapped; NaN on the diagonal. node: (P, P, 2, 2) int, the
    skin node of that maximum (-1 on the diagonal). signed_mm: (P, P, 2, 2) mm, I_ij at that node (its sign).
    """

    names: tuple[str, ...]
    peak_mm: np.ndarray
    node: np.ndarray
    signed_mm: np.ndarray

    @property
    def pair_peak_mm(self) -> np.ndarray:
        """(P, P) mm, the largest interaction of each pair over its four sign combinations (NaN on the diagonal)."""
        with np.errstate(all="ignore"):
            return np.max(self.peak_mm, axis=(2, 3))

    def rows(self) -> list[tuple[str, str, str, str, float]]:
        """One row per pair and sign (i < j): (name_i, sign_i, name_j, sign_j, peak mm), largest first."""
        P = len(self.names)
        out = [(self.names[i], "+-"[si], self.names[j], "+-"[sj], float(self.peak_mm[i, j, si, sj]))
               for i in range(P) for j in range(i + 1, P) for si in range(2) for sj in range(2)]
        return sorted(out, key=lambda row: -row[4])


def interaction_map(ensemble: Ensemble) -> InteractionMap:
    """The interaction map of a full-factorial ensemble (it must hold u0, every rank-1 and every rank-2 member at the
    parameters' min and max). Raises BasisError naming a missing member."""
    commanded = np.asarray(ensemble.commanded, dtype=float)
    x = np.asarray(ensemble.normal_displacement, dtype=float)
    lower, upper = np.asarray(ensemble.lower, dtype=float), np.asarray(ensemble.upper, dtype=float)
    names = tuple(ensemble.names)
    P = len(names)
    if commanded.shape != (len(x), P):
        raise BasisError(f"ensemble states must be (M, {P}), got {commanded.shape}")
    index = {row.tobytes(): m for m, row in enumerate(commanded)}

    def member(state: np.ndarray) -> np.ndarray:
        m = index.get(np.asarray(state, dtype=float).tobytes())
        if m is None:
            setting = ", ".join(f"{n}={v:g}" for n, v in zip(names, state, strict=True) if v != 0) or "all zero"
            raise BasisError(f"the interaction map needs a full-factorial ensemble; it has no member {setting}")
        return x[m]

    level = np.stack([upper, lower])  # (2, P): sign index 0 = max, 1 = min
    u0 = member(np.zeros(P))
    single = np.zeros((P, 2, x.shape[1]))
    for i in range(P):
        for s in range(2):
            state = np.zeros(P)
            state[i] = level[s, i]
            single[i, s] = member(state) - u0
    peak = np.full((P, P, 2, 2), np.nan)
    node = np.full((P, P, 2, 2), -1, dtype=np.int64)
    signed = np.full((P, P, 2, 2), np.nan)
    for i in range(P):
        for j in range(i + 1, P):
            for si in range(2):
                for sj in range(2):
                    state = np.zeros(P)
                    state[i], state[j] = level[si, i], level[sj, j]
                    field = member(state) - u0 - single[i, si] - single[j, sj]
                    k = int(np.argmax(np.abs(field)))
                    for (a, b, sa, sb) in ((i, j, si, sj), (j, i, sj, si)):
                        peak[a, b, sa, sb], node[a, b, sa, sb], signed[a, b, sa, sb] = abs(field[k]), k, field[k]
    return InteractionMap(names=names, peak_mm=peak, node=node, signed_mm=signed)
