"""Sample videos of a model: condition frames and controls from dataset clips, the jitted sampler,
and the outputs (an mp4 with the views tiled, a frame-grid PNG, the latents as ``.npy``).

    g = generate(Sampling(model, codec, mesh, data, flow), params, frames=33, guidance=2.0)

Used by the training loop (periodic samples) and by ``jaxdrive sample``; a training run gives its
:class:`Sampling` by :meth:`jaxdrive.train.run.Run.sampling`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive import flow
from jaxdrive.config import DataConfig, FlowConfig, StreamConfig
from jaxdrive.generate.guidance import check_controls, check_scale, describe
from jaxdrive.generate.rollout import rollout, to_numpy_video
from jaxdrive.models.dit.config import DiTConfig
from jaxdrive.models.dit.model import DiT
from jaxdrive.models.latents import LatentCodec
from jaxdrive.parallel.mesh import batch_axes
from jaxdrive.validate import check_positive_int

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Sampling:
    """What sampling a model needs besides its parameters: the DiT's config, the latent codec, the
    mesh, the dataset the condition clips come from (``data``), the flow settings it was trained with
    (TPD, shift, condition frames), T5 embeddings for ``text="embeddings"`` models, the window
    (latent frames per sampler call; default: the latent frames of ``data.frames``) and the
    source-frame stride between its frames (default ``data.stride``); ``precomputed``: ``data.path``
    holds latent windows (``jaxdrive data encode``); ``stream``: STAGE's streaming settings of a
    model trained frame by frame; ``guidance``: the classifier-free guidance scale it samples with
    unless told otherwise (the run's ``sample.cfg``); ``warp_start``: the level a warp-guided
    model's generated frames start from, noised from their warp (the run's ``sample.warp_start``)."""

    model: DiTConfig
    codec: LatentCodec
    mesh: Mesh
    data: DataConfig
    flow: FlowConfig = FlowConfig()
    text_embeddings: object = None
    window: int | None = None
    stride: int | None = None
    precomputed: bool = False
    steps: int = 20
    stream: StreamConfig = StreamConfig()
    guidance: float = 1.0
    warp_start: float = 1.0

    @property
    def latent_window(self) -> int:
        return self.codec.latent_frames(self.data.frames) if self.window is None else self.window

    @property
    def frame_stride(self) -> int:
        return self.data.stride if self.stride is None else self.stride


def dataset_inputs(
    spec: Sampling,
    *,
    frames: int,
    views=None,
    clips: int = 1,
    split: str | None = None,
    seed: int = 0,
    controls=None,
    scene: bool = False,
    masks: bool = False,
    shuffle_boxes: bool = False,
    indices=None,
    poses: bool = False,
    records=None,
):
    """Model inputs of ``clips`` dataset clips of ``frames`` pixel frames (no condition dropped):
    the first frames give the condition latents, every frame its controls. A precomputed dataset
    (``latents.precomputed``) gives its stored windows: ``frames`` at most the window's frame count
    (a prefix of a window; its latents are cut to ``codec.latent_frames(frames)``: exact for
    frame-wise codecs, for the causal VAE the window's encoding, which may differ slightly from
    encoding the prefix alone where the VAE normalises over a chunk of frames).

    ``controls(sample, clip, where) -> sample`` (:func:`jaxdrive.generate.future.future_controls`)
    gives each sample its controls for all ``frames``; the clip then needs to hold only as many
    frames as it has, and ``video`` holds those. ``scene``: keep the first clip's map, poses and
    boxes under ``inputs["scene"]`` (the frame grid's BEV panel). ``masks``: also the recorded
    frames' exact class ids ``inputs["class_masks"] [B, V, F, H, W]`` (synthetic clips:
    :func:`jaxdrive.data.class_masks.class_masks`). ``shuffle_boxes`` (the controllability control
    of ``jaxdrive eval``): clip ``i`` is conditioned on the boxes of clip ``i + 1`` (cyclically),
    and ``inputs["box_class_masks"]`` are the class masks of the boxes each clip got. ``indices``:
    the split's clips to take (default ``0 .. clips - 1``). ``poses``: also ``inputs["poses"]``,
    the samples' ``ego_to_world [B, F, 4, 4]``, ``intrinsics [B, V, 3, 3]`` (of the sampled frame
    size) and ``cam_to_ego [B, V, 4, 4]`` (the warp baseline of ``jaxdrive eval --routes``).
    ``records``: clip records (as the dataset stores them) to take the clips from instead of a
    split of ``data.path``."""
    from jaxdrive.data.batches import model_inputs
    from jaxdrive.data.pipeline import CONDITIONS
    from jaxdrive.data.tfds_io import open_source
    from jaxdrive.data.transforms import collate, sample_clip

    d = spec.data
    source = None if records is None else _Records(records)
    for name in [] if records is not None else [split] if split else ["validation", d.split]:
        try:
            source = open_source(d.path, name)
            break
        except ValueError:
            if split or name == d.split:  # the last one tried: say why it failed
                raise
    views = list(range(d.views)) if views is None else views
    rng = np.random.default_rng(seed)
    samples = []
    if controls is not None and spec.precomputed:
        raise ValueError(
            "controls: predicted or routed controls need clips, not the precomputed latent windows "
            "of latents.precomputed"
        )
    if (masks or shuffle_boxes) and spec.precomputed:
        raise ValueError(
            "masks: class masks need clips with their instance ids, not the precomputed latent windows "
            "of latents.precomputed"
        )
    for i in range(clips) if indices is None else indices:
        clip = source[i % len(source)]
        where = f"{source.split} clip {i}"
        if spec.precomputed:
            samples.append(_window_prefix(spec, clip, frames, views, f"{source.split} window {i}"))
            continue
        have = int(np.shape(clip["ego_to_world"])[0])
        stride = spec.frame_stride
        recorded = 1 + (have - 1) // stride
        if frames > recorded and controls is None:
            raise ValueError(
                f"frames: expected at most {recorded} frames (the dataset's clips have "
                f"{have} at stride {stride}), got {frames}"
            )
        sample = sample_clip(
            clip,
            size=(d.height, d.width),
            frames=min(frames, recorded),
            stride=stride,
            views=views,
            rng=rng,
            where=where,
            instances=masks or shuffle_boxes,
        )
        samples.append(sample if controls is None else controls(sample, clip, where))
    extra = {}
    if masks or shuffle_boxes:
        from jaxdrive.data.class_masks import class_masks_of

        own = [class_masks_of(s) for s in samples]
        for s in samples:
            del s["instance_ids"]  # not a model input
        extra["class_masks"] = np.stack(own)
        if shuffle_boxes:
            if len(samples) < 2 or len(source) < 2:
                raise ValueError(
                    f"shuffle_boxes: expected at least 2 clips from a split of at least 2 clips to "
                    f"shuffle boxes between, got {len(samples)} from a split of {len(source)}"
                )
            fields = ("boxes", "box_classes", "box_ids", "box_valid")
            given = [{k: s[k] for k in fields} for s in samples]
            for i, s in enumerate(samples):
                s.update(given[(i + 1) % len(samples)])
            extra["box_class_masks"] = np.roll(extra["class_masks"], -1, axis=0)
    batch = collate(samples)
    if poses:
        extra["poses"] = {k: np.asarray(batch[k], np.float32) for k in ("ego_to_world", "intrinsics", "cam_to_ego")}
    kept = None
    if scene:
        kept = {k: np.asarray(batch[k][0]) for k in ("bev_map", "ego_to_world", "boxes", "box_valid")}
        kept["predicted_from"] = int(samples[0].get("predicted_from", frames))
    batch.pop("predicted_from", None)
    batch["drop"] = {n: np.zeros((len(samples),), bool) for n in CONDITIONS}  # nothing dropped; CFG adds the nulls
    inputs = model_inputs(batch, spec.model, spec.text_embeddings)
    if kept is not None:
        inputs["scene"] = kept
    inputs.update(extra)
    return inputs


class _Records:
    """Clip records given by the caller, read as a split (:func:`dataset_inputs`)."""

    split = "given"

    def __init__(self, records):
        self.records = list(records)
        if not self.records:
            raise ValueError("records: expected at least one clip record, got none")

    def __len__(self):
        return len(self.records)

    def __getitem__(self, i):
        return self.records[i]


def _window_prefix(spec: Sampling, record, frames: int, views, where: str) -> dict:
    """The first ``frames`` frames of a stored latent window as a sample (its latents cut to
    ``codec.latent_frames(frames)``), at the sampling stride: a distilled coarse model reads every
    ``(K - 1)``-th frame of the dense windows it was trained on (frame-wise latents)."""
    from jaxdrive.data.schema import WINDOW_FIELDS
    from jaxdrive.data.transforms import take_window

    codec = spec.codec
    step, rest = divmod(spec.frame_stride, spec.data.stride)
    if rest or (step > 1 and codec.temporal != 1):
        raise ValueError(
            f"stride: expected a multiple of the windows' stride {spec.data.stride} (and frame-wise "
            f"latents to skip frames), got {spec.frame_stride} with temporal compression "
            f"{codec.temporal}"
        )
    have, temporal = int(np.shape(record["ego_to_world"])[0]), codec.temporal
    recorded = 1 + (have - 1) // step
    if frames > recorded or (frames - 1) % temporal:
        form = f"1 + {temporal}k frames, " if temporal > 1 else ""
        raise ValueError(
            f"frames: expected {form}at most the {recorded} frames of the dataset's latent windows "
            f"(latents.precomputed fixes the length), got {frames}"
        )
    s = take_window(record, frames=have, views=views, where=where)
    picked = slice(0, step * (frames - 1) + 1, step)
    s.update(
        {k: s[k][picked] for k, (_, spec_) in WINDOW_FIELDS.items() if spec_[0] == "F"},
        latents=s["latents"][:, : codec.latent_frames(step * (frames - 1) + 1)][:, ::step],
        frame_times=s["frame_times"][picked],
        fps=np.float32(s["fps"] / step),
    )
    return s


@dataclasses.dataclass(frozen=True)
class Generated:
    """What :func:`generate` returns: ``video [clips, V, F, H, W, 3]`` in [-1, 1] and its
    ``latents``; ``recorded``, the dataset clips' own frames at the same positions (decoded stored
    latents for a precomputed dataset); ``cond_frames`` and ``window``: the given frames and the
    first sampler window's frames, in pixel frames; ``guidance``: the scales it sampled with
    (:func:`jaxdrive.generate.guidance.describe`)."""

    video: np.ndarray
    latents: np.ndarray
    recorded: np.ndarray
    cond_frames: int
    window: int
    guidance: dict = dataclasses.field(default_factory=dict)


def generate(
    spec: Sampling,
    params,
    *,
    frames: int | None = None,
    views=None,
    steps: int | None = None,
    guidance: float | None = None,
    control_guidance=None,
    cond_frames: int | None = None,
    overlap: int | None = None,
    clips: int | None = None,
    seed: int = 0,
    progress: bool = False,
) -> Generated:
    """Generate ``clips`` clips conditioned on dataset clips (see :class:`Generated`). ``guidance``
    None: the run's (``spec.guidance``); ``control_guidance``: control -> its own scale
    (:mod:`jaxdrive.generate.guidance`). ``frames``
    defaults to the training clip (``data.frames``; the window's frames for a model whose window is
    not the data clip, a distilled coarse model); ``clips`` to the size of the mesh's batch axes
    (``data x fsdp``), the least a batch-sharded sampler can run; ``progress``: a progress bar over
    the rollout's windows."""
    mesh, codec, window = spec.mesh, spec.codec, spec.latent_window
    sizes = dict(zip(mesh.axis_names, mesh.axis_sizes))
    shards = sizes.get("data", 1) * sizes.get("fsdp", 1)
    clips = shards if clips is None else check_positive_int("clips", clips)
    if clips % shards:
        raise ValueError(f"clips: expected a multiple of the mesh's data x fsdp size {shards}, got {clips}")
    if frames is None:
        frames = spec.data.frames if codec.latent_frames(spec.data.frames) == window else window
    frames = check_positive_int("frames", frames)
    steps = spec.steps if steps is None else check_positive_int("steps", steps)
    guidance = check_scale("guidance", spec.guidance if guidance is None else guidance)
    controls = check_controls(spec.model, spec.data.drop_prob, control_guidance or {})
    total = codec.latent_frames(frames)
    cond = max(1, spec.flow.cond_frames) if cond_frames is None else cond_frames
    overlap = max(1, cond) if overlap is None else overlap
    inputs = dataset_inputs(spec, frames=frames, views=views, clips=clips, seed=seed)
    d, f = spec.data, spec.flow
    shift = f.shift if f.shift > 0 else flow.resolution_shift(d.height, d.width, window)
    # the batch as the DiT shards it; every process holds the same clips
    batch_sharding = NamedSharding(mesh, P(batch_axes(mesh) or None))
    inputs = jax.tree_util.tree_map(lambda x: jax.device_put(np.asarray(x), batch_sharding), inputs)
    cond = min(cond, window - 1)
    with jax.set_mesh(mesh):
        latents = rollout(
            DiT(spec.model),
            codec,
            params,
            codec.params,
            inputs,
            total_frames=total,
            window=window,
            overlap=overlap,
            cond_frames=cond,
            steps=steps,
            guidance=guidance,
            control_guidance=controls,
            key=jax.random.key(seed),
            shift=shift,
            tpd=f.tpd,
            tpd_omega=f.tpd_omega,
            progress=progress,
            mesh=mesh,
        )
        video = to_numpy_video(codec, codec.params, latents)
        recorded = (
            np.asarray(inputs["video"])
            if "video" in inputs
            else to_numpy_video(codec, codec.params, inputs["latents"][:, :, :total])
        )
    pixel = lambda n: codec.pixel_frames(n) if n else 0
    return Generated(
        video,
        np.asarray(latents),
        recorded,
        pixel(cond),
        min(pixel(window), video.shape[2]),
        guidance=describe(guidance, controls),
    )


