"""A training run from a :class:`jaxdrive.config.Config`: mesh, model, state, data, the loop.

    run = Run(config)                       # checks everything before compiling anything
    state, optimizer, shardings = run.init_state()
    step = run.step_fn(optimizer, shardings)
    summary = train(config, "runs/tiny")    # resumes from runs/tiny/checkpoints when present

``Run`` is what a config determines (mesh, codec, model, shapes, data); it holds no state: its
methods return what they make. Restores (resume, a distillation teacher, ``jaxdrive sample``) read
into the target of :meth:`Run.abstract_state` (``jax.eval_shape`` with shardings), never into a
freshly initialised state.

The loop (:func:`train`): one jitted step per update (:mod:`jaxdrive.train.flow_step`), metrics
every ``train.log_every`` steps (``metrics.jsonl``, TensorBoard, a progress bar), checkpoints
every ``train.checkpoint_every`` steps, at the end, on SIGTERM / SIGINT (after the step in
flight) and when ``train.max_bad_steps`` non-finite losses in a row stop the run (the state then
is the last good one: non-finite steps never update it). A run started in a directory that holds
checkpoints continues from the newest readable one, with the data iterator where it was, so a
stopped and resumed run ends with the same parameters as one that never stopped.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import signal
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
from jax.sharding import PartitionSpec as P

from jaxdrive.config import Config, to_dict
from jaxdrive.config_checks import check_sections
from jaxdrive.data.batches import TextEmbeddings, model_inputs, stack_micro_batches
from jaxdrive.logs import deprecated_log
from jaxdrive.models.dit.model import param_trace_shapes
from jaxdrive.models.latents import LatentCodec
from jaxdrive.parallel import Processes, host_local_to_global, shard_params, wait_for_all_processes
from jaxdrive.train import flow_step
from jaxdrive.train.checkpoint import Checkpoints
from jaxdrive.train.common import (  # noqa: F401
    CONFIG_FILE,
    Stop,
    abstract_train_state,
    batch_axes,
    batch_shards,
    load_run_config,
    mesh_from_config,
    model_frames,
    sampling_spec,
)
from jaxdrive.train.encode import check_dataset
from jaxdrive.train.metrics import MetricsWriter
from jaxdrive.train.optim import make_optimizer
from jaxdrive.train.state import create_state
from jaxdrive.train.workdir_lock import job_workdir_lock

logger = logging.getLogger(__name__)


def check_batch(config: Config, mesh, batch: int | None = None, name: str = "data.batch_size") -> tuple[int, int]:
    """``(micro-batch per process, micro-batch global)`` of the global ``batch`` (default
    ``data.batch_size``); ``ValueError`` naming ``name`` when it does not divide over processes,
    accumulation steps and the mesh's batch axes."""
    shards = batch_shards(mesh)
    b = config.data.batch_size if batch is None else batch
    a, procs = config.optim.grad_accum, jax.process_count()
    micro = b // a if b % a == 0 else None
    if micro is None or micro % shards or micro % procs:
        raise ValueError(
            f"{name}: expected a multiple of optim.grad_accum ({a}) x the batch mesh "
            f"axes data x fsdp ({shards}) and of the process count ({procs}), got {b}"
        )
    return micro // procs, micro


def training_buckets(config: Config, compression: int):
    """The (H, W, F) buckets a run trains on, each with its global batch
    (:class:`jaxdrive.data.buckets.Bucket`): ``data.buckets``, or the one bucket
    ``data.height x data.width x data.frames`` at ``data.batch_size``."""
    from jaxdrive.data.buckets import parse_bucket_specs, parse_buckets

    d = config.data
    frames = d.frames
    if config.flow.self_rollout_rate:  # a rollout's two windows (jaxdrive.train.self_rollout)
        from jaxdrive.train.self_rollout import clip_frames

        frames = clip_frames(d.frames, config.flow.cond_frames, compression)
    specs = parse_bucket_specs(d.buckets) if d.buckets else {(d.height, d.width, frames): (d.batch_size, 1.0)}
    try:
        return parse_buckets(specs, compression=compression)
    except ValueError as e:  # parse_buckets names its argument "buckets"
        raise ValueError(f"data.{e}") from None


