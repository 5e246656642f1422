"""The method on the real hood (issue 3's FE model): coarse in the default run, default resolution when slow.

Truth is the embedded FE solver with its exact pad contact (an independent code path from the estimators). The slow
test is the validation of section 4.1 at default resolution over 1400 random members: it writes Fig. 8/9/10-style
PNGs and a JSON summary to benchmarks/out/method_validation/ and checks the targets of issue 4.
"""

import json
import time
from pathlib import Path

import numpy as np
import pytest

hood_preset = pytest.importorskip("hood_decomp.core.fe.hood_preset", reason="needs the FE hood model (issue 3)")

from hood_decomp.cli import main  # noqa: E402
from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble, validation_plan  # noqa: E402
from hood_decomp.core.fe.model import skin_surface  # noqa: E402
from hood_decomp.core.fe.solver import build_solver, reduce_model  # noqa: E402
from hood_decomp.core.method.contact_estimation import ContactEstimator  # noqa: E402
from hood_decomp.core.method.decomposition import decompose, reconstruct_members  # noqa: E402
from hood_decomp.core.method.estimation import estimate_pca  # noqa: E402
from hood_decomp.core.method.hierarchical import HierarchicalBasis  # noqa: E402
from hood_decomp.core.method.pca import PCABasis  # noqa: E402
from hood_decomp.core.types import DisplacementField  # noqa: E402

OUT = Path(__file__).resolve().parents[3] / "benchmarks" / "out" / "method_validation"
NOISE_MM = 0.02


def build(resolution: str, n_validation: int):
    model = hood_preset.build_hood(resolution)
    skin = skin_surface(model)
    reduced = reduce_model(build_solver(model))
    commanded, rank = factorial_plan(model.lower, model.upper)
    training = simulate_ensemble(reduced, commanded, rank, model.lower, model.upper)
    validation = simulate_ensemble(reduced, validation_plan(model.lower, model.upper, n_validation, seed=1),
                                   np.full(n_validation, -1), model.lower, model.upper)
    return model, skin, reduced, training, validation


def field(skin, values, noise=float("nan")):
    return DisplacementField(skin.model_id, values, float(np.isfinite(values).mean()), noise)


def run_validation(skin, reduced, training, validation, model, noise_seed=0):
    """Errors (M, P) mm of the PCA and contact estimators, noise-free and noisy, and lifted-buffer checks."""
    pca = PCABasis(n_components=10).fit(training)
    contact = ContactEstimator().fit(reduced, model.lower, model.upper)
    rng = np.random.default_rng(noise_seed)
    n_b = reduced.n_bilateral
    out = {"pca": [], "contact": [], "contact_noisy": [], "noisy_std": [], "noisy_flag_ok": [], "observable": [],
           "lifted_wrong": 0, "commanded_above": 0.0, "seconds": []}
    for values, effective, commanded, fraction in zip(validation.normal_displacement, validation.effective,
                                                      validation.commanded, validation.contact_fraction, strict=True):
        out["pca"].append(estimate_pca(pca, field(skin, values)).values - effective)
        start = time.perf_counter()
        estimate = contact.estimate(field(skin, values))
        out["seconds"].append(time.perf_counter() - start)
        out["contact"].append(estimate.values - effective)
        lifted = fraction == 0
        out["observable"].append(np.concatenate([np.ones(n_b, bool), ~lifted]))  # hinges, locks, pads in contact
        out["lifted_wrong"] += int(np.any(estimate.lifted[n_b:] != lifted))
        above = commanded[n_b:][lifted] - estimate.values[n_b:][lifted]
        out["commanded_above"] = max(out["commanded_above"], float(above.max(initial=-np.inf)))
        noisy = values + rng.normal(0.0, NOISE_MM, values.size)
        estimate = contact.estimate(field(skin, noisy, NOISE_MM))
        out["contact_noisy"].append(estimate.values - effective)
        out["noisy_std"].append(estimate.std)
        out["noisy_flag_ok"].append(np.concatenate([np.ones(n_b, bool), estimate.lifted[n_b:] == lifted]))
    for key in ("pca", "contact", "contact_noisy", "noisy_std", "noisy_flag_ok", "observable"):
        out[key] = np.array(out[key])
    return pca, out


@pytest.fixture(scope="module")
def coarse():
    return build("coarse", 150)


@pytest.fixture(scope="module")
def coarse_validation(coarse):
    """(PCA basis, run_validation's result) on the coarse hood's 150 validation members."""
    model, skin, reduced, training, validation = coarse
    return run_validation(skin, reduced, training, validation, model)


