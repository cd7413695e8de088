"""Where the clean condition frames and the JDC anchors sit in a clip of ``F`` latent frames.

Training (:func:`draw_condition_masks`, one pattern per clip) and sampling (the strategies of
``jaxdrive.generate``) read the same masks from :func:`pattern_masks`, so a model is trained on
exactly the layouts it is asked to fill in.

- ``"prefix"``: the first ``n_cond`` frames are given and the rest is predicted. The tail frame is
  an anchor candidate: MiLA's coarse stage predicts it and the (Re)fine stage starts it from that
  prediction (MiLA [2503.15875v1] sec. 3.3; appendix B, stage 3 sets "the tail anchor frame to noisy anchor frame"
  for 75% of the clips).
- ``"ends"``: the first ``n_cond`` frames and the last frame are given, the frames between are
  interpolated (LongDWM [2506.01546v1] sec. 3.2, eq. 6: the fine DiT's last frame is "dropped with a fixed ratio",
  so one model learns prediction and interpolation; ``n_cond = 1`` pins both ends). No anchors.
- ``"anchors"``: the first ``n_cond`` frames are given; every ``anchor_every``-th frame counted
  from the last given one is an anchor candidate (MiLA's low-fps anchors inside a (Re)fine window:
  4 given + 12 generated frames with ``anchor_every = 12`` make the tail the anchor). With
  ``n_cond = 0`` the count starts at a virtual frame -1.

Anchor candidates become JDC anchors (noise level ``g``, MiLA [2503.15875v1] eq. 8-12) when the caller says so:
the sampler when it holds a prediction for them, training for a fraction of the clips.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.validate import check_choice, check_positive_int, is_concrete

PATTERNS = ("prefix", "ends", "anchors")


def max_cond(pattern: str, frames: int) -> int:
    """The most frames ``n_cond`` may give at the start, leaving one frame to generate."""
    check_choice("pattern", pattern, PATTERNS)
    return frames - (2 if pattern == "ends" else 1)


def _check_n_cond(n_cond, pattern, frames):
    if isinstance(n_cond, bool):
        raise ValueError(f"n_cond: expected an int or an int array [B], got {n_cond!r}")
    n = jnp.asarray(n_cond)
    if not jnp.issubdtype(n.dtype, jnp.integer) or n.ndim > 1:
        raise ValueError(f"n_cond: expected an int or an int array [B], got dtype {n.dtype} shape {list(n.shape)}")
    most = max_cond(pattern, frames)
    if most < 0:
        raise ValueError(
            f"frames: expected >= 2 for pattern {pattern!r} (the last frame is given and one "
            f"frame is generated), got {frames}"
        )
    if is_concrete(n) and n.size and (int(jnp.min(n)) < 0 or int(jnp.max(n)) > most):
        raise ValueError(
            f"n_cond: expected values in [0, {most}] for pattern {pattern!r} with {frames} frames "
            f"(at least one frame generated), got {np.asarray(n).tolist()}"
        )
    return n


def pattern_masks(pattern: str, frames: int, n_cond, *, anchor_every: int = 0):
    """``(cond_mask, anchor_mask)`` of one pattern (module docstring).

    ``n_cond``: the number of clean frames at the start, a Python int (masks ``[F]``) or an int
    array ``[B]`` (masks ``[B, F]``), in ``[0, F - 1]`` (``[0, F - 2]`` for ``"ends"``), checked
    when concrete. ``anchor_every`` (>= 1, ``"anchors"`` only): the anchors' spacing in frames.
    ``anchor_mask`` holds the anchor candidates, never a condition frame.
    """
    check_choice("pattern", pattern, PATTERNS)
    frames = check_positive_int("frames", frames)
    if pattern == "anchors":
        anchor_every = check_positive_int("anchor_every", anchor_every)
    else:
        anchor_every = check_positive_int("anchor_every", anchor_every, minimum=0)
    n = _check_n_cond(n_cond, pattern, frames)[..., None]
    frame = jnp.arange(frames)
    cond = frame < n
    if pattern == "prefix":
        anchors = (frame == frames - 1) & ~cond
    elif pattern == "ends":
        cond = cond | (frame == frames - 1)
        anchors = jnp.zeros_like(cond)
    else:
        anchors = ~cond & ((frame - (n - 1)) % anchor_every == 0)
    return cond, anchors


def check_patterns(patterns, pattern_rates=(), anchor_every: int = 0, *, prefix: str = "") -> None:
    """ValueErrors naming ``{prefix}patterns`` / ``{prefix}pattern_rates`` / ``{prefix}anchor_every``:
    a non-empty tuple of distinct :data:`PATTERNS`; rates empty (equal) or one per pattern,
    non-negative, summing to 1 within 1e-6; ``anchor_every >= 1`` when ``"anchors"`` is drawn."""
    patterns, rates = tuple(patterns), tuple(pattern_rates)
    if not patterns or len(set(patterns)) != len(patterns):
        raise ValueError(f"{prefix}patterns: expected distinct names out of {list(PATTERNS)}, got {list(patterns)}")
    for p in patterns:
        check_choice(f"{prefix}patterns", p, PATTERNS)
    if rates:
        if len(rates) != len(patterns):
            raise ValueError(
                f"{prefix}pattern_rates: expected {len(patterns)} rates (one per pattern of "
                f"{list(patterns)}) or none, got {list(rates)}"
            )
        if any(not r >= 0 for r in rates) or abs(math.fsum(rates) - 1.0) > 1e-6:
            raise ValueError(f"{prefix}pattern_rates: expected non-negative rates summing to 1, got {list(rates)}")
    if "anchors" in patterns:
        check_positive_int(f"{prefix}anchor_every", anchor_every)
    else:
        check_positive_int(f"{prefix}anchor_every", anchor_every, minimum=0)


def draw_condition_masks(
    key,
    batch: int,
    frames: int,
    *,
    patterns=("prefix",),
    pattern_rates=(),
    cond_frames: int = 1,
    cond_frames_random: bool = True,
    anchor_every: int = 0,
    anchor_rate: float = 0.0,
):
    """Per clip a pattern, its given frames and its JDC anchors: ``(cond_mask, anchor_mask)`` ``[B, F]``.

    Each clip draws a pattern out of ``patterns`` with probabilities ``pattern_rates`` (empty:
    equal), then ``n_cond`` clean frames at the start: ``0..cond_frames`` uniformly when
    ``cond_frames_random``, else exactly ``cond_frames``, capped so that one frame is generated
    (:func:`max_cond`). The pattern's anchor candidates are JDC anchors in a fraction
    ``anchor_rate`` of the clips (one draw per clip), otherwise ordinary generated frames.
    Keyword names follow ``FlowConfig`` (the flow package does not import the config).
    """
    check_patterns(patterns, pattern_rates, anchor_every)
    batch = check_positive_int("batch", batch)
    frames = check_positive_int("frames", frames)
    cond_frames = check_positive_int("cond_frames", cond_frames, minimum=0)
    if not 0.0 <= anchor_rate <= 1.0:
        raise ValueError(f"anchor_rate: expected a value in [0, 1], got {anchor_rate!r}")
    patterns = tuple(patterns)
    for p in patterns:
        if max_cond(p, frames) < 0:
            raise ValueError(f"frames: expected >= 2 for pattern {p!r}, got {frames}")
    k_pattern, k_cond, k_anchor = jax.random.split(key, 3)
    if len(patterns) == 1:
        which = jnp.zeros((batch,), jnp.int32)
    else:
        rates = jnp.asarray(pattern_rates or (1.0 / len(patterns),) * len(patterns), jnp.float32)
        which = jax.random.choice(k_pattern, len(patterns), (batch,), p=rates)
    most = jnp.asarray([min(cond_frames, max_cond(p, frames)) for p in patterns], jnp.int32)[which]
    if cond_frames_random:
        n_cond = jax.random.randint(k_cond, (batch,), 0, most + 1)
    else:
        n_cond = most
    cond = jnp.zeros((batch, frames), bool)
    anchors = jnp.zeros((batch, frames), bool)
    for i, p in enumerate(patterns):
        # n_cond is drawn for the chosen pattern; capped here so the others' masks stay defined
        c, a = pattern_masks(p, frames, jnp.minimum(n_cond, max_cond(p, frames)), anchor_every=anchor_every)
        chosen = (which == i)[:, None]
        cond, anchors = jnp.where(chosen, c, cond), jnp.where(chosen, a, anchors)
    keep = jax.random.uniform(k_anchor, (batch, 1)) < anchor_rate
    return cond, anchors & keep