def sharded_state(boxed_params, mesh, optim_config, total_steps: int, seed: int):
    """``(state, optimizer)``: parameters placed by their logical names, the optimizer state and
    EMA created on the mesh (sharded like the parameters)."""
    with jax.set_mesh(mesh):
        params = shard_params(boxed_params, mesh)
    return state_from_params(params, mesh, optim_config, total_steps, seed)


def state_from_params(params, mesh, optim_config, total_steps: int, seed: int):
    """``(state, optimizer)`` at step 0 for placed ``params``: optimizer state and EMA created on
    the mesh, sharded like the parameters."""
    with jax.set_mesh(mesh):
        optimizer = make_optimizer(optim_config, total_steps, params)
        ema = optim_config.ema_decay > 0
        state = jax.jit(lambda p: create_state(p, optimizer, seed, ema=ema))(params)
    return state, optimizer


def check_warp(config: Config, temporal: int = 1) -> None:
    """LongDWM's warp-guided control needs pixel clips to warp, and one window per clip; its
    source frame a given frame that is a latent frame of its own (``temporal``: the codec's
    temporal compression): ``ValueError`` naming the option that rules it out."""
    d = config.data
    if not (np.isfinite(d.warp_depth) and d.warp_depth > 0):
        raise ValueError(
            f"data.warp_depth: expected a positive depth in metres for a model with controls.warp, got {d.warp_depth}"
        )
    last = max(config.flow.cond_frames - 1, 0) if temporal == 1 else 0
    if isinstance(d.warp_frame, bool) or not isinstance(d.warp_frame, int) or not 0 <= d.warp_frame <= last:
        raise ValueError(
            f"data.warp_frame: expected a given frame to warp from, 0 to {last} (flow.cond_frames "
            f"{config.flow.cond_frames}, temporal compression {temporal}), got {d.warp_frame!r}"
        )
    for name, value, ok in (
        ("latents.precomputed", config.latents.precomputed, False),
        ("flow.distill_teacher", config.flow.distill_teacher, ""),
        ("stream.enabled", config.stream.enabled, False),
    ):
        if value != ok:
            raise ValueError(
                f"{name}: expected {ok!r} with model.controls.warp (the warp is made from the clip's "
                f"pixels, one warped clip per window), got {value!r}"
            )


def global_micro_batches(inputs: list[dict], mesh):
    """This process's micro-batches (host model inputs) -> one global ``[A, b, ...]`` tree with
    ``b`` over the mesh's batch axes (``data``/``fsdp``) and the rest replicated."""
    return host_local_to_global(stack_micro_batches(inputs), mesh, P(None, batch_axes(mesh) or None))


