"""The layers of the diffusion transformer and the attentions they are made of.

Video activations are ``[B, F, S, V, D]``: F token frames, S spatial patches of one view, V views.
Sequence parallelism shards **S** (the spatial patches) over the mesh axis ``seq`` in both
layouts (MagicDrive-V2 [2411.13807v3] appendix A: "partition each input across the spatial dimension"). Which
attentions communicate:

- spatial self-attention (factorized; per frame over all views' tokens, MiLA [2503.15875v1] eq. 3, or per view)
  and cross-view attention (MagicDrive-V2): their sequences run over S, so they use the
  sequence-sharded kernels (``attn_impl``: ring / all-to-all under a ``seq`` mesh);
- full 3D attention (CogVideoX) over ``[text; video]``: sequence-sharded likewise, the text
  padded and split into one chunk per ``seq`` shard;
- STAGE's HTFT cross-attention to past features (sharded queries and keys): sequence-sharded;
- temporal attention (per spatial position over frames) and cross-attention to text and control
  tokens: **no communication** (every device holds all frames of its patches and all context
  tokens); they run a local kernel (``local_attn_impl``; the cross-attention ``cross_attn_impl``
  where set).

Every attention goes through :func:`jaxdrive.attention.attention`. Sequences are built so
that the sharded axis S is the major part of the merged sequence (see
:func:`jaxdrive.models.tokens.to_sequence`): each device then holds one contiguous chunk, which
is what the ring and all-to-all kernels expect. Attention without positions inside the sequence
(or with RoPE applied before merging) does not depend on the token order, so the order is free.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import PartitionSpec

from jaxdrive.attention import attention
from jaxdrive.models.dit.config import DiTConfig
from jaxdrive.models.embeddings import apply_rope, rope_1d
from jaxdrive.models.layers import MLP, AttnProj, Dense, LayerNorm, modulate
from jaxdrive.models.params import ZEROS, normal, param
from jaxdrive.models.tokens import TEXT, VIDEO, from_sequence, merge, reshape, split, to_sequence
from jaxdrive.parallel.mesh import explicit_mesh, mesh_axis_size, spec_of
from jaxdrive.parallel.rules import constrain, reshard_like


@struct.dataclass
class LayerContext:
    """What every layer reads besides the video tokens, built once by the DiT: timestep embeddings
    (``t0``: the adaLN-single vectors of the factorized layout; ``t``/``t_text``: CogVideoX's per-frame
    and text-stream embeddings), ``rope`` (the full layout's 3D RoPE tables), the projected ``text``
    tokens with ``text_mask``, control ``tokens [B, F, V, N, D]`` with ``tokens_mask`` and ``warp``
    tokens. A pytree, so ``nn.scan`` broadcasts it to every layer."""

    t0: jax.Array | None = None
    t: jax.Array | None = None
    t_text: jax.Array | None = None
    rope: tuple[jax.Array | np.ndarray, jax.Array | np.ndarray] | None = None  # (cos, sin)
    text: jax.Array | None = None
    text_mask: jax.Array | None = None
    tokens: jax.Array | None = None
    tokens_mask: jax.Array | None = None
    warp: jax.Array | None = None


# Token order of merged video sequences: S (sharded) major, then F, then V.
SFV = (2, 1, 3)
VIDEO_HEADS = ("batch", "frames", "tokens", "views", "heads", "head_dim")


def _out(proj: AttnProj, o):
    """Output projection of attention output ``o [B, F, S, V, H, Dh]`` brought back to the video
    sharding (splitting a merged batch can spread the batch mesh axes over the split axes)."""
    return proj.out(constrain(o, VIDEO_HEADS))


def _proj(cfg: DiTConfig, name: str, *, qk_norm=None, zero_out=False, eps=None):
    return AttnProj(
        cfg.heads,
        cfg.head_dim,
        cfg.width,
        qkv_bias=cfg.qkv_bias,
        qk_norm=cfg.qk_norm if qk_norm is None else qk_norm,
        eps=1e-6 if eps is None else eps,
        dtype=cfg.compute_dtype,
        zero_out=zero_out,
        name=name,
    )


def spatial_attention(proj: AttnProj, x, impl: str, per_view: bool):
    """Self-attention within each frame: over all views' patches (MiLA [2503.15875v1] eq. 3,
    ``Q, K, V in R^{T x (V H W) x C}``) or, ``per_view``, within each view's patches."""
    q, (k, v) = proj.q(x), proj.kv(x)  # [B, F, S, V, H, Dh]
    shape = q.shape
    if per_view:
        seq = lambda a: merge(merge(jnp.transpose(a, (0, 1, 3, 2, 4, 5)), 0), 0)  # [B F V, S]
        o = attention(seq(q), seq(k), seq(v), impl=impl)
        o = jnp.transpose(split(split(o, 0, shape[0]), 1, shape[1]), (0, 1, 3, 2, 4, 5))
    else:
        seq = lambda a: merge(merge(a, 2), 0)  # [B F, S V]
        o = attention(seq(q), seq(k), seq(v), impl=impl)
        o = split(split(o, 0, shape[0]), 2, shape[2])
    return _out(proj, o)


