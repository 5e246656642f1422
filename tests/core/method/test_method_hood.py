"""The method on the real hood (issue 3's FE model): coarse in the default run, default resolution when slow.

Truth is the embedded FE solver with its exact pad contact (an independent code path from the estimators;
tests/hood_validation.py). The slow tests are section 4.1's validation at default resolution on the first
DEFAULT_MEMBERS of the 1400 random members that benchmarks/bench_method_hood.py runs in full (with the Fig. 8/9/10-style
figures and RESULTS.md's table): every bound below is a maximum or a rate that a quarter of the members tests as well,
and the strict xfails stay failing on it (buffers 0.08 mm and HINGE_X 0.012 mm against 0.004 mm over 1400).
"""

import json

import numpy as np
import pytest

hood_preset = pytest.importorskip("hood_decomp.core.fe.hood_preset", reason="needs the FE hood model (issue 3)")

from hood_decomp.cli import main  # noqa: E402
from hood_decomp.core.fe.ensemble import simulate_ensemble, validation_plan  # noqa: E402
from hood_decomp.core.fe.model import skin_surface  # noqa: E402
from hood_decomp.core.fe.solver import build_solver, reduce_model  # noqa: E402
from hood_decomp.core.method.contact_estimation import ContactEstimator  # noqa: E402
from hood_decomp.core.method.decomposition import decompose, reconstruct_members  # noqa: E402
from hood_decomp.core.method.estimation import estimate_pca  # noqa: E402
from hood_decomp.core.method.hierarchical import HierarchicalBasis  # noqa: E402
from tests.hood_validation import build, field, run_validation, validation_members  # noqa: E402

DEFAULT_MEMBERS = 350


@pytest.fixture(scope="module")
def coarse():
    model, skin, reduced, training = build("coarse")
    return model, skin, reduced, training, validation_members(model, reduced, 150)


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
def default_validation(default_hood):
    """Section 4.1 at default resolution on the session's default hood and the first DEFAULT_MEMBERS of the
    benchmark's 1400 validation members (benchmarks/bench_method_hood.py runs all 1400 and draws the figures)."""
    model, reduced = default_hood.model, default_hood.reduced
    validation = validation_members(model, reduced, DEFAULT_MEMBERS)
    _, result = run_validation(default_hood.skin, reduced, default_hood.ensemble, validation, model)
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
