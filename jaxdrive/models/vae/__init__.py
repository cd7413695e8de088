"""The 3D causal video VAE (CogVideoX architecture).

- ``model.py``: :class:`~jaxdrive.models.vae.model.CausalVAE` and its config, the encoder and
  decoder, chunked / whole / frame-wise / tiled passes;
- ``layers.py``: its layers (causal 3D convolution, spatial norm, resnet, down- and upsampling);
- ``stream.py``: the streaming decode (latents pushed part by part).

This package re-exports what the module ``jaxdrive.models.vae`` held before it became one
(``from jaxdrive.models.vae import CausalVAE``); jaxdrive itself imports from the modules.
"""

from jaxdrive.models.vae.model import (
    MODES,
    CausalVAE,
    Decoder3D,
    Encoder3D,
    VAEConfig,
    chunk_plan,
    fold_views,
    tiled_apply,
)

__all__ = ["MODES", "CausalVAE", "Decoder3D", "Encoder3D", "VAEConfig", "chunk_plan", "fold_views", "tiled_apply"]
