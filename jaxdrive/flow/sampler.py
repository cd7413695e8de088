"""The jitted sampling loop: Euler or Heun over per-frame noise levels, with condition frames
held fixed and classifier-free guidance over several conditions in one batched call.

The whole loop is one ``lax.scan`` over the steps, so a sampler compiles once for a given input
shape and step count (the schedule values themselves are traced data).

Guidance (Ho & Salimans 2022; per-condition composition after Liu et al. 2022, as MiLA drops text
and waypoints independently, appendix B):

- ``guidance_scale=s`` (a number): all conditions against all-null,
  ``v = v_c + (s - 1) (v_c - v_null)``; a Python ``s = 1`` skips the null evaluation and
  returns ``v_c`` exactly;
- ``guidance_scale={"text": s1, "traj": s2}``: per-condition scales,
  ``v = v_null + sum_k s_k (v_k - v_null)``, where ``v_k`` keeps condition k and nulls the other
  named ones; conditions not named are never nulled;
- ``guidance_scale=s`` with ``control_guidance={"boxes": (s_k, cond_without_k), ...}``:
  compositional guidance of single controls on top of the plain one,

      v = v_null + s (v_c - v_null) + sum_k (s_k - s) (v_c - v_{c without k}),

  one more forward per control (``v_{c without k}``: every condition on but control k, nulled).
  Where the controls act independently (Liu et al. 2022, "Compositional Visual Generation with
  Composable Diffusion Models", its conjunction: the conditional scores add), ``v_c - v_{c without k}``
  is control k's own direction, so control k is guided at ``s_k`` and everything else at ``s``;
  InstructPix2Pix (Brooks et al. 2023, eq. 3) gives two conditions their own scales the same way
  with a nested chain, which depends on the order of the conditions, where this leave-one-out
  form does not. With every ``s_k = s`` the sum vanishes: plain guidance exactly. With a Python
  ``s = 1`` the null evaluation is skipped (``v = v_c + sum_k (s_k - 1) (v_c - v_{c without k})``).

Scales are checked to be finite and >= 0 where they are concrete (a negative scale pushes away
from the condition it names).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.flow.rectified import expand_per_frame
from jaxdrive.parallel.rules import reshard_like
from jaxdrive.validate import check_choice, check_range, check_shape, is_concrete

METHODS = ("euler", "heun")


def _per_step_sigmas(sigmas, x, cond_mask):
    """Schedule -> ``[N + 1, B]`` or ``[N + 1, B, F]`` with condition frames pinned to 0."""
    sigmas = jnp.asarray(sigmas, jnp.float32)
    batch = x.shape[0]
    if sigmas.ndim == 1:
        sigmas = jnp.broadcast_to(sigmas[:, None], (sigmas.shape[0], batch))
    elif sigmas.ndim == 2:
        check_shape("sigmas", sigmas, (None, batch))
    elif sigmas.ndim == 3:
        if x.ndim < 5:
            raise ValueError(
                f"sigmas: a per-frame schedule [N + 1, B, F] needs x of shape "
                f"[B, ..., F, h, w, C], got x of shape {list(x.shape)}"
            )
        check_shape("sigmas", sigmas, (None, batch, x.shape[-4]))
    else:
        raise ValueError(f"sigmas: expected shape [N + 1], [N + 1, B] or [N + 1, B, F], got {list(sigmas.shape)}")
    if sigmas.shape[0] < 2:
        raise ValueError(f"sigmas: expected at least 2 levels (one step), got {sigmas.shape[0]}")
    if is_concrete(sigmas):
        s = np.asarray(sigmas)
        if s.min() < 0.0 or s.max() > 1.0:
            raise ValueError(f"sigmas: expected values in [0, 1], got values in [{s.min():g}, {s.max():g}]")
        if (np.diff(s, axis=0) > 0).any():
            raise ValueError(
                "sigmas: expected a non-increasing schedule along the steps (axis 0), got a level that rises"
            )
    if cond_mask is not None:
        if x.ndim < 5:
            raise ValueError(f"cond_mask: needs x of shape [B, ..., F, h, w, C], got {list(x.shape)}")
        check_shape("cond_mask", cond_mask, (batch, x.shape[-4]))
        if sigmas.ndim == 2:
            sigmas = jnp.broadcast_to(sigmas[:, :, None], sigmas.shape + (x.shape[-4],))
        sigmas = jnp.where(jnp.asarray(cond_mask, bool)[None], 0.0, sigmas)
    return sigmas


def _check_scale(name: str, scale) -> None:
    check_range(name, scale, 0.0, float("inf"), hi_open=True)


def _control_variants(cond, null_cond, scale, control_guidance):
    """Compositional guidance of single controls (module docstring): the variants
    ``[v_c, (v_null,) v_{c without k}...]`` and their combination."""
    if isinstance(scale, Mapping):
        raise ValueError(
            "control_guidance: expected one guidance_scale number with it (the plain scale the "
            f"controls' own scales add to), got per-condition scales {dict(scale)}"
        )
    scale = 1.0 if scale is None else scale
    _check_scale("guidance_scale", scale)
    names = list(control_guidance)
    pairs = []
    for k in names:
        entry = control_guidance[k]
        if not isinstance(entry, tuple) or len(entry) != 2:
            raise ValueError(f"control_guidance[{k!r}]: expected (scale, cond without {k}), got {type(entry).__name__}")
        _check_scale(f"control_guidance[{k!r}]", entry[0])
        pairs.append(entry)
    plain = not (isinstance(scale, (int, float)) and scale == 1.0)
    if plain and null_cond is None:
        raise ValueError("null_cond: expected the null conditions when guidance_scale is set, got None")
    variants = [cond] + ([null_cond] if plain else []) + [c for _, c in pairs]

    def combine(vs):
        v_c = vs[0]
        v = v_c + (scale - 1.0) * (v_c - vs[1]) if plain else v_c
        rest = vs[2:] if plain else vs[1:]
        return v + sum((s_k - scale) * (v_c - v_k) for (s_k, _), v_k in zip(pairs, rest))

    return variants, combine


def _guidance_variants(cond, null_cond, guidance_scale, control_guidance=None):
    """The condition pytrees evaluated in one batch, and how to combine their velocities."""
    if control_guidance:
        return _control_variants(cond, null_cond, guidance_scale, control_guidance)
    if guidance_scale is None:
        return [cond], lambda vs: vs[0]
    for name, value in guidance_scale.items() if isinstance(guidance_scale, Mapping) else [(None, guidance_scale)]:
        _check_scale("guidance_scale" if name is None else f"guidance_scale[{name!r}]", value)
    if null_cond is None:
        raise ValueError("null_cond: expected the null conditions when guidance_scale is set, got None")
    if not isinstance(guidance_scale, Mapping):
        scale = guidance_scale
        if isinstance(scale, (int, float)) and scale == 1.0:
            return [cond], lambda vs: vs[0]  # v_c + 0 * (...): skip the null half of the batch
        return [cond, null_cond], lambda vs: vs[0] + (scale - 1.0) * (vs[0] - vs[1])
    if not isinstance(cond, Mapping) or not isinstance(null_cond, Mapping):
        raise ValueError(
            "cond: per-condition guidance scales need cond and null_cond as mappings "
            f"keyed by condition name, got {type(cond).__name__} and {type(null_cond).__name__}"
        )
    names = list(guidance_scale)
    missing = [k for k in names if k not in cond or k not in null_cond]
    if missing:
        raise ValueError(
            f"guidance_scale: expected names present in cond and null_cond ({sorted(cond)}), got unknown {missing}"
        )

    def variant(on):
        return {k: (cond[k] if (k not in names or k in on) else null_cond[k]) for k in cond}

    variants = [variant(())] + [variant((k,)) for k in names]
    scales = [guidance_scale[k] for k in names]

    def combine(vs):
        v_null = vs[0]
        return v_null + sum(s * (v - v_null) for s, v in zip(scales, vs[1:]))

    return variants, combine


def _interleave(leaves):
    """Stack per-variant arrays ``[B, ...]`` to ``[B * n, ...]`` with each sample's variants
    adjacent (sample-major), so a batch-sharded axis stays sharded the same way: every device
    evaluates all guidance variants of its own samples and nothing crosses devices."""
    stacked = jnp.stack(leaves, axis=1)
    return stacked.reshape((stacked.shape[0] * stacked.shape[1],) + stacked.shape[2:])


def _like(v, x):
    """``v`` with exactly ``x``'s sharding: the Euler update cannot add two differently sharded
    arrays under an Explicit mesh (the network may return its batch sharded otherwise)."""
    return reshard_like(v, x)


def _batched_velocity(velocity_fn, variants, combine, per_step: bool = False):
    """One call of ``velocity_fn`` over all guidance variants stacked along the batch. With
    ``per_step`` it takes a step input (batch-major leaves, given to every variant) and returns
    ``(v, out)``: ``out`` is the conditional variant's."""
    n = len(variants)
    if n == 1:
        if per_step:

            def velocity(x, s, inp):
                v, out = velocity_fn(x, s, variants[0], inp)
                return _like(v, x), out

            return velocity
        return lambda x, s, inp=None: _like(velocity_fn(x, s, variants[0]), x)
    stacked = jax.tree_util.tree_map(lambda *leaves: _interleave(leaves), *variants)

    def stacked_velocity(x, sigma, inp=None):
        args = (_interleave([x] * n), _interleave([sigma] * n), stacked)
        out = None
        if per_step:
            v, out = velocity_fn(*args, jax.tree_util.tree_map(lambda a: _interleave([a] * n), inp))
            out = jax.tree_util.tree_map(lambda a: a.reshape((x.shape[0], n) + a.shape[1:])[:, 0], out)
        else:
            v = velocity_fn(*args)
        v = v.reshape((x.shape[0], n) + v.shape[1:])
        v = _like(combine([v[:, i] for i in range(n)]), x)
        return (v, out) if per_step else v

    return stacked_velocity


