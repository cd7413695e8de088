"""The 3D causal video VAE (CogVideoX architecture), with flat memory for minute-long videos.

``CausalVAE(config)`` holds no parameters: ``vae.init(key)`` makes them, ``vae.encode(params,
video)`` returns the posterior mean and ``vae.decode(params, latents)`` the video, all jitted.

Layouts (channels-last): ``video [B, F, H, W, 3]`` or ``[B, V, F, H, W, 3]`` in [-1, 1] (views are
folded into the batch, which is sharded over ``data``/``fsdp`` under a mesh); unscaled latents
``[B, (V,) F', h, w, C]``. With the default ``temporal_compression = 4``, ``F = 1 + 4k`` frames give
``F' = 1 + k`` latent frames; ``h = H / s``, ``w = W / s`` with ``s = 2 ** (len(block_out_channels) - 1)``.
The scaling factor is exposed (:meth:`CausalVAE.scale_latents`), never applied by encode/decode.

Modes (``config.mode``, or the ``mode=`` argument):

- ``"chunked"`` (default): CogVideoX's released weights are used with diffusers' chunking, so
  this is the numerically faithful mode. Encoding takes ``encode_chunk_frames`` (8) frames at a
  time and decoding ``decode_chunk_latents`` (2) latent frames, the remainder joining the first
  chunk; each causal convolution's last input frames carry over to the next chunk (the *cache*).
  The chunks after the first run in one ``lax.fori_loop`` that writes into the output in place, so
  temporary memory does not grow with the video length.
- ``"whole"``: the whole clip in one pass. GroupNorm takes its statistics over time, so this
  differs from ``"chunked"`` (on the order of 0.1-0.3 on a random model).
- ``"frame_wise"``: every frame is its own one-frame clip (LongDWM's Coarse DiT), ``F -> F``.
  All frames of all clips go through at once, or, with ``frame_wise_batch`` k, k frames of every
  clip at a time in a ``lax.map``, so the temporaries are those of k frames (MiLA's step encodes
  4 clips x 6 views x 16 frames per device on the fly: 126 GiB at once). Equal either way.

In every mode ``clip_batch`` k codes the clips (each view of a clip is one) k of every device
at a time in a ``lax.map``, so the temporaries are those of k clips a device (MagicDrive-V2's
stage 3 encodes 3 clips x 6 views of 9 frames at 848 x 1600 per device on the fly: 105 GiB a
convolution activation at once). Equal either way.

A video generated part by part decodes as its latents come, equal to the whole-clip decode, with
:mod:`jaxdrive.models.vae.stream` (``"chunked"`` and ``"frame_wise"`` only).

Spatial tiling (``config.tiling`` or ``tiled=``) follows diffusers' ``tiled_encode`` /
``tiled_decode``: overlapping tiles of ``tile_sample_height x tile_sample_width`` pixels, blended
linearly over the overlap, for resolutions whose activations do not fit at once.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive import validate
from jaxdrive.models.layers import GroupNorm
from jaxdrive.models.params import abstract_params, host_params_for_key
from jaxdrive.models.tokens import merge, split
from jaxdrive.models.vae import layers as L
from jaxdrive.parallel.mesh import entry_axes, spec_of
from jaxdrive.parallel.rules import constrain, logical_to_spec

MODES = ("chunked", "whole", "frame_wise")


@dataclasses.dataclass(frozen=True)
class VAEConfig:
    """Architecture and inference settings; the defaults are CogVideoX-2B's VAE."""

    in_channels: int = 3
    out_channels: int = 3
    block_out_channels: tuple[int, ...] = (128, 256, 256, 512)
    layers_per_block: int = 3
    latent_channels: int = 16
    norm_num_groups: int = 32
    norm_eps: float = 1e-6
    temporal_compression: int = 4
    scaling_factor: float = 1.15258426
    shift_factor: float = 0.0
    mode: str = "chunked"
    encode_chunk_frames: int = 8
    decode_chunk_latents: int = 2
    frame_wise_batch: int = 0  # frame_wise mode: frames of each clip per lax.map step (0: all at once)
    clip_batch: int = 0  # clips (x views) each device codes per lax.map step (0: all at once)
    tiling: bool = False
    tile_sample_height: int = 240
    tile_sample_width: int = 360
    tile_overlap_height: float = 1 / 6
    tile_overlap_width: float = 1 / 5
    dtype: str = "float32"  # compute dtype; params are always float32

    def __post_init__(self):
        object.__setattr__(self, "block_out_channels", tuple(int(c) for c in self.block_out_channels))
        for name in (
            "in_channels",
            "out_channels",
            "layers_per_block",
            "latent_channels",
            "norm_num_groups",
            "temporal_compression",
            "encode_chunk_frames",
            "decode_chunk_latents",
            "tile_sample_height",
            "tile_sample_width",
        ):
            validate.check_positive_int(name, getattr(self, name))
        if not self.block_out_channels:
            raise ValueError("block_out_channels: expected at least one block, got ()")
        for c in self.block_out_channels:
            if c % self.norm_num_groups:
                raise ValueError(
                    f"block_out_channels: expected multiples of norm_num_groups "
                    f"{self.norm_num_groups}, got {list(self.block_out_channels)}"
                )
        levels = math.log2(self.temporal_compression)
        if levels != int(levels) or levels > len(self.block_out_channels) - 1:
            raise ValueError(
                f"temporal_compression: expected a power of 2 up to "
                f"{2 ** (len(self.block_out_channels) - 1)} (one level per downsampling "
                f"block), got {self.temporal_compression}"
            )
        if (
            isinstance(self.frame_wise_batch, bool)
            or not isinstance(self.frame_wise_batch, int)
            or self.frame_wise_batch < 0
        ):
            raise ValueError(
                f"frame_wise_batch: expected frames per step >= 0 (0: all at once), got {self.frame_wise_batch!r}"
            )
        if isinstance(self.clip_batch, bool) or not isinstance(self.clip_batch, int) or self.clip_batch < 0:
            raise ValueError(
                f"clip_batch: expected clips per device and step >= 0 (0: all at once), got {self.clip_batch!r}"
            )
        if self.encode_chunk_frames % self.temporal_compression:
            raise ValueError(
                f"encode_chunk_frames: expected a multiple of temporal_compression "
                f"{self.temporal_compression}, got {self.encode_chunk_frames}"
            )
        validate.check_choice("mode", self.mode, MODES)
        validate.check_choice("dtype", self.dtype, ("float32", "bfloat16", "float16"))
        validate.check_range("tile_overlap_height", self.tile_overlap_height, 0, 1, hi_open=True)
        validate.check_range("tile_overlap_width", self.tile_overlap_width, 0, 1, hi_open=True)

    @property
    def spatial_compression(self) -> int:
        return 2 ** (len(self.block_out_channels) - 1)

    def tile_geometry(self, axis: str) -> dict:
        """diffusers' tile arithmetic for one axis (kept verbatim: it decides tile boundaries).

        Raises ``ValueError`` for a tile size and overlap whose strides in pixels and in latents
        disagree: the blended tiles, cropped to their stride, would not tile the frame."""
        sample = getattr(self, f"tile_sample_{axis}")
        overlap = getattr(self, f"tile_overlap_{axis}")
        latent = int(sample / self.spatial_compression)
        geo = dict(
            tile_sample=sample,
            tile_latent=latent,
            encode_stride=int(sample * (1 - overlap)),
            encode_blend=int(latent * overlap),
            encode_keep=latent - int(latent * overlap),
            decode_stride=int(latent * (1 - overlap)),
            decode_blend=int(sample * overlap),
            decode_keep=sample - int(sample * overlap),
        )
        s = self.spatial_compression
        if (
            min(geo["tile_latent"], geo["encode_stride"], geo["decode_stride"]) < 1
            or geo["encode_keep"] * s != geo["encode_stride"]
            or geo["decode_keep"] != geo["decode_stride"] * s
        ):
            raise ValueError(
                f"tile_overlap_{axis}: expected a tile size and overlap whose strides agree in "
                f"pixels and latents (spatial compression {s}), got tile_sample_{axis} = "
                f"{sample} and tile_overlap_{axis} = {overlap}"
            )
        return geo


