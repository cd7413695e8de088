"""Streaming decode: latents pushed part by part, each video frame returned as soon as it is final,
the whole equal to a decode of the whole clip.

    dec = codec.stream_decoder(total_latent_frames)
    for part in parts:                        # scaled latents [B, V, n, h, w, C], as the DiT makes them
        write(dec.push(part))                 # NumPy [B, V, m, H, W, 3] in [-1, 1]; m may be 0
    write(dec.flush())                        # checks that every latent frame came; returns the rest

- ``space_to_depth`` codec and the VAE's ``"frame_wise"`` mode: frame-wise, every pushed part
  decodes at once (one compilation per distinct part length).
- VAE ``"chunked"`` mode: diffusers' chunk boundaries depend on the clip length (the remainder
  joins the *first* chunk, :func:`jaxdrive.models.vae.model.chunk_plan`), so the decoder takes the
  total up front, buffers pushed latents on the host until a chunk is complete and decodes exactly
  the chunks of the whole-clip pass, threading :class:`Decoder3D`'s causal cache from one chunk to
  the next (the first chunk without a cache, as :func:`jaxdrive.models.vae.model._run_chunks`). One
  jitted function, traced twice (first chunk, steady chunk) whatever the length; the cache has a
  fixed size and decoded frames go to the host, so device memory does not grow with the video.
  With spatial tiling on and frames larger than a tile, every tile keeps its own cache and the
  tiles are blended per chunk as :func:`jaxdrive.models.vae.model.tiled_apply` does: the same video as the
  whole-clip tiled decode.
- VAE ``"whole"`` mode cannot stream (its GroupNorm statistics span the whole clip): rejected.

Latents are read to the host (``np.asarray``) while they wait for their chunk: a single-process
decode, as writing an mp4 is.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive import validate
from jaxdrive.models.vae.model import Decoder3D, chunk_plan, fold_views, tiled_apply

STREAMING_MODES = ("chunked", "frame_wise")


@functools.partial(jax.jit, static_argnums=(0,))
def _decode_chunk(vae, params, latents, cache):
    """One chunk of scaled ``latents [B, V, n, h, w, C]`` -> (video clipped to [-1, 1], cache);
    ``cache=None`` starts the video (its frame 0 is decoded as an image)."""
    z, unfold = fold_views(vae.unscale_latents(latents))
    weights = {"params": params["decoder"]}
    apply = lambda t, k: Decoder3D(vae.config).apply(weights, t, k)
    geo = vae._tiles(z, "tile_latent", vae.config.tiling)
    y, cache = apply(z, cache) if geo is None else tiled_apply(apply, z, *geo, "decode", caches=cache or {})
    return jnp.clip(unfold(y.astype(jnp.float32)), -1.0, 1.0), cache


class StreamDecoder:
    """Decodes a clip of ``total_latent_frames`` latent frames pushed in parts (module docstring).

    Made by :meth:`jaxdrive.models.latents.LatentCodec.stream_decoder`."""

    def __init__(self, codec, total_latent_frames: int):
        self.total = validate.check_positive_int("total_latent_frames", total_latent_frames)
        vae = codec.vae
        if vae is not None and vae.config.mode not in STREAMING_MODES:
            raise ValueError(
                f"latents.vae_mode: expected one of {list(STREAMING_MODES)} for a streaming "
                f"decode (the 'whole' mode's GroupNorm takes its statistics over the whole "
                f"clip), got {vae.config.mode!r}"
            )
        self.codec = codec
        self.chunked = vae is not None and vae.config.mode == "chunked"
        if self.chunked:
            self._first, _ = chunk_plan(self.total, vae.config.decode_chunk_latents)
        self.pushed = 0  # latent frames received
        self._pending: list[np.ndarray] = []
        self._cache = None
        self._shape: tuple[int, int, int, int, int] | None = None  # [B, V, h, w, C] of the first part
        self._flushed = False

    def push(self, latents) -> np.ndarray:
        """Scaled ``latents [B, V, n, h, w, C]`` (the next ``n`` latent frames) -> the video frames
        ``[B, V, m, H, W, 3]`` (NumPy float32, clipped to [-1, 1]) that are final now."""
        if self._flushed:
            raise ValueError(f"latents: expected no push after flush(), got a part of shape {list(np.shape(latents))}")
        self._check(latents)
        n = np.shape(latents)[2]
        self.pushed += n
        if not self.chunked:
            return self._empty() if n == 0 else _to_host(self.codec.decode(self.codec.params, latents))
        self._pending.append(np.asarray(latents, np.float32))
        out = []
        while sum(p.shape[2] for p in self._pending) >= self._chunk_len():
            out.append(self._decode_next())
        return np.concatenate(out, axis=2) if out else self._empty()

    def flush(self) -> np.ndarray:
        """The frames not returned yet (none: every chunk decodes as soon as it is complete);
        raises unless all ``total_latent_frames`` were pushed. The decoder is finished after it."""
        if self.pushed != self.total:
            raise ValueError(
                f"total_latent_frames: expected all {self.total} latent frames pushed before flush(), got {self.pushed}"
            )
        self._flushed, self._cache = True, None
        return self._empty()

    # ---------------------------------------------------------------- internals
    def _chunk_len(self) -> int:
        return self.codec.vae.config.decode_chunk_latents if self._cache is not None else self._first

    def _decode_next(self) -> np.ndarray:
        buffered = np.concatenate(self._pending, axis=2)
        size = self._chunk_len()
        chunk, rest = buffered[:, :, :size], buffered[:, :, size:]
        self._pending = [rest] if rest.shape[2] else []
        video, self._cache = _decode_chunk(self.codec.vae, self.codec.params, chunk, self._cache)
        return _to_host(video)

    def _check(self, latents):
        validate.check_ndim("latents", latents, 6)
        if not np.issubdtype(np.result_type(latents), np.floating):
            raise ValueError(f"latents: expected a floating dtype, got {np.result_type(latents)}")
        shape = list(np.shape(latents))
        b, v, n, h, w, c = shape
        if self._shape is None:
            if c != self.codec.channels:
                raise ValueError(
                    f"latents: expected {self.codec.channels} channels in the last axis, got shape {shape}"
                )
            self._shape = (b, v, h, w, c)
        else:
            validate.check_shape("latents", latents, (*self._shape[:2], None, *self._shape[2:]))
        if n > self.total - self.pushed:
            raise ValueError(
                f"latents: expected at most {self.total - self.pushed} more latent frames "
                f"(total_latent_frames = {self.total}, {self.pushed} pushed), got {n}"
            )

    def _empty(self) -> np.ndarray:
        assert self._shape is not None  # set by the first push; flush() follows every frame pushed
        b, v, h, w, _ = self._shape
        s = self.codec.spatial
        return np.zeros((b, v, 0, h * s, w * s, 3), np.float32)


def _to_host(video) -> np.ndarray:
    """A host copy: on a CPU ``np.asarray`` of a device array may be a view that keeps the device
    buffer alive as long as any frame of it is kept."""
    return np.array(video, copy=True)
