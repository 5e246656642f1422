"""The scan step's error model against the scatter of repeated scans (independent: only the scan noise differs) and
the marker registration's pose covariance against the scatter of repeated marker fits."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hood_decomp.core.scan.registration import marker_pose_covariance, rigid_from_markers
from hood_decomp.core.scan.scan_field import ScanFieldEstimator, field_from_scan
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan
from tests.skins import along_normals, crowned_patch, smooth_field

REPEATS = 12


@pytest.fixture(scope="module")
def repeated():
    """REPEATS scans of one displaced patch that differ only in their range noise (0.03 mm)."""
    skin = crowned_patch(57, 49, hole_radius_mm=110.0)
    displacement = along_normals(skin, smooth_field(skin, amplitude_mm=1.0))
    estimator = ScanFieldEstimator().fit(skin)
    config = ScannerConfig(n_points=100_000, noise_mm=0.03, outlier_fraction=0.0, dropout_fraction=0.0, n_holes=0,
                           pose_error_deg=0.0, pose_error_mm=0.0, marker_noise_mm=0.0)
    fields = []
    for seed in range(REPEATS):
        scan = synthesize_scan(skin, displacement, config, seed)
        # same pose and sampling every time; only the range noise draw changes (the scanner's rng is seeded alike up
        # to the noise, so the repeat-to-repeat scatter is the noise's, without the smoothing bias)
        fields.append(field_from_scan(skin, scan.points, scanner_pose=scan.true_transform, estimator=estimator)[0])
    return skin, fields, estimator


def test_node_std_and_correlation_predict_the_scatter_of_repeated_scans(repeated):
    """Fails if the stated node std is off the repeat-to-repeat scatter by more than 20 % (median over nodes), or if
    the correlation sums do not predict the variance of smooth averages of the field (patch means over ~100 nodes)
    between 0.4 and 1.5 times: white noise (correlation 1) would predict 5-10 times too little there; also if the
    twiced/plain variance ratio (about 1.78) is dropped from the node variance. Measured (twiced): node std ratio
    0.957, block-average ratio 0.787 (the blocks' 0/1 edges cut the ~130 mm correlation: on smooth fields the model
    is exact, see the Monte Carlo test below)."""
    assert repeated[2].twicing_
    skin, fields, _ = repeated
    values = np.array([f.normal_displacement for f in fields])
    seen = np.all(np.isfinite(values), axis=0)
    errors = values[:, seen] - values[:, seen].mean(axis=0)
    empirical = np.sqrt(np.sum(errors**2, axis=0) / (REPEATS - 1))
    model = fields[0].error_model
    assert model.kind == "scan" and model.correlation_length_mm > 0
    stated = np.nanmean([f.error_model.node_std[seen] for f in fields], axis=0)
    ratio = float(np.median(empirical / stated))
    assert 0.8 < ratio < 1.25, ratio
    correlation = model.correlation[seen]
    assert np.median(correlation) > 3.0  # the smoothing correlates neighbours
    # smooth averages: 0/1 indicators of 250 x 250 mm blocks (~100 nodes at 25 mm spacing)
    xy = skin.points[seen, :2]
    blocks = np.floor((xy - xy.min(axis=0)) / 250.0).astype(int)
    keys = blocks[:, 0] * 1000 + blocks[:, 1]
    predicted, observed = [], []
    for key in np.unique(keys):
        members = keys == key
        if members.sum() < 50:
            continue
        q = members / np.sqrt(members.sum())
        predicted.append(np.sum(q**2 * stated**2 * correlation))
        observed.append(np.sum((errors @ q) ** 2) / (REPEATS - 1))
    pooled = float(np.sum(observed) / np.sum(predicted))
    print(f"node std ratio {ratio:.3f}, smooth-average variance ratio {pooled:.3f}")
    assert 0.4 < pooled < 1.5, pooled


def test_marker_pose_covariance_matches_the_scatter_of_marker_fits():
    """Fails if the 6 x 6 pose covariance of the marker fit (sigma^2 (sum J^T J)^-1 about the marker centroid) is off
    the scatter of 2,000 Kabsch fits to noisy markers by more than 10 % on any rotation or translation variance, or
    if the rotation-translation cross terms of a twist about the centroid are not ~0."""
    rng = np.random.default_rng(0)
    nominal = np.array([[0, 0, 0], [1500, 0, 10], [1500, 1300, 0], [0, 1300, 20], [750, -100, 0], [750, 1400, 5],
                        [-100, 650, 0], [1600, 650, 15]], float)
    sigma = 0.03
    covariance, center = marker_pose_covariance(nominal, sigma)
    twists = []
    for _ in range(2000):
        transform, _ = rigid_from_markers(nominal + rng.normal(0.0, sigma, nominal.shape), nominal)
        rotation, translation = transform[:3, :3], transform[:3, 3]
        omega = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                          rotation[1, 0] - rotation[0, 1]]) / 2.0
        # displacement of the centroid by the fitted correction, as a twist about it
        twists.append(np.concatenate([omega, rotation @ center + translation - center]))
    empirical = np.cov(np.array(twists).T)
    np.testing.assert_allclose(np.diag(empirical), np.diag(covariance), rtol=0.1)
    assert np.max(np.abs(covariance[:3, 3:])) == 0.0
    scale = np.sqrt(np.max(np.diag(empirical)[:3]) * np.max(np.diag(empirical)[3:]))
    assert np.max(np.abs(empirical[:3, 3:])) < 0.1 * scale


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_the_smoothing_bias_allowance_matches_the_bias_on_a_coarse_mesh(coarse_hood):
    """The area FALLBACK (a skin prepared without its part's fields: this bare skin; the measured per-skin value is the
    next test's). The scan step's smoothing bias against the FE truth on the coarse hood (375 mm^2 nodes), 4 states,
    0.02 mm noise, points in the part frame: the allowance the one error model makes for it on a smooth unit-norm
    field's coefficient (``ModelCheck.bias_mm2``: the rough excess over the node noise times the bias' correlation sum)
    must cover the bias' largest projection on the skin's degree-2 smooth fields within a factor 2 in every state, and
    not exceed its mean projection more than 20 times (median over the states).
    Fails if the bias correlation is a node count again (tuned on the default hood's 59 mm^2 nodes: 30-80 times
    the mean projection here, the coarse scans' 97.4-99.95 % coverage and no false alarm of run 4), or if the bias
    term is dropped or under-counted (the within-model test then alarms on complete-model scans). Measured:
    allowance / largest projection 0.83-1.65, allowance / mean projection 1.8-3.9 (before twicing: 1.0-3.9 and
    4.7-12.4)."""
    from hood_decomp.core.fe.ensemble import solve_members
    from hood_decomp.core.method.bases import estimate_field
    from hood_decomp.core.method.residual import smooth_modes

    bases, reduced, skin = coarse_hood.bases, coarse_hood.reduced, coarse_hood.skin
    rng = np.random.default_rng(15)
    config = ScannerConfig(n_points=120_000, noise_mm=0.02, pose_error_deg=0.0, pose_error_mm=0.0, n_holes=0)
    to_largest, to_mean = [], []
    # a bare preparation of its own: field_from_scan(skin) takes the prepared skin registered for this skin object,
    # which carries the measured value once any test has read the bases file's scan skin
    bare = ScanFieldEstimator().fit(skin)
    for seed in range(4):
        member = solve_members(reduced, rng.uniform(bases.pca.lower_, bases.pca.upper_)[None])
        scan = synthesize_scan(skin, member.displacement[0], config, seed)
        field, _ = field_from_scan(skin, scan.points, scanner_pose=scan.true_transform, estimator=bare)
        bias = field.normal_displacement - member.normal_displacement[0]
        seen = np.isfinite(bias)
        projection = (smooth_modes(skin.points[seen], 2).T @ bias[seen]) ** 2  # node noise: ~1 % of it
        allowance = estimate_field(bases, field).check.bias_mm2
        to_largest.append(allowance / projection.max())
        to_mean.append(allowance / projection.mean())
    print(f"allowance / largest projection {np.round(to_largest, 2)}, / mean projection {np.round(to_mean, 1)}")
    assert min(to_largest) > 0.5, to_largest
    assert np.median(to_mean) < 20.0, to_mean


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_the_measured_bias_correlation_and_floor_match_noise_free_scans_of_fe_states(coarse_hood):
    """The bias correlation a prepared skin stores (core.loop.scan_skin: 24 FE states through the scan step's own
    field path on surface samples, minus what a scan reads of them) against the truth of 8 other FE states scanned
    noise-free by the synthetic scanner (Phong surface, 120,000 points, ray-cast, no pose error) through the public
    field path: the field minus what a scan reads of the FE state (its normal displacement less its slide,
    core.method.surface_reading, which the estimator takes out), split by the within-model test's own arithmetic
    (``bias_correlation_of``: mean smooth projection over the rough level per node). Must agree within 0.6-1.6
    times; fails if the per-skin measurement is removed (the area fallback, 157 nodes, is 6.6 times the truth), if
    it is made from one point per node at the node (13.3 nodes: 0.56 times), if the slide is left in the truth (55.4
    nodes: the stored value 0.39 times it), or if the stored value does not reach a scanned field's error model.
    Measured (issue 15 run 13): stored 21.8, truth 23.8. The same for the bias' level per node the prepared skin
    stores (``bias_variance_floor``, run 17): equal to the test's rough level written out here on the 24 states, and
    within 0.6-1.6 times the 8 scans' (stored 1.15e-5, scans 1.23e-5 mm^2); fails if it is not stored, does not reach
    the field, or is the sum over the states instead of their mean (24 times)."""
    from hood_decomp.core.fe.ensemble import solve_members
    from hood_decomp.core.loop.scan_skin import prepared_scan_skin, scan_bias
    from hood_decomp.core.method.residual import bias_correlation_of, smooth_modes
    from hood_decomp.core.method.surface_reading import SurfaceGradient, slide
    from hood_decomp.core.scan.scan_field import smoothing_bias_correlation

    bases, reduced, skin = coarse_hood.bases, coarse_hood.reduced, coarse_hood.skin
    arrays = prepared_scan_skin(bases)
    stored = float(arrays["bias_correlation"][0])
    # no outlier pass: on a noise-free cloud it would drop the curvature's own residuals (the next test)
    estimator = ScanFieldEstimator(outlier_sigma=1e9).fit(skin, prepared=arrays)
    gradient = SurfaceGradient.fit(skin)
    config = ScannerConfig(n_points=120_000, noise_mm=0.0, pose_error_deg=0.0, pose_error_mm=0.0, n_holes=0,
                           outlier_fraction=0.0, dropout_fraction=0.0)
    rng = np.random.default_rng(99)
    biases = []
    for seed in range(8):
        member = solve_members(reduced, rng.uniform(bases.pca.lower_, bases.pca.upper_)[None])
        moved, normal = member.displacement[0], member.normal_displacement[0]
        scan = synthesize_scan(skin, moved, config, seed)
        field = field_from_scan(skin, scan.points, scanner_pose=scan.true_transform, estimator=estimator)[0]
        assert field.error_model.bias_correlation == stored
        biases.append(field.normal_displacement - (normal - slide(gradient, normal, moved)))
    truth = bias_correlation_of(np.column_stack(biases), bases.pca.components_.T, field.error_model,
                                smooth_modes(skin.points, 2))
    print(f"stored {stored:.1f}, truth {truth:.1f}, area fallback {smoothing_bias_correlation(skin):.1f} nodes")
    assert 0.6 < stored / truth < 1.6, (stored, truth)
    # the bias' level per node (FieldErrorModel.bias_variance_floor): the stored one is the test's rough level of the
    # 24 states' biases (written out below, not through residual._smooth_split), and within a factor of the level
    # of the 8 noise-free scans
    floor = float(arrays["bias_variance_floor"][0])
    assert field.error_model.bias_variance_floor == floor
    states, state_errors = scan_bias(estimator, bases)
    design, modes = bases.pca.components_.T, smooth_modes(skin.points, 2)
    assert floor == pytest.approx(_rough_level(states, design, state_errors, modes), rel=1e-6)
    scanned = _rough_level(np.column_stack(biases), design, field.error_model, modes)
    print(f"bias variance floor stored {floor:.3g}, noise-free scans {scanned:.3g} mm^2 per node")
    assert 0.6 < floor / scanned < 1.6, (floor, scanned)


def _rough_level(bias: np.ndarray, design: np.ndarray, errors, modes: np.ndarray) -> float:
    """Mean over the columns of ``bias`` (N, k) mm of the rough energy (outside the span of ``design`` and ``modes``)
    over its expectation under ``errors`` (sum v - tr Q^T diag(v g) Q, Q an orthonormal basis of the span), times the
    mean node variance v: the within-model test's bias level per node (mm^2) at noise scale 1."""
    import scipy.linalg

    seen = np.all(np.isfinite(bias), axis=1)
    v, g = np.asarray(errors.node_std, float)[seen] ** 2, np.asarray(errors.correlation, float)[seen]
    q = scipy.linalg.orth(np.column_stack([design[seen], modes[seen]]))
    r = bias[seen]
    rough = np.sum(r * r, axis=0) - np.sum((q.T @ r) ** 2, axis=0)
    expected = v.sum() - float(np.sum((v * g)[:, None] * q * q))
    return float(np.mean(rough / expected * v.mean()))


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_twicing_removes_most_of_the_smoothing_bias_on_a_coarse_mesh(coarse_hood):
    """The scan step's node values against the FE truth on scans of the coarse hood (50 mm smoothing radius, 2
    states, 0.02 mm noise, no pose error): the twiced fit's RMS error must be below 0.65 times the plain fit's on
    the same points (node noise is about 0.0011-0.0015 mm of it), and a noise-free scan of the undeformed part must
    read below 0.001 mm RMS. Fails if the twicing pass is dropped or adds the residual fit with the wrong sign or
    from the wrong cell sums (the bias then stays or grows), or if the nominal geometry's quadrics bias the field.
    Measured: see the printout (about 0.5 times; 12-scan means: bias 0.009-0.011 -> 0.0043-0.005 mm); undeformed
    0.0004 mm. (Noise-free deformed scans do not show it: with no noise the outlier pass drops the curvature's own
    residuals.)"""
    from hood_decomp.core.fe.ensemble import solve_members

    bases, reduced, skin = coarse_hood.bases, coarse_hood.reduced, coarse_hood.skin
    plain, twiced = (ScanFieldEstimator(twicing=flag).fit(skin) for flag in (False, True))
    assert ScanFieldEstimator().fit(skin).twicing_  # on by default at this radius
    rng = np.random.default_rng(3)
    config = ScannerConfig(n_points=120_000, noise_mm=0.0, pose_error_deg=0.0, pose_error_mm=0.0, n_holes=0,
                           outlier_fraction=0.0, dropout_fraction=0.0)
    flat = synthesize_scan(skin, np.zeros((skin.n_nodes, 3)), config, 0)
    still = field_from_scan(skin, flat.points, scanner_pose=flat.true_transform, estimator=twiced)[0]
    assert np.sqrt(np.nanmean(still.normal_displacement**2)) < 0.001
    noisy = dataclasses.replace(config, noise_mm=0.02)
    for seed in range(2):
        member = solve_members(reduced, rng.uniform(bases.pca.lower_, bases.pca.upper_)[None])
        scan = synthesize_scan(skin, member.displacement[0], noisy, seed)
        rms = []
        for estimator in (plain, twiced):
            field = field_from_scan(skin, scan.points, scanner_pose=scan.true_transform, estimator=estimator)[0]
            bias = field.normal_displacement - member.normal_displacement[0]
            rms.append(float(np.sqrt(np.nanmean(bias**2))))
        print(f"RMS error plain {rms[0]:.4f} mm, twiced {rms[1]:.4f} mm")
        assert rms[1] < 0.65 * rms[0], rms


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_node_variance_and_smooth_projections_match_a_monte_carlo_of_white_point_noise():
    """The stated node variance and correlation sums against a Monte Carlo of the smoother itself on the coarse hood's
    skin (50 mm radius, twiced, free edges and cut-outs): one noise-free scan's points, each moved along its node's
    normal by independent white noise (0.02 mm) in 60 repeats, each turned into a field by the public path. Fails if
    the mean node variance is off the repeat-to-repeat scatter by more than 10 %, or if the variance of the field's
    projections on the skin's degree-2 smooth fields, as the within-model test states it (sum_i q_i^2 s_i^2 g_i), is
    off by more than 20 %: the kernel-average model with a constant twicing factor (1.8) over-stated it 1.47 times
    here (measured 0.68), so does dropping the plane fit's equivalent kernel (its one-sided inflation applied to a
    whole node's correlation sum) or the twiced weights 2 L - L L. Measured: node 1.005, smooth 0.927
    (benchmarks/RESULTS.md, issue 15 run 8)."""
    from hood_decomp.core.fe.hood_preset import build_preset
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.method.residual import smooth_modes

    skin = skin_surface(build_preset("hood", "coarse"))
    estimator = ScanFieldEstimator().fit(skin)
    assert estimator.twicing_
    config = ScannerConfig(n_points=100_000, noise_mm=0.0, outlier_fraction=0.0, dropout_fraction=0.0, n_holes=3,
                           pose_error_deg=0.0, pose_error_mm=0.0, marker_noise_mm=0.0)
    scan = synthesize_scan(skin, np.zeros((skin.n_nodes, 3)), config, 7)
    rotation, shift = scan.true_transform[:3, :3], scan.true_transform[:3, 3]
    points = scan.points @ rotation.T + shift
    node = estimator.point_distances(points).node
    points, direction = points[node >= 0], skin.normals[node[node >= 0]]
    rng = np.random.default_rng(11)
    sigma, repeats = 0.02, 60
    fields = [estimator.field(points + rng.normal(0.0, sigma, (points.shape[0], 1)) * direction)
              for _ in range(repeats)]
    values = np.array([f.normal_displacement for f in fields])
    seen = np.all(np.isfinite(values), axis=0)
    errors = values[:, seen] - values[:, seen].mean(axis=0)
    variance = np.mean([f.error_model.node_std[seen] ** 2 for f in fields], axis=0)
    correlation = np.mean([f.error_model.correlation[seen] for f in fields], axis=0)
    node_ratio = float(np.mean(np.var(errors, axis=0, ddof=1)) / np.mean(variance))
    modes = smooth_modes(skin.points[seen], 2)
    smooth_ratio = float(np.sum(np.var(errors @ modes, axis=0, ddof=1)) / np.sum(modes.T**2 @ (variance * correlation)))
    print(f"node variance ratio {node_ratio:.3f}, smooth projections {smooth_ratio:.3f}, noise "
          f"{np.mean([f.noise_rms for f in fields]):.4f} mm")
    assert 0.9 < node_ratio < 1.1, node_ratio
    assert 0.8 < smooth_ratio < 1.2, smooth_ratio
