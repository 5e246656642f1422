"""Mutation testing of the method (core/method) and the close loop (core/loop) with cosmic-ray.

Every mutant is one small change cosmic-ray makes to one module (an operator swapped, a number changed, a condition
negated, ...). A module's fast tests then run against it: the mutant is killed when they fail (or time out) and
survives when they pass. The tests never see the working tree's sources: the package is copied to a work directory
outside the repository (default $TMPDIR/hood_decomp_mutation) and that copy, first on PYTHONPATH, is what cosmic-ray
mutates in place and what the tests import. The tests run from a snapshot of tests/ and pyproject.toml taken when
the script starts (cwd = the snapshot), so tests edited in the working tree during a run change nothing.

    scripts/with-env python benchmarks/mutation.py [--modules pca decomposition ...] [--sample N]
                                                   [--resume | --retest-survivors]

One cosmic-ray session per module (config and sqlite in the work directory), each with the module's own fast test
command (``pytest -x -m "not slow"`` over the test files in TARGETS), one worker, a timeout of 4 x the unmutated run +
10 s. Before mutating, the unmutated copy must pass that command (the control), or nothing here means anything.

Sample: cosmic-ray enumerates every mutant of a module (about 4,200 over the ten modules with all its operators, too
many for one sequential worker at ~3 s a mutant). With ``--sample N`` (default 3) the mutants of each module are
sorted by (line, column, operator, occurrence) and every N-th is kept, starting with the first: a deterministic,
systematic sample spread evenly over the source and the operators. The rest are marked skipped in the session.
``--sample 1`` runs them all. Sampled mutants inside type annotations are then left out as well and counted apart
("in annotations"): every module here has ``from __future__ import annotations`` (PEP 563), so an annotation is never
evaluated and a mutant there (``int | None`` -> ``int // None``) cannot change what the code does.

Report (stdout, and JSON in benchmarks/out/mutation.json): per module the mutants run, killed (tests failed), timeout
(counted as killed), incompetent, survived, equivalent, and score = (killed + timeout) / (run - equivalent).
Equivalent mutants (same behaviour as the original for every input the code can get) and justified survivors (a
behaviour change no finite test can tell, e.g. a log message) are listed in NOTES below, each with its reason; a
note matches a mutant by module, operator and the changed source line before and after. Survivors without a note are
reported as unexplained. A note on a mutant that was killed is reported as contradicted (and the mutant counts as
killed).

--resume runs only the mutants a session has not run yet (after an interruption); --retest-survivors runs the
survivors of the previous sessions again (after new tests). Both need the module's source unchanged since the
session was made; otherwise the module's session is made anew.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import datetime
import fcntl
import hashlib
import json
import os
import pathlib
import shlex
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "ros2_ws" / "src" / "hood_decomp" / "hood_decomp"
OUT = ROOT / "benchmarks" / "out" / "mutation.json"
DEFAULT_WORKDIR = pathlib.Path(tempfile.gettempdir()) / "hood_decomp_mutation"

M = "tests/core/method/"
L = "tests/core/loop/"


@dataclasses.dataclass(frozen=True)
class Target:
    name: str
    module: str  # path below the package
    tests: tuple[str, ...]  # test files (relative to the repository root), the fast ones that exercise the module


TARGETS = (
    Target("pca", "core/method/pca.py",
           (M + "test_mutants_pca.py", M + "test_pca.py", M + "test_planted_truth.py", M + "test_estimation.py")),
    Target("hierarchical", "core/method/hierarchical.py",
           (M + "test_mutants_hierarchical.py", M + "test_hierarchical.py", M + "test_planted_truth.py",
            M + "test_decomposition.py")),
    Target("estimation", "core/method/estimation.py",
           (M + "test_mutants_estimation.py", M + "test_estimation.py", M + "test_pca.py", M + "test_planted_truth.py",
            M + "test_contact_estimation.py")),
    Target("contact_estimation", "core/method/contact_estimation.py",
           (M + "test_mutants_contact_estimation.py", M + "test_contact_estimation.py")),
    Target("decomposition", "core/method/decomposition.py",
           (M + "test_mutants_decomposition.py", M + "test_decomposition.py", M + "test_planted_truth.py")),
    Target("bases", "core/method/bases.py", (M + "test_mutants_bases.py",)),
    Target("correction", "core/method/correction.py", (M + "test_mutants_correction.py", M + "test_correction.py")),
    Target("residual", "core/method/residual.py", (M + "test_mutants_residual.py", M + "test_residual.py")),
    Target("candidates", "core/loop/candidates.py", (L + "test_mutants_candidates.py",)),
    Target("close_loop", "core/loop/close_loop.py", (L + "test_mutants_close_loop.py",)),
)


@dataclasses.dataclass(frozen=True)
class Note:
    """A reviewed mutant: ``kind`` "equivalent" (excluded from the score) or "justified" (a survivor that counts as
    survived, with the reason no test kills it). old/new: the changed source line before and after (stripped)."""

    module: str
    operator: str
    old: str
    new: str
    kind: str
    reason: str


# Reviewed mutants. Equivalent: the mutated code does what the original does for every input it can get (excluded
# from the score). Justified: a survivor with a behaviour change no reasonable finite test separates (counted as
# survived). Each note names the line it matches, before and after, exactly as the report prints them.
_PCA75 = "if self.n_components is not None and self.n_components + 1 < m:"
_PCA75_WHY = ("only switches between the partial and the full eigensolve where n_components + 1 >= M; there count = M "
              "and the partial solve covers the whole spectrum: scipy's evr driver returns bit-identical eigenpairs "
              "for subset_by_index=[0, M-1] and for the full problem (checked on the test ensemble)")
_CENTRED = ("the PCA member weights are eigenvectors of the centred Gram matrix with non-zero eigenvalues, so they "
            "are orthogonal to the ones vector: weights.sum(axis=0) = 0 (to round-off, ~1e-16), and adding or "
            "subtracting the mean row times those sums changes nothing")
_EST57 = "if n_unseen < valid.size // 2:"
_EST57_WHY = ("chooses between two ways to form the same normal matrix (full Gram minus the unseen part, or the seen "
              "part directly); this mutant forms it directly where the original subtracts, which differs by "
              "round-off only (the direct way is the accurate one) and costs time")
NOTES: tuple[Note, ...] = (
    Note("pca", "core/ReplaceBinaryOperator_Add_Sub", _PCA75, _PCA75.replace("+ 1 <", "- 1 <"), "equivalent",
         _PCA75_WHY),
    Note("pca", "core/ReplaceBinaryOperator_Add_Mul", _PCA75, _PCA75.replace("+ 1 <", "* 1 <"), "equivalent",
         _PCA75_WHY),
    Note("pca", "core/ReplaceBinaryOperator_Add_FloorDiv", _PCA75, _PCA75.replace("+ 1 <", "// 1 <"), "equivalent",
         _PCA75_WHY),
    Note("pca", "core/ReplaceBinaryOperator_Add_BitOr", _PCA75, _PCA75.replace("+ 1 <", "| 1 <"), "equivalent",
         _PCA75_WHY + "; n | 1 is n + 1 for even n and n for odd n"),
    Note("pca", "core/ReplaceComparisonOperator_Lt_NotEq", _PCA75, _PCA75.replace("< m:", "!= m:"), "equivalent",
         _PCA75_WHY),
    Note("pca", "core/ReplaceBinaryOperator_Sub_Add",
         "self.components_3d_ = np.tensordot(weights.T, disp, axes=1) - weights.sum(axis=0)[:, None, None] * mean3",
         "self.components_3d_ = np.tensordot(weights.T, disp, axes=1) + weights.sum(axis=0)[:, None, None] * mean3",
         "equivalent", _CENTRED),
    Note("pca", "core/ReplaceBinaryOperator_Sub_Add",
         "self.component_reactions_ = weights.T @ (reactions - self.mean_reaction_)",
         "self.component_reactions_ = weights.T @ (reactions + self.mean_reaction_)", "equivalent", _CENTRED),
    Note("hierarchical", "core/ReplaceBinaryOperator_Mul_Pow",
         "self.q = np.zeros((2 * n_params + 2, x.shape[1]))  # rows 0..k-1 span the basis; grows by doubling",
         "self.q = np.zeros((2 ** n_params + 2, x.shape[1]))  # rows 0..k-1 span the basis; grows by doubling",
         "equivalent", "only the initial capacity of the span buffer changes (never below 3 rows); it doubles when "
         "full, and the rows past k are never read"),
    Note("hierarchical", "core/ReplaceBinaryOperator_BitAnd_Mul",
         "hit = np.flatnonzero((rank == 1) & (np.sign(commanded[:, p]) == sign))",
         "hit = np.flatnonzero((rank == 1) * (np.sign(commanded[:, p]) == sign))", "equivalent",
         "* of two boolean arrays is their logical and"),
    Note("hierarchical", "core/ReplaceComparisonOperator_Gt_GtE",
         "raise BasisError(f\"expected one rank-1 member with {label} at its {'max' if sign > 0 else 'min'}, \"",
         "raise BasisError(f\"expected one rank-1 member with {label} at its {'max' if sign >= 0 else 'min'}, \"",
         "equivalent", "sign is +1.0 or -1.0 here (the loop's two values), so >= 0 and > 0 agree"),
    Note("hierarchical", "core/ReplaceComparisonOperator_Eq_LtE",
         "rank_error[r] = build.grow_rank(r, np.flatnonzero(rank == r), commanded, names, self.epsilon, trace)",
         "rank_error[r] = build.grow_rank(r, np.flatnonzero(rank <= r), commanded, names, self.epsilon, trace)",
         "equivalent", "members of lower ranks are already in the span when rank r is grown (their parts outside "
         "it are round-off, ~1e-15 mm), so they are never the worst member, never below a rank-r member's error, and "
         "a member's negated partner has its rank"),
    Note("estimation", "core/ReplaceComparisonOperator_Eq_LtE", "if n_valid == 0:", "if n_valid <= 0:",
         "equivalent", "n_valid is a count, never negative"),
    Note("estimation", "core/ReplaceComparisonOperator_Lt_Eq", _EST57, _EST57.replace("<", "=="), "equivalent",
         _EST57_WHY),
    Note("estimation", "core/ReplaceComparisonOperator_Lt_Is", _EST57, _EST57.replace("<", "is"), "equivalent",
         _EST57_WHY),
    Note("estimation", "core/NumberReplacer", _EST57, _EST57.replace("// 2", "// 3"), "equivalent", _EST57_WHY),
    Note("estimation", "core/ReplaceComparisonOperator_Eq_LtE", "scale[scale == 0.0] = 1.0",
         "scale[scale <= 0.0] = 1.0", "equivalent", "scale is a square root of values clipped at 0, never negative"),
    Note("estimation", "core/NumberReplacer",
         "if eigval.size and eigval[0] <= 1e-12 * max(eigval[-1], 1e-300):",
         "if eigval.size and eigval[0] <= 1e-12 * max(eigval[-1], -1.0):", "equivalent",
         "the largest eigenvalue of the positive semi-definite normal matrix (scaled to unit diagonal) is > 0, or 0 "
         "for a zero matrix, where 0 <= 1e-12 x 0 holds as 0 <= 1e-312 does: singular either way"),
)

_C170 = "for _ in range(4 * active.size + 8):"
_C170_WHY = ("caps the active-set iteration at 4 S + 8 steps (S springs); it ends earlier on convergence or on a "
             "revisited state, within 3 steps from every start on the test models, so a cap above 3 acts the same")
_C241 = "height = model.z0 + model.Sa @ u[:n_b] + model.H @ f - model.preload"
_C247 = "return np.where(cand.active, f / model.k, np.abs(height - reference))"
_ORDER_WHY = ("ranks the springs the local search flips first (the MAX_FLIPS closest to changing state); the flips "
              "only restart the active-set iteration, which reaches a pad's contact state from any of its springs, "
              "so another order finds the same states on the test models (a wrong order that leaves a pad out "
              "altogether is killed by test_local_search_flips_the_lowest_spring_of_every_lifted_pad)")
_C253 = "for _ in range(2 * self.model_.k.size):"
_C253_WHY = ("caps the local search at 2 S rounds; it stops as soon as a round does not improve the fit, after 1-3 "
             "rounds on the test models")
_C295 = "grad = (cand.lift[n_b + springs] / model.k[springs, None]).sum(axis=0)"
_C295_WHY = ("std of a pad's total compression, used only to lift a pad whose compression is below 2 of its std on a "
             "noisy field; separating it needs a pad compressed by 2-3 std, where which contact state the fit "
             "selects is itself decided by the noise draw (not constructed)")
_C307 = "std[n_b + pad] = max(std[n_b + pad], values[n_b + pad] - position)"
_C307_WHY = ("the light-touch std is max(std of b, b - position); the mutant takes another parameter's std as the "
             "first term, which matters only when that std exceeds b - position on a field where the pad passed its "
             "2-sigma compression test; not constructed")
NOTES += (
    Note("contact_estimation", "core/ReplaceTrueWithFalse", "@dataclass(frozen=True)", "@dataclass(frozen=False)",
         "equivalent", "_Candidate is private and no code assigns to its fields; frozen only guards against it"),
    Note("contact_estimation", "core/NumberReplacer", "if eigval[0] <= 1e-12 * max(eigval[-1], 1e-300):",
         "if eigval[0] <= 1e-12 * max(eigval[-1], -1.0):", "equivalent",
         "the largest eigenvalue of the positive semi-definite reduced normal matrix is > 0, or 0 for a zero matrix, "
         "where 0 <= 1e-12 x 0 holds as 0 <= 1e-312 does: infeasible either way"),
    Note("contact_estimation", "core/ReplaceBinaryOperator_BitAnd_Mul",
         "penetration = ~cand.active & touching & (pen > pen_tol)",
         "penetration = ~cand.active * touching & (pen > pen_tol)", "equivalent",
         "* of two boolean arrays is their logical and (and binds before &)"),
    Note("contact_estimation", "core/ReplaceBinaryOperator_BitOr_Add", "active = (active & ~tension) | penetration",
         "active = (active & ~tension) + penetration", "equivalent", "+ of two boolean arrays is their logical or"),
    Note("contact_estimation", "core/NumberReplacer", "n_nodes = model.w0.shape[0]", "n_nodes = model.w0.shape[ -1]",
         "equivalent", "w0 is one-dimensional (N,), so its first and last axis are the same"),
    Note("contact_estimation", "core/ReplaceFalseWithTrue", "improved = False", "improved = True", "equivalent",
         "an extra local-search round from an unchanged best candidate repeats the same flips, whose active-set runs "
         "are cached and already in the candidates: it adds nothing, and the cap ends it"),
    Note("contact_estimation", "core/ReplaceComparisonOperator_Lt_NotEq", "improved |= cand.rss < best.rss",
         "improved |= cand.rss != best.rss", "equivalent",
         "a new worse candidate leaves the best unchanged, so the extra round it triggers repeats cached flips and "
         "adds nothing (see improved = True)"),
    Note("contact_estimation", "core/NumberReplacer", "sigma2 = best_rss / max(n_valid, 1)",
         "sigma2 = best_rss / max(n_valid, 2)", "equivalent",
         "differs only for one seen node; every candidate has at least one unknown, so with one node either no "
         "candidate is feasible (FieldError) or the best fits it exactly, best_rss = 0 and sigma2 = 0 both ways"),
    Note("contact_estimation", "core/NumberReplacer",
         "compression = float(np.sum(f[springs] / model.k[springs])) if springs.size else 0.0",
         "compression = float(np.sum(f[springs] / model.k[springs])) if springs.size else 1.0", "equivalent",
         "a pad without springs is never touching, and the compression is read only for touching pads"),
    Note("contact_estimation", "core/NumberReplacer",
         "compression_std = np.sqrt(max(float(grad @ cov @ grad), 0.0))",
         "compression_std = np.sqrt(max(float(grad @ cov @ grad), -1.0))", "justified",
         "differs only when round-off makes the quadratic form negative (NaN std: the touch reported lifted); the "
         "variance is >= 0 mathematically and no finite test input was found that rounds it below 0 (issue 21 "
         "removed the 1e-7 mm floor that made this equivalent)"),
    Note("contact_estimation", "core/NumberReplacer",
         'f_std = np.sqrt(np.clip(np.einsum("st,tu,su->s", df, cov, df), 0.0, None))',
         'f_std = np.sqrt(np.clip(np.einsum("st,tu,su->s", df, cov, df), -1.0, None))', "justified",
         "differs only where round-off makes a force variance negative (NaN tolerance: no tension flagged on that "
         "spring); the variance is >= 0 mathematically and no finite test input was found that rounds it below 0"),
    *(Note("contact_estimation", op, _C170, _C170.replace("4 * active.size + 8", new), "justified", _C170_WHY)
      for op, new in (("core/ReplaceBinaryOperator_Add_Pow", "4 * active.size ** 8"),
                      ("core/ReplaceBinaryOperator_Add_LShift", "4 * active.size << 8"),
                      ("core/ReplaceBinaryOperator_Add_BitXor", "4 * active.size ^ 8"),
                      ("core/ReplaceBinaryOperator_Mul_Mod", "4 % active.size + 8"),
                      ("core/ReplaceBinaryOperator_Mul_BitAnd", "4 & active.size + 8"),
                      ("core/NumberReplacer", " 5 * active.size + 8"),
                      ("core/NumberReplacer", "4 * active.size + 9"))),
    Note("contact_estimation", "core/NumberReplacer",
         "sigma2 = float(np.nansum(residual**2)) / max(n_valid - theta.size, 1)",
         "sigma2 = float(np.nansum(residual**2)) / max(n_valid - theta.size, 2)", "justified",
         "differs only for a field with at most one seen node more than the unknowns (min_coverage lowered to ~0); "
         "there the selection prefers exact-fit contact states, so no noisy reference fit to compare with"),
    *(Note("contact_estimation", op, _C241, _C241.replace(old, new), "justified", _ORDER_WHY)
      for op, old, new in (("core/ReplaceBinaryOperator_Add_Sub", "+ model.H @ f", "- model.H @ f"),
                           ("core/ReplaceBinaryOperator_Add_Mul", "+ model.H @ f", "* model.H @ f"),
                           ("core/ReplaceBinaryOperator_Add_FloorDiv", "+ model.H @ f", "// model.H @ f"),
                           ("core/ReplaceBinaryOperator_Sub_Mul", "- model.preload", "* model.preload"),
                           ("core/ReplaceBinaryOperator_Sub_FloorDiv", "- model.preload", "// model.preload"))),
    Note("contact_estimation", "core/ReplaceComparisonOperator_Eq_GtE",
         "lowest = np.array([height[model.pad_of == p].min(initial=np.inf) for p in range(b.size)])",
         "lowest = np.array([height[model.pad_of >= p].min(initial=np.inf) for p in range(b.size)])", "justified",
         _ORDER_WHY),
    *(Note("contact_estimation", op, _C247, _C247.replace(old, new), "justified", _ORDER_WHY)
      for op, old, new in (("core/ReplaceBinaryOperator_Sub_Div", "height - reference", "height / reference"),
                           ("core/ReplaceBinaryOperator_Sub_Mod", "height - reference", "height % reference"),
                           ("core/ReplaceBinaryOperator_Div_Add", "f / model.k", "f + model.k"),
                           ("core/ReplaceBinaryOperator_Div_Mod", "f / model.k", "f % model.k"))),
    *(Note("contact_estimation", op, _C253, _C253.replace("2 * self", new), "justified", _C253_WHY)
      for op, new in (("core/ReplaceBinaryOperator_Mul_Pow", "2 ** self"),
                      ("core/ReplaceBinaryOperator_Mul_BitOr", "2 | self"),
                      ("core/NumberReplacer", " 1 * self"))),
    *(Note("contact_estimation", op, _C295, _C295.replace(old, new), "justified", _C295_WHY)
      for op, old, new in (("core/ReplaceBinaryOperator_Add_Sub", "n_b + springs", "n_b - springs"),
                           ("core/ReplaceBinaryOperator_Add_FloorDiv", "n_b + springs", "n_b // springs"),
                           ("core/ReplaceBinaryOperator_Add_BitOr", "n_b + springs", "n_b | springs"),
                           ("core/ReplaceBinaryOperator_Div_Pow", "] / model.k", "] ** model.k"))),
    *(Note("contact_estimation", op, _C307, _C307.replace("max(std[n_b + pad]", new), "justified", _C307_WHY)
      for op, new in (("core/ReplaceBinaryOperator_Add_Sub", "max(std[n_b - pad]"),
                      ("core/ReplaceBinaryOperator_Add_Mul", "max(std[n_b * pad]"),
                      ("core/ReplaceBinaryOperator_Add_BitOr", "max(std[n_b | pad]"))),
    Note("decomposition", "core/ReplaceBinaryOperator_BitAnd_Mul",
         "zero = (np.abs(estimate.values) <= np.maximum(zero_tol_mm, 3.0 * np.nan_to_num(estimate.std))) & "
         "~estimate.lifted",
         "zero = (np.abs(estimate.values) <= np.maximum(zero_tol_mm, 3.0 * np.nan_to_num(estimate.std))) * "
         "~estimate.lifted", "equivalent", "* of two boolean arrays is their logical and"),
    Note("decomposition", "core/ReplaceComparisonOperator_Gt_NotEq",
         "share=float(partial[i].sum() / grand) if grand > 0 else 0.0,",
         "share=float(partial[i].sum() / grand) if grand != 0 else 0.0,", "equivalent",
         "grand is a sum of vector norms, never negative"),
    Note("bases", "core/ReplaceComparisonOperator_Eq_GtE", 'if method == "pca":', 'if method >= "pca":',
         "equivalent", "method is \"contact\" or \"pca\" here (anything else was refused above), and \"contact\" < "
         "\"pca\""),
    Note("residual", "core/ReplaceFalseWithTrue", "n_regions, labels = connected_components(sub, directed=False)",
         "n_regions, labels = connected_components(sub, directed=True)", "equivalent",
         "the adjacency is symmetric, and scipy's directed mode with its default weak connection then finds the same "
         "components"),
    Note("residual", "core/ReplaceComparisonOperator_Gt_GtE",
         "exceeding = seen & (np.abs(np.nan_to_num(mean)) > z * sigma * factor)",
         "exceeding = seen & (np.abs(np.nan_to_num(mean)) >= z * sigma * factor)", "justified",
         "differs only when a ring mean equals the threshold exactly (z is an irrational quantile; a residual is not "
         "built to hit it to the last bit)"),
    Note("residual", "core/NumberReplacer",
         "centroid = (weight @ skin.points[nodes]) / weight.sum() if weight.sum() > 0 else skin.points[nodes].mean(0)",
         "centroid = (weight @ skin.points[nodes]) / weight.sum() if weight.sum() > -1 else skin.points[nodes].mean(0)",
         "justified", "differs only for a region whose residual is exactly 0 at every node (its nodes exceed through "
         "their neighbours' ring means alone); possible with cancelling patterns, not constructed"),
)

_KEEP = "keep = size > NEGLIGIBLE_RTOL * max(size.max(), 1e-300)"
NOTES += (
    Note("candidates", "core/NumberReplacer",
         "length = float(np.linalg.norm(vector)) if vector.shape == (3,) else 0.0",
         "length = float(np.linalg.norm(vector)) if vector.shape == (3,) else -1.0", "equivalent",
         "a length of 0 or -1 both fail the next line's `length > 0` and raise the same ModelError"),
    Note("candidates", "core/ReplaceComparisonOperator_Eq_GtE", 'elif boundary.kind == "unilateral":',
         'elif boundary.kind >= "unilateral":', "equivalent",
         "a boundary's kind is one of BOUNDARY_KINDS (checked when the model is made); here it is \"unilateral\" or "
         "\"force\", and \"force\" < \"unilateral\""),
    Note("candidates", "core/ReplaceComparisonOperator_Eq_GtE", 'elif boundary.kind == "force":',
         'elif boundary.kind >= "force":', "equivalent",
         "fixed, prescribed and unilateral boundaries took the branches above, so the kind is \"force\" here"),
    Note("candidates", "core/ReplaceComparisonOperator_Eq_GtE", 'if kind == "motion":', 'if kind >= "motion":',
         "equivalent", "the entry's kind was checked to be one of KINDS = (\"motion\", \"force\") above, and "
         "\"force\" < \"motion\""),
    Note("candidates", "core/ReplaceComparisonOperator_Eq_GtE", 'if candidate.kind == "motion":',
         'if candidate.kind >= "motion":', "equivalent",
         "a candidate's kind is \"motion\" or \"force\" (KINDS; its unit is looked up in UNITS), and \"force\" < "
         "\"motion\""),
    Note("candidates", "core/NumberReplacer", _KEEP, _KEEP.replace("1e-300", "-1.0"), "equivalent",
         "size is a maximum of absolute values, >= 0: the floor matters only when every candidate's size is 0, where "
         "0 > 1e-309 and 0 > 0 are both false (every candidate dropped either way)"),
    Note("candidates", "core/ReplaceComparisonOperator_Gt_GtE", _KEEP, _KEEP.replace("size >", "size >="),
         "justified", "differs only for a candidate whose largest response equals 1e-9 x the largest of all to the "
         "last bit (a zero response stays below the positive floor either way); not constructed"),
)

_CL320 = ("decisiveness = (scores[1].weighted_rss - best.weighted_rss) / variance if len(scores) > 1 else np.inf")
_CL395 = "if best.within_after and best.p_adjusted < alpha and ratio > threshold:"
NOTES += (
    Note("close_loop", "core/ReplaceTrueWithFalse", "for estimate, sigma in zip(estimates, noise, strict=True):",
         "for estimate, sigma in zip(estimates, noise, strict=False):", "equivalent",
         "both sequences are made from the same fields (one estimate and one noise level per field), so their "
         "lengths are equal and strict only guards against a future caller"),
    Note("close_loop", "core/ReplaceComparisonOperator_Eq_Is",
         "if not len(fields) == len(current) == len(noise) >= 1:",
         "if not len(fields) == len(current) is len(noise) >= 1:", "justified",
         "CPython keeps one object per small int (-5..256), so `is` and `==` agree on the lengths of up to 256 "
         "fields; 257 fields traced jointly would separate them (not constructed: minutes of fits)"),
    Note("close_loop", "core/NumberReplacer", "variance = max(best.weighted_rss / dof1, 1e-300)",
         "variance = max(best.weighted_rss / dof1, -1.0)", "justified",
         "differs only when the best candidate fits every seen node to the last bit (weighted RSS exactly 0: a "
         "division by zero instead of a huge likelihood ratio); a field with any noise or round-off never does"),
    Note("close_loop", "core/ReplaceComparisonOperator_Gt_NotEq", _CL320, _CL320.replace("> 1 else", "!= 1 else"),
         "equivalent", "there is at least one candidate (ModelError above otherwise), so len(scores) != 1 is "
         "len(scores) > 1"),
    Note("close_loop", "core/NumberReplacer",
         "explained=float(weights @ (rss0 - rss)) / excess if excess > 0 else 0.0, f_statistic=statistic,",
         "explained=float(weights @ (rss0 - rss)) / excess if excess > 1 else 0.0, f_statistic=statistic,",
         "justified", "differs only for 0 < excess <= 1; pairs are fitted only when the best single leaves the fields "
         "outside the model (its weighted RSS above the chi-square(d) quantile at alpha, which exceeds the "
         "degrees of freedom by far more than 1 for alpha <= 0.1), so excess > 1 there unless alpha is near 0.5"),
    Note("close_loop", "core/ReplaceComparisonOperator_Lt_IsNot", _CL395,
         _CL395.replace("p_adjusted < alpha", "p_adjusted is not alpha"), "justified",
         "drops the significance test of the second effect; differs only when the best pair brings the fields "
         "within the model and beats the runner-up pair by more than the chi-square quantile while its own gain "
         "over the single is not significant after Bonferroni (a gain between ~7 and ~12 variance units with every "
         "other pair gaining almost nothing); searched for on the 20 x 20 hood and not found. Where it happens the "
         "original takes the 'alike' branch, which misstates the reason (and fails with one pair)"),
    Note("close_loop", "core/ReplaceComparisonOperator_Gt_GtE", _CL395, _CL395.replace("ratio >", "ratio >="),
         "justified", "differs only when the likelihood ratio between the two best pairs equals the chi-square "
         "quantile to the last bit; not constructed"),
    Note("close_loop", "core/NumberReplacer", "variance = max(weighted / dof2, 1e-300)",
         "variance = max(weighted / dof2, -1.0)", "justified",
         "differs only when a pair fits every seen node to the last bit (weighted RSS exactly 0); a field with any "
         "noise or round-off never does"),
    Note("close_loop", "core/ReplaceComparisonOperator_NotEq_IsNot", 'if within_before or trace.outcome != "found":',
         'if within_before or trace.outcome is not "found":', "equivalent",
         "a trace's outcome is always one of this module's string constants, and CPython interns identifier-like "
         "constants: \"found\" is one object, so `is not` agrees with `!=`"),
    Note("close_loop", "core/ReplaceComparisonOperator_Eq_Lt", 'current = before if method == "contact" else tuple(',
         'current = before if method < "contact" else tuple(', "equivalent",
         "method is \"contact\" or \"pca\" (estimate_field checks it first): with the mutant a contact run takes "
         "the else branch, which estimates the same fields with the same contact estimator of the same reduced model "
         "and ranges, so the same estimates, computed twice"),
)


# ---------------------------------------------------------------------------------------------------------------------
# Sessions


def _source_hash(path: pathlib.Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _environment(copy_parent: pathlib.Path, repo: pathlib.Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(copy_parent), str(repo), env.get("PYTHONPATH", "")])
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    # The venv's and ROS's pytest plugins (cov, hypothesis, colcon, ...) cost ~1 s a run and no test here uses them.
    env["PYTEST_DISABLE_PLUGIN_AUTOLOAD"] = "1"
    env.setdefault("MPLBACKEND", "Agg")
    return env


def _test_command(target: Target, repo: pathlib.Path) -> str:
    tests = [t for t in target.tests if (repo / t).is_file()]
    if not tests:
        raise SystemExit(f"{target.name}: none of its test files exists: {target.tests}")
    return f'{sys.executable} -m pytest -x -q --no-header -p no:cacheprovider -m "not slow" ' + " ".join(tests)


def _cosmic_ray(*args: str, env: dict[str, str], cwd: pathlib.Path) -> None:
    run = subprocess.run([sys.executable, "-m", "cosmic_ray.cli", *args], cwd=cwd, env=env, capture_output=True,
                         text=True)
    if run.returncode != 0:
        raise SystemExit(f"cosmic-ray {' '.join(args)} failed:\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}")


def annotation_spans(source: str) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """(start, end) (line, column) of every annotation in a module with postponed annotations (PEP 563), else []."""
    tree = ast.parse(source)
    postponed = any(isinstance(node, ast.ImportFrom) and node.module == "__future__"
                    and any(alias.name == "annotations" for alias in node.names) for node in tree.body)
    if not postponed:
        return []
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            a = node.args
            found += [arg.annotation for arg in (*a.posonlyargs, *a.args, *a.kwonlyargs, a.vararg, a.kwarg)
                      if arg is not None and arg.annotation is not None]
            if node.returns is not None:
                found.append(node.returns)
        elif isinstance(node, ast.AnnAssign):
            found.append(node.annotation)
    return [((n.lineno, n.col_offset), (n.end_lineno, n.end_col_offset)) for n in found]


def _in_annotation(position, spans) -> bool:
    return any(start <= tuple(position) < end for start, end in spans)


def _sample(session: pathlib.Path, source: str, every: int) -> tuple[int, int, int]:
    """Keep every ``every``-th mutant (sorted by position, operator, occurrence) and mark the rest skipped, then mark
    the kept ones inside annotations skipped too; return (enumerated, in annotations, kept and run)."""
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    spans = annotation_spans(source)
    with use_db(str(session), WorkDB.Mode.open) as db:
        items = sorted(db.work_items, key=lambda w: (tuple(w.mutations[0].start_pos), tuple(w.mutations[0].end_pos),
                                                     w.mutations[0].operator_name, w.mutations[0].occurrence))
        dropped = [w.job_id for i, w in enumerate(items) if i % every != 0]
        annotated = [w.job_id for w in items if _in_annotation(w.mutations[0].start_pos, spans)]
        kept_annotated = set(annotated) - set(dropped)
        if dropped:
            db.set_multiple_results(dropped, WorkResult(output="not in the sample",
                                                        worker_outcome=WorkerOutcome.SKIPPED))
        if kept_annotated:
            db.set_multiple_results(sorted(kept_annotated), WorkResult(output="annotation (never evaluated)",
                                                                       worker_outcome=WorkerOutcome.SKIPPED))
    return len(items), len(annotated), len(items) - len(dropped) - len(kept_annotated)


def _forget_survivors(session: pathlib.Path) -> int:
    """Delete the survivors' results so that ``cosmic-ray exec`` runs them again; return how many."""
    with sqlite3.connect(session) as db:
        count = db.execute("SELECT COUNT(*) FROM work_results WHERE UPPER(test_outcome) = 'SURVIVED'").fetchone()[0]
        db.execute("DELETE FROM work_results WHERE UPPER(test_outcome) = 'SURVIVED'")
    return int(count)


