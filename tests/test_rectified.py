import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jaxdrive import flow

SHAPE = (2, 3, 4, 5, 2)  # [B, F, h, w, C]


def _data(seed=0, shape=SHAPE):
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    return jax.random.normal(k1, shape), jax.random.normal(k2, shape)


def test_add_noise_worked_number():
    x = jnp.full((1, 1, 1, 1, 1), 2.0)
    n = jnp.full((1, 1, 1, 1, 1), -1.0)
    # (1 - 0.25) * 2 + 0.25 * (-1) = 1.25
    assert float(flow.add_noise(x, n, jnp.array([0.25]))[0, 0, 0, 0, 0]) == pytest.approx(1.25)
    assert float(flow.velocity_target(x, n)[0, 0, 0, 0, 0]) == -3.0


def test_add_noise_endpoints_exact():
    x, n = _data()
    np.testing.assert_array_equal(flow.add_noise(x, n, jnp.zeros(2)), x)
    np.testing.assert_array_equal(flow.add_noise(x, n, jnp.ones(2)), n)


def test_per_frame_sigma_hits_the_frame_axis_of_multiview_latents():
    x, n = _data(shape=(2, 6, 3, 2, 2, 4))  # [B, V, F, h, w, C]
    sigma = jnp.array([[0.0, 0.5, 1.0], [1.0, 0.0, 0.25]])
    out = flow.add_noise(x, n, sigma)
    for b in range(2):
        for f in range(3):
            s = float(sigma[b, f])
            np.testing.assert_allclose(out[b, :, f], (1 - s) * x[b, :, f] + s * n[b, :, f], atol=1e-6)


def test_per_sample_equals_constant_per_frame():
    x, n = _data()
    s = jnp.array([0.3, 0.7])
    np.testing.assert_array_equal(flow.add_noise(x, n, s), flow.add_noise(x, n, jnp.broadcast_to(s[:, None], (2, 3))))


@given(st.floats(0.01, 0.99), st.integers(0, 2**16))
def test_conversions_round_trip(s, seed):
    x, n = _data(seed)
    sigma = jnp.array([s, 1 - s])
    xt = flow.add_noise(x, n, sigma)
    v = flow.velocity_target(x, n)
    np.testing.assert_allclose(flow.data_from_velocity(xt, v, sigma), x, atol=2e-5)
    np.testing.assert_allclose(flow.noise_from_velocity(xt, v, sigma), n, atol=2e-5)
    np.testing.assert_allclose(flow.velocity_from_data(xt, x, sigma), v, rtol=1e-3, atol=2e-3)
    np.testing.assert_allclose(flow.velocity_from_noise(xt, n, sigma), v, rtol=1e-3, atol=2e-3)


def test_euler_step_along_exact_velocity_stays_on_the_path():
    x, n = _data()
    v = flow.velocity_target(x, n)
    s, s2 = jnp.array([0.9, 0.6]), jnp.array([0.4, 0.1])
    np.testing.assert_allclose(flow.euler_step(flow.add_noise(x, n, s), v, s, s2), flow.add_noise(x, n, s2), atol=1e-6)


