"""LongDWM's fine-to-coarse flow distillation, sec. 3.3, eq. 7-8.

A dense clip of ``F = n * (K - 1) + 1`` frames (eq. 7; the paper uses K = 13, n = 12, F = 145)
holds ``n + 1`` coarse frames at indices ``0, K-1, 2(K-1), ...``; consecutive coarse frames bound
segments of K frames that share their end frames. One noise draw and one level are applied to the
whole dense clip; the frozen fine model (teacher) denoises each segment on its own, the coarse
model (student) denoises the coarse frames (the same noisy latents, picked out of the dense
clip), and eq. 8 pulls the student's coarse predictions towards the teacher's:

    L_distill = || D^f_frozen(v(d, t))[c1 .. cK] - D^c(v(d, t)[c1 .. cK]) ||^2          (eq. 8)

Indices count the models' latent frames. Layout ``[B, ..., F, h, w, C]`` (frame axis -4).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxdrive.flow.rectified import FRAME_AXIS, expand_per_frame
from jaxdrive.validate import check_choice, check_positive_int, check_same_shape, check_shape

BOUNDARIES = ("mean", "start", "end")


def _num_segments(frames: int, segment_len: int, name: str) -> int:
    segment_len = check_positive_int("segment_len", segment_len, minimum=2)
    if frames < segment_len or (frames - 1) % (segment_len - 1):
        raise ValueError(
            f"{name}: expected n * (segment_len - 1) + 1 frames with n >= 1 (segment_len = {segment_len}), got {frames}"
        )
    return (frames - 1) // (segment_len - 1)


def coarse_indices(frames: int, segment_len: int):
    """Indices of the coarse frames in a dense clip of ``frames`` frames: ``0, K-1, 2(K-1), ...``."""
    n = _num_segments(frames, segment_len, "frames")
    return jnp.arange(n + 1) * (segment_len - 1)


def dense_to_coarse(x, segment_len: int):
    """The coarse frames of a dense clip: ``[B, ..., F, h, w, C] -> [B, ..., n + 1, h, w, C]``."""
    idx = coarse_indices(jnp.shape(x)[FRAME_AXIS], segment_len)
    return jnp.take(x, idx, axis=jnp.ndim(x) + FRAME_AXIS)


def split_segments(x, segment_len: int):
    """Dense clip -> its overlapping segments folded into the batch.

    ``[B, ..., F, h, w, C] -> [B * n, ..., K, h, w, C]``, sample-major (sample b's segments are
    rows ``b * n .. b * n + n - 1``), ready for one batched call of the fine model. Works for
    per-frame arrays ``[B, F]`` too (noise levels, masks): ``-> [B * n, K]``.
    """
    x = jnp.asarray(x)
    frame_axis = 1 if x.ndim == 2 else x.ndim + FRAME_AXIS
    n = _num_segments(x.shape[frame_axis], segment_len, "x frames")
    starts = jnp.arange(n) * (segment_len - 1)
    idx = starts[:, None] + jnp.arange(segment_len)[None, :]  # [n, K]
    seg = jnp.take(x, idx, axis=frame_axis)  # [B, .., n, K, ...]
    seg = jnp.moveaxis(seg, frame_axis, 1)  # [B, n, .., K, ...]
    return seg.reshape((x.shape[0] * n,) + seg.shape[2:])


def coarse_from_segments(seg, batch: int, *, boundary: str = "mean"):
    """Per-segment predictions ``[B * n, ..., K, h, w, C]`` -> coarse frames ``[B, ..., n + 1, ...]``.

    Interior coarse frames end one segment and start the next; the paper concatenates "the
    first and last latent of each segment" without saying which copy wins. ``boundary``:
    ``"mean"`` (default) averages the two predictions, ``"start"`` takes the segment that starts
    at the frame, ``"end"`` the one that ends there. The clip's first and last coarse frames have
    a single prediction.
    """
    check_choice("boundary", boundary, BOUNDARIES)
    seg = jnp.asarray(seg)
    if seg.ndim < 5 or seg.shape[0] % batch:
        raise ValueError(f"seg: expected shape [B * n, ..., K, h, w, C] with B = {batch}, got {list(seg.shape)}")
    n = seg.shape[0] // batch
    seg = seg.reshape((batch, n) + seg.shape[1:])
    fa = seg.ndim + FRAME_AXIS
    first = jnp.take(seg, 0, axis=fa)  # [B, n, ..., h, w, C]
    last = jnp.take(seg, seg.shape[fa] - 1, axis=fa)
    return jnp.moveaxis(coarse_from_ends(first, last, boundary=boundary), 1, fa - 1)


def coarse_from_ends(first, last, *, boundary: str = "mean"):
    """The coarse frames from the first and last frame predictions of each segment,
    ``[B, n, ...]`` each -> ``[B, n + 1, ...]`` (``boundary`` as :func:`coarse_from_segments`).
    For callers that run the fine model one segment at a time."""
    check_choice("boundary", boundary, BOUNDARIES)
    check_same_shape("last", last, "first", first)
    if boundary == "mean":
        interior = 0.5 * (last[:, :-1] + first[:, 1:])
    elif boundary == "start":
        interior = first[:, 1:]
    else:
        interior = last[:, :-1]
    return jnp.concatenate([first[:, :1], interior, last[:, -1:]], axis=1)


def distill_loss(student, teacher, *, cond_mask=None):
    """LongDWM [2506.01546v1] eq. 8: mean squared distance from the student's coarse predictions to the frozen
    teacher's, ``[B, ..., n + 1, h, w, C]`` each. No gradient flows into ``teacher``.

    ``cond_mask [B, n + 1]`` excludes clean condition frames (the student's first coarse frame).
    Both predictions must be in the same space (data estimates as in the paper, or velocities at
    the shared level, which differ from data estimates by the factor sigma).
    """
    check_same_shape("teacher", teacher, "student", student)
    sq = jnp.square(jnp.asarray(student, jnp.float32) - jax.lax.stop_gradient(jnp.asarray(teacher, jnp.float32)))
    if cond_mask is None:
        return jnp.mean(sq)
    student = jnp.asarray(student)
    check_shape("cond_mask", cond_mask, (student.shape[0], student.shape[FRAME_AXIS]))
    keep = expand_per_frame(~jnp.asarray(cond_mask, bool), student, "cond_mask")
    keep = jnp.broadcast_to(keep, sq.shape)
    return jnp.sum(jnp.where(keep, sq, 0.0)) / jnp.maximum(jnp.sum(keep), 1)
