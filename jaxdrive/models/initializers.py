"""Random keys for parameter initialisation that compile quickly.

Flax derives one key per parameter (``fold_in``) and draws each parameter from it. With JAX's
default threefry keys, XLA compiles an unrolled 20-round hash for every one of those calls: on a
CPU the CogVideoX-layout VAE's ``init`` took 64 s to compile, nearly all of it hashing. An
``unsafe_rbg`` key (XLA's RngBitGenerator, with cheap split and fold_in) compiles the same init
in under 10 s. :func:`init_key` derives such a key from the caller's key deterministically.

The trade-off, acceptable for initial values: ``unsafe_rbg`` streams are not guaranteed to be
identical across JAX versions, backends or shardings of the initialised arrays. Initialise once,
then shard (``jaxdrive.parallel.shard_params``) or save the parameters; do not rely on a seed to
reproduce parameters bit for bit on another platform.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def init_key(key):
    """An ``unsafe_rbg`` key determined by ``key`` (a typed key or raw ``uint32[2]`` key data)."""
    data = jax.random.key_data(key) if jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key) else key
    data = jnp.asarray(data, jnp.uint32).reshape(-1)[:2]
    return jax.random.wrap_key_data(jnp.concatenate([data, data]), impl="unsafe_rbg")
