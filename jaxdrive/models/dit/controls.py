"""Condition encoders of the diffusion transformer: timestep / fps embeddings, cameras, ego
waypoints and frame times (MiLA [2503.15875v1] eq. 1-2), MagicDrive-V2's spatial-temporal trajectory, box and
map encoders, the built-in caption encoder, and the temporal downsampling that aligns per-frame
conditions with the latent frames of a 3D VAE.

Frame alignment: a per-frame condition comes either per latent frame (``F'`` frames) or per pixel
frame (``F = 1 + r (F' - 1)`` with ``r`` the VAE's temporal compression, 4 for CogVideoX's VAE).
Pixel-frame conditions go through :class:`TemporalDownsample`, which groups frames as the causal
VAE does (latent frame 0 <- pixel frame 0; latent frame j <- pixel frames ``r (j - 1) + 1 .. r j``,
the first group padded by repeating frame 0, as the VAE's causal padding does) and maps each group
with a learned linear layer (MagicDrive-V2 [2411.13807v3] sec. 4.3: downsampling "aligned with the adopted 3D
VAE", which keeps each frame's information instead of repeating a reduced code).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive import geometry
from jaxdrive.attention import attention
from jaxdrive.models.embeddings import apply_rope, fourier_features, rope_1d, timestep_embedding
from jaxdrive.models.layers import MLP, AttnProj, Dense, LayerNorm, lookup
from jaxdrive.models.params import ZEROS, Init, normal, param
from jaxdrive.models.tokens import merge, split
from jaxdrive.parallel.rules import constrain
from jaxdrive.validate import check_trailing_shape


def frame_mode(name: str, frames: int, latent_frames: int, ratio: int) -> str:
    """``"latent"`` when a condition has ``latent_frames`` frames, ``"pixel"`` when it has
    ``1 + ratio (latent_frames - 1)``; otherwise ``ValueError`` naming the condition."""
    pixel = 1 + ratio * (latent_frames - 1)
    if frames == latent_frames:
        return "latent"
    if frames == pixel:
        return "pixel"
    raise ValueError(
        f"{name}: expected {latent_frames} (latent) or {pixel} (pixel) frames for "
        f"{latent_frames} latent frames, got {frames}"
    )


def group_frames(x, ratio: int, axis: int = 1):
    """``[..., F, ...]`` with ``F = 1 + r (F' - 1)`` -> ``[..., F', r, ...]``: the causal VAE's
    frame groups, the first padded by repeating frame 0."""
    first = jax.lax.slice_in_dim(x, 0, 1, axis=axis)
    padded = jnp.concatenate([first] * (ratio - 1) + [x], axis=axis)
    return split(padded, axis, padded.shape[axis] // ratio)


class TemporalDownsample(nn.Module):
    """Pixel-frame features ``[B, F, ..., D]`` -> latent-frame features ``[B, F', ..., D]``.

    Each causal group of ``ratio`` frames (see the module docstring) is concatenated along the
    features and mapped by one linear layer. ``mask [B, F, ...]`` (optional) becomes "any frame of
    the group valid"."""

    width: int
    ratio: int
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, x, mask=None):
        g = group_frames(x, self.ratio)  # [B, F', r, ..., D]
        g = jnp.moveaxis(g, 2, -2)  # [B, F', ..., r, D]
        y = Dense(self.width, ("channels", "embed"), dtype=self.dtype)(merge(g, g.ndim - 2))
        if mask is None:
            return y, None
        return y, jnp.any(group_frames(mask, self.ratio), axis=2)


class TimestepMLP(nn.Module):
    """Sinusoidal embedding then ``linear_2(silu(linear_1(.)))`` (DiT's timestep embedder; also
    Open-Sora's fps embedder and CogVideoX's ``TimestepEmbedding``)."""

    freq_dim: int
    out: int
    flip_sin_to_cos: bool = True
    shift: float = 0.0
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, t):
        e = timestep_embedding(t, self.freq_dim, flip_sin_to_cos=self.flip_sin_to_cos, shift=self.shift)
        init = normal(0.02)
        h = Dense(self.out, ("channels", "embed"), dtype=self.dtype, kernel_init=init, name="linear_1")(e)
        return Dense(self.out, ("mlp", "embed"), dtype=self.dtype, kernel_init=init, name="linear_2")(jax.nn.silu(h))