def sample(
    velocity_fn: Callable,
    x,
    sigmas,
    *,
    cond=None,
    null_cond=None,
    guidance_scale=None,
    cond_mask=None,
    method: str = "euler",
    return_trajectory: bool = False,
    step_inputs=None,
    control_guidance=None,
):
    """Integrate the flow ODE from ``sigmas[0]`` to ``sigmas[-1]`` in one ``lax.scan``.

    Args:
      velocity_fn: ``(x, sigma, cond) -> v`` with ``v`` shaped like ``x``; ``sigma`` is ``[B]``
        for a per-sample schedule, else ``[B, F]``; ``cond`` is a pytree whose leaves have the
        batch as axis 0 (``None`` when no conditions are given).
      x: the start ``[B, ...]`` (per-frame schedules need ``[B, ..., F, h, w, C]``): noise at level
        ``sigmas[0]`` for generated frames (JDC-renoised anchors for anchor frames) and the clean
        frames where ``cond_mask`` is set.
      sigmas: ``[N + 1]`` shared levels, ``[N + 1, B]``, or a per-frame schedule ``[N + 1, B, F]``
        (e.g. :func:`jaxdrive.flow.frame_schedule` with TPD and JDC anchors). Non-increasing in
        [0, 1] along the steps (checked when concrete).
      cond, null_cond, guidance_scale, control_guidance: see the module docstring
        (``control_guidance``: ``{name: (scale, cond with that control nulled)}``). With guidance, ``velocity_fn``
        sees a batch of ``n * B`` (``n`` variants), ordered sample-major: rows ``b * n .. b * n +
        n - 1`` are sample b's variants, which keeps a batch-sharded axis local to its devices.
      cond_mask: ``[B, F]`` bool; those frames get level 0 and come out bit-identical to ``x``.
      method: ``"euler"`` (one evaluation per step) or ``"heun"`` (two, second order; a step that
        ends at level 0 falls back to Euler, where the velocity of a sharp distribution blows up).
      return_trajectory: also return the state after every step, ``[N, *x.shape]``.
      step_inputs: a pytree whose leaves have the steps as axis 0 (``[N, B, ...]``); then
        ``velocity_fn(x, sigma, cond, step_input) -> (v, step_output)`` sees step i's slice and
        its outputs (of the conditional variant, of the step's first evaluation) are returned
        stacked ``[N, B, ...]``: STAGE's per-step feature buffer (:mod:`jaxdrive.generate.streaming`).

    Returns the final state, or ``(final, trajectory)``; with ``step_inputs`` the step outputs
    come last: ``(final, outputs)`` or ``(final, trajectory, outputs)``.
    """
    check_choice("method", method, METHODS)
    x = jnp.asarray(x)
    levels = _per_step_sigmas(sigmas, x, cond_mask)
    variants, combine = _guidance_variants(cond, null_cond, guidance_scale, control_guidance)
    per_step = step_inputs is not None
    velocity = _batched_velocity(velocity_fn, variants, combine, per_step)
    keep = None if cond_mask is None else expand_per_frame(jnp.asarray(cond_mask, bool), x, "cond_mask")
    x_cond = x

    def expand(s):
        return expand_per_frame(s, x)

    def pin(y):
        # Re-impose the condition frames, also before Heun's second evaluation, so whatever the
        # model returns on them can never reach the other frames.
        y = y.astype(x.dtype)
        return y if keep is None else jnp.where(keep, x_cond, y)

    def evaluate(state, s, inp):
        return velocity(state, s, inp) if per_step else (velocity(state, s), None)

    def step(state, xs):
        s, s_next, inp = xs
        v, out = evaluate(state, s, inp)
        ds = expand(s_next) - expand(s)
        euler = pin(state + ds * v)
        if method == "heun":

            def heun():
                v_next, _ = evaluate(euler, s_next, inp)
                corrected = state + ds * 0.5 * (v + v_next)
                return pin(jnp.where(expand(s_next) > 0.0, corrected, euler))

            new = jax.lax.cond(jnp.all(s_next == 0.0), lambda: euler, heun)
        else:
            new = euler
        return new, (new if return_trajectory else None, out)

    final, (traj, outs) = jax.lax.scan(step, x, (levels[:-1], levels[1:], step_inputs))
    result = (final, traj) if return_trajectory else (final,)
    if per_step:
        result = result + (outs,)
    return result if len(result) > 1 else result[0]
