"""Force-deformation models of the membrane (thesis §2.4): Hertz, per-PV linear fits, force matching."""

import numpy as np
import pytest
from scipy import stats

from defgraspnets.tactile.force_models import (
    ForceMatchingController,
    HertzModel,
    LinearForceModel,
    PVForceModel,
    depth_force_proxy,
    effective_modulus,
    effective_radius,
    fit_hertz,
    fit_linear,
    fit_linear_per_state,
    fit_polynomial,
    force_error_table,
    hertz_force,
    indentation_depth,
    mean_and_standard_error,
)


def test_effective_properties_and_hertz_law():
    # rigid indenter (E = inf) on an elastic sphere: E* = E / (1 - nu^2)
    assert effective_modulus(1e5, 0.5, np.inf, 0.3) == pytest.approx(1e5 / 0.75)
    assert effective_radius(0.005, np.inf) == pytest.approx(0.005)
    assert effective_radius(0.005, 0.05) == pytest.approx(1 / (200 + 20))
    e, r = 2e5, 0.004
    f = hertz_force([0.0, 0.001, -0.001, 0.004], e, r)
    assert f[0] == 0 and f[2] == 0
    assert f[1] == pytest.approx(4 / 3 * e * np.sqrt(r) * 0.001**1.5)
    assert f[3] / f[1] == pytest.approx(4**1.5)
    model = HertzModel.from_materials(e, r)
    assert model.indentation(model.force(0.003)) == pytest.approx(0.003)
    with pytest.raises(ValueError, match="poisson"):
        effective_modulus(1e5, 0.7, 1e5, 0.3)


def test_hertz_fit_recovers_parameters_and_uncertainty_from_noisy_data():
    rng = np.random.default_rng(0)
    e_true, r_star, sigma = 8.0e4, effective_radius(0.005, 0.05), 0.02
    delta = np.linspace(0.5e-3, 10e-3, 40)
    f_true = hertz_force(delta, e_true, r_star)
    fits = [fit_hertz(delta, f_true + sigma * rng.standard_normal(delta.size), r_star) for _ in range(300)]
    e_hat = np.array([f.effective_modulus for f in fits])
    e_std = np.array([f.effective_modulus_std for f in fits])
    assert abs(e_hat.mean() - e_true) < 3 * e_hat.std() / np.sqrt(e_hat.size)  # unbiased
    assert e_std.mean() == pytest.approx(e_hat.std(), rel=0.15)  # reported SE matches the scatter
    assert np.abs(e_hat - e_true).max() < 5 * e_std.mean()
    assert np.mean([f.residual_std for f in fits]) == pytest.approx(sigma, rel=0.05)
    with pytest.raises(ValueError, match="pre-contact"):
        fit_hertz([0.0, 1e-3], [0.0, 1.0])