class Run:
    """Everything a run builds from its config (see the module docstring)."""

    def __init__(
        self,
        config: Config,
        *,
        devices=None,
        total_steps: int | None = None,
        codec: LatentCodec | None = None,
        check_data: bool = True,
    ):
        """``codec``: the latents' codec in place of the one ``config.latents`` loads, and
        ``check_data=False``: ``data.path`` is not read, nor is ``train.init_from`` asked for, and a
        distillation teacher without a run directory is this run's own model (the memory
        planner's run: its VAE parameters are shapes only, and it needs no data and no earlier
        stage's weights)."""
        check_sections(config)
        self.config = config
        self._planning = not check_data
        self.total_steps = int(total_steps or config.train.steps)
        self.mesh = mesh_from_config(config, devices)
        check_batch(config, self.mesh)
        self.codec = LatentCodec.from_config(config.latents) if codec is None else codec
        self.buckets = training_buckets(config, max(self.codec.temporal, 1))
        for b in self.buckets if config.data.buckets else ():  # the default bucket is data.batch_size's
            check_batch(config, self.mesh, b.batch_size, name=f"data.buckets {'x'.join(map(str, b.key))}")
        if check_data:
            check_dataset(config, self.codec)  # latent windows or clips, as latents.precomputed says
            if config.data.routes and Path(config.data.path).exists():  # else the pipeline names it
                from jaxdrive.data.route_mix import check_route_mix, parse_route_mix

                check_route_mix(config.data.path, parse_route_mix(config.data.routes))
        model = config.model
        if config.train.compute_dtype != model.dtype:
            model = model.replace(dtype=config.train.compute_dtype)
        self.codec.check_model(model)
        tensor = dict(zip(self.mesh.axis_names, self.mesh.axis_sizes)).get("tensor", 1)
        if model.heads % tensor:
            raise ValueError(f"model.heads: expected a multiple of the mesh axis tensor ({tensor}), got {model.heads}")
        d = config.data
        grid = self.codec.spatial * model.patch[1]
        for name, (h, w) in [("data.height, data.width", (d.height, d.width))] + [
            (f"data.buckets {'x'.join(map(str, b.key))}", (b.height, b.width)) for b in self.buckets
        ]:
            if h % grid or w % (self.codec.spatial * model.patch[2]):
                raise ValueError(f"{name}: expected multiples of latent compression x patch ({grid}), got {h} x {w}")
        if check_data and config.train.init_from and not Path(config.train.init_from).is_dir():
            raise ValueError(
                f"train.init_from: expected a run directory or a diffusers transformer folder, got "
                f"{config.train.init_from!r} (not a directory)"
            )
        if config.train.init_map:
            from jaxdrive.train.init_from import parse_name_map

            parse_name_map(config.train.init_map)
        teacher = self._teacher_model() if config.flow.distill_teacher else None
        self.training = flow_step.FlowTraining(
            model,
            config.flow,
            self.codec,
            teacher,
            config.stream,
            warp_frame=config.data.warp_frame,
            warp_depth=config.data.warp_depth,
        )
        # frames the trained model sees, and the source-frame stride between them
        self.latent_frames, self.frame_stride = model_frames(config, self.codec)
        from jaxdrive.train.stream_step import check_stream

        check_stream(config, self.latent_frames, needs_init=check_data)
        if model.controls.warp:
            check_warp(config, max(self.codec.temporal, 1))
        self.tokens_per_step = self.tokens(d.batch_size, d.height, d.width, self.latent_frames)
        self.text = None
        if model.controls.text == "embeddings":
            self.text = TextEmbeddings(d.text_embeddings) if d.text_embeddings else None

    def tokens(self, batch: int, height: int, width: int, latent_frames: int) -> int:
        """Video tokens of a global batch of ``batch`` clips at ``height x width`` pixels."""
        m, sp = self.training.model, self.codec.spatial
        return (
            batch
            * self.config.data.views
            * latent_frames
            * (height // (sp * m.patch[1]))
            * (width // (sp * m.patch[2]))
        )

    def batch_tokens(self, batch) -> int:
        """Video tokens of a global batch from :meth:`global_batch` (its bucket's shape)."""
        x = batch["latents"] if "latents" in batch else batch["video"]  # [A, b, V, F, H, W, C]
        frames = x.shape[3] if "latents" in batch else self.codec.latent_frames(x.shape[3])
        h, w = (
            (x.shape[4] * self.codec.spatial, x.shape[5] * self.codec.spatial)
            if "latents" in batch
            else (x.shape[4], x.shape[5])
        )
        return self.tokens(x.shape[0] * x.shape[1], h, w, frames)

    def _teacher_model(self):
        """The fine model of LongDWM's distillation, from the config of the run directory
        ``flow.distill_teacher`` (its parameters: :meth:`frozen_params`)."""
        cfg, path = self.config, self.config.flow.distill_teacher
        if self.codec.temporal != 1:
            raise ValueError(
                f"latents: expected frame-wise latents (temporal compression 1) for distillation "
                f"(a segment boundary must be a latent frame; LongDWM encodes frames one by one), "
                f"got temporal compression {self.codec.temporal}"
            )
        try:
            tcfg = load_run_config(path)
        except ValueError as e:
            if self._planning:  # LongDWM's fine and coarse models are one transformer: plan with this one's
                logger.warning("flow.distill_teacher: no run at %r; the plan's teacher is this run's own model", path)
                tcfg = cfg
            else:
                raise ValueError(
                    f"flow.distill_teacher: expected the run directory of the fine model, got {path!r} ({e})"
                ) from e
        model = tcfg.model.replace(dtype=cfg.train.compute_dtype)
        try:
            self.codec.check_model(model)
        except ValueError as e:
            raise ValueError(
                f"flow.distill_teacher: the fine model of {path} does not read this run's latents: {e}"
            ) from e
        self._teacher_config = tcfg
        return model

    def frozen_params(self) -> dict:
        """The parameters the step reads but does not train (see :func:`flow_step.train_step`):
        the VAE's and, when distilling, the fine model's (EMA) parameters, restored from its run
        directory (call once per run; nothing is cached here)."""
        teacher = None
        abstract = self.teacher_abstract_state()
        if abstract is not None:  # restored on this run's mesh; its own data plays no part
            _, teacher = restore_latest_params(
                abstract,
                self.config.flow.distill_teacher,
                keep=self._teacher_config.train.keep_checkpoints,
                option="flow.distill_teacher",
            )
        return {"codec": self.codec.params, "teacher": teacher}

    def teacher_abstract_state(self):
        """The distillation teacher's train state as shapes with their shardings on this run's
        mesh (None when the run does not distill): what :meth:`frozen_params` restores into, and
        what the planner counts, at no memory."""
        if self.training.teacher is None:
            return None
        t = self._teacher_config
        abstract, _ = abstract_train_state(t.model, t.optim, t.train.steps, self.mesh, seed=t.train.seed)
        return abstract

    def sampling(self):
        """The :class:`jaxdrive.generate.samples.Sampling` of this run's model (its window and
        frame stride, a distilled coarse model's included; :func:`jaxdrive.train.common.sampling_spec`)."""
        from dataclasses import replace

        spec = sampling_spec(self.config, self.mesh, self.codec)
        return replace(spec, model=self.training.model, text_embeddings=self.text)

    # ------------------------------------------------------------------ state
    def boxed_params(self):
        """The model's initial parameters in ``nn.LogicallyPartitioned`` boxes, drawn on the host
        (``train.seed``), from the model traced as :meth:`abstract_state` traces it."""
        dit = self.training.dit
        return dit.init_params(self.config.train.seed, boxed=True, **param_trace_shapes(dit.config))

    @deprecated_log
    def init_state(self):
        """``(state, optimizer, shardings)``: a fresh state on the mesh (params FSDP / tensor
        sharded by their logical names; with ``train.init_from``, the parameters another run or a
        diffusers folder has, :mod:`jaxdrive.train.init_from`, and what it loaded in the log), its
        optimizer and the state's shardings. ``log=`` is deprecated (:func:`jaxdrive.logs.deprecated_log`)."""
        cfg, t = self.config, self.config.train
        with jax.set_mesh(self.mesh):
            params = shard_params(self.boxed_params(), self.mesh)
        if t.init_from:
            from jaxdrive.train.init_from import init_from

            params, report = init_from(
                params,
                t.init_from,
                mesh=self.mesh,
                ema=t.init_from_ema,
                name_map=t.init_map,
                target_model=self.training.model,
            )
            logger.info("%s", report.summary())
        state, optimizer = state_from_params(params, self.mesh, cfg.optim, self.total_steps, cfg.train.seed)
        return state, optimizer, jax.tree_util.tree_map(lambda x: x.sharding, state)

    def abstract_state(self):
        """``(abstract state, optimizer)``: the state's ``jax.ShapeDtypeStruct`` leaves with their
        shardings on the mesh (:func:`abstract_train_state`; the restore target of a checkpoint)."""
        cfg = self.config
        return abstract_train_state(self.training.model, cfg.optim, self.total_steps, self.mesh, seed=cfg.train.seed)

    def step_fn(self, optimizer, shardings):
        """The jitted train step for the state's ``optimizer`` and ``shardings``."""
        return flow_step.make_train_step(
            self.training, optimizer, self.config.optim.ema_decay, state_shardings=shardings
        )

    # ------------------------------------------------------------------ data
    def dataset(self, split: str | None = None):
        from jaxdrive.data.pipeline import CONDITIONS, make_pipeline
        from jaxdrive.data.tfds_io import open_source

        d = self.config.data
        split = split or d.split
        if d.routes and split == "train":  # each scene along a route of the mix (jaxdrive.data.route_mix)
            from jaxdrive.data.route_mix import open_routed_scenes, parse_route_mix

            source = open_routed_scenes(d.path, parse_route_mix(d.routes))
        else:
            source = open_source(d.path, split)
        stride = 1 if self.config.latents.precomputed else d.stride  # latent windows are strided already
        procs = jax.process_count()
        buckets = {
            b.key: (b.batch_size // (procs * self.config.optim.grad_accum), b.prob, b.repeat) for b in self.buckets
        }
        return make_pipeline(
            source,
            buckets,
            stride=stride,
            views=list(range(d.views)),
            drop_probs={n: d.drop_prob for n in CONDITIONS},
            seed=d.shuffle_seed,
            num_threads=d.threads,
            prefetch=2 if d.threads else 0,
            compression=max(self.codec.temporal, 1),
            rate_head=d.rate_head,
            rate_strides=d.rate_strides,
            warp_depth=d.warp_depth if self.training.model.controls.warp else 0.0,
            warp_frame=d.warp_frame,
            skip_bad_records=d.skip_bad_records,
            route_parting=d.route_parting if d.routes and split == "train" else 0.0,
            given_frames=self.codec.pixel_frames(max(self.config.flow.cond_frames, 1)),
        )

    def global_batch(self, micro_batches: list[dict]):
        """Host micro-batches (this process's samples) -> one global ``[A, b, ...]`` tree."""
        t = self.training
        return global_micro_batches(
            [
                model_inputs(
                    b,
                    t.model,
                    self.text,
                    foreground=t.flow.foreground_k > 0,
                    teacher=t.teacher,
                    poses=t.flow.self_rollout_rate > 0,
                )
                for b in micro_batches
            ],
            self.mesh,
        )


class _BadRecords:
    """The clips the data pipeline skipped as unreadable (``data.skip_bad_records``), summed over
    processes. Each process counts the ``bad_records`` of its own batches; the sum (a host
    all-gather) is taken only where every process stands at the same step: when metrics are
    logged and when a checkpoint is saved, whose metadata keeps it for a resumed run."""

    def __init__(self, total: int = 0):
        self.total, self.pending = int(total), 0

    def add(self, micro_batches: list[dict]) -> None:
        self.pending += sum(int(b.pop("bad_records", 0)) for b in micro_batches)

    def sync(self) -> int:
        n = sum(Processes().gather(self.pending))
        self.total, self.pending = self.total + n, 0
        return self.total


def _save(ckpts, step, state, it, config, **extra) -> bool:
    """Start saving checkpoint ``step``; False (and a warning) when it, or the asynchronous write
    of an earlier one that surfaces here, fails: orbax commits a checkpoint by renaming its
    temporary folder, so the ones written before stay intact."""
    try:
        ckpts.save(step, state, it.get_state(), {"step": step, "time": time.time(), **extra, "config": to_dict(config)})
        return True
    except Exception as e:  # OSError (disk full), or orbax's wrapping of one
        logger.warning(
            "checkpoint %s could not be written (%s: %s); checkpoints kept: %s",
            ckpts.directory / str(step),
            type(e).__name__,
            str(e)[:200],
            _kept(ckpts),
        )
        return False


def _kept(ckpts) -> list[int]:
    try:
        return ckpts.steps()
    except Exception:
        return []


def _compile_together(step_fn, compiled: set, *args) -> None:
    """Several processes: compile the step for a new batch shape, then wait for the others before
    running it, so that its collectives start together: a process that compiles slower (a busy
    host) would otherwise make the first collective of the faster ones time out."""
    if jax.process_count() == 1:
        return
    shapes = tuple((x.shape, str(x.dtype)) for x in jax.tree_util.tree_leaves(args[-1]))
    if shapes not in compiled:
        compiled.add(shapes)
        step_fn.lower(*args).compile()  # jit reuses this executable for the call that follows
        wait_for_all_processes(f"jaxdrive.train: step compiled for batch shape {len(compiled)}")


@dataclasses.dataclass
class _Loop:
    """What the parts of one :func:`train` call share: the run, where it writes, its data
    iterator, and the state, step and outcome that the loop moves on."""

    run: Run
    workdir: Path
    ckpts: Checkpoints
    it: Any
    state: Any
    step: int
    bad_records: _BadRecords
    started: float  # time.perf_counter() when train() was called
    cache: tuple  # (the compilation cache's folder, its counts when train() was called)
    writer: MetricsWriter | None = None
    status: str = "done"
    row: dict = dataclasses.field(default_factory=dict)
    first_step: float | None = None

    def counts(self) -> dict:
        """What metrics rows and checkpoint metadata add (a sum over processes: every process
        calls it at the same point of the loop)."""
        return {"bad_records": self.bad_records.sync()} if self.run.config.data.skip_bad_records else {}

    def save(self, **extra) -> bool:
        """:func:`_save` of the current step and state."""
        return _save(self.ckpts, self.step, self.state, self.it, self.run.config, **extra)


@deprecated_log
def train(config: Config, workdir, *, on_step=None, progress: bool = True, devices=None) -> dict:
    """Train (or resume) in ``workdir``; returns ``{"step", "status", "loss", ...}``.
    ``devices``: the devices the config's mesh spans (default: all of them, :class:`Run`).
    ``status``: ``"done"``, ``"interrupted"`` (a signal), ``"diverged"`` (non-finite losses) or
    ``"save_failed"`` (a checkpoint could not be written: stopped by ``train.on_save_error="stop"``,
    or the final one).
    ``bad_records``: with ``data.skip_bad_records``, the unreadable clips the pipeline replaced since
    the run began (resumes included), all processes together, as every metrics row also says;
    None without it.
    ``on_step(step, metrics)`` is called after every step (tests). The returned
    ``first_step_seconds`` is the time from this call to the end of the first step (compiling
    included) and ``compile_cache`` what the persistent cache gave (:mod:`jaxdrive.compile_cache`).
    Progress (a resume, the first step's time, written samples) is logged at INFO, what stops or
    endangers the run (non-finite losses, a checkpoint not written, a signal) at WARNING
    (:mod:`jaxdrive.logs`); ``log=`` is deprecated (:func:`jaxdrive.logs.deprecated_log`).
    Once the config is checked the run holds ``workdir``'s lock to its end (process 0 for the job,
    :mod:`jaxdrive.train.workdir_lock`): a ``workdir`` another live run holds is refused with a
    :class:`~jaxdrive.train.workdir_lock.WorkdirLocked` (a ``ValueError``) naming it; a killed run's
    lock is taken over with a warning."""
    from jaxdrive import compile_cache

    started = time.perf_counter()
    cache = compile_cache.enable(config.train.compile_cache), compile_cache.counts()
    workdir = Path(workdir)
    run = Run(config, devices=devices)
    with job_workdir_lock(workdir):  # from here to the last checkpoint's commit
        loop, optimizer, shardings = _start(run, workdir, started, cache)
        if jax.process_index() == 0:
            workdir.mkdir(parents=True, exist_ok=True)
            (workdir / CONFIG_FILE).write_text(json.dumps(to_dict(config), indent=1))
        step_fn, frozen = run.step_fn(optimizer, shardings), run.frozen_params()
        loop.writer = MetricsWriter(
            workdir,
            total_steps=run.total_steps,
            start_step=loop.step,
            tokens_per_step=run.tokens_per_step,
            progress=progress,
        )
        with Stop() as stop, jax.set_mesh(run.mesh):
            _steps(loop, step_fn, frozen, stop, on_step)
        _finish(loop)
        return _summary(loop, step_fn)


def _start(run: Run, workdir: Path, started: float, cache: tuple):
    """``(loop, optimizer, shardings)`` at the run's start: resumed from the newest readable
    checkpoint of ``workdir`` (the data iterator where it was), else a fresh state at step 0."""
    it = iter(run.dataset())
    ckpts = Checkpoints(workdir, keep=run.config.train.keep_checkpoints)
    abstract, optimizer = run.abstract_state()
    restored = ckpts.restore_latest(abstract)
    if restored is not None:
        start, state, data_state, meta = restored
        it.set_state(data_state)
        shardings = jax.tree_util.tree_map(lambda x: x.sharding, abstract)
        logger.info("resuming from checkpoint %s (step %d)", ckpts.directory / str(start), start)
    else:
        state, optimizer, shardings = run.init_state()
        start, meta = 0, {}
    bad_records = _BadRecords(meta.get("bad_records", 0))
    return _Loop(run, workdir, ckpts, it, state, start, bad_records, started, cache), optimizer, shardings


def _steps(loop: _Loop, step_fn, frozen, stop: Stop, on_step) -> None:
    """The loop from ``loop.step`` to ``train.steps``, then the final checkpoint; a stop on the
    way (:func:`_stops`) ends it with its own checkpoint."""
    tokens, compiled_shapes = 0, set()
    while loop.step < loop.run.total_steps:
        metrics, bad, batch_tokens = _step(loop, step_fn, frozen, compiled_shapes)
        tokens = _log(loop, metrics, bad, tokens + batch_tokens)
        if on_step is not None:
            on_step(loop.step, metrics)
        if _stops(loop, bad, stop):
            return
    if not loop.save(status=loop.status, **loop.counts()):
        loop.status = "save_failed"


def _step(loop: _Loop, step_fn, frozen, compiled_shapes: set) -> tuple[dict, int, int]:
    """One update from the next ``optim.grad_accum`` micro-batches: ``(metrics, non-finite steps
    in a row, the batch's video tokens)``. The first logs the time since :func:`train` began."""
    run = loop.run
    micro = [next(loop.it) for _ in range(run.config.optim.grad_accum)]
    loop.bad_records.add(micro)
    batch = run.global_batch(micro)
    tokens = run.batch_tokens(batch)  # buckets differ in tokens per step
    _compile_together(step_fn, compiled_shapes, loop.state, frozen, batch)
    loop.state, metrics = step_fn(loop.state, frozen, batch)  # compiled once per bucket shape
    loop.step += 1
    bad = int(metrics["bad_steps"])
    if loop.first_step is None:
        from jaxdrive import compile_cache

        loop.first_step = time.perf_counter() - loop.started
        logger.info("first step done %.1f s after the start; %s", loop.first_step, compile_cache.describe(*loop.cache))
    return metrics, bad, tokens


def _log(loop: _Loop, metrics, bad: int, tokens: int) -> int:
    """A metrics row every ``train.log_every`` steps, at the last step and at a non-finite one;
    returns the video tokens not yet in a row."""
    step, run = loop.step, loop.run
    if not (step % run.config.train.log_every == 0 or step == run.total_steps or bad):
        return tokens
    # skipped (all steps so far) and the last step whose update was applied
    loop.row = loop.writer.write(
        step, {**jax.device_get(metrics), "last_good_step": step - bad, **loop.counts()}, tokens=tokens
    )
    return 0


def _stops(loop: _Loop, bad: int, stop: Stop) -> bool:
    """What follows a step: a stop on ``train.max_bad_steps`` non-finite losses, the checkpoint and
    samples that are due, a stop on a failed save (``train.on_save_error="stop"``) or a signal.
    True when the run stops (``loop.status`` says why)."""
    cfg, step = loop.run.config.train, loop.step
    if bad >= cfg.max_bad_steps:
        return _diverged(loop, bad)
    if cfg.checkpoint_every and step % cfg.checkpoint_every == 0 and _save_stops(loop):
        return True
    if cfg.sample_every and step % cfg.sample_every == 0:
        from jaxdrive.generate.samples import write_samples

        write_samples(loop.run.sampling(), loop.state, loop.workdir / "samples" / f"step_{step:07d}")
    return _interrupted(loop, stop)


def _diverged(loop: _Loop, bad: int) -> bool:
    """Stop on non-finite losses, with a checkpoint of the last good state."""
    loop.status = "diverged"
    loop.save(status=loop.status, **loop.counts())
    logger.warning(
        "stopping: %d non-finite losses in a row at step %d (train.max_bad_steps = %d); "
        "checkpoint %s holds the last good parameters",
        bad,
        loop.step,
        loop.run.config.train.max_bad_steps,
        loop.ckpts.directory / str(loop.step),
    )
    return True


def _save_stops(loop: _Loop) -> bool:
    """The checkpoint every ``train.checkpoint_every`` steps; True (status ``"save_failed"``) when
    it fails and ``train.on_save_error`` is ``"stop"``."""
    if loop.save(**loop.counts()) or loop.run.config.train.on_save_error != "stop":
        return False
    loop.status = "save_failed"
    logger.warning(
        "stopping at step %d (train.on_save_error = 'stop'); the last checkpoint is the newest of %s",
        loop.step,
        _kept(loop.ckpts),
    )
    return True


def _interrupted(loop: _Loop, stop: Stop) -> bool:
    """Stop, with a checkpoint, when any process got SIGTERM / SIGINT."""
    signum = stop.agreed()  # one process's signal stops every process
    if signum is None:
        return False
    loop.status = "interrupted"
    loop.save(status=loop.status, **loop.counts())
    logger.warning(
        "signal %s: saved checkpoint %s; run the same command to resume",
        signal.Signals(signum).name,
        loop.ckpts.directory / str(loop.step),
    )
    return True


def _finish(loop: _Loop) -> None:
    """Wait for the last checkpoint's write (status ``"save_failed"`` when it fails), close the
    metrics."""
    try:
        with Stop():  # a late SIGTERM (the launcher stopping the others) waits for the commit
            loop.ckpts.close()  # waits for the last asynchronous write
    except Exception as e:
        loop.status = "save_failed"
        logger.warning(
            "the last checkpoint could not be written (%s: %s); checkpoints kept: %s",
            type(e).__name__,
            str(e)[:200],
            _kept(loop.ckpts),
        )
    loop.writer.close()


def _summary(loop: _Loop, step_fn) -> dict:
    """What :func:`train` returns."""
    from jaxdrive import compile_cache

    cache_dir, cache_before = loop.cache
    # programs the step compiled: one per bucket shape met since this process started
    compiled = step_fn._cache_size() if hasattr(step_fn, "_cache_size") else None
    now = compile_cache.counts()
    skipping = loop.run.config.data.skip_bad_records
    return {
        "step": loop.step,
        "status": loop.status,
        "loss": loop.row.get("loss"),
        "state": loop.state,
        "run": loop.run,
        "bad_records": loop.bad_records.total if skipping else None,  # summed by the last save
        "compiled_steps": compiled,
        "first_step_seconds": loop.first_step,
        "compile_cache": {
            "folder": None if cache_dir is None else str(cache_dir),
            **{k: now[k] - cache_before[k] for k in now},
        },
    }


@deprecated_log
def restore_params(run: Run, workdir, *, ema: bool = True, option: str = "workdir"):
    """``(step, params)`` of the newest readable checkpoint of ``workdir`` (EMA when kept); a
    damaged newer one is skipped with a warning in the log; errors name ``option`` (how the
    caller calls ``workdir``). ``log=`` is deprecated (:func:`jaxdrive.logs.deprecated_log`)."""
    return restore_latest_params(
        run.abstract_state()[0], workdir, keep=run.config.train.keep_checkpoints, ema=ema, option=option
    )


def restore_latest_params(abstract, workdir, *, keep: int, ema: bool = True, option: str = "workdir"):
    """``(step, params)`` of the newest readable checkpoint of ``workdir`` restored into the
    abstract train state ``abstract`` (:func:`abstract_train_state`; EMA when kept); errors name
    ``option``."""
    ckpts = Checkpoints(workdir, keep=keep, asynchronous=False, option=option)
    restored = ckpts.restore_latest_weights(abstract, ema=ema)
    ckpts.close()
    if restored is None:
        raise ValueError(f"{option}: expected checkpoints under {Path(workdir) / 'checkpoints'}, found none")
    return restored
