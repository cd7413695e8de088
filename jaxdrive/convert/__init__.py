"""diffusers-format safetensors -> jaxdrive parameters (never pickle)."""

from .diffusers_vae import load_diffusers_vae, vae_config_from_diffusers

__all__ = ["load_diffusers_vae", "vae_config_from_diffusers"]
