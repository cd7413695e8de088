"""Training losses over per-frame noise levels.

- :func:`flow_loss`: MiLA [2503.15875v1] eq. 15, the rectified-flow velocity loss with frames at their own
  levels (TPD), anchor frames at the JDC level g, and clean condition frames excluded.
- :func:`structure_loss`: LongDWM [2506.01546v1] eq. 4, the latent structure-preservation loss, an L2 distance
  after a 2D high-pass filter in the frequency domain of the latent height and width.
- STAGE's foreground weight map ``W_aux`` (:mod:`jaxdrive.flow.weights`) enters either loss as
  ``weight_map``.

Arrays follow ``[B, ..., F, h, w, C]``; masks and frame weights are ``[B, F]``; a weight map is
``[B, ..., F, h, w]`` (the array's shape without channels, e.g. W_aux ``[B, V, F, h, w]``).
Each loss is a mean over the channels and pixels of the frames it covers, so its scale does not
depend on how many condition frames a clip has.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.flow.rectified import expand_per_frame, velocity_target
from jaxdrive.validate import check_range, check_same_shape, check_shape


def _frame_weights(x, cond_mask, frame_weight):
    """Per-frame weights ``[B, F]`` (0 on condition frames), broadcast against ``x``."""
    batch, frames = x.shape[0], x.shape[-4]
    w = jnp.ones((batch, frames), jnp.float32)
    if frame_weight is not None:
        check_shape("frame_weight", frame_weight, (batch, frames))
        w = w * jnp.asarray(frame_weight, jnp.float32)
    if cond_mask is not None:
        check_shape("cond_mask", cond_mask, (batch, frames))
        w = jnp.where(jnp.asarray(cond_mask, bool), 0.0, w)
    return expand_per_frame(w, x, "frame weights")


def _pixel_weights(x, weight_map):
    if weight_map is None:
        return 1.0
    check_shape("weight_map", weight_map, x.shape[:-1])
    return jnp.asarray(weight_map, jnp.float32)[..., None]


def _weighted_mean(sq_err, x, cond_mask, frame_weight, weight_map):
    if x.ndim < 5:
        raise ValueError(f"x: expected shape [B, ..., F, h, w, C] (5 or more axes), got {list(x.shape)}")
    fw = _frame_weights(x, cond_mask, frame_weight)
    pw = _pixel_weights(x, weight_map)
    numer = jnp.sum(sq_err * fw * pw)
    # Normalise by the covered elements (not their weights): W_aux has mean 1 per image and
    # frame weights scale a frame's share of the loss.
    denom = jnp.sum(jnp.broadcast_to(fw > 0, sq_err.shape).astype(jnp.float32))
    return numer / jnp.maximum(denom, 1.0)


def flow_loss(v_pred, x, noise, *, cond_mask=None, frame_weight=None, weight_map=None):
    """MiLA [2503.15875v1] eq. 15: ``mean ||(noise - x) - v_pred||^2`` over the frames being denoised.

    ``v_pred`` is the network's velocity at ``x_sigma = add_noise(x, noise, sigma)`` with per-frame
    sigma (TPD levels ``f(t, phi_s)`` for generated frames, ``g(t)`` for anchors, the mask ``m_s``
    of eq. 15 only decides which level a frame was noised to, so both terms share one form here).
    ``cond_mask [B, F]``: clean condition frames, excluded. ``frame_weight [B, F]``: optional
    per-frame factors (e.g. to weigh anchors). ``weight_map [B, ..., F, h, w]``: optional
    per-pixel weights (STAGE's W_aux). Computed in float32.
    """
    check_same_shape("v_pred", v_pred, "x", x)
    target = velocity_target(jnp.asarray(x, jnp.float32), jnp.asarray(noise, jnp.float32))
    sq_err = jnp.square(jnp.asarray(v_pred, jnp.float32) - target)
    return _weighted_mean(sq_err, x, cond_mask, frame_weight, weight_map)


def per_frame_flow_loss(v_pred, x, noise):
    """Mean squared velocity error of each frame, ``[B, F]``, for logging loss against frame index."""
    check_same_shape("v_pred", v_pred, "x", x)
    err = jnp.square(
        jnp.asarray(v_pred, jnp.float32) - velocity_target(jnp.asarray(x, jnp.float32), jnp.asarray(noise, jnp.float32))
    )
    frame_axis = x.ndim - 4
    other = tuple(a for a in range(1, x.ndim) if a != frame_axis)
    return jnp.mean(err, axis=other)


def high_pass_mask(height: int, width: int, cutoff: float):
    """Boolean ``[h, w]`` mask of the 2D FFT bins whose radial frequency exceeds ``cutoff``.

    Radial frequency is ``sqrt(fy^2 + fx^2) / 0.5`` with ``fy, fx`` in cycles per latent pixel,
    i.e. 1 at the Nyquist frequency of each axis. ``cutoff`` in [0, 1]: 0 keeps everything but
    the mean (DC), 1 keeps only the corner bins beyond Nyquist radius.
    """
    check_range("cutoff", cutoff, 0.0, 1.0)
    fy = jnp.fft.fftfreq(height)[:, None] / 0.5
    fx = jnp.fft.fftfreq(width)[None, :] / 0.5
    return jnp.sqrt(fy**2 + fx**2) > cutoff


@jax.named_scope("high_pass")  # complex64 on purpose: train.program.F32_DOTS_ALLOWED
def high_pass(x, cutoff: float = 0.25):
    """LongDWM's ``H``: the 2D high-pass of ``x [..., h, w, C]`` over the latent height and width."""
    x = jnp.asarray(x, jnp.float32)
    h, w = x.shape[-3], x.shape[-2]
    mask = high_pass_mask(h, w, cutoff)[:, :, None]
    # The 2D DFT as two small matrix products, not jnp.fft: XLA's CPU FFT fails (a RET_CHECK on
    # its input layout in fft_thunk) inside sharded programs, and the latent grid is small, so
    # the dense DFT costs O(h w (h + w)) per channel and runs as ordinary dots on any backend.
    fh, fw = _dft(h), _dft(w)
    spectrum = jnp.einsum("ah,...hwc,bw->...abc", fh, x.astype(jnp.complex64), fw)
    y = jnp.einsum("ah,...hwc,bw->...abc", jnp.conj(fh) / h, spectrum * mask, jnp.conj(fw) / w)
    return jnp.real(y)


def _dft(n: int) -> np.ndarray:
    """The ``n``-point DFT matrix ``exp(-2 pi i j k / n)`` (complex64)."""
    k = np.arange(n)
    return np.exp(-2j * np.pi * np.outer(k, k) / n).astype(np.complex64)


def structure_loss(x_pred, x, *, cutoff: float = 0.25, cond_mask=None, weight_map=None):
    """LongDWM [2506.01546v1] eq. 4: ``mean ||H(x_pred) - H(x)||^2``, ``H`` a 2D FFT high-pass over (h, w).

    ``x_pred`` is the denoiser's data estimate (``data_from_velocity(x_t, v, sigma)``), ``x`` the
    clean latents, both ``[B, ..., F, h, w, C]``. ``cutoff`` (fraction of Nyquist, see
    :func:`high_pass_mask`) is not given in the paper; 0.25 keeps the upper three quarters of the
    radial band. ``H`` is linear, so the loss filters the difference once.
    """
    check_same_shape("x_pred", x_pred, "x", x)
    diff = jnp.asarray(x_pred, jnp.float32) - jnp.asarray(x, jnp.float32)
    return _weighted_mean(jnp.square(high_pass(diff, cutoff)), x, cond_mask, None, weight_map)
