"""STAGE's streaming generation: one new (latent) frame at a time, with the HTFT feature buffer.

Frame ``j`` is denoised in a window of three latent frames, ``[anchor, condition, new]`` = the
clip's first frame (global consistency), frame ``j - 1`` (the condition frame) and the new frame,
the first two clean and pinned, under the controls of those three frames (STAGE [2506.13138v1] sec. A). With
HTFT (STAGE [2506.13138v1] sec. B), at denoising step ``i`` the ``htft_layers`` of the new window fuse the
features that the same layers produced at step ``i`` for the frames at ``taps`` (-1, -5, -10) of a
ring buffer of the last ``buffer`` (10) frames (:func:`jaxdrive.models.htft.buffer_init`: per
layer ``[steps, B, N, S, V, D]``, preallocated). The features a frame stores are those of its
window's new slot; the first frame (the anchor) has none.

- :func:`stream_frame`: the whole denoising loop of one frame, a ``lax.scan`` over the steps
  (:func:`jaxdrive.flow.sample` with per-step inputs: step i reads its buffer slot and returns the
  new features, written into the ring when the frame is done). Jitted with the buffer donated:
  the loop over frames compiles once and device memory stays flat in the length.
- :func:`observe_frame`: a given (recorded) frame's features, with the frame itself noised to
  each step's level: what the buffer holds for the given frames, and, at one level, what
  training's teacher-forced pass computes (:mod:`jaxdrive.train.stream_step`).
- :func:`streaming`: the strategy (:mod:`jaxdrive.generate.strategies`' interface): frames go to
  the host (and the mp4) as they are done.

Every frame's noise comes from ``fold_in(key, j)``; with no taps the strategy equals a
frame-by-frame rollout of :func:`jaxdrive.generate.windows.sample_window` over the same windows.
"""

from __future__ import annotations

from collections.abc import Iterator

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive import flow
from jaxdrive.generate.guidance import sampler_guidance
from jaxdrive.generate.windows import STREAM_WINDOW as WINDOW  # anchor, condition, new
from jaxdrive.generate.windows import Tracker, WindowModel, to_mesh
from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.models.htft import buffer_init, buffer_push, buffer_select
from jaxdrive.models.htft import check_taps as check_offsets
from jaxdrive.parallel.rules import constrain, reshard_like

NEW = 2  # the new frame's slot
COND_MASK = (True, True, False)


def window_frames(j, temporal: int):
    """The frames whose per-frame controls the window ``[0, j - 1, j]`` (latent frames) sees, at
    the controls' rate: ``[0, j - 1, j]`` for frame-wise latents; for a causal VAE of temporal
    compression ``t`` the ``1 + 2 t`` pixel frames ``[0] + latent(j - 1) + latent(j)``, where
    latent ``l >= 1`` covers pixel frames ``t (l - 1) + 1 .. t l`` and latent 0 only pixel frame 0
    (repeated). ``j``: an int or an int array ``[B]`` (then ``[B, 1 + 2 t]``)."""
    j = jnp.asarray(j, jnp.int32)[..., None]

    def latent(frame):
        return jnp.where(frame >= 1, temporal * (frame - 1) + 1 + jnp.arange(temporal), 0)

    return jnp.concatenate([jnp.zeros_like(j), latent(j - 1), latent(j)], axis=-1)


def window_controls(controls: Conditions, j, temporal: int) -> Conditions:
    """The per-frame fields of ``controls`` at :func:`window_frames` ``(j, temporal)``: on the host
    for an int ``j``, traced (one index per clip) for ``j [B]``."""
    idx = window_frames(j, temporal)
    if idx.ndim == 1:
        pos = np.asarray(idx)

        def take(name, v):
            v = np.asarray(v)
            if v.shape[1] <= pos.max():
                raise ValueError(
                    f"controls.{name}: expected at least {pos.max() + 1} frames for frame "
                    f"{int(np.max(j))}, got {v.shape[1]}"
                )
            return v[:, pos]

        return controls.per_frame(take)

    return controls.per_frame(lambda name, v: gather_frames(v, idx, 1))


def gather_frames(a, idx, axis: int):
    """``a``'s entries ``idx [B, K]`` along ``axis`` for each sample ``b`` (per-clip frames),
    keeping ``a``'s sharding (a gather with traced indices otherwise returns its own)."""
    ix = idx.reshape(idx.shape[:1] + (1,) * (axis - 1) + idx.shape[1:] + (1,) * (a.ndim - axis - 1))
    return reshard_like(jnp.take_along_axis(a, ix, axis=axis), a)


def noise_like(key, x):
    """Standard normal noise shaped and (under an Explicit mesh) sharded like ``x``."""
    return reshard_like(jax.random.normal(key, x.shape, jnp.float32), x)


