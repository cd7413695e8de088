"""Training windows whose given frames are the model's own output (``flow.self_rollout_rate``).

A rollout's first window starts from recorded frames; every later one starts from frames the model
made, with their blur, drift and token grid, which a model trained on recorded given frames has
never seen (GameNGen, arXiv 2408.14837: quality "degrades fast after 20-30 steps" without noise on
its context; DIAMOND, arXiv 2405.12399, and STAGE's stage 3, ``stream.self_rollout``, train on the
model's own rollout instead). Here a step trains, with probability ``flow.self_rollout_rate``, the
second window of a two-window rollout of its clip, as ``jaxdrive sample --strategy rollout``
makes it:

1. the clip has ``2F - k`` frames (:func:`clip_frames`; ``F`` the window, ``data.frames``; ``k``
   its given frames, ``flow.cond_frames``);
2. the first window, frames ``0 .. F - 1`` with the recorded ``0 .. k - 1`` given, is sampled by
   the model in ``flow.self_rollout_steps`` Euler steps without gradients
   (:func:`jaxdrive.generate.windows.sample_window`: the sampler's own code, its given-frame
   noise ``flow.given_noise_sample``, no guidance);
3. the trained window is frames ``F - k .. 2F - k - 1``: its given frames are the first window's
   last ``k`` sampled ones, its other frames the recorded ones (the loss's targets); a warp-guided
   model's warp (``controls.warp``) comes from its own ``data.warp_frame``, a generated frame,
   warped along the recorded poses on the device (:func:`device_warp`).

Other steps train the first window, recorded given frames, as without the option. One coin a step
(``lax.cond``): a step that does not roll out costs what it did, a step that does about
``self_rollout_steps`` more forward passes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxdrive.parallel.rules import reshard_like


def clip_frames(frames: int, given: int, compression: int) -> int:
    """The pixel frames of a self-rollout clip: two windows of ``frames`` overlapping by ``given``
    (``2F - k``). Needs a frame-wise codec (``compression`` 1): a causal VAE's latent window does
    not start at an arbitrary pixel frame."""
    if compression != 1:
        raise ValueError(
            f"flow.self_rollout_rate: expected a frame-wise codec (temporal compression 1) for windows "
            f"that start at any frame, got temporal compression {compression}"
        )
    return 2 * frames - given


def fill_holes(frames, holes, iterations: int = 6):
    """``frames [..., H, W, C]`` with ``holes [..., H, W]`` filled on the device: each pass gives a
    hole pixel with known neighbours (3 x 3) their mean, and what is left after ``iterations``
    passes takes the frame's mean. The host's Navier-Stokes inpainting
    (:func:`jaxdrive.warp.inpaint_holes`) has no device twin; the warp's holes are thin bands at
    the borders, which a few passes cover."""
    known = (~holes)[..., None].astype(frames.dtype)
    x = frames * known

    def box(a):
        pad = [(0, 0)] * (a.ndim - 3) + [(1, 1), (1, 1), (0, 0)]
        a = jnp.pad(a, pad)
        h, w = a.shape[-3] - 2, a.shape[-2] - 2
        return sum(a[..., i : i + h, j : j + w, :] for i in range(3) for j in range(3))

    for _ in range(iterations):
        s, n = box(x), box(known)
        grown = n > 0
        x = jnp.where((known > 0) | ~grown, x, s / jnp.maximum(n, 1.0))
        known = jnp.maximum(known, grown.astype(known.dtype))
    total = jnp.sum(x, axis=(-3, -2), keepdims=True)
    count = jnp.maximum(jnp.sum(known, axis=(-3, -2), keepdims=True), 1.0)
    return jnp.where(known > 0, x, total / count)


def device_warp(pixels, poses, intrinsics, cam_to_ego, depth: float):
    """The depth-free warp of ``pixels [B, V, H, W, 3]`` (one frame a view) along ``poses [B, n, 4,
    4]`` (ego poses relative to that frame's), holes filled by :func:`fill_holes`: ``[B, V, n, H,
    W, 3]``; :func:`jaxdrive.warp.warp_views` on the device (LongDWM [2506.01546v1] appendix A.2,
    eq. 9)."""
    from jaxdrive.warp import camera_motion, depth_free_warp

    def one(image, k, motion):  # a view: [H, W, 3], [3, 3], [n, 4, 4]
        return depth_free_warp(image, k, motion, depth)

    motion = camera_motion(poses, cam_to_ego)  # [B, V, n, 4, 4]
    warped, holes = jax.vmap(jax.vmap(one))(pixels, intrinsics, motion)
    return fill_holes(warped, holes)


def _replicated(*arrays):
    """``arrays`` unsharded under an Explicit mesh (as they are without one)."""
    if jax.sharding.get_abstract_mesh().empty:
        return arrays
    return tuple(jax.reshard(a, jax.sharding.PartitionSpec()) for a in arrays)


def _window(cond, lo: int, hi: int, warp_latents):
    """The conditions of clip frames ``lo .. hi - 1`` (frame-wise: latent and pixel frames agree)."""
    out = cond.per_frame(lambda name, v: v[:, lo:hi])
    return out if warp_latents is None else out.replace(warp=warp_latents)


def _sampler_model(training, window: int, height: int, width: int):
    from jaxdrive import flow
    from jaxdrive.generate.windows import WindowModel

    f = training.flow
    shift = f.shift if f.shift > 0 else flow.resolution_shift(height, width, window)
    return WindowModel(
        training.dit,
        None,
        window=window,
        cond_frames=f.cond_frames,
        steps=f.self_rollout_steps,
        shift=shift,
        tpd=f.tpd,
        tpd_omega=f.tpd_omega,
        value_range=training.codec.value_range,
        given_noise=f.given_noise_sample,
    )


def training_window(training, params, codec_params, x, cond, inputs: dict, key):
    """``(x, cond, loss_fields)`` of the window a step trains (module docstring) from the latents
    ``x [B, V, 2F - k, h, w, C]`` of a self-rollout clip and its conditions ``cond`` (a warp-guided
    model's ``warp`` encoded for the whole clip, from the clip's frame ``training.warp_frame``)."""
    from jaxdrive.generate.windows import sample_window

    k = training.flow.cond_frames
    b, v, nf, h, w, _ = x.shape
    f = (nf + k) // 2
    if 2 * f - k != nf:
        raise ValueError(f"x: expected a clip of 2F - k latent frames (k = {k}), got {nf}")
    loss_fields = inputs.get("loss")
    warp, warp_frame = cond.warp, training.warp_frame

    def fields(lo):
        if not loss_fields:
            return loss_fields
        return {n: (a[:, lo : lo + f] if n in ("boxes", "box_valid") else a) for n, a in loss_fields.items()}

    def first(_):
        return x[:, :, :f], _window(cond, 0, f, None if warp is None else warp[:, :, :f]), fields(0)

    def second(_):
        hgt, wid = h * training.codec.spatial, w * training.codec.spatial
        given = jnp.broadcast_to(jnp.arange(f) < k, (b, f))
        ctrl = _window(cond, 0, f, None if warp is None else warp[:, :, :f]).replace(drop=None)
        made = sample_window(
            _sampler_model(training, f, hgt, wid), jax.lax.stop_gradient(params), x[:, :, :f], given, ctrl, key
        )
        made = jax.lax.stop_gradient(made)
        lo = f - k
        window = jnp.concatenate([made[:, :, lo:], x[:, :, f:]], axis=2)
        warp_b = None
        if warp is not None:  # from the window's own warp frame: a generated one
            src = training.codec.decode(codec_params, window[:, :, warp_frame : warp_frame + 1])[:, :, 0]
            # one frame a view, small: replicated, as the batched inverses and gathers want it
            src, e2w, k_, c2e = _replicated(
                src, inputs["warp"]["poses"][:, lo : lo + f], inputs["warp"]["intrinsics"], inputs["warp"]["cam_to_ego"]
            )
            rel = jnp.linalg.inv(e2w[:, warp_frame : warp_frame + 1]) @ e2w
            pixels = device_warp(src, rel, k_, c2e, training.warp_depth)
            warp_b = jax.lax.stop_gradient(training.codec.encode(codec_params, pixels))
        return window, _window(cond, lo, lo + f, warp_b), fields(lo)

    def second_like_first(_):  # both branches' outputs typed alike, shardings included
        return jax.tree_util.tree_map(reshard_like, second(_), first(_))

    coin = jax.random.bernoulli(jax.random.fold_in(key, 7), training.flow.self_rollout_rate)
    return jax.lax.cond(coin, second_like_first, first, None)