class FourierMLP(nn.Module):
    """MiLA [2503.15875v1] eq. 1: ``h_c = MLP(FFT(c))``, Fourier features of the raw parameters then a 2-layer MLP.
    ``zero_out``: the last layer starts at zero (a control added to a model trained without it)."""

    out: int
    num_freqs: int = 8
    temperature: float = 100.0
    dtype: jnp.dtype = jnp.float32
    zero_out: bool = False

    @nn.compact
    def __call__(self, c):
        f = fourier_features(c, self.num_freqs, self.temperature)
        h = Dense(self.out, ("channels", "embed"), dtype=self.dtype, name="fc1")(f)
        return Dense(
            self.out, ("mlp", "embed"), dtype=self.dtype, kernel_init=ZEROS if self.zero_out else None, name="fc2"
        )(jax.nn.silu(h))


def null_param(module: nn.Module, name: str, shape, names):
    """A learned null embedding (classifier-free guidance), initialised N(0, 1 / shape[-1])."""
    return param(module, name, normal(1.0 / np.sqrt(shape[-1])), shape, names)


def use_null(drop, value, null):
    """``value`` with the rows where ``drop [B]`` is True replaced by ``null`` (broadcast)."""
    if drop is None:
        return value
    d = jnp.asarray(drop, bool).reshape((-1,) + (1,) * (value.ndim - 1))
    return jnp.where(d, null.astype(value.dtype), value)


class EncoderLayer(nn.Module):
    """A pre-norm transformer layer (self-attention with an optional key mask and rotary tables,
    then an MLP) for the small condition encoders; ``axis_name`` is the logical name of the width."""

    width: int
    heads: int
    impl: str = "xla"
    dtype: jnp.dtype = jnp.float32
    axis_name: str = "embed"

    @nn.compact
    def __call__(self, x, mask=None, rope=None):
        name = self.axis_name
        proj = AttnProj(
            self.heads, self.width // self.heads, self.width, dtype=self.dtype, context_name=name, name="attn"
        )
        h = LayerNorm(name="norm1", name_=name)(x)
        q, (k, v) = proj.q(h), proj.kv(h)
        if rope is not None:
            q, k = apply_rope(q, *rope), apply_rope(k, *rope)
        x = x + proj.out(attention(q, k, v, impl=self.impl, kv_mask=mask))
        mlp = MLP(4 * self.width, self.width, dtype=self.dtype, in_name=name, name="mlp")
        return x + mlp(LayerNorm(name="norm2", name_=name)(x))