class Encoder3D(nn.Module):
    """Video ``[N, T, H, W, Cin]`` -> posterior moments ``[N, T', h, w, 2 C]`` (mean, log-variance)."""

    config: VAEConfig

    @nn.compact
    def __call__(self, x, cache=None):
        c, dtype = self.config, jnp.dtype(self.config.dtype)
        cache = cache or {}
        new = {}
        levels = int(math.log2(c.temporal_compression))
        h, new["conv_in"] = L.CausalConv3d(c.block_out_channels[0], dtype=dtype, name="conv_in")(
            x, cache.get("conv_in")
        )
        for i, width in enumerate(c.block_out_channels):
            for j in range(c.layers_per_block):
                key = f"down_blocks_{i}/resnets_{j}"
                h, new[key] = L.ResnetBlock3D(
                    width, c.norm_num_groups, c.norm_eps, dtype=dtype, name=key.replace("/", "_")
                )(h, cache=cache.get(key))
            if i < len(c.block_out_channels) - 1:
                h = L.Downsample3D(
                    width, compress_time=i < levels, dtype=dtype, name=f"down_blocks_{i}_downsamplers_0"
                )(h)
        for j in range(2):
            key = f"mid_block/resnets_{j}"
            h, new[key] = L.ResnetBlock3D(
                c.block_out_channels[-1], c.norm_num_groups, c.norm_eps, dtype=dtype, name=key.replace("/", "_")
            )(h, cache=cache.get(key))
        h = nn.silu(GroupNorm(c.norm_num_groups, 1e-6, name="norm_out")(h))
        h, new["conv_out"] = L.CausalConv3d(2 * c.latent_channels, dtype=dtype, name="conv_out")(
            h, cache.get("conv_out")
        )
        return h, new


