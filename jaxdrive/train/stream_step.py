"""STAGE's training (STAGE [2506.13138v1] sec. C): the loss of one micro-batch of a streaming model.

Every clip ``x [B, V, F, h, w, C]`` (latent frames) gives one window ``[anchor, condition, new]``
= frames ``[0, j - 1, j]`` with ``j`` drawn per clip in ``1 .. F - 1`` (so the buffer of the new
frame holds anywhere from none to all of its taps, as at the start of a stream and later), the
new frame noised to a level drawn per clip, the two others clean; the loss is MiLA [2503.15875v1] eq. 15's over
the new frame, weighted by STAGE's W_aux when ``flow.foreground_k > 0``. The three stages are
one step with settings (``configs/stage.py``):

1. streaming learning: the condition frame is the recorded frame ``j - 1``; no taps (HTFT off).
2. HTFT learning: the taps on, the base frozen (``optim.trainable`` = HTFT's parameters). The
   features of the past frames ``j - 1, j - 5, j - 10`` at the same level come from a no-gradient
   pass of the same model over frames ``1 .. F - 2`` of the clip, frame by frame in a
   ``lax.scan``, each fusing its own past from the same pass: what the sampler's buffer holds
   (:func:`jaxdrive.generate.streaming.observe_frame` at one level), for recorded frames.
3. learning through simulating inference (``stream.self_rollout``): once per clip, the model
   streams the clip from its first frame (:func:`jaxdrive.generate.streaming.stream_frame`,
   ``stream.rollout_steps`` steps, its own HTFT buffer), without gradients; its frames are then
   the condition frames, of the window and of the feature pass, in place of the recorded ones.

Augmentation (all stages): ``stream.degrade_rate`` of the condition frames DCT low-passed
(:func:`jaxdrive.flow.degrade_frames`) and Gaussian noise of std ``stream.cond_noise`` on them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxdrive import flow
from jaxdrive.generate.streaming import gather_frames, noise_like
from jaxdrive.models.htft import check_taps, write_slot
from jaxdrive.models.tokens import VIDEO
from jaxdrive.parallel.rules import constrain
from jaxdrive.validate import check_positive_int, check_range


def check_stream(config, latent_frames: int, needs_init: bool = True) -> None:
    """The ``stream`` section against the rest of the config: ``ValueError`` naming the option.
    ``needs_init=False`` (a plan, which loads no weights): stage 2 may leave ``train.init_from`` unset."""
    s, m = config.stream, config.model
    if not s.enabled:
        return
    check_positive_int("stream.buffer", s.buffer)
    check_taps(s.taps, s.buffer, "stream.taps")
    if s.taps and not m.htft_layers:
        raise ValueError(
            f"stream.taps: HTFT needs a model with HTFT layers (model.htft_layers), got taps "
            f"{list(s.taps)} for a model without them (stage 1: stream.taps=())"
        )
    check_positive_int("stream.rollout_steps", s.rollout_steps)
    check_range("stream.degrade_rate", s.degrade_rate, 0.0, 1.0)
    check_range("stream.degrade_keep", s.degrade_keep, 0.0, 1.0, lo_open=True)
    check_range("stream.cond_noise", s.cond_noise, 0.0, float("inf"))
    if latent_frames < 2:
        raise ValueError(f"data.frames: streaming windows need clips of at least 2 latent frames, got {latent_frames}")
    f, d = config.flow, config.data
    for name, value, ok in (
        ("data.buckets", d.buckets, ()),
        ("flow.distill_teacher", f.distill_teacher, ""),
        ("flow.jdc_anchor_rate", f.jdc_anchor_rate, 0.0),
        ("flow.tpd", f.tpd, False),
        ("flow.structure_weight", f.structure_weight, 0.0),
    ):
        if value != ok:
            raise ValueError(f"{name}: expected {ok!r} with stream.enabled (one new frame per window), got {value!r}")
    if needs_init and s.taps and config.optim.trainable and not config.train.init_from:
        raise ValueError(
            "train.init_from: HTFT learning (STAGE stage 2) trains HTFT over a frozen stage-1 model "
            "(optim.trainable), expected the stage-1 run directory, got none"
        )


def _frame(x, j):
    """Latent frame ``j`` (an int array ``[B]``, or a scalar) of ``x [B, V, F, h, w, C]`` as ``[B, V, 1, ...]``."""
    j = jnp.broadcast_to(jnp.asarray(j, jnp.int32), (x.shape[0],))
    return gather_frames(x, j[:, None], 2)


def _augment(key, prev, stream):
    """STAGE's augmentation of the condition frames ``[B, V, 1, ...]``: DCT low-pass of a
    ``degrade_rate`` share, then noise of std ``cond_noise``."""
    k_mask, k_noise = jax.random.split(key)
    if stream.degrade_rate > 0:
        mask = jax.random.uniform(k_mask, (prev.shape[0], 1)) < stream.degrade_rate
        prev = flow.degrade_frames(prev, mask, stream.degrade_keep)
    if stream.cond_noise > 0:
        prev = prev + stream.cond_noise * noise_like(k_noise, prev)
    return prev


def stream_model(training, hw):
    """The :class:`jaxdrive.generate.windows.WindowModel` of the stage-3 rollout at ``hw`` pixels."""
    from jaxdrive.generate.windows import WindowModel

    s = training.stream
    from jaxdrive.generate.streaming import WINDOW

    return WindowModel(
        training.dit,
        None,
        window=WINDOW,
        steps=s.rollout_steps,
        shift=_shift(training, hw),
        streaming=True,
        stream_buffer=s.buffer,
        stream_taps=_taps(training),
        value_range=training.codec.value_range,
    )


def _taps(training) -> tuple[int, ...]:
    return tuple(training.stream.taps) if training.model.htft_layers else ()


def _shift(training, hw) -> float:
    """``flow.shift``, or the resolution rule's for a window at ``hw`` pixels (as the sampler)."""
    f = training.flow
    if f.shift > 0:
        return f.shift
    from jaxdrive.generate.streaming import WINDOW

    return flow.resolution_shift(*hw, WINDOW)