def cross_view_attention(proj: AttnProj, x, offsets, impl: str):
    """MagicDrive-V2's cross-view attention (sec. 4.2, after MagicDrive): the tokens of view v
    attend to all tokens of the views ``v + o`` (mod V) for ``o`` in ``offsets``."""
    q, (k, v) = proj.q(x), proj.kv(x)  # [B, F, S, V, H, Dh]
    shape = q.shape

    def neighbours(a):  # [B F V, S O, H, Dh]
        a = jnp.stack([jnp.roll(a, -o, axis=3) for o in offsets], axis=3)  # [B, F, S, O, V, ...]
        a = jnp.transpose(a, (0, 1, 4, 2, 3, 5, 6))  # [B, F, V, S, O, ...]
        return merge(merge(merge(a, 3), 0), 0)

    qs = merge(merge(jnp.transpose(q, (0, 1, 3, 2, 4, 5)), 0), 0)
    o = attention(qs, neighbours(k), neighbours(v), impl=impl)
    o = jnp.transpose(split(split(o, 0, shape[0]), 1, shape[1]), (0, 1, 3, 2, 4, 5))
    return _out(proj, o)


def temporal_attention(proj: AttnProj, x, impl: str, theta: float):
    """Self-attention over the frames of each (patch, view) position with RoPE over the frame index
    (Open-Sora's temporal attention); local: every device holds all frames of its patches."""
    q, (k, v) = proj.q(x), proj.kv(x)  # [B, F, S, V, H, Dh]
    cos, sin = (jnp.asarray(a)[:, None, None, None, :] for a in rope_1d(np.arange(q.shape[1]), q.shape[-1], theta))
    q, k = apply_rope(q, cos, sin), apply_rope(k, cos, sin)
    fn = lambda q, k, v: attention(q, k, v, impl=impl)
    over_views = jax.vmap(fn, in_axes=2, out_axes=2)  # [B, F, V, H, Dh] -> vmap V
    o = jax.vmap(over_views, in_axes=2, out_axes=2)(q, k, v)  # vmap S
    return _out(proj, o)