def test_linear_fit_matches_reference_regression():
    rng = np.random.default_rng(1)
    d = np.linspace(0, 8e-3, 25)
    f = 150.0 * d + 0.1 + 0.03 * rng.standard_normal(d.size)
    fit = fit_linear(d, f)
    ref = stats.linregress(d, f)
    assert fit.slope == pytest.approx(ref.slope)
    assert fit.intercept == pytest.approx(ref.intercept)
    assert fit.slope_std == pytest.approx(ref.stderr)
    assert fit.intercept_std == pytest.approx(ref.intercept_stderr)
    assert fit.r_squared == pytest.approx(ref.rvalue**2)
    assert fit.model.indentation(fit.model.force(4e-3)) == pytest.approx(4e-3)
    with pytest.raises(ValueError, match="non-finite"):
        fit_linear([0.0, 1.0, np.nan], [0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="same length"):
        fit_linear([0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 2.0])


def test_slope_versus_pv_quartic_gives_a_force_model_per_gas_state():
    rng = np.random.default_rng(2)
    pv = np.linspace(30.0, 110.0, 9)  # [N m]

    def k_true(x):  # monotone, non-linear slope [N/m] (cf. Fig. 2.10)
        return 400.0 * (1 - np.exp(-(x - 20.0) / 30.0)) + 50.0

    delta = np.linspace(0.5e-3, 8e-3, 30)
    series_d = [delta] * pv.size
    series_f = [k_true(p) * delta + 0.01 * rng.standard_normal(delta.size) for p in pv]
    fits = fit_linear_per_state(series_d, series_f)
    slopes = np.array([f.slope for f in fits])
    assert np.allclose(slopes, k_true(pv), rtol=0.02)
    model = PVForceModel.fit(pv, slopes, order=4)
    assert model.slope_fit.order == 4
    grid = np.linspace(35.0, 105.0, 15)
    assert np.allclose(model.slope_fit(grid), k_true(grid), rtol=0.02)
    assert (model.slope_fit.standard_error(grid) > 0).all()
    lin = model.at(61.2)
    assert lin.force(5e-3) == pytest.approx(k_true(61.2) * 5e-3, rel=0.02)
    with pytest.raises(ValueError, match="outside the characterized range"):
        model.at(150.0)
    with pytest.raises(ValueError, match="distinct"):
        fit_polynomial([1.0, 1.0, 2.0, 2.0, 3.0], [1.0, 2.0, 3.0, 4.0, 5.0], order=4)


def test_polynomial_fit_is_exact_for_a_quartic():
    x = np.linspace(20.0, 120.0, 12)
    y = 1e-5 * x**4 - 2e-3 * x**3 + 0.1 * x**2 + x + 3
    fit = fit_polynomial(x, y, 4)
    assert np.allclose(fit(x), y, rtol=1e-9)
    assert fit(70.0) == pytest.approx(1e-5 * 70**4 - 2e-3 * 70**3 + 0.1 * 70**2 + 70 + 3)


def spherical_dent_depth(depth=0.004, size=64):
    """Reference depth image of a flat membrane at 6 cm and a dent from a 1 cm sphere."""
    r, c = np.mgrid[0:size, 0:size] - (size - 1) / 2
    rho = np.hypot(r, c) * 0.5e-3
    ref = np.full((size, size), 0.06)
    dent = np.clip(depth - (0.005 - np.sqrt(np.clip(0.005**2 - rho**2, 0, None))), 0, None)
    return ref - dent, ref


def test_indentation_depth_from_depth_images():
    img, ref = spherical_dent_depth(0.004)
    assert indentation_depth(img, ref) == pytest.approx(0.004, abs=2e-5)
    noisy = img.copy()
    noisy[0, 0] -= 0.02  # one outlier pixel
    assert indentation_depth(noisy, ref) == pytest.approx(0.02)
    assert indentation_depth(noisy, ref, percentile=99.9) < 0.0045
    holed = img.copy()
    holed[:10] = np.nan
    assert indentation_depth(holed, ref) == pytest.approx(0.004, abs=2e-5)
    with pytest.raises(ValueError, match="no pixel"):
        indentation_depth(np.full_like(img, np.nan), ref)
    with pytest.raises(ValueError, match="equal shapes"):
        indentation_depth(img[:-1], ref)


def test_depth_force_proxy_sums_depth_decrease():
    img, ref = spherical_dent_depth(0.004)
    assert depth_force_proxy(img, ref) == pytest.approx(float((ref - img).sum()))
    assert depth_force_proxy(ref, ref) == 0.0
    deeper, _ = spherical_dent_depth(0.006)
    assert depth_force_proxy(deeper, ref) > depth_force_proxy(img, ref)


def simulate_force_matching(controller, desired_force, true_model, steps=60, noise=0.0, seed=0):
    """Plant: the membrane indentation follows the actuator travel past first contact."""
    rng = np.random.default_rng(seed)
    z_contact, z = 0.010, 0.0  # actuator position [m]; contact starts at 10 mm travel
    forces = []
    for _ in range(steps):
        delta = max(z - z_contact, 0.0)
        measured = delta + noise * rng.standard_normal()
        z += controller.step(measured, desired_force).displacement
        forces.append(float(true_model.force(max(z - z_contact, 0.0))))
    return np.array(forces)


def test_force_matching_controller_converges_to_the_desired_force():
    model = LinearForceModel(slope=250.0)
    ctrl = ForceMatchingController(model, gain=0.5, max_step=2e-3)
    for f_des in (0.5, 1.0, 2.0):
        forces = simulate_force_matching(ctrl, f_des, model)
        assert forces[-1] == pytest.approx(f_des, abs=1e-6)
        assert (np.abs(forces[-10:] - f_des) < 1e-5).all()
    # with depth noise the mean error stays small; with a wrong model it reflects the model error
    noisy = simulate_force_matching(ctrl, 1.0, model, steps=400, noise=5e-5)
    mean, se = mean_and_standard_error(noisy[100:] - 1.0)
    assert abs(mean) < 0.01 and se < 0.01
    hertz = HertzModel(coefficient=5e4)
    biased = simulate_force_matching(ForceMatchingController(model), 1.0, hertz)
    assert biased[-1] == pytest.approx(float(hertz.force(1.0 / 250.0)), rel=1e-6)
    # unit gain and no saturation: the target is reached in one step
    cmd = ForceMatchingController(model, gain=1.0, max_step=1.0).step(0.001, 1.0)
    assert cmd.target_indentation == pytest.approx(0.004)
    assert cmd.displacement == pytest.approx(0.003)
    with pytest.raises(ValueError, match="desired_force"):
        ctrl.step(0.0, -1.0)


def test_force_error_table_mean_and_standard_error():
    pv = np.array([32.5] * 3 + [61.2] * 3)
    desired = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])
    actual = desired + np.array([0.2, 0.3, 0.4, -0.1, 0.0, 0.1])
    table = force_error_table(pv, actual, desired)
    assert set(table) == {32.5, 61.2}
    assert table[32.5][0] == pytest.approx(0.3)
    assert table[32.5][1] == pytest.approx(0.1 / np.sqrt(3))
    assert table[61.2][0] == pytest.approx(0.0, abs=1e-12)
    m, se = mean_and_standard_error([5.0])
    assert m == 5.0 and np.isnan(se)
