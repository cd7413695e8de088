"""diffusers-format safetensors -> jaxdrive parameters (never pickle)."""
