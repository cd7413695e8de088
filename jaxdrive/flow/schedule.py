"""Per-frame noise levels of a clip: condition frames, TPD and JDC anchors in one place.

Training (one base level per sample) and sampling (one base level per step) build their
``[B, F]`` levels here, so the two can never disagree about which frame sits at which level.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from jaxdrive.flow.jdc import DEFAULT_ANCHOR_SLOPE, jdc_anchor_sigma
from jaxdrive.flow.tpd import tpd_frame_sigmas
from jaxdrive.validate import check_ndim, check_range, check_shape


def frame_sigmas(
    sigma,
    cond_mask,
    *,
    anchor_mask=None,
    tpd: bool = False,
    omega: float = math.pi / 2,
    anchor_slope: float = DEFAULT_ANCHOR_SLOPE,
):
    """Per-frame levels ``[B, F]`` from base levels ``sigma [B]``.

    - condition frames (``cond_mask [B, F]`` True) are clean: 0;
    - JDC anchor frames (``anchor_mask [B, F]`` True, MiLA [2503.15875v1] sec. 3.3) sit at
      ``g = anchor_slope * sigma`` (:func:`jdc_anchor_sigma`);
    - the remaining (generated) frames sit at ``sigma``, or with ``tpd=True`` at MiLA's [2503.15875v1]
      eq. 13-14 levels ranked along the clip among the generated frames only.

    A frame marked both condition and anchor is a condition frame.
    """
    check_ndim("sigma", sigma, 1)
    check_range("sigma", sigma, 0.0, 1.0)
    batch = jnp.shape(sigma)[0]
    check_ndim("cond_mask", cond_mask, 2)
    check_shape("cond_mask", cond_mask, (batch, None))
    cond = jnp.asarray(cond_mask, bool)
    anchors = jnp.zeros_like(cond) if anchor_mask is None else jnp.asarray(anchor_mask, bool)
    check_shape("anchor_mask", anchors, cond.shape)
    anchors = anchors & ~cond
    sigma = jnp.asarray(sigma, jnp.float32)
    if tpd:
        levels = tpd_frame_sigmas(sigma, cond | anchors, omega)
    else:
        levels = jnp.broadcast_to(sigma[:, None], cond.shape)
    g = jdc_anchor_sigma(sigma, anchor_slope)[:, None]
    levels = jnp.where(anchors, g, levels)
    return jnp.where(cond, 0.0, levels)


def frame_schedule(base_sigmas, cond_mask, **kwargs):
    """A sampling schedule ``[N + 1]`` -> per-frame schedule ``[N + 1, B, F]``.

    Applies :func:`frame_sigmas` (same keyword arguments) at every step, for :func:`sample`.
    """
    check_ndim("base_sigmas", base_sigmas, 1)
    check_range("base_sigmas", base_sigmas, 0.0, 1.0)
    cond = jnp.asarray(cond_mask, bool)
    check_ndim("cond_mask", cond, 2)
    base = jnp.asarray(base_sigmas, jnp.float32)
    per_step = jnp.broadcast_to(base[:, None], (base.shape[0], cond.shape[0]))
    return jax.vmap(lambda s: frame_sigmas(s, cond, **kwargs))(per_step)
