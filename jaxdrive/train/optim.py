"""The optimizer: AdamW with warmup and a decay schedule, global-norm clipping, and parameter
masks for partial training.

Partial training follows the papers' recipes: MiLA's stage 1 trains only its new modules, the
last block and the output layer (appendix B); STAGE's stage 2 trains only the HTFT modules. A
recipe names the trainable parameters with regular expressions over their paths
(``"blocks_27/.*"``, ``"htft.*"``); every other parameter gets no update and no optimizer state.
Weight decay applies to matrices and kernels (``ndim >= 2``), not to biases, norms or embeddings
of one dimension. Gradient accumulation happens inside the train step (micro-batches in a
``lax.scan``), so one optimizer step is one call.

The global norm is computed once a step: :func:`square_sums` gives each gradient's sum of squares,
the train step turns them into its ``grad_norm`` metric and its finiteness check
(:func:`jaxdrive.train.state.apply_gradients`), and passes them to the optimizer's clipping
(``square_sums=`` in ``update``), which would otherwise compute them a second time. A small model
has a few hundred parameter arrays, and these per-array reductions were a quarter of its train
step's compiled program.
"""

from __future__ import annotations

import operator
import re

import jax
import jax.numpy as jnp
import optax

from jaxdrive.config import OptimConfig


def learning_rate(config: OptimConfig, total_steps: int) -> optax.Schedule:
    """Linear warmup to ``lr`` over ``warmup_steps``, then cosine / linear decay to
    ``lr * min_lr_ratio`` at ``total_steps``, or constant."""
    warmup = max(int(config.warmup_steps), 0)
    rest = max(int(total_steps) - warmup, 1)
    floor = config.lr * config.min_lr_ratio
    if config.schedule == "cosine":
        after = optax.cosine_decay_schedule(config.lr, rest, alpha=config.min_lr_ratio)
    elif config.schedule == "linear":
        after = optax.linear_schedule(config.lr, floor, rest)
    else:
        after = optax.constant_schedule(config.lr)
    if warmup == 0:
        return after
    return optax.join_schedules([optax.linear_schedule(0.0, config.lr, warmup), after], [warmup])


def square_sums(grads):
    """Each leaf's sum of squares, the terms of :func:`global_norm`: for real leaves the same numbers
    as ``optax.tree.norm`` sums (it adds the squared imaginary part, zero for them)."""
    return jax.tree_util.tree_map(
        lambda g: jnp.sum(jnp.square(g) if not jnp.iscomplexobj(g) else jnp.square(g.real) + jnp.square(g.imag)),
        grads,
    )


def global_norm(sums) -> jax.Array:
    """The global norm from :func:`square_sums` (bit for bit ``optax.tree.norm`` of the gradients:
    the same terms added in the same order)."""
    return jnp.sqrt(jax.tree_util.tree_reduce(operator.add, sums, initializer=0))


def clip_by_global_norm(max_norm: float) -> optax.GradientTransformationExtraArgs:
    """``optax.clip_by_global_norm`` that takes the gradients' :func:`square_sums` when the caller
    has them (``update(..., square_sums=...)``): inside :func:`make_optimizer`'s partition they
    arrive masked to the trained parameters, as the updates do, so the norm is the trained ones'.
    The same numbers as optax's, whichever way the norm comes; the same (empty) state."""

    def update(updates, state, params=None, *, square_sums=None, **extra_args):
        del params, extra_args
        norm = optax.tree.norm(updates) if square_sums is None else global_norm(square_sums)
        trigger = jnp.squeeze(norm < max_norm)
        clip = lambda t: jax.lax.select(trigger, t, (t / norm.astype(t.dtype)) * max_norm)
        return jax.tree_util.tree_map(clip, updates), state

    return optax.GradientTransformationExtraArgs(optax.init_empty_state, update)


LAST_LAYER = "{last}"


def _resolve_last(patterns, paths) -> tuple[str, ...]:
    """``patterns`` with :data:`LAST_LAYER` replaced by the highest ``N`` of a ``layers_N/`` path
    (a scanned stack, ``layers_0_40``, is not one layer)."""
    if not any(LAST_LAYER in p for p in patterns):
        return tuple(patterns)
    layers = [int(m[1]) for path in paths if (m := re.match(r"layers_(\d+)/", path))]
    if not layers:
        bad = next(p for p in patterns if LAST_LAYER in p)
        raise ValueError(
            f"optim.trainable: '{LAST_LAYER}' names the last DiT layer (layers_N, the highest N), "
            f"expected parameters with such a layer (a scanned stack needs model.scan_breaks ending "
            f"at the last layer), got {bad!r} over paths such as {paths[:3]}"
        )
    return tuple(p.replace(LAST_LAYER, str(max(layers))) for p in patterns)


def trainable_labels(params, patterns) -> object:
    """``"train"`` / ``"freeze"`` per parameter: trainable when its path matches any pattern (all
    are trainable without patterns). ``{last}`` in a pattern is the DiT's last layer's index,
    read from the parameters (:func:`_resolve_last`), so a depth changed after the config was
    built moves it. A pattern that matches nothing raises ``ValueError``."""
    if not patterns:
        return jax.tree_util.tree_map(lambda _: "train", params)
    name = lambda path: jax.tree_util.keystr(path, simple=True, separator="/")  # "a/b/kernel"
    paths = [name(p) for p, _ in jax.tree_util.tree_flatten_with_path(params)[0]]
    patterns = _resolve_last(patterns, paths)
    compiled = [re.compile(p) for p in patterns]
    for pattern, rx in zip(patterns, compiled):
        if not any(rx.search(path) for path in paths):
            raise ValueError(
                f"optim.trainable: expected patterns that match parameter paths, got {pattern!r} "
                f"(no match among {len(paths)} paths such as {paths[:3]})"
            )
    return jax.tree_util.tree_map_with_path(
        lambda path, _: "train" if any(rx.search(name(path)) for rx in compiled) else "freeze", params
    )


def make_optimizer(config: OptimConfig, total_steps: int, params) -> optax.GradientTransformation:
    """The optimizer for ``params`` (a tree of arrays or ``ShapeDtypeStruct``) under ``config``;
    its ``update`` takes the gradients' :func:`square_sums` as ``square_sums=`` (optional)."""
    decay_mask = jax.tree_util.tree_map(lambda p: len(p.shape) >= 2, params)
    inner = []
    if config.clip_norm > 0:
        inner.append(clip_by_global_norm(config.clip_norm))
    inner.append(
        optax.adamw(
            learning_rate(config, total_steps),
            b1=config.b1,
            b2=config.b2,
            eps=config.eps,
            weight_decay=config.weight_decay,
            mask=decay_mask,
        )
    )
    tx = optax.chain(*inner)
    if config.trainable:
        tx = optax.multi_transform(
            {"train": tx, "freeze": optax.set_to_zero()},
            trainable_labels(params, config.trainable),
            mask_compatible_extra_args=True,  # square_sums masked as the updates are
        )
    return tx