def self_rollout(training, params, x, cond, key):
    """Stage 3: the clip streamed by the model from its first frame, ``[B, V, F - 1, ...]`` (frames
    0 .. F - 2: the recorded first one, then the model's), without gradients."""
    from jaxdrive.generate.streaming import new_buffer, stream_frame, window_controls

    b, v, nf, h, w, _ = x.shape
    model, taps = stream_model(training, (h * training.codec.spatial, w * training.codec.spatial)), _taps(training)
    params = jax.lax.stop_gradient(params)
    buffer = new_buffer(model, b, v, (h, w)) if taps else None
    anchor = x[:, :, :1]

    def frame(carry, p):
        prev, buf = carry
        ctrl = window_controls(cond, jnp.full((b,), p), training.codec.temporal)
        new, buf = stream_frame(model, taps, params, anchor, prev, ctrl, jax.random.fold_in(key, p), buf)
        return (new, buf), new[:, :, 0]

    _, frames = jax.lax.scan(frame, (anchor, buffer), jnp.arange(1, nf - 1))
    return jax.lax.stop_gradient(jnp.concatenate([anchor, jnp.moveaxis(frames, 0, 2)], axis=2))


def past_features(training, params, x, given, cond, sigma, key):
    """Stage 2 / 3: the HTFT features of frames ``1 .. F - 2`` at the levels ``sigma [B]``, each
    from the window ``[x_0, given_{p-1}, given_p noised]`` fusing its own taps among the frames
    before it: ``{layer: [B, F, S, V, D]}`` (frame 0 and F - 1 zero), without gradients."""
    from jaxdrive.generate.streaming import window_controls

    taps, temporal = _taps(training), training.codec.temporal
    m = training.model
    b, v, nf, h, w, _ = x.shape
    s = (h // m.patch[1]) * (w // m.patch[2])
    params = jax.lax.stop_gradient(params)
    store = {i: constrain(jnp.zeros((b, nf, s, v, m.width), jnp.float32), VIDEO) for i in m.htft_layers}
    anchor = x[:, :, :1]

    def frame(store, p):
        pj = jnp.full((b,), p)
        feats, mask = select(store, pj, taps)
        noise = noise_like(jax.random.fold_in(key, p), anchor)
        window = jnp.concatenate([anchor, _frame(given, pj - 1), flow.add_noise(_frame(given, pj), noise, sigma)], 2)
        _, out = _forward(training, params, window, sigma, window_controls(cond, pj, temporal), feats, mask)
        return {i: write_slot(store[i], out[i], p, 1) for i in store}, None

    if nf > 2:
        store, _ = jax.lax.scan(frame, store, jnp.arange(1, nf - 1))
    return jax.lax.stop_gradient(store)


def select(store, j, taps):
    """The features of frames ``j + taps`` (``j [B]``) from a per-frame ``store``:
    ``({layer: [B, K, S, V, D]}, mask [B, K])``, mask False for frames before frame 1 (the anchor
    frame has no features)."""
    idx = j[:, None] + jnp.asarray(taps, jnp.int32)[None]
    mask = idx >= 1
    return {k: gather_frames(a, jnp.maximum(idx, 0), 1) for k, a in store.items()}, mask


def _forward(training, params, window, sigma, cond, features, features_mask):
    """The DiT on a streaming window, the new frame at ``sigma [B]``: ``(velocity, the new slot's
    features)`` (:func:`jaxdrive.generate.streaming.window_velocity`, as the sampler)."""
    from jaxdrive.generate.streaming import window_conditions, window_velocity

    mask, cond = window_conditions(training.dit, window, cond)
    levels = jnp.where(mask, 0.0, sigma[:, None])
    past = None if features is None else {"features": features, "mask": features_mask}
    return window_velocity(training.dit, params)(window, levels, cond, past)


def stream_loss_fn(training, params, x, inputs: dict, key):
    """The loss of one micro-batch of latents ``x`` (module docstring) and its metrics."""
    from jaxdrive.generate.streaming import COND_MASK, window_controls

    cond, loss_fields = inputs["cond"], inputs.get("loss")
    s, f, temporal = training.stream, training.flow, training.codec.temporal
    b, _, nf, h, w, _ = x.shape
    k_j, k_sig, k_noise, k_roll, k_past, k_aug = jax.random.split(key, 6)
    j = jax.random.randint(k_j, (b,), 1, nf)
    hw = (h * training.codec.spatial, w * training.codec.spatial)
    sigma = flow.sample_sigmas(
        k_sig, (b,), distribution=f.sigma_sampling, loc=f.logit_loc, scale=f.logit_scale, shift=_shift(training, hw)
    )
    given = self_rollout(training, params, x, cond, k_roll) if s.self_rollout else x
    taps = _taps(training)
    feats = mask = None
    if taps:
        feats, mask = select(past_features(training, params, x, given, cond, sigma, k_past), j, taps)
    target = _frame(x, j)
    noise = noise_like(k_noise, target)
    anchor, prev = x[:, :, :1], _augment(k_aug, _frame(given, j - 1), s)
    window = jnp.concatenate([anchor, prev, flow.add_noise(target, noise, sigma)], axis=2)
    v, _ = _forward(training, params, window, sigma, window_controls(cond, j, temporal), feats, mask)
    clean = jnp.concatenate([anchor, prev, target], axis=2)
    noise3 = jnp.concatenate([jnp.zeros_like(anchor), jnp.zeros_like(prev), noise], axis=2)
    weight_map = None
    if loss_fields:
        frames = jnp.stack([jnp.zeros_like(j), temporal * (j - 1), temporal * j], axis=1)  # newest pixel frame
        pick = lambda a: gather_frames(a, frames, 1)
        weight_map = flow.foreground_weight_map(
            pick(loss_fields["boxes"]),
            pick(loss_fields["box_valid"]),
            loss_fields["intrinsics"],
            loss_fields["cam_to_ego"],
            map_hw=(h, w),
            image_hw=hw,
            k=f.foreground_k,
            c=f.foreground_c,
        )
    cond_mask = jnp.broadcast_to(jnp.asarray(COND_MASK), (b, 3))
    loss = flow.flow_loss(v, clean, noise3, cond_mask=cond_mask, weight_map=weight_map)
    return loss, {"flow_loss": loss, "loss": loss}
