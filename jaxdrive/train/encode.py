"""Precomputed latents: ``jaxdrive data encode`` encodes a clip dataset's training windows once, so
that the train step reads latents instead of running the VAE on every batch.

    encode_dataset(config, "data/latents")        # the clips of config.data.path -> latent windows
    # then train with --set latents.precomputed=true --set data.path=data/latents

Each clip is cut into windows of ``data.frames`` frames at ``data.stride``, starting at frames 0,
``every``, ``2 every``, ... (``every`` defaults to the window's span in source frames: no overlap);
each window keeps the first ``data.views`` views and is resized and centre-cropped to
(``data.height``, ``data.width``) by the pipeline's :func:`jaxdrive.data.pipeline.sample_clip`, so
intrinsics and waypoints are adjusted exactly as in training. The video is encoded in jitted
batches by :class:`jaxdrive.models.latents.LatentCodec` (scaled latents) and the windows are written
by :func:`jaxdrive.data.tfds_io.write_dataset` as records of kind ``"windows"``
(:data:`jaxdrive.data.schema.WINDOW_FIELDS`), in order: clip by clip, window by window. The
dataset's metadata (``"encoded"``) records what produced the latents; :func:`check_dataset`
compares it with a run's config before anything compiles.

Scale: each encoder call is one global batch sharded over the mesh's batch axes (``data``,
``fsdp``); with several processes each encodes a contiguous range of every split's clips and
writes its own shards, which together read as the one-process output (:func:`encode_dataset`).

Distillation (LongDWM, :mod:`jaxdrive.train.distill_step`) reads such windows as it reads clips:
its latents are frame-wise, so a dense window's latents are every frame both the coarse model
(every ``(K - 1)``-th) and the frozen fine model (each K-frame segment) take, and its poses and
controls are stored with it.
"""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive.config_checks import check_sections
from jaxdrive.models.latents import LatentCodec
from jaxdrive.parallel import Processes, global_to_host_local, host_local_to_global
from jaxdrive.progress import Progress
from jaxdrive.train.common import batch_axes, batch_shards, mesh_from_config
from jaxdrive.validate import check_positive_int

log = logging.getLogger(__name__)

METADATA_KEY = "encoded"
_CODEC_FIELDS = ("source", "factor", "scale", "vae_path", "vae_mode")
_DATA_FIELDS = ("height", "width", "frames", "stride", "views")


def _span(data) -> int:
    """Source frames a window covers."""
    return 1 + (data.frames - 1) * data.stride


def _starts(have: int, data, every: int) -> range:
    """Window starts in a clip of ``have`` frames."""
    return range(0, have - _span(data) + 1, every)


def _window_count(source, data, every: int, clips) -> int | None:
    """How many windows the ``clips`` of ``source`` give, from its stored frame counts (None without them)."""
    counts = source.frame_counts
    return None if counts is None else sum(len(_starts(int(counts[i]), data, every)) for i in clips)


def _too_short(source, data, longest: int) -> ValueError:
    return ValueError(
        f"data.frames: {data.frames} frames at stride {data.stride} need {_span(data)} source frames, "
        f"but the longest clip of split {source.split!r} of {source.path} has {longest}"
    )


def _windows(source, data, every: int, clips):
    """``sample_clip`` of every window of the ``clips`` (indices) of ``source``, in order."""
    from jaxdrive.data.transforms import sample_clip

    count = longest = 0
    for i in clips:
        clip = source[i]
        have = int(np.shape(clip["ego_to_world"])[0])
        longest = max(longest, have)
        for start in _starts(have, data, every):
            count += 1
            window = sample_clip(
                clip,
                size=(data.height, data.width),
                frames=data.frames,
                stride=data.stride,
                start=start,
                views=list(range(data.views)),
                where=f"{source.path} split {source.split!r} clip {i}",
            )
            del window["frame_times"]  # uniform frames: take_window rebuilds them from the fps
            yield window
    if count == 0 and len(clips) == len(source):
        raise _too_short(source, data, longest)


def _encoded(windows, codec: LatentCodec, batch: int, mesh, processes: Processes, video_shape, bar):
    """The windows with ``video`` replaced by its ``latents``, ``batch`` windows of this process
    per encoder call; ``bar`` counts them. The calls' batches are global arrays over the mesh's
    batch axes (this process's windows on its devices); every process makes the same calls until
    all have run out (one without windows left encodes zeros of ``video_shape``), and the last
    batch is padded, so that the encoder compiles once."""
    spec = P(batch_axes(mesh) or None)
    params = jax.device_put(jax.tree_util.tree_map(np.asarray, codec.params), NamedSharding(mesh, P()))
    encode = jax.jit(codec.encode, out_shardings=NamedSharding(mesh, spec))
    windows = iter(windows)
    while True:
        pending = list(itertools.islice(windows, batch))
        if not any(processes.gather(len(pending))):
            return
        video = np.stack([w.pop("video") for w in pending]) if pending else np.zeros((1, *video_shape), np.float32)
        video = np.concatenate([video, np.repeat(video[-1:], batch - len(video), axis=0)])
        with jax.set_mesh(mesh):
            latents = global_to_host_local(encode(params, host_local_to_global(video, mesh, spec)))
        for w, z in zip(pending, np.asarray(latents, np.float32)):
            w["latents"] = z
        bar.update(len(pending))
        yield from pending


