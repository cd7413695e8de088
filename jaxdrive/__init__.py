"""jaxdrive: long-horizon multi-view driving world models in JAX/Flax.

Layers (docs/concepts/architecture.md): ``flow`` (noise-level math, losses, sampler), ``parallel`` (meshes,
sharding rules, sequence-sharded attention), ``models`` (DiT, 3D causal VAE), ``data``,
``train``, ``generate`` (long-video strategies), ``convert`` (diffusers weights), ``eval``,
``bench``; ``jaxdrive.WorldModel`` (:mod:`jaxdrive.world_model`) loads a trained run and generates.
"""

__version__ = "0.1.0"

from jaxdrive import flow  # noqa: E402,F401  (the pure math every other layer uses)


def __getattr__(name):
    # jaxdrive.WorldModel on first use: importing jaxdrive stays as light as the flow math
    if name in ("WorldModel", "Generation"):
        from jaxdrive import world_model

        return getattr(world_model, name)
    raise AttributeError(f"module 'jaxdrive' has no attribute {name!r}")