def test_coarse_hood_estimators(coarse, coarse_validation):
    reduced = coarse[2]
    _, result = coarse_validation
    n_b = reduced.n_bilateral
    assert np.abs(result["contact"]).max() <= 1e-6
    assert result["lifted_wrong"] == 0 and result["commanded_above"] <= 0.01
    # Hinges and locks with the paper's estimator: the 0.0005 mm target is for the default mesh (slow test); the
    # coarse mesh's contact nonlinearity leaks a little more into them.
    assert np.abs(result["pca"][:, :n_b]).max() <= 0.002
    # ~1000 skin nodes and soft pad springs: with noise a buffer's commanded position is known to ~0.05-0.3 mm only;
    # what must hold is that the stated std covers the error where the contact flag is right, and that a wrong flag
    # (a pad near the onset of contact) costs little.
    z = np.abs(result["contact_noisy"] / result["noisy_std"])[result["noisy_flag_ok"]]
    assert np.mean(z > 3.0) <= 0.02
    # Bounds at 1.5x today's figures (2026-11-23, 150 members, seed 0): 4 wrong noisy flags of 300 pad states costing
    # at most 0.014 mm; hinges and locks 0.024 mm.
    assert (~result["noisy_flag_ok"]).sum() <= 6
    assert np.abs(result["contact_noisy"][~result["noisy_flag_ok"]]).max(initial=0.0) <= 0.021
    assert np.abs(result["contact_noisy"][:, :n_b]).max() <= 0.036


def test_coarse_hood_stated_std_is_the_spread(coarse, coarse_validation):
    """Fails if the contact estimator's std is inflated or shrunk (std x10 or / 10 both fail): per parameter, the
    median |error| / std over the members whose contact flag is right must be near a Gaussian's 0.674 (today
    0.62-0.80 over 150 members), and the error itself stays bounded."""
    model = coarse[0]
    _, result = coarse_validation
    z = np.abs(result["contact_noisy"] / result["noisy_std"])
    for p, name in enumerate(model.names):
        right = result["noisy_flag_ok"][:, p]
        assert 0.45 <= np.median(z[right, p]) <= 1.2, f"{name}: median |z| {np.median(z[right, p]):.3f}"
    assert np.abs(result["contact_noisy"])[result["observable"]].max() <= 0.05  # today 0.032 mm (BUFFER_L)


def test_coarse_hood_pca_estimator_today(coarse, coarse_validation):
    """Regression bounds beside the strict xfail of the paper's target: fails if the paper's PCA estimator gets
    worse than 1.5x today's figures (buffers 0.099 / 0.112 mm, eq. 5 without its centring term: 0.73 mm; lifted flag
    wrong on 6 of 150 members)."""
    _, skin, reduced, _, validation = coarse
    pca, result = coarse_validation
    n_b = reduced.n_bilateral
    assert np.abs(result["pca"][:, n_b:]).max() <= 0.17
    lifted_wrong = sum(
        int(np.any(estimate_pca(pca, field(skin, values)).lifted[n_b:] != (fraction == 0)))
        for values, fraction in zip(validation.normal_displacement, validation.contact_fraction, strict=True))
    assert lifted_wrong <= 9


def test_coarse_hood_hierarchical_and_decomposition(coarse):
    model, skin, reduced, training, validation = coarse
    basis = HierarchicalBasis(epsilon=0.01).fit(training)
    error = np.abs(reconstruct_members(basis, validation.normal_displacement) - validation.normal_displacement)
    assert error.max() <= 0.025  # the paper's Fig. 10 bound
    assert error.max() <= 0.001  # 1.5x today's 0.0006 mm (2026-11-23)
    contact = ContactEstimator().fit(reduced, model.lower, model.upper)
    f = field(skin, validation.normal_displacement[0])
    result = decompose(basis, f, contact.estimate(f))
    total = sum(e.partial_displacement for e in result.effects)
    np.testing.assert_allclose(sum(e.contribution for e in result.effects)[total > 0], 1.0, atol=1e-12)
    assert result.reconstruction_rms < 0.0011  # 1.5x today's 0.0007 mm (2026-11-23)


def test_cli_bases_estimate_on_the_coarse_hood(tmp_path, capsys):
    from hood_decomp.io.ensemble_store import write_ensemble
    from hood_decomp.io.fields import write_field
    from hood_decomp.io.model_files import save_model

    model = hood_preset.build_hood("coarse")
    skin = skin_surface(model)
    reduced = reduce_model(build_solver(model))
    save_model(model, tmp_path / "model")
    write_ensemble(tmp_path / "e.h5", reduced, skin, model.lower, model.upper, n_validation=0)
    code = main(["bases", "--ensemble", str(tmp_path / "e.h5"), "--model", str(tmp_path / "model"),
                 "--out", str(tmp_path / "b.h5"), "--epsilon", "0.01", "--plots", str(tmp_path / "plots")])
    assert code == 0, capsys.readouterr().err
    assert (tmp_path / "plots" / "explained_variance.png").is_file()
    truth = validation_plan(model.lower, model.upper, 1, seed=4)
    member = simulate_ensemble(reduced, truth, np.array([-1]), model.lower, model.upper)
    write_field(tmp_path / "f.vtu", skin, field(skin, member.normal_displacement[0]))
    assert main(["estimate", "--bases", str(tmp_path / "b.h5"), "--field", str(tmp_path / "f.vtu"),
                 "--json", str(tmp_path / "e.json")]) == 0
    result = json.loads((tmp_path / "e.json").read_text())
    for i, name in enumerate(model.names):
        # float32 storage of the ensemble does not matter here: the contact estimator uses the reduced model.
        assert result["parameters_mm"][name] == pytest.approx(member.effective[0, i], abs=1e-6)


