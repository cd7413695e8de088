"""Shared layers of jaxdrive's models: sharded dense layers, norms (layer, RMS, group), the MLP, adaLN modulation,
embedding lookups and the attention projections.

Every parameter carries logical axis names (``nn.with_logical_partitioning``; the names are those
of :mod:`jaxdrive.parallel.rules`). A dense layer gathers its FSDP-sharded kernel at use
(:func:`jaxdrive.parallel.constrain` with the activation rules) and, under an Explicit mesh, states
the sharding of its output, since Explicit mode refuses to guess where the partial sums of a
contraction over a ``tensor``-sharded dimension go.

Parameters are float32; a layer computes in ``dtype`` (its inputs and kernels are cast), norms and
softmax compute in float32.
"""

from __future__ import annotations

import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec

from jaxdrive.models.params import ONES, ZEROS, Init, param
from jaxdrive.parallel.mesh import entry_axes, explicit_mesh, mesh_axis_size, spec_of
from jaxdrive.parallel.rules import logical_to_spec


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def add_bias(y, b, spec=None):
    """``y + b`` over ``y``'s last ``b.ndim`` axes, its bias gradient a contraction with ones.

    XLA:CPU turns the plain reduction of the gradient over the token axes into a windowed tree
    reduction that runs several times slower than a matrix-vector product of the same size
    (``jaxdrive.bench.ops``). ``spec``: the bias's ``PartitionSpec`` under an Explicit mesh (the
    contraction over batch-sharded tokens sums across devices into it), else None."""
    return y + b


def _add_bias_fwd(y, b, spec):
    return y + b, jnp.zeros((0,) * b.ndim, b.dtype)  # carries b's rank and dtype, no data


def _add_bias_bwd(spec, like, g):
    lead = g.ndim - like.ndim
    letters = "".join(chr(ord("a") + i) for i in range(g.ndim))
    # ones over the token axes, sharded as the gradient's token axes
    ones = jnp.ones(g.shape[:lead], g.dtype, out_sharding=None if spec is None else PartitionSpec(*spec_of(g)[:lead]))
    db = jnp.einsum(f"{letters},{letters[:lead]}->{letters[lead:]}", g, ones, out_sharding=spec)
    return g, db.astype(like.dtype)


add_bias.defvjp(_add_bias_fwd, _add_bias_bwd)


