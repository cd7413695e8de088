import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jaxdrive import flow


def test_worked_numbers():
    # g = 0.5, a1 = 0.1: a2 = 0.4 / 0.9
    assert float(flow.jdc_alpha2(0.5, 0.1)) == pytest.approx(4 / 9)
    # eq. 11 at a1 = 0.1, a2 = 0.5: (0.5 - 0.1 + 0.2) / 0.5 = 1.2
    assert float(flow.jdc_noise_var(0.1, 0.5)) == pytest.approx(1.2)
    # no prior error: the second stage is plain rectified flow with unit noise
    assert float(flow.jdc_noise_var(0.0, 0.7)) == pytest.approx(1.0)


@given(st.floats(0.0, 0.95), st.floats(0.0, 1.0))
def test_eq12_and_eq20_hold(a1, u):
    g = a1 + u * (1 - a1)  # any level in [a1, 1]
    a2 = float(flow.jdc_alpha2(g, a1))
    assert 0.0 <= a2 <= 1.0 + 1e-6
    assert 1 - (1 - a1) * (1 - a2) == pytest.approx(g, abs=1e-5)  # eq. 12
    if a2 > 1e-3:
        var = float(flow.jdc_noise_var(a1, a2))
        # eq. 20: a2^2 s^2 + a1^2 (1 - a2)^2 = g^2
        assert a2**2 * var + a1**2 * (1 - a2) ** 2 == pytest.approx(g**2, rel=1e-4, abs=1e-6)


@pytest.mark.parametrize("g, a1", [(0.6, 0.2), (0.3, 0.3), (0.9, 0.0), (1.0, 0.5)])
def test_monte_carlo_total_noise_is_g_around_the_clean_signal(g, a1):
    """eq. 8 error model + eq. 9 re-noising = a point of the rectified-flow path at level g."""
    k_x, k_n1, k_r = jax.random.split(jax.random.PRNGKey(7), 3)
    shape = (4, 2, 64, 64, 4)
    x = jax.random.normal(k_x, shape)
    z = (1 - a1) * x + a1 * jax.random.normal(k_n1, shape)  # eq. 8
    xn = flow.jdc_renoise(k_r, z, g, a1)  # eq. 9
    residual = xn - (1 - g) * x  # total noise (eq. 10)
    assert float(jnp.std(residual)) == pytest.approx(g, rel=0.01, abs=1e-3)
    assert abs(float(jnp.mean(residual))) < 0.01
    # the noise is independent of the signal: the regression of xn on x has slope 1 - g
    slope = float(jnp.sum(xn * x) / jnp.sum(x * x))
    assert slope == pytest.approx(1 - g, abs=0.01)


def test_g_equal_alpha1_leaves_anchors_unchanged():
    z = jax.random.normal(jax.random.PRNGKey(0), (2, 3, 4, 4, 2))
    np.testing.assert_allclose(flow.jdc_renoise(jax.random.PRNGKey(1), z, 0.25, 0.25), z, atol=1e-7)


def test_per_frame_g():
    z = jnp.zeros((2, 3, 8, 8, 4))
    g = jnp.array([[0.1, 0.5, 0.9], [0.2, 0.2, 0.2]])
    out = flow.jdc_renoise(jax.random.PRNGKey(0), z, g, 0.1)
    # zero signal: what remains is the n2 part, std a2 * s = sqrt(g^2 - a1^2 (1 - a2)^2)
    a2 = (g - 0.1) / 0.9
    want = jnp.sqrt(g**2 - 0.01 * (1 - a2) ** 2)
    np.testing.assert_allclose(out[0, 0], 0.0, atol=1e-7)
    assert float(jnp.std(out[0, 2])) == pytest.approx(float(want[0, 2]), rel=0.15)


def test_anchor_schedule_is_linear_and_reaches_zero():
    s = jnp.linspace(0, 1, 5)
    np.testing.assert_allclose(flow.jdc_anchor_sigma(s, 0.5), 0.5 * s)
    assert float(flow.jdc_anchor_sigma(0.0, 0.8)) == 0.0


