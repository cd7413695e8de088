"""The optimizer: AdamW with warmup and a decay schedule, global-norm clipping, and parameter
masks for partial training.

Partial training follows the papers' recipes: MiLA's stage 1 trains only its new modules, the
last block and the output layer (appendix B); STAGE's stage 2 trains only the HTFT modules. A
recipe names the trainable parameters with regular expressions over their paths
(``"blocks_27/.*"``, ``"htft.*"``); every other parameter gets no update and no optimizer state.
Weight decay applies to matrices and kernels (``ndim >= 2``), not to biases, norms or embeddings
of one dimension. Gradient accumulation happens inside the train step (micro-batches in a
``lax.scan``), so one optimizer step is one call.
"""

from __future__ import annotations

import re

import jax
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


def trainable_labels(params, patterns) -> object:
    """``"train"`` / ``"freeze"`` per parameter: trainable when its path matches any pattern (all
    are trainable without patterns). A pattern that matches nothing raises ``ValueError``."""
    if not patterns:
        return jax.tree_util.tree_map(lambda _: "train", params)
    compiled = [re.compile(p) for p in patterns]
    name = lambda path: jax.tree_util.keystr(path, simple=True, separator="/")  # "a/b/kernel"
    paths = [name(p) for p, _ in jax.tree_util.tree_flatten_with_path(params)[0]]
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
    """The optimizer for ``params`` (a tree of arrays or ``ShapeDtypeStruct``) under ``config``."""
    decay_mask = jax.tree_util.tree_map(lambda p: len(p.shape) >= 2, params)
    inner = []
    if config.clip_norm > 0:
        inner.append(optax.clip_by_global_norm(config.clip_norm))
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
            {"train": tx, "freeze": optax.set_to_zero()}, trainable_labels(params, config.trainable)
        )
    return tx
