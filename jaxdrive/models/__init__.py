"""Flax linen modules: layers, embeddings, the attention kernel registry, condition encoders, the
diffusion transformer, the 3D causal VAE and STAGE's HTFT feature-transfer module."""