class TemporalEncoder(nn.Module):
    """A small pre-norm transformer over frames, per item, with RoPE over the frame index
    (MagicDrive-V2 [2411.13807v3] sec. 4.3: "a temporal transformer and RoPE"). ``x [B, F, *items, D]``,
    ``mask [B, F, *items]`` (False frames are not attended to)."""

    width: int
    layers: int
    heads: int
    impl: str = "xla"
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, x, mask=None):
        if self.layers == 0:
            return x
        f = x.shape[1]
        items = x.shape[2:-1]
        seq = jnp.moveaxis(x, 1, -2)  # [B, *items, F, D]
        m = None if mask is None else jnp.moveaxis(mask, 1, -1)
        for _ in range(len(items)):
            seq = merge(seq, 0)
            m = None if m is None else merge(m, 0)
        rope = tuple(jnp.asarray(a)[:, None, :] for a in rope_1d(np.arange(f), self.width // self.heads))
        for i in range(self.layers):
            seq = EncoderLayer(self.width, self.heads, self.impl, self.dtype, name=f"layer_{i}")(seq, m, rope)
        for size in reversed(items):
            seq = split(seq, 0, seq.shape[0] // size)
        return jnp.moveaxis(seq, -2, 1)


def align_frames(module, name, x, mask, latent_frames, ratio, width, dtype):
    """Per-frame features ``[B, Fc, ..., D]`` -> ``[B, F', ..., D]`` (downsampled when pixel-framed).
    The downsampling parameters exist either way (created at initialisation from one frame), so
    one model takes both kinds of input."""
    down = TemporalDownsample(width, ratio, dtype, name=f"{name}_down")
    if frame_mode(name, x.shape[1], latent_frames, ratio) == "latent":
        if module.is_initializing():
            down(x[:, :1])
        return x, mask
    return down(x, mask)


class CameraEncoder(nn.Module):
    """Per-view camera embedding ``[B, V, D]`` (MiLA [2503.15875v1] eq. 1): Fourier + MLP of the normalised
    intrinsics ``(fx / W, fy / H, cx / W, cy / H)`` and the camera-to-ego rotation and translation.

    Intrinsics are in pixels of the stored resolution, ``(H, W) = image_hw``; normalising makes the
    embedding independent of the resolution (a choice: MiLA does not say how it scales them)."""

    width: int
    num_freqs: int
    temperature: float
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, intrinsics, cam_to_ego, image_hw):
        h, w = image_hw
        k = intrinsics.astype(jnp.float32)
        params = jnp.stack([k[..., 0, 0] / w, k[..., 1, 1] / h, k[..., 0, 2] / w, k[..., 1, 2] / h], -1)
        pose = cam_to_ego[..., :3, :4].astype(jnp.float32).reshape(*cam_to_ego.shape[:-2], 12)
        return FourierMLP(self.width, self.num_freqs, self.temperature, self.dtype)(jnp.concatenate([params, pose], -1))


class _PerFrameFourier(nn.Module):
    """The fields of a per-frame Fourier + MLP encoder (MiLA [2503.15875v1] eq. 1) with the VAE's frame ratio."""

    width: int
    num_freqs: int
    temperature: float
    ratio: int
    dtype: jnp.dtype = jnp.float32


class WaypointEncoder(_PerFrameFourier):
    """Ego waypoints per frame ``[B, Fw, 2]`` -> ``[B, F', D]`` (MiLA [2503.15875v1] eq. 1), downsampled to latent
    frames when given per pixel frame."""

    @nn.compact
    def __call__(self, waypoints, latent_frames):
        h = FourierMLP(self.width, self.num_freqs, self.temperature, self.dtype)(waypoints)
        return align_frames(self, "waypoints", h, None, latent_frames, self.ratio, self.width, self.dtype)[0]


def latent_frame_times(frame_times, latent_frames: int, ratio: int):
    """Times ``[B, F]`` per pixel frame (``F = 1 + ratio (F' - 1)``) or per latent frame ->
    ``[B, F']``, relative to the first frame (a window cut from a longer clip gets the times of the
    same window alone). Latent frame j takes pixel frame ``ratio j``'s time: the newest frame of its
    causal group (:func:`group_frames`), the frame it has seen last."""
    t = jnp.asarray(frame_times, jnp.float32)
    t = t - t[:, :1]
    if frame_mode("frame_times", t.shape[1], latent_frames, ratio) == "pixel":
        t = group_frames(t, ratio)[:, :, -1]
    return t


class FrameTimeEncoder(_PerFrameFourier):
    """Each frame's time ``[B, Ft]`` (seconds, per pixel or latent frame) -> ``[B, F', D]``:
    Fourier + MLP (MiLA [2503.15875v1] eq. 1) of :func:`latent_frame_times`, the last layer zero-initialised
    (``Controls.frame_time``: mixed frame rates in one clip, MiLA [2503.15875v1] appendix B)."""

    @nn.compact
    def __call__(self, frame_times, latent_frames):
        t = latent_frame_times(frame_times, latent_frames, self.ratio)
        return FourierMLP(self.width, self.num_freqs, self.temperature, self.dtype, zero_out=True)(t[..., None])


class TrajectoryEncoder(nn.Module):
    """MagicDrive-V2's ego trajectory encoder: poses ``[B, Ft, 4, 4]`` (ego-to-world) -> each frame's
    pose relative to the first (sec. 3) -> Fourier + MLP of the 3 x 4 matrix ("an MLP for camera
    poses", sec. 4.3) -> temporal transformer with RoPE -> downsampled to ``[B, F', D]``."""

    width: int
    heads: int
    layers: int
    num_freqs: int
    temperature: float
    ratio: int
    impl: str = "xla"
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, ego_to_world, latent_frames):
        rel = geometry.relative_to_first(ego_to_world)[..., :3, :4]
        h = FourierMLP(self.width, self.num_freqs, self.temperature, self.dtype)(rel.reshape(*rel.shape[:-2], 12))
        h = TemporalEncoder(self.width, self.layers, self.heads, self.impl, self.dtype)(h)
        return align_frames(self, "trajectory", h, None, latent_frames, self.ratio, self.width, self.dtype)[0]


def box_visibility(corners_cam, intrinsics, image_hw, min_depth: float = 0.1):
    """Per-view visibility of boxes from their corners in camera coordinates ``[..., 8, 3]``:
    some corner lies at depth > ``min_depth`` and the image-space extent of those corners overlaps
    the image ``[0, W] x [0, H]``. A lenient test on purpose: a box that spans the view with all
    corners outside it (a bus passing close by) still counts as visible."""
    h, w = image_hw
    px, depth = geometry.project_to_image(corners_cam, intrinsics)
    front = depth > min_depth
    big = jnp.float32(1e9)
    u_lo = jnp.min(jnp.where(front, px[..., 0], big), -1)
    u_hi = jnp.max(jnp.where(front, px[..., 0], -big), -1)
    v_lo = jnp.min(jnp.where(front, px[..., 1], big), -1)
    v_hi = jnp.max(jnp.where(front, px[..., 1], -big), -1)
    return jnp.any(front, -1) & (u_hi >= 0) & (u_lo <= w) & (v_hi >= 0) & (v_lo <= h)


def box_corner_features(corners, box_range, num_freqs: int, temperature: float):
    """Corners ``[..., 8, 3]`` (metres) -> Fourier features ``[..., 24 (1 + 2 num_freqs)]``
    (:func:`jaxdrive.models.embeddings.fourier_features`) of the corners divided by ``box_range``
    (metres; None: raw metres), so a corner ``box_range`` away is 1 (``DiTConfig.box_range``)."""
    if box_range is not None and not (isinstance(box_range, (int, float)) and 0 < box_range < float("inf")):
        raise ValueError(f"box_range: expected a positive number of metres or None, got {box_range!r}")
    check_trailing_shape("corners", corners, (8, 3), "[..., 8, 3]")
    c = jnp.asarray(corners, jnp.float32)
    if box_range is not None:
        c = c / box_range
    return fourier_features(c.reshape(*c.shape[:-2], 24), num_freqs, temperature)


class BoxEncoder(nn.Module):
    """MagicDrive-V2's spatial-temporal box encoder (sec. 4.3, Fig. 4b).

    ``boxes [B, Fb, N, 7]`` (ego frame of their frame), ``classes [B, Fb, N]``, ``valid [B, Fb, N]``
    -> tokens ``[B, F', Vb, N, D]`` and mask ``[B, F', Vb, N]``, ``Vb`` = number of views with
    ``per_view`` (corners moved into each camera; a box invisible to a camera is padded and masked
    for that view, keeping one box sequence length across views and frames) else 1. Each box:
    Fourier features of its 8 corners concatenated with a class embedding, an MLP; then a temporal
    transformer with RoPE over the frames of each box; then downsampling to latent frames.
    ``box_range`` (metres; None: raw metres) divides the corners before their ``num_freqs``
    Fourier features (``DiTConfig.box_range``: MagicDrive min-max normalises its corners).
    """

    width: int
    heads: int
    layers: int
    num_classes: int
    num_freqs: int
    temperature: float
    ratio: int
    per_view: bool
    impl: str = "xla"
    dtype: jnp.dtype = jnp.float32
    box_range: float | None = None

    @nn.compact
    def __call__(self, boxes, classes, valid, latent_frames, intrinsics=None, cam_to_ego=None, image_hw=None):
        corners = geometry.box_corners(boxes)  # [B, Fb, N, 8, 3]
        valid = jnp.asarray(valid, bool)
        if self.per_view:
            pts = corners[:, :, None]  # [B, Fb, 1, N, 8, 3]
            flat = pts.reshape(*pts.shape[:3], -1, 3)
            cam = geometry.ego_to_camera(flat, cam_to_ego[:, None])  # [B, Fb, V, N*8, 3]
            coords = cam.reshape(*cam.shape[:3], corners.shape[2], 8, 3)
            vis = box_visibility(coords, intrinsics[:, None, :, None], image_hw)
            mask = valid[:, :, None] & vis  # [B, Fb, V, N]
        else:
            coords, mask = corners[:, :, None], valid[:, :, None]
        feats = box_corner_features(coords, self.box_range, self.num_freqs, self.temperature)
        table = param(self, "class_embed", normal(0.02), (self.num_classes, self.width), ("vocab", "embed"))
        table = constrain(table, (None, "embed"))  # whole table on every device for the lookup
        cls = lookup(table, jnp.clip(jnp.asarray(classes, jnp.int32), 0, self.num_classes - 1))
        cls = jnp.broadcast_to(cls[:, :, None], feats.shape[:-1] + (self.width,))
        h = Dense(self.width, ("channels", "embed"), dtype=self.dtype, name="fc1")(jnp.concatenate([feats, cls], -1))
        h = Dense(self.width, ("mlp", "embed"), dtype=self.dtype, name="fc2")(jax.nn.silu(h))
        h = h * mask[..., None]
        h = TemporalEncoder(self.width, self.layers, self.heads, self.impl, self.dtype)(h, mask)
        h, mask = align_frames(self, "boxes", h, mask, latent_frames, self.ratio, self.width, self.dtype)
        return h, mask


class Conv3x3(nn.Module):
    """3x3 convolution, NHWC, "same" padding, stride ``stride``; LeCun-normal kernel, zero bias."""

    features: int
    stride: int = 1
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, x):
        names = ("kernel", "kernel", "channels", "channels")
        w = param(self, "kernel", Init("lecun", fan_in_axes=3), (3, 3, x.shape[-1], self.features), names)
        y = jax.lax.conv_general_dilated(
            x.astype(self.dtype),
            w.astype(self.dtype),
            (self.stride,) * 2,
            "SAME",
            dimension_numbers=("NHWC", "HWIO", "NHWC"),
        )
        return y + param(self, "bias", ZEROS, (self.features,), ("channels",)).astype(self.dtype)


