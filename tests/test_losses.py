import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jaxdrive import flow

SHAPE = (2, 4, 8, 8, 3)


def _data(seed=0, shape=SHAPE):
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(seed), 3)
    return jax.random.normal(k1, shape), jax.random.normal(k2, shape), jax.random.normal(k3, shape)


def test_flow_loss_worked_number_and_zero_at_target():
    x, n, _ = _data()
    target = flow.velocity_target(x, n)
    assert float(flow.flow_loss(target, x, n)) == 0.0
    assert float(flow.flow_loss(target + 0.5, x, n)) == pytest.approx(0.25)


def test_condition_frames_are_excluded_and_do_not_dilute():
    x, n, junk = _data()
    target = flow.velocity_target(x, n)
    cond = jnp.array([[True, False, False, False], [True, True, False, False]])
    v = jnp.where(flow.expand_per_frame(cond, x), junk * 100, target + 0.5)
    # condition frames carry garbage that must not count; the rest err by 0.5 everywhere
    assert float(flow.flow_loss(v, x, n, cond_mask=cond)) == pytest.approx(0.25)
    g = jax.grad(lambda v: flow.flow_loss(v, x, n, cond_mask=cond))(v)
    np.testing.assert_array_equal(g[0, 0], 0.0)
    np.testing.assert_array_equal(g[1, :2], 0.0)
    assert float(jnp.abs(g[0, 1]).min()) > 0


def test_frame_weight_and_weight_map():
    x, n, _ = _data()
    target = flow.velocity_target(x, n)
    v = target + 1.0
    fw = jnp.array([[1.0, 2.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]])
    # one frame of eight counts twice: (7 + 2) / 8
    assert float(flow.flow_loss(v, x, n, frame_weight=fw)) == pytest.approx(9 / 8)
    wmap = jnp.ones(SHAPE[:-1]).at[:, :, :4].set(3.0).at[:, :, 4:].set(1.0)
    assert float(flow.flow_loss(v, x, n, weight_map=wmap)) == pytest.approx(2.0)


def test_multiview_layout():
    x, n, _ = _data(shape=(2, 6, 3, 4, 4, 2))
    cond = jnp.array([[True, False, False], [False, False, False]])
    v = flow.velocity_target(x, n) + jnp.arange(3.0).reshape(1, 1, 3, 1, 1, 1)
    # sample 0: frames 1, 2 err by 1, 2; sample 1: frames 0, 1, 2 err by 0, 1, 2 -> (1+4+0+1+4) / 5
    assert float(flow.flow_loss(v, x, n, cond_mask=cond)) == pytest.approx(2.0)
    per = flow.per_frame_flow_loss(v, x, n)
    np.testing.assert_allclose(per, [[0, 1, 4], [0, 1, 4]], atol=1e-6)


def test_high_pass_removes_smooth_content_and_keeps_checkerboard():
    h = w = 8
    const = jnp.ones((1, h, w, 1)) * 3.0
    np.testing.assert_allclose(flow.high_pass(const, 0.0), 0.0, atol=1e-6)
    checker = ((jnp.arange(h)[:, None] + jnp.arange(w)[None, :]) % 2 * 2.0 - 1.0)[None, :, :, None]
    np.testing.assert_allclose(flow.high_pass(checker, 0.9), checker, atol=1e-5)
    slow = jnp.cos(2 * jnp.pi * jnp.arange(h) / h)[None, :, None, None] * jnp.ones((1, h, w, 1))
    np.testing.assert_allclose(flow.high_pass(slow, 0.5), 0.0, atol=1e-5)  # radial freq 0.25 < 0.5


@pytest.mark.slow(seconds=5)
@given(st.floats(0.0, 1.0), st.integers(0, 1000))
def test_structure_loss_is_parseval_energy_of_the_masked_spectrum(cutoff, seed):
    x, _, y = _data(seed, shape=(1, 2, 6, 10, 2))
    loss = flow.structure_loss(y, x, cutoff=cutoff)
    spec = jnp.fft.fft2(y - x, axes=(-3, -2))
    mask = flow.high_pass_mask(6, 10, cutoff)[:, :, None]
    energy = jnp.sum(jnp.abs(spec) ** 2 * mask) / (6 * 10)
    assert float(loss) == pytest.approx(float(energy) / y.size, rel=1e-4, abs=1e-7)


