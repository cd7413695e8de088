"""Temporal Progressive Denoising (TPD), MiLA [2503.15875v1] sec. 3.4, eq. 13-14, in the sigma convention.

MiLA denoises frames nearer the condition frames faster so later frames can lean on them:

    f(t, phi_s) = 1 - (cos((1 - t) w + phi_s) - cos(phi_s)) / (cos(w + phi_s) - cos(phi_s))   (13)
    phi_s = 0.5 pi * s / |S|                                                                  (14)

with MiLA's progress ``t`` (0 = noise). With ``sigma = 1 - t`` frame ``s`` of the ``S`` noisy
frames gets the level

    sigma_s = 1 - f(1 - sigma, phi_s) = (cos(sigma w + phi_s) - cos phi_s) / (cos(w + phi_s) - cos phi_s)
            = sin(phi_s + sigma w / 2) sin(sigma w / 2) / (sin(phi_s + w / 2) sin(w / 2)),

the second form being the one computed (no cancellation).

Because ``phi_s + sigma w`` stays in [0, pi) where cos decreases, ``sigma_s`` rises monotonically
from 0 at sigma = 0 to 1 at sigma = 1 for every frame (all frames finish together, MiLA's first
requirement); frame 0 (phi = 0) follows the convex ``(1 - cos(sigma w)) / (1 - cos w)`` and is
nearly clean early, and frames with larger phi follow ever more concave curves, so an earlier
frame is never noisier than a later one.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

from jaxdrive.validate import check_ndim, check_positive_int, check_range


def _check_omega(omega):
    check_range("omega", omega, 0.0, math.pi / 2, lo_open=True)


def tpd_level(sigma, phi, omega=math.pi / 2):
    """``sigma_s`` of one frame with phase ``phi`` (broadcasting), clipped into [0, 1].

    ``sigma`` in [0, 1], ``phi`` in [0, pi/2), ``omega`` in (0, pi/2]: checked when concrete;
    traced values must honour the same ranges.
    """
    check_range("sigma", sigma, 0.0, 1.0)
    check_range("phi", phi, 0.0, math.pi / 2, hi_open=True)
    _check_omega(omega)
    sigma = jnp.asarray(sigma, jnp.float32)
    phi = jnp.asarray(phi, jnp.float32)
    # cos(a) - cos(b) = -2 sin((a + b) / 2) sin((a - b) / 2) turns eq. 13's differences of
    # nearly equal cosines (small omega or sigma) into products, free of cancellation in fp32.
    half = 0.5 * omega
    level = (jnp.sin(phi + sigma * half) * jnp.sin(sigma * half)) / (jnp.sin(phi + half) * jnp.sin(half))
    # Pin the endpoints: numerator and denominator may be evaluated by different code paths.
    level = jnp.where(sigma >= 1.0, 1.0, jnp.where(sigma <= 0.0, 0.0, level))
    return jnp.clip(level, 0.0, 1.0)


def tpd_sigmas(sigma, num_frames: int, omega=math.pi / 2):
    """MiLA [2503.15875v1] eq. 13-14: base level(s) ``[...]`` -> per-frame levels ``[..., num_frames]``.

    Frame ``s = 0 .. num_frames - 1`` (in order of distance from the condition frames) has phase
    ``phi_s = (pi / 2) * s / num_frames``. sigma = 1 gives all ones and sigma = 0 all zeros
    exactly.
    """
    num_frames = check_positive_int("num_frames", num_frames)
    phi = (0.5 * math.pi / num_frames) * jnp.arange(num_frames, dtype=jnp.float32)
    return tpd_level(jnp.asarray(sigma, jnp.float32)[..., None], phi, omega)


def tpd_frame_sigmas(sigma, cond_mask, omega=math.pi / 2):
    """TPD over the noisy frames of clips whose condition frames may sit anywhere.

    ``sigma [B]`` base levels, ``cond_mask [B, F]`` (True = clean condition frame) -> ``[B, F]``:
    condition frames get 0; the ``S`` noisy frames get ``tpd_sigmas`` in their order along the
    clip (``s`` = rank among the noisy frames, ``|S|`` = their count), as MiLA indexes the noisy
    frames of a batch. With the condition frames first this equals ``tpd_sigmas`` on the rest.
    """
    check_ndim("sigma", sigma, 1)
    check_ndim("cond_mask", cond_mask, 2)
    if jnp.shape(cond_mask)[0] != jnp.shape(sigma)[0]:
        raise ValueError(
            f"cond_mask: expected shape [B, F] with B = {jnp.shape(sigma)[0]} (from sigma), "
            f"got {list(jnp.shape(cond_mask))}"
        )
    noisy = ~jnp.asarray(cond_mask, bool)
    rank = jnp.cumsum(noisy, axis=1) - 1
    count = jnp.maximum(jnp.sum(noisy, axis=1, keepdims=True), 1)
    phi = (0.5 * math.pi) * rank.astype(jnp.float32) / count
    levels = tpd_level(jnp.asarray(sigma, jnp.float32)[:, None], jnp.where(noisy, phi, 0.0), omega)
    return jnp.where(noisy, levels, 0.0)
