"""STAGE's DCT degradation of condition frames (STAGE [2506.13138v1] sec. 4C, data augmentation).

STAGE low-passes the condition frame with a discrete cosine transform during training so the
model learns to cope with the blur and artifacts of its own earlier outputs. jaxdrive keeps the
lowest ``keep_ratio`` of the DCT-II coefficients along each of the height and width axes and
zeroes the rest (orthonormal DCT, so ``keep_ratio = 1`` is the identity).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.flow.rectified import expand_per_frame
from jaxdrive.validate import check_range, check_shape


@functools.cache
def dct_matrix(n: int) -> np.ndarray:
    """The orthonormal DCT-II matrix ``D [n, n]``: ``coeffs = D @ signal``, ``signal = D.T @ coeffs``."""
    k = np.arange(n)[:, None]
    i = np.arange(n)[None, :]
    d = np.sqrt(2.0 / n) * np.cos(np.pi * (i + 0.5) * k / n)
    d[0] /= np.sqrt(2.0)
    return d.astype(np.float32)


def _lowpass_projector(n: int, keep):
    """``D^T diag(k < ceil(keep * n)) D``: the projection onto the lowest DCT bins, ``[..., n, n]``."""
    d = jnp.asarray(dct_matrix(n))
    kept = jnp.arange(n) < jnp.maximum(jnp.ceil(keep[..., None] * n), 1)
    return jnp.einsum("ki,...k,kj->...ij", d, kept.astype(jnp.float32), d)


@jax.named_scope("dct_lowpass")  # float32 on purpose: train.program.F32_DOTS_ALLOWED
def dct_lowpass(x, keep_ratio):
    """Low-pass ``x [B, ..., h, w, C]`` over (h, w) keeping ``ceil(keep_ratio * n)`` DCT bins per axis.

    ``keep_ratio`` in (0, 1]: a scalar, or ``[B]`` for a ratio per sample (drawn by the caller).
    At least the DC bin is always kept.
    """
    x = jnp.asarray(x)
    if x.ndim < 4:
        raise ValueError(f"x: expected shape [B, ..., h, w, C] (4 or more axes), got {list(x.shape)}")
    check_range("keep_ratio", keep_ratio, 0.0, 1.0, lo_open=True)
    keep = jnp.asarray(keep_ratio, jnp.float32)
    if keep.ndim == 1:
        check_shape("keep_ratio", keep, (x.shape[0],))
    elif keep.ndim != 0:
        raise ValueError(f"keep_ratio: expected a scalar or shape [{x.shape[0]}], got {list(keep.shape)}")
    keep = jnp.broadcast_to(keep, (x.shape[0],))
    # Separable projections as small matmuls: cheap at latent sizes and, unlike an FFT-based
    # DCT, indifferent to how the batch axes are sharded.
    rows = _lowpass_projector(x.shape[-3], keep)  # [B, h, h]
    cols = _lowpass_projector(x.shape[-2], keep)  # [B, w, w]
    out = jnp.einsum("bij,b...jwc->b...iwc", rows, x.astype(jnp.float32))
    out = jnp.einsum("bvw,b...hwc->b...hvc", cols, out)
    return out.astype(x.dtype)


def degrade_frames(x, frame_mask, keep_ratio):
    """Apply :func:`dct_lowpass` to the frames where ``frame_mask [B, F]`` is True; others pass
    through bit for bit. ``x [B, ..., F, h, w, C]``."""
    x = jnp.asarray(x)
    if x.ndim < 5:
        raise ValueError(f"x: expected shape [B, ..., F, h, w, C] (5 or more axes), got {list(x.shape)}")
    check_shape("frame_mask", frame_mask, (x.shape[0], x.shape[-4]))
    mask = expand_per_frame(jnp.asarray(frame_mask, bool), x, "frame_mask")
    return jnp.where(mask, dct_lowpass(x, keep_ratio), x)
