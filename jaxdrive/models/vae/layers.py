"""Layers of the CogVideoX 3D causal VAE, channels-last: activations ``[N, T, H, W, C]``.

The architecture is CogVideoX's (Yang et al. 2024, "CogVideoX", sec. 2.1), the VAE that
MagicDrive-V2 adopts (its sec. 4.1, appendix G-H); the numerics follow the diffusers
implementation (``AutoencoderKLCogVideoX``) so that its released weights load and give the same
numbers.

- :class:`CausalConv3d`: a 3D convolution that sees no future frame. Time is padded at the front
  with ``kt - 1`` copies of the first frame, or with the ``kt - 1`` last input frames of the
  previous chunk (the *cache*) when a long video is processed chunk by chunk; space is
  zero-padded. Every call returns ``(y, new_cache)``.
- GroupNorm (:class:`jaxdrive.models.layers.GroupNorm`, shared with HTFT): statistics over (time,
  height, width, channels of the group) per example, in float32. Because the statistics span
  time, a chunked pass differs from a whole-clip pass.
- :class:`SpatialNorm3D`: the decoder's normalisation conditioned on the latent ``zq`` (Zheng et
  al. 2022, MoVQ): ``GroupNorm(f) * conv_y(zq) + conv_b(zq)`` with ``zq`` resized by nearest
  neighbour to ``f``, the first frame separately from the rest.
- :class:`ResnetBlock3D`, :class:`Downsample3D` (average pooling over time that keeps frame 0,
  then a stride-2 spatial convolution), :class:`Upsample3D` (nearest x2, frame 0 only in space).

Caches are nested dicts of arrays with one entry per causal convolution of kernel > 1 in time;
their shapes do not depend on the chunk length, so they thread through ``lax.scan``.
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.models.layers import GroupNorm
from jaxdrive.models.params import ZEROS, Init, param

# Logical names (jaxdrive.parallel.rules): convolution weights are small and replicated.
CONV3D_AXES = ("kernel", "kernel", "kernel", "channels", "channels")
CONV2D_AXES = ("kernel", "kernel", "channels", "channels")
VECTOR_AXES = ("channels",)
# Kernels as flax's lecun_normal (fan in: the taps times the input channels).
LECUN_3D, LECUN_2D = Init("lecun_truncated", fan_in_axes=4), Init("lecun_truncated", fan_in_axes=3)


def conv(x, kernel, bias, *, strides=(1, 1, 1), padding=((0, 0), (0, 0), (0, 0)), dtype=None):
    """``[N, T, H, W, Cin] -> [N, T', H', W', Cout]`` with a 3D kernel ``[kt, kh, kw, Cin, Cout]``
    (a 2D kernel ``[kh, kw, Cin, Cout]`` is applied per frame)."""
    if kernel.ndim == 4:
        kernel = kernel[None]
    dtype = dtype or x.dtype
    y = jax.lax.conv_general_dilated(
        x.astype(dtype), kernel.astype(dtype), strides, padding, dimension_numbers=("NDHWC", "DHWIO", "NDHWC")
    )
    return y + bias.astype(dtype)


class CausalConv3d(nn.Module):
    """Causal 3D convolution with a chunk cache (see the module docstring)."""

    features: int
    kernel_size: tuple[int, int, int] = (3, 3, 3)
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x, cache=None):
        kt, kh, kw = self.kernel_size
        kernel = param(self, "kernel", LECUN_3D, (kt, kh, kw, x.shape[-1], self.features), CONV3D_AXES)
        bias = param(self, "bias", ZEROS, (self.features,), VECTOR_AXES)
        new_cache = None
        if kt > 1:
            front = jnp.repeat(x[:, :1], kt - 1, axis=1) if cache is None else cache.astype(x.dtype)
            x = jnp.concatenate([front, x], axis=1)
            new_cache = x[:, x.shape[1] - (kt - 1) :]
        pad = ((0, 0), ((kh - 1) // 2,) * 2, ((kw - 1) // 2,) * 2)
        return conv(x, kernel, bias, padding=pad, dtype=self.dtype), new_cache


def nearest_resize(x, size):
    """Nearest-neighbour resize of ``[N, T, H, W, C]`` to ``size = (T', H', W')`` with PyTorch's
    ``F.interpolate(mode="nearest")`` index rule ``src = floor(dst * in / out)``."""
    for axis, out in zip((1, 2, 3), size):
        n = x.shape[axis]
        if n != out:
            idx = np.minimum(np.floor(np.arange(out) * (n / out)).astype(np.int64), n - 1)
            x = jnp.take(x, idx, axis=axis)
    return x


class SpatialNorm3D(nn.Module):
    """``GroupNorm(f) * conv_y(zq) + conv_b(zq)``, ``zq`` resized to ``f`` (first frame apart)."""

    groups: int
    eps: float = 1e-6
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, f, zq):
        t, h, w = f.shape[1:4]
        if t > 1 and t % 2 == 1:
            zq = jnp.concatenate(
                [nearest_resize(zq[:, :1], (1, h, w)), nearest_resize(zq[:, 1:], (t - 1, h, w))], axis=1
            )
        else:
            zq = nearest_resize(zq, (t, h, w))
        c = f.shape[-1]
        y, _ = CausalConv3d(c, (1, 1, 1), self.dtype, name="conv_y")(zq)
        b, _ = CausalConv3d(c, (1, 1, 1), self.dtype, name="conv_b")(zq)
        return GroupNorm(self.groups, self.eps, name="norm_layer")(f) * y + b


class ResnetBlock3D(nn.Module):
    """norm -> SiLU -> causal conv, twice, plus a (1x1x1 where channels change) shortcut.

    ``zq`` given: the norms are :class:`SpatialNorm3D` (decoder); else :class:`GroupNorm`."""

    features: int
    groups: int
    eps: float = 1e-6
    spatial_norm: bool = False
    dtype: Any = jnp.float32

    def _norm(self, name, x, zq):
        if self.spatial_norm:
            return SpatialNorm3D(self.groups, self.eps, self.dtype, name=name)(x, zq)
        return GroupNorm(self.groups, self.eps, name=name)(x)

    @nn.compact
    def __call__(self, x, zq=None, cache=None):
        cache = cache or {}
        new = {}
        h = nn.silu(self._norm("norm1", x, zq))
        h, new["conv1"] = CausalConv3d(self.features, dtype=self.dtype, name="conv1")(h, cache.get("conv1"))
        h = nn.silu(self._norm("norm2", h, zq))
        h, new["conv2"] = CausalConv3d(self.features, dtype=self.dtype, name="conv2")(h, cache.get("conv2"))
        if x.shape[-1] != self.features:
            x, _ = CausalConv3d(self.features, (1, 1, 1), self.dtype, name="conv_shortcut")(x)
        return x + h, new


def _pool_time(x):
    """Average pairs of frames; with an odd count frame 0 is kept as it is (CogVideoX)."""
    if x.shape[1] % 2 == 1:
        first, rest = x[:, :1], x[:, 1:]
        if rest.shape[1] == 0:
            return first
        return jnp.concatenate([first, _pool_time(rest)], axis=1)
    n, t = x.shape[:2]
    return jnp.mean(x.reshape(n, t // 2, 2, *x.shape[2:]), axis=2)


class Downsample3D(nn.Module):
    """Optional temporal average pooling (frame 0 kept), then a stride-2 3x3 convolution per
    frame with one row/column of zeros padded at the bottom/right."""

    features: int
    compress_time: bool = False
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x):
        kernel = param(self, "kernel", LECUN_2D, (3, 3, x.shape[-1], self.features), CONV2D_AXES)
        bias = param(self, "bias", ZEROS, (self.features,), VECTOR_AXES)
        if self.compress_time:
            x = _pool_time(x)
        return conv(x, kernel, bias, strides=(1, 2, 2), padding=((0, 0), (0, 1), (0, 1)), dtype=self.dtype)


def _upsample(x, time: bool):
    x = jnp.repeat(jnp.repeat(x, 2, axis=2), 2, axis=3)
    return jnp.repeat(x, 2, axis=1) if time else x


class Upsample3D(nn.Module):
    """Nearest x2 in space (and in time when compressing time), then a 3x3 convolution per frame.

    Frame 0 of a video is an image: it is upsampled in space only, so ``T`` latent frames give
    ``1 + 2 (T - 1)`` frames. ``first_chunk`` says whether ``x`` starts the video. diffusers
    decides by parity instead (odd ``T``: frame 0 apart; even ``T``: every frame doubled), which
    is the same for the chunks it makes from an odd number of latent frames (CogVideoX's 13
    included), but turns an even number ``F'`` into ``4 F'`` frames instead of ``1 + 4 (F' - 1)``;
    jaxdrive keeps the ``F = 1 + 4k <-> F' = 1 + k`` correspondence for every ``k``."""

    features: int
    compress_time: bool = False
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x, first_chunk: bool = True):
        kernel = param(self, "kernel", LECUN_2D, (3, 3, x.shape[-1], self.features), CONV2D_AXES)
        bias = param(self, "bias", ZEROS, (self.features,), VECTOR_AXES)
        if self.compress_time and first_chunk:
            x = jnp.concatenate([_upsample(x[:, :1], False), _upsample(x[:, 1:], True)], axis=1)
        else:
            x = _upsample(x, self.compress_time)
        return conv(x, kernel, bias, padding=((0, 0), (1, 1), (1, 1)), dtype=self.dtype)
