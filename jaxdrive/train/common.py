"""What every training run shares, below the loops that use it (:mod:`jaxdrive.train.run`, the
auxiliary models' :mod:`jaxdrive.train.aux_run`, :mod:`jaxdrive.train.encode`,
:mod:`jaxdrive.train.init_from`): the run directory's config file, the mesh a config asks for and
its batch axes, the abstract train state a checkpoint restores into, and the SIGTERM / SIGINT flag.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path

import flax.linen as nn
import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive.config import Config
from jaxdrive.parallel import batch_axes, batch_shards, make_mesh, param_shardings  # noqa: F401  (re-exported)
from jaxdrive.parallel.host import Processes
from jaxdrive.train.optim import make_optimizer
from jaxdrive.train.state import create_state

CONFIG_FILE = "config.json"


def mesh_from_config(config: Config, devices=None):
    m = config.mesh
    devices = list(jax.devices() if devices is None else devices)
    sizes = {"data": m.data, "fsdp": m.fsdp, "seq": m.seq, "tensor": m.tensor}
    fixed = int(np.prod([s for s in sizes.values() if s != -1]))
    if -1 not in sizes.values() and fixed != len(devices):
        raise ValueError(
            f"mesh: expected sizes whose product is the device count {len(devices)}, got {sizes} (product {fixed})"
        )
    return make_mesh(**sizes, devices=devices)


def abstract_train_state(model, optim_config, total_steps: int, mesh, *, seed: int = 0):
    """``(abstract state, optimizer)`` of a :class:`jaxdrive.models.dit.model.DiT` config ``model``:
    the state's ``jax.ShapeDtypeStruct`` leaves with their shardings on ``mesh``, from
    ``jax.eval_shape``: the target a checkpoint restores into, with no parameter allocated (at 1B+
    parameters a fresh state would double host and device memory)."""
    from jaxdrive.models.dit.model import DiT, param_trace_shapes

    boxed = DiT(model).abstract_params(**param_trace_shapes(model))
    params = jax.tree_util.tree_map(
        lambda x, sh: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sh), nn.unbox(boxed), param_shardings(boxed, mesh)
    )
    optimizer = make_optimizer(optim_config, total_steps, params)
    ema = optim_config.ema_decay > 0
    with jax.set_mesh(mesh):
        shapes = jax.eval_shape(jax.jit(lambda p: create_state(p, optimizer, seed, ema=ema)), params)
    # eval_shape gives abstract-mesh shardings (None for scalars): place them on this mesh
    on_mesh = lambda x: jax.ShapeDtypeStruct(
        x.shape, x.dtype, sharding=NamedSharding(mesh, x.sharding.spec if x.sharding is not None else P())
    )
    return jax.tree_util.tree_map(on_mesh, shapes), optimizer


def load_run_config(workdir) -> Config:
    """The config a run in ``workdir`` was started with (``workdir/config.json``). A run saved
    before ``model.box_range`` existed embedded its box corners in raw metres: it loads with
    ``box_range=None``, so its parameters keep meaning what they were trained for."""
    from jaxdrive.config import from_dict

    path = Path(workdir) / CONFIG_FILE
    if not path.is_file():
        raise ValueError(f"workdir: expected a training run directory with {CONFIG_FILE}, got {str(workdir)!r}")
    try:
        data = json.loads(path.read_text())  # data, never executed
    except json.JSONDecodeError as e:
        raise ValueError(f"workdir: expected JSON in {path}, got a file that is not ({e})") from None
    if not isinstance(data, dict):
        raise ValueError(f"workdir: expected a JSON object in {path}, got {type(data).__name__}")
    if isinstance(data.get("model"), dict):
        data["model"].setdefault("box_range", None)
    return from_dict(Config, data)


class Stop:
    """SIGTERM / SIGINT set a flag that the loop reads after the step in flight, through
    :meth:`agreed` where several processes run it."""

    def __init__(self):
        self.signum = None
        self._old = {}

    def __enter__(self):
        for s in (signal.SIGTERM, signal.SIGINT):
            try:
                self._old[s] = signal.signal(s, self._handle)
            except ValueError:  # not the main thread: no handlers, nothing to restore
                pass
        return self

    def _handle(self, signum, frame):
        self.signum = signum

    def agreed(self) -> int | None:
        """The signal any process of the job got (the lowest-numbered one's), else None; every
        process must call it at the same point of its loop. A signal sent to one process only (a
        preempted host, not the whole pod) stops them all at the same step: alone it would save a
        checkpoint, a collective write, that the others never join, and hang there."""
        got = [s for s in Processes().gather(self.signum or 0) if s]  # one process: no collective
        return got[0] if got else None

    def __exit__(self, *exc):
        for s, h in self._old.items():
            signal.signal(s, h)


def model_frames(config: Config, codec) -> tuple[int, int]:
    """``(latent frames, source-frame stride)`` the run's model sees: the latents of
    ``data.frames`` at ``data.stride``, or for LongDWM's distilled coarse model one latent frame
    per segment of ``flow.distill_segment_len`` frames (LongDWM [2506.01546v1] eq. 7-8)."""
    d, f = config.data, config.flow
    if f.distill_teacher:
        return (d.frames - 1) // (f.distill_segment_len - 1) + 1, d.stride * (f.distill_segment_len - 1)
    return codec.latent_frames(d.frames), d.stride


def sampling_spec(config: Config, mesh, codec):
    """The :class:`jaxdrive.generate.samples.Sampling` of a run's model from its config alone (no
    train state, no optimizer, no teacher): the model at the run's compute dtype, its window and
    frame stride, the text embeddings of an ``embeddings`` model. :meth:`jaxdrive.train.run.Run.sampling`
    and :class:`jaxdrive.world_model.WorldModel` both build it here."""
    from jaxdrive.data.batches import TextEmbeddings
    from jaxdrive.generate.samples import Sampling
    from jaxdrive.generate.streaming import WINDOW

    c = config
    model = c.model if c.train.compute_dtype == c.model.dtype else c.model.replace(dtype=c.train.compute_dtype)
    text = None
    if model.controls.text == "embeddings" and c.data.text_embeddings:
        text = TextEmbeddings(c.data.text_embeddings)
    frames, stride = model_frames(c, codec)
    return Sampling(
        model,
        codec,
        mesh,
        c.data,
        c.flow,
        text_embeddings=text,
        window=WINDOW if c.stream.enabled else frames,
        stride=stride,
        precomputed=c.latents.precomputed,
        steps=c.train.sample_steps,
        stream=c.stream,
        guidance=c.sample.cfg,
        warp_start=c.sample.warp_start,
    )
