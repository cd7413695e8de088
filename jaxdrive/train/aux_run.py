"""The training loop of jaxdrive's small auxiliary models: the future-controls predictor
(:mod:`jaxdrive.train.predictor_run`) and the segmentation evaluator
(:mod:`jaxdrive.train.segmenter_run`).

Both are a few hundred thousand parameters trained on one device from batches held in host
memory, so they share one loop instead of the DiT's sharded one: the run directory is laid out as a
DiT run's (``config.json``, ``checkpoints/``, ``metrics.jsonl``), checkpoints are atomic, a step's
batch comes from ``batch(step)`` alone (a resumed run sees the same data), SIGTERM / SIGINT save
and stop, and ``train.max_bad_steps`` non-finite losses in a row stop the run as diverged.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import jax

from jaxdrive.config import from_dict, to_dict

logger = logging.getLogger(__name__)


def fit(config, workdir, params, loss, batch, *, files=None, progress: bool = True, on_step=None) -> dict:
    """Train (or resume) ``params`` in ``workdir`` under ``config`` (``optim`` and ``train``
    sections): ``loss(params, batch) -> (scalar, {name: scalar})`` is jitted, ``batch(step)``
    gives the host batch of a step. ``files``: ``{name: json-able}`` written beside
    ``config.json``. Returns ``{"step", "status", "loss", "params"}`` (EMA parameters when kept);
    ``status`` as a DiT run's: ``"done"``, ``"interrupted"`` or ``"diverged"``.
    ``on_step(step, metrics)`` is called after every step (tests). A resume is logged at INFO, a
    diverged run at WARNING."""
    from jaxdrive import compile_cache
    from jaxdrive.train.checkpoint import Checkpoints
    from jaxdrive.train.common import Stop
    from jaxdrive.train.metrics import MetricsWriter
    from jaxdrive.train.optim import make_optimizer
    from jaxdrive.train.state import apply_gradients, create_state

    t, o = config.train, config.optim
    compile_cache.enable(t.compile_cache)
    workdir = Path(workdir)
    optimizer = make_optimizer(o, t.steps, params)
    state = create_state(params, optimizer, t.seed, ema=o.ema_decay > 0)
    ckpts = Checkpoints(workdir, keep=t.keep_checkpoints)
    restored = ckpts.restore_latest(state)
    start = 0
    if restored is not None:
        start, state = restored[0], restored[1]
        logger.info("resuming from checkpoint %s (step %d)", ckpts.directory / str(start), start)
    if jax.process_index() == 0:
        workdir.mkdir(parents=True, exist_ok=True)
        (workdir / "config.json").write_text(json.dumps(to_dict(config), indent=1))
        for name, value in (files or {}).items():
            (workdir / name).write_text(json.dumps(value, indent=1))

    @jax.jit
    def train_step(state, batch):
        (value, parts), grads = jax.value_and_grad(loss, has_aux=True)(state.params, batch)
        state = apply_gradients(state, grads, value, optimizer, o.ema_decay, state.rng)
        return state, {"loss": value, **parts}

    writer = MetricsWriter(workdir, total_steps=t.steps, start_step=start, progress=progress)
    meta = lambda step, status: {"step": step, "status": status, "config": to_dict(config)}
    step, row, status = start, {}, "done"
    with Stop() as stop:  # SIGTERM / SIGINT: save, then stop (the same command resumes)
        while step < t.steps:
            state, metrics = train_step(state, batch(step))
            step += 1
            bad = int(state.bad_steps)
            if on_step is not None:
                on_step(step, metrics)
            if step % t.log_every == 0 or step == t.steps or bad:
                row = writer.write(step, {**jax.device_get(metrics), "bad_steps": bad})
            if bad >= t.max_bad_steps:
                status = "diverged"
                logger.warning(
                    "stopping: %d non-finite losses in a row at step %d (train.max_bad_steps = %d); "
                    "the checkpoint holds the last good parameters",
                    bad,
                    step,
                    t.max_bad_steps,
                )
                break
            if stop.agreed() is not None:
                status = "interrupted"
                break
            if t.checkpoint_every and step % t.checkpoint_every == 0:
                ckpts.save(step, state, None, meta(step, "running"))
    ckpts.save(step, state, None, meta(step, status))
    ckpts.close()
    writer.close()
    params = state.ema if state.ema is not None else state.params
    return {"step": step, "status": status, "loss": row.get("loss"), "params": params}


def load_trained(workdir, cls, section: str, init, *, option: str, what: str):
    """``(config, params)`` of a finished run of ``fit``: its ``config.json`` read as ``cls`` (it
    must have the ``section`` key) and its newest checkpoint's parameters (EMA when kept);
    ``init(config) -> params`` gives their shapes (only traced). A ``ValueError`` names
    ``option`` when the directory is not such a run or none of its checkpoints load."""
    from jaxdrive.train.checkpoint import Checkpoints
    from jaxdrive.train.optim import make_optimizer
    from jaxdrive.train.state import create_state

    path = Path(workdir) / "config.json"
    try:
        data = json.loads(path.read_text()) if path.is_file() else {}
    except ValueError:
        data = {}
    if not isinstance(data, dict) or section not in data:
        raise ValueError(
            f"{option}: expected a {what} run directory (config.json with a {section!r} section), got {str(workdir)!r}"
        )
    config = from_dict(cls, data)
    meta = Checkpoints(workdir, asynchronous=False, option=option)
    if not meta.steps():
        meta.close()
        raise ValueError(f"{option}: expected checkpoints under {Path(workdir) / 'checkpoints'}, found none")
    params = jax.eval_shape(lambda: init(config))
    optimizer = make_optimizer(config.optim, config.train.steps, params)
    abstract = jax.eval_shape(lambda: create_state(init(config), optimizer, 0, ema=config.optim.ema_decay > 0))
    restored = meta.restore_latest_weights(abstract)
    meta.close()
    if restored is None:
        raise ValueError(
            f"{option}: expected checkpoints of this {what} ({getattr(config, section)}), got none "
            f"that load under {Path(workdir) / 'checkpoints'}: {meta.skipped[-1] if meta.skipped else ''}"
        )
    return config, restored[1]
