"""Ring and all-to-all (Ulysses) attention against the dense single-device reference.

Forward and the gradients w.r.t. q, k, v (random cotangent) on 8 fake CPU devices, on meshes
seq=8, data=2 x seq=4 and fsdp=2 x seq=2 x tensor=2, with and without kv_mask / causal_block,
lengths the seq axis does not divide (padded path), cross attention (Lq != Lk), several K/V
pieces per chunk, bf16 inputs, the tile-size rule, and the errors.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive.attention import softmax_blocks as sb
from jaxdrive.attention.ring import ring_attention
from jaxdrive.attention.ulysses import ulysses_attention

from dit_fixtures import max_rel

NAMES = ("data", "fsdp", "seq", "tensor")
MESHES = {"seq8": (1, 1, 8, 1), "data2_seq4": (2, 1, 4, 1), "fsdp2_seq2_tensor2": (1, 2, 2, 2)}
IMPLS = {"ring": ring_attention, "ulysses": ulysses_attention}
SCALE = 0.35
TOL = 1e-5


def _mesh(shape, names=NAMES):
    return jax.make_mesh(shape, names, axis_types=(AxisType.Explicit,) * len(names))


def _inputs(seed, b, lq, lk, h, d, with_mask):
    """Drawn with NumPy: eager ``jax.random`` calls compile one program per shape."""
    rng = np.random.default_rng(seed)
    q, k, v, ct = (jnp.asarray(rng.standard_normal((b, n, h, d), np.float32)) for n in (lq, lk, lk, lq))
    mask = None
    if with_mask:
        mask = rng.random((b, lk)) < 0.6
        mask[0] = False  # one batch row sees no key at all -> output 0
        mask = jnp.asarray(mask)
    return q, k, v, ct, mask


def _check(impl, mesh, q, k, v, ct, mask, causal_block, **kw):
    fn = jax.jit(
        lambda q, k, v: IMPLS[impl](q, k, v, mesh=mesh, scale=SCALE, kv_mask=mask, causal_block=causal_block, **kw)
    )
    ref = lambda q, k, v: sb.attend_block(q, k, v, scale=SCALE, kv_mask=mask, causal_block=causal_block)[0]
    out, vjp = jax.vjp(fn, q, k, v)
    want, vjp_ref = jax.vjp(jax.jit(ref), *(jnp.asarray(np.asarray(x)) for x in (q, k, v)))  # unsharded
    assert out.shape == q.shape and out.dtype == q.dtype
    errs = [max_rel(out, want)] + [max_rel(g, r) for g, r in zip(vjp(ct), vjp_ref(ct))]
    assert all(np.isfinite(e) for e in errs), errs
    assert max(errs) <= TOL, dict(zip(["o", "dq", "dk", "dv"], errs))
    if mask is not None:  # the fully masked batch row is exactly 0
        assert np.abs(np.asarray(out)[0]).max() == 0.0
    return errs


@pytest.mark.slow(seconds=4)
@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("mesh_name", MESHES)
@pytest.mark.parametrize("with_mask,causal_block", [(False, None), (True, 5)])
def test_matches_dense_on_meshes(impl, mesh_name, with_mask, causal_block):
    q, k, v, ct, mask = _inputs(0, 4, 64, 64, 8, 8, with_mask)
    _check(impl, _mesh(MESHES[mesh_name]), q, k, v, ct, mask, causal_block)


@pytest.mark.slow(seconds=4)
@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("with_mask,causal_block", [(True, None), (False, 3)])
def test_mask_and_causal_separately(impl, with_mask, causal_block):
    q, k, v, ct, mask = _inputs(1, 2, 64, 64, 8, 8, with_mask)
    _check(impl, _mesh(MESHES["seq8"]), q, k, v, ct, mask, causal_block)


@pytest.mark.slow(seconds=4)
@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("mesh_name", ["seq8", "fsdp2_seq2_tensor2"])
@pytest.mark.parametrize("with_mask,causal_block", [(False, None), (True, 4)])
def test_padded_length(impl, mesh_name, with_mask, causal_block):
    """L = 37 is not a multiple of the seq size: padded keys are masked, padded rows dropped."""
    q, k, v, ct, mask = _inputs(2, 4, 37, 37, 8, 8, with_mask)
    _check(impl, _mesh(MESHES[mesh_name]), q, k, v, ct, mask, causal_block)


@pytest.mark.slow(seconds=8)
@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("lq,lk", [(21, 45)])
def test_cross_attention(impl, lq, lk):
    q, k, v, ct, mask = _inputs(3, 2, lq, lk, 8, 8, True)
    _check(impl, _mesh(MESHES["data2_seq4"]), q, k, v, ct, mask, 6)


@pytest.mark.slow(seconds=7)
@pytest.mark.parametrize("impl", IMPLS)
def test_presharded_inputs_under_set_mesh(impl):
    mesh = _mesh(MESHES["fsdp2_seq2_tensor2"])
    q, k, v, ct, mask = _inputs(4, 4, 32, 32, 4, 8, True)
    spec = NamedSharding(mesh, P(("data", "fsdp"), "seq", "tensor", None))
    q, k, v = (jax.device_put(x, spec) for x in (q, k, v))
    with jax.set_mesh(mesh):
        _check(impl, mesh, q, k, v, ct, mask, 4)


@pytest.mark.parametrize("impl", IMPLS)
def test_mesh_without_seq_axis(impl):
    q, k, v, _, _ = _inputs(5, 2, 16, 16, 8, 8, False)
    mesh = _mesh((2, 4), ("data", "tensor"))
    with pytest.raises(ValueError, match="mesh"):
        IMPLS[impl](q, k, v, mesh=mesh, scale=SCALE)


@pytest.mark.parametrize("impl", IMPLS)
def test_batch_not_divisible(impl):
    q, k, v, _, _ = _inputs(6, 3, 16, 16, 8, 8, False)
    with pytest.raises(ValueError, match=r"q: .*batch"):
        IMPLS[impl](q, k, v, mesh=_mesh(MESHES["data2_seq4"]), scale=SCALE)


@pytest.mark.parametrize("impl", IMPLS)
def test_heads_not_divisible_by_tensor(impl):
    q, k, v, _, _ = _inputs(7, 2, 16, 16, 3, 8, False)
    with pytest.raises(ValueError, match=r"q: .*'tensor'"):
        IMPLS[impl](q, k, v, mesh=_mesh(MESHES["fsdp2_seq2_tensor2"]), scale=SCALE)


def test_ulysses_heads_not_divisible_by_seq():
    q, k, v, _, _ = _inputs(8, 2, 16, 16, 4, 8, False)
    with pytest.raises(ValueError, match=r"q: .*size 8 of mesh axis 'seq'.*4 heads"):
        ulysses_attention(q, k, v, mesh=_mesh(MESHES["seq8"]), scale=SCALE)
    # the ring has no such constraint
    out = jax.eval_shape(lambda q, k, v: ring_attention(q, k, v, mesh=_mesh(MESHES["seq8"]), scale=SCALE), q, k, v)
    assert out.shape == q.shape


@pytest.mark.parametrize("impl", IMPLS)
def test_bad_arguments(impl):
    q, k, v, _, _ = _inputs(9, 2, 16, 16, 8, 8, False)
    mesh = _mesh(MESHES["seq8"])
    with pytest.raises(ValueError, match="kv_mask"):
        IMPLS[impl](q, k, v, mesh=mesh, scale=SCALE, kv_mask=jnp.ones((2, 15), bool))
    with pytest.raises(ValueError, match="causal_block"):
        IMPLS[impl](q, k, v, mesh=mesh, scale=SCALE, causal_block=0)
    with pytest.raises(ValueError, match="v"):
        IMPLS[impl](q, k, v[:, :8], mesh=mesh, scale=SCALE)
    with pytest.raises(ValueError, match="k"):
        IMPLS[impl](q, k[..., :4], v, mesh=mesh, scale=SCALE)


@pytest.mark.slow(seconds=6)
def test_ulysses_with_small_local_blocks():
    """The local kernel really tiles the gathered sequence (several query and key blocks)."""
    from functools import partial

    from jaxdrive.attention.blockwise import blockwise_attention

    mesh = _mesh(MESHES["data2_seq4"])
    q, k, v, ct, mask = _inputs(10, 2, 60, 60, 8, 8, True)
    local = partial(blockwise_attention, block_q=16, block_k=8)
    fn = lambda q, k, v: ulysses_attention(q, k, v, mesh=mesh, scale=SCALE, kv_mask=mask, causal_block=5, local=local)
    ref = lambda q, k, v: sb.attend_block(q, k, v, scale=SCALE, kv_mask=mask, causal_block=5)[0]
    out, vjp = jax.vjp(jax.jit(fn), q, k, v)
    want, vjp_ref = jax.vjp(ref, q, k, v)
    errs = [max_rel(out, want)] + [max_rel(g, r) for g, r in zip(vjp(ct), vjp_ref(ct))]
    assert max(errs) <= TOL, errs


@pytest.mark.slow(seconds=5)
@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("lq,lk,causal_block", [(150, 150, None), (150, 150, 7), (70, 150, 5)])
def test_several_pieces_per_chunk(impl, lq, lk, causal_block):
    """block = 16 on seq = 4: 38-token key chunks are padded to 3 tiles and K/V travel (ring) or
    cross (all-to-all) in 3 pieces per chunk; causal blocks straddle pieces, the mask hides a
    whole batch row, and lengths do not divide the mesh."""
    from jaxdrive.attention import seq_shard

    assert seq_shard.tile_size(seq_shard.chunk(lk, 4), 8, 16) == 16
    q, k, v, ct, mask = _inputs(11, 2, lq, lk, 8, 8, True)
    _check(impl, _mesh(MESHES["data2_seq4"]), q, k, v, ct, mask, causal_block, block=16)


def test_tile_size_shrinks_with_the_chunk():
    from jaxdrive.attention.seq_shard import MIN_TILE, TILE_FRACTION, tile_size

    assert tile_size(65536, 64, 512) == 512  # long chunks: the block
    assert tile_size(8192, 64, 512) == 128  # 128^2 * 16 <= 8192 * 64 < 256^2 * 16
    assert tile_size(512, 64, 512) == 32
    assert tile_size(8, 8, 512) == MIN_TILE  # never below the floor
    assert tile_size(10**5, 8, 24) == 24  # a block that is no power of two, kept whole
    assert tile_size(100, 8, 24) == MIN_TILE  # or halved, but not below the floor
    for rows in (1, 7, 100, 1000, 4096, 10**5):
        for dim in (8, 64, 128):
            t = tile_size(rows, dim, 512)
            assert t == MIN_TILE or t * t * TILE_FRACTION <= rows * dim
            assert t == 512 or (2 * t) ** 2 * TILE_FRACTION > rows * dim


@pytest.mark.parametrize("impl", IMPLS)
def test_bfloat16_inputs(impl):
    """Residuals and dK/dV are kept in the input dtype: bf16 in, bf16 out, close to fp32 dense."""
    mesh = _mesh(MESHES["fsdp2_seq2_tensor2"])
    q, k, v, ct, mask = _inputs(12, 2, 64, 64, 8, 8, True)
    fn = jax.jit(lambda q, k, v: IMPLS[impl](q, k, v, mesh=mesh, scale=SCALE, kv_mask=mask, causal_block=4))
    ref = lambda q, k, v: sb.attend_block(q, k, v, scale=SCALE, kv_mask=mask, causal_block=4)[0]
    low = [x.astype(jnp.bfloat16) for x in (q, k, v)]
    out, vjp = jax.vjp(fn, *low)
    want, vjp_ref = jax.vjp(ref, *(x.astype(jnp.float32) for x in low))
    grads = vjp(ct.astype(jnp.bfloat16))
    assert out.dtype == jnp.bfloat16 and all(g.dtype == jnp.bfloat16 for g in grads)
    errs = [max_rel(out.astype(jnp.float32), want)]
    errs += [max_rel(g.astype(jnp.float32), r) for g, r in zip(grads, vjp_ref(ct))]
    assert max(errs) <= 1e-2, errs  # bf16 rounds at 2^-8 ~ 4e-3
