"""Inputs of the long-video strategy tests: given latent frames, a horizon's controls, and the
window models' parameters."""

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
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


def moved_params(dit, frames: int, scale: float = 0.05):
    """``dit``'s parameters (seed 0, inputs of 2 views of ``frames`` H x W latent frames), every
    leaf moved off its initialisation by ``scale`` * N(0, 1): zero-initialised layers too (the
    output layer, HTFT's, the warp embedding), so that every input reaches the output."""
    params = jax.tree_util.tree_map(
        jnp.asarray, nn.unbox(dit.init_params(0, batch=1, views=2, frames=frames, height=H, width=W))
    )
    return _moved(params, scale)


@functools.partial(jax.jit, static_argnums=1)
def _moved(params, scale):
    # jitted: drawn eagerly, the noise compiled one program per leaf shape (5 s of a file's compiling).
    # Each leaf takes its own key of jax.random.key(1), split in tree order; the barrier keeps XLA
    # from folding the normal's own factor into `scale`, so the values are the eager draw's, bit for bit
    leaves, tree = jax.tree_util.tree_flatten(params)
    keys = jax.random.split(jax.random.key(1), len(leaves))
    noise = jax.lax.optimization_barrier([jax.random.normal(k, p.shape) for p, k in zip(leaves, keys)])
    return tree.unflatten([p + scale * n for p, n in zip(leaves, noise)])
