"""The diffusion transformer of jaxdrive: one linen module for MiLA, LongDWM, STAGE and
MagicDrive-V2, with per-frame noise levels, multi-view attention and the driving controls.

    from jaxdrive.models.dit import DiT
    from jaxdrive.models.dit.presets import preset

    dit = DiT(preset("tiny"))
    params = dit.init_params(seed=0)                  # on the host; or dit.init(key, ...) on devices
    v = dit.forward(params, latents, sigma, Conditions(text=ids, text_mask=mask))  # latents [B, V, F', h, w, C]

Layouts (``DiTConfig.layout``): ``"factorized"`` (STDiT-3 / STDiT-2 layers with spatial attention
over all views, MiLA [2503.15875v1] eq. 3, or per view plus MagicDrive-V2's cross-view attention; temporal
attention with RoPE; cross-attention to text and control tokens; adaLN-single) and ``"full"``
(CogVideoX: full 3D attention over ``[text; video]`` with expert adaLN, 3D RoPE or 3D sin-cos).

**Noise levels.** ``sigma`` is ``[B]`` (broadcast) or ``[B, F']`` per latent frame; the net
embeds ``timestep_scale * sigma`` per frame, so each frame gets its own modulation (adaLN-single
vectors, the final layer's shift/scale, CogVideoX's expert adaLN). Condition frames carry 0. With
a patch spanning ``pt > 1`` frames a token frame takes the mean level of its frames. The text
stream of the full layout is modulated by the embedding of the largest level of the clip (the
whole clip's level for an imported model, whose sigma is ``[B]``; a choice, CogVideoX has one
level per clip).

**Sequence parallelism** shards the spatial patches S of the activations ``[B, F, S, V, D]`` over
``seq``; :mod:`jaxdrive.models.dit.blocks` lists which attentions communicate.

**Conditions** come as one :class:`jaxdrive.models.dit.conditions.Conditions` (``cond``), each field
for a control of ``DiTConfig.controls`` (:class:`jaxdrive.models.dit.config.Controls`), each
droppable for classifier-free guidance by ``cond.drop={name: [B] bool}``:

- learned nulls replace the embedding of a dropped ``text``, ``fps``, ``camera``, ``waypoints``,
  ``trajectory``, ``boxes`` or ``warp``; leaving the input out (None) is the same as dropping it
  for every sample;
- a dropped or absent ``frame_times`` adds nothing (its embedding's last layer starts at zero,
  so the "null" is the model without the control);
- the projected layout (``controls.layout``) is dropped with ``boxes`` (absent boxes: likewise)
  and then adds nothing;
- a dropped ``map`` is the all-zero map (MagicDrive-V2 [2411.13807v3] appendix E, after MagicDrive); leaving
  ``bev_map`` out switches the ControlNet branch off;
- condition frames are set by ``cond_latents``/``cond_mask`` (interpolation = first and last frame
  in the mask, LongDWM's fine DiT dropping the last frame = leaving it out of the mask).

**STAGE hook.** ``return_features=True`` also returns ``{layer: [B, F, S, V, D]}``, the outputs of
the ``htft_layers`` before fusion; ``cond.features={layer: [B, K, S, V, D]}`` (past frames' features
at the same layer and denoising step) with ``cond.features_mask [B, K]`` are fused after those layers by
:class:`jaxdrive.models.htft.HTFT` (STAGE [2506.13138v1] sec. 4B).
"""

from __future__ import annotations

import functools
from types import MappingProxyType

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.flow.rectified import skip_coefficients
from jaxdrive.models.dit.blocks import LayerContext, layer_class
from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.models.dit.config import DiTConfig, check_config, layer_runs
from jaxdrive.models.dit.controls import (
    MapEncoder,
    TimestepMLP,
    null_param,
    use_null,
)
from jaxdrive.models.dit.embed import (
    additive_conditions,
    clip_embeddings,
    control_tokens,
    patchify,
    reference_input,
    text_context,
    unpatchify,
    unpatchify_overlap,
)
from jaxdrive.models.dit.inputs import example_inputs
from jaxdrive.models.embeddings import rope_3d, sincos_2d, sincos_3d
from jaxdrive.models.htft import HTFT
from jaxdrive.models.layers import MLP, Dense, LayerNorm, modulate
from jaxdrive.models.params import ZEROS, Init, abstract_params, count_params, host_params, normal, param
from jaxdrive.models.tokens import TEXT, VIDEO, pool_frames
from jaxdrive.parallel.rules import constrain

