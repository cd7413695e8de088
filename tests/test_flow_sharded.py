"""The flow math on batch-sharded arrays (explicit mesh, 8 devices) equals the single-device
result, forward and gradients."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive import flow

B = 8


@pytest.fixture(scope="module")
def mesh():
    return jax.make_mesh((4, 2), ("data", "fsdp"), axis_types=(AxisType.Explicit,) * 2)


def _inputs():
    ks = jax.random.split(jax.random.PRNGKey(0), 3)
    x = jax.random.normal(ks[0], (B, 2, 5, 4, 6, 2))  # [B, V, F, h, w, C]
    noise = jax.random.normal(ks[1], x.shape)
    sigma = flow.sample_sigmas(ks[2], (B,))
    cond = jnp.zeros((B, 5), bool).at[:, 0].set(True)
    anchor = jnp.zeros((B, 5), bool).at[:, -1].set(True)
    return x, noise, sigma, cond, anchor


def _loss(x, noise, sigma, cond, anchor):
    s = flow.frame_sigmas(sigma, cond, anchor_mask=anchor, tpd=True)
    x_t = flow.add_noise(x, noise, s)
    v = 0.5 * x_t  # a stand-in network
    x_cond = flow.degrade_frames(x, cond, 0.5)
    return flow.flow_loss(v + x_cond, x, noise, cond_mask=cond) + flow.structure_loss(
        flow.data_from_velocity(x_t, v, s), x, cond_mask=cond
    )


def _put(mesh, tree):
    spec = NamedSharding(mesh, P(("data", "fsdp")))
    return jax.tree_util.tree_map(lambda a: jax.device_put(a, spec), tree)


def test_losses_and_gradients_match_single_device(mesh):
    args = _inputs()
    ref = jax.jit(jax.value_and_grad(_loss))(*args)
    with jax.set_mesh(mesh):
        out = jax.jit(jax.value_and_grad(_loss))(*_put(mesh, args))
    np.testing.assert_allclose(out[0], ref[0], rtol=1e-5)
    np.testing.assert_allclose(out[1], ref[1], rtol=1e-5, atol=1e-6)


@pytest.mark.slow(seconds=3)
def test_sampler_and_segments_match_single_device(mesh):
    x, noise, _, cond, anchor = _inputs()

    def velocity(x_t, s, c):
        return 0.2 * x_t * (1 + flow.expand_per_frame(s, x_t)) + c["text"][:, None, None, None, None, None]

    sched = flow.frame_schedule(flow.sampling_sigmas(4), cond, anchor_mask=anchor, tpd=True)
    c, null = {"text": jnp.ones(B)}, {"text": jnp.zeros(B)}
    run = jax.jit(functools.partial(flow.sample, velocity, method="heun", guidance_scale=2.0))
    ref = run(noise, sched, cond=c, null_cond=null, cond_mask=cond)
    with jax.set_mesh(mesh):
        n_s, c_s, null_s, cm_s = _put(mesh, (noise, c, null, cond))
        out = run(n_s, sched, cond=c_s, null_cond=null_s, cond_mask=cm_s)
        seg = jax.jit(lambda a: flow.coarse_from_segments(flow.split_segments(a, 3), B))(_put(mesh, x))
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(out[:, :, 0], noise[:, :, 0])
    np.testing.assert_array_equal(seg, flow.dense_to_coarse(x, 3))
