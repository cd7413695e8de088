"""Building blocks of the diffusion transformer: sharded dense layers, norms, modulation, the
sinusoidal timestep / position embeddings, rotary embeddings, Fourier features, the attention
projections and the token-layout helpers of sequence parallelism.

Every parameter carries logical axis names (``nn.with_logical_partitioning``; the names are those
of :mod:`jaxdrive.parallel.rules`). A dense layer gathers its FSDP-sharded kernel at use
(:func:`jaxdrive.parallel.constrain` with the activation rules) and, under an Explicit mesh, states
the sharding of its output, since Explicit mode refuses to guess where the partial sums of a
contraction over a ``tensor``-sharded dimension go.

Parameters are float32; a layer computes in ``dtype`` (its inputs and kernels are cast), norms and
softmax compute in float32.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import AxisType, PartitionSpec

from jaxdrive.parallel.rules import constrain, logical_to_spec

# Logical names of the DiT's video activations [B, F, S, V, D]: F token frames, S spatial patches
# of one view (the axis sequence parallelism shards), V views.
VIDEO = ("batch", "frames", "tokens", "views", "embed")
TEXT = ("batch", "text_tokens", "embed")


def _explicit_mesh():
    """The context mesh when it has an Explicit axis (where outputs need stated shardings)."""
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or not any(t == AxisType.Explicit for t in mesh.axis_types):
        return None
    return mesh


def mesh_axis_size(name: str) -> int:
    """Size of mesh axis ``name`` in the context mesh (1 without a mesh or without that axis)."""
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or name not in mesh.axis_names:
        return 1
    return int(dict(zip(mesh.axis_names, mesh.axis_sizes))[name])


def _spec_of(x) -> tuple:
    spec = tuple(getattr(getattr(jax.typeof(x), "sharding", None), "spec", ()) or ())
    return spec + (None,) * (x.ndim - len(spec))


def _axes(entry) -> tuple:
    return () if entry is None else (entry,) if isinstance(entry, str) else tuple(entry)


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
            raise ValueError(f"names: expected input and output names for features {feats}, "
                             f"got {self.names}")
        in_shape = x.shape[x.ndim - n_in:]
        init = self.kernel_init or Init("xavier", fan_in_axes=n_in)
        kernel = param(self, "kernel", init, tuple(in_shape) + feats, self.names).astype(self.dtype)
        lead = "".join(chr(ord("a") + i) for i in range(x.ndim - n_in))
        cin = "".join(chr(ord("n") + i) for i in range(n_in))
        cout = "".join(chr(ord("u") + i) for i in range(len(feats)))
        out_sharding = None
        mesh = _explicit_mesh()
        if mesh is not None:
            lead_spec = _spec_of(x)[:x.ndim - n_in]
            used = {a for e in lead_spec for a in _axes(e)}
            out_spec = logical_to_spec(self.names[n_in:], shape=feats, mesh=mesh)
            out_spec = tuple(None if set(_axes(e)) & used else e for e in out_spec)
            out_sharding = PartitionSpec(*lead_spec, *out_spec)
        y = jnp.einsum(f"{lead}{cin},{cin}{cout}->{lead}{cout}", x.astype(self.dtype), kernel,
                       out_sharding=out_sharding)
        if self.use_bias:
            y = y + param(self, "bias", self.bias_init, feats, self.names[n_in:]).astype(self.dtype)
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
            y = y * param(self, "scale", ONES, (x.shape[-1],), names) + param(self, "bias", ZEROS,
                                                                               (x.shape[-1],), names)
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
    return {"gelu_tanh": lambda x: jax.nn.gelu(x, approximate=True),
            "gelu": lambda x: jax.nn.gelu(x, approximate=False),
            "silu": jax.nn.silu}[name]


# ------------------------------------------------------------------ sinusoids and positions


def timestep_embedding(t, dim: int, *, flip_sin_to_cos: bool = True, shift: float = 0.0,
                       max_period: float = 10000.0):
    """Sinusoidal embedding of (float) timesteps ``t [...]`` -> ``[..., dim]`` (float32).

    Transformer positional encoding as used for diffusion timesteps: frequencies
    ``exp(-log(max_period) * i / (dim / 2 - shift))``, halves ``[sin, cos]``, or ``[cos, sin]``
    with ``flip_sin_to_cos`` (Open-Sora's and CogVideoX's choice). An odd ``dim`` is zero-padded.
    """
    half = dim // 2
    exponent = -math.log(max_period) * jnp.arange(half, dtype=jnp.float32) / (half - shift)
    args = jnp.asarray(t, jnp.float32)[..., None] * jnp.exp(exponent)
    emb = jnp.concatenate([jnp.sin(args), jnp.cos(args)], axis=-1)
    if flip_sin_to_cos:
        emb = jnp.concatenate([emb[..., half:], emb[..., :half]], axis=-1)
    if dim % 2:
        emb = jnp.pad(emb, [(0, 0)] * (emb.ndim - 1) + [(0, 1)])
    return emb


def sincos_1d(pos, dim: int) -> np.ndarray:
    """Fixed 1D sin-cos positions ``[M, dim]`` = ``[sin(p w_i), cos(p w_i)]``, ``w_i = 10000^(-2i/dim)``
    (Vaswani et al. 2017; MAE's ``get_1d_sincos_pos_embed_from_grid``). Computed in float64."""
    if dim % 2:
        raise ValueError(f"dim: expected an even embedding size, got {dim}")
    omega = 1.0 / 10000 ** (np.arange(dim // 2, dtype=np.float64) / (dim / 2.0))
    out = np.outer(np.asarray(pos, np.float64).reshape(-1), omega)
    return np.concatenate([np.sin(out), np.cos(out)], axis=1)


def sincos_2d(height: int, width: int, dim: int, scale: float = 1.0) -> np.ndarray:
    """2D sin-cos positions ``[height * width, dim]`` (row-major): half the features encode the
    column, half the row (MAE / PixArt / CogVideoX order: column first); coordinates are divided by
    ``scale`` (the interpolation scale)."""
    rows, cols = np.meshgrid(np.arange(height) / scale, np.arange(width) / scale, indexing="ij")
    return np.concatenate([sincos_1d(cols, dim // 2), sincos_1d(rows, dim // 2)], axis=1)


def sincos_3d(frames: int, height: int, width: int, dim: int, spatial_scale: float = 1.0,
              temporal_scale: float = 1.0) -> np.ndarray:
    """3D sin-cos positions ``[frames, height * width, dim]`` of CogVideoX (Yang et al. 2024,
    sec. 2.2): ``dim / 4`` features for time, ``3 dim / 4`` for the 2D spatial grid."""
    if dim % 16:
        raise ValueError(f"width: 3D sin-cos positions need a width divisible by 16, got {dim}")
    spatial = sincos_2d(height, width, 3 * dim // 4, spatial_scale)
    temporal = sincos_1d(np.arange(frames) / temporal_scale, dim // 4)
    return np.concatenate([np.broadcast_to(temporal[:, None], (frames, height * width, dim // 4)),
                           np.broadcast_to(spatial[None], (frames, height * width, 3 * dim // 4))],
                          axis=-1)


def rope_1d(pos, dim: int, theta: float = 10000.0) -> tuple[np.ndarray, np.ndarray]:
    """Rotary embedding tables ``(cos, sin) [M, dim]`` for positions ``pos [M]`` (Su et al. 2021,
    RoFormer eq. 34): frequency ``theta^(-2i/dim)`` shared by the feature pair (2i, 2i + 1)."""
    if dim % 2:
        raise ValueError(f"head_dim: rotary embeddings need an even size, got {dim}")
    freqs = 1.0 / theta ** (np.arange(0, dim, 2, dtype=np.float32) / dim)
    ang = np.outer(np.asarray(pos, np.float32).reshape(-1), freqs)
    return np.repeat(np.cos(ang), 2, axis=1), np.repeat(np.sin(ang), 2, axis=1)


def rope_3d(frames: int, height: int, width: int, dim: int, *, theta: float = 10000.0,
            base: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """3D rotary tables ``(cos, sin) [frames, height * width, dim]`` (CogVideoX): ``dim / 4``
    features rotate with the frame index, ``3 dim / 8`` each with the row and the column.

    ``base = (base_h, base_w)``: CogVideoX 1.0 fits the grid into its training grid, centred and
    keeping the aspect ratio, and spreads the positions over that region (the diffusers pipeline's
    ``get_resize_crop_region_for_grid``); ``None`` uses integer positions (CogVideoX 1.5).
    """
    if dim % 8:
        raise ValueError(f"head_dim: 3D rotary embeddings need a head size divisible by 8, got {dim}")
    rows, cols = np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64)
    if base is not None:
        (top, left), (bottom, right) = _crop_region((height, width), base)
        rows = np.linspace(top, bottom * (height - 1) / height, height)
        cols = np.linspace(left, right * (width - 1) / width, width)
    dt, ds = dim // 4, dim // 8 * 3
    tables = [rope_1d(np.arange(frames), dt, theta), rope_1d(rows, ds, theta), rope_1d(cols, ds, theta)]

    def grid(i):
        t, h, w = (np.broadcast_to(x[idx], (frames, height, width, x.shape[-1]))
                   for x, idx in zip((tables[0][i], tables[1][i], tables[2][i]),
                                     ((slice(None), None, None), (None, slice(None), None),
                                      (None, None, slice(None)))))
        return np.concatenate([t, h, w], axis=-1).reshape(frames, height * width, dim)
    return grid(0), grid(1)


def _crop_region(grid: tuple[int, int], base: tuple[int, int]):
    h, w = grid
    th, tw = base
    if h / w > th / tw:
        rh, rw = th, int(round(th / h * w))
    else:
        rw, rh = tw, int(round(tw / w * h))
    top, left = int(round((th - rh) / 2.0)), int(round((tw - rw) / 2.0))
    return (top, left), (top + rh, left + rw)


def apply_rope(x, cos, sin):
    """Rotate feature pairs (2i, 2i + 1) of ``x [..., D]`` by the tables (broadcast against x)."""
    xf = x.astype(jnp.float32)
    pairs = xf.reshape(*xf.shape[:-1], -1, 2)
    rotated = jnp.stack([-pairs[..., 1], pairs[..., 0]], axis=-1).reshape(xf.shape)
    return (xf * cos + rotated * sin).astype(x.dtype)


def fourier_features(x, num_freqs: int, temperature: float = 100.0, include_input: bool = True):
    """Fourier features of ``x [..., k]`` -> ``[..., k (1 + 2 n)]``: ``sin(f_i x), cos(f_i x)`` with
    ``f_i = temperature^(i / n)``, ``i < n`` (MagicDrive's Fourier embedder; MiLA eq. 1's
    ``FFT(c)``). ``include_input`` keeps ``x`` itself first."""
    x = jnp.asarray(x, jnp.float32)
    freqs = jnp.asarray(temperature ** (np.arange(num_freqs) / num_freqs), jnp.float32)
    ang = x[..., None] * freqs                                   # [..., k, n]
    feats = merge(merge(jnp.stack([jnp.sin(ang), jnp.cos(ang)], axis=-1), x.ndim), x.ndim - 1)
    return jnp.concatenate([x, feats], axis=-1) if include_input else feats


# ------------------------------------------------------------------ attention projections


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
        self.to_out = Dense(self.width, ("heads", "head_dim", "embed"), self.out_bias, self.dtype,
                            kernel_init=init)
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


# ------------------------------------------------------------------ token layouts


def merge(x, axis: int):
    """Merge ``axis`` and ``axis + 1`` into one. One merge at a time: under Explicit sharding a
    merge whose major axis is sharded (and minor axis not) keeps a block-contiguous sharding."""
    s = x.shape
    return x.reshape(*s[:axis], s[axis] * s[axis + 1], *s[axis + 2:])


def split(x, axis: int, major: int):
    """Split ``axis`` into ``(major, rest)`` (inverse of :func:`merge`)."""
    s = x.shape
    return x.reshape(*s[:axis], major, s[axis] // major, *s[axis + 1:])


def reshape(x, shape: Sequence[int]):
    """``x.reshape(shape)`` where only unsharded axes change: the longest common prefix of the two
    shapes keeps its sharding and the rest is unsharded (Explicit mode cannot infer a reshape that
    touches several axes at once)."""
    shape = tuple(int(s) for s in shape)
    if _explicit_mesh() is None:
        return x.reshape(shape)
    keep = 0
    while keep < min(x.ndim, len(shape)) and x.shape[keep] == shape[keep]:
        keep += 1
    spec = _spec_of(x)
    if any(e is not None for e in spec[keep:]):
        raise ValueError(f"x: reshape {list(x.shape)} -> {list(shape)} would move sharded axes {spec}")
    return jax.lax.reshape(x, shape, out_sharding=PartitionSpec(*spec[:keep], *([None] * (len(shape) - keep))))


def lookup(table, ids):
    """Rows of an embedding ``table [N, D]`` at integer ``ids [...]`` -> ``[..., D]``, sharded like
    ``ids`` under an Explicit mesh (where a gather needs its output sharding stated)."""
    if _explicit_mesh() is None:
        return jnp.take(table, ids, axis=0)
    return table.at[ids].get(out_sharding=PartitionSpec(*_spec_of(ids), None))


def to_sequence(x, order: Sequence[int]):
    """Transpose ``x [B, ...axes..., H, Dh]`` so the axes in ``order`` (indices into x, the sharded
    one first) follow the batch, then merge them into one sequence axis: ``[B, L, H, Dh]``."""
    perm = [0, *order] + [i for i in range(1, x.ndim) if i not in order]
    y = jnp.transpose(x, perm)
    for _ in range(len(order) - 1):
        y = merge(y, 1)
    return y


def from_sequence(y, shape: Sequence[int], order: Sequence[int]):
    """Inverse of :func:`to_sequence` for an array whose pre-transpose shape was ``shape``."""
    sizes = [shape[i] for i in order]
    for i in range(len(order) - 1):
        y = split(y, 1 + i, sizes[i])
    perm = [0, *order] + [i for i in range(1, len(shape)) if i not in order]
    inv = np.argsort(perm)
    return jnp.transpose(y, inv)


def pool_frames(x, pt: int, axis: int = 1):
    """Mean over groups of ``pt`` consecutive frames along ``axis`` (latent frames -> token frames
    when the patch spans ``pt`` frames)."""
    if pt == 1:
        return x
    return jnp.mean(split(x, axis, x.shape[axis] // pt), axis=axis + 1)
