"""attention(): the dense reference, the blockwise kernel and the dispatcher's contract."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive.attention import attention

from dit_fixtures import max_rel


def _qkvd(b=2, lq=40, lk=40, h=3, d=8, seed=0):
    """q, k, v and an output cotangent, drawn with NumPy (eager jax.random compiles per shape)."""
    rng = np.random.default_rng(seed)
    return tuple(jnp.asarray(rng.standard_normal((b, n, h, d), np.float32)) for n in (lq, lk, lk, lq))


def test_reference_matches_jax_dot_product_attention():
    q, k, v, _ = _qkvd()
    np.testing.assert_allclose(
        attention(q, k, v, impl="xla"), jax.nn.dot_product_attention(q, k, v), rtol=1e-5, atol=1e-5
    )
    # causal_block = 1 is token-causal attention; one block spanning everything is no mask at all
    np.testing.assert_allclose(
        attention(q, k, v, impl="xla", causal_block=1),
        jax.nn.dot_product_attention(q, k, v, is_causal=True),
        rtol=1e-5,
        atol=1e-5,
    )
    np.testing.assert_allclose(
        attention(q, k, v, impl="xla", causal_block=40), attention(q, k, v, impl="xla"), rtol=1e-6, atol=1e-6
    )


def test_causal_block_worked_example():
    # 4 tokens, blocks of 2: tokens 0-1 see 0-1, tokens 2-3 see all four; v holds the positions
    q = jnp.zeros((1, 4, 1, 2))
    k = jnp.zeros((1, 4, 1, 2))
    v = jnp.arange(4.0).reshape(1, 4, 1, 1) * jnp.ones((1, 4, 1, 2))
    out = attention(q, k, v, impl="xla", causal_block=2)[0, :, 0, 0]
    np.testing.assert_allclose(out, [0.5, 0.5, 1.5, 1.5], atol=1e-6)  # uniform weights over allowed keys


LAYOUTS = [
    dict(lq=40, lk=40),
    dict(lq=40, lk=40, mask=True),
    dict(lq=40, lk=40, causal_block=5),
    dict(lq=37, lk=37, mask=True, causal_block=4),  # lengths that do not divide the blocks
    dict(lq=12, lk=50, mask=True),  # cross-attention (e.g. to text tokens)
]


@pytest.mark.parametrize("layout", LAYOUTS)
def test_blockwise_matches_dense_forward_and_gradients(layout):
    q, k, v, do = _qkvd(lq=layout["lq"], lk=layout["lk"])
    mask = None
    if layout.get("mask"):
        mask = jnp.ones((2, layout["lk"]), bool).at[1, layout["lk"] - 9 :].set(False)
    kw = dict(kv_mask=mask, causal_block=layout.get("causal_block"))
    ref_out, ref_vjp = jax.vjp(jax.jit(lambda *a: attention(*a, impl="xla", **kw)), q, k, v)
    run = jax.jit(lambda *a: attention(*a, impl="blockwise", block_q=16, block_k=8, **kw))
    out, vjp = jax.vjp(run, q, k, v)
    assert max_rel(out, ref_out) <= 1e-5
    for got, want in zip(vjp(do), ref_vjp(do)):
        assert max_rel(got, want) <= 1e-5


def test_fully_masked_rows_are_zero_not_nan():
    q, k, v, do = _qkvd(lq=8, lk=8)
    mask = jnp.zeros((2, 8), bool).at[0].set(True)  # sample 1 has no key at all
    for impl in ("xla", "blockwise"):
        out, vjp = jax.vjp(lambda *a: attention(*a, impl=impl, kv_mask=mask, block_q=4, block_k=4), q, k, v)
        np.testing.assert_array_equal(out[1], 0.0)
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in vjp(do))


def test_blockwise_memory_is_linear_in_length():
    # compiled temporary memory of forward + backward (deterministic, read from the program)
    def temp(impl, length):
        q = jax.ShapeDtypeStruct((1, length, 1, 16), jnp.float32)
        f = jax.jit(
            jax.grad(lambda q, k, v: attention(q, k, v, impl=impl, block_q=256, block_k=256).sum(), argnums=(0, 1, 2))
        )
        return f.lower(q, q, q).compile().memory_analysis().temp_size_in_bytes

    dense, blockwise = temp("xla", 4096), temp("blockwise", 4096)
    assert blockwise < 0.1 * dense, (blockwise, dense)


def test_auto_on_one_device_equals_xla_for_short_sequences():
    q, k, v, _ = _qkvd()
    np.testing.assert_array_equal(attention(q, k, v), attention(q, k, v, impl="xla"))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(impl="flash"), "impl: expected one of"),
        (dict(kv_mask=jnp.ones((2, 39), bool)), r"kv_mask: expected shape \[2, 40\] \(\[B, Lk\]\), got \[2, 39\]"),
        (dict(kv_mask=jnp.ones((2, 40))), "kv_mask: expected dtype bool, got float32"),
        (dict(causal_block=0), "causal_block: expected an integer >= 1, got 0"),
        (dict(impl="ring"), r"mesh: impl 'ring' needs a mesh with a 'seq' axis, got None"),
        (
            dict(impl="ulysses", mesh=jax.make_mesh((8,), ("data",))),
            r"mesh: impl 'ulysses' needs a mesh with a 'seq' axis, got \('data',\)",
        ),
        (dict(impl="cudnn"), "impl: 'cudnn' needs GPU devices"),
    ],
)
def test_bad_arguments(kwargs, match):
    q, k, v, _ = _qkvd()
    with pytest.raises(ValueError, match=match):
        attention(q, k, v, **kwargs)


def test_bad_shapes_and_dtypes():
    q, k, v, _ = _qkvd()
    with pytest.raises(ValueError, match=r"v: expected the shape of k"):
        attention(q, k, v[:, :5])
    with pytest.raises(ValueError, match=r"k: expected shape \[2, Lk, 3, 8\]"):
        attention(q, k[..., :4], v[..., :4])
    with pytest.raises(ValueError, match="k, v: expected the dtype of q"):
        attention(q, k.astype(jnp.bfloat16), v.astype(jnp.bfloat16))
    with pytest.raises(ValueError, match=r"q: expected shape \[B, L, H, D\]"):
        attention(q[0], k, v)
    with pytest.raises(ValueError, match="causal_block: needs self-attention"):
        attention(q[:, :10], k, v, causal_block=2)


def test_auto_shards_over_seq_and_never_fails_where_xla_works():
    from jax.sharding import AxisType

    q, k, v, _ = _qkvd(b=2, lq=32, lk=32, h=4)
    mesh = jax.make_mesh((1, 1, 8, 1), ("data", "fsdp", "seq", "tensor"), axis_types=(AxisType.Explicit,) * 4)
    ref = attention(q, k, v, impl="xla", causal_block=4)
    with jax.set_mesh(mesh):  # the context mesh is picked up
        out = jax.jit(lambda *a: attention(*a, causal_block=4))(q, k, v)
    assert max_rel(out, ref) <= 1e-5
    # 3 heads cannot be split over tensor = 2: auto falls back to one device instead of failing
    q3, k3, v3, _ = _qkvd(b=2, lq=16, lk=16, h=3)
    odd = jax.make_mesh((1, 1, 4, 2), ("data", "fsdp", "seq", "tensor"), axis_types=(AxisType.Explicit,) * 4)
    np.testing.assert_allclose(attention(q3, k3, v3, mesh=odd), attention(q3, k3, v3, impl="xla"), atol=1e-6)


@pytest.mark.slow(seconds=3)
def test_sharded_output_takes_the_input_sharding_so_any_use_differentiates():
    # slicing a size-1 head axis of the output once broke the shard_map transpose (cotangent typed
    # without the 'tensor' axis); the output now carries q's own sharding
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    mesh = jax.make_mesh((1, 1, 8, 1), ("data", "fsdp", "seq", "tensor"), axis_types=(AxisType.Explicit,) * 4)
    x = jax.random.normal(jax.random.PRNGKey(0), (2, 16, 8))

    def loss(x, impl, mesh=None):
        h = x[:, :, None, :]
        return jnp.sum(attention(h, h, h, impl=impl, mesh=mesh, causal_block=4)[:, :, 0] * jnp.cos(x))

    ref = jax.jit(jax.grad(loss), static_argnums=1)(x, "xla")  # one program, not op by op
    with jax.set_mesh(mesh):
        xs = jax.device_put(x, NamedSharding(mesh, P(None, "seq", None)))
        got = jax.jit(jax.grad(lambda x: loss(x, "ring", mesh)))(xs)
    assert max_rel(got, ref) <= 1e-5


@pytest.mark.slow(seconds=4)
@pytest.mark.parametrize("causal_block", [None, 7])
def test_ring_tiles_chunks_longer_than_its_block(causal_block):
    # chunks of 38 tokens with block = 16: padded to 4 x 48 and attended tile by tile
    from jax.sharding import AxisType

    from jaxdrive.attention.ring import ring_attention

    mesh = jax.make_mesh(
        (1, 1, 4, 1), ("data", "fsdp", "seq", "tensor"), axis_types=(AxisType.Explicit,) * 4, devices=jax.devices()[:4]
    )
    q, k, v, do = _qkvd(b=2, lq=150, lk=150, h=2)
    mask = jnp.ones((2, 150), bool).at[1, 120:].set(False)
    ref, ref_vjp = jax.vjp(
        jax.jit(lambda *a: attention(*a, impl="xla", kv_mask=mask, causal_block=causal_block)), q, k, v
    )
    run = jax.jit(
        lambda *a: ring_attention(*a, mesh=mesh, scale=8**-0.5, kv_mask=mask, causal_block=causal_block, block=16)
    )
    out, vjp = jax.vjp(run, q, k, v)
    assert max_rel(out, ref) <= 1e-5
    for got, want in zip(vjp(do), ref_vjp(do)):
        assert max_rel(got, want) <= 1e-5


@pytest.mark.slow(seconds=5)
@pytest.mark.parametrize("kw", [dict(), dict(mask=True), dict(causal_block=8), dict(mask=True, causal_block=8)])
def test_splash_kernel_matches_dense_in_the_pallas_interpreter(kw):
    # the TPU kernel itself, run by the Pallas interpreter on CPU: padded lengths, segment-id
    # masking, the block-causal mask computed in the kernel, its own backward kernels
    from jaxdrive.attention.splash import splash_attention

    q, k, v, do = _qkvd(b=2, lq=200, lk=200, h=2, d=64)
    mask = jnp.ones((2, 200), bool).at[1].set(False) if kw.get("mask") else None  # sample 1: no key
    causal_block = kw.get("causal_block")
    ref, ref_vjp = jax.vjp(
        jax.jit(lambda *a: attention(*a, impl="xla", kv_mask=mask, causal_block=causal_block)), q, k, v
    )
    out, vjp = jax.vjp(
        lambda *a: splash_attention(
            *a, scale=64**-0.5, kv_mask=mask, causal_block=causal_block, tile=128, interpret=True
        ),
        q,
        k,
        v,
    )
    assert max_rel(out, ref) <= 1e-5
    for got, want in zip(vjp(do), ref_vjp(do)):
        assert bool(jnp.all(jnp.isfinite(got))) and max_rel(got, want) <= 1e-5
    if mask is not None:
        np.testing.assert_array_equal(out[1], 0.0)


@pytest.mark.slow(seconds=10)
@pytest.mark.parametrize("causal_block", [None, 8])
def test_splash_runs_per_device_in_shard_map_on_a_sharded_mesh(causal_block):
    # a Mosaic kernel cannot be partitioned by XLA: on a mesh whose batch is sharded (data x fsdp)
    # and heads split (tensor) each device must call it on its own examples; the interpreter runs
    # the same code path on 8 fake CPU devices. Forward and gradients against dense attention,
    # the output typed like q
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxdrive.attention.splash import splash_attention

    mesh = jax.make_mesh((2, 2, 1, 2), ("data", "fsdp", "seq", "tensor"), axis_types=(AxisType.Explicit,) * 4)
    q, k, v, do = _qkvd(b=4, lq=136, lk=136, h=2, d=64)
    mask = jnp.ones((4, 136), bool).at[1, 100:].set(False)
    ref, ref_vjp = jax.vjp(
        jax.jit(lambda *a: attention(*a, impl="xla", kv_mask=mask, causal_block=causal_block)), q, k, v
    )
    spec = P(("data", "fsdp"), None, "tensor", None)
    with jax.set_mesh(mesh):
        put = lambda x, s=spec: jax.device_put(x, NamedSharding(mesh, s))
        sq, sk, sv, sdo = map(put, (q, k, v, do))
        smask = put(mask, P(("data", "fsdp"), None))
        run = jax.jit(
            lambda *a: splash_attention(
                *a, scale=64**-0.5, kv_mask=smask, causal_block=causal_block, tile=128, interpret=True
            )
        )
        out, vjp = jax.vjp(run, sq, sk, sv)
        grads = vjp(sdo)
    assert out.sharding.spec == spec
    assert max_rel(out, ref) <= 1e-5
    for got, want in zip(grads, ref_vjp(do)):
        assert max_rel(got, want) <= 1e-5


def test_splash_keeps_a_seq_sharded_query_sharded_without_a_causal_mask():
    # a text cross-attention: the video queries sharded over `seq`, a few keys whole on every
    # device. Each device runs its own query rows against all keys (nothing of q is gathered);
    # forward and gradients against dense attention, the shard_map's q typed over seq
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxdrive.attention.splash import splash_attention

    mesh = jax.make_mesh((1, 2, 2, 2), ("data", "fsdp", "seq", "tensor"), axis_types=(AxisType.Explicit,) * 4)
    q, _, _, do = _qkvd(b=2, lq=136, lk=136, h=2, d=64)
    _, k, v, _ = _qkvd(b=2, lq=40, lk=40, h=2, d=64, seed=3)
    mask = jnp.ones((2, 40), bool).at[1, 30:].set(False)
    ref, ref_vjp = jax.vjp(jax.jit(lambda *a: attention(*a, impl="xla", kv_mask=mask)), q, k, v)
    q_spec, kv_spec = P(("data", "fsdp"), "seq", "tensor", None), P(("data", "fsdp"), None, "tensor", None)
    with jax.set_mesh(mesh):
        put = lambda x, s: jax.device_put(x, NamedSharding(mesh, s))
        sq, sdo, sk, sv = put(q, q_spec), put(do, q_spec), put(k, kv_spec), put(v, kv_spec)
        smask = put(mask, P(("data", "fsdp"), None))
        run = lambda *a: splash_attention(*a, scale=64**-0.5, kv_mask=smask, tile=128, interpret=True)
        out, vjp = jax.vjp(jax.jit(run), sq, sk, sv)
        grads = vjp(sdo)
        eqns = [e for e in jax.make_jaxpr(run)(sq, sk, sv).eqns if e.primitive.name == "shard_map"]
    assert len(eqns) == 1
    in_q, in_k, in_v, _ = eqns[0].params["in_specs"][-4:]  # after the kernel's closed-over constants
    assert (in_q, in_k, in_v) == (q_spec, kv_spec, kv_spec)
    assert out.sharding.spec == q_spec
    assert max_rel(out, ref) <= 1e-5
    for got, want in zip(grads, ref_vjp(do)):
        assert max_rel(got, want) <= 1e-5


@pytest.mark.slow(seconds=5)
def test_splash_on_a_one_device_mesh_with_explicit_axes():
    # one chip (a v5e-1, or the bench's one-chip step): the batch is typed over data x fsdp of
    # size 1, and the kernel's vmap refused the mask's unsharded segment ids beside it
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxdrive.attention.splash import splash_attention

    names = ("data", "fsdp", "seq", "tensor")
    mesh = jax.make_mesh((1, 1, 1, 1), names, axis_types=(AxisType.Explicit,) * 4, devices=jax.devices()[:1])
    q, k, v, _ = _qkvd(b=2, lq=72, lk=72, h=2, d=64)
    ref = attention(q, k, v, impl="xla")
    with jax.set_mesh(mesh):
        put = lambda x: jax.device_put(x, NamedSharding(mesh, P(("data", "fsdp"))))
        run = jax.jit(lambda *a: splash_attention(*a, scale=64**-0.5, tile=128, interpret=True))
        out = run(*map(put, (q, k, v)))
    assert max_rel(out, ref) <= 1e-5


def test_auto_asks_the_mesh_devices_not_the_backend():
    # a TPU step compiled ahead of time on a CPU host: "auto" must see the mesh's TPUs
    from jaxdrive.attention import dispatch
    from jaxdrive.parallel.mesh import mesh_platform

    mesh = jax.make_mesh((1, 1, 1, 1), ("data", "fsdp", "seq", "tensor"), devices=jax.devices()[:1])
    tpu = mesh.abstract_mesh.update(abstract_device=jax.sharding.AbstractDevice("TPU v5e", 1, "tpu"))
    assert mesh_platform(mesh) == "cpu" and mesh_platform(tpu) == "tpu"
    q, k, v, _ = _qkvd()
    assert dispatch._auto(q, k, v, tpu, None, None) == "splash"
    assert dispatch._auto(q, k, v, mesh.abstract_mesh, None, None) == "xla"


def test_splash_needs_a_tpu():
    q, k, v, _ = _qkvd()
    with pytest.raises(ValueError, match="impl: 'splash' needs TPU devices .the mesh.s, else the backend.s., got cpu"):
        attention(q, k, v, impl="splash")


def test_auto_picks_ring_under_the_context_mesh():
    # under jax.set_mesh the mesh is an AbstractMesh (no devices): ring's layout check must read
    # its axis sizes from it, else "auto" silently fell back to one-device attention
    from jax.sharding import AxisType

    q, k, v, _ = _qkvd(b=2, lq=32, lk=32, h=4)
    mesh = jax.make_mesh((1, 1, 8, 1), ("data", "fsdp", "seq", "tensor"), axis_types=(AxisType.Explicit,) * 4)
    with jax.set_mesh(mesh):
        jaxpr = str(jax.make_jaxpr(lambda *a: attention(*a))(q, k, v))
    assert "ppermute" in jaxpr


def test_one_device_kernels_take_sequence_sharded_inputs():
    # q, k, v sharded over seq (a DiT's activations, also on a seq axis of size 1): xla gathers K/V,
    # blockwise gathers all three, and the output keeps q's sharding instead of an illegal sharding
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    q, k, v, _ = _qkvd(b=2, lq=32, lk=32, h=4)
    ref = attention(q, k, v, impl="xla", causal_block=8)
    for shape in ((1, 1, 8, 1), (8, 1, 1, 1)):
        mesh = jax.make_mesh(shape, ("data", "fsdp", "seq", "tensor"), axis_types=(AxisType.Explicit,) * 4)
        for impl in ("xla", "blockwise"):
            with jax.set_mesh(mesh):
                put = lambda x: jax.device_put(x, NamedSharding(mesh, P(None, "seq", None, None)))
                fn = lambda *a: attention(*a, impl=impl, causal_block=8, block_q=8, block_k=8)
                out = jax.jit(fn)(put(q), put(k), put(v))
                assert out.sharding.spec == P(None, "seq", None, None)
            assert max_rel(out, ref) <= 1e-5


@pytest.mark.slow(seconds=5)
@pytest.mark.parametrize("impl", ["ring", "ulysses", "auto"])
def test_a_mesh_given_outside_its_context_asks_to_enter_it(impl):
    # outside jax.set_mesh the sharded output's type names a mesh that later ops cannot place:
    # the forward ran, and jax.grad failed in JAX with a bare error about device assignment
    from jax.sharding import AxisType

    q, k, v, _ = _qkvd(b=2, lq=32, lk=32, h=4)
    names = ("data", "fsdp", "seq", "tensor")
    mesh = jax.make_mesh((1, 1, 4, 1), names, axis_types=(AxisType.Explicit,) * 4, devices=jax.devices()[:4])
    other = jax.make_mesh((2, 1, 2, 1), names, axis_types=(AxisType.Explicit,) * 4, devices=jax.devices()[:4])
    loss = lambda q: jnp.sum(jnp.sin(attention(q, k, v, impl=impl, mesh=mesh, causal_block=8)))
    enter = (
        r"^mesh: impl '(ring|ulysses)' runs on the mesh it is given only inside it: call attention within "
        r"`with jax.set_mesh\(mesh\):`"
    )
    with pytest.raises(ValueError, match=enter):
        attention(q, k, v, impl=impl, mesh=mesh, causal_block=8)
    with pytest.raises(ValueError, match=enter):
        jax.grad(loss)(q)
    with jax.set_mesh(other), pytest.raises(ValueError, match=enter):  # another mesh's context
        jax.grad(loss)(q)
    ref = jax.jit(jax.grad(lambda q: jnp.sum(jnp.sin(attention(q, k, v, impl="xla", causal_block=8)))))(q)
    with jax.set_mesh(mesh):
        assert max_rel(jax.grad(loss)(q), ref) <= 1e-5


def test_blockwise_takes_operands_of_other_shardings_forward_and_backward():
    # a DiT's full layout under an Explicit mesh: q/k/v head-sharded with the batch replicated, the
    # text mask batch-sharded. The tile loops' carries must keep one sharding type (they did not:
    # fori_loop refused the step), and the result equals the dense reference, gradients included.
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    q, k, v, do = _qkvd(b=2, lq=24, lk=24, h=4)
    mask = jnp.arange(24)[None, :] < jnp.array([[20], [24]])
    loss = lambda impl: lambda q, k, v, m: jnp.sum(attention(q, k, v, impl=impl, kv_mask=m, block_q=8, block_k=8) * do)
    ref, ref_grads = jax.jit(jax.value_and_grad(loss("xla"), argnums=(0, 1, 2)))(q, k, v, mask)
    mesh = jax.make_mesh((2, 1, 1, 4), ("data", "fsdp", "seq", "tensor"), axis_types=(AxisType.Explicit,) * 4)
    with jax.set_mesh(mesh):
        heads = lambda x: jax.device_put(x, NamedSharding(mesh, P(None, None, "tensor", None)))
        m = jax.device_put(mask, NamedSharding(mesh, P(("data", "fsdp"), None)))
        out, grads = jax.jit(jax.value_and_grad(loss("blockwise"), argnums=(0, 1, 2)))(heads(q), heads(k), heads(v), m)
    assert abs(float(out) - float(ref)) <= 1e-4 * abs(float(ref))
    for g, r in zip(grads, ref_grads):
        assert max_rel(g, r) <= 1e-5
