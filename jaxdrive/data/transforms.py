"""Per-clip transforms of the input pipeline (:mod:`jaxdrive.data.pipeline`): a stored clip to one
training sample (:func:`sample_clip`: frames, views, resize and crop with their labels), a stored
latent window taken whole (:func:`take_window`), LongDWM's warped frames of a sample
(:func:`clip_warp`), and samples to a batch (:func:`collate`). The pipeline's module docstring
gives the batch layout they produce."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import numpy as np

from jaxdrive.data import schema
from jaxdrive.data.buckets import frame_offsets
from jaxdrive.data.resize import adjust_intrinsics, resize_crop_labels, resize_crop_video, resize_plan
from jaxdrive.validate import check_positive_int

log = logging.getLogger(__name__)


def _view_indices(views, num_views: int, where: str) -> np.ndarray:
    if views is None:
        return np.arange(num_views)
    idx = [schema.CAMERAS.index(v) if isinstance(v, str) and v in schema.CAMERAS else v for v in views]
    if any(isinstance(i, str) for i in idx) or any(not 0 <= int(i) < num_views for i in idx):
        raise ValueError(
            f"views: expected indices in [0, {num_views}) or names in {list(schema.CAMERAS)} "
            f"for {where} with {num_views} views, got {list(views)}"
        )
    return np.asarray(idx, np.int64)


def sample_clip(
    clip: Mapping,
    *,
    size: tuple[int, int],
    frames: int,
    stride: int = 1,
    start: int = 0,
    views=None,
    crop: str = "center",
    rng: np.random.Generator | None = None,
    where: str = "clip",
    head: int = 0,
    tail_stride: int | None = None,
    instances: bool = False,
) -> dict:
    """One training sample from a clip: ``frames`` frames from ``start`` every ``stride``, a view
    subset, resized and cropped to ``size`` with intrinsics to match, waypoints re-expressed in
    the ego frame of the first sampled frame.

    Mixed rates (:func:`frame_offsets`): frames ``0 .. head - 1`` every ``stride``, then every
    ``tail_stride`` (``head = 0``: ``tail_stride`` throughout; None: ``stride``). ``frame_times``
    ``[F]`` are seconds from the first sampled frame (source index / clip fps); ``fps`` is the
    clip fps over the stride of the generated part (``tail_stride`` when ``head < frames``).
    ``instances``: also ``instance_ids [V, F, H, W]`` (the synthetic world's per-pixel track ids,
    resized by :func:`resize_crop_labels`); a clip without them is refused."""
    stride = check_positive_int("stride", stride)
    head = check_positive_int("head", head, minimum=0)
    tail = stride if tail_stride is None else check_positive_int("tail_stride", tail_stride)
    T = int(np.shape(clip["ego_to_world"])[0])
    offsets = frame_offsets(frames, stride, head, tail)
    need = int(offsets[-1]) + 1
    if start < 0 or start + need > T:
        rate = f"stride {stride}" if tail == stride else f"stride {stride} ({head} frames) then {tail}"
        raise ValueError(
            f"{where}: {frames} frames at {rate} from frame {start} need "
            f"{need} source frames, but the clip has {T}: the clip length or frame stride "
            f"is too long for this scene"
        )
    t = start + offsets
    v = _view_indices(views, int(np.shape(clip["video"])[0]), where)
    video = np.asarray(clip["video"])[v[:, None], t[None, :]]
    plan = resize_plan(video.shape[-3:-1], size, crop=crop, rng=rng)
    e2w = np.asarray(clip["ego_to_world"], np.float64)[t]
    rel = np.linalg.inv(e2w[0]) @ e2w
    rel[0] = np.eye(4)  # exactly (0, 0) at the first frame, as the schema states
    out = {
        "video": resize_crop_video(video, plan),
        "intrinsics": adjust_intrinsics(np.asarray(clip["intrinsics"])[v], plan),
        "cam_to_ego": np.asarray(clip["cam_to_ego"], np.float32)[v],
        "ego_to_world": e2w.astype(np.float32),
        "waypoints": rel[:, :2, 3].astype(np.float32),
        "fps": np.float32(float(clip["fps"]) / (tail if head < frames else stride)),
        "frame_times": (offsets / float(clip["fps"])).astype(np.float32),
    }
    for name in ("boxes", "box_classes", "box_ids", "box_valid", "bev_map"):
        out[name] = np.asarray(clip[name])[t]
    if instances:
        if "instance_ids" not in clip:
            raise ValueError(
                f"{where}: expected per-pixel instance_ids (synthetic clips have them; nuScenes clips "
                f"do not), got a clip without them"
            )
        out["instance_ids"] = resize_crop_labels(np.asarray(clip["instance_ids"])[v[:, None], t[None, :]], plan)
    for name, value in clip.items():
        if isinstance(value, str):
            out[name] = value
    return out


def take_window(record: Mapping, *, frames: int, views=None, where: str = "window") -> dict:
    """One training sample from a stored latent window (:data:`schema.WINDOW_FIELDS`): a view
    subset of the whole window, shaped and typed as :func:`sample_clip`'s output with
    ``latents`` for ``video``."""
    have = int(np.shape(record["ego_to_world"])[0])
    if have != frames:
        raise ValueError(
            f"{where}: expected a latent window of {frames} frames (the bucket's), got {have}: "
            f"encode the dataset with the frame count you train with"
        )
    v = _view_indices(views, int(np.shape(record["latents"])[0]), where)
    out = {}
    for name, (_, spec) in schema.WINDOW_FIELDS.items():
        value = np.asarray(record[name])
        out[name] = value[v] if spec[0] == "V" else value
    out["fps"] = np.float32(record["fps"])  # stored as float64 by TFDS; sample_clip's dtype
    out["frame_times"] = (np.arange(frames) / float(record["fps"])).astype(np.float32)  # uniform frames
    for name, value in record.items():
        if isinstance(value, str):
            out[name] = value
    return out


def pad_boxes(s: dict, n: int, where: str) -> None:
    """Pad (invalid slots) or cut the box axis to ``n``, keeping valid boxes first; log cuts."""
    valid = s["box_valid"]
    have = valid.shape[1]
    if have > n:
        order = np.argsort(~valid, axis=1, kind="stable")[:, :n]
        lost = int(valid.sum() - np.take_along_axis(valid, order, 1).sum())
        if lost:
            log.warning("%s: dropped %d valid boxes beyond max_boxes=%d", where, lost, n)
        for k in ("boxes", "box_classes", "box_ids", "box_valid"):
            idx = order[..., None] if s[k].ndim == 3 else order
            s[k] = np.take_along_axis(s[k], idx, 1)
    elif have < n:
        for k in ("boxes", "box_classes", "box_ids", "box_valid"):
            pad = [(0, 0)] * s[k].ndim
            pad[1] = (0, n - have)
            s[k] = np.pad(s[k], pad, constant_values=-1 if k in ("box_classes", "box_ids") else 0)


def collate(samples: Sequence[dict], *, max_boxes: int | None = None) -> dict:
    """Stack samples of one bucket into a batch (box slots padded to a common N)."""
    n = max_boxes or max(s["box_valid"].shape[1] for s in samples)
    for i, s in enumerate(samples):
        pad_boxes(s, n, f"sample {i} (index {s.get('index')})")
    batch = {}
    for k, v in samples[0].items():
        if isinstance(v, str):
            batch[k] = [s[k] for s in samples]
        elif isinstance(v, dict):
            batch[k] = {n: np.array([s[k][n] for s in samples]) for n in v}
        else:
            shapes = {np.shape(s[k]) for s in samples}
            if len(shapes) > 1:
                raise ValueError(
                    f"batch field {k!r}: expected one shape within a bucket, got {sorted(shapes)} "
                    f"(indices {[s.get('index') for s in samples]})"
                )
            batch[k] = np.stack([s[k] for s in samples])
    return batch


def clip_warp(sample: Mapping, depth: float, frame: int = 0) -> np.ndarray:
    """LongDWM's warped frames of a training sample (sec. 3.4: from the clip's own future poses, so
    the model learns to correct the warp's distortions): its frame ``frame`` (LongDWM: the first;
    the world recipe: the last given one) of every view warped along the sample's ego poses
    relative to that frame's, at one ``depth``, holes inpainted on the host
    (:func:`jaxdrive.warp.warp_views`): ``[V, F, H, W, 3]`` in [-1, 1] like ``video``."""
    from jaxdrive.warp import warp_views

    e2w = np.asarray(sample["ego_to_world"], np.float64)
    poses = np.linalg.inv(e2w[frame]) @ e2w
    return warp_views(
        np.asarray(sample["video"])[:, frame],
        np.asarray(sample["intrinsics"]),
        np.asarray(sample["cam_to_ego"]),
        poses.astype(np.float32),
        depth,
    )
