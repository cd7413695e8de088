import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive import flow

SHAPE = (2, 4, 3, 3, 2)  # [B, F, h, w, C]


def _point_and_noise(seed=0):
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    return jax.random.normal(k1, SHAPE), jax.random.normal(k2, SHAPE)


def exact_velocity(x0):
    """The flow of a distribution concentrated on x0: v = (x_t - x0) / sigma."""

    def v(x, sigma, cond):
        return (x - x0) / flow.expand_per_frame(sigma, x)

    return v


@pytest.mark.parametrize("method", ["euler", "heun"])
@pytest.mark.parametrize("steps", [1, 7])
def test_lands_on_the_single_data_point(method, steps):
    x0, noise = _point_and_noise()
    out = flow.sample(exact_velocity(x0), noise, flow.sampling_sigmas(steps, shift=2.0), method=method)
    np.testing.assert_allclose(out, x0, atol=1e-5)


@pytest.mark.slow(seconds=6)
@pytest.mark.parametrize("method", ["euler", "heun"])
def test_per_frame_tpd_schedule_with_conditions(method):
    x0, noise = _point_and_noise(1)
    cond = jnp.array([[True, False, False, False], [True, True, False, False]])
    start = jnp.where(flow.expand_per_frame(cond, noise), x0 + 3.0, noise)  # clean frames differ from x0
    sched = flow.frame_schedule(flow.sampling_sigmas(6), cond, tpd=True)
    out, traj = flow.sample(exact_velocity(x0), start, sched, cond_mask=cond, method=method, return_trajectory=True)
    assert traj.shape == (6,) + SHAPE
    np.testing.assert_array_equal(out[0, 0], start[0, 0])  # bit-identical condition frames
    np.testing.assert_array_equal(out[1, :2], start[1, :2])
    np.testing.assert_array_equal(traj[:, 0, 0], jnp.broadcast_to(start[0, 0], traj[:, 0, 0].shape))
    np.testing.assert_allclose(out[0, 1:], x0[0, 1:], atol=1e-5)
    np.testing.assert_allclose(out[1, 2:], x0[1, 2:], atol=1e-5)


@pytest.mark.parametrize("method", ["euler", "heun"])
def test_condition_frames_bit_identical_even_if_the_model_returns_nan_there(method):
    x0, noise = _point_and_noise(2)
    cond = jnp.array([[True, False, False, False]] * 2)

    def v(x, sigma, c):
        # a model that mixes frames: a NaN kept on a condition frame would spread to the others
        mixed = x - x0 + 0.1 * jnp.mean(x, axis=1, keepdims=True)
        return jnp.where(flow.expand_per_frame(cond, x), jnp.nan, mixed)

    out = flow.sample(v, noise, flow.sampling_sigmas(3), cond_mask=cond, method=method)
    np.testing.assert_array_equal(out[:, 0], noise[:, 0])
    assert bool(jnp.all(jnp.isfinite(out)))


def _linear_model(x, sigma, cond):
    """A toy conditional model: v depends on each condition differently."""
    s = flow.expand_per_frame(sigma, x)
    text = cond["text"][:, None, None, None, None]
    traj = cond["traj"][:, None, None, None, None]
    return 0.3 * x * (1 + s) + text + 2.0 * traj * x


def _conds():
    cond = {"text": jnp.array([1.0, -2.0]), "traj": jnp.array([0.5, 0.25])}
    null = {"text": jnp.zeros(2), "traj": jnp.zeros(2)}
    return cond, null


def _counted(fn):
    """``fn`` and the list of the batch sizes it is called with."""
    calls = []

    def model(x, s, c):
        calls.append(x.shape[0])
        return fn(x, s, c)

    return model, calls


def test_cfg_scale_one_equals_the_conditional_output_exactly():
    _, noise = _point_and_noise()
    cond, null = _conds()
    sig = flow.sampling_sigmas(4)
    plain = flow.sample(_linear_model, noise, sig, cond=cond)
    guided = flow.sample(_linear_model, noise, sig, cond=cond, null_cond=null, guidance_scale=1.0)
    np.testing.assert_array_equal(guided, plain)
    # a traced scale of 1 runs the batched path: equal up to float rounding
    traced = jax.jit(lambda s: flow.sample(_linear_model, noise, sig, cond=cond, null_cond=null, guidance_scale=s))(
        jnp.float32(1.0)
    )
    np.testing.assert_allclose(traced, plain, rtol=1e-6, atol=1e-6)
    other = flow.sample(_linear_model, noise, sig, cond=cond, null_cond=null, guidance_scale=3.0)
    assert float(jnp.abs(other - plain).max()) > 1e-3


