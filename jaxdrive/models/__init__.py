"""Flax linen modules: layers, embeddings, condition encoders, the diffusion transformer, the 3D
causal VAE and STAGE's HTFT feature-transfer module (attention itself is :mod:`jaxdrive.attention`)."""