class Decoder3D(nn.Module):
    """Latents ``[N, T', h, w, C]`` -> video ``[N, T, H, W, Cout]``; every norm after the first
    convolution is conditioned on the latents (SpatialNorm3D). Without a cache the chunk starts
    the video, and its frame 0 is decoded as an image (see :class:`Upsample3D`)."""

    config: VAEConfig

    @nn.compact
    def __call__(self, z, cache=None):
        c, dtype = self.config, jnp.dtype(self.config.dtype)
        cache = cache or {}
        new = {}
        levels = int(math.log2(c.temporal_compression))
        widths = c.block_out_channels[::-1]
        h, new["conv_in"] = L.CausalConv3d(widths[0], dtype=dtype, name="conv_in")(z, cache.get("conv_in"))
        resnet = functools.partial(
            L.ResnetBlock3D, groups=c.norm_num_groups, eps=c.norm_eps, spatial_norm=True, dtype=dtype
        )
        for j in range(2):
            key = f"mid_block/resnets_{j}"
            h, new[key] = resnet(widths[0], name=key.replace("/", "_"))(h, z, cache.get(key))
        for i, width in enumerate(widths):
            for j in range(c.layers_per_block + 1):
                key = f"up_blocks_{i}/resnets_{j}"
                h, new[key] = resnet(width, name=key.replace("/", "_"))(h, z, cache.get(key))
            if i < len(widths) - 1:
                h = L.Upsample3D(width, compress_time=i < levels, dtype=dtype, name=f"up_blocks_{i}_upsamplers_0")(
                    h, first_chunk=not cache
                )
        h = nn.silu(L.SpatialNorm3D(c.norm_num_groups, 1e-6, dtype, name="norm_out")(h, z))
        h, new["conv_out"] = L.CausalConv3d(c.out_channels, dtype=dtype, name="conv_out")(h, cache.get("conv_out"))
        return h, new