class Dense(nn.Module):
    """``y = x . W + b`` contracting the last ``len(in_names)`` dims of ``x``.

    ``features``: output dims; ``names``: logical names of the kernel, input dims then output dims
    (the bias takes the output names). ``kernel_init`` defaults to Glorot-uniform; pass
    :data:`ZEROS` for the zero-initialised projections of control branches.
    """

    features: int | tuple[int, ...]
    names: tuple
    use_bias: bool = True
    dtype: jnp.dtype = jnp.float32
    kernel_init: Init | None = None
    bias_init: Init = ZEROS

    @nn.compact
    def __call__(self, x):
        feats = (self.features,) if isinstance(self.features, int) else tuple(self.features)
        n_in = len(self.names) - len(feats)
        if n_in < 1:
            raise ValueError(f"names: expected input and output names for features {feats}, got {self.names}")
        in_shape = x.shape[x.ndim - n_in :]
        init = self.kernel_init or Init("xavier", fan_in_axes=n_in)
        kernel = param(self, "kernel", init, tuple(in_shape) + feats, self.names).astype(self.dtype)
        lead_shape = x.shape[: x.ndim - n_in]
        lead_spec, out_spec = (None,) * len(lead_shape), (None,) * len(feats)
        mesh = explicit_mesh()
        if mesh is not None:
            lead_spec = spec_of(x)[: x.ndim - n_in]
            used = {a for e in lead_spec for a in entry_axes(e)}
            out_spec = logical_to_spec(self.names[n_in:], shape=feats, mesh=mesh)
            out_spec = tuple(None if set(entry_axes(e)) & used else e for e in out_spec)
        # Tokens as one axis where the sharding allows it (only the first leading axis sharded):
        # XLA:CPU then reduces the bias gradient over a 2D array, several times faster than over the
        # 5D video layout, and the kernel gradient's transposes are plain 2D ones.
        flat = len(lead_shape) > 1 and all(math.prod(map(mesh_axis_size, entry_axes(e))) == 1 for e in lead_spec[1:])
        if flat:
            merged = (math.prod(lead_shape), *x.shape[len(lead_shape) :])  # major axis sharded: contiguous blocks
            x = (
                x.reshape(merged)
                if mesh is None
                else jax.lax.reshape(
                    x, merged, out_sharding=PartitionSpec(lead_spec[0], *spec_of(x)[len(lead_shape) :])
                )
            )
        lead = "".join(chr(ord("a") + i) for i in range(1 if flat else len(lead_shape)))
        cin = "".join(chr(ord("n") + i) for i in range(n_in))
        cout = "".join(chr(ord("u") + i) for i in range(len(feats)))
        out_sharding = None
        if mesh is not None:
            out_sharding = PartitionSpec(*(lead_spec[:1] if flat else lead_spec), *out_spec)
        y = jnp.einsum(
            f"{lead}{cin},{cin}{cout}->{lead}{cout}", x.astype(self.dtype), kernel, out_sharding=out_sharding
        )
        if self.use_bias:
            bias = param(self, "bias", self.bias_init, feats, self.names[n_in:]).astype(self.dtype)
            y = add_bias(y, bias, None if mesh is None else PartitionSpec(*out_spec))
        if flat:
            y = (
                y.reshape(*lead_shape, *feats)
                if mesh is None
                else jax.lax.reshape(y, (*lead_shape, *feats), out_sharding=PartitionSpec(*lead_spec, *out_spec))
            )
        return y


class LayerNorm(nn.Module):
    """LayerNorm over the last axis in float32; ``affine`` adds learned ``scale``/``bias``."""

    eps: float = 1e-6
    affine: bool = True
    name_: str = "embed"

    @nn.compact
    def __call__(self, x):
        dtype = x.dtype
        x = x.astype(jnp.float32)
        mean = x.mean(-1, keepdims=True)
        var = jnp.square(x - mean).mean(-1, keepdims=True)
        y = (x - mean) * jax.lax.rsqrt(var + self.eps)
        if self.affine:
            names = (self.name_,)
            y = y * param(self, "scale", ONES, (x.shape[-1],), names) + param(
                self, "bias", ZEROS, (x.shape[-1],), names
            )
        return y.astype(dtype)


class RMSNorm(nn.Module):
    """RMSNorm over the last axis in float32 with a learned scale (Open-Sora 1.2's qk-norm)."""

    eps: float = 1e-6
    name_: str = "head_dim"

    @nn.compact
    def __call__(self, x):
        dtype = x.dtype
        x = x.astype(jnp.float32)
        y = x * jax.lax.rsqrt(jnp.square(x).mean(-1, keepdims=True) + self.eps)
        return (y * param(self, "scale", ONES, (x.shape[-1],), (self.name_,))).astype(dtype)