def test_guidance_combines_as_documented_in_one_batched_call():
    _, noise = _point_and_noise()
    cond, null = _conds()
    sigma = jnp.array([0.7, 0.7])
    model, calls = _counted(_linear_model)

    scales = {"text": 2.0, "traj": 4.0}
    one_step = flow.sample(model, noise, jnp.array([0.7, 0.2]), cond=cond, null_cond=null, guidance_scale=scales)
    assert calls == [3 * SHAPE[0]]  # null, text-only, traj-only stacked in one call
    v_null = _linear_model(noise, sigma, {"text": null["text"], "traj": null["traj"]})
    v_text = _linear_model(noise, sigma, {"text": cond["text"], "traj": null["traj"]})
    v_traj = _linear_model(noise, sigma, {"text": null["text"], "traj": cond["traj"]})
    v = v_null + 2.0 * (v_text - v_null) + 4.0 * (v_traj - v_null)
    np.testing.assert_allclose(one_step, noise - 0.5 * v, rtol=1e-5, atol=1e-5)

    calls.clear()
    joint = flow.sample(model, noise, jnp.array([0.7, 0.2]), cond=cond, null_cond=null, guidance_scale=5.0)
    assert calls == [2 * SHAPE[0]]
    v_c, v_n = _linear_model(noise, sigma, cond), v_null
    np.testing.assert_allclose(joint, noise - 0.5 * (v_n + 5.0 * (v_c - v_n)), rtol=1e-5, atol=1e-5)


def test_unnamed_conditions_are_never_nulled():
    _, noise = _point_and_noise()
    cond, null = _conds()
    seen = []

    def model(x, s, c):
        seen.append(c["traj"])
        return _linear_model(x, s, c)

    flow.sample(model, noise, jnp.array([0.5, 0.0]), cond=cond, null_cond=null, guidance_scale={"text": 2.0})
    # variants are interleaved sample-major: [b0 null, b0 text, b1 null, b1 text]
    np.testing.assert_array_equal(seen[0], jnp.repeat(cond["traj"], 2))


def _coupled_model(x, sigma, cond):
    """A toy model whose conditions interact (text x traj): composition is not additive."""
    s = flow.expand_per_frame(sigma, x)
    text = cond["text"][:, None, None, None, None]
    traj = cond["traj"][:, None, None, None, None]
    return 0.3 * x * (1 + s) + text * traj + jnp.tanh(text + traj * x)


def _without(cond, null, name):
    return {k: (null[k] if k == name else v) for k, v in cond.items()}


@pytest.mark.parametrize("scale", [1.0, 3.0])
def test_control_guidance_with_every_scale_equal_to_the_plain_one_is_plain_guidance(scale):
    _, noise = _point_and_noise()
    cond, null = _conds()
    sig = flow.sampling_sigmas(4)
    plain = flow.sample(_coupled_model, noise, sig, cond=cond, null_cond=null, guidance_scale=scale)
    controls = {k: (scale, _without(cond, null, k)) for k in ("text", "traj")}
    composed = flow.sample(
        _coupled_model, noise, sig, cond=cond, null_cond=null, guidance_scale=scale, control_guidance=controls
    )
    np.testing.assert_allclose(composed, plain, rtol=1e-6, atol=1e-6)
    # another scale for one control moves the samples: the extra forwards are used
    controls["traj"] = (scale + 2.0, controls["traj"][1])
    other = flow.sample(
        _coupled_model, noise, sig, cond=cond, null_cond=null, guidance_scale=scale, control_guidance=controls
    )
    assert float(jnp.abs(other - plain).max()) > 1e-3


