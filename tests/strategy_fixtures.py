"""Inputs of the long-video strategy tests: given latent frames and a horizon's controls."""

import numpy as np

from jaxdrive.models.dit.conditions import Conditions

H, W, C = 4, 8, 48  # latents of 16 x 32 pixels, space-to-depth 4


def horizon_inputs(length: int, views: int = 2, given: int = 2, seed: int = 0):
    rng = np.random.default_rng(seed)
    first = rng.normal(size=(1, views, given, H, W, C)).astype(np.float32)
    controls = Conditions(
        waypoints=np.cumsum(rng.normal(size=(1, length, 2)), axis=1).astype(np.float32),
        fps=np.full((1,), 12.0, np.float32),
    )
    return first, controls
