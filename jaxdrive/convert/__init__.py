"""diffusers-format safetensors -> jaxdrive parameters (never pickle)."""

from jaxdrive.convert.diffusers_dit import config_from_diffusers, load_diffusers_transformer
from jaxdrive.convert.diffusers_vae import load_diffusers_vae, vae_config_from_diffusers

__all__ = ["config_from_diffusers", "load_diffusers_transformer", "load_diffusers_vae", "vae_config_from_diffusers"]
