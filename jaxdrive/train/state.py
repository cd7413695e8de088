"""The train state: everything a run needs to continue exactly where it stopped.

``TrainState`` holds the float32 parameters, the optimizer state, the EMA parameters, the step,
the random key (as raw ``uint32`` key data, so that checkpoints hold plain arrays) and two
counters of non-finite steps. :func:`apply_gradients` is the one place where an update is
applied: a step whose loss or gradients' global norm is not finite leaves parameters, optimizer
state and EMA unchanged and is counted (``bad_steps`` in a row, ``skipped`` in all). The norm is
the one the clipping uses: one reduction per gradient serves the check, the clipping and the
``grad_norm`` metric.
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp
import optax

from jaxdrive.train.optim import global_norm, square_sums


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


def apply_gradients(
    state: TrainState, grads, loss, optimizer: optax.GradientTransformation, ema_decay: float, rng
) -> TrainState:
    """The next state after one update with ``grads`` (or the same state, counted, when ``loss``
    or the gradients' global norm is not finite: a NaN or an infinity in any gradient makes it so,
    and so does a norm past float32's range, ~1.8e19). ``rng`` is the key data the next step
    starts from. The gradients' :func:`jaxdrive.train.optim.square_sums` serve both the check and
    the optimizer's clipping (:func:`jaxdrive.train.optim.make_optimizer`), so each gradient is
    reduced once. :func:`apply_gradients_and_norm` also gives the norm."""
    return apply_gradients_and_norm(state, grads, loss, optimizer, ema_decay, rng)[0]


def apply_gradients_and_norm(
    state: TrainState, grads, loss, optimizer: optax.GradientTransformation, ema_decay: float, rng
) -> tuple[TrainState, jax.Array]:
    """:func:`apply_gradients` and the gradients' global norm (the one its check and clipping use,
    a train step's ``grad_norm`` metric), from one reduction per gradient."""
    optimizer = optax.with_extra_args_support(optimizer)  # any optax optimizer; ours reads square_sums

    def update(state, grads, sums):
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params, square_sums=sums)
        params = optax.apply_updates(state.params, updates)
        ema = state.ema
        if ema is not None:
            ema = jax.tree_util.tree_map(lambda e, p: ema_decay * e + (1.0 - ema_decay) * p, ema, params)
        return state.replace(params=params, opt_state=opt_state, ema=ema, bad_steps=jnp.zeros_like(state.bad_steps))

    def skip(state, grads, sums):
        del grads, sums
        return state.replace(bad_steps=state.bad_steps + 1, skipped=state.skipped + 1)

    def check_and_update(state, grads, loss):
        sums = square_sums(grads)
        norm = global_norm(sums)
        ok = jnp.isfinite(loss) & jnp.isfinite(norm)
        # one conditional, not a select per leaf: the same numbers, and far less for XLA to compile
        return jax.lax.cond(ok, update, skip, state, grads, sums), norm

    new, norm = _with_auto_axes(check_and_update, state)(state, grads, loss)
    return new.replace(step=state.step + 1, rng=rng), norm


def _with_auto_axes(fn, state: TrainState):
    """``fn(state, ...) -> (state, scalar)`` run with the mesh's axes Auto
    (``jax.sharding.auto_axes``), its state resharded as ``state`` is and its scalar replicated.
    The norm, the check and the update are per-leaf reductions and elementwise operations: under
    Explicit axes JAX annotates every one of them with its sharding (one ``Sharding`` op per
    operation, a third of a small model's train step, and one per leaf on the conditional's
    results), which XLA then propagates; the same numbers."""
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or not mesh.explicit_axes:
        return fn
    specs = jax.tree_util.tree_map(lambda x: jax.typeof(x).sharding.spec, state)
    return jax.sharding.auto_axes(fn, out_sharding=(specs, jax.sharding.PartitionSpec()))
