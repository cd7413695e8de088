"""Rectified flow in the noise-level convention of jaxdrive.

``x_sigma = (1 - sigma) * x + sigma * noise``: sigma = 1 is pure noise, sigma = 0 is data; the
network predicts the velocity ``v = noise - x`` (MiLA [2503.15875v1] eq. 4-6 with MiLA's progress t = 1 - sigma;
MagicDrive-V2 and Open-Sora v1.2 use sigma = t/1000 directly).

Noise levels are per sample ``[B]`` or per frame ``[B, F]``. Arrays follow the channels-last
layout ``[B, ..., F, h, w, C]`` (e.g. latents ``[B, V, F, h, w, C]`` or ``[B, F, h, w, C]``): a
per-frame sigma lines up with axis 0 and the frame axis -4.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxdrive.validate import check_range, check_same_shape

FRAME_AXIS = -4  # [B, ..., F, h, w, C]
PREDICTIONS = ("velocity", "data")  # what a network's output is (DiTConfig.prediction)


def expand_per_frame(values, x, name: str = "sigma"):
    """Reshape ``[B]`` or ``[B, F]`` values so they broadcast against ``x [B, ..., F, h, w, C]``.

    Shared by every function that takes per-sample or per-frame quantities (noise levels, frame
    masks, frame weights). Raises ``ValueError`` naming ``name`` when the shapes do not line up.
    """
    values = jnp.asarray(values)
    xs = tuple(x.shape)
    if values.ndim == 1:
        if not xs or values.shape[0] != xs[0]:
            raise ValueError(
                f"{name}: expected shape [B] or [B, F] with B = {xs[0] if xs else '?'} "
                f"(the batch of an array of shape {list(xs)}), got {list(values.shape)}"
            )
        return values.reshape(values.shape + (1,) * (len(xs) - 1))
    if values.ndim == 2:
        if len(xs) < 5 or values.shape != (xs[0], xs[FRAME_AXIS]):
            want = f"[{xs[0]}, {xs[FRAME_AXIS]}]" if len(xs) >= 5 else "[B] (per-frame needs [B, ..., F, h, w, C])"
            raise ValueError(
                f"{name}: expected shape [B] or [B, F] = {want} for an array of shape "
                f"{list(xs)}, got {list(values.shape)}"
            )
        middle = (1,) * (len(xs) - 5)
        return values.reshape((xs[0],) + middle + (xs[FRAME_AXIS], 1, 1, 1))
    raise ValueError(f"{name}: expected shape [B] or [B, F], got {list(values.shape)}")


def noise_given_frames(x, noise, cond_mask, level):
    """The given frames of ``x [B, ..., F, h, w, C]`` (``cond_mask [B, F]``) noised to ``level``
    (``[B]``, one level a clip) on the flow's path, the other frames unchanged, and each frame's
    level ``[B, F]`` (``level`` where given, 0 elsewhere): what the model is told of its context.

    GameNGen (Valevski et al. 2024, arXiv 2408.14837, sec. 3.2.1, "noise augmentation"): a
    model trained on clean context frames and rolled out on its own outputs sees their errors
    compound ("quality degrades fast after 20-30 steps"); trained with context frames corrupted
    by noise of a level drawn per example up to 0.7, and told the level, it learns to correct
    what it is given, and at sampling a small level does the same.
    """
    check_same_shape("noise", noise, "x", x)
    m = jnp.asarray(cond_mask, bool)
    frame_level = jnp.where(m, jnp.asarray(level, jnp.float32)[:, None], 0.0)
    return add_noise(x, noise, frame_level), frame_level


def warp_path(x, noise, warp, levels, on):
    """The noisy input of the frames ``on [B, F]`` taken from the warp: ``(1 - s) warp + s noise``
    at their levels ``levels [B, F]`` (> 0 where on), the others ``(1 - s) x + s noise`` as
    usual; returns ``(x_t, noise')`` with ``noise'`` the noise that puts ``x_t`` on the path of
    ``x``, ``noise + (1 - s) / s (warp - x)`` where on, so that the velocity loss against
    ``(x, noise')`` is the usual one of a data estimate of ``x`` from that input.

    The path SDEdit samples on (Meng et al. 2022, arXiv 2108.01073, sec. 3: the guide, here
    LongDWM's warp, sec. 3.4, perturbed to level ``t0`` and denoised from there;
    ``sample.warp_start``): trained only on ``(1 - s) x + s noise``, a model reads a noised warp,
    whose signal already holds the warp, off its path and its correction overshoots; trained on
    this one too, it learns the correction from exactly the input the sampler starts from.
    """
    check_same_shape("noise", noise, "x", x)
    check_same_shape("warp", warp, "x", x)
    s = _levels(levels, x)
    m = expand_per_frame(jnp.asarray(on, bool), x, "on")
    s_on = jnp.where(m, s, 1.0)  # the given frames (level 0) are off the path: no division by their 0
    x_t = jnp.where(m, add_noise(warp, noise, levels), add_noise(x, noise, levels))
    implied = jnp.where(m, noise + (1.0 - s_on) / s_on * (warp - x), noise)
    return x_t.astype(x.dtype), implied.astype(noise.dtype)


def _levels(sigma, x):
    check_range("sigma", sigma, 0.0, 1.0)
    return expand_per_frame(sigma, x).astype(jnp.promote_types(x.dtype, jnp.float32))


def add_noise(x, noise, sigma):
    """Point on the straight path from data to noise: ``(1 - sigma) * x + sigma * noise``.

    MiLA [2503.15875v1] eq. 4-5 (there with progress t = 1 - sigma). ``sigma`` is ``[B]`` or ``[B, F]`` in
    [0, 1]; values are checked when concrete, and the contract holds for traced values.
    """
    check_same_shape("noise", noise, "x", x)
    s = _levels(sigma, x)
    return ((1.0 - s) * x + s * noise).astype(x.dtype)


def velocity_target(x, noise):
    """The rectified-flow velocity ``noise - x`` that the network learns (MiLA [2503.15875v1] eq. 15, y)."""
    check_same_shape("noise", noise, "x", x)
    return noise - x


def data_from_velocity(x_t, v, sigma):
    """Data estimate ``x = x_t - sigma * v``."""
    check_same_shape("v", v, "x_t", x_t)
    return (x_t - _levels(sigma, x_t) * v).astype(x_t.dtype)


def noise_from_velocity(x_t, v, sigma):
    """Noise estimate ``noise = x_t + (1 - sigma) * v``."""
    check_same_shape("v", v, "x_t", x_t)
    return (x_t + (1.0 - _levels(sigma, x_t)) * v).astype(x_t.dtype)


def velocity_from_data(x_t, x, sigma):
    """Velocity from a data estimate, ``(x_t - x) / sigma``; undefined (inf/nan) at sigma = 0."""
    check_same_shape("x", x, "x_t", x_t)
    return ((x_t - x) / _levels(sigma, x_t)).astype(x_t.dtype)


def velocity_from_noise(x_t, noise, sigma):
    """Velocity from a noise estimate, ``(noise - x_t) / (1 - sigma)``; undefined at sigma = 1."""
    check_same_shape("noise", noise, "x_t", x_t)
    return ((noise - x_t) / (1.0 - _levels(sigma, x_t))).astype(x_t.dtype)


def skip_coefficients(sigma, sigma_data: float):
    """EDM's preconditioning of a data-predicting network (Karras et al. 2022, "Elucidating the
    Design Space of Diffusion-Based Generative Models", eq. 7 and Table 1), for this flow's
    ``x_sigma = (1 - sigma) x + sigma noise``: ``(c_skip, c_out)`` such that the estimate
    ``c_skip x_sigma + c_out F`` leaves the network ``F`` a target of unit variance,
    ``(x - c_skip x_sigma) / c_out``, for data of standard deviation ``sigma_data``:

        c_skip = (1 - sigma) sigma_data^2 / ((1 - sigma)^2 sigma_data^2 + sigma^2)
        c_out  = sigma sigma_data / sqrt((1 - sigma)^2 sigma_data^2 + sigma^2)

    (EDM's ``c_skip = sigma_data^2 / (sigma^2 + sigma_data^2)`` with its ``x + sigma n`` written
    as ``(x_sigma / (1 - sigma))`` at level ``sigma / (1 - sigma)``). ``c_skip x_sigma`` is the
    linear least-squares estimate of ``x``; at level 0 it is ``x_sigma`` itself and ``c_out`` is 0,
    at level 1 it is 0 and ``c_out = sigma_data``. ``sigma`` any shape; returns two arrays of it."""
    check_range("sigma_data", sigma_data, 0.0, float("inf"), lo_open=True, hi_open=True)
    check_range("sigma", sigma, 0.0, 1.0)
    s = jnp.asarray(sigma, jnp.float32)
    var = jnp.square((1.0 - s) * sigma_data) + jnp.square(s)
    return (1.0 - s) * sigma_data**2 / var, s * sigma_data / jnp.sqrt(var)


def euler_step(x_t, v, sigma, sigma_next):
    """One Euler step of the flow ODE from level ``sigma`` to ``sigma_next``: ``x + (s' - s) v``."""
    check_same_shape("v", v, "x_t", x_t)
    ds = _levels(sigma_next, x_t) - _levels(sigma, x_t)
    return (x_t + ds * v).astype(x_t.dtype)


def velocity_from_output(out, x_t, sigma, prediction: str = "velocity", min_sigma: float = 0.05):
    """The velocity a network's output stands for: the output itself (``"velocity"``), or, for a
    network that predicts the clean data (``"data"``), ``(x_t - out) / max(sigma, min_sigma)``.

    Data prediction is Li & He 2025 ("Back to Basics: Let Denoising Generative Models Denoise",
    JiT, eq. 6 and its clamp of ``1 - t`` at 0.05): clean data lies on a low-dimensional manifold,
    so a network narrower than its token (a 64-wide DiT on 192-number tokens) can still predict
    it, where predicting ``noise - x`` means passing the token's full-dimensional noise through.
    Training keeps the velocity loss on the converted output (JiT's v-loss). ``min_sigma`` keeps
    frames at level 0 (condition frames) finite; the sampler's last step from ``s >= min_sigma``
    to 0 lands exactly on ``out``."""
    if prediction not in PREDICTIONS:
        raise ValueError(f"prediction: expected one of {list(PREDICTIONS)}, got {prediction!r}")
    check_same_shape("out", out, "x_t", x_t)
    if prediction == "velocity":
        return out
    check_range("min_sigma", min_sigma, 0.0, 1.0, lo_open=True)
    s = jnp.maximum(_levels(sigma, x_t), min_sigma)
    return ((x_t - out) / s).astype(x_t.dtype)