class GroupNorm(nn.Module):
    """Group normalisation in float32 with a learned per-channel scale and bias: statistics over the
    ``D / groups`` channels of a group and every axis after the first ``keep``, which keep their
    own statistics. ``keep=1``: per example (the VAE's ``[N, T, H, W, C]``: CogVideoX's statistics
    span time); ``keep=2``: per example and frame (HTFT's ``[B, F, S, V, D]``, STAGE [2506.13138v1] sec. 4B)."""

    groups: int
    eps: float = 1e-6
    keep: int = 1
    name_: str = "channels"

    @nn.compact
    def __call__(self, x):
        c = x.shape[-1]
        xf = x.astype(jnp.float32).reshape(*x.shape[:-1], self.groups, c // self.groups)
        axes = tuple(range(self.keep, x.ndim - 1)) + (x.ndim,)
        mean = jnp.mean(xf, axis=axes, keepdims=True)
        var = jnp.mean(jnp.square(xf - mean), axis=axes, keepdims=True)
        y = ((xf - mean) * jax.lax.rsqrt(var + self.eps)).reshape(x.shape)
        names = (self.name_,)
        return (y * param(self, "scale", ONES, (c,), names) + param(self, "bias", ZEROS, (c,), names)).astype(x.dtype)


def modulate(x, shift, scale):
    """adaLN modulation ``x * (1 + scale) + shift`` (DiT, Peebles & Xie 2023, eq. for adaLN)."""
    return x * (1.0 + scale) + shift


class MLP(nn.Module):
    """``fc2(act(fc1(x)))`` with the hidden features tensor-parallel (``mlp``)."""

    hidden: int
    out: int
    act: str = "gelu_tanh"
    dtype: jnp.dtype = jnp.float32
    zero_out: bool = False
    in_name: str = "embed"

    @nn.compact
    def __call__(self, x):
        h = Dense(self.hidden, (self.in_name, "mlp"), dtype=self.dtype, name="fc1")(x)
        h = activation(self.act)(h)
        init = ZEROS if self.zero_out else None
        return Dense(self.out, ("mlp", "embed"), dtype=self.dtype, kernel_init=init, name="fc2")(h)


def activation(name: str):
    return {
        "gelu_tanh": lambda x: jax.nn.gelu(x, approximate=True),
        "gelu": lambda x: jax.nn.gelu(x, approximate=False),
        "silu": jax.nn.silu,
    }[name]


def lookup(table, ids):
    """Rows of an embedding ``table [N, D]`` at integer ``ids [...]`` -> ``[..., D]``, sharded like
    ``ids`` under an Explicit mesh (where a gather needs its output sharding stated)."""
    if explicit_mesh() is None:
        return jnp.take(table, ids, axis=0)
    return table.at[ids].get(out_sharding=PartitionSpec(*spec_of(ids), None))


class AttnProj(nn.Module):
    """q/k/v projections (with optional qk-norm) and the output projection of one attention layer.

    The caller arranges tokens into sequences and calls :func:`jaxdrive.attention.attention`
    between :meth:`q`/:meth:`kv` and :meth:`out`. ``qk_norm``: ``"rms"`` (Open-Sora 1.2),
    ``"layer"`` (CogVideoX, affine LayerNorm over the head features) or ``"none"``.
    ``zero_out`` zero-initialises the output projection (branches that must start as a no-op).
    """

    heads: int
    head_dim: int
    width: int
    qkv_bias: bool = True
    out_bias: bool = True
    qk_norm: str = "none"
    eps: float = 1e-6
    dtype: jnp.dtype = jnp.float32
    zero_out: bool = False
    context_name: str = "embed"

    def setup(self):
        hd = (self.heads, self.head_dim)
        names = lambda src: (src, "heads", "head_dim")
        self.to_q = Dense(hd, names("embed"), self.qkv_bias, self.dtype)
        self.to_k = Dense(hd, names(self.context_name), self.qkv_bias, self.dtype)
        self.to_v = Dense(hd, names(self.context_name), self.qkv_bias, self.dtype)
        init = ZEROS if self.zero_out else None
        self.to_out = Dense(self.width, ("heads", "head_dim", "embed"), self.out_bias, self.dtype, kernel_init=init)
        if self.qk_norm == "rms":
            self.norm_q, self.norm_k = RMSNorm(self.eps), RMSNorm(self.eps)
        elif self.qk_norm == "layer":
            self.norm_q = LayerNorm(self.eps, name_="head_dim")
            self.norm_k = LayerNorm(self.eps, name_="head_dim")

    def q(self, x):
        q = self.to_q(x)
        return self.norm_q(q) if self.qk_norm != "none" else q

    def kv(self, x):
        k = self.to_k(x)
        if self.qk_norm != "none":
            k = self.norm_k(k)
        return k, self.to_v(x)

    def out(self, o):
        return self.to_out(o.astype(self.dtype))