@pytest.fixture(scope="module")
def default_validation():
    """Section 4.1 at default resolution, 1400 validation members; writes figures and a JSON summary."""
    from hood_decomp.plots.method import plot_error_boxplot, plot_error_histogram, plot_explained_variance

    model, skin, reduced, training, validation = build("default", 1400)
    pca, result = run_validation(skin, reduced, training, validation, model)
    OUT.mkdir(parents=True, exist_ok=True)
    names = list(model.names)
    plot_explained_variance(pca.explained_variance_ratio_, OUT / "fig8_explained_variance.png")
    for key in ("pca", "contact", "contact_noisy"):
        plot_error_boxplot(names, result[key], OUT / f"fig9_{key}.png", f"estimation error ({key}), 1400 members")
    z = np.abs(result["contact_noisy"] / result["noisy_std"])
    summary = {"skin_nodes": skin.n_nodes, "noisy_max_z_flag_right": float(z[result["noisy_flag_ok"]].max()),
               "noisy_fraction_z_above_3_flag_right": float(np.mean(z[result["noisy_flag_ok"]] > 3.0)),
               "noisy_flag_wrong_pads": int((~result["noisy_flag_ok"]).sum()),
               "noisy_median_std_mm": dict(zip(names, np.median(result["noisy_std"], axis=0).tolist(), strict=True)),
               "members": validation.n_members, "n_pad_springs": int(reduced.k.size),
               "contact_seconds_mean": float(np.mean(result["seconds"])),
               "lifted_wrong": result["lifted_wrong"], "commanded_above_reported_mm": result["commanded_above"],
               "pca_notes": list(pca.notes_)}
    for key in ("pca", "contact", "contact_noisy"):
        summary[f"{key}_max_abs_mm"] = dict(zip(names, np.abs(result[key]).max(axis=0).tolist(), strict=True))
        observable = np.where(result["observable"], np.abs(result[key]), 0.0).max(axis=0)
        summary[f"{key}_max_abs_observable_mm"] = dict(zip(names, observable.tolist(), strict=True))
    for epsilon in (0.1, 0.01):
        start = time.perf_counter()
        basis = HierarchicalBasis(epsilon=epsilon).fit(training)
        seconds = time.perf_counter() - start
        worst = np.abs(reconstruct_members(basis, validation.normal_displacement)
                       - validation.normal_displacement).max(axis=1)
        plot_error_histogram(worst, OUT / f"fig10_eps{epsilon}.png",
                             f"max reconstruction error, epsilon {epsilon} mm, {len(basis.effect_names_)} effects")
        summary[f"hierarchical_eps{epsilon}"] = {"effects": list(basis.effect_names_), "seconds": seconds,
                                                 "validation_max_error_mm": float(worst.max()),
                                                 "validation_median_max_error_mm": float(np.median(worst))}
    (OUT / "summary.json").write_text(json.dumps(summary, indent=2))
    return reduced.n_bilateral, result


@pytest.mark.slow
def test_default_contact_estimator_noise_free(default_validation):
    _, result = default_validation
    assert np.abs(result["contact"]).max() <= 1e-6
    assert result["lifted_wrong"] == 0 and result["commanded_above"] <= 0.01


@pytest.mark.slow
def test_default_pca_estimator_hinges_and_locks(default_validation):
    n_b, result = default_validation
    assert np.abs(result["pca"][:, :n_b]).max() <= 0.0005


@pytest.mark.slow
def test_default_noisy_std_covers_the_error(default_validation):
    _, result = default_validation
    z = np.abs(result["contact_noisy"] / result["noisy_std"])[result["noisy_flag_ok"]]
    # Gaussian errors exceed 3 std in 0.27 % of cases; the choice of the contact state adds a few outliers.
    assert np.mean(z > 3.0) <= 0.01


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="buffers in contact: the field is piecewise affine in the states (lifted / "
                   "partial / full pad contact), the paper's state map is one linear map: ~0.08 mm; see RESULTS.md")
def test_default_pca_estimator_paper_target_all_parameters(default_validation):
    _, result = default_validation
    assert np.abs(result["pca"])[result["observable"]].max() <= 0.004


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="0.02 mm noise: HINGE_X's stated std (the Cramer-Rao bound of this field) is "
                   "0.0034 mm, so the max over 1400 members is ~3.4 std = 0.012 mm; see RESULTS.md")
def test_default_noisy_contact_estimator_target(default_validation):
    _, result = default_validation
    assert np.abs(result["contact_noisy"])[result["observable"]].max() <= 0.004
