"""Video <-> the latents the DiT is trained on: a saved 3D VAE, or exact frame-wise pixel folding.

    codec = LatentCodec.from_config(config.latents)            # loads the VAE when source = "vae"
    z = codec.encode(codec.params, video)     # video [B, V, F, H, W, 3] in [-1, 1] -> [B, V, F', h, w, C]
    video = codec.decode(codec.params, z)
    dec = codec.stream_decoder(F')           # or part by part: dec.push(z_part) ..., dec.flush()

``"vae"``: a jaxdrive VAE (``jaxdrive convert vae`` or :func:`save_pretrained`), views folded
into the batch, latents scaled by the VAE's scaling factor (:meth:`CausalVAE.scale_latents`).
``"space_to_depth"``: every ``factor x factor`` pixel patch of each frame becomes one latent
vector of ``3 factor^2`` channels; exact, parameter-free and frame-wise (F' = F), so the CPU demo
needs no VAE training. ``params`` is an explicit argument so that a jitted step takes the VAE's
weights as an input (not as constants baked into the program).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import jax.numpy as jnp

from jaxdrive import validate
from jaxdrive.models.tokens import reshape  # keeps the batch sharding under Explicit meshes

if TYPE_CHECKING:
    from jaxdrive.models.vae.model import CausalVAE


def space_to_depth(video, factor: int):
    """``[..., F, H, W, C]`` -> ``[..., F, H / f, W / f, f f C]`` (row-major within a patch)."""
    *lead, f, h, w, c = video.shape
    if h % factor or w % factor:
        raise ValueError(f"video: expected height and width divisible by {factor}, got {h} x {w}")
    x = reshape(video, (*lead, f, h // factor, factor, w // factor, factor, c))
    x = jnp.moveaxis(x, -4, -3)  # [..., F, h, w, fy, fx, C]
    return reshape(x, (*lead, f, h // factor, w // factor, factor * factor * c))


def depth_to_space(latents, factor: int, channels: int = 3):
    """Inverse of :func:`space_to_depth`."""
    *lead, f, h, w, _ = latents.shape
    x = reshape(latents, (*lead, f, h, w, factor, factor, channels))
    x = jnp.moveaxis(x, -3, -4)  # [..., F, h, fy, w, fx, C]
    return reshape(x, (*lead, f, h * factor, w * factor, channels))


@dataclasses.dataclass(frozen=True)
class LatentCodec:
    """Encode / decode between pixels and DiT latents (see the module docstring)."""

    source: str = "space_to_depth"
    factor: int = 4
    scale: float = 1.0
    vae: CausalVAE | None = None  # a CausalVAE when source == "vae"
    params: object = dataclasses.field(default=None, compare=False, hash=False)

    @classmethod
    def from_config(cls, config, *, shardings=None) -> LatentCodec:
        """From a :class:`jaxdrive.config.LatentConfig`; loads the VAE of ``config.vae_path``."""
        validate.check_choice("latents.source", config.source, ("vae", "space_to_depth"))
        if config.source == "space_to_depth":
            validate.check_positive_int("latents.factor", config.factor)
            return cls("space_to_depth", config.factor, config.scale)
        if not config.vae_path:
            raise ValueError(
                "latents.vae_path: expected a saved jaxdrive VAE (jaxdrive convert vae) "
                "when latents.source is 'vae', got ''"
            )
        from jaxdrive.models.pretrained import load_pretrained

        vae, params = load_pretrained(
            config.vae_path,
            shardings=shardings,
            mode=config.vae_mode,
            frame_wise_batch=config.vae_frame_batch,
            clip_batch=config.vae_clip_batch,
        )
        return cls("vae", 1, 1.0, vae, params)

    # the DiT's view of the codec: latent channels, spatial and temporal compression
    @property
    def channels(self) -> int:
        return 3 * self.factor**2 if self.vae is None else self.vae.config.latent_channels

    @property
    def spatial(self) -> int:
        return self.factor if self.vae is None else self.vae.config.spatial_compression

    @property
    def temporal(self) -> int:
        return 1 if self.vae is None or self.vae.config.mode == "frame_wise" else self.vae.config.temporal_compression

    @property
    def value_range(self) -> tuple[float, float] | None:
        """The interval every encoded latent lies in: ``(-scale, scale)`` for space-to-depth
        latents (pixels in [-1, 1], rearranged and scaled); None for a VAE's (unbounded)."""
        return (-self.scale, self.scale) if self.vae is None else None

    def latent_frames(self, frames: int) -> int:
        return frames if self.vae is None else self.vae.latent_frames(frames)

    def pixel_frames(self, latent_frames: int) -> int:
        """Pixel frames that ``latent_frames`` latent frames decode to (the inverse of :meth:`latent_frames`)."""
        return latent_frames if self.vae is None else self.vae.video_frames(latent_frames)

    def encode(self, params, video):
        """``[B, V, F, H, W, 3]`` in [-1, 1] -> latents ``[B, V, F', h, w, C]`` (scaled)."""
        if self.vae is None:
            return space_to_depth(jnp.asarray(video, jnp.float32), self.factor) * self.scale
        return self.vae.scale_latents(self.vae.encode(params, video))

    def decode(self, params, latents):
        """Latents ``[B, V, F', h, w, C]`` -> video ``[B, V, F, H, W, 3]``, clipped to [-1, 1]."""
        if self.vae is None:
            video = depth_to_space(jnp.asarray(latents, jnp.float32) / self.scale, self.factor)
        else:
            video = self.vae.decode(params, self.vae.unscale_latents(latents))
        return jnp.clip(video, -1.0, 1.0)

    def stream_decoder(self, total_latent_frames: int):
        """A :class:`jaxdrive.models.vae.stream.StreamDecoder` for a clip of ``total_latent_frames``
        latent frames: ``push(part)`` returns the frames that are final, ``flush()`` the rest, and
        together they equal :meth:`decode` of the whole clip (the VAE's ``"whole"`` mode is rejected)."""
        from jaxdrive.models.vae.stream import StreamDecoder

        return StreamDecoder(self, total_latent_frames)

    def check_model(self, dit_config) -> None:
        """The DiT must read these latents: channels and the compressions its conditions assume."""
        for name, want, got in (
            ("model.in_channels", self.channels, dit_config.in_channels),
            ("model.vae_spatial", self.spatial, dit_config.vae_spatial),
            ("model.vae_temporal", self.temporal, dit_config.vae_temporal),
        ):
            if want != got:
                raise ValueError(f"{name}: expected {want} to match the latents ({self.source}), got {got}")
