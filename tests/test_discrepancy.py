"""Model discrepancy for planning: the variogram estimate recovers a known process
and finds none in pure noise, the whitened features reproduce the kernel, the
augmented design reduces to the exact-model plan when there is no discrepancy,
and a planner that knows the model is not exact measures where the heliostat
operates instead of where the model has the most leverage."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj


def _normals(rng, h, m, spread=0.3):
    n = rng.normal(size=(h, m, 3)) * spread + np.array([0.0, 0.0, 1.0])
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _draw(process: hj.ModelDiscrepancy, normals: np.ndarray, rng) -> np.ndarray:
    """Residuals of ``process`` plus its nugget at ``normals`` (H, M, 3): exact GP draws."""
    h, m, _ = normals.shape
    out = np.empty((h, m, 2))
    for k in range(h):
        cov = np.asarray(process.kernel(normals[k], normals[k])) + 1e-9 * np.eye(m)
        out[k] = np.linalg.cholesky(cov) @ rng.normal(size=(m, 2)) + float(process.nugget_mrad) * rng.normal(
            size=(m, 2)
        )
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_variogram_estimate_recovers_a_known_process(seed):
    rng = np.random.default_rng(seed)
    truth = hj.ModelDiscrepancy(amplitude_mrad=1.0, length=0.3, nugget_mrad=0.3)
    normals = _normals(rng, 12, 60)
    est = hj.estimate_discrepancy(_draw(truth, normals, rng), normals, np.ones((12, 60), bool))
    # 12 heliostats x 60 records: the amplitude to ~20 %, the length to a factor 1.4
    # (one grid step of the length search is a factor 1.24), the nugget to ~20 %
    assert 0.8 < float(est.amplitude_mrad) < 1.25
    assert 0.3 / 1.4 < float(est.length) < 0.3 * 1.4
    assert 0.24 < float(est.nugget_mrad) < 0.36


def test_variogram_estimate_finds_no_process_in_pure_noise_and_ignores_unused_records():
    rng = np.random.default_rng(2)
    normals = _normals(rng, 20, 60)
    noise = 0.3 * rng.normal(size=(20, 60, 2))
    use = np.ones((20, 60), bool)
    use[:, 50:] = False
    noise[:, 50:] = 1e3  # gross values outside `use` must not enter
    est = hj.estimate_discrepancy(noise, normals, use)
    assert float(est.amplitude_mrad) < 0.1  # vs 1.0 above; the nugget carries the noise
    assert 0.27 < float(est.nugget_mrad) < 0.33
    few = hj.estimate_discrepancy(noise[:1, :5], normals[:1, :5], use[:1, :5])  # 10 pairs < 3 bins x 12
    assert float(few.amplitude_mrad) == 0.0


def test_model_discrepancy_rejects_bad_values():
    with pytest.raises(ValueError, match="amplitude_mrad"):
        hj.ModelDiscrepancy(amplitude_mrad=-1.0, length=0.2)
    with pytest.raises(ValueError, match="length"):
        hj.ModelDiscrepancy(amplitude_mrad=1.0, length=0.0)


def test_whitened_features_reproduce_the_kernel_at_the_inducing_normals():
    rng = np.random.default_rng(4)
    process = hj.ModelDiscrepancy(amplitude_mrad=0.7, length=0.25)
    points = _normals(rng, 2, 80)
    u = hj.inducing_normals(jnp.asarray(points), jnp.ones((2, 80), bool), 16)
    assert u.shape == (2, 16, 3)
    # farthest-point sampling: inducing normals are taken from the points, all distinct
    for k in range(2):
        d = np.linalg.norm(np.asarray(u[k])[:, None] - points[k][None], axis=-1)
        assert np.all(d.min(axis=1) < 1e-12)
        assert np.min(np.linalg.norm(np.asarray(u[k])[:, None] - np.asarray(u[k])[None], axis=-1) + np.eye(16)) > 0
    phi_u = np.asarray(hj.discrepancy_features(process, u[0], u[0]))
    np.testing.assert_allclose(phi_u @ phi_u.T, np.asarray(process.kernel(u[0], u[0])), atol=1e-6)
    # elsewhere the projected variance never exceeds the prior variance tau^2
    phi = np.asarray(jax.jit(hj.discrepancy_features)(process, jnp.asarray(points[0]), u[0]))
    np.testing.assert_allclose(
        phi, np.asarray(hj.discrepancy_features(process, jnp.asarray(points[0]), u[0])), rtol=1e-9, atol=1e-12
    )
    assert np.all(np.sum(phi**2, axis=1) <= 0.7**2 * (1 + 1e-6))
    zero = hj.ModelDiscrepancy(amplitude_mrad=0.0, length=0.25)
    assert np.all(np.asarray(hj.discrepancy_features(zero, jnp.asarray(points[0]), u[0])) == 0.0)


def test_augmented_jacobian_layout():
    jac = jnp.arange(2 * 3 * 2 * 4, dtype=jnp.float64).reshape(2, 3, 2, 4)
    phi = jnp.arange(2 * 3 * 5, dtype=jnp.float64).reshape(2, 3, 5) + 100.0
    out = np.asarray(hj.augment_jacobian(jac, phi))
    assert out.shape == (2, 3, 2, 4 + 10)
    np.testing.assert_array_equal(out[..., :4], np.asarray(jac))
    np.testing.assert_array_equal(out[..., 0, 4:9], np.asarray(phi))
    np.testing.assert_array_equal(out[..., 1, 9:], np.asarray(phi))
    assert np.all(out[..., 0, 9:] == 0) and np.all(out[..., 1, 4:9] == 0)


def test_a_planner_that_knows_the_model_is_not_exact_measures_where_it_operates():
    """One parameter, the envelope at normal n0. Candidate A at n0 (Jacobian 1), candidate B
    far away (Jacobian 3: more leverage). Trusting the model, B teaches the parameter most;
    with a discrepancy much larger than the noise, B's residual is mostly B's own
    discrepancy, and A, which also measures the discrepancy where the heliostat
    operates, is worth more."""
    n0 = np.array([0.0, 0.0, 1.0])
    n1 = np.array([np.sin(0.8), 0.0, np.cos(0.8)])
    normals = np.stack([n0, n1])
    jac = jnp.asarray(np.array([[[1.0], [0.0]], [[3.0], [0.0]]])[None])  # (1, 2, 2, 1)
    cov = jnp.ones((1, 1, 1))
    valid = jnp.ones((1, 2), bool)
    exact = hj.plan_measurements(cov, jac, valid, jnp.ones((1, 1, 1)), 0.1, 1)
    assert int(exact.chosen[0, 0]) == 1

    process = hj.ModelDiscrepancy(amplitude_mrad=1.0, length=0.2)
    u = hj.inducing_normals(jnp.asarray(normals[None]), valid, 2)
    phi = hj.discrepancy_features(process, jnp.asarray(normals), u[0])[None]  # (1, 2, B)
    jac_aug = hj.augment_jacobian(jac, phi)
    g = jac_aug.shape[-1]
    cov_aug = jnp.eye(g)[None]
    env = hj.augment_jacobian(jnp.asarray([[[1.0], [0.0]]]), phi[0, :1])[0]  # the envelope: n0 only
    m = (env.T @ env)[None]
    aware = hj.plan_measurements(cov_aug, jac_aug, valid, m, 0.1, 1)
    assert int(aware.chosen[0, 0]) == 0
    # and its predicted uncertainty counts the discrepancy: above the exact model's
    assert float(aware.uncertainty_before_mrad[0]) > float(exact.uncertainty_before_mrad[0])
