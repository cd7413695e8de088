"""Parameters of jaxdrive's models (the DiT, the VAE, HTFT): how a layer declares one and how
they are initialised.

A layer creates each parameter with :func:`param`: float32, boxed with logical axis names
(:mod:`jaxdrive.parallel.rules`) and drawn by an :class:`Init`. An ``Init`` draws either in JAX
(flax's ``init``, e.g. jitted with sharded outputs) or on the host with NumPy. The host draw is
the fast initialisation of every model (``DiT.init_params``, ``CausalVAE.init``,
:func:`host_init`): in JAX, XLA compiles one random draw per parameter, which for a model with
hundreds of parameters takes minutes on a CPU (CogVideoX's VAE: 64 s to compile with threefry
keys, about 10 s with ``unsafe_rbg`` ones); the host draw compiles nothing (that VAE's 216 M
values take about 8 s on 2 CPU cores), and a seed gives the same values on every backend.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.parallel.rules import constrain


@dataclasses.dataclass(frozen=True)
class Init:
    """A parameter initialiser that runs in JAX (``flax`` init, e.g. jitted and sharded) or on the
    host with NumPy (:func:`host_params`), from the same distribution.

    ``kind``: ``"zeros"``, ``"ones"``, ``"normal"`` (``std``), ``"xavier"`` (Glorot-uniform,
    ``fan_in_axes`` leading dims are the fan-in, the rest the fan-out), ``"lecun"`` (normal with
    std ``1 / sqrt(fan in)``) or ``"lecun_truncated"`` (flax's ``lecun_normal``: a normal
    truncated at 2 standard deviations, scaled to std ``1 / sqrt(fan in)``; the VAE's kernels)."""

    kind: str = "xavier"
    std: float = 0.02
    fan_in_axes: int = 1

    def _fans(self, shape):
        return int(np.prod(shape[: self.fan_in_axes])), int(np.prod(shape[self.fan_in_axes :]))

    def __call__(self, key, shape, dtype=jnp.float32):
        shape = tuple(shape)
        if self.kind == "zeros":
            return jnp.zeros(shape, dtype)
        if self.kind == "ones":
            return jnp.ones(shape, dtype)
        fan_in, fan_out = self._fans(shape)
        if self.kind == "xavier":
            lim = math.sqrt(6.0 / (fan_in + fan_out))
            return jax.random.uniform(key, shape, dtype, -lim, lim)
        if self.kind == "lecun_truncated":  # flax's lecun_normal itself, fans as declared here
            axes = tuple(range(len(shape)))
            return jax.nn.initializers.variance_scaling(
                1.0, "fan_in", "truncated_normal", in_axis=axes[: self.fan_in_axes], out_axis=axes[self.fan_in_axes :]
            )(key, shape, dtype)
        std = self.std if self.kind == "normal" else 1.0 / math.sqrt(fan_in)
        return std * jax.random.normal(key, shape, dtype)

    def host(self, rng: np.random.Generator, shape, rank: int) -> np.ndarray:
        """NumPy values for a parameter of ``shape`` whose last ``rank`` dims are one layer's
        (leading dims come from scanned layers)."""
        shape = tuple(shape)
        if self.kind == "zeros":
            return np.zeros(shape, np.float32)
        if self.kind == "ones":
            return np.ones(shape, np.float32)
        fan_in, fan_out = self._fans(shape[len(shape) - rank :])
        if self.kind == "xavier":
            lim = math.sqrt(6.0 / (fan_in + fan_out))
            return rng.uniform(-lim, lim, shape).astype(np.float32)
        if self.kind == "lecun_truncated":
            z = rng.standard_normal(shape)
            tails = np.abs(z) > 2.0
            while tails.any():  # redrawn until none is left: a normal truncated at +-2
                z[tails] = rng.standard_normal(int(tails.sum()))
                tails = np.abs(z) > 2.0
            return (z * (1.0 / math.sqrt(fan_in) / TRUNCATED_STD)).astype(np.float32)
        std = self.std if self.kind == "normal" else 1.0 / math.sqrt(fan_in)
        return (std * rng.standard_normal(shape)).astype(np.float32)


ZEROS, ONES = Init("zeros"), Init("ones")
# Standard deviation of a standard normal truncated to (-2, 2) (flax's constant).
TRUNCATED_STD = 0.87962566103423978


def normal(std: float) -> Init:
    return Init("normal", std)


_RECORDER: dict | None = None


@contextlib.contextmanager
def record_inits():
    """Within the block, :func:`param` records ``path -> (Init, rank)`` of each parameter created."""
    global _RECORDER
    previous, _RECORDER = _RECORDER, {}
    try:
        yield _RECORDER
    finally:
        _RECORDER = previous


def param(module: nn.Module, name: str, init: Init, shape, names):
    """``module.param`` boxed with logical ``names`` (float32), gathered for use (:func:`constrain`)."""
    # unbox=True (flax's default) spelled out: the stub's overload for it types the unboxed value
    value: jax.Array = module.param(
        name, nn.with_logical_partitioning(init, tuple(names)), tuple(shape), jnp.float32, unbox=True
    )
    if _RECORDER is not None:
        assert module.scope is not None  # bound: module.param above raises on an unbound module
        _RECORDER[tuple(module.scope.path) + (name,)] = (init, len(shape))
    return constrain(value, tuple(names))


def abstract_params(module: nn.Module, *args, **kwargs) -> tuple[Any, dict]:
    """``(boxed params tree of jax.ShapeDtypeStruct, {path: (Init, rank)})`` of ``module`` for
    these call arguments, from ``jax.eval_shape`` (nothing is compiled or allocated)."""
    with record_inits() as rec:
        tree = jax.eval_shape(lambda: module.init(jax.random.PRNGKey(0), *args, **kwargs)["params"])
    return tree, dict(rec)


def host_init(module: nn.Module, *args, seed: int = 0, boxed: bool = False, **kwargs):
    """``{"params": ...}`` for ``module.apply``, drawn on the host (:func:`host_params`)."""
    return {"params": host_params(*abstract_params(module, *args, **kwargs), seed, boxed=boxed)}


def host_params(abstract, recorded: dict, seed=0, *, boxed: bool = False):
    """Fill an abstract boxed params tree (``jax.eval_shape`` of ``init`` under
    :func:`record_inits`) with NumPy values drawn per each parameter's :class:`Init`, in path
    order, from ``np.random.default_rng(seed)``."""
    from flax.traverse_util import flatten_dict, unflatten_dict

    rng = np.random.default_rng(seed)  # a Generator passes through: parts can share one stream
    out = {}
    for path, leaf in sorted(flatten_dict(abstract).items()):
        key = path[1:] if path[0] == "params" else path
        if key not in recorded:
            raise ValueError(f"params: {'/'.join(path)} was not created through jaxdrive's param() helper")
        init, rank = recorded[key]
        value = leaf.value if isinstance(leaf, nn.LogicallyPartitioned) else leaf
        arr = init.host(rng, value.shape, rank)
        out[path] = leaf.replace_boxed(arr) if boxed and isinstance(leaf, nn.LogicallyPartitioned) else arr
    return unflatten_dict(out)


def count_params(params) -> int:
    """Number of parameters in a params tree: of arrays, of ``jax.ShapeDtypeStruct`` leaves (from
    ``jax.eval_shape``, nothing allocated), boxed or not."""
    return int(sum(math.prod(x.shape) for x in jax.tree_util.tree_leaves(params)))


def host_params_for_key(key, parts: dict, *, boxed: bool = False) -> dict:
    """``{name: params}`` for ``parts = {name: abstract_params(module, ...)}``, drawn as
    :func:`host_params` does from one NumPy stream seeded by the data of the JAX ``key`` (the
    parts one after the other). The draw runs in a ``jax.pure_callback``, so the values are the
    same eagerly and under ``jax.jit``, and ``jax.eval_shape`` gives their shapes."""

    def draw(data):
        rng = np.random.default_rng(np.asarray(data, np.uint32).reshape(-1))
        return {name: host_params(abstract, recorded, rng) for name, (abstract, recorded) in parts.items()}

    shapes = {name: nn.unbox(abstract) for name, (abstract, _) in parts.items()}
    values = jax.pure_callback(draw, shapes, _key_data(key))
    if not boxed:
        return values
    is_box = lambda x: isinstance(x, nn.LogicallyPartitioned)
    return {
        name: jax.tree_util.tree_map(lambda box, v: box.replace_boxed(v), parts[name][0], values[name], is_leaf=is_box)
        for name in parts
    }


def _key_data(key):
    """``uint32`` data of a typed key or of a raw ``PRNGKey`` array."""
    if jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key):
        return jax.random.key_data(key)
    return jnp.asarray(key, jnp.uint32)
