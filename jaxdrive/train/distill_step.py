"""LongDWM's fine-to-coarse flow distillation inside the train step (sec. 3.3, eq. 7-8).

The batch holds dense clips of ``F = n (K - 1) + 1`` frames (``data.frames``; K =
``flow.distill_segment_len``). The model being trained is the coarse one: it sees the ``n + 1``
coarse frames ``0, K-1, 2(K-1), ...`` with their per-frame controls and ``fps / (K - 1)``. One
level per clip (condition frames clean) and one noise draw cover the whole dense clip, so the
coarse model's noisy input is exactly the coarse frames of the dense noisy clip (eq. 7). The
frozen fine model (the run in ``flow.distill_teacher``) denoises each K-frame segment on its own,
one segment at a time (a ``lax.map``, so only one segment's activations are live), with the
segment's controls: per-frame ones sliced, waypoints re-expressed in the ego frame of the
segment's first frame (as the data pipeline gives them for a clip starting there). Eq. 8 pulls
the coarse model's data estimates towards the fine model's at the coarse frames
(:func:`jaxdrive.flow.distill_loss`), next to its own flow loss.

The fine model must read the same latents frame by frame: LongDWM's coarse model encodes frames
one by one, and a segment boundary is a latent frame only without temporal compression.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec

from jaxdrive import flow
from jaxdrive.data.batches import POSES
from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.parallel.mesh import explicit_mesh, spec_of


def coarse_conditions(cond: Conditions, segment_len: int) -> Conditions:
    """The coarse model's conditions: per-frame ones at the coarse frames, ``fps / (K - 1)``."""
    step = segment_len - 1
    cond = cond.per_frame(lambda _, v: v[:, ::step])
    return cond if cond.fps is None else cond.replace(fps=cond.fps / step)


def coarse_fields(fields: dict, segment_len: int) -> dict:
    """Per-frame arrays of a dict (the W_aux loss's boxes) at the coarse frames; the rest as is."""
    return {k: v[:, :: segment_len - 1] if k in ("boxes", "box_classes", "box_valid") else v for k, v in fields.items()}


def relative_waypoints(poses):
    """Ego positions ``[B, K, 2]`` in the ego frame of each clip's first pose, from
    ``ego_to_world [B, K, 4, 4]``: ``(R_0^T (t_k - t_0))_xy`` (the pipeline's waypoints)."""
    r0 = poses[:, 0, :3, :3]
    d = poses[:, :, :3, 3] - poses[:, :1, :3, 3]
    return jnp.einsum("bji,bkj->bki", r0, d)[..., :2]


def segment_conditions(cond: Conditions, poses, start, segment_len: int) -> Conditions:
    """The fine model's conditions for the segment of K frames from ``start`` (traced is fine):
    per-frame ones sliced, waypoints re-expressed in the ego frame of the segment's first pose
    (``poses``: the clip's ``ego_to_world [B, F, 4, 4]``)."""
    cut = lambda v: jax.lax.dynamic_slice_in_dim(v, start, segment_len, axis=1)
    out = cond.per_frame(lambda _, v: cut(v))
    return out if cond.waypoints is None else out.replace(waypoints=relative_waypoints(cut(poses)))


def teacher_coarse_estimate(teacher, params, x, x_t, levels, cond, inputs: dict, *, segment_len: int, boundary: str):
    """The frozen fine model's data estimates at the coarse frames, ``[B, V, n + 1, h, w, C]``.

    ``teacher``: the fine :class:`jaxdrive.models.dit.model.DiT`; ``x``, ``x_t`` the clean and noisy
    dense latents; ``levels``, ``cond`` ``[B, F]`` dense levels and condition frames;
    ``inputs`` the fine model's ``{"cond": Conditions, POSES: ego poses}``
    (:func:`jaxdrive.data.batches.model_inputs` with ``teacher``)."""
    frames, axis = x.shape[-4], x.ndim - 4
    n = (frames - 1) // (segment_len - 1)

    def segment(i):
        start = i * (segment_len - 1)
        cut = lambda a, ax: jax.lax.dynamic_slice_in_dim(a, start, segment_len, axis=ax)
        xs, ls = cut(x_t, axis), cut(levels, 1)
        seg_cond = segment_conditions(inputs["cond"], inputs[POSES], start, segment_len)
        if teacher.config.controls.cond_frames is not None:
            seg_cond = seg_cond.replace(cond_latents=cut(x, axis), cond_mask=cut(cond, 1))
        c = teacher.config
        v = flow.velocity_from_output(
            teacher.forward(params, xs, ls, seg_cond), xs, ls, c.prediction, c.prediction_min_sigma
        )
        d = unsharded_axis(flow.data_from_velocity(xs, v, ls), axis)
        return jnp.take(d, 0, axis=axis), jnp.take(d, segment_len - 1, axis=axis)

    first, last = jax.lax.map(segment, jnp.arange(n))  # [n, B, V, h, w, C] each
    coarse = flow.coarse_from_ends(jnp.moveaxis(first, 0, 1), jnp.moveaxis(last, 0, 1), boundary=boundary)
    return jax.lax.stop_gradient(jnp.moveaxis(coarse, 1, axis))  # [B, n+1, V, ...] -> frame axis


def unsharded_axis(x, axis: int):
    """``x`` with dimension ``axis`` gathered under an Explicit mesh, where picking frames from an
    axis sharded over ``seq`` (even of size 1) is refused; ``x`` as it is otherwise."""
    spec = list(spec_of(x))
    if explicit_mesh() is None or spec[axis] is None:
        return x
    spec[axis] = None
    return jax.reshard(x, PartitionSpec(*spec))


def dense_levels(sigma, cond, frames: int, segment_len: int):
    """Dense levels and condition frames ``[B, F]`` from the coarse ones: every frame at the
    clip's level ``sigma [B]``, the coarse condition frames clean (eq. 7: one level per clip)."""
    cond_dense = jnp.zeros((cond.shape[0], frames), bool).at[:, :: segment_len - 1].set(cond)
    return jnp.where(cond_dense, 0.0, sigma[:, None]), cond_dense