def window_conditions(dit, window, cond: Conditions):
    """``(cond_mask [B, 3], cond)`` of a streaming ``window [B, V, 3, h, w, C]``: the anchor and
    condition slots given (and the condition-frame control fed the window)."""
    mask = jnp.broadcast_to(jnp.asarray(COND_MASK), (window.shape[0], WINDOW))
    if dit.config.controls.cond_frames is not None:
        cond = cond.replace(cond_latents=window, cond_mask=mask)
    return mask, cond


def window_inputs(model: WindowModel, anchor, prev, controls: Conditions):
    """``(x_cond [B, V, 3, h, w, C] (the new slot zero), cond_mask [B, 3], conditions)`` of one
    streaming window to sample (no guidance drops)."""
    x = jnp.concatenate([anchor, reshard_like(prev, anchor), jnp.zeros_like(anchor)], axis=2)
    mask, cond = window_conditions(model.dit, x, controls.replace(drop=None))
    return x, mask, cond


def window_velocity(dit, params):
    """``(x, sigma, cond, past) -> (v, the new slot's features {layer: [B, S, V, D]})`` of ``dit``
    on a streaming window; ``past``: ``{"features": {layer: [B, K, S, V, D]}, "mask": [B, K]}`` or
    None (no HTFT). The sampler passes it as per-step inputs, so guidance stacks it with its
    variants like every other batch input; the training step calls it directly."""
    m = dit.config

    def velocity(x, sigma, c, past):
        if past is not None:
            c = c.replace(features=past["features"], features_mask=past["mask"])
        out, feats = dit.forward(params, x, sigma, c, return_features=True)
        v = flow.velocity_from_output(out, x, sigma, m.prediction, m.prediction_min_sigma)
        return v, {k: f[:, NEW] for k, f in feats.items()}

    return velocity


def _per_step(buffer, taps):
    """The buffer's taps as per-step inputs: ``{"features": [steps, B, K, S, V, D] per layer,
    "mask": [steps, B, K]}``."""
    past, mask = buffer_select(buffer, taps)
    steps = jax.tree_util.tree_leaves(past)[0].shape[0]
    return {"features": past, "mask": jnp.broadcast_to(mask, (steps,) + mask.shape)}


def stream_frame(
    model: WindowModel, taps: tuple[int, ...], params, anchor, prev, controls: Conditions, key, buffer=None
):
    """One new latent frame ``[B, V, 1, h, w, C]`` after ``anchor`` and ``prev`` (``[B, V, 1, h,
    w, C]`` each) under the window's ``controls`` (:func:`window_controls`), and the buffer with its
    features pushed (``buffer`` None or no ``taps``: HTFT off, returns None); the frame is clipped to
    ``model.value_range`` (:meth:`WindowModel.in_range`). Guidance as
    :func:`jaxdrive.generate.windows.sample_window` (``controls.drop``: the conditions it drops,
    and each clip's own drops)."""
    m = model.dit.config
    x_cond, mask, cond = window_inputs(model, anchor, prev, controls)
    guidance = sampler_guidance(cond, controls.drop or {}, x_cond.shape[0], model.guidance, model.control_guidance)
    schedule = flow.frame_schedule(flow.sampling_sigmas(model.steps, shift=model.shift), mask)
    noise = noise_like(key, x_cond)
    x0 = jnp.where(mask[:, None, :, None, None, None], x_cond, noise)
    if buffer is None or not taps or not m.htft_layers:
        out = flow.sample(
            lambda x, s, c: window_velocity(model.dit, params)(x, s, c, None)[0],
            x0,
            schedule,
            cond_mask=mask,
            **guidance,
        )
        return model.in_range(out[:, :, NEW:]), None
    out, feats = flow.sample(
        window_velocity(model.dit, params),
        x0,
        schedule,
        cond_mask=mask,
        step_inputs=_per_step(buffer, taps),
        **guidance,
    )
    return model.in_range(out[:, :, NEW:]), buffer_push(buffer, feats)


def observe_frame(
    model: WindowModel,
    taps: tuple[int, ...],
    params,
    anchor,
    prev,
    frame,
    controls: Conditions,
    key,
    buffer,
    sigmas=None,
):
    """A known ``frame``'s features pushed into ``buffer``: at each level of ``sigmas`` (default
    the sampling schedule's levels before the last) the window ``[anchor, prev, frame noised to
    that level]`` through the model, fusing the buffer's taps as a generated frame would (with
    each clip's drops of ``controls.drop``, as the conditional branch of a generated frame's guidance)."""
    x_cond, mask, cond = window_inputs(model, anchor, prev, controls)
    cond = cond.replace(drop=controls.drop)
    if sigmas is None:
        sigmas = flow.sampling_sigmas(model.steps, shift=model.shift)[:-1]
    noise = noise_like(key, frame)
    velocity = window_velocity(model.dit, params)

    def step(_, xs):
        s, past = xs
        x = x_cond.at[:, :, NEW:].set(flow.add_noise(frame, noise, jnp.broadcast_to(s, (frame.shape[0],))))
        levels = jnp.where(mask, 0.0, s)
        return None, velocity(x, levels, cond, past)[1]

    sigmas = jnp.asarray(sigmas, jnp.float32)
    _, new = jax.lax.scan(step, None, (sigmas, _per_step(buffer, taps)))
    return buffer_push(buffer, new)