class MapEncoder(nn.Module):
    """The BEV map ``[B, Fm, Hm, Wm, C]`` -> control features ``[B, F', S, D]`` on the token grid
    ``(gh, gw)`` (MagicDrive-V2 [2411.13807v3] sec. 4.3, Fig. 4a: a conv encoder, then temporal downsampling with
    new parameters aligned with the VAE). Three stride-2 3x3 convolutions, a bilinear resize to
    the token grid, a linear map to the width, then :class:`TemporalDownsample`. The map is the
    same for every view; the ControlNet branch learns the view-specific use through its
    camera-conditioned blocks (as MagicDrive does)."""

    width: int
    hidden: int
    ratio: int
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, bev, latent_frames, grid_hw):
        b, fm = bev.shape[:2]
        x = merge(jnp.asarray(bev, jnp.float32), 0).astype(self.dtype)  # [B * Fm, Hm, Wm, C]
        conv = lambda n, s, name: Conv3x3(n, s, self.dtype, name=name)
        x = jax.nn.silu(conv(self.hidden, 1, "conv_in")(x))
        for i in range(3):
            x = jax.nn.silu(conv(self.hidden, 2, f"down_{i}")(x))
        x = jax.image.resize(x, (x.shape[0], *grid_hw, x.shape[-1]), "linear")
        x = Dense(self.width, ("channels", "embed"), dtype=self.dtype, name="proj")(x)
        x = merge(split(x, 0, b), 2)  # [B, Fm, S, D]
        return align_frames(self, "bev_map", x, None, latent_frames, self.ratio, self.width, self.dtype)[0]


