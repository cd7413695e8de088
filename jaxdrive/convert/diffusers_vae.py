"""diffusers ``AutoencoderKLCogVideoX`` (safetensors) -> :class:`jaxdrive.models.vae.model.CausalVAE`.

PyTorch names map to jaxdrive's parameter paths by rule: list indices join their module
(``down_blocks.0.resnets.1`` -> ``down_blocks_0_resnets_1``), the wrapper ``.conv`` of causal and
resampling convolutions is dropped, convolution weights ``[O, I, (T,) H, W]`` become kernels
``[(T,) H, W, I, O]`` and GroupNorm weights become ``scale``.
"""

from __future__ import annotations

import re

import einops
import jax
import numpy as np

from jaxdrive.convert.safetensors_io import WEIGHTS, assemble_params, read_config, read_weights
from jaxdrive.models.vae.model import CausalVAE, VAEConfig

CLASS_NAME = "AutoencoderKLCogVideoX"


def vae_config_from_diffusers(config: dict, source="config.json", **overrides) -> VAEConfig:
    """The :class:`VAEConfig` of a diffusers ``AutoencoderKLCogVideoX`` config dict."""

    def unsupported(key, value, want):
        raise ValueError(f"{source}: {key}: expected {want} (the CogVideoX VAE), got {value!r}")

    if config.get("act_fn", "silu") != "silu":
        unsupported("act_fn", config["act_fn"], "'silu'")
    for key, block in (("down_block_types", "CogVideoXDownBlock3D"), ("up_block_types", "CogVideoXUpBlock3D")):
        if any(t != block for t in config.get(key, [block])):
            unsupported(key, config[key], f"only {block!r}")
    for key in ("use_quant_conv", "use_post_quant_conv"):
        if config.get(key, False):
            unsupported(key, config[key], "False")
    for key in ("latents_mean", "latents_std"):
        if config.get(key) is not None:
            unsupported(key, config[key], "None")
    fields = dict(
        in_channels=config.get("in_channels", 3),
        out_channels=config.get("out_channels", 3),
        block_out_channels=tuple(config.get("block_out_channels", (128, 256, 256, 512))),
        layers_per_block=config.get("layers_per_block", 3),
        latent_channels=config.get("latent_channels", 16),
        norm_num_groups=config.get("norm_num_groups", 32),
        norm_eps=config.get("norm_eps", 1e-6),
        temporal_compression=int(config.get("temporal_compression_ratio", 4)),
        scaling_factor=config.get("scaling_factor", 1.15258426),
        shift_factor=config.get("shift_factor") or 0.0,
        tile_sample_height=config.get("sample_height", 480) // 2,
        tile_sample_width=config.get("sample_width", 720) // 2,
    )
    fields.update(overrides)
    return VAEConfig(**fields)


def vae_param_path(name: str) -> tuple[str, ...]:
    """jaxdrive path of a diffusers parameter name (without the weight -> kernel/scale rename)."""
    name = re.sub(r"\.(\d+)", r"_\1", name)
    name = re.sub(r"(blocks_\d+|mid_block)\.(resnets|downsamplers|upsamplers)", r"\1_\2", name)
    name = re.sub(r"\.conv\.(weight|bias)$", r".\1", name)
    return tuple(name.split("."))


def _convert(name: str, value: np.ndarray) -> tuple[tuple[str, ...], np.ndarray]:
    path = vae_param_path(name)
    if path[-1] == "weight":
        if value.ndim == 5:  # PyTorch Conv3d [out, in, t, h, w] -> flax's taps first
            return path[:-1] + ("kernel",), einops.rearrange(value, "o i t h w -> t h w i o")
        if value.ndim == 4:
            return path[:-1] + ("kernel",), einops.rearrange(value, "o i h w -> h w i o")
        return path[:-1] + ("scale",), value
    return path, value


def load_diffusers_vae(path, **overrides):
    """``(vae, params)`` from a diffusers directory of ``AutoencoderKLCogVideoX`` (``config.json``
    + ``diffusion_pytorch_model.safetensors``). ``overrides`` set :class:`VAEConfig` fields such
    as ``mode``, ``tiling`` or ``dtype``. Unknown or missing keys raise ``ValueError`` listing them."""
    config = read_config(path, CLASS_NAME)
    vae = CausalVAE(vae_config_from_diffusers(config, f"{path}/config.json", **overrides))
    flat, origin = {}, {}
    for name, value in read_weights(path).items():
        key, flat[key] = _convert(name, np.asarray(value))
        origin[key] = name
    expected = jax.eval_shape(vae.init, jax.random.PRNGKey(0))
    params = assemble_params(expected, flat, f"{path}/{WEIGHTS}", origin)
    return vae, jax.tree_util.tree_map(jax.numpy.asarray, params)