_STREAM = jax.jit(stream_frame, static_argnums=(0, 1), donate_argnums=(7,))
_OBSERVE = jax.jit(observe_frame, static_argnums=(0, 1), donate_argnums=(8,))


BUFFER_AXES = (None, "batch", None, "tokens", "views", "embed")  # [steps, B, slots, S, V, D]


def new_buffer(model: WindowModel, batch: int, views: int, latent_hw: tuple[int, int]):
    """The empty ring of ``model``: ``model.stream_buffer`` frames x ``model.steps`` steps per HTFT
    layer, for windows of ``views`` views of ``latent_hw`` latents."""
    m = model.dit.config
    s = (latent_hw[0] // m.patch[1]) * (latent_hw[1] // m.patch[2])
    buf = buffer_init({i: (batch, s, views, m.width) for i in m.htft_layers}, model.stream_buffer, steps=model.steps)
    # sharded like the features it stores: zeros alone come replicated, and under a mesh the ring of
    # the whole batch (STAGE's stage-3 step at paper size: 126 GiB) sat on every device
    buf["data"] = {i: constrain(a, BUFFER_AXES) for i, a in buf["data"].items()}
    return buf


def buffer_bytes(model: WindowModel, batch: int, views: int, latent_hw: tuple[int, int]) -> int:
    """Device bytes of :func:`new_buffer` (fixed: it never grows)."""
    shapes = jax.eval_shape(lambda: new_buffer(model, batch, views, latent_hw))
    return int(sum(x.size * x.dtype.itemsize for x in jax.tree_util.tree_leaves(shapes)))


def check_taps(models, taps) -> tuple[int, ...]:
    """``taps`` of ``streaming`` for ``models`` (a :class:`jaxdrive.generate.strategies.Models`;
    None: the model's own): offsets within its buffer, and only for a model with HTFT layers;
    ``ValueError`` naming ``taps``."""
    main = models.main
    if taps is None:
        return main.stream_taps
    taps = check_offsets(taps, main.stream_buffer, "taps")
    if taps and not main.dit.config.htft_layers:
        raise ValueError(
            f"taps: HTFT streaming needs a model with HTFT layers (model.htft_layers, STAGE stage 2), "
            f"got taps {list(taps)} for a model without them"
        )
    return taps


def streaming(
    models, controls: Conditions, first, length: int, *, key, tracker: Tracker | None = None, mesh=None, taps=None
) -> Iterator[np.ndarray]:
    """STAGE's streaming strategy (module docstring): the given frames ``first [B, V, k, h, w, C]``
    (the first is the anchor) are observed into the buffer, then each next latent frame is
    sampled from the anchor and the frame before it and yielded at once. ``taps`` default to the
    model's (its run's ``stream.taps``); ``()`` turns HTFT off."""
    tracker = tracker or Tracker()
    model = models.main
    taps = check_taps(models, taps)
    first = np.asarray(first, np.float32)
    b, v, given, h, w, _ = first.shape
    htft = bool(taps)
    buffer = new_buffer(model, b, v, (h, w)) if htft else None
    tracker.notes["stream"] = {
        "buffer_frames": model.stream_buffer if htft else 0,
        "taps": list(taps),
        "buffer_bytes": buffer_bytes(model, b, v, (h, w)) if htft else 0,
    }
    anchor = to_mesh(first[:, :, :1], mesh)
    yield first
    prev = first[:, :, :1]
    for j in range(1, length):
        ctrl = to_mesh(window_controls(controls, j, model.temporal), mesh)
        k = jax.random.fold_in(key, j)
        if j < given:  # a given frame: only its features are needed
            frame = first[:, :, j : j + 1]
            if htft:
                buffer = tracker.call(
                    model,
                    model.params,
                    anchor,
                    to_mesh(prev, mesh),
                    to_mesh(frame, mesh),
                    ctrl,
                    k,
                    buffer,
                    fn=_OBSERVE,
                    static=(taps,),
                )
        else:
            out, buffer = tracker.call(
                model, model.params, anchor, to_mesh(prev, mesh), ctrl, k, buffer, fn=_STREAM, static=(taps,)
            )
            frame = np.array(out)  # a copy: on a CPU asarray would keep the device buffer alive
            del out
            yield frame
        prev = frame
