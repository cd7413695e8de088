"""Joint Denoising and Correcting flow (JDC), MiLA [2503.15875v1] sec. 3.3, eq. 8-12 and appendix A.

A predicted anchor frame ``z`` is modelled as the true frame ``x`` plus noise of scale alpha1
(eq. 8): ``z = (1 - a1) x + a1 n1``. JDC brings it to a noise level ``g`` by
``x_n = (1 - a2) z + a2 n2`` with ``n2 ~ N(0, s^2)`` (eq. 9), so that

    x_n = (1 - a2)(1 - a1) x + a2 n2 + a1 (1 - a2) n1                          (eq. 10)

lies on the rectified-flow path of ``x`` at level ``g``: signal ``1 - g = (1 - a1)(1 - a2)``
(eq. 12) and total noise standard deviation ``g`` (appendix A, eq. 20), which gives

    a2  = (g - a1) / (1 - a1)                                                   (eq. 12)
    s^2 = (a2 - 2 a1 a2 + 2 a1) / a2                                            (eq. 11 / 21)

The network then denoises the anchors jointly with the frames between them and corrects them.
In jaxdrive's convention MiLA's noise scales are noise levels (sigma): 0 = clean, 1 = noise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxdrive.flow.rectified import add_noise, expand_per_frame
from jaxdrive.validate import check_range, is_concrete

DEFAULT_ALPHA1 = 0.1
DEFAULT_ANCHOR_SLOPE = 0.5


def _check_alpha1(alpha1):
    check_range("alpha1", alpha1, 0.0, 1.0, hi_open=True)


def _check_g_not_below_alpha1(g, alpha1):
    if is_concrete((g, alpha1)):
        gap = jnp.asarray(g, jnp.float32) - jnp.asarray(alpha1, jnp.float32)
        if gap.size and float(jnp.min(gap)) < 0.0:
            raise ValueError(
                f"g: expected g >= alpha1 = {float(jnp.max(jnp.asarray(alpha1))):g} (eq. 12 cannot "
                f"remove noise the anchor already has), got min g = {float(jnp.min(jnp.asarray(g))):g}"
            )


def jdc_alpha2(g, alpha1):
    """MiLA [2503.15875v1] eq. 12 solved for the second noise scale: ``a2 = (g - a1) / (1 - a1)``.

    ``alpha1`` in [0, 1), ``g`` in [alpha1, 1]; checked when concrete, a contract when traced.
    """
    _check_alpha1(alpha1)
    check_range("g", g, 0.0, 1.0)
    _check_g_not_below_alpha1(g, alpha1)
    g = jnp.asarray(g, jnp.float32)
    alpha1 = jnp.asarray(alpha1, jnp.float32)
    return (g - alpha1) / (1.0 - alpha1)


def jdc_noise_var(alpha1, alpha2):
    """MiLA [2503.15875v1] eq. 11: variance of ``n2``, ``(a2 - 2 a1 a2 + 2 a1) / a2``.

    ``alpha1`` in [0, 1), ``alpha2`` in (0, 1]; diverges as alpha2 -> 0 (while ``a2^2 s^2``
    stays finite, see :func:`jdc_renoise`).
    """
    _check_alpha1(alpha1)
    check_range("alpha2", alpha2, 0.0, 1.0, lo_open=True)
    alpha1 = jnp.asarray(alpha1, jnp.float32)
    alpha2 = jnp.asarray(alpha2, jnp.float32)
    return (alpha2 - 2.0 * alpha1 * alpha2 + 2.0 * alpha1) / alpha2


def jdc_renoise(key, z, g, alpha1):
    """MiLA [2503.15875v1] eq. 9: bring predicted anchors ``z`` to noise level ``g``.

    ``z [B, ..., F, h, w, C]`` (or any ``[B, ...]`` with a ``[B]`` or scalar ``g``); ``g`` a
    scalar, ``[B]`` or ``[B, F]``; ``alpha1`` the assumed noise scale of the prediction, a scalar
    (MiLA holds it constant). Returns ``(1 - a2) z + a2 n2`` with ``n2 ~ N(0, s^2)`` from eq.
    11-12. ``a2 * n2`` is drawn as ``sqrt(a2 (a2 + 2 a1 (1 - a2))) * N(0, 1)``, the same
    law written without dividing by ``a2``, so ``g = alpha1`` (``a2 = 0``) leaves ``z`` unchanged
    instead of producing inf * 0.
    """
    z = jnp.asarray(z)
    _check_alpha1(alpha1)
    check_range("g", g, 0.0, 1.0)
    _check_g_not_below_alpha1(g, alpha1)
    g = jnp.asarray(g, jnp.float32)
    a1 = jnp.asarray(alpha1, jnp.float32)
    if g.ndim == 0:
        g = jnp.broadcast_to(g, z.shape[:1])
    if a1.ndim != 0:
        raise ValueError(f"alpha1: expected a scalar, got shape {list(a1.shape)}")
    g = expand_per_frame(g, z, "g")
    a2 = (g - a1) / (1.0 - a1)
    noise_std = jnp.sqrt(jnp.maximum(a2 * (a2 + 2.0 * a1 * (1.0 - a2)), 0.0))
    n = jax.random.normal(key, z.shape, jnp.float32)
    return ((1.0 - a2) * z + noise_std * n).astype(z.dtype)


def jdc_anchor_sigma(sigma, slope=DEFAULT_ANCHOR_SLOPE):
    """The anchors' noise level ``g`` as a function of the base level ``sigma`` (MiLA [2503.15875v1] sec. 3.3).

    MiLA fixes alpha1 and makes ``g(t)`` "a linear function" of the base noise level. Our
    reading: ``g = slope * sigma`` with ``0 < slope <= 1``. A linear map that reaches 0 together
    with the base level (all frames must finish clean together, as in TPD) has no intercept, and
    ``slope <= 1`` keeps the anchors, which already hold a good estimate, never noisier than the
    frames being generated. JDC needs ``g >= alpha1`` at the level where anchors are re-noised
    (the first sampling step), i.e. ``slope * sigma_max >= alpha1``.
    """
    check_range("slope", slope, 0.0, 1.0, lo_open=True)
    check_range("sigma", sigma, 0.0, 1.0)
    return jnp.asarray(slope, jnp.float32) * jnp.asarray(sigma, jnp.float32)


def jdc_training_anchors(key, x, noise, levels, anchor_mask, alpha1=DEFAULT_ALPHA1):
    """Noisy latents for training with JDC anchors made as the sampler makes them: ``(x_t, noise_eff)``.

    ``x``, ``noise`` ``[B, ..., F, h, w, C]``; ``levels [B, F]`` (anchors at their ``g``, e.g. from
    :func:`jaxdrive.flow.frame_sigmas`); ``anchor_mask [B, F]``; ``alpha1`` a scalar in [0, 1).

    At sampling a predicted anchor ``z`` is re-noised to ``g`` by :func:`jdc_renoise`. Training
    draws the prediction by MiLA [2503.15875v1] eq. 8, ``z = (1 - a1) x + a1 n1`` (the truth plus alpha1 noise),
    and re-noises it with :func:`jdc_renoise` (eq. 9) where ``g >= alpha1``. Where ``g < alpha1``
    (late in sampling the model has been denoising the anchor, not re-noising it) the anchor is the
    plain flow-path point ``add_noise(x, noise, g)``. Every other frame is ``add_noise(x, noise,
    levels)`` with ``noise`` unchanged, bit for bit.

    ``noise_eff`` is ``noise`` except on re-noised anchors, where it is ``(x_t - (1 - g) x) / g``,
    the standard-normal noise that puts ``x_t`` on the flow path of ``x`` at ``g`` (eq. 10-12;
    appendix A). The velocity target ``noise_eff - x`` (MiLA [2503.15875v1] eq. 15's y) is then exactly the
    velocity of the sample the network sees, and a data-predicting network's
    ``(x_t - x) / g`` equals it too.
    """
    x = jnp.asarray(x)
    noise = jnp.asarray(noise)
    _check_alpha1(alpha1)
    a1 = jnp.asarray(alpha1, jnp.float32)
    if a1.ndim != 0:
        raise ValueError(f"alpha1: expected a scalar, got shape {list(a1.shape)}")
    levels = jnp.asarray(levels, jnp.float32)
    if levels.ndim != 2:
        raise ValueError(f"levels: expected shape [B, F], got {list(levels.shape)}")
    check_range("levels", levels, 0.0, 1.0)
    anchor_mask = jnp.asarray(anchor_mask, bool)
    if anchor_mask.shape != levels.shape:
        raise ValueError(
            f"anchor_mask: expected shape {list(levels.shape)} (that of levels), got {list(anchor_mask.shape)}"
        )
    x_t = add_noise(x, noise, levels)
    k_pred, k_renoise = jax.random.split(key)
    n1 = jax.random.normal(k_pred, x.shape, jnp.float32)
    z = add_noise(x, n1.astype(x.dtype), jnp.broadcast_to(a1, x.shape[:1]))  # eq. 8
    renoise = anchor_mask & (levels >= a1) & (levels > 0.0)
    g = jnp.where(renoise, levels, 1.0)  # off the re-noised anchors any g in [a1, 1] will do
    x_n = jdc_renoise(k_renoise, z, g, alpha1)  # eq. 9
    on = expand_per_frame(renoise, x, "anchor_mask")
    g_x = expand_per_frame(g, x, "levels")
    noise_eff = jnp.where(on, (x_n.astype(jnp.float32) - (1.0 - g_x) * x) / g_x, noise)
    return jnp.where(on, x_n, x_t).astype(x_t.dtype), noise_eff.astype(noise.dtype)
