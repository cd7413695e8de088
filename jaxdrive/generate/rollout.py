"""Sampling a clip with the trained DiT, and rolling windows out to long videos.

:func:`sample_window` draws one window of latents with the jitted sampler
(:func:`jaxdrive.flow.sample`): the first frames are clean condition frames (pinned, level 0),
the others start from noise and follow the per-frame schedule of
:func:`jaxdrive.flow.frame_schedule` (TPD when the run trained with it), with classifier-free
guidance against the learned nulls of every droppable condition the model uses.

:func:`rollout` reaches clips longer than the training window autoregressively (the streaming of
STAGE / MiLA's continuation): each next window overlaps the last ``overlap`` generated latent
frames, which it takes as its condition frames, and reads the per-frame controls (waypoints,
poses, boxes, map) of its own frames. Every window has the training window's length, so the
sampler compiles once; a last window that would run past the end starts earlier and conditions
on all frames it overlaps.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from jaxdrive import flow
from jaxdrive.models.conditions import Conditions
from jaxdrive.models.dit import DiT
from jaxdrive.validate import check_positive_int


def _velocity_fn(dit: DiT, params):
    m = dit.config

    def velocity(x, sigma, cond):
        out = dit.forward(params, x, sigma, cond)
        return flow.velocity_from_output(out, x, sigma, m.prediction, m.prediction_min_sigma)
    return velocity


def sample_window(dit: DiT, params, x_cond, cond_mask, controls: Conditions, key, *, steps: int,
                  guidance: float, shift: float = 1.0, tpd: bool = False, tpd_omega: float = np.pi / 2,
                  method: str = "euler"):
    """Latents ``[B, V, F', h, w, C]`` of one window: ``x_cond`` holds the clean condition frames
    where ``cond_mask [B, F']`` is set; ``controls`` are the window's conditions, whose ``drop``
    names the conditions guidance drops (all of them at once, against their learned nulls)."""
    names = list(controls.drop or {})
    cond = controls.replace(drop=None)
    if dit.config.controls.cond_frames is not None:
        cond = cond.replace(cond_latents=x_cond, cond_mask=cond_mask)
    b = x_cond.shape[0]
    null = None
    if names and guidance != 1.0:
        cond = cond.with_drops(names, False, b)
        null = cond.with_drops(names, True, b)
    schedule = flow.frame_schedule(flow.sampling_sigmas(steps, shift=shift), cond_mask,
                                   tpd=tpd, omega=tpd_omega)
    noise = jax.random.normal(key, x_cond.shape, jnp.float32)
    keep = cond_mask[:, None, :, None, None, None]
    x0 = jnp.where(keep, x_cond, noise)
    return flow.sample(_velocity_fn(dit, params), x0, schedule, cond=cond, null_cond=null,
                       guidance_scale=None if null is None else guidance, cond_mask=cond_mask, method=method)


def _window_controls(controls: Conditions, start: int, window: int, temporal: int) -> Conditions:
    """The conditions of latent frames ``[start, start + window)``; per-frame ones are per pixel
    frame when ``temporal > 1`` (``1 + temporal (F' - 1)`` frames)."""
    lo = start * temporal
    return controls.per_frame(lambda _, v: v[:, lo: lo + 1 + temporal * (window - 1)])


def window_starts(total_frames: int, window: int, overlap: int) -> list[int]:
    """The first latent frame of each window of a rollout: 0, then each next window overlaps the
    last ``overlap`` generated frames, and the last one ends at ``total_frames``."""
    for name, value in (("total_frames", total_frames), ("window", window), ("overlap", overlap)):
        check_positive_int(name, value)
    if total_frames > window and overlap >= window:       # the windows would not advance
        raise ValueError(f"overlap: expected fewer than window = {window} frames, got {overlap}")
    starts, done = [0], window
    while done < total_frames:
        starts.append(min(done - overlap, total_frames - window))
        done = starts[-1] + window
    return starts


def rollout(dit: DiT, codec, params, codec_params, inputs: dict, *, total_frames: int, window: int,
            overlap: int, cond_frames: int, steps: int, guidance: float, key, shift: float = 1.0,
            tpd: bool = False, tpd_omega: float = np.pi / 2, progress: bool = False):
    """Latents ``[B, V, total_frames, h, w, C]`` generated window by window (module docstring);
    ``progress``: a progress bar over the windows (on process 0).


    ``inputs``: :func:`jaxdrive.data.batches.model_inputs` of clips that cover the whole
    length (per-frame controls in ``cond`` for every frame; ``video`` needs only the first ``cond_frames``
    latent frames' pixels; a precomputed dataset gives ``latents`` instead, of at least ``window``
    frames). ``window``: latent frames per window (the training length);
    ``overlap``: frames each next window conditions on (``1 <= overlap < window``)."""
    check_positive_int("total_frames", total_frames)
    check_positive_int("window", window)
    check_positive_int("overlap", overlap)
    if overlap >= window:
        raise ValueError(f"overlap: expected fewer than window = {window} frames, got {overlap}")
    if not 0 <= cond_frames < min(window, total_frames):
        raise ValueError(f"cond_frames: expected in [0, {min(window, total_frames)}), got {cond_frames}")
    window = min(window, total_frames)
    controls = jax.tree_util.tree_map(jnp.asarray, inputs["cond"])
    if "latents" in inputs:                                            # stored (latents.precomputed)
        first = jnp.asarray(inputs["latents"])[:, :, :window]
    else:
        pixel_window = 1 + codec.temporal * (window - 1)
        first = codec.encode(codec_params, jnp.asarray(inputs["video"])[:, :, :pixel_window])  # [B, V, window, h, w, C]
    shape = first.shape[:2] + (total_frames,) + first.shape[3:]
    out = jnp.zeros(shape, jnp.float32, device=first.sharding)         # sharded like the windows
    sample = jax.jit(lambda p, xc, m, c, k: sample_window(dit, p, xc, m, c, k, steps=steps, guidance=guidance,
                                                          shift=shift, tpd=tpd, tpd_omega=tpd_omega))
    done = 0
    b = first.shape[0]
    starts = window_starts(total_frames, window, overlap)
    for start in tqdm(starts, unit="window", disable=not progress or jax.process_index() != 0):
        if done == 0:
            x_cond, n_cond = first, cond_frames
        else:
            x_cond = jax.lax.dynamic_slice_in_dim(out, start, window, axis=2)
            n_cond = done - start
        mask = jnp.broadcast_to(jnp.arange(window)[None] < n_cond, (b, window))
        key, sub = jax.random.split(key)
        z = sample(params, x_cond, mask, _window_controls(controls, start, window, codec.temporal), sub)
        out = jax.lax.dynamic_update_slice_in_dim(out, z, start, axis=2)
        done = start + window
        if progress:            # dispatch is asynchronous: wait, so that the bar counts finished windows
            out.block_until_ready()
    return out


def to_numpy_video(codec, codec_params, latents) -> np.ndarray:
    """Decoded video ``[B, V, F, H, W, 3]`` in [-1, 1] as NumPy."""
    return np.asarray(jax.jit(codec.decode)(codec_params, latents))