def run_target(target: Target, workdir: pathlib.Path, copy: pathlib.Path, every: int, mode: str) -> dict:
    """Make (or reuse) the module's session, run the control, then the mutants; return timing and session facts."""
    repo = workdir / "repo"
    env = _environment(copy.parent, repo)
    source = PACKAGE / target.module
    session = workdir / f"{target.name}.sqlite"
    meta_path = workdir / f"{target.name}.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    command = _test_command(target, repo)

    start = time.perf_counter()
    control = subprocess.run(shlex.split(command), cwd=repo, env=env, capture_output=True, text=True)
    control_s = time.perf_counter() - start
    if control.returncode != 0:
        raise SystemExit(f"{target.name}: the unmutated copy fails its tests; fix them first:\n"
                         f"{control.stdout[-4000:]}\n{control.stderr[-2000:]}")
    timeout = round(4.0 * control_s + 10.0, 1)
    config = workdir / f"{target.name}.toml"
    config.write_text(
        "[cosmic-ray]\n"
        f'module-path = "{copy / target.module}"\n'
        f"timeout = {timeout}\n"
        "excluded-modules = []\n"
        f"test-command = {json.dumps(command)}\n"
        "\n[cosmic-ray.distributor]\n"
        'name = "local"\n'
    )
    reuse = (mode in ("resume", "retest") and session.is_file() and meta.get("source_sha256") == _source_hash(source)
             and meta.get("sample_every") == every)
    if mode in ("resume", "retest") and not reuse:
        print(f"{target.name}: no session for today's source and sample; making it anew", flush=True)
    if not reuse:
        session.unlink(missing_ok=True)
        _cosmic_ray("init", str(config), str(session), env=env, cwd=repo)
        total, annotated, kept = _sample(session, source.read_text(), every)
        meta = {"source_sha256": _source_hash(source), "sample_every": every, "enumerated": total,
                "in_annotations": annotated, "sampled": kept}
        meta_path.write_text(json.dumps(meta))
    elif mode == "retest":
        print(f"{target.name}: running {_forget_survivors(session)} survivors again", flush=True)
    meta.update(control_s=round(control_s, 1), timeout_s=timeout, test_command=command)
    meta_path.write_text(json.dumps(meta))

    start = time.perf_counter()
    _cosmic_ray("exec", str(config), str(session), env=env, cwd=repo)
    meta["exec_s"] = round(time.perf_counter() - start, 1)
    meta_path.write_text(json.dumps(meta))
    return meta