def context_attention(proj: AttnProj, x, ctx: LayerContext, impl: str):
    """Cross-attention of the video tokens to the context: text tokens ``ctx.text [B, L, D]``
    (with ``text_mask``) and per-(frame, view) control tokens ``ctx.tokens [B, F, V, N, D]``
    (with ``tokens_mask``): the tokens of frame f, view v see the text and their own controls
    (MagicDrive-V2: cross-attention for text, boxes, cameras and trajectory). Local: the
    context is replicated over ``seq``. Returns 0 when there is no context."""
    text, tokens = ctx.text, ctx.tokens
    if text is None and tokens is None:
        return jnp.zeros_like(x)
    q = proj.q(x)  # [B, F, S, V, H, Dh]
    shape = q.shape
    if tokens is None:
        k, v = proj.kv(text)
        o = attention(to_sequence(q, SFV), k, v, impl=impl, kv_mask=ctx.text_mask)
        return _out(proj, from_sequence(o, shape, SFV))
    b, f, _, nv = shape[:4]
    kc, vc = proj.kv(tokens)  # [B, F, V, N, H, Dh]
    mc = ctx.tokens_mask
    assert mc is not None  # control tokens come with their mask
    if text is not None:
        kt, vt = proj.kv(text)  # [B, L, H, Dh]
        # the text's sharding may differ from the control tokens' (text replicated, boxes per sample)
        grow = lambda a, like: reshard_like(jnp.broadcast_to(a[:, None, None], (b, f, nv) + a.shape[1:]), like)
        kc, vc = jnp.concatenate([grow(kt, kc), kc], 3), jnp.concatenate([grow(vt, vc), vc], 3)
        tm = ctx.text_mask
        tm = jnp.ones(text.shape[:2], bool) if tm is None else tm
        mc = jnp.concatenate([grow(tm, mc), mc], 3)
    groups = lambda a: merge(merge(a, 0), 0)  # [B F V, ...]
    qs = groups(jnp.transpose(q, (0, 1, 3, 2, 4, 5)))
    o = attention(qs, groups(kc), groups(vc), impl=impl, kv_mask=groups(mc))
    o = jnp.transpose(split(split(o, 0, b), 1, f), (0, 1, 3, 2, 4, 5))
    return _out(proj, o)


