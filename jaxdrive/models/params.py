"""Parameters of jaxdrive's models: how a layer declares one and how they are initialised.

A layer creates each parameter with :func:`param`: float32, boxed with logical axis names
(:mod:`jaxdrive.parallel.rules`) and drawn by an :class:`Init`. An ``Init`` draws either in JAX
(flax's ``init``, e.g. jitted with sharded outputs) or on the host with NumPy
(:func:`host_params`): compiling one random draw per parameter takes minutes on a CPU for a
model with hundreds of parameters, and the host draw compiles nothing.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.parallel.rules import constrain


@dataclasses.dataclass(frozen=True)
class Init:
    """A parameter initialiser that runs in JAX (``flax`` init, e.g. jitted and sharded) or on the
    host with NumPy (:func:`host_params`, which needs no compilation: compiling one random draw per
    parameter takes minutes on a CPU for a model with hundreds of parameters).

    ``kind``: ``"zeros"``, ``"ones"``, ``"normal"`` (``std``), ``"xavier"`` (Glorot-uniform,
    ``fan_in_axes`` leading dims are the fan-in, the rest the fan-out) or ``"lecun"`` (normal with
    std ``1 / sqrt(fan in)``)."""

    kind: str = "xavier"
    std: float = 0.02
    fan_in_axes: int = 1

    def _fans(self, shape):
        return int(np.prod(shape[:self.fan_in_axes])), int(np.prod(shape[self.fan_in_axes:]))

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
        fan_in, fan_out = self._fans(shape[len(shape) - rank:])
        if self.kind == "xavier":
            lim = math.sqrt(6.0 / (fan_in + fan_out))
            return rng.uniform(-lim, lim, shape).astype(np.float32)
        std = self.std if self.kind == "normal" else 1.0 / math.sqrt(fan_in)
        return (std * rng.standard_normal(shape)).astype(np.float32)


ZEROS, ONES = Init("zeros"), Init("ones")


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
    value = module.param(name, nn.with_logical_partitioning(init, tuple(names)), tuple(shape), jnp.float32)
    if _RECORDER is not None:
        _RECORDER[tuple(module.scope.path) + (name,)] = (init, len(shape))
    return constrain(value, tuple(names))


def abstract_params(module: nn.Module, *args, **kwargs):
    """``(boxed params tree of jax.ShapeDtypeStruct, {path: (Init, rank)})`` of ``module`` for
    these call arguments, from ``jax.eval_shape`` (nothing is compiled or allocated)."""
    with record_inits() as rec:
        tree = jax.eval_shape(lambda: module.init(jax.random.PRNGKey(0), *args, **kwargs)["params"])
    return tree, dict(rec)


def host_init(module: nn.Module, *args, seed: int = 0, boxed: bool = False, **kwargs):
    """``{"params": ...}`` for ``module.apply``, drawn on the host (:func:`host_params`)."""
    return {"params": host_params(*abstract_params(module, *args, **kwargs), seed, boxed=boxed)}


def host_params(abstract, recorded: dict, seed: int = 0, *, boxed: bool = False):
    """Fill an abstract boxed params tree (``jax.eval_shape`` of ``init`` under
    :func:`record_inits`) with NumPy values drawn per each parameter's :class:`Init`."""
    from flax.traverse_util import flatten_dict, unflatten_dict
    rng = np.random.default_rng(seed)
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