# ---------------------------------------------------------------------------------------------------------------------
# Report


def _changed_lines(diff: str) -> tuple[str, str]:
    old = [line[1:].strip() for line in diff.splitlines() if line.startswith("-") and not line.startswith("---")]
    new = [line[1:].strip() for line in diff.splitlines() if line.startswith("+") and not line.startswith("+++")]
    return " / ".join(old), " / ".join(new)


def _find_note(module: str, operator: str, old: str, new: str) -> Note | None:
    for note in NOTES:
        if note.module == module and note.operator == operator and note.old == old and note.new == new:
            return note
    return None


def collect(target: Target, workdir: pathlib.Path) -> dict:
    """Classify every mutant of the module's session."""
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import TestOutcome, WorkerOutcome

    session = workdir / f"{target.name}.sqlite"
    meta = json.loads((workdir / f"{target.name}.json").read_text())
    counts = dict.fromkeys(("in_annotations", "run", "killed", "timeout", "incompetent", "survived", "equivalent",
                            "justified", "pending"), 0)
    survivors, equivalents, contradicted = [], [], []
    text = (PACKAGE / target.module).read_text()
    original = text.splitlines()
    spans = annotation_spans(text)
    with use_db(str(session), WorkDB.Mode.open) as db:
        done = {item.job_id: (item, result) for item, result in db.completed_work_items}
        counts["pending"] = sum(1 for item in db.work_items if item.job_id not in done)
    for item, result in done.values():
        mutation = item.mutations[0]
        if result.worker_outcome == WorkerOutcome.SKIPPED and result.output == "not in the sample":
            continue
        if _in_annotation(mutation.start_pos, spans):
            counts["in_annotations"] += 1
            continue
        if result.worker_outcome in (WorkerOutcome.SKIPPED, WorkerOutcome.NO_TEST):
            continue
        counts["run"] += 1
        line = int(mutation.start_pos[0])
        old, new = _changed_lines(result.diff or "")
        if not old and 0 < line <= len(original):
            old = original[line - 1].strip()
        entry = {"operator": mutation.operator_name, "occurrence": mutation.occurrence, "line": line, "old": old,
                 "new": new}
        note = _find_note(target.name, mutation.operator_name, old, new)
        if result.worker_outcome == WorkerOutcome.EXCEPTION or result.test_outcome == TestOutcome.INCOMPETENT:
            counts["incompetent"] += 1
        elif result.test_outcome == TestOutcome.KILLED:
            counts["timeout" if (result.output or "").strip() == "timeout" else "killed"] += 1
            if note is not None:
                contradicted.append({**entry, "kind": note.kind, "reason": note.reason})
        elif note is not None and note.kind == "equivalent":
            counts["equivalent"] += 1
            equivalents.append({**entry, "reason": note.reason})
        else:
            counts["survived"] += 1
            if note is not None:
                counts["justified"] += 1
            survivors.append({**entry, "reason": note.reason if note else "UNEXPLAINED"})
    scored = counts["run"] - counts["equivalent"] - counts["incompetent"]
    detected = counts["killed"] + counts["timeout"]
    return {
        "module": target.module,
        **counts,
        "enumerated": meta.get("enumerated"),
        "sample_every": meta.get("sample_every"),
        "score": detected / scored if scored else float("nan"),
        "control_s": meta.get("control_s"),
        "timeout_s": meta.get("timeout_s"),
        "exec_s": meta.get("exec_s"),
        "test_command": meta.get("test_command", "").replace(sys.executable, "python"),
        "survivors": sorted(survivors, key=lambda s: s["line"]),
        "equivalents": sorted(equivalents, key=lambda s: s["line"]),
        "contradicted_notes": contradicted,
    }