def test_jit():
    z = jnp.ones((2, 1, 2, 2, 1))
    out = jax.jit(flow.jdc_renoise)(jax.random.PRNGKey(0), z, jnp.array([0.5, 0.6]), 0.2)
    assert out.shape == z.shape and bool(jnp.all(jnp.isfinite(out)))


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: flow.jdc_alpha2(0.5, 1.0), r"alpha1: expected values in \[0.0, 1.0\), got 1"),
        (lambda: flow.jdc_alpha2(0.5, -0.1), "alpha1: expected values in"),
        (lambda: flow.jdc_alpha2(0.1, 0.3), r"g: expected g >= alpha1 = 0.3 .*got min g = 0.1"),
        (lambda: flow.jdc_alpha2(1.2, 0.3), r"g: expected values in \[0.0, 1.0\]"),
        (lambda: flow.jdc_noise_var(0.1, 0.0), r"alpha2: expected values in \(0.0, 1.0\]"),
        (
            lambda: flow.jdc_renoise(jax.random.PRNGKey(0), jnp.ones((2, 1, 1, 1, 1)), 0.1, 0.2),
            "g: expected g >= alpha1",
        ),
        (
            lambda: flow.jdc_renoise(jax.random.PRNGKey(0), jnp.ones((2, 1, 1, 1, 1)), jnp.ones(3) * 0.5, 0.2),
            r"g: expected shape \[B\] or \[B, F\]",
        ),
        (
            lambda: flow.jdc_renoise(jax.random.PRNGKey(0), jnp.ones((2, 1, 1, 1, 1)), 0.5, jnp.array([0.1, 0.2])),
            "alpha1: expected a scalar",
        ),
        (lambda: flow.jdc_anchor_sigma(0.5, 0.0), r"slope: expected values in \(0.0, 1.0\]"),
    ],
)
def test_bad_inputs(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# ------------------------------------------------------------------------- training anchors
def _anchor_case(g_values, shape=(3, 2, 64, 64, 4)):
    """Clean latents, noise and levels with frame 1 of every clip an anchor at g_values[b]."""
    k_x, k_n = jax.random.split(jax.random.PRNGKey(11))
    x = jax.random.normal(k_x, shape)
    noise = jax.random.normal(k_n, shape)
    levels = jnp.stack([jnp.full(len(g_values), 0.7), jnp.asarray(g_values)], axis=1)
    anchor = jnp.zeros((shape[0], 2), bool).at[:, 1].set(True)
    return x, noise, levels, anchor


@pytest.mark.slow(seconds=4)
def test_training_anchors_follow_the_samplers_law():
    """Train-time anchors and sample-time anchors (jdc_renoise of eq. 8's z) have one law: per
    element mean (1 - g) x and std g around it, independent of x; noise_eff is N(0, 1)."""
    a1, gs = 0.1, [0.2, 0.5, 0.9]
    x, noise, levels, anchor = _anchor_case(gs)
    x_t, eps = flow.jdc_training_anchors(jax.random.PRNGKey(5), x, noise, levels, anchor, a1)
    k_n1, k_r = jax.random.split(jax.random.PRNGKey(6))
    z = (1 - a1) * x + a1 * jax.random.normal(k_n1, x.shape)  # eq. 8
    sampled = flow.jdc_renoise(k_r, z[:, 1], jnp.asarray(gs), a1)  # what the sampler does
    n = x[0, 1].size
    se_mean, se_std = 4 / np.sqrt(n), 4 / np.sqrt(2 * n)  # 4 Monte-Carlo standard errors
    for b, g in enumerate(gs):
        xa = x[b, 1]
        for got in (x_t[b, 1], sampled[b]):
            residual = got - (1 - g) * xa
            assert float(jnp.mean(residual)) == pytest.approx(0.0, abs=g * se_mean)
            assert float(jnp.std(residual)) == pytest.approx(g, abs=g * se_std)
            # independent of x: the regression of the residual on x has slope 0
            assert float(jnp.sum(residual * xa) / jnp.sum(xa * xa)) == pytest.approx(0.0, abs=g * se_mean)
        e = eps[b, 1]
        assert float(jnp.mean(e)) == pytest.approx(0.0, abs=se_mean)
        assert float(jnp.std(e)) == pytest.approx(1.0, abs=se_std)
        # eps is the flow noise of x_t: x_t = add_noise(x, eps, g)
        np.testing.assert_allclose(x_t[b, 1], (1 - g) * xa + g * e, atol=1e-5)
        # and it is not the step's noise (the anchor carries eq. 8's prediction error)
        assert float(jnp.mean(jnp.square(e - noise[b, 1]))) > 0.01
    # frame 0 is no anchor: untouched, bit for bit
    np.testing.assert_array_equal(x_t[:, 0], flow.add_noise(x, noise, levels)[:, 0])
    np.testing.assert_array_equal(eps[:, 0], noise[:, 0])


def test_training_anchors_worked_cases():
    x, noise, levels, anchor = _anchor_case([0.05, 0.1, 0.6], shape=(3, 2, 2, 4, 8, 3))
    plain = flow.add_noise(x, noise, levels)
    # no anchors: add_noise and the noise itself, exactly
    x_t, eps = flow.jdc_training_anchors(jax.random.PRNGKey(0), x, noise, levels, jnp.zeros_like(anchor), 0.1)
    np.testing.assert_array_equal(x_t, plain)
    np.testing.assert_array_equal(eps, noise)
    x_t, eps = flow.jdc_training_anchors(jax.random.PRNGKey(0), x, noise, levels, anchor, 0.1)
    # g = 0.05 < alpha1: the plain flow-path point; g = alpha1: eq. 8's z itself, not the step's noise
    np.testing.assert_array_equal(x_t[0], plain[0])
    np.testing.assert_array_equal(eps[0], noise[0])
    assert not np.allclose(x_t[1, :, 1], plain[1, :, 1])
    np.testing.assert_allclose(
        x_t[1:, :, 1],
        (1 - levels[1:, 1, None, None, None, None]) * x[1:, :, 1]
        + levels[1:, 1, None, None, None, None] * eps[1:, :, 1],
        atol=1e-5,
    )


def test_training_anchor_targets_for_velocity_and_data_prediction():
    """A perfect network gets zero loss on anchors either way: its velocity (x_t - x) / g and the
    data predictor's converted output equal the target noise_eff - x."""
    x, noise, levels, anchor = _anchor_case([0.3, 0.6, 0.9], shape=(3, 2, 2, 4, 8, 3))
    x_t, eps = flow.jdc_training_anchors(jax.random.PRNGKey(2), x, noise, levels, anchor, 0.1)
    v_data = flow.velocity_from_output(x, x_t, levels, "data", 0.05)
    cond = jnp.zeros_like(anchor)
    assert float(flow.flow_loss(v_data, x, eps, cond_mask=cond)) == pytest.approx(0.0, abs=1e-9)
    # the anchors count in eq. 15: the old noise as target leaves an error on them only
    wrong = flow.per_frame_flow_loss(v_data, x, noise)
    assert float(jnp.max(wrong[:, 0])) < 1e-9 and float(jnp.min(wrong[:, 1])) > 1e-3
    assert float(flow.flow_loss(v_data, x, noise, cond_mask=cond)) > 1e-3


def test_training_anchors_jit_and_bad_inputs():
    x, noise, levels, anchor = _anchor_case([0.3, 0.6, 0.9], shape=(3, 2, 2, 4, 8, 3))
    out = jax.jit(flow.jdc_training_anchors)(jax.random.PRNGKey(0), x, noise, levels, anchor, 0.1)
    ref = flow.jdc_training_anchors(jax.random.PRNGKey(0), x, noise, levels, anchor, 0.1)
    np.testing.assert_allclose(out[0], ref[0], atol=1e-6)
    with pytest.raises(ValueError, match=r"anchor_mask: expected shape \[3, 2\]"):
        flow.jdc_training_anchors(jax.random.PRNGKey(0), x, noise, levels, anchor[:, :1], 0.1)
    with pytest.raises(ValueError, match=r"levels: expected shape \[B, F\]"):
        flow.jdc_training_anchors(jax.random.PRNGKey(0), x, noise, levels[:, 0], anchor, 0.1)
    with pytest.raises(ValueError, match="alpha1: expected values in"):
        flow.jdc_training_anchors(jax.random.PRNGKey(0), x, noise, levels, anchor, 1.0)
    with pytest.raises(ValueError, match="noise: expected the shape of x"):
        flow.jdc_training_anchors(jax.random.PRNGKey(0), x, noise[:1], levels, anchor, 0.1)
