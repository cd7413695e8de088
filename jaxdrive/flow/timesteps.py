"""Noise-level sampling for training and the sampling schedules for inference.

Training draws sigma per sample ``[B]`` or per frame ``[B, F]`` from a uniform or logit-normal
law (Esser et al. 2024, SD3, eq. 19; MagicDrive-V2 and Open-Sora v1.2 train rectified flow this
way) and then shifts it towards noise for large inputs (Open-Sora v1.2 ``timestep_transform``):
``s' = r * s / (1 + (r - 1) * s)`` with ``r = sqrt(pixels / base_pixels) *
sqrt(latent_frames / base_latent_frames) * scale``. A larger clip keeps more signal at the same
noise level, so it needs more noise to be equally hard.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from jaxdrive.validate import check_choice, check_positive_int, check_range

DISTRIBUTIONS = ("uniform", "logit_normal")


def sample_sigmas(
    key, shape, *, distribution: str = "logit_normal", loc: float = 0.0, scale: float = 1.0, shift: float = 1.0
):
    """Draw training noise levels of ``shape`` (``(B,)`` or ``(B, F)``) in [0, 1].

    ``distribution``: ``"uniform"`` (U[0, 1]) or ``"logit_normal"`` (sigmoid of N(loc, scale^2),
    SD3 eq. 19). ``shift`` is the ratio ``r`` of :func:`shift_sigmas` (1 = no shift); get it from
    :func:`resolution_shift` for Open-Sora v1.2's resolution- and length-aware shift.
    """
    check_choice("distribution", distribution, DISTRIBUTIONS)
    if not isinstance(shape, tuple) or not all(isinstance(n, int) and n >= 1 for n in shape):
        raise ValueError(f"shape: expected a tuple of positive ints such as (B,) or (B, F), got {shape!r}")
    check_range("scale", scale, 0.0, math.inf, lo_open=True)
    if distribution == "uniform":
        sigma = jax.random.uniform(key, shape, jnp.float32)
    else:
        sigma = jax.nn.sigmoid(loc + scale * jax.random.normal(key, shape, jnp.float32))
    return shift_sigmas(sigma, shift)


def shift_sigmas(sigma, ratio):
    """Open-Sora v1.2's time shift ``r * s / (1 + (r - 1) * s)``.

    Maps [0, 1] onto itself monotonically with 0 -> 0 and 1 -> 1; ``r > 1`` moves levels towards
    noise, ``r < 1`` towards data, ``r = 1`` is the identity. ``ratio`` must be > 0 (a scalar or
    an array that broadcasts against ``sigma``, e.g. ``[B]`` against ``[B]``).
    """
    check_range("sigma", sigma, 0.0, 1.0)
    check_range("ratio", ratio, 0.0, math.inf, lo_open=True)
    sigma = jnp.asarray(sigma, jnp.float32)
    ratio = jnp.asarray(ratio, jnp.float32)
    return ratio * sigma / (1.0 + (ratio - 1.0) * sigma)


def resolution_shift(
    height: int,
    width: int,
    latent_frames: int,
    *,
    base_pixels: int = 512 * 512,
    base_latent_frames: int = 1,
    scale: float = 1.0,
) -> float:
    """The shift ratio of Open-Sora v1.2 for a clip of ``height x width`` pixels.

    ``r = sqrt(height * width / base_pixels) * sqrt(latent_frames / base_latent_frames) * scale``.
    Open-Sora counts time in latent frames (its ``num_frames // 17 * 5``); here the caller passes
    the latent frame count directly, so the rule holds for any VAE (CogVideoX: 1 + (F - 1) / 4).
    Images use ``latent_frames = 1``.
    """
    for name, n in (
        ("height", height),
        ("width", width),
        ("latent_frames", latent_frames),
        ("base_pixels", base_pixels),
        ("base_latent_frames", base_latent_frames),
    ):
        check_positive_int(name, n)
    check_range("scale", scale, 0.0, math.inf, lo_open=True)
    return math.sqrt(height * width / base_pixels) * math.sqrt(latent_frames / base_latent_frames) * scale


def sampling_sigmas(num_steps: int, *, shift: float = 1.0, sigma_max: float = 1.0):
    """The inference schedule ``[num_steps + 1]``: evenly spaced levels, shifted, from ``sigma_max``
    to 0.

    The last entry is exactly 0 and the schedule is strictly decreasing. Open-Sora v1.2 samples
    with this schedule (``1 - i / N``) and the same shift as in training. Below 1, ``sigma_max`` is
    the schedule's first level itself (SDEdit's start, ``sample.warp_start``): the even spacing
    runs from the unshifted level the shift maps to it, the shift with the inverse ratio.
    """
    check_positive_int("num_steps", num_steps)
    check_range("sigma_max", sigma_max, 0.0, 1.0, lo_open=True)
    top = sigma_max if sigma_max == 1.0 else shift_sigmas(sigma_max, 1.0 / shift)
    base = jnp.linspace(top, 0.0, num_steps + 1, dtype=jnp.float32)
    return shift_sigmas(base, shift).at[-1].set(0.0)
