"""What enters the DiT's layers (:class:`jaxdrive.models.dit.model.DiT`): latents to patch tokens
and back (:func:`patchify`, :func:`unpatchify`, :func:`unpatchify_overlap`), the newest given frame as an input
(:func:`reference_input`), and each condition's embedding, as functions of the DiT module they
build their parameters in (the DiT's module docstring says how each is dropped):

- :func:`additive_conditions`: added to the video tokens (MiLA [2503.15875v1] eq. 2) - camera,
  waypoints, frame times, the projected layout (:func:`layout_tokens`), the reference frame and
  the concat-mode condition frames;
- :func:`clip_embeddings`: added to the timestep embedding - fps and CogVideoX's ofs;
- :func:`text_context`: the text tokens (caption encoder or precomputed embeddings, learned null);
- :func:`control_tokens`: the cross-attention tokens - trajectory and boxes.

Each runs inside the DiT's ``__call__``, so the submodules and parameters it makes are the DiT's,
under the same names as when they were its methods.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.models.dit.controls import (
    BoxEncoder,
    CameraEncoder,
    CaptionEncoder,
    FrameTimeEncoder,
    TimestepMLP,
    TrajectoryEncoder,
    WaypointEncoder,
    null_param,
    use_null,
)
from jaxdrive.models.dit.layout import LayoutEncoder
from jaxdrive.models.layers import Dense
from jaxdrive.models.params import ZEROS
from jaxdrive.models.tokens import VIDEO, pool_frames, reshape
from jaxdrive.parallel.rules import constrain


def patchify(x, patch):
    """``[B, V, F', h, w, C]`` -> tokens ``[B, F' / pt, (h / ph) (w / pw), V, pt ph pw C]``."""
    b, nv, nf, h, w, c = x.shape
    pt, ph, pw = patch
    x = reshape(x, (b, nv, nf // pt, pt, h // ph, ph, w // pw, pw, c))
    x = jnp.transpose(x, (0, 2, 4, 6, 1, 3, 5, 7, 8))
    return reshape(x, (b, nf // pt, (h // ph) * (w // pw), nv, pt * ph * pw * c))


def unpatchify(tokens, patch, grid_hw, channels):
    """Inverse of :func:`patchify`."""
    b, ft, _, nv, _ = tokens.shape
    pt, ph, pw = patch
    gh, gw = grid_hw
    x = reshape(tokens, (b, ft, gh, gw, nv, pt, ph, pw, channels))
    x = jnp.transpose(x, (0, 4, 1, 5, 2, 6, 3, 7, 8))
    return reshape(x, (b, nv, ft * pt, gh * ph, gw * pw, channels))


def tent_window(n: int) -> np.ndarray:
    """The weights of an overlapping token's ``2 n`` positions along one axis: a tent rising from
    ``1 / (2 n)`` at the window's edges to ``1 - 1 / (2 n)`` beside its centre, so the two tokens
    over any position weigh it ``1`` in all (a partition of unity): ``n=2`` gives ``[1, 3, 3, 1] / 4``."""
    i = np.arange(2 * n) + 0.5
    return 1.0 - np.abs(i - n) / n


def unpatchify_overlap(tokens, patch, grid_hw, channels):
    """Overlapping output patches (``DiTConfig.out_patches="overlap"``): each token of
    ``tokens [B, F'/pt, S, V, pt (2 ph) (2 pw) C]`` paints a ``2 ph x 2 pw`` patch centred on its
    own ``ph x pw`` footprint (a margin of ``ph / 2``, ``pw / 2`` into its neighbours), weighted by
    :func:`tent_window` along each axis and summed with its neighbours' (overlap-add, the
    learned transposed convolution of stride ``p`` and kernel ``2 p`` that resize-free decoders
    use against block seams; Odena et al. 2016, "Deconvolution and checkerboard artifacts").
    A seam between two tokens' predictions is spread over their overlap, not drawn on the token
    grid's lines; at the frame's edges, where one token covers a position, it is divided by the
    weight it got. Tokens that agree on their overlap give back the image they describe exactly.
    Returns ``[B, V, F', h, w, C]``; ``ph`` and ``pw`` must be even (checked by the config)."""
    b, ft, s, nv, _ = tokens.shape
    pt, ph, pw = patch
    gh, gw = grid_hw
    wh, ww = tent_window(ph).reshape(2, ph), tent_window(pw).reshape(2, pw)
    x = reshape(tokens, (b, ft, s, nv, pt, 2, ph, 2, pw, channels))
    # each quarter of the patches is a token-aligned image; on a canvas with a half-token margin
    # all round, quarter (qi, qj) sits qi ph rows and qj pw columns in (pads and a slice: no
    # reshape that would move the h, w axes' sharding)
    canvas = 0.0
    for qi in range(2):
        for qj in range(2):
            w = jnp.asarray(wh[qi][:, None, None] * ww[qj][None, :, None], x.dtype)  # [ph, pw, 1]
            quarter = reshape(x[:, :, :, :, :, qi, :, qj] * w, (b, ft, s, nv, pt * ph * pw * channels))
            img = unpatchify(quarter, patch, grid_hw, channels)  # [B, V, F', h, w, C]
            pad = [(0, 0)] * 3 + [(qi * ph, (1 - qi) * ph), (qj * pw, (1 - qj) * pw), (0, 0)]
            canvas = canvas + jnp.pad(img, pad)
    out = canvas[:, :, :, ph // 2 : ph // 2 + gh * ph, pw // 2 : pw // 2 + gw * pw]
    # the weight each position got: 1 inside, less on the frame's outer half-token
    norm = _overlap_weight(ph, gh)[:, None] * _overlap_weight(pw, gw)[None, :]
    return out / jnp.asarray(norm[..., None], out.dtype)


def _overlap_weight(p: int, g: int) -> np.ndarray:
    """The summed :func:`tent_window` weight of each of ``g * p`` positions along one axis."""
    total = np.zeros(g * p + p)  # the canvas of unpatchify_overlap: a margin of p / 2 each side
    for k in range(g):
        total[k * p : k * p + 2 * p] += tent_window(p)
    return total[p // 2 : p // 2 + g * p]


def reference_input(x, cond_latents, cond_mask, warp=None, warp_dropped=None):
    """``[ref * given, given]`` for every frame of ``x [B, V, F', h, w, C]``: ``ref`` the latents of
    the newest frame in ``cond_mask [B, F']`` (``controls.reference_frame``), ``given`` 1 where a
    clip has a condition frame (0 and zeros for a clip without, or with no ``cond_latents``).
    With ``warp`` (``[B, V, F', h, w, C]``, ``reference_frame="warp"``) each frame's reference is
    its own warped latents, ``[warp, 1]``, except in the clips of ``warp_dropped [B]``.
    The out-dimension of the DiT equals ``C``, so ``[..., :-1]`` is the residual's base."""
    b, nv, nf, h, w, c = x.shape
    if warp is not None:
        newest = reference_input(x, cond_latents, cond_mask)
        warped = jnp.concatenate([jnp.asarray(warp, jnp.float32), jnp.ones_like(x[..., :1])], axis=-1)
        if warp_dropped is None:
            return warped
        return jnp.where(jnp.asarray(warp_dropped, bool)[:, None, None, None, None, None], newest, warped)
    if cond_latents is None:
        return jnp.zeros((b, nv, nf, h, w, c + 1), jnp.float32)
    m = jnp.asarray(cond_mask, bool)
    last = jnp.max(jnp.where(m, jnp.arange(nf)[None], -1), axis=1)  # [B]; -1: none given
    # a one-hot sum over frames, not a gather: it keeps the batch sharding of an Explicit mesh
    pick = (jnp.arange(nf)[None] == last[:, None]).astype(jnp.float32)[:, None, :, None, None, None]
    ref = jnp.sum(jnp.asarray(cond_latents, jnp.float32) * pick, axis=2, keepdims=True)
    like_x = jnp.zeros_like(x[..., :1])  # both halves take x's sharding before the concatenate
    given = like_x + jnp.sum(pick, axis=2, keepdims=True)
    return jnp.concatenate([like_x + ref, given], axis=-1)


def additive_conditions(module, cfg, x, cond: Conditions, drop, hw, grid, ref):
    """Conditions added to the tokens (MiLA [2503.15875v1] eq. 2, ``h_fuse = h_f + h_c``) and the concat-mode
    condition frames.

    Reading of MiLA [2503.15875v1] eq. 1 (``h_c = MLP(FFT(c))`` over all cameras and waypoints fused): one
    Fourier + MLP per condition, summed: the camera term per view, the waypoint term per frame.
    This keeps each condition droppable on its own with its own learned null (MiLA [2503.15875v1] appendix B
    drops conditions independently), which one MLP over the concatenation would not allow."""
    c, dt, width = cfg.controls, cfg.compute_dtype, cfg.width
    intrinsics, cam_to_ego, waypoints = cond.intrinsics, cond.cam_to_ego, cond.waypoints
    cond_latents, cond_mask = cond.cond_latents, cond.cond_mask
    b, nv, nf = x.shape[:3]
    pt = cfg.patch[0]
    add = jnp.zeros((), dt)
    image_hw = (hw[0] * cfg.vae_spatial, hw[1] * cfg.vae_spatial)
    if c.camera:
        null = null_param(module, "camera_null", (width,), ("embed",))
        if intrinsics is None:
            cam = jnp.broadcast_to(null.astype(dt), (b, nv, width))
        else:
            cam = CameraEncoder(width, c.fourier_freqs, c.fourier_temperature, dt, name="camera_embed")(
                intrinsics, cam_to_ego, image_hw
            )
            cam = use_null(drop.get("camera"), cam, null)
        add = add + cam[:, None, None]  # [B, 1, 1, V, D]
    if c.waypoints:
        null = null_param(module, "waypoints_null", (width,), ("embed",))
        if waypoints is None:
            wp = jnp.broadcast_to(null.astype(dt), (b, nf // pt, width))
        else:
            wp = WaypointEncoder(
                width, c.fourier_freqs, c.fourier_temperature, cfg.vae_temporal, dt, name="waypoints_embed"
            )(jnp.asarray(waypoints, jnp.float32), nf)
            wp = use_null(drop.get("waypoints"), pool_frames(wp, pt), null)
        add = add + wp[:, :, None, None]  # [B, Ft, 1, 1, D]
    if c.frame_time and cond.frame_times is not None:
        ft = FrameTimeEncoder(
            width, c.fourier_freqs, c.fourier_temperature, cfg.vae_temporal, dt, name="frame_time_embed"
        )(cond.frame_times, nf)
        ft = use_null(drop.get("frame_time"), pool_frames(ft, pt), jnp.zeros((), dt))
        add = add + ft[:, :, None, None]  # [B, Ft, 1, 1, D]
    if c.layout and cond.boxes is not None:
        add = add + layout_tokens(module, cfg, cond, drop, hw, nf)
    if ref is not None:
        add = add + Dense(width, ("channels", "embed"), dtype=dt, kernel_init=ZEROS, name="reference_embed")(
            constrain(patchify(ref, cfg.patch), VIDEO[:-1] + ("channels",))
        )
    if c.cond_frames == "concat":
        if cond_latents is None:
            cl, cm = jnp.zeros_like(x), jnp.zeros((b, nf), bool)
        else:
            cl, cm = jnp.asarray(cond_latents, jnp.float32), jnp.asarray(cond_mask, bool)
        mb = jnp.broadcast_to(cm[:, None, :, None, None, None], x.shape[:-1] + (1,)).astype(jnp.float32)
        cin = jnp.concatenate([cl * mb, mb], axis=-1)
        add = add + Dense(width, ("channels", "embed"), dtype=dt, kernel_init=ZEROS, name="cond_embed")(
            constrain(patchify(cin, cfg.patch), VIDEO[:-1] + ("channels",))
        )
    return add


def layout_tokens(module, cfg, cond: Conditions, drop, hw, nf):
    """The projected layout control (``controls.layout``, :mod:`jaxdrive.models.dit.layout`):
    the canvas of the boxes and the BEV map in every camera on the latent grid ``hw``,
    encoded, patchified, then a zero-initialised projection per token (the gate: a model
    initialised from a run without the control starts unchanged) -> ``[B, Ft, S, V, D]``.
    Dropped with the boxes (``drop["boxes"]``): a dropped row adds nothing, the model without
    the control. The caller adds nothing when the boxes are absent."""
    c, dt = cfg.controls, cfg.compute_dtype
    image_hw = (hw[0] * cfg.vae_spatial, hw[1] * cfg.vae_spatial)
    feats = LayoutEncoder(
        c.num_classes,
        c.map_channels,
        c.layout_hidden,
        c.layout_samples,
        tuple(c.layout_bev_range),
        cfg.vae_temporal,
        dt,
        name="layout_embed",
    )(
        cond.boxes,
        cond.box_classes,
        cond.box_valid,
        cond.intrinsics,
        cond.cam_to_ego,
        cond.bev_map,
        image_hw,
        hw,
        nf,
    )  # [B, V, F', h, w, hidden]
    tokens = constrain(patchify(feats, cfg.patch), VIDEO[:-1] + ("channels",))
    out = Dense(cfg.width, ("channels", "embed"), dtype=dt, kernel_init=ZEROS, name="layout_gate")(tokens)
    return use_null(drop.get("boxes"), out, jnp.zeros((), dt))


def clip_embeddings(module, cfg, b, fps, ofs, drop):
    """Per-clip additions to the timestep embedding: fps (Open-Sora) and ofs (CogVideoX 1.5)."""
    extra = jnp.zeros((b, cfg.t_dim), cfg.compute_dtype)
    if cfg.controls.fps:
        null = null_param(module, "fps_null", (cfg.t_dim,), ("embed",))
        if fps is None:
            extra = extra + null.astype(extra.dtype)
        else:
            e = TimestepMLP(256, cfg.t_dim, dtype=cfg.compute_dtype, name="fps_embedder")(fps)
            extra = extra + use_null(drop.get("fps"), e, null)
    if cfg.ofs_embed_dim is not None:
        o = jnp.full((b,), 2.0, jnp.float32) if ofs is None else jnp.asarray(ofs, jnp.float32)
        extra = extra + TimestepMLP(
            cfg.ofs_embed_dim,
            cfg.ofs_embed_dim,
            cfg.flip_sin_to_cos,
            cfg.freq_shift,
            cfg.compute_dtype,
            name="ofs_embedder",
        )(o)
    return extra


def text_context(module, cfg, b, text, text_mask, drop):
    c = cfg.controls
    if c.text is None:
        return None, None
    if text is not None:
        mask = jnp.ones(np.shape(text)[:2], bool) if text_mask is None else jnp.asarray(text_mask, bool)
        if c.text == "caption":
            y = CaptionEncoder(
                cfg.text_dim,
                c.caption_vocab,
                cfg.text_len,
                c.caption_layers,
                cfg.local_attn_impl,
                cfg.compute_dtype,
                name="caption_encoder",
            )(text, mask)
        else:
            y = jnp.asarray(text, cfg.compute_dtype)
    if not c.text_null:
        return y, (None if text_mask is None else mask)
    # the learned null is text_len tokens (Open-Sora's y_embedding); given text is padded to
    # text_len (padding masked) so that a dropped row and an absent text are the same input
    null = null_param(module, "text_null", (cfg.text_len, cfg.text_dim), ("text_tokens", "text_embed"))
    if text is None:
        return (
            jnp.broadcast_to(null.astype(cfg.compute_dtype), (b,) + null.shape),
            jnp.ones((b, cfg.text_len), bool),
        )
    pad = cfg.text_len - y.shape[1]
    y = jnp.pad(y, ((0, 0), (0, pad), (0, 0)))
    mask = jnp.pad(mask, ((0, 0), (0, pad)))
    return use_null(drop.get("text"), y, null), use_null(drop.get("text"), mask, jnp.ones((), bool))


def control_tokens(module, cfg, b, nv, nf, hw, cond: Conditions, drop):
    """Cross-attention tokens per (token frame, view): trajectory (1) and boxes (N)."""
    c, dt, width, pt = cfg.controls, cfg.compute_dtype, cfg.width, cfg.patch[0]
    intrinsics, cam_to_ego, ego_to_world = cond.intrinsics, cond.cam_to_ego, cond.ego_to_world
    boxes, box_classes, box_valid = cond.boxes, cond.box_classes, cond.box_valid
    ft = nf // pt
    toks, masks = [], []
    if c.trajectory:
        null = null_param(module, "trajectory_null", (width,), ("embed",))
        if ego_to_world is None:
            tr = jnp.broadcast_to(null.astype(dt), (b, ft, width))
        else:
            tr = TrajectoryEncoder(
                width,
                cfg.heads,
                c.encoder_layers,
                c.fourier_freqs,
                c.fourier_temperature,
                cfg.vae_temporal,
                cfg.local_attn_impl,
                dt,
                name="trajectory_embed",
            )(ego_to_world, nf)
            tr = use_null(drop.get("trajectory"), pool_frames(tr, pt), null)
        # over the batch axes, as the box tokens below: the two are concatenated per token
        toks.append(
            constrain(jnp.broadcast_to(tr[:, :, None, None], (b, ft, nv, 1, width)), ("batch", None, None, None, None))
        )
        masks.append(constrain(jnp.ones((b, ft, nv, 1), bool), ("batch", None, None, None)))
    if c.boxes:
        null = null_param(module, "boxes_null", (width,), ("embed",))
        if boxes is None:
            bt = jnp.broadcast_to(null.astype(dt), (b, ft, nv, 1, width))
            bm = jnp.ones((b, ft, nv, 1), bool)
        else:
            image_hw = (hw[0] * cfg.vae_spatial, hw[1] * cfg.vae_spatial)
            bt, bm = BoxEncoder(
                width,
                cfg.heads,
                c.encoder_layers,
                c.num_classes,
                cfg.box_freqs,
                c.fourier_temperature,
                cfg.vae_temporal,
                c.box_per_view,
                cfg.local_attn_impl,
                dt,
                cfg.box_range,
                name="boxes_embed",
            )(boxes, box_classes, box_valid, nf, intrinsics, cam_to_ego, image_hw)
            bt = pool_frames(bt, pt)
            bm = jnp.any(bm.reshape(b, ft, pt, *bm.shape[2:]), axis=2)
            # per-sample over the batch axes only: the encoder's reshapes over views may leave
            # another layout, which the drop's per-sample select below cannot broadcast with
            bt = constrain(jnp.broadcast_to(bt, (b, ft, nv) + bt.shape[3:]), ("batch", None, None, None, None))
            bm = constrain(jnp.broadcast_to(bm, (b, ft, nv) + bm.shape[3:]), ("batch", None, None, None))
            d = drop.get("boxes")
            if d is not None:
                first = jnp.arange(bm.shape[-1]) == 0
                bt = use_null(d, bt, null)
                bm = use_null(d, bm, first)
        toks.append(bt)
        masks.append(bm)
    if not toks:
        return None, None
    return jnp.concatenate(toks, axis=3), jnp.concatenate(masks, axis=3)
