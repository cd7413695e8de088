"""Shared helpers of the DiT tests: cached initialisation, perturbed parameters, jitted calls.

Compiling is the expensive part on a CPU, so each (config, input shapes) is initialised once per
process and every test calls one jitted function per input structure.
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax.traverse_util import flatten_dict, unflatten_dict

from jaxdrive.models.dit import DiT
from jaxdrive.models.dit.conditions import Conditions

# Zero-initialised projections of the control branches (they must leave the output unchanged).
# "out" is a ControlNet branch layer's output projection (distinct from attention's "to_out").
BRANCH_ZERO = ("warp_proj", "map_in", "cond_embed", "reference_embed", "linear_out", "cross_view", "out", "layout_gate")


def split_inputs(ex: dict):
    """``(latents, sigma, text, kw)`` of :func:`example_inputs`: ``kw`` the other given conditions
    as a dict (tests swap and drop fields by name); :func:`conditions` puts them back together."""
    kw = ex["cond"].given()
    return ex["latents"], ex["sigma"], kw.pop("text", None), kw


def conditions(text, kw) -> Conditions:
    return Conditions(text=text, **kw)


@functools.cache
def boxed_params(cfg, shapes: tuple):
    """Boxed (logically partitioned) params of ``DiT(cfg)`` for inputs built from ``shapes``
    (host initialisation: nothing to compile)."""
    return DiT(cfg).init_params(0, boxed=True, **dict(shapes))


def perturb(params, scale=0.05, seed=1, skip=()):
    """``params`` + N(0, scale^2) noise, except leaves whose path has a part named in ``skip``
    (e.g. :data:`BRANCH_ZERO`, to keep those branches at their zero initialisation). The noise is
    drawn with NumPy: eager ``jax.random.normal`` compiles one program per leaf shape (a third of
    the compile time of a test of the all-controls model)."""
    flat = flatten_dict(params)
    rng = np.random.default_rng(seed)
    out = {}
    for path, leaf in sorted(flat.items()):
        if any(part in skip for part in path):
            out[path] = leaf
            continue
        value = np.asarray(leaf, np.float32) + scale * rng.standard_normal(np.shape(leaf), np.float32)
        out[path] = jnp.asarray(value.astype(leaf.dtype))
    return unflatten_dict(out)


def params_for(cfg, shapes: tuple, *, skip=BRANCH_ZERO, scale=0.05):
    """Unboxed params with every non-branch parameter perturbed (the final projection and the
    cross-attention outputs start at zero, which would make outputs trivially equal)."""
    return perturb(jax.tree_util.tree_map(jnp.asarray, nn.unbox(boxed_params(cfg, shapes))), scale=scale, skip=skip)


@functools.cache
def forward_fn(cfg, **static):
    dit = DiT(cfg)
    return jax.jit(lambda p, lat, sig, text, kw: dit.forward(p, lat, sig, conditions(text, kw), **static))


def max_rel(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b)) / (np.max(np.abs(b)) + 1e-30))


def tree_max_rel(got, want):
    """max |got - want| over all leaves, relative to the largest |want| of the whole tree (leaves
    whose true gradient is 0, e.g. key biases under softmax, only carry rounding noise)."""
    g = [np.asarray(x, np.float64) for x in jax.tree_util.tree_leaves(got)]  # NumPy: no program per shape
    w = [np.asarray(x, np.float64) for x in jax.tree_util.tree_leaves(want)]
    scale = max(float(np.max(np.abs(x))) for x in w)
    return max(float(np.max(np.abs(a - b))) for a, b in zip(g, w)) / scale