def joint_attention(proj: AttnProj, xv, xt, *, impl: str, rope=None, text_mask=None):
    """CogVideoX's full 3D attention over ``[text; video]`` (Yang et al. 2024, sec. 2.2).

    ``xv [B, F, S, V, D]`` video, ``xt [B, L, D]`` text; ``rope = (cos, sin) [F, S, Dh]`` rotates
    the video queries and keys only. Under a ``seq`` mesh of size n the text is padded to a
    multiple of n and the joint sequence is laid out as n chunks ``[text_i; video_i]``, one per
    device, so that the video never leaves its shard; attention is order-free, so this is the
    same attention as over ``[text; video]``. Returns ``(video out, text out)``.
    """
    qv, (kv_, vv) = proj.q(xv), proj.kv(xv)
    qt, (kt, vt) = proj.q(xt), proj.kv(xt)
    if rope is not None:
        cos, sin = (jnp.asarray(a)[:, :, None, None, :] for a in rope)
        qv, kv_ = apply_rope(qv, cos, sin), apply_rope(kv_, cos, sin)
    shape = qv.shape
    seqs_v = [to_sequence(a, SFV) for a in (qv, kv_, vv)]  # [B, N, H, Dh]
    b, lt, n_vid = xt.shape[0], xt.shape[1], seqs_v[0].shape[1]
    n = mesh_axis_size("seq")
    if n_vid % n or shape[2] % n:
        n = 1
    lp = -(-lt // n) * n
    tmask = jnp.ones((b, lt), bool) if text_mask is None else jnp.asarray(text_mask, bool)
    tmask = jnp.pad(tmask, ((0, 0), (0, lp - lt)))
    pad = lambda a: jnp.pad(a, ((0, 0), (0, lp - lt), (0, 0), (0, 0)))
    seqs_t = [constrain(pad(a), ("batch", "tokens", "heads", "head_dim")) for a in (qt, kt, vt)]
    vmask = jnp.ones((b, n_vid), bool)

    def join(t, v):
        if n == 1:
            if explicit_mesh() is not None:
                # unsharded over the sequence: one seq device, or a frame's tokens the seq axis does
                # not divide (the clip's may still be sharded, the text's need not divide at all)
                spec = list(spec_of(v))
                spec[1] = None
                t, v = (jax.reshard(a, PartitionSpec(*spec)) for a in (t, v))
            return jnp.concatenate([t, v], axis=1)
        return merge(jnp.concatenate([split(t, 1, n), split(v, 1, n)], axis=2), 1)

    q, k, v = (join(t, v) for t, v in zip(seqs_t, seqs_v))
    mask = join(constrain(tmask, ("batch", "tokens")), constrain(vmask, ("batch", "tokens")))
    o = attention(q, k, v, impl=impl, kv_mask=None if text_mask is None and lp == lt else mask)
    if n == 1:
        ot, ov = o[:, :lt], o[:, lt:]
    else:
        chunks = split(o, 1, n)
        ot = merge(chunks[:, :, : lp // n], 1)
        ov = merge(chunks[:, :, lp // n :], 1)
        ot = constrain(ot, ("batch", None, "heads", "head_dim"))[:, :lt]
    return _out(proj, from_sequence(ov, shape, SFV)), proj.out(ot)


class CrossView(nn.Module):
    """Pre-norm cross-view attention with a zero-initialised output projection (MagicDrive)."""

    cfg: DiTConfig

    @nn.compact
    def __call__(self, x):
        cfg = self.cfg
        h = LayerNorm(cfg.norm_eps, name="norm")(x)
        return cross_view_attention(_proj(cfg, "attn", zero_out=True), h, cfg.neighbor_offsets, cfg.attn_impl)


def _table(module, n: int, width: int):
    return param(module, "scale_shift_table", normal(1.0 / np.sqrt(width)), (n, width), (None, "embed"))


def _chunks(table, t0, n: int):
    """adaLN-single (PixArt-alpha sec. 2.3): per-block ``table [n, D]`` + the shared per-frame
    ``t0 [B, F, n D]`` -> n vectors ``[B, F, 1, 1, D]`` broadcasting over patches and views."""
    b, f = t0.shape[:2]
    mod = table[None, None] + t0.reshape(b, f, n, -1)
    return [mod[:, :, i, None, None, :] for i in range(n)]


class STBlock(nn.Module):
    """One STDiT-3 block (Open-Sora 1.2; MagicDrive-V2's MVDiT block when spatial and
    ``cross_view``): modulated self-attention (spatial or temporal), [cross-view attention],
    cross-attention to the context, modulated MLP; per-frame adaLN-single modulation."""

    cfg: DiTConfig
    temporal: bool

    @nn.compact
    def __call__(self, x, ctx):
        cfg = self.cfg
        shift, scale, gate, shift_m, scale_m, gate_m = _chunks(_table(self, 6, cfg.width), ctx.t0, 6)
        h = modulate(LayerNorm(cfg.norm_eps, affine=False, name="norm1")(x), shift, scale)
        grown = self.temporal and cfg.temporal == "zero_init"  # added to a spatial-only model: identity at init
        proj = _proj(cfg, "attn", zero_out=grown)
        if self.temporal:
            a = temporal_attention(proj, h, cfg.local_attn_impl, cfg.rope_theta)
        else:
            a = spatial_attention(proj, h, cfg.attn_impl, cfg.multiview == "cross_view")
        x = x + gate * a
        if not self.temporal and cfg.multiview == "cross_view":
            x = x + CrossView(cfg, name="cross_view")(x)
        x = x + context_attention(_proj(cfg, "cross_attn", qk_norm="none", zero_out=True), x, ctx, cfg.cross_impl)
        h = modulate(LayerNorm(cfg.norm_eps, affine=False, name="norm2")(x), shift_m, scale_m)
        mlp = MLP(int(cfg.width * cfg.mlp_ratio), cfg.width, dtype=cfg.compute_dtype, zero_out=grown, name="mlp")
        return x + gate_m * mlp(h)


class FactorizedLayer(nn.Module):
    """One layer of the factorized layout: ``stdit3`` = spatial block then temporal block (each with
    its own table); ``stdit2`` = spatial attention, [cross-view], temporal attention,
    cross-attention and MLP under one 9-vector modulation (Open-Sora 1.1's STDiT-2 block, the
    base of MiLA). Warp-guided frames (LongDWM [2506.01546v1] sec. 3.4) enter at the layer input through a
    zero-initialised projection."""

    cfg: DiTConfig

    @nn.compact
    def __call__(self, x, ctx):
        cfg = self.cfg
        x = constrain(x, VIDEO)
        if ctx.warp is not None:
            x = x + Dense(cfg.width, ("embed", None), dtype=cfg.compute_dtype, kernel_init=ZEROS, name="warp_proj")(
                ctx.warp
            )
        if cfg.block == "stdit3":
            x = STBlock(cfg, False, name="spatial")(x, ctx)
            if cfg.temporal != "off":
                x = STBlock(cfg, True, name="temporal")(x, ctx)
            return constrain(x, VIDEO)
        chunks = _chunks(_table(self, 9, cfg.width), ctx.t0, 9)
        shift, scale, gate, shift_m, scale_m, gate_m, shift_t, scale_t, gate_t = chunks
        h = modulate(LayerNorm(cfg.norm_eps, affine=False, name="norm1")(x), shift, scale)
        x = x + gate * spatial_attention(_proj(cfg, "attn"), h, cfg.attn_impl, cfg.multiview == "cross_view")
        if cfg.multiview == "cross_view":
            x = x + CrossView(cfg, name="cross_view")(x)
        h = modulate(LayerNorm(cfg.norm_eps, affine=False, name="norm_temp")(x), shift_t, scale_t)
        x = x + gate_t * temporal_attention(_proj(cfg, "attn_temp"), h, cfg.local_attn_impl, cfg.rope_theta)
        x = x + context_attention(_proj(cfg, "cross_attn", qk_norm="none", zero_out=True), x, ctx, cfg.cross_impl)
        h = modulate(LayerNorm(cfg.norm_eps, affine=False, name="norm2")(x), shift_m, scale_m)
        x = x + gate_m * MLP(int(cfg.width * cfg.mlp_ratio), cfg.width, dtype=cfg.compute_dtype, name="mlp")(h)
        return constrain(x, VIDEO)


class FullBlock(nn.Module):
    """One CogVideoX block: expert adaLN (one LayerNorm, separate shift/scale/gate for the video and
    the text tokens from one linear map of the timestep embedding), full attention over
    ``[text; video]``, shared MLP. Per-frame noise levels give each video frame its own
    modulation; the text stream takes the embedding ``ctx.t_text``. Optional: warp injection at
    the input and a zero-initialised cross-attention to per-(frame, view) control tokens (boxes,
    trajectory), the same context attention the factorized layout uses."""

    cfg: DiTConfig

    @nn.compact
    def __call__(self, carry, ctx):
        cfg = self.cfg
        xv, xt = carry
        xv = constrain(xv, VIDEO)
        if ctx.warp is not None:
            xv = xv + Dense(cfg.width, ("embed", None), dtype=cfg.compute_dtype, kernel_init=ZEROS, name="warp_proj")(
                ctx.warp
            )
        rope = ctx.rope
        for i, sub in enumerate(("attn", "ff")):
            lin = Dense(6 * cfg.width, ("embed", None), dtype=cfg.compute_dtype, name=f"norm{i + 1}_linear")
            norm = LayerNorm(cfg.norm_eps, name=f"norm{i + 1}")
            mv = lin(jax.nn.silu(ctx.t))  # [B, F, 6D]: video shift, scale, gate
            mt = lin(jax.nn.silu(ctx.t_text))  # [B, 6D]: text (last three)
            b, f = mv.shape[:2]
            mv = reshape(mv, (b, f, 6, 1, 1, cfg.width))
            mt = reshape(mt, (b, 6, 1, cfg.width))
            hv = modulate(norm(xv), mv[:, :, 0], mv[:, :, 1])
            ht = modulate(norm(xt), mt[:, 3], mt[:, 4])
            if sub == "attn":
                ov, ot = joint_attention(
                    _proj(cfg, "attn", eps=1e-6), hv, ht, impl=cfg.attn_impl, rope=rope, text_mask=ctx.text_mask
                )
            else:
                mlp = MLP(int(cfg.width * cfg.mlp_ratio), cfg.width, dtype=cfg.compute_dtype, name="ff")
                ov, ot = mlp(hv), mlp(ht)
            xv = xv + mv[:, :, 2] * ov
            xt = xt + mt[:, 5] * ot
        if ctx.tokens is not None:
            h = LayerNorm(cfg.norm_eps, name="ctx_norm")(xv)
            xv = xv + context_attention(
                _proj(cfg, "ctx_attn", qk_norm="none", zero_out=True),
                h,
                LayerContext(tokens=ctx.tokens, tokens_mask=ctx.tokens_mask),
                cfg.cross_impl,
            )
        return constrain(xv, VIDEO), constrain(xt, TEXT)


def layer_class(cfg: DiTConfig):
    return FullBlock if cfg.layout == "full" else FactorizedLayer
