"""Fixed embeddings of positions and noise levels: sinusoidal timestep embeddings, 1D / 2D / 3D
sin-cos positions, rotary tables (1D, CogVideoX's 3D) and Fourier features. Tables are computed
with NumPy (float64 where the references do), embeddings of traced values in float32."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from jaxdrive.models.tokens import reshape


def timestep_embedding(t, dim: int, *, flip_sin_to_cos: bool = True, shift: float = 0.0, max_period: float = 10000.0):
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


def sincos_3d(
    frames: int, height: int, width: int, dim: int, spatial_scale: float = 1.0, temporal_scale: float = 1.0
) -> np.ndarray:
    """3D sin-cos positions ``[frames, height * width, dim]`` of CogVideoX (Yang et al. 2024,
    sec. 2.2): ``dim / 4`` features for time, ``3 dim / 4`` for the 2D spatial grid."""
    if dim % 16:
        raise ValueError(f"width: 3D sin-cos positions need a width divisible by 16, got {dim}")
    spatial = sincos_2d(height, width, 3 * dim // 4, spatial_scale)
    temporal = sincos_1d(np.arange(frames) / temporal_scale, dim // 4)
    return np.concatenate(
        [
            np.broadcast_to(temporal[:, None], (frames, height * width, dim // 4)),
            np.broadcast_to(spatial[None], (frames, height * width, 3 * dim // 4)),
        ],
        axis=-1,
    )


def rope_1d(pos, dim: int, theta: float = 10000.0) -> tuple[np.ndarray, np.ndarray]:
    """Rotary embedding tables ``(cos, sin) [M, dim]`` for positions ``pos [M]`` (Su et al. 2021,
    RoFormer eq. 34): frequency ``theta^(-2i/dim)`` shared by the feature pair (2i, 2i + 1)."""
    if dim % 2:
        raise ValueError(f"head_dim: rotary embeddings need an even size, got {dim}")
    freqs = 1.0 / theta ** (np.arange(0, dim, 2, dtype=np.float32) / dim)
    ang = np.outer(np.asarray(pos, np.float32).reshape(-1), freqs)
    return np.repeat(np.cos(ang), 2, axis=1), np.repeat(np.sin(ang), 2, axis=1)


def rope_3d(
    frames: int, height: int, width: int, dim: int, *, theta: float = 10000.0, base: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
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
        t, h, w = (
            np.broadcast_to(x[idx], (frames, height, width, x.shape[-1]))
            for x, idx in zip(
                (tables[0][i], tables[1][i], tables[2][i]),
                ((slice(None), None, None), (None, slice(None), None), (None, None, slice(None))),
            )
        )
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
    ``f_i = temperature^(i / n)``, ``i < n`` (MagicDrive's Fourier embedder; MiLA [2503.15875v1] eq. 1's
    ``FFT(c)``). ``include_input`` keeps ``x`` itself first."""
    x = jnp.asarray(x, jnp.float32)
    freqs = jnp.asarray(temperature ** (np.arange(num_freqs) / num_freqs), jnp.float32)
    ang = x[..., None] * freqs  # [..., k, n]
    # one reshape that keeps x's leading shardings (two merges lost the batch sharding of a
    # size-1 batch under an Explicit mesh, and the concatenation below then refused the operands)
    feats = reshape(jnp.stack([jnp.sin(ang), jnp.cos(ang)], axis=-1), (*x.shape[:-1], x.shape[-1] * num_freqs * 2))
    return jnp.concatenate([x, feats], axis=-1) if include_input else feats