POLICIES = {
    "full": jax.checkpoint_policies.nothing_saveable,
    "dots": jax.checkpoint_policies.checkpoint_dots,
    "dots_no_batch": jax.checkpoint_policies.dots_with_no_batch_dims_saveable,
}


class _Body(nn.Module):
    """One layer as a scan body: ``carry -> layer(carry) [+ residual]``; with ``emit`` it also
    returns a zero-initialised projection of its video output (a ControlNet branch layer)."""

    cfg: DiTConfig
    emit: bool = False

    @nn.compact
    def __call__(self, carry, res, ctx):
        cfg = self.cfg
        # a layer's output keeps its input's dtype (float32 parameters promote a bf16 stream), so a
        # scan's carry has one type
        carry = jax.tree_util.tree_map(
            lambda new, old: new.astype(old.dtype), layer_class(cfg)(cfg, name="layer")(carry, ctx), carry
        )
        video = carry[0] if cfg.layout == "full" else carry
        if res is not None:
            video = video + res
            carry = (video, carry[1]) if cfg.layout == "full" else video
        out = None
        if self.emit:
            out = Dense(cfg.width, ("embed", None), dtype=cfg.compute_dtype, kernel_init=ZEROS, name="out")(video)
        return carry, out


@functools.cache
def _body_class(remat: str, scanned: bool):
    if remat == "none":
        return _Body
    return nn.remat(_Body, policy=POLICIES[remat], prevent_cse=not scanned)


def _video(cfg, carry):
    return carry[0] if cfg.layout == "full" else carry


def _with_video(cfg, carry, video):
    return (video, carry[1]) if cfg.layout == "full" else video


def _with_given_frames(cfg: DiTConfig, latents, sigma, cond: Conditions) -> tuple[jax.Array, jax.Array]:
    """``(x [B, V, F', h, w, C] float32, sigma [B, F'])``: with ``controls.cond_frames ==
    "replace"`` the given frames (``cond.cond_mask``) take ``cond.cond_latents`` and level 0, or
    ``cond.cond_sigma`` where the given frames were noised (:func:`jaxdrive.flow.noise_given_frames`)."""
    x = constrain(jnp.asarray(latents, jnp.float32), ("batch", "views", "frames", None, None, None))
    b, nf = x.shape[0], x.shape[2]
    sig = jnp.broadcast_to(jnp.asarray(sigma, jnp.float32).reshape(b, -1), (b, nf))
    if cond.cond_latents is not None and cfg.controls.cond_frames == "replace":
        m = jnp.asarray(cond.cond_mask, bool)
        x = jnp.where(m[:, None, :, None, None, None], jnp.asarray(cond.cond_latents, jnp.float32), x)
        given = 0.0 if cond.cond_sigma is None else jnp.asarray(cond.cond_sigma, jnp.float32)
        sig = jnp.where(m, given, sig)
    return x, sig


@functools.lru_cache(maxsize=16)
def _traced_params(config: DiTConfig, shapes: tuple) -> tuple:
    """``abstract_params`` of ``DiT(config)`` for :func:`example_inputs` ``shapes``: the model is
    traced once per config, not once per call (a run's init, its checkpoint target and every
    restore each asked for it, and a small DiT takes seconds to trace on a CPU). The tree holds
    only shapes and dtypes, the same whatever mesh the caller is under. The trace attends with
    "xla": the parameters are the same for every kernel, and one traced without a mesh cannot run
    a TPU-only or sequence-sharded kernel (a step compiled for TPU devices asks for splash)."""
    config = config.replace(attn_impl="xla", local_attn_impl="xla", cross_attn_impl=None)
    tree, recorded = abstract_params(DiT(config, parent=None), **example_inputs(config, **dict(shapes)))
    plain = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype)  # no sharding from the caller's mesh
    return jax.tree_util.tree_map(plain, tree), MappingProxyType(recorded)


