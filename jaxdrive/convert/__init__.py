"""diffusers-format safetensors -> jaxdrive parameters (never pickle)."""

from jaxdrive.convert.diffusers_dit import config_from_diffusers, load_diffusers_transformer

__all__ = ["config_from_diffusers", "load_diffusers_transformer"]