def write_samples(spec: Sampling, state_or_params, outdir, *, fps: float | None = None, **kwargs) -> dict:
    """Generate (``kwargs`` as :func:`generate`) and write under ``outdir``: ``sample.mp4``,
    ``frames.png`` (each row: the recorded frame left, the generated one right), ``latents.npy`` and ``quality.json``
    (PSNR / SSIM of the first clip against its recorded frames, beside the repeat-the-last-frame
    and noise baselines: :func:`jaxdrive.generate.quality.clip_quality`; and the ``guidance`` used).
    Returns the paths and the
    quality summary (``"quality"``), and logs what it wrote at INFO. EMA parameters are used when
    the state keeps them."""
    from jaxdrive.generate.quality import clip_quality
    from jaxdrive.media import write_frame_grid, write_mp4

    params = state_or_params
    if hasattr(state_or_params, "params"):
        params = state_or_params.ema if state_or_params.ema is not None else state_or_params.params
    g = generate(spec, params, **kwargs)
    video = g.video
    out = {}
    if jax.process_index() == 0:
        outdir = Path(outdir)
        outdir.mkdir(parents=True, exist_ok=True)
        rate = fps or 12.0
        out["video"] = write_mp4(outdir / "sample.mp4", video[0], fps=rate)
        out["grid"] = write_frame_grid(
            outdir / "frames.png", video[0], num_frames=min(6, video.shape[2]), reference=g.recorded[0]
        )
        np.save(outdir / "latents.npy", g.latents)
        out["latents"] = outdir / "latents.npy"
        if g.cond_frames:  # quality is measured against what the given frames continue
            q = {
                **clip_quality(video[0], g.recorded[0], cond_frames=g.cond_frames, window=g.window),
                "guidance": g.guidance,
            }
            out["quality"] = q
            out["quality_json"] = outdir / "quality.json"
            out["quality_json"].write_text(json.dumps(q, indent=1))
        logger.info("wrote %d frames x %d views: %s, %s", video.shape[2], video.shape[1], out["video"], out["grid"])
    return out