def test_control_guidance_combines_as_documented_with_one_forward_more_per_control():
    _, noise = _point_and_noise()
    cond, null = _conds()
    sigma = jnp.array([0.7, 0.7])
    model, calls = _counted(_coupled_model)
    controls = {"traj": (5.0, _without(cond, null, "traj"))}
    one_step = flow.sample(
        model, noise, jnp.array([0.7, 0.2]), cond=cond, null_cond=null, guidance_scale=2.0, control_guidance=controls
    )
    assert calls == [3 * SHAPE[0]]  # cond, null, cond without traj: one batched call
    v_c, v_null = _coupled_model(noise, sigma, cond), _coupled_model(noise, sigma, null)
    v_no_traj = _coupled_model(noise, sigma, controls["traj"][1])
    v = v_null + 2.0 * (v_c - v_null) + (5.0 - 2.0) * (v_c - v_no_traj)
    np.testing.assert_allclose(one_step, noise - 0.5 * v, rtol=1e-5, atol=1e-5)
    calls.clear()  # plain scale 1: no null forward
    one_step = flow.sample(
        model, noise, jnp.array([0.7, 0.2]), cond=cond, null_cond=null, guidance_scale=1.0, control_guidance=controls
    )
    assert calls == [2 * SHAPE[0]]
    np.testing.assert_allclose(one_step, noise - 0.5 * (v_c + 4.0 * (v_c - v_no_traj)), rtol=1e-5, atol=1e-5)


def test_compiles_once_for_a_shape_and_step_count():
    x0, noise = _point_and_noise()
    traces = []

    def v(x, sigma, cond):
        traces.append(1)
        return (x - x0) / flow.expand_per_frame(sigma, x)

    run = jax.jit(functools.partial(flow.sample, v, method="heun"))
    a = run(noise, flow.sampling_sigmas(8))
    n_traces = len(traces)
    b = run(noise * 2.0, flow.sampling_sigmas(8, shift=3.0))  # new values, same shapes
    assert len(traces) == n_traces
    np.testing.assert_allclose(a, x0, atol=1e-5)
    np.testing.assert_allclose(b, x0, atol=1e-5)
    run(noise, flow.sampling_sigmas(9))  # another step count is another program
    assert len(traces) > n_traces


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(method="dpm"), "method: expected one of"),
        (dict(sigmas=jnp.array([0.0, 0.5, 1.0])), "sigmas: expected a non-increasing schedule"),
        (dict(sigmas=jnp.array([1.5, 0.0])), r"sigmas: expected values in \[0, 1\]"),
        (dict(sigmas=jnp.array([1.0])), "sigmas: expected at least 2 levels"),
        (dict(sigmas=jnp.ones((3, 2, 5))), r"sigmas: expected shape \[\*, 2, 4\], got \[3, 2, 5\]"),
        (dict(cond_mask=jnp.zeros((2, 3), bool)), r"cond_mask: expected shape \[2, 4\], got \[2, 3\]"),
        (dict(guidance_scale=2.0, cond={"text": jnp.ones(2)}), "null_cond: expected the null conditions"),
        (
            dict(guidance_scale={"map": 2.0}, cond={"text": jnp.ones(2)}, null_cond={"text": jnp.zeros(2)}),
            r"guidance_scale: expected names present in cond and null_cond \(\['text'\]\), got unknown \['map'\]",
        ),
        (
            dict(guidance_scale=-2.0, cond={"text": jnp.ones(2)}, null_cond={"text": jnp.zeros(2)}),
            r"guidance_scale: expected values in \[0.0, inf\), got -2",
        ),
        (
            dict(guidance_scale={"text": -1.0}, cond={"text": jnp.ones(2)}, null_cond={"text": jnp.zeros(2)}),
            r"guidance_scale\['text'\]: expected values in \[0.0, inf\), got -1",
        ),
        (
            dict(
                guidance_scale=2.0,
                cond={"text": jnp.ones(2)},
                null_cond={"text": jnp.zeros(2)},
                control_guidance={"text": (-3.0, {"text": jnp.zeros(2)})},
            ),
            r"control_guidance\['text'\]: expected values in \[0.0, inf\), got -3",
        ),
        (
            dict(
                guidance_scale=2.0, cond={"text": jnp.ones(2)}, control_guidance={"text": (3.0, {"text": jnp.zeros(2)})}
            ),
            "null_cond: expected the null conditions",
        ),
    ],
)
def test_bad_inputs(kwargs, match):
    _, noise = _point_and_noise()
    args = dict(sigmas=flow.sampling_sigmas(2))
    args.update(kwargs)
    sigmas = args.pop("sigmas")
    with pytest.raises(ValueError, match=match):
        flow.sample(lambda x, s, c: x, noise, sigmas, **args)