def test_structure_loss_ignores_low_frequency_errors_and_conditions():
    x, _, y = _data()
    low = jnp.ones_like(x) * 0.7  # a pure DC offset
    assert float(flow.structure_loss(x + low, x)) == pytest.approx(0.0, abs=1e-10)
    cond = jnp.array([[False, True, True, True], [False, True, True, True]])
    y = x.at[:, 1:].set(y[:, 1:])  # errors only on condition frames
    assert float(flow.structure_loss(y, x, cond_mask=cond)) == 0.0


def test_bad_inputs():
    x, n, _ = _data()
    with pytest.raises(ValueError, match=r"cond_mask: expected shape \[2, 4\], got \[2, 3\]"):
        flow.flow_loss(x, x, n, cond_mask=jnp.zeros((2, 3), bool))
    with pytest.raises(ValueError, match=r"weight_map: expected shape \[2, 4, 8, 8\]"):
        flow.flow_loss(x, x, n, weight_map=jnp.ones((2, 4, 8)))
    with pytest.raises(ValueError, match="v_pred: expected the shape of x"):
        flow.flow_loss(x[:1], x, n)
    with pytest.raises(ValueError, match=r"cutoff: expected values in \[0.0, 1.0\]"):
        flow.structure_loss(x, x, cutoff=1.5)
    with pytest.raises(ValueError, match=r"x: expected shape \[B, ..., F, h, w, C\]"):
        flow.flow_loss(x[0], x[0], n[0])


def test_structure_loss_worked_number():
    # an error that is the finest checkerboard of amplitude 0.3 passes any cutoff < 1: loss 0.09
    h = w = 8
    checker = ((jnp.arange(h)[:, None] + jnp.arange(w)[None, :]) % 2 * 2.0 - 1.0)[None, None, :, :, None]
    x = jnp.zeros((1, 1, h, w, 1))
    assert float(flow.structure_loss(x + 0.3 * checker, x, cutoff=0.9)) == pytest.approx(0.09, rel=1e-5)


@given(st.lists(st.booleans(), min_size=8, max_size=8), st.integers(0, 1000))
def test_flow_loss_is_the_mean_over_non_condition_frames(mask_bits, seed):
    x, n, v = _data(seed)
    cond = jnp.array(mask_bits).reshape(2, 4)
    err = np.asarray((v - (n - x)) ** 2)
    keep = ~np.asarray(cond)
    want = err[keep].mean() if keep.any() else 0.0
    assert float(flow.flow_loss(v, x, n, cond_mask=cond)) == pytest.approx(want, rel=1e-5, abs=1e-7)


def test_high_pass_is_the_fft_high_pass_and_runs_sharded():
    """The DFT-by-matrices high-pass equals NumPy's FFT one, and its loss and gradient inside a
    sharded program (where XLA's CPU FFT failed on its input layout) equal the unsharded ones."""
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxdrive.flow.losses import high_pass, high_pass_mask, structure_loss

    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 2, 3, 8, 14, 4)).astype(np.float32)
    y = rng.normal(size=x.shape).astype(np.float32)
    mask = high_pass_mask(8, 14, 0.25)[:, :, None]
    want = np.real(np.fft.ifft2(np.fft.fft2(x, axes=(-3, -2)) * mask, axes=(-3, -2)))
    np.testing.assert_allclose(np.asarray(high_pass(x)), want, atol=2e-5)
    fn = jax.value_and_grad(lambda a, b: structure_loss(2.0 * a, b))
    ref_v, ref_g = jax.jit(fn)(x, y)
    mesh = jax.make_mesh((2, 4), ("data", "seq"), axis_types=(AxisType.Explicit,) * 2)
    put = lambda a: jax.device_put(a, NamedSharding(mesh, P("data")))
    with jax.set_mesh(mesh):
        v, g = jax.jit(fn)(put(x), put(y))
    np.testing.assert_allclose(float(v), float(ref_v), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(g), np.asarray(ref_g), atol=1e-6)
