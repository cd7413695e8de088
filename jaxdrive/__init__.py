"""jaxdrive: long-horizon multi-view driving world models in JAX/Flax.

Layers (docs/concepts/architecture.md): ``flow`` (noise-level math, losses, sampler), ``parallel`` (meshes,
sharding rules, sequence-sharded attention), ``models`` (DiT, 3D causal VAE), ``data``,
``train``, ``generate`` (long-video strategies), ``convert`` (diffusers weights), ``eval``,
``bench``.
"""

__version__ = "0.1.0"

from jaxdrive import flow  # noqa: E402,F401  (the pure math every other layer uses)