class CaptionEncoder(nn.Module):
    """The built-in caption encoder: token ids ``[B, L]`` (from
    :func:`jaxdrive.data.text.tokenize_captions`) and ``mask [B, L]`` -> ``[B, L, dim]``.
    An embedding table, learned positions, ``layers`` pre-norm transformer layers, a final norm.
    Small and trained with the DiT, so that the synthetic default needs no external text model."""

    dim: int
    vocab: int
    max_len: int
    layers: int
    impl: str = "xla"
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, ids, mask):
        table = constrain(
            param(self, "embed", normal(0.02), (self.vocab, self.dim), ("vocab", "text_embed")), (None, "text_embed")
        )
        pos = param(self, "pos", normal(0.02), (self.max_len, self.dim), ("text_tokens", "text_embed"))
        ids = jnp.clip(jnp.asarray(ids, jnp.int32), 0, self.vocab - 1)
        x = (lookup(table, ids) + pos[: ids.shape[1]]).astype(self.dtype)
        heads = self.dim // 64 if self.dim % 64 == 0 else 1
        for i in range(self.layers):
            x = EncoderLayer(self.dim, heads, self.impl, self.dtype, "text_embed", name=f"layer_{i}")(x, mask)
        return LayerNorm(name="norm_out", name_="text_embed")(x)