def prepare(workdir: pathlib.Path) -> pathlib.Path:
    """Copy the package and snapshot the tests into ``workdir``; return the package copy (checked to be imported)."""
    copy = workdir / "pkg" / "hood_decomp"
    repo = workdir / "repo"
    for folder in (copy.parent, repo):
        if folder.exists():
            shutil.rmtree(folder)
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "tests", repo / "tests", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    shutil.copy2(ROOT / "pyproject.toml", repo / "pyproject.toml")
    check = subprocess.run([sys.executable, "-c", "import hood_decomp; print(hood_decomp.__file__)"], cwd=repo,
                           env=_environment(copy.parent, repo), capture_output=True, text=True)
    if pathlib.Path(check.stdout.strip()).resolve().parent != copy.resolve():
        raise SystemExit(f"the tests would import {check.stdout.strip() or check.stderr}, not the copy {copy}")
    return copy


def print_report(rows: dict[str, dict]) -> None:
    print()
    every = sorted({row["sample_every"] for row in rows.values()})
    print(f"sample: every {'/'.join(map(str, every))}-th mutant per module (sorted by line, column, operator, "
          "occurrence), after leaving out the mutants inside annotations (never evaluated)")
    print("| module | enumerated | in annotations | run | killed | timeout | incompetent | survived (justified) | "
          "equivalent | score |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    keys = ("enumerated", "in_annotations", "run", "killed", "timeout", "incompetent", "survived", "justified",
            "equivalent")
    total = dict.fromkeys(keys, 0)
    for name, row in rows.items():
        for key in keys:
            total[key] += row[key] or 0
        print(f"| {name} | {row['enumerated']} | {row['in_annotations']} | {row['run']} | {row['killed']} | "
              f"{row['timeout']} | {row['incompetent']} | {row['survived']} ({row['justified']}) | "
              f"{row['equivalent']} | {100 * row['score']:.1f} % |")
    scored = total["run"] - total["equivalent"] - total["incompetent"]
    score = (total["killed"] + total["timeout"]) / scored if scored else float("nan")
    print(f"| **all** | {total['enumerated']} | {total['in_annotations']} | {total['run']} | {total['killed']} | "
          f"{total['timeout']} | {total['incompetent']} | {total['survived']} ({total['justified']}) | "
          f"{total['equivalent']} | **{100 * score:.1f} %** |")
    share = total["equivalent"] / total["run"] if total["run"] else 0.0
    print(f"\nequivalent: {total['equivalent']} of {total['run']} run ({100 * share:.1f} %)")
    for name, row in rows.items():
        for eq in row["equivalents"]:
            print(f"  EQUIVALENT {name}:{eq['line']} {eq['operator']}: {eq['old']!r} -> {eq['new']!r}: {eq['reason']}")
    for name, row in rows.items():
        for s in row["survivors"]:
            print(f"  SURVIVED {name}:{s['line']} {s['operator']}: {s['old']!r} -> {s['new']!r}: {s['reason']}")
        for c in row["contradicted_notes"]:
            print(f"  NOTE CONTRADICTED (killed) {name}:{c['line']} {c['operator']}: {c['old']!r} -> {c['new']!r}")
        if row["pending"]:
            print(f"  {name}: {row['pending']} mutants not run yet (use --resume)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--modules", nargs="*", default=None, help=f"of {[t.name for t in TARGETS]} (default: all)")
    parser.add_argument("--sample", type=int, default=3, help="keep every N-th mutant per module (1: all)")
    parser.add_argument("--workdir", type=pathlib.Path, default=DEFAULT_WORKDIR,
                        help="sessions and the package copy (never inside the repository)")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--resume", action="store_true", help="run only the mutants not run yet")
    group.add_argument("--retest-survivors", action="store_true", help="run the previous survivors again")
    parser.add_argument("--report-only", action="store_true", help="report the existing sessions, run nothing")
    args = parser.parse_args()
    names = [t.name for t in TARGETS]
    unknown = set(args.modules or ()) - set(names)
    if unknown:
        parser.error(f"unknown modules {sorted(unknown)}; known: {names}")
    targets = [t for t in TARGETS if args.modules is None or t.name in args.modules]
    workdir = args.workdir.resolve()
    if workdir == ROOT or ROOT in workdir.parents:
        parser.error("the work directory must be outside the repository (it holds the mutated copy)")
    workdir.mkdir(parents=True, exist_ok=True)
    mode = "resume" if args.resume else "retest" if args.retest_survivors else "fresh"

    rows: dict[str, dict] = {}
    if args.report_only:
        for target in targets:
            rows[target.name] = collect(target, workdir)
    else:
        with open(workdir / "lock", "w") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                parser.error(f"another run holds {workdir}; wait for it or use --report-only")
            try:
                copy = prepare(workdir)
                for target in targets:
                    start = time.perf_counter()
                    run_target(target, workdir, copy, args.sample, mode)
                    rows[target.name] = row = collect(target, workdir)
                    print(f"{target.name}: {row['run']} run, {row['killed'] + row['timeout']} killed, "
                          f"{row['survived']} survived, {row['equivalent']} equivalent, score "
                          f"{100 * row['score']:.1f} %, {time.perf_counter() - start:.0f} s", flush=True)
            finally:
                # The copy is only ever mutated inside cosmic-ray's exec; drop it so no mutated file outlives the run.
                shutil.rmtree(workdir / "pkg", ignore_errors=True)
    print_report(rows)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    previous = json.loads(OUT.read_text()) if OUT.is_file() else {}
    modules = {**previous.get("modules", {}), **rows}
    OUT.write_text(json.dumps({
        "date": datetime.date.today().isoformat(),
        "cosmic_ray": _version(),
        "modules": modules,
        "notes": [dataclasses.asdict(n) for n in NOTES],
    }, indent=1))
    print(f"\nwrote {OUT.relative_to(ROOT)}")
    return 0


def _version() -> str:
    from importlib.metadata import version

    return version("cosmic-ray")


if __name__ == "__main__":
    sys.exit(main())
