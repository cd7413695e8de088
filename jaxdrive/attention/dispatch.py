"""The one attention entry point of jaxdrive: every model layer calls :func:`attention`.

Implementations (``impl``):

- ``"xla"``: dense softmax attention, the reference (fp32 scores and softmax).
- ``"blockwise"``: O(L) memory on one device, forward and backward
  (:mod:`jaxdrive.attention.blockwise`).
- ``"ring"``: the sequence sharded over the mesh axis ``seq``; key/value chunks travel around the
  ring (:mod:`jaxdrive.attention.ring`).
- ``"ulysses"``: all-to-all from sequence- to head-sharding over ``seq``, a local blockwise kernel,
  and back (:mod:`jaxdrive.attention.ulysses`).
- ``"cudnn"``: ``jax.nn.dot_product_attention(..., implementation="cudnn")`` on GPUs (fp16/bf16).
- ``"splash"``: JAX's Pallas splash kernel on TPUs (:mod:`jaxdrive.attention.splash`), inside
  ``shard_map`` over the batch and heads on a mesh.

"TPU" and "GPU" are the platform of the mesh's devices (:func:`jaxdrive.parallel.mesh.mesh_platform`),
not the backend the host process started: a step compiled ahead of time for TPU topology devices
on a CPU host gets the TPU kernel.
- ``"auto"``: ``"ring"`` when the mesh shards ``seq``; else ``"splash"`` on TPU or ``"cudnn"``
  where it applies; else ``"blockwise"`` for long sequences and ``"xla"`` for short ones. It
  never fails where ``"xla"`` works, given that a ``mesh`` passed in is the context mesh.

Masks: ``kv_mask [B, Lk]`` (True = attend; e.g. padded text tokens) and ``causal_block = n``:
token block i (n tokens, e.g. one latent frame) attends to blocks <= i. A query row with no
allowed key returns 0 in every implementation.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.attention import softmax_blocks, splash
from jaxdrive.attention.blockwise import blockwise_attention
from jaxdrive.attention.ring import ring_attention
from jaxdrive.attention.seq_shard import layout
from jaxdrive.attention.ulysses import ulysses_attention
from jaxdrive.parallel.mesh import context_mesh, mesh_platform, spec_of
from jaxdrive.validate import check_choice, check_positive_int

IMPLS = ("auto", "xla", "blockwise", "ring", "ulysses", "cudnn", "splash")
# Above this many (query, key) pairs per head, "auto" prefers the O(L) kernel on one device.
AUTO_BLOCKWISE_PAIRS = 4096 * 4096


def _check_inputs(q, k, v, kv_mask, causal_block):
    for name, x in (("q", q), ("k", k), ("v", v)):
        if np.ndim(x) != 4:
            raise ValueError(f"{name}: expected shape [B, L, H, D], got {list(np.shape(x))}")
    if k.shape != v.shape:
        raise ValueError(f"v: expected the shape of k {list(k.shape)}, got {list(v.shape)}")
    if (k.shape[0], k.shape[2], k.shape[3]) != (q.shape[0], q.shape[2], q.shape[3]):
        raise ValueError(
            f"k: expected shape [{q.shape[0]}, Lk, {q.shape[2]}, {q.shape[3]}] (B, H, D of q), got {list(k.shape)}"
        )
    if not (q.dtype == k.dtype == v.dtype):
        raise ValueError(f"k, v: expected the dtype of q ({q.dtype}), got {k.dtype} and {v.dtype}")
    if kv_mask is not None:
        if tuple(np.shape(kv_mask)) != (k.shape[0], k.shape[1]):
            raise ValueError(
                f"kv_mask: expected shape [{k.shape[0]}, {k.shape[1]}] ([B, Lk]), got {list(np.shape(kv_mask))}"
            )
        if jnp.result_type(kv_mask) != jnp.bool_:
            raise ValueError(f"kv_mask: expected dtype bool, got {jnp.result_type(kv_mask)}")
    if causal_block is not None:
        check_positive_int("causal_block", causal_block)
        if q.shape[1] != k.shape[1]:
            raise ValueError(f"causal_block: needs self-attention (Lq == Lk), got Lq = {q.shape[1]}, Lk = {k.shape[1]}")


def _check_entered(mesh, impl):
    """The sharded kernels type their output with ``mesh``: outside that mesh's context whatever
    follows them cannot place it (``jax.grad`` seeding the loss's cotangent fails with a bare
    error about device assignment), so ask for the context up front."""
    context = context_mesh()
    if context is None or context != getattr(mesh, "abstract_mesh", mesh):
        raise ValueError(
            f"mesh: impl {impl!r} runs on the mesh it is given only inside it: call "
            f"attention within `with jax.set_mesh(mesh):`; got mesh {dict(mesh.shape)} "
            f"under context mesh {None if context is None else dict(context.shape)}"
        )


def _seq_size(mesh) -> int:
    return 1 if mesh is None or "seq" not in mesh.axis_names else int(mesh.shape["seq"])


def _cudnn_applies(q, kv_mask, causal_block, mesh) -> bool:
    return mesh_platform(mesh) == "gpu" and q.dtype in (jnp.float16, jnp.bfloat16) and causal_block is None


def _ring_applies(q, k, v, mesh, kv_mask, causal_block) -> bool:
    try:  # batch divisible by data x fsdp, heads by tensor: otherwise "auto" must not fail
        layout(q, k, v, kv_mask, causal_block, mesh, "seq")
    except ValueError:
        return False
    return True


def _auto(q, k, v, mesh, kv_mask, causal_block) -> str:
    if _seq_size(mesh) > 1 and _ring_applies(q, k, v, mesh, kv_mask, causal_block):
        return "ring"
    if splash.available(mesh):
        return "splash"
    if _cudnn_applies(q, kv_mask, causal_block, mesh):
        return "cudnn"
    return "blockwise" if q.shape[1] * k.shape[1] > AUTO_BLOCKWISE_PAIRS else "xla"


def _gather_sequence(x):
    """``x [B, L, ...]`` with its sequence axis gathered when an Explicit mesh shards it (e.g. over
    ``seq``, even of size 1): a one-device kernel contracting q against k with both sharded over
    the same mesh axis is an illegal sharding."""
    if x is None:
        return x
    spec = spec_of(x)
    if len(spec) < 2 or spec[1] is None:
        return x
    return jax.sharding.reshard(x, jax.sharding.PartitionSpec(spec[0], None, *spec[2:]))


def _gather_kv(k, v, kv_mask):
    """Dense attention keeps q's sharding (the output stays sequence-sharded like q) and gathers
    K/V: an all-gather of K/V, no more."""
    return _gather_sequence(k), _gather_sequence(v), _gather_sequence(kv_mask)


def _blockwise(q, k, v, *, kv_mask, **kw):
    """The O(L) kernel slices q in tiles: it runs on gathered sequences, and the output takes q's
    sequence sharding back."""
    spec = spec_of(q)
    k, v, kv_mask = _gather_kv(k, v, kv_mask)
    o = blockwise_attention(_gather_sequence(q), k, v, kv_mask=kv_mask, **kw)
    if spec[1] is not None:
        o = jax.sharding.reshard(o, jax.sharding.PartitionSpec(*spec))
    return o


def _batch_like(q, k, v, kv_mask):
    """K, V and the mask resharded to q's batch sharding (K and V to its head sharding too): under
    an Explicit mesh a batched dot needs equal batch shardings, and the text of a cross-attention
    may be sharded over the batch where the video tokens are not (jax 0.11 refuses the mix)."""
    qs = spec_of(q)

    def like(x, want):
        if x is None or tuple(spec_of(x)) == want:
            return x
        return jax.sharding.reshard(x, jax.sharding.PartitionSpec(*want))

    ks, vs = spec_of(k), spec_of(v)
    return (
        like(k, (qs[0], ks[1], qs[2], ks[3])),
        like(v, (qs[0], vs[1], qs[2], vs[3])),
        None if kv_mask is None else like(kv_mask, (qs[0],) + spec_of(kv_mask)[1:]),
    )


def _xla(q, k, v, scale, kv_mask, causal_block):
    k, v, kv_mask = _batch_like(q, *_gather_kv(k, v, kv_mask))
    return softmax_blocks.attend_block(q, k, v, scale=scale, kv_mask=kv_mask, causal_block=causal_block)[0].astype(
        q.dtype
    )


def _cudnn(q, k, v, scale, kv_mask):
    mask = None if kv_mask is None else jnp.asarray(kv_mask, bool)[:, None, None, :]
    return jax.nn.dot_product_attention(q, k, v, mask=mask, scale=scale, implementation="cudnn")


def attention(
    q,
    k,
    v,
    *,
    impl: str = "auto",
    kv_mask=None,
    causal_block=None,
    mesh=None,
    scale=None,
    block_q: int = 512,
    block_k: int = 512,
):
    """Softmax attention ``softmax(q k^T * scale) v`` over ``q [B, Lq, H, D]``, ``k, v [B, Lk, H, D]``.

    ``scale`` defaults to ``1 / sqrt(D)``. ``mesh`` (or the mesh set with ``jax.set_mesh``) is
    needed by ``"ring"`` and ``"ulysses"``, which shard the sequence over its ``seq`` axis, the
    batch over ``data``/``fsdp`` and the heads over ``tensor``; a ``mesh`` given must also be the
    context mesh (``with jax.set_mesh(mesh):``). ``block_q``/``block_k`` are the
    tile sizes of ``"blockwise"``. Raises ``ValueError`` naming the argument for mismatched
    shapes or dtypes, a mask of the wrong length, an unknown impl, a mesh without ``seq`` for
    ring/ulysses or one given outside its context, or an impl this backend lacks.
    """
    check_choice("impl", impl, IMPLS)
    _check_inputs(q, k, v, kv_mask, causal_block)
    scale = 1.0 / math.sqrt(q.shape[-1]) if scale is None else float(scale)
    mesh = context_mesh() if mesh is None else mesh
    if impl == "auto":
        impl = _auto(q, k, v, mesh, kv_mask, causal_block)
    if impl == "xla":
        return _xla(q, k, v, scale, kv_mask, causal_block)
    if impl == "blockwise":
        return _blockwise(
            q, k, v, scale=scale, kv_mask=kv_mask, causal_block=causal_block, block_q=block_q, block_k=block_k
        )
    if impl == "cudnn":
        if not _cudnn_applies(q, kv_mask, causal_block, mesh):
            raise ValueError(
                f"impl: 'cudnn' needs GPU devices, fp16/bf16 inputs and no causal_block, "
                f"got {mesh_platform(mesh)} devices, dtype {q.dtype}, "
                f"causal_block {causal_block}"
            )
        return _cudnn(q, k, v, scale, kv_mask)
    if impl == "splash":
        if not splash.available(mesh):
            raise ValueError(
                f"impl: 'splash' needs TPU devices (the mesh's, else the backend's), got {mesh_platform(mesh)}"
            )
        return splash.splash_attention(q, k, v, scale=scale, kv_mask=kv_mask, causal_block=causal_block, mesh=mesh)
    if mesh is None or "seq" not in mesh.axis_names:
        raise ValueError(
            f"mesh: impl {impl!r} needs a mesh with a 'seq' axis, got "
            f"{None if mesh is None else tuple(mesh.axis_names)}"
        )
    _check_entered(mesh, impl)
    if impl == "ring":
        return ring_attention(q, k, v, mesh=mesh, scale=scale, kv_mask=kv_mask, causal_block=causal_block)
    return ulysses_attention(q, k, v, mesh=mesh, scale=scale, kv_mask=kv_mask, causal_block=causal_block)
