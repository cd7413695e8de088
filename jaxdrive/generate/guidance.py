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
from jaxdrive.validate import check_range, check_shape

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


def _row_drops(drop, batch: int) -> dict:
    """The per-clip drops ``drop`` as ``{condition: [batch] bool}``: a mapping of ``[batch]`` bool
    arrays (``Conditions.drop``, checked: a ``ValueError`` names ``drop[name]``), or condition
    names (none of them dropped for any clip)."""
    if not isinstance(drop, Mapping):
        return {n: jnp.full((batch,), False, bool) for n in drop}
    for name, value in drop.items():
        check_shape(f"drop[{name!r}]", value, [batch])
        if jnp.result_type(value) != jnp.bool_:
            raise ValueError(f"drop[{name!r}]: expected dtype bool, got {jnp.result_type(value)}")
    return {n: jnp.asarray(v) for n, v in drop.items()}


def sampler_guidance(cond, drop, batch: int, scale: float, controls=()) -> dict:
    """:func:`jaxdrive.flow.sample`'s guidance arguments for the conditions ``cond`` (no drops
    set) of ``batch`` clips: ``drop`` names the conditions with a learned null (the drops the model
    trained with), ``scale`` is the plain scale and ``controls`` ``((control, scale), ...)`` as
    :func:`check_controls` returns. Without guidance ``{"cond": ...}`` (one forward per step).

    ``drop`` is ``Conditions.drop`` (``{condition: [batch] bool}``; a wrong shape or dtype is a
    ``ValueError`` naming ``drop[name]``) or a sequence of names (no clip drops any). Its values
    are each clip's own drops, with the meaning the DiT gives them: a clip whose value is True is
    sampled without that condition (its learned null) in every branch, the conditional one
    included, so guidance does not change that clip for that condition (its control's term
    ``v_c - v_{c without k}`` is zero) and the clip comes out as with that condition left out. A
    clip whose value is False keeps it in the conditional branch and is guided against its null.
    This reading and not "True: guide this clip", because ``drop`` means it everywhere else (the
    data pipeline's per-clip drops, :meth:`Conditions.from_batch`), and the samplers' callers
    pass all False ("nothing dropped; CFG adds the nulls"), whose samples stay bit for bit.
    """
    rows = _row_drops(drop, batch)
    names = list(rows)
    if not names or (scale == 1.0 and not controls):
        return {"cond": cond.replace(drop=rows) if isinstance(drop, Mapping) and rows else cond}
    out = {"cond": cond.replace(drop=rows), "guidance_scale": scale}
    # every branch's drops derive from the caller's arrays, so that they keep their sharding: the
    # sampler stacks the branches, and under an Explicit mesh a replicated and a batch-sharded
    # drop cannot be concatenated
    nulls = {n: jnp.logical_or(v, True) for n, v in rows.items()}
    if scale != 1.0:
        out["null_cond"] = cond.replace(drop=nulls)
    if controls:
        per = {}
        for control, s in controls:
            off = [n for n in names if n in CONTROLS[control]]
            if not off:
                raise ValueError(
                    f"control_guidance: expected conditions of the {control} control among the "
                    f"ones with a null ({names}), got none"
                )
            nulled = {n: nulls[n] if n in off else rows[n] for n in names}
            per[control] = (s, cond.replace(drop=nulled))
        out["control_guidance"] = per
    return out


def describe(guidance: float, controls=()) -> dict:
    """The plain scale ``guidance`` and the per-control ``controls`` (``((control, scale), ...)``)
    for reports: ``{"cfg": s, "cfg_boxes": s_boxes, ...}`` (a control without its own scale is
    left out)."""
    return {"cfg": guidance, **{f"cfg_{control}": scale for control, scale in controls}}
