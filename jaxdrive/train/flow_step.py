"""The rectified-flow train step of the DiT: the loss and the jitted update.

One step (:func:`make_train_step`) takes the train state and a stack of ``grad_accum``
micro-batches ``[A, b, ...]`` (each made on the host by :func:`jaxdrive.data.batches.model_inputs`:
the video or latents and the model's :class:`~jaxdrive.models.dit.conditions.Conditions`), and for
each micro-batch (in a ``lax.scan``):

1. encodes the video to latents ``x`` (:class:`jaxdrive.models.latents.LatentCodec`; a VAE runs
   on the fly, without gradients), or takes the batch's precomputed ``latents``;
2. draws a base level per clip (logit-normal or uniform, then Open-Sora's shift; SD3 eq. 19),
   a condition pattern per clip (:func:`jaxdrive.flow.draw_condition_masks`: ``flow.patterns``
   prefix / ends / anchors at ``flow.pattern_rates``) with ``k`` clean condition frames at the
   start (``0..cond_frames`` per clip, or exactly ``cond_frames``), the pattern's JDC anchors (at
   ``g = slope * sigma``, MiLA [2503.15875v1] sec. 3.3) for a fraction ``jdc_anchor_rate`` of clips, and
   per-frame levels by :func:`jaxdrive.flow.frame_sigmas` (TPD when on, MiLA [2503.15875v1] eq. 13-14);
3. noises ``x_sigma = (1 - sigma) x + sigma noise`` per frame (for a share ``flow.warp_path_rate``
   of the clips of a warp-guided model, the generated frames from the warp instead,
   :func:`jaxdrive.flow.warp_path`: the path ``sample.warp_start`` samples on), anchors as the sampler makes them
   (:func:`jaxdrive.flow.jdc_training_anchors`, MiLA [2503.15875v1] eq. 8-12: the truth plus alpha1 noise,
   re-noised to ``g``); the condition frames sit at level 0, i.e. clean, and the DiT sees level 0
   for them (and ``cond_latents`` when it has a condition-frame control);
4. predicts the velocity with the batch's classifier-free-guidance drops (the data pipeline draws
   them, 15% per condition by default) and takes MiLA [2503.15875v1] eq. 15's loss over the non-condition frames,
   anchors included (weighted per pixel by STAGE's foreground map W_aux when
   ``flow.foreground_k > 0``), plus LongDWM's structure-preservation loss when weighted, plus
   LongDWM's fine-to-coarse distillation from a frozen fine model when ``flow.distill_teacher``
   names one (:mod:`jaxdrive.train.distill_step`).

With ``stream.enabled`` steps 2-4 are STAGE's frame-by-frame loss instead
(:mod:`jaxdrive.train.stream_step`). With ``flow.self_rollout_rate`` the batch holds two windows
of a rollout and the step trains one of them, the second with the model's own frames given
(:mod:`jaxdrive.train.self_rollout`).

Gradients are averaged over the micro-batches, then :func:`jaxdrive.train.state.apply_gradients`
updates (or skips a non-finite step). The step is jitted with the state's shardings as in/out
shardings and the state donated; the batch is ``[A, b, ...]`` sharded over ``data``/``fsdp`` on
axis 1, activations shard their tokens over ``seq`` inside the DiT.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive import flow
from jaxdrive.config import FlowConfig, StreamConfig
from jaxdrive.models.dit.config import DiTConfig
from jaxdrive.models.dit.model import DiT
from jaxdrive.models.latents import LatentCodec
from jaxdrive.train import distill_step
from jaxdrive.train.state import TrainState, apply_gradients_and_norm


# ------------------------------------------------------------------------------ the loss
@dataclasses.dataclass(frozen=True)
class FlowTraining:
    """What the loss needs besides parameters and data (hashable: a static jit argument)."""

    model: DiTConfig
    flow: FlowConfig
    codec: LatentCodec
    teacher: DiTConfig | None = None  # the frozen fine model of LongDWM's distillation
    stream: StreamConfig = StreamConfig()  # STAGE's frame-by-frame training when enabled
    # a warp-guided model's data.warp_frame and data.warp_depth, for the warps the step makes itself
    # (flow.self_rollout_rate: jaxdrive.train.self_rollout)
    warp_frame: int = 0
    warp_depth: float = 0.0

    @property
    def dit(self) -> DiT:
        return DiT(self.model)


def draw_levels(key, x, config: FlowConfig, *, height: int, width: int):
    """Per-clip base levels, condition and anchor masks, per-frame levels (step 2 of the module
    docstring): ``(sigma [B], cond_mask [B, F'], levels [B, F'], anchor_mask [B, F'])``."""
    b, nf = x.shape[0], x.shape[-4]
    k_sig, k_masks = jax.random.split(key)
    shift = config.shift if config.shift > 0 else flow.resolution_shift(height, width, nf)
    sigma = flow.sample_sigmas(
        k_sig, (b,), distribution=config.sigma_sampling, loc=config.logit_loc, scale=config.logit_scale, shift=shift
    )
    cond, anchor = flow.draw_condition_masks(
        k_masks,
        b,
        nf,
        patterns=config.patterns,
        pattern_rates=config.pattern_rates,
        cond_frames=config.cond_frames,
        cond_frames_random=config.cond_frames_random,
        anchor_every=config.anchor_every,
        anchor_rate=config.jdc_anchor_rate,
    )
    levels = flow.frame_sigmas(
        sigma, cond, anchor_mask=anchor, tpd=config.tpd, omega=config.tpd_omega, anchor_slope=config.jdc_slope
    )
    return sigma, cond, levels, anchor


def foreground_weights(training: FlowTraining, fields: dict, x, *, height: int, width: int):
    """STAGE's W_aux ``[B, V, F', h, w]`` for latents ``x``: latent frame j takes the boxes of
    pixel frame ``temporal * j`` (the newest frame a causal VAE's latent j has seen)."""
    frames = np.arange(x.shape[-4]) * training.codec.temporal
    f = training.flow
    return flow.foreground_weight_map(
        fields["boxes"][:, frames],
        fields["box_valid"][:, frames],
        fields["intrinsics"],
        fields["cam_to_ego"],
        map_hw=x.shape[-3:-1],
        image_hw=(height, width),
        k=f.foreground_k,
        c=f.foreground_c,
    )


def flow_loss_fn(training: FlowTraining, params, codec_params, inputs: dict, key, teacher_params=None):
    """The loss of one micro-batch and its metrics (steps 1-4 of the module docstring)."""
    cond, loss_fields, teacher_inputs = inputs["cond"], inputs.get("loss"), inputs.get("teacher")
    # precomputed latents (jaxdrive data encode) or the video encoded here
    x = (
        inputs["latents"]
        if "latents" in inputs
        else (jax.lax.stop_gradient(training.codec.encode(codec_params, inputs["video"])))
    )
    if training.model.controls.warp:  # LongDWM's warped frames enter encoded, like the latents
        if "warp_video" not in inputs:
            raise ValueError(
                "inputs: expected 'warp_video' (the pipeline's warp_depth > 0) for a model with controls.warp, got none"
            )
        cond = cond.replace(warp=jax.lax.stop_gradient(training.codec.encode(codec_params, inputs["warp_video"])))
    if training.flow.self_rollout_rate > 0:  # a rollout's first or (its given frames the model's) second window
        from jaxdrive.train.self_rollout import training_window

        x, cond, loss_fields = training_window(
            training, params, codec_params, x, cond, inputs, jax.random.fold_in(key, 11)
        )
    if training.stream.enabled:  # STAGE: one [anchor, condition, new] window per clip
        from jaxdrive.train.stream_step import stream_loss_fn

        return stream_loss_fn(training, params, x, inputs, key)
    height, width = x.shape[-3] * training.codec.spatial, x.shape[-2] * training.codec.spatial
    k_levels, k_noise = jax.random.split(key)
    noise = jax.random.normal(k_noise, x.shape, jnp.float32)
    distill = training.teacher is not None
    if distill:  # the coarse model sees the coarse frames of the dense clip
        seg = training.flow.distill_segment_len
        dense, dense_noise = x, noise
        x, noise = flow.dense_to_coarse(x, seg), flow.dense_to_coarse(noise, seg)
        cond = distill_step.coarse_conditions(cond, seg)
        loss_fields = loss_fields and distill_step.coarse_fields(loss_fields, seg)
    sigma, given, levels, anchor = draw_levels(k_levels, x, training.flow, height=height, width=width)
    if training.flow.jdc_anchor_rate > 0:  # anchors as the sampler makes them; noise = their flow noise
        x_t, noise = flow.jdc_training_anchors(
            jax.random.fold_in(k_noise, 1), x, noise, levels, anchor, training.flow.jdc_alpha1
        )
    else:
        x_t = flow.add_noise(x, noise, levels)
    if training.flow.warp_path_rate > 0:  # SDEdit's path: these clips' generated frames noised from the warp
        coin = jax.random.bernoulli(jax.random.fold_in(k_noise, 3), training.flow.warp_path_rate, (x.shape[0],))
        x_t, noise = flow.warp_path(x, noise, cond.warp, levels, coin[:, None] & ~given)
    if training.model.controls.cond_frames is not None:
        cond = cond.replace(cond_latents=x, cond_mask=given)
        if training.flow.given_noise_max > 0:  # GameNGen: the context noised, its level told
            k_given = jax.random.fold_in(k_noise, 2)
            level = jax.random.uniform(
                jax.random.fold_in(k_given, 1), (x.shape[0],), maxval=training.flow.given_noise_max
            )
            noisy, cond_sigma = flow.noise_given_frames(
                x, jax.random.normal(k_given, x.shape, jnp.float32), given, level
            )
            cond = cond.replace(cond_latents=noisy, cond_sigma=cond_sigma)
    m = training.model
    v = flow.velocity_from_output(
        training.dit.forward(params, x_t, levels, cond), x_t, levels, m.prediction, m.prediction_min_sigma
    )
    weight_map = None
    if loss_fields:
        weight_map = foreground_weights(training, loss_fields, x, height=height, width=width)
    loss = flow.flow_loss(v, x, noise, cond_mask=given, weight_map=weight_map)
    metrics = {"flow_loss": loss}
    f = training.flow
    if f.structure_weight > 0:
        s = flow.structure_loss(flow.data_from_velocity(x_t, v, levels), x, cutoff=f.structure_cutoff, cond_mask=given)
        metrics["structure_loss"] = s
        loss = loss + f.structure_weight * s
    if distill:
        d_levels, d_cond = distill_step.dense_levels(sigma, given, dense.shape[-4], seg)
        target = distill_step.teacher_coarse_estimate(
            DiT(training.teacher),
            teacher_params,
            dense,
            flow.add_noise(dense, dense_noise, d_levels),
            d_levels,
            d_cond,
            teacher_inputs,
            segment_len=seg,
            boundary=f.distill_boundary,
        )
        d = flow.distill_loss(flow.data_from_velocity(x_t, v, levels), target, cond_mask=given)
        metrics["distill_loss"] = d
        loss = loss + f.distill_weight * d
    metrics["loss"] = loss
    return loss, metrics


def train_step(training: FlowTraining, optimizer, ema_decay: float, state: TrainState, frozen, batch: dict):
    """One update from the micro-batches ``batch`` (leaves ``[A, b, ...]``). ``frozen``: the
    parameters that are not trained, ``{"codec": VAE params, "teacher": fine DiT params}`` (either
    may be None; None for both). Returns ``(state, metrics)``; metrics are means over the
    micro-batches plus ``grad_norm``, ``skipped`` and ``bad_steps``."""
    frozen = frozen or {}
    codec_params, teacher_params = frozen.get("codec"), frozen.get("teacher")
    key, next_key = jax.random.split(state.key)
    n = jax.tree_util.tree_leaves(batch)[0].shape[0]
    keys = jax.random.split(key, n)
    grad_fn = jax.value_and_grad(
        lambda p, inp, k: flow_loss_fn(training, p, codec_params, inp, k, teacher_params), has_aux=True
    )

    def micro(acc, xs):
        inp, k = xs
        (_, metrics), grads = grad_fn(state.params, inp, k)
        return jax.tree_util.tree_map(jnp.add, acc, (grads, metrics)), None

    first = jax.tree_util.tree_map(lambda x: x[0], batch)
    if n == 1:  # no loop: a one-trip scan still costs a zeroed gradient tree and an add per leaf
        (_, metrics), grads = grad_fn(state.params, first, keys[0])
    else:
        zeros = jax.tree_util.tree_map(jnp.zeros_like, state.params)
        m0 = jax.eval_shape(lambda: grad_fn(state.params, first, keys[0])[0][1])
        m0 = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), m0)
        (grads, metrics), _ = jax.lax.scan(micro, (zeros, m0), (batch, keys))
        grads = jax.tree_util.tree_map(lambda g: g / n, grads)
        metrics = {k: v / n for k, v in metrics.items()}
    new, grad_norm = apply_gradients_and_norm(
        state, grads, metrics["loss"], optimizer, ema_decay, jax.random.key_data(next_key)
    )
    metrics.update(grad_norm=grad_norm, skipped=new.skipped, bad_steps=new.bad_steps)
    return new, metrics


def make_train_step(training: FlowTraining, optimizer, ema_decay: float, *, state_shardings):
    """``train_step`` jitted with the state's shardings in and out and the state donated; the
    frozen params (VAE, teacher) and the batch keep the shardings they come with
    (:meth:`jaxdrive.train.run.Run.global_batch`). Call it under ``jax.set_mesh(mesh)``."""
    fn = lambda state, frozen, batch: train_step(training, optimizer, ema_decay, state, frozen, batch)
    return jax.jit(
        fn, in_shardings=(state_shardings, None, None), out_shardings=(state_shardings, None), donate_argnums=(0,)
    )
