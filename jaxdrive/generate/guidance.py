"""Classifier-free guidance of a trained model: the plain scale and the per-control scales.

The formula is :mod:`jaxdrive.flow.sampler`'s (compositional guidance, Liu et al. 2022):

    v = v_null + s (v_c - v_null) + sum_k (s_k - s) (v_c - v_{c without k})

``s`` is the plain scale (``--cfg``, the run's ``sample.cfg`` by default) and ``s_k`` a control's
own (``--cfg-boxes``, ``--cfg-route``): each control costs one more batched forward per step, and
with ``s_k = s`` it is plain guidance. A control is a set of the DiT's conditions (:data:`CONTROLS`)
that training drops together, so that the model has a learned null for it alone:

- ``boxes``: the 3D boxes (the data pipeline's ``boxes`` drop);
- ``route``: the ego's route, every condition the pipeline's ``trajectory`` drop nulls at once:
  the waypoints (MiLA), the ego poses (MagicDrive-V2's trajectory) and the frames warped along
  them (LongDWM's warp), whichever the model takes. Guiding one of them alone would ask for a
  null the model never saw.

A control the model does not take, or a model trained without drops (``data.drop_prob = 0``: its
nulls never trained), is a ``ValueError`` naming the option, before anything compiles.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable, Mapping

import jax.numpy as jnp

from jaxdrive.models.dit.conditions import BATCH_DROPS
from jaxdrive.validate import check_range

CONTROLS = {"boxes": BATCH_DROPS["boxes"], "route": BATCH_DROPS["trajectory"]}


def check_scale(name: str, value) -> float:
    """``value`` as a guidance scale: a finite number >= 0 (1: no guidance, 0: unconditional)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name}: expected a guidance scale (a number >= 0), got {value!r}")
    check_range(name, value, 0.0, float("inf"), hi_open=True)
    return float(value)


def check_controls(
    model,
    drop_prob: float,
    scales: Mapping[str, float | None],
    *,
    option: Callable[[str], str] = lambda c: f"control_guidance[{c!r}]",
) -> tuple[tuple[str, float], ...]:
    """The per-control scales ``scales`` (control name -> scale; None: not guided on its own)
    checked against a model (its :class:`jaxdrive.models.dit.config.DiTConfig` ``model`` and the
    ``data.drop_prob`` it trained with); returns ``((control, scale), ...)`` in :data:`CONTROLS`
    order, the form :class:`jaxdrive.generate.windows.WindowModel` keeps. ``option`` names a
    control's option in the errors (the CLI's ``--cfg-boxes``)."""
    unknown = sorted(set(scales) - set(CONTROLS))
    if unknown:
        raise ValueError(f"control_guidance: expected controls from {list(CONTROLS)}, got {unknown}")
    on = set(model.controls.enabled())
    out = []
    for control, conditions in CONTROLS.items():
        if scales.get(control) is None:
            continue
        scale = check_scale(option(control), scales[control])
        if not on & set(conditions):
            raise ValueError(
                f"{option(control)}: expected a model trained with the {control} control (one of "
                f"model.controls.{', '.join(conditions)}), got a model without it (its controls: "
                f"{', '.join(sorted(on)) or 'none'})"
            )
        if drop_prob <= 0:
            raise ValueError(
                f"{option(control)}: expected a model trained with condition drops (data.drop_prob > "
                f"0), whose learned null the {control} control is guided against; got "
                f"data.drop_prob = {drop_prob}"
            )
        out.append((control, scale))
    return tuple(out)


def sampler_guidance(cond, names, batch: int, scale: float, controls=()) -> dict:
    """:func:`jaxdrive.flow.sample`'s guidance arguments for the conditions ``cond`` (no drops
    set) of ``batch`` clips: ``names`` are the conditions with a learned null (the drops the model
    trained with), ``scale`` the plain scale and ``controls`` ``((control, scale), ...)`` as
    :func:`check_controls` returns. Without guidance ``{"cond": cond}`` (one forward per step)."""
    names = list(names)
    if not names or (scale == 1.0 and not controls):
        return {"cond": cond}
    on = cond.with_drops(names, False, batch)
    out = {"cond": on, "guidance_scale": scale}
    if scale != 1.0:
        out["null_cond"] = cond.with_drops(names, True, batch)
    if controls:
        per = {}
        for control, s in controls:
            off = [n for n in names if n in CONTROLS[control]]
            if not off:
                raise ValueError(
                    f"control_guidance: expected conditions of the {control} control among the "
                    f"ones with a null ({names}), got none"
                )
            per[control] = (s, on.replace(drop={n: jnp.full((batch,), n in off, bool) for n in names}))
        out["control_guidance"] = per
    return out


def describe(guidance: float, controls=()) -> dict:
    """The plain scale ``guidance`` and the per-control ``controls`` (``((control, scale), ...)``)
    for reports: ``{"cfg": s, "cfg_boxes": s_boxes, ...}`` (a control without its own scale is
    left out)."""
    return {"cfg": guidance, **{f"cfg_{control}": scale for control, scale in controls}}