def encode_dataset(
    config,
    out,
    *,
    splits=None,
    every: int | None = None,
    batch: int = 8,
    overwrite: bool = False,
    progress: bool = False,
    devices=None,
) -> Path:
    """Write the latent windows of the clip dataset ``config.data.path`` to ``out`` (module
    docstring); returns the dataset path. ``splits``: the splits to encode (default: all of the
    dataset's); ``every``: source frames between window starts; ``batch``: windows per encoder call
    (all processes together), a multiple of the mesh's batch axes data x fsdp (the mesh of
    ``config.mesh`` over ``devices``, default all); ``progress``: the progress over this process's
    windows (with a total and an ETA when the dataset records its clips' frame counts): a tqdm bar
    when stderr is a terminal, else a ``jaxdrive.progress`` log line at every twentieth of them
    (:mod:`jaxdrive.progress`).

    With several processes (:func:`jaxdrive.parallel.initialize_distributed`) each encodes a
    contiguous range of every split's clips and writes its windows as its own shards of the one
    dataset (:func:`jaxdrive.data.tfds_io.write_dataset` with ``processes``; ``out`` on a
    filesystem all of them see), which then reads exactly as the one-process output."""
    from jaxdrive.data.tfds_io import dataset_info, open_source, write_dataset

    check_sections(config)
    d = config.data
    every = _span(d) if every is None else check_positive_int("every", every)
    batch = check_positive_int("batch", batch)
    mesh = mesh_from_config(config, devices)
    processes, shards = Processes(), batch_shards(mesh)
    if shards % processes.count:
        raise ValueError(
            f"mesh: expected batch axes data x fsdp spread over the {processes.count} processes "
            f"(a multiple of the process count), got data x fsdp = {shards}"
        )
    if batch % shards:
        raise ValueError(f"batch: expected a multiple of the mesh's batch axes data x fsdp ({shards}), got {batch}")
    info = dataset_info(d.path)
    if info["kind"] != "clips":
        raise ValueError(f"data.path: expected a clip dataset to encode, got {d.path} holding {info['kind']}")
    splits = list(info["splits"]) if splits is None else list(splits)
    for split in splits:
        if split not in info["splits"]:
            raise ValueError(f"splits: expected splits of {d.path} ({sorted(info['splits'])}), got {split!r}")
    codec = LatentCodec.from_config(config.latents)
    metadata = {
        METADATA_KEY: {
            "source_path": str(Path(info["path"]).resolve()),
            "latents": {k: getattr(config.latents, k) for k in _CODEC_FIELDS},
            "data": {k: getattr(d, k) for k in _DATA_FIELDS},
            "every": every,
            "latent_channels": codec.channels,
            "latent_frames": codec.latent_frames(d.frames),
        }
    }
    sources = {s: open_source(d.path, s) for s in splits}
    for src in sources.values():  # every process sees the same counts: all stop here together
        if src.frame_counts is not None and _window_count(src, d, every, range(len(src))) == 0:
            raise _too_short(src, d, int(src.frame_counts.max(initial=0)))
    # this process's clips: a contiguous range of each split, so its windows are a contiguous run
    mine = {s: np.array_split(np.arange(len(src)), processes.count)[processes.index] for s, src in sources.items()}
    counts = [_window_count(src, d, every, mine[s]) for s, src in sources.items()]
    total = None if None in counts else sum(counts)
    video_shape = (d.views, d.frames, d.height, d.width, 3)
    # a plain line (stderr not a terminal) at every twentieth of the windows, or every 1000
    lines = max(1, total // 20) if total else 1000
    with Progress(total, unit="window", desc="encode", enabled=progress, every=lines) as bar:
        path = write_dataset(
            out,
            {
                s: _encoded(
                    _windows(src, d, every, mine[s]), codec, batch // processes.count, mesh, processes, video_shape, bar
                )
                for s, src in sources.items()
            },
            name="jaxdrive_latents",
            kind="windows",
            metadata=metadata,
            overwrite=overwrite,
            description=f"jaxdrive latent windows of {d.path} (jaxdrive data encode).",
            processes=processes,
        )
    log.info("encoded %s -> %s", d.path, path)
    return path


def check_dataset(config, codec: LatentCodec) -> None:
    """``ValueError`` unless ``data.path`` holds what ``latents.precomputed`` says (latent windows
    or clips) and, for windows, was encoded as the config says: latents source (and factor and
    scale for space_to_depth, vae_mode for a VAE, which ignores the other two), latent channels,
    data height, width, frames, views and stride."""
    from jaxdrive.data.tfds_io import dataset_info

    d, lat = config.data, config.latents
    if not lat.precomputed and not Path(d.path).exists():
        return  # the pipeline names a missing clip dataset when it opens it
    info = dataset_info(d.path)
    if lat.precomputed and info["kind"] != "windows":
        raise ValueError(
            f"data.path: expected latent windows written by 'jaxdrive data encode' (latents.precomputed "
            f"is true), got {d.path} holding {info['kind']}: encode it, or set latents.precomputed=false"
        )
    if not lat.precomputed:
        if info["kind"] == "windows":
            raise ValueError(
                f"latents.precomputed: expected true for {d.path} (latent windows written by "
                f"'jaxdrive data encode'), got false"
            )
        return
    meta = info["metadata"].get(METADATA_KEY)
    if not isinstance(meta, dict):
        raise ValueError(
            f"data.path: expected the metadata of 'jaxdrive data encode' ({METADATA_KEY!r}) in "
            f"{d.path}, got {sorted(info['metadata'])}"
        )
    codec_fields = ("source",) + (("factor", "scale") if lat.source == "space_to_depth" else ("vae_mode",))
    pairs = [(f"latents.{k}", meta["latents"].get(k), getattr(lat, k)) for k in codec_fields]
    pairs += [(f"data.{k}", meta["data"].get(k), getattr(d, k)) for k in _DATA_FIELDS]
    pairs.append(("latent channels", meta.get("latent_channels"), codec.channels))
    for name, stored, value in pairs:
        if stored != value:
            raise ValueError(
                f"{name}: expected {stored!r} (what the latent windows at {d.path} were encoded with), got {value!r}"
            )