class DiT(nn.Module):
    """The diffusion transformer (see the module docstring). ``config``: a :class:`DiTConfig`."""

    config: DiTConfig

    # ------------------------------------------------------------------ public API

    def forward(self, params, latents, sigma, cond: Conditions | None = None, *, rngs=None, **kw):
        """``self.apply({"params": params}, latents, sigma, cond, **kw)``: the network output
        ``[B, V, F', h, w, C_out]`` (the velocity ``noise - x``, or the clean latents with
        ``prediction="data"``: :func:`jaxdrive.flow.velocity_from_output` turns either into the
        velocity)."""
        return self.apply({"params": params}, latents, sigma, cond, rngs=rngs, **kw)

    def init_params(self, seed: int = 0, *, boxed: bool = False, **shapes):
        """Float32 parameters drawn on the host with NumPy (seeded by ``seed``), each from the
        initialiser its layer declares: nothing is compiled, which on a CPU is the difference
        between a second and minutes. ``boxed=True`` keeps the ``nn.LogicallyPartitioned`` boxes
        (for :func:`jaxdrive.parallel.shard_params`). ``shapes`` go to :func:`example_inputs`
        (the parameter shapes do not depend on them). ``self.init(key, ...)`` (e.g. jitted with
        ``out_shardings`` from :func:`jaxdrive.parallel.param_shardings`) initialises on devices."""
        tree, recorded = _traced_params(self.config, tuple(sorted(shapes.items())))
        return host_params(tree, recorded, seed, boxed=boxed)

    def abstract_params(self, **shapes):
        """The boxed params tree with ``jax.ShapeDtypeStruct`` leaves (``jax.eval_shape``)."""
        tree = _traced_params(self.config, tuple(sorted(shapes.items())))[0]
        return jax.tree_util.tree_map(lambda x: x, tree)  # the caller's own containers

    # ------------------------------------------------------------------ the network

    @nn.compact
    def __call__(self, latents, sigma, cond: Conditions | None = None, *, return_features=False, deterministic=True):
        """Network output ``[B, V, F', h, w, C_out]`` (and ``{layer: features}`` with
        ``return_features``) for ``latents [B, V, F', h, w, C]`` at levels ``sigma [B]``/``[B, F']``
        under the conditions ``cond`` (:class:`~jaxdrive.models.dit.conditions.Conditions`; None: none
        given). ``deterministic=False`` enables HTFT's dropout (rng ``"dropout"``).
        """
        cfg = check_config(self.config)
        c = (Conditions() if cond is None else cond).check(cfg, latents, sigma)
        drop = {k: jnp.asarray(v, bool) for k, v in (c.drop or {}).items()}
        x, sig = _with_given_frames(cfg, latents, sigma, c)
        _, nv, nf, h, w, _ = x.shape
        grid = (h // cfg.patch[1], w // cfg.patch[2])
        ref = None
        if cfg.controls.reference_frame:
            warp = c.warp if cfg.controls.reference_frame == "warp" else None
            ref = reference_input(x, c.cond_latents, c.cond_mask, warp, drop.get("warp"))
        hid = self._video_tokens(cfg, x, c, drop, grid, ref)
        t, ctx = self._noise_level_context(cfg, pool_frames(sig, cfg.patch[0]), c, drop, nf, grid)
        carry, ctx = self._token_context(cfg, hid, ctx, c, drop, nv, nf, (h, w))
        residuals = None
        if cfg.controls.map and c.bev_map is not None:
            residuals = self._map_branch(cfg, carry, ctx, c.bev_map, drop, nf, grid)
        carry, feats = self._stack(cfg, carry, ctx, residuals, c.features, c.features_mask, deterministic)
        out = self._output(cfg, _video(cfg, carry), t, x, ref, grid, sig)
        return (out, feats) if return_features else out

    # ------------------------------------------------------------------ steps of the network

    def _video_tokens(
        self, cfg: DiTConfig, x: jax.Array, c: Conditions, drop: dict, grid: tuple[int, int], ref
    ) -> jax.Array:
        """The video tokens ``[B, Ft, S, V, D]``: patch embedding, positions and the additive
        conditions (MiLA [2503.15875v1] eq. 2: h_fuse = h_f + h_c)."""
        dt = cfg.compute_dtype
        nf, h, w = x.shape[2:5]
        tokens = constrain(patchify(x, cfg.patch), VIDEO[:-1] + ("channels",))
        hid = Dense(cfg.width, ("channels", "embed"), dtype=dt, name="patch_embed")(tokens)
        if cfg.layout == "factorized":
            pos = sincos_2d(*grid, cfg.width, cfg.spatial_interpolation_scale)
            hid = hid + jnp.asarray(pos, dt)[None, None, :, None]
        elif cfg.positions == "sincos":
            pos = sincos_3d(
                nf // cfg.patch[0], *grid, cfg.width, cfg.spatial_interpolation_scale, cfg.temporal_interpolation_scale
            )
            hid = hid + jnp.asarray(pos, dt)[None, :, :, None]
        hid = hid + additive_conditions(self, cfg, x, c, drop, (h, w), grid, ref)
        hid = constrain(hid, VIDEO)
        self.sow("intermediates", "tokens", hid)
        return hid

    def _noise_level_context(
        self, cfg: DiTConfig, sig_tok: jax.Array, c: Conditions, drop: dict, nf: int, grid: tuple[int, int]
    ) -> tuple[jax.Array, LayerContext]:
        """The token frames' levels ``sig_tok [B, Ft]`` as per-frame timestep embeddings ``t [B,
        Ft, Dt]`` (+ fps, + ofs), and the layer context holding the modulation they drive (the
        full layout's text level and 3D RoPE, or adaLN-single's ``t0``)."""
        dt, pt = cfg.compute_dtype, cfg.patch[0]
        temb = TimestepMLP(cfg.time_freq_dim, cfg.t_dim, cfg.flip_sin_to_cos, cfg.freq_shift, dt, name="t_embedder")
        t = temb(sig_tok * cfg.timestep_scale)  # [B, Ft, Dt]
        extra = clip_embeddings(self, cfg, sig_tok.shape[0], c.fps, c.ofs, drop)
        t = t + extra[:, None]
        ctx = LayerContext()
        if cfg.layout == "full":
            # flax.struct.dataclass adds .replace at runtime; its stub does not declare it
            ctx = ctx.replace(  # type: ignore[attr-defined]
                t=t,
                t_text=temb(jnp.max(sig_tok, axis=1) * cfg.timestep_scale) + extra,
            )
            if cfg.positions == "rope":
                ctx = ctx.replace(rope=rope_3d(nf // pt, *grid, cfg.head_dim, theta=cfg.rope_theta, base=cfg.rope_base))
        else:
            k = 6 if cfg.block == "stdit3" else 9
            # flax.struct.dataclass adds .replace at runtime; its stub does not declare it
            ctx = ctx.replace(  # type: ignore[attr-defined]
                t0=Dense(
                    k * cfg.width,
                    ("embed", None),
                    dtype=dt,
                    kernel_init=normal(0.02),
                    name="t_block",
                )(jax.nn.silu(t))
            )
        self.sow("intermediates", "modulation", t if ctx.t0 is None else ctx.t0)
        return t, ctx

    def _token_context(
        self, cfg: DiTConfig, hid: jax.Array, ctx, c: Conditions, drop: dict, nv: int, nf: int, hw: tuple[int, int]
    ):
        """The layers' carry (the video tokens ``hid``; with the projected text in the full
        layout) and ``ctx`` with what they attend to: text, control and warp tokens."""
        dt, b = cfg.compute_dtype, hid.shape[0]
        text_ctx, tmask = text_context(self, cfg, b, c.text, c.text_mask, drop)
        tok, tok_mask = control_tokens(self, cfg, b, nv, nf, hw, c, drop)
        ctx = ctx.replace(tokens=tok, tokens_mask=tok_mask)
        if c.warp is not None:
            wt = Dense(cfg.width, ("channels", "embed"), dtype=dt, name="warp_embed")(
                constrain(patchify(jnp.asarray(c.warp, jnp.float32), cfg.patch), VIDEO[:-1] + ("channels",))
            )
            ctx = ctx.replace(
                warp=use_null(drop.get("warp"), wt, null_param(self, "warp_null", (cfg.width,), ("embed",)))
            )
        carry: jax.Array | tuple[jax.Array, jax.Array] = hid  # (video, text) in the full layout
        if cfg.layout == "full":
            carry = (
                hid,
                constrain(Dense(cfg.width, ("text_embed", "embed"), dtype=dt, name="text_proj")(text_ctx), TEXT),
            )
            ctx = ctx.replace(text_mask=tmask)
        elif text_ctx is not None:
            ctx = ctx.replace(
                text=MLP(cfg.width, cfg.width, dtype=dt, in_name="text_embed", name="text_proj")(text_ctx),
                text_mask=tmask,
            )
        return carry, ctx

    def _output(self, cfg: DiTConfig, video, t, x, ref, grid: tuple[int, int], sig) -> jax.Array:
        """The network output ``[B, V, F', h, w, C_out]`` of the last layer's ``video`` tokens:
        the final layer, unpatchified, U-ViT's convolutions and the given frame's residual (with
        ``sigma_data``, EDM's skip from the input ``x`` at the frames' levels ``sig [B, F']``)."""
        out = self._final(cfg, video, t)
        # the head is per frame: frames over seq keep a long window's output split across the mesh
        out = constrain(out, ("batch", "out_frames", None, "views", None))
        to_latents = unpatchify_overlap if cfg.out_patches == "overlap" else unpatchify
        out = to_latents(out, cfg.patch, grid, cfg.out_dim).astype(jnp.float32)
        if cfg.final_conv:
            out = out + self._final_conv(cfg, out, x, ref)
        base = None
        if cfg.controls.reference_frame in ("residual", "warp"):
            assert ref is not None  # made above: reference_frame is set
            base = ref[..., :-1]  # the change from the newest given frame, or from the warp
        if cfg.sigma_data:
            return self._skip(cfg, out, x, base, sig)
        return out if base is None else out + base

    @staticmethod
    def _skip(cfg, out, x, base, sig):
        """EDM's preconditioning of the data estimate (Karras et al. 2022, eq. 7;
        :func:`jaxdrive.flow.skip_coefficients`) around the reference ``base`` (or 0):
        ``base + c_skip (x - (1 - sigma) base) + c_out out``."""
        s = sig[:, None, :, None, None, None]
        c_skip, c_out = skip_coefficients(s, cfg.sigma_data)
        base = 0.0 if base is None else base
        return base + c_skip * (x - (1.0 - s) * base) + c_out * out

    # ------------------------------------------------------------------ pieces

    def _map_branch(self, cfg, carry, ctx, bev_map, drop, nf, grid):
        """MagicDrive-V2's map ControlNet (sec. 4.2, Zhang et al. 2023): the map encoder's tokens
        enter a trainable copy of the first ``map_blocks`` layers through a zero-initialised
        projection; each copy's output returns through a zero-initialised projection and is added
        to the output of the matching base layer. Returns the residuals ``[map_blocks, ...]``."""
        c, dt, pt = cfg.controls, cfg.compute_dtype, cfg.patch[0]
        bev = jnp.asarray(bev_map, jnp.float32)
        if drop.get("map") is not None:
            bev = use_null(drop["map"], bev, jnp.zeros((), jnp.float32))
        m = MapEncoder(cfg.width, c.map_hidden, cfg.vae_temporal, dt, name="map_embed")(bev, nf, grid)
        # the encoder folds frames into the batch: put the batch back on the batch axes alone
        m = constrain(pool_frames(m, pt), ("batch", "frames", "tokens", "embed"))  # [B, Ft, S, D]
        m = Dense(cfg.width, ("embed", None), dtype=dt, kernel_init=ZEROS, name="map_in")(m)
        video = _video(cfg, carry)
        branch = _with_video(cfg, carry, constrain(video + m[:, :, :, None], VIDEO))
        _, res = self._run(cfg, branch, ctx, 0, c.map_blocks, None, "control", emit=True)
        return res

    def _run(self, cfg, carry, ctx, start, end, res, prefix, emit=False):
        """Layers ``start .. end - 1``: one ``nn.scan`` when ``scan_layers`` and more than one
        layer (params stacked on a leading ``layers`` axis), else a Python loop. The residual
        stream between layers is float32 whatever the compute dtype (mixed precision: each layer
        computes in ``dtype``, the sums of its residual branches are kept in float32)."""
        carry = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), carry)
        if cfg.scan_layers and end - start > 1:
            body = nn.scan(
                _body_class(cfg.remat, True),
                variable_axes={"params": 0},
                split_rngs={"params": True, "dropout": True},
                in_axes=(0, nn.broadcast),
                length=end - start,
                metadata_params={nn.PARTITION_NAME: "layers"},
            )
            return body(cfg, emit, name=f"{prefix}_{start}_{end}")(carry, res, ctx)
        outs = []
        for i in range(start, end):
            layer = _body_class(cfg.remat, False)(cfg, emit, name=f"{prefix}_{i}")
            carry, y = layer(carry, None if res is None else res[i - start], ctx)
            outs.append(y)
        return carry, (jnp.stack(outs) if emit else None)

    def _stack(self, cfg, carry, ctx, residuals, features, features_mask, deterministic):
        """The base layers, run by run (:func:`jaxdrive.models.dit.config.layer_runs`)."""
        feats = {}
        for start, end in layer_runs(cfg):
            res = None
            if residuals is not None and start < cfg.controls.map_blocks:
                res = residuals[start:end]
            carry, _ = self._run(cfg, carry, ctx, start, end, res, "layers")
            if end - 1 in cfg.htft_layers:
                video = _video(cfg, carry)
                feats[end - 1] = video
                if features is not None:
                    fused = HTFT(
                        cfg.width,
                        cfg.heads,
                        cfg.head_dim,
                        cfg.htft_groups,
                        cfg.htft_dropout,
                        impl=cfg.attn_impl,
                        dtype=cfg.compute_dtype,
                        name=f"htft_{end - 1}",
                    )(
                        video,
                        jnp.asarray(features[end - 1], cfg.compute_dtype),
                        features_mask,
                        deterministic=deterministic,
                    )
                    carry = _with_video(cfg, carry, fused)
        return carry, feats

    def _final(self, cfg, x, t):
        dt = cfg.compute_dtype
        if cfg.layout == "factorized":
            # T2I final layer (PixArt-alpha): per-frame shift/scale = table + t
            table = param(self, "final_table", normal(1.0 / np.sqrt(cfg.width)), (2, cfg.width), (None, "embed"))
            mod = table[None, None] + t[:, :, None, :]  # [B, Ft, 2, D]
            shift, scale = mod[:, :, 0, None, None], mod[:, :, 1, None, None]
            h = modulate(LayerNorm(cfg.norm_eps, affine=False, name="final_norm")(x), shift, scale)
        else:
            # CogVideoX: norm_final, then AdaLayerNorm (shift, scale from silu(t))
            h = LayerNorm(cfg.norm_eps, name="norm_final")(x)
            mod = Dense(2 * cfg.width, ("embed", None), dtype=dt, name="norm_out_linear")(jax.nn.silu(t))
            shift, scale = mod[:, :, None, None, : cfg.width], mod[:, :, None, None, cfg.width :]
            h = modulate(LayerNorm(cfg.norm_eps, name="norm_out")(h), shift, scale)
        p = cfg.patch[0] * cfg.patch[1] * cfg.patch[2] * cfg.out_dim * (4 if cfg.out_patches == "overlap" else 1)
        return Dense(p, ("embed", "channels"), dtype=dt, kernel_init=ZEROS, name="proj_out")(h)

    def _final_conv(self, cfg, out, x, ref):
        """U-ViT's 3x3 convolutions after the unpatchify (Bao et al. 2023, sec. 3.1): a token's
        output is a linear map of its own hidden state, so neighbouring tokens' outputs meet at a
        seam the network never sees; two convolutions over the output, the input (and the given
        frame) smooth across it. The last one starts at zero: the network's output unchanged."""
        split = lambda a: constrain(a, ("batch", "views", "out_frames", None, None, None))  # per frame: frames over seq
        h = jnp.concatenate([split(a) for a in [out, x] + ([ref] if ref is not None else [])], axis=-1)
        h = jax.nn.silu(_conv3x3(self, "final_conv_1", h, cfg.final_conv, Init("lecun", fan_in_axes=3)))
        return _conv3x3(self, "final_conv_2", h, out.shape[-1], ZEROS)


def _conv3x3(module, name, x, features, init):
    """A "same" 3x3 convolution over the ``h, w`` axes of ``x [..., h, w, C]`` as nine shifted
    dense maps: any leading axes, and no reshape that would move their sharding."""
    h, w = x.shape[-3:-1]
    kernel = param(module, f"{name}_kernel", init, (3, 3, x.shape[-1], features), (None, None, "channels", None))
    xp = jnp.pad(x, [(0, 0)] * (x.ndim - 3) + [(1, 1), (1, 1), (0, 0)])
    y = sum(
        jnp.einsum("...c,cd->...d", xp[..., i : i + h, j : j + w, :], kernel[i, j]) for i in range(3) for j in range(3)
    )
    return y + param(module, f"{name}_bias", ZEROS, (features,), (None,))


def param_trace_shapes(cfg: DiTConfig) -> dict:
    """The input shapes to trace ``DiT(cfg)``'s parameters with (:meth:`DiT.init_params`,
    :meth:`DiT.abstract_params`). Parameter shapes do not depend on the inputs' (cross-view
    attention needs two views); callers that use these share one trace, cached per config and
    shapes: a run's init and its checkpoint target alike."""
    return {"views": 2 if cfg.multiview == "cross_view" else 1}


def param_count(cfg: DiTConfig) -> int:
    """Number of parameters of ``DiT(cfg)``, from ``jax.eval_shape`` (nothing is allocated)."""
    return count_params(DiT(cfg).abstract_params(**param_trace_shapes(cfg)))


__all__ = ["DiT", "DiTConfig", "example_inputs", "param_count", "patchify", "unpatchify"]