def test_jit_vmap_grad():
    x, n = _data()
    sigma = jnp.full((2, 3), 0.4)
    np.testing.assert_allclose(jax.jit(flow.add_noise)(x, n, sigma), flow.add_noise(x, n, sigma), atol=1e-7)
    per_clip = jax.vmap(lambda a, b, s: flow.add_noise(a[None], b[None], s[None])[0])(x, n, sigma)
    np.testing.assert_allclose(per_clip, flow.add_noise(x, n, sigma), atol=1e-7)
    g = jax.grad(lambda s: flow.add_noise(x, n, s).sum())(sigma)
    np.testing.assert_allclose(g, (n - x).sum(axis=(2, 3, 4)), rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize(
    "sigma, match",
    [
        (jnp.array([0.5, 1.5]), r"sigma: expected values in \[0.0, 1.0\], got values in \[0.5, 1.5\]"),
        (jnp.array([-0.1, 0.5]), "sigma: expected values in"),
        (jnp.array([0.5, 0.5, 0.5]), r"sigma: expected shape \[B\] or \[B, F\]"),
        (jnp.zeros((2, 4)), r"sigma: expected shape \[B\] or \[B, F\] = \[2, 3\]"),
        (jnp.zeros((2, 3, 1)), "sigma: expected shape"),
    ],
)
def test_add_noise_rejects_bad_sigma(sigma, match):
    x, n = _data()
    with pytest.raises(ValueError, match=match):
        flow.add_noise(x, n, sigma)


def test_add_noise_rejects_mismatched_noise():
    x, n = _data()
    with pytest.raises(ValueError, match=r"noise: expected the shape of x \[2, 3, 4, 5, 2\], got \[2, 3, 4, 5, 1\]"):
        flow.add_noise(x, n[..., :1], jnp.ones(2))


def test_traced_sigma_is_not_inspected():
    x, n = _data()
    # Under jit a traced sigma cannot be range-checked (doing so would raise a concretization
    # error); the call traces and gives the eager result.
    sigma = jnp.array([0.2, 0.3])
    np.testing.assert_allclose(jax.jit(flow.add_noise)(x, n, sigma), flow.add_noise(x, n, sigma), atol=1e-7)


@given(st.floats(0.06, 0.99), st.integers(0, 2**16))
def test_data_prediction_gives_the_velocity_of_its_data_estimate(s, seed):
    x, n = _data(seed)
    sigma = jnp.array([s, 1 - s if 1 - s > 0.05 else 0.5])
    xt = flow.add_noise(x, n, sigma)
    # a perfect data prediction is the true velocity; a velocity output passes through untouched
    np.testing.assert_allclose(
        flow.velocity_from_output(x, xt, sigma, "data"), flow.velocity_target(x, n), rtol=1e-3, atol=2e-3
    )
    np.testing.assert_array_equal(flow.velocity_from_output(n, xt, sigma, "velocity"), n)


def test_data_prediction_worked_number_and_clamp():
    xt = jnp.full((2, 1, 1, 1, 1), 1.0)
    out = jnp.full((2, 1, 1, 1, 1), 0.5)
    # (1 - 0.5) / 0.25 = 2; below min_sigma the level is clamped: (1 - 0.5) / 0.05 = 10, finite at 0
    v = flow.velocity_from_output(out, xt, jnp.array([0.25, 0.0]), "data", min_sigma=0.05)
    np.testing.assert_allclose(v.ravel(), [2.0, 10.0], rtol=1e-6)
    # an Euler step from s >= min_sigma to 0 lands on the data estimate
    s = jnp.array([0.3, 0.05])
    v = flow.velocity_from_output(out, xt, s, "data")
    np.testing.assert_allclose(flow.euler_step(xt, v, s, jnp.zeros(2)), out, atol=1e-6)


@pytest.mark.parametrize(
    "kw, match",
    [(dict(prediction="noise"), "prediction: expected one of"), (dict(prediction="data", min_sigma=0.0), "min_sigma")],
)
def test_velocity_from_output_rejects_bad_arguments(kw, match):
    x = jnp.ones((1, 1, 1, 1, 1))
    with pytest.raises(ValueError, match=match):
        flow.velocity_from_output(x, x, jnp.ones(1) * 0.5, **kw)


def test_skip_coefficients_worked_number_and_ends():
    """EDM's c_skip, c_out (Karras et al. 2022, eq. 7) in this flow's convention: at level 0.5 and
    sigma_data 0.5, var = 0.25^2 + 0.5^2 = 0.3125, c_skip = 0.5 * 0.25 / 0.3125 = 0.4, c_out =
    0.25 / sqrt(0.3125) = 0.44721; level 0 passes the input through, level 1 only the network."""
    c_skip, c_out = flow.skip_coefficients(jnp.asarray([0.0, 0.5, 1.0]), 0.5)
    np.testing.assert_allclose(c_skip, [1.0, 0.4, 0.0], atol=1e-6)
    np.testing.assert_allclose(c_out, [0.0, 0.4472136, 0.5], atol=1e-6)


@given(st.floats(0.05, 0.95), st.floats(0.1, 2.0))
def test_skip_coefficients_leave_a_unit_variance_target_at_its_least_squares_optimum(s, sd):
    """For data of standard deviation ``sd``, ``c_skip x_t`` is the least-squares linear estimate
    of ``x`` and the network's target ``(x - c_skip x_t) / c_out`` has unit variance (analytic
    moments of ``x_t = (1 - s) x + s n``)."""
    c_skip, c_out = (float(a) for a in flow.skip_coefficients(s, sd))

    def residual_var(c):  # Var(x - c x_t)
        return (1 - c * (1 - s)) ** 2 * sd**2 + (c * s) ** 2

    assert residual_var(c_skip) / c_out**2 == pytest.approx(1.0, rel=1e-5)
    for dc in (-1e-3, 1e-3):
        assert residual_var(c_skip + dc) > residual_var(c_skip)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(sigma=0.5, sigma_data=0.0), r"sigma_data: expected values in \(0"),
        (dict(sigma=1.5, sigma_data=0.5), r"sigma: expected values in \[0"),
    ],
)
def test_skip_coefficients_reject_bad_arguments(kw, match):
    with pytest.raises(ValueError, match=match):
        flow.skip_coefficients(**kw)
