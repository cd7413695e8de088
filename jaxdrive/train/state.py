"""The train state: everything a run needs to continue exactly where it stopped.

``TrainState`` holds the float32 parameters, the optimizer state, the EMA parameters, the step,
the random key (as raw ``uint32`` key data, so that checkpoints hold plain arrays) and two
counters of non-finite steps. :func:`apply_gradients` is the one place where an update is
applied: a step whose loss or gradients are not finite leaves parameters, optimizer state and EMA
unchanged and is counted (``bad_steps`` in a row, ``skipped`` in all).
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp
import optax


@flax.struct.dataclass
class TrainState:
    step: jax.Array
    params: object
    opt_state: object
    ema: object
    rng: jax.Array  # uint32 key data of the run's random stream
    bad_steps: jax.Array  # non-finite steps in a row
    skipped: jax.Array  # non-finite steps since the start

    @property
    def key(self):
        return jax.random.wrap_key_data(self.rng)


def create_state(params, optimizer: optax.GradientTransformation, seed: int, *, ema: bool = True) -> TrainState:
    """A fresh state at step 0 (EMA starts at the parameters; ``ema=False`` keeps none)."""
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        opt_state=optimizer.init(params),
        ema=jax.tree_util.tree_map(jnp.copy, params) if ema else None,
        rng=jax.random.key_data(jax.random.key(seed)),
        bad_steps=jnp.zeros((), jnp.int32),
        skipped=jnp.zeros((), jnp.int32),
    )


def all_finite(tree) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]))


def apply_gradients(
    state: TrainState, grads, loss, optimizer: optax.GradientTransformation, ema_decay: float, rng
) -> TrainState:
    """The next state after one update with ``grads`` (or the same state, counted, when ``loss``
    or ``grads`` are not finite). ``rng`` is the key data the next step starts from."""
    ok = jnp.isfinite(loss) & all_finite(grads)

    def update(state):
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        ema = state.ema
        if ema is not None:
            ema = jax.tree_util.tree_map(lambda e, p: ema_decay * e + (1.0 - ema_decay) * p, ema, params)
        return state.replace(params=params, opt_state=opt_state, ema=ema, bad_steps=jnp.zeros_like(state.bad_steps))

    def skip(state):
        return state.replace(bad_steps=state.bad_steps + 1, skipped=state.skipped + 1)

    # one conditional, not a select per leaf: the same numbers, and far less for XLA to compile
    new = jax.lax.cond(ok, update, skip, state)
    return new.replace(step=state.step + 1, rng=rng)
