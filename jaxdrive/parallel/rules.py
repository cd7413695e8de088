"""Logical axis names -> mesh axes: the one place where jaxdrive decides how arrays are sharded.

Modules name the dimensions of their parameters (``nn.with_logical_partitioning``) and of their
activations at block boundaries (:func:`constrain`) with the *logical* names below; this module
maps them to the mesh axes ``data``, ``fsdp``, ``seq``, ``tensor`` (see ``mesh.py``).

``LOGICAL_AXIS_RULES`` is the table: ``name -> (activation axes, parameter axes, meaning)``.
Activations and parameters differ only where FSDP applies: a parameter's ``embed`` dimension is
sharded over ``fsdp`` (gathered by XLA before use) while an activation's ``embed`` is not (its
batch is already split over ``data`` and ``fsdp``). ``ACTIVATION_RULES`` and ``PARAM_RULES`` are
the two columns as ``{name: axes}`` dicts; ``axes`` is ``None`` (replicated), one mesh axis or a
tuple of mesh axes.

Choices:

* An unknown logical name raises ``ValueError`` (a typo would otherwise replicate silently).
* One mesh axis may appear only once in a spec; a second use raises ``ValueError``.
* When :func:`logical_to_spec` gets ``mesh``, mesh axes missing from that mesh are dropped (a
  missing axis is a size-1 axis). When it also gets ``shape``, a dimension not divisible by the
  product of its mesh axes keeps the longest prefix of those axes that divides it (often none:
  replicated) and logs a warning once per (names, shape, mesh shape). Tiny test configs thus run
  on any mesh; production configs should see no such warning.

Using the rules in a module under an Explicit mesh (the default of ``make_mesh``):

* gather an FSDP parameter at its use with ``w = constrain(w, names)``: the activation rules
  leave ``embed`` unsharded, so this all-gathers over ``fsdp`` and keeps ``tensor`` sharding;
* a contraction over a ``tensor``-sharded dimension needs its output sharding, e.g.
  ``jnp.einsum(..., out_sharding=logical_to_spec(out_names, mesh=jax.sharding.get_abstract_mesh()))``
  (Explicit mode refuses to guess where the partial sums go);
* do not install these rules as flax's global ``nn.logical_axis_rules`` context: flax would then
  constrain parameters with them at unboxing, bypassing the fallback above.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence

import flax.linen as nn
import jax
import numpy as np
from flax.core import meta
from jax.sharding import AxisType, NamedSharding, PartitionSpec

from jaxdrive.parallel.mesh import BATCH_AXES, entry_axes

_log = logging.getLogger(__name__)

Axes = str | tuple[str, ...] | None

# name: (activation axes, parameter axes, meaning)
LOGICAL_AXIS_RULES: dict[str, tuple[Axes, Axes, str]] = {
    "batch": (BATCH_AXES, None, "examples; FSDP shards the batch like data parallelism"),
    "views": (None, None, "camera views V (cross-view attention needs all views local)"),
    "frames": (None, None, "latent or pixel frames F when not folded into tokens"),
    "out_frames": (
        "seq",
        None,
        "frames of the DiT's per-frame output head (final layer, unpatchify, final "
        "convolutions): sequence parallel, so a long window's output stays split",
    ),
    "height": (None, None, "latent / pixel rows"),
    "width": (None, None, "latent / pixel columns"),
    "tokens": ("seq", None, "the flattened video sequence (frames x patches): sequence parallel"),
    "kv": (None, None, "key/value sequence inside attention (gathered; ring attention rotates it)"),
    "embed": (None, "fsdp", "model width D: params FSDP-sharded, activations whole"),
    "heads": ("tensor", "tensor", "attention heads: tensor (Megatron) parallel"),
    "head_dim": (None, None, "per-head features"),
    "mlp": ("tensor", "tensor", "MLP hidden features: tensor parallel"),
    "text_tokens": (None, None, "caption tokens L (short: replicated)"),
    "text_embed": (None, None, "text-encoder width (its projection's embed side carries fsdp)"),
    "cond": (None, None, "condition items: boxes N, waypoints, map cells after pooling"),
    "channels": (None, None, "latent / pixel / VAE conv channels"),
    "kernel": (None, None, "convolution taps (time, height, width)"),
    "vocab": ("tensor", "tensor", "output classes / codebook entries"),
    "layers": (None, None, "stacked (scanned) layers"),
}

ACTIVATION_RULES: dict[str, Axes] = {k: v[0] for k, v in LOGICAL_AXIS_RULES.items()}
PARAM_RULES: dict[str, Axes] = {k: v[1] for k, v in LOGICAL_AXIS_RULES.items()}

_warned: set = set()


def _as_tuple(axes: Axes) -> tuple[str, ...]:
    return () if axes is None else (axes,) if isinstance(axes, str) else tuple(axes)


def _mesh_sizes(mesh) -> dict[str, int]:
    return dict(zip(mesh.axis_names, mesh.axis_sizes))


def logical_to_spec(
    names: Sequence[str | None],
    rules: Mapping[str, Axes] = ACTIVATION_RULES,
    *,
    shape: Sequence[int] | None = None,
    mesh=None,
) -> PartitionSpec:
    """``PartitionSpec`` for an array whose dimensions carry logical ``names`` (``None`` = any).

    ``rules`` defaults to ``ACTIVATION_RULES``; pass ``PARAM_RULES`` for parameters. With
    ``mesh`` (a ``Mesh`` or ``AbstractMesh``) axes absent from it are dropped; with ``shape`` as
    well, indivisible dimensions fall back as described in the module docstring.
    """
    names = tuple(names)
    if shape is not None and len(shape) != len(names):
        raise ValueError(f"names: expected {len(shape)} names for shape {list(shape)}, got {len(names)}: {names}")
    sizes = None if mesh is None else _mesh_sizes(mesh)
    used: dict[str, str] = {}
    entries: list[Axes] = []
    dropped = []
    for i, name in enumerate(names):
        if name is None:
            entries.append(None)
            continue
        if name not in rules:
            raise ValueError(f"names: expected logical axis names from {sorted(rules)}, got {name!r}")
        axes = entry_axes(rules[name])
        for ax in axes:
            if ax in used:
                raise ValueError(
                    f"names: expected each mesh axis once per array, got {ax!r} "
                    f"for both {used[ax]!r} and {name!r} in {names}"
                )
            used[ax] = name
        if sizes is not None:
            axes = tuple(ax for ax in axes if ax in sizes)
            if shape is not None:
                keep = len(axes)
                while keep and shape[i] % math.prod(sizes[a] for a in axes[:keep]):
                    keep -= 1
                if keep < len(axes):
                    dropped.append((name, shape[i], axes[keep:]))
                axes = axes[:keep]
        entries.append(None if not axes else axes[0] if len(axes) == 1 else axes)
    if dropped:
        key = (names, tuple(shape), tuple(sorted(sizes.items())))
        if key not in _warned:
            _warned.add(key)
            _log.warning(
                "sharding fallback for %s with shape %s on mesh %s: not divisible, unsharded over %s",
                names,
                list(shape),
                sizes,
                [(n, d, list(a)) for n, d, a in dropped],
            )
    return PartitionSpec(*entries)


def constrain(
    x: jax.Array, names: Sequence[str | None], mesh=None, rules: Mapping[str, Axes] = ACTIVATION_RULES
) -> jax.Array:
    """Shard activation ``x`` as its logical ``names`` say, inside or outside ``jax.jit``.

    Uses ``mesh`` or else the mesh set by ``jax.set_mesh``; a no-op when there is neither.
    Explicit mesh axes go through ``jax.sharding.reshard`` (the sharding becomes part of the
    type), Auto axes through ``jax.lax.with_sharding_constraint``.
    """
    if len(names) != x.ndim:
        raise ValueError(
            f"names: expected {x.ndim} names for x of shape {list(x.shape)}, got {len(names)}: {tuple(names)}"
        )
    target = jax.sharding.get_abstract_mesh() if mesh is None else mesh
    if target is None or target.empty:
        return x
    spec = logical_to_spec(names, rules, shape=x.shape, mesh=target)
    sharding = spec if mesh is None else NamedSharding(mesh, spec)
    types = dict(zip(target.axis_names, target.axis_types))
    used = [ax for entry in spec for ax in entry_axes(entry)]
    if any(types[ax] == AxisType.Explicit for ax in used) or (
        not used and all(t == AxisType.Explicit for t in types.values())
    ):
        return jax.sharding.reshard(x, sharding)
    return jax.lax.with_sharding_constraint(x, sharding)


def _is_box(x) -> bool:
    return isinstance(x, meta.AxisMetadata)


def _leaf_sharding(leaf, mesh, rules) -> NamedSharding:
    value = leaf.value if _is_box(leaf) else leaf
    shape = tuple(getattr(value, "shape", ()))
    if isinstance(leaf, nn.LogicallyPartitioned):
        spec = logical_to_spec(leaf.names, rules, shape=shape, mesh=mesh)
    elif isinstance(leaf, nn.Partitioned):  # names are mesh axes already
        spec = PartitionSpec(*leaf.names)
    else:
        spec = PartitionSpec()  # no metadata: replicated
    return NamedSharding(mesh, spec)


def param_shardings(params, mesh, rules: Mapping[str, Axes] = PARAM_RULES):
    """A ``NamedSharding`` per array of a flax params tree (real or from ``jax.eval_shape``).

    Leaves boxed in ``nn.LogicallyPartitioned`` map their names through ``rules``; leaves boxed
    in ``nn.Partitioned`` use their names as mesh axes; unboxed leaves are replicated. The result
    has the structure of the *unboxed* tree (``nn.unbox(params)``), ready for ``in_shardings``.
    """
    return jax.tree_util.tree_map(lambda leaf: _leaf_sharding(leaf, mesh, rules), params, is_leaf=_is_box)


def shard_params(params, mesh, rules: Mapping[str, Axes] = PARAM_RULES):
    """``params`` unboxed and placed with :func:`param_shardings` (plain ``jax.Array`` leaves).

    Host (NumPy) leaves must hold the same values in every process (parameters drawn from one
    seed, :meth:`jaxdrive.models.dit.DiT.init_params`): with several processes each places only
    the shards of its own devices (``jax.make_array_from_callback``). ``jax.device_put`` would
    first check that the processes agree by gathering every array from all of them: the whole
    model over the network once per host (on 2 processes of the tiny config, 1 s of 105 gathers)."""
    shardings = param_shardings(params, mesh, rules)
    values = jax.tree_util.tree_map(lambda x: x.value if _is_box(x) else x, params, is_leaf=_is_box)
    if jax.process_count() == 1:
        return jax.device_put(values, shardings)
    return jax.tree_util.tree_map(_place_host_value, values, shardings)


def _place_host_value(x, sharding):
    if isinstance(x, jax.Array):  # already on devices (e.g. restored): jax.device_put reshards it
        return jax.device_put(x, sharding)
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])


def reshard_like(v: jax.Array, x: jax.Array) -> jax.Array:
    """``v`` with exactly ``x``'s sharding under an Explicit mesh, where operations that combine
    arrays (a concatenate, an update slice, an add in a loop carry) need equal shardings; ``v``
    as it is without a mesh or when ``x`` carries none."""
    spec = getattr(getattr(jax.typeof(x), "sharding", None), "spec", None)
    if spec is None or jax.sharding.get_abstract_mesh().empty:
        return v
    return jax.reshard(v, spec)