def chunk_plan(total: int, size: int) -> tuple[int, int]:
    """diffusers' temporal chunking: ``(first chunk length, number of further chunks of size)``;
    the remainder ``total % size`` joins the first chunk."""
    n = max(total // size, 1)
    return (total if n == 1 else size + total % size), n - 1


def _run_chunks(apply, x, size: int):
    """``apply(chunk, cache) -> (y, cache)`` over time chunks of ``x [N, T, ...]``, cache threaded.

    The first chunk (which holds the remainder) runs on its own; the others run in one
    ``fori_loop`` that writes each output into a preallocated buffer in place."""
    first, rest = chunk_plan(x.shape[1], size)
    y0, cache = apply(x[:, :first], None)
    if rest == 0:
        return y0
    step = jax.eval_shape(apply, x[:, first : first + size], cache)[0].shape[1]
    # padding y0 gives the buffer y0's sharding: a fresh jnp.zeros would be unsharded, and under
    # an Explicit mesh the loop's batch-sharded chunks could not be written into it
    out = jnp.pad(y0, [(0, 0), (0, rest * step)] + [(0, 0)] * (y0.ndim - 2))

    def body(i, carry):
        out, cache = carry
        y, cache = apply(jax.lax.dynamic_slice_in_dim(x, first + i * size, size, axis=1), cache)
        return jax.lax.dynamic_update_slice_in_dim(out, y, y0.shape[1] + i * step, axis=1), cache

    return jax.lax.fori_loop(0, rest, body, (out, cache))[0]


def _blend(a, b, extent: int, axis: int):
    """diffusers' blend_v / blend_h: the first ``extent`` rows (columns) of ``b`` fade in from the
    last ones of ``a``."""
    extent = min(a.shape[axis], b.shape[axis], extent)
    if extent == 0:
        return b
    w = jnp.asarray(np.arange(extent) / extent, b.dtype)
    w = w.reshape([-1 if d == axis else 1 for d in range(b.ndim)])
    head = (
        jax.lax.slice_in_dim(a, a.shape[axis] - extent, a.shape[axis], axis=axis) * (1 - w)
        + jax.lax.slice_in_dim(b, 0, extent, axis=axis) * w
    )
    return jnp.concatenate([head, jax.lax.slice_in_dim(b, extent, b.shape[axis], axis=axis)], axis=axis)


def tiled_apply(apply, x, geo_h: dict, geo_w: dict, kind: str, caches=None):
    """Run ``apply`` on overlapping spatial tiles of ``x [N, T, H, W, C]`` and blend them, in
    diffusers' order: each tile is blended with the already-blended tiles above and to its left.

    Tiles of one shape (interior, right edge, bottom edge, corner) go through one ``lax.map``:
    one tile at a time, as tiling is for memory, and one compilation per shape.

    With ``caches`` (a streaming decode, :mod:`jaxdrive.models.vae.stream`): ``apply(tile, cache)
    -> (y, cache)`` and every tile keeps its own causal cache, ``{tile shape: caches stacked over
    the tiles of that shape}`` (``{}`` for the first chunk); returns ``(video, new caches)``."""
    size_h = geo_h["tile_sample"] if kind == "encode" else geo_h["tile_latent"]
    size_w = geo_w["tile_sample"] if kind == "encode" else geo_w["tile_latent"]
    rows = range(0, x.shape[2], geo_h[f"{kind}_stride"])
    cols = range(0, x.shape[3], geo_w[f"{kind}_stride"])
    groups: dict[tuple[int, int], list] = {}
    for i in rows:
        for j in cols:
            shape = (min(size_h, x.shape[2] - i), min(size_w, x.shape[3] - j))
            groups.setdefault(shape, []).append((i, j))
    out, new_caches = {}, {}
    for (h, w), starts in groups.items():
        tiles = jnp.stack([x[:, :, i : i + h, j : j + w] for i, j in starts])
        if caches is None:
            results = jax.lax.map(apply, tiles)
        else:
            results, new_caches[(h, w)] = jax.lax.map(lambda a: apply(*a), (tiles, caches.get((h, w))))
        out.update({start: results[g] for g, start in enumerate(starts)})
    grid = [[out[(i, j)] for j in cols] for i in rows]
    mosaic = []
    for r, row in enumerate(grid):
        for c in range(len(row)):
            if r > 0:
                row[c] = _blend(grid[r - 1][c], row[c], geo_h[f"{kind}_blend"], axis=2)
            if c > 0:
                row[c] = _blend(row[c - 1], row[c], geo_w[f"{kind}_blend"], axis=3)
        mosaic.append(jnp.concatenate([t[:, :, : geo_h[f"{kind}_keep"], : geo_w[f"{kind}_keep"]] for t in row], axis=3))
    video = jnp.concatenate(mosaic, axis=2)
    return video if caches is None else (video, new_caches)


@dataclasses.dataclass(frozen=True)
class CausalVAE:
    """The VAE's functions over explicit ``params`` (see the module docstring)."""

    config: VAEConfig = VAEConfig()

    # ---------------------------------------------------------------- parameters
    def init(self, key, *, boxed: bool = False):
        """Fresh parameters ``{"encoder": ..., "decoder": ...}``, drawn on the host seeded by
        ``key`` (:func:`jaxdrive.models.params.host_params_for_key`: nothing random is compiled).
        ``boxed=True`` keeps flax's logical-axis metadata, for
        :func:`jaxdrive.parallel.param_shardings`."""
        c = self.config
        s = c.spatial_compression
        video = jnp.zeros((1, 1, s, s, c.in_channels), jnp.float32)
        latent = jnp.zeros((1, 1, 1, 1, c.latent_channels), jnp.float32)
        parts = {"encoder": abstract_params(Encoder3D(c), video), "decoder": abstract_params(Decoder3D(c), latent)}
        return host_params_for_key(key, parts, boxed=boxed)

    # ---------------------------------------------------------------- shapes
    def latent_frames(self, frames: int) -> int:
        """Latent frames for ``frames`` input frames in the configured mode."""
        if self.config.mode == "frame_wise":
            return frames
        return 1 + (frames - 1) // self.config.temporal_compression

    def video_frames(self, latent_frames: int) -> int:
        if self.config.mode == "frame_wise":
            return latent_frames
        return 1 + (latent_frames - 1) * self.config.temporal_compression

    def scale_latents(self, z):
        """Latents as the diffusion model sees them: ``(z - shift_factor) * scaling_factor``."""
        return (z - self.config.shift_factor) * self.config.scaling_factor

    def unscale_latents(self, z):
        return z / self.config.scaling_factor + self.config.shift_factor

    # ---------------------------------------------------------------- checks
    def _check(self, name, x, channels, *, pixels: bool, mode: str):
        c = self.config
        validate.check_ndim(name, x, (5, 6))
        if not jnp.issubdtype(jnp.result_type(x), jnp.floating):
            raise ValueError(f"{name}: expected a floating dtype, got {jnp.result_type(x)}")
        if x.shape[-1] != channels:
            raise ValueError(f"{name}: expected {channels} channels in the last axis, got shape {list(x.shape)}")
        frames = x.shape[-4]
        if pixels:
            s = c.spatial_compression
            if x.shape[-3] % s or x.shape[-2] % s:
                raise ValueError(
                    f"{name}: expected height and width divisible by the spatial "
                    f"compression {s}, got {x.shape[-3]} x {x.shape[-2]}"
                )
            r = c.temporal_compression
            if mode != "frame_wise" and (frames - 1) % r:
                raise ValueError(
                    f"{name}: expected 1 + {r}k frames, got {frames} (pad or trim the clip, or use mode='frame_wise')"
                )
            validate.check_range(name, x, -1.0, 1.0)
        if frames < 1:
            raise ValueError(f"{name}: expected at least one frame, got shape {list(x.shape)}")

    def _resolve(self, mode, tiled):
        mode = self.config.mode if mode is None else mode
        validate.check_choice("mode", mode, MODES)
        return mode, self.config.tiling if tiled is None else bool(tiled)

    # ---------------------------------------------------------------- encode / decode
    def posterior(self, params, video, *, mode: str | None = None, tiled: bool | None = None):
        """``(mean, logvar)`` of the diagonal Gaussian posterior, each ``[B, (V,) F', h, w, C]``."""
        mode, tiled = self._resolve(mode, tiled)
        self._check("video", video, self.config.in_channels, pixels=True, mode=mode)
        return _posterior(self, params, video, mode, tiled)

    def encode(self, params, video, *, mode: str | None = None, tiled: bool | None = None):
        """The posterior mean (unscaled latents) of ``video [B, (V,) F, H, W, 3]`` in [-1, 1]."""
        return self.posterior(params, video, mode=mode, tiled=tiled)[0]

    def decode(self, params, latents, *, mode: str | None = None, tiled: bool | None = None):
        """Video ``[B, (V,) F, H, W, 3]`` from unscaled ``latents [B, (V,) F', h, w, C]``."""
        mode, tiled = self._resolve(mode, tiled)
        self._check("latents", latents, self.config.latent_channels, pixels=False, mode=mode)
        return _decode(self, params, latents, mode, tiled)

    # ---------------------------------------------------------------- internals
    def _run(self, kind: str, params, x, mode: str, tiled: bool):
        """Encoder (``kind="encode"``: ``[N, F, H, W, Cin] -> [N, F', h, w, 2C]`` moments) or
        decoder (``"decode"``: ``[N, F', h, w, C] -> [N, F, H, W, Cout]``) in the given mode."""
        c = self.config
        module, chunk, tile_key = (
            (Encoder3D(c), c.encode_chunk_frames, "tile_sample")
            if kind == "encode"
            else (Decoder3D(c), c.decode_chunk_latents, "tile_latent")
        )
        if mode == "frame_wise" and 0 < c.frame_wise_batch < x.shape[1]:
            return self._frame_groups(kind, params, x, tiled)
        if mode == "frame_wise":
            # one merge / split at a time: under an Explicit mesh the clips' axis stays sharded
            out = self._run(kind, params, merge(x, 0)[:, None], "whole", tiled)
            return split(out[:, 0], 0, x.shape[0])
        weights = {"params": params["encoder" if kind == "encode" else "decoder"]}
        apply = lambda t, cache: module.apply(weights, t, cache)
        run = (lambda t: apply(t, None)[0]) if mode == "whole" else (lambda t: _run_chunks(apply, t, chunk))
        geo = self._tiles(x, tile_key, tiled)
        return run(x) if geo is None else tiled_apply(run, x, *geo, kind)

    def _frame_groups(self, kind: str, params, x, tiled: bool):
        """Frame-wise ``x [N, F, ...]`` in groups of ``frame_wise_batch`` k frames of every clip, one
        group per ``lax.map`` step (the remainder a step of its own): the temporaries of k frames.
        The groups are a leading axis split off the frames, not a vmap, so the clips' axis keeps
        its sharding under an Explicit mesh."""
        k = self.config.frame_wise_batch
        n, frames = x.shape[:2]
        g = frames // k
        each = lambda t: self._run(kind, params, t, "frame_wise", tiled)  # t [N, k, ...]: all at once
        groups = jnp.moveaxis(x[:, : g * k], 1, 0).reshape(g, k, n, *x.shape[2:])
        out = jax.lax.map(lambda t: jnp.moveaxis(each(jnp.moveaxis(t, 0, 1)), 1, 0), groups)  # [g, k, N, ...]
        out = jnp.moveaxis(out.reshape(g * k, *out.shape[2:]), 0, 1)
        return out if frames == g * k else jnp.concatenate([out, each(x[:, g * k :])], axis=1)

    def _coded(self, kind: str, params, x, mode: str, tiled: bool):
        """:meth:`_run` on folded clips ``x [N, ...]``, ``clip_batch`` clips of every device per
        ``lax.map`` step (:func:`_clip_groups`): the temporaries of that share. The device axis
        stays the major factor of every reshape, so the clips' sharding holds."""
        groups = _clip_groups(x.shape[0], self.config.clip_batch)
        if groups is None:
            return self._run(kind, params, x, mode, tiled)
        shards, steps = groups
        n = x.shape[0]
        per = n // (shards * steps)
        each = lambda t: self._run(kind, params, t, mode, tiled)
        entry = spec_of(x)[0]  # the clips' mesh axes, stated at each reshape (below)
        batches = jnp.moveaxis(
            _reshape(x, (shards, steps, per, *x.shape[1:]), 0, entry), 1, 0
        )  # [steps, shards, per, ...]
        batches = _reshape(batches, (steps, shards * per, *x.shape[1:]), 1, entry)
        out = jax.lax.map(each, batches)  # [steps, shards * per, ...]
        out = jnp.moveaxis(_reshape(out, (steps, shards, per, *out.shape[2:]), 1, entry), 0, 1)
        return _reshape(out, (n, *out.shape[3:]), 0, entry)

    def _tiles(self, x, tile_key: str, tiled: bool) -> tuple[dict, dict] | None:
        """``(geometry of height, of width)`` when ``x [N, T, H, W, C]`` is tiled, else None: with
        tiling on, a frame larger than one tile (``tile_key``: "tile_sample" or "tile_latent")."""
        if not tiled:
            return None
        geo_h, geo_w = self.config.tile_geometry("height"), self.config.tile_geometry("width")
        return (geo_h, geo_w) if x.shape[2] > geo_h[tile_key] or x.shape[3] > geo_w[tile_key] else None


def _reshape(x, shape: tuple, axis: int, entry):
    """``x.reshape(shape)`` with output axis ``axis`` sharded over ``entry`` (a spec entry; None:
    unsharded, no mesh). JAX infers the output sharding of most splits and merges, but not where
    size-1 axes sit beside the split axis (one clip a device and step, one frame a clip: the
    image buckets of MagicDrive-V2's first stage), which it refuses under an Explicit mesh."""
    if entry is None:
        return x.reshape(shape)
    spec = [None] * len(shape)
    spec[axis] = entry
    return jax.lax.reshape(x, shape, out_sharding=jax.sharding.PartitionSpec(*spec))


def _clip_groups(n: int, clip_batch: int) -> tuple[int, int] | None:
    """``(shards, steps)`` for ``n`` folded clips coded ``clip_batch`` per device and step: the
    devices the batch axes split them over (the mesh set by ``jax.set_mesh``; 1 without) and the
    steps, each taking the largest divisor of a device's count up to ``clip_batch``. None when
    one step holds them all."""
    if clip_batch <= 0:
        return None
    mesh, shards = jax.sharding.get_abstract_mesh(), 1
    if mesh is not None and not mesh.empty:
        spec = logical_to_spec(("batch",), shape=(n,), mesh=mesh)
        sizes = dict(zip(mesh.axis_names, mesh.axis_sizes))
        shards = math.prod(sizes[a] for a in entry_axes(spec[0])) if len(spec) else 1
    per = n // shards
    k = max(d for d in range(1, min(clip_batch, per) + 1) if per % d == 0)
    return None if k >= per else (shards, per // k)


def fold_views(x):
    """``[B, V, F, ...] -> [B * V, F, ...]`` (batch sharded over data/fsdp), and the unfold."""
    if x.ndim == 5:
        return constrain(x, ("batch", None, None, None, None)), lambda y: y
    b, v = x.shape[:2]
    folded = constrain(x.reshape(b * v, *x.shape[2:]), ("batch", None, None, None, None))
    return folded, lambda y: y.reshape(b, v, *y.shape[1:])


@functools.partial(jax.jit, static_argnums=(0, 3, 4))
def _posterior(vae: CausalVAE, params, video, mode: str, tiled: bool):
    x, unfold = fold_views(video)
    moments = vae._coded("encode", params, x, mode, tiled).astype(jnp.float32)
    c = vae.config.latent_channels
    mean, logvar = moments[..., :c], jnp.clip(moments[..., c:], -30.0, 20.0)
    return unfold(mean), unfold(logvar)


@functools.partial(jax.jit, static_argnums=(0, 3, 4))
def _decode(vae: CausalVAE, params, latents, mode: str, tiled: bool):
    z, unfold = fold_views(latents)
    return unfold(vae._coded("decode", params, z, mode, tiled).astype(jnp.float32))
