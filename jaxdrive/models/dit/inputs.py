"""Example inputs of the DiT for initialisation, parameter counts, benchmarks and tests.

The checks of real inputs live with them: :meth:`jaxdrive.models.dit.conditions.Conditions.check`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.models.dit.config import DiTConfig


def example_inputs(
    cfg: DiTConfig,
    *,
    batch: int = 1,
    views: int = 1,
    frames: int = 1,
    height: int | None = None,
    width: int | None = None,
    text_len: int = 4,
    boxes: int = 2,
    pixel_frames: bool = True,
    past: int = 1,
    map_hw: tuple[int, int] = (16, 16),
    seed: int = 0,
) -> dict:
    """Keyword arguments for ``DiT.init`` / ``DiT.__call__`` with every input ``cfg`` takes:
    ``latents [batch, views, frames, height, width, C]`` (height/width default to one patch grid
    of 2 x 2 tokens), ``sigma [batch, frames]``, and ``cond``, a
    :class:`~jaxdrive.models.dit.conditions.Conditions` with each enabled control (per-frame controls
    per pixel frame when ``pixel_frames``). Random values, deterministic in ``seed``."""
    rng = np.random.default_rng(seed)
    pt, ph, pw = cfg.patch
    frames = max(frames, pt)
    height = 2 * ph if height is None else height
    width = 2 * pw if width is None else width
    c = cfg.controls

    def f32(*s: int) -> np.ndarray:
        return rng.standard_normal(s).astype(np.float32)

    out: dict[str, Any] = {
        "latents": f32(batch, views, frames, height, width, cfg.in_channels),
        "sigma": rng.uniform(0, 1, (batch, frames)).astype(np.float32),
    }
    fc = 1 + cfg.vae_temporal * (frames - 1) if pixel_frames else frames
    if c.text == "embeddings":
        out["text"] = f32(batch, text_len, cfg.text_dim)
        out["text_mask"] = np.ones((batch, text_len), bool)
    elif c.text == "caption":
        out["text"] = rng.integers(1, c.caption_vocab, (batch, text_len)).astype(np.int32)
        out["text_mask"] = np.ones((batch, text_len), bool)
    if c.fps:
        out["fps"] = rng.uniform(2, 12, (batch,)).astype(np.float32)
    if c.camera or (c.boxes and c.box_per_view) or c.layout:
        out.update(example_cameras(batch, views, height * cfg.vae_spatial, width * cfg.vae_spatial))
    if c.waypoints:
        out["waypoints"] = np.cumsum(np.abs(f32(batch, fc, 2)), axis=1)
    if c.frame_time:  # 12 fps, then 1 fps: a mixed-rate clip (MiLA [2503.15875v1] appendix B)
        steps = np.where(np.arange(fc) < min(fc, 4), 1 / 12, 1.0)
        out["frame_times"] = np.tile(np.cumsum(steps) - steps[0], (batch, 1)).astype(np.float32)
    if c.trajectory:
        poses = np.tile(np.eye(4, dtype=np.float32), (batch, fc, 1, 1))
        poses[:, :, 0, 3] = np.arange(fc) * 0.5
        out["ego_to_world"] = poses
    if c.boxes or c.layout:
        b = np.zeros((batch, fc, boxes, 7), np.float32)
        b[..., 0] = rng.uniform(-20, 20, (batch, fc, boxes))
        b[..., 1] = rng.uniform(-20, 20, (batch, fc, boxes))
        b[..., 3:6] = (4.0, 2.0, 1.6)
        b[..., 6] = rng.uniform(-3, 3, (batch, fc, boxes))
        out["boxes"] = b
        out["box_classes"] = rng.integers(0, c.num_classes, (batch, fc, boxes)).astype(np.int32)
        out["box_valid"] = rng.uniform(0, 1, (batch, fc, boxes)) < 0.8
    if c.map or c.layout:
        out["bev_map"] = (rng.uniform(0, 1, (batch, fc, *map_hw, c.map_channels)) < 0.3).astype(np.float32)
    if c.cond_frames:
        out["cond_latents"] = f32(batch, views, frames, height, width, cfg.in_channels)
        out["cond_mask"] = np.zeros((batch, frames), bool)
        out["cond_mask"][:, 0] = True
    if c.warp:
        out["warp"] = f32(batch, views, frames, height, width, cfg.in_channels)
    if cfg.htft_layers:
        s = (height // ph) * (width // pw)
        out["features"] = {i: f32(batch, past, s, views, cfg.width) for i in cfg.htft_layers}
        out["features_mask"] = np.ones((batch, past), bool)
    if cfg.ofs_embed_dim is not None:
        out["ofs"] = np.full((batch,), 2.0, np.float32)
    return {"latents": out.pop("latents"), "sigma": out.pop("sigma"), "cond": Conditions(**out)}


def example_cameras(batch: int, views: int, image_h: int, image_w: int) -> dict:
    """A ring of ``views`` cameras around the ego car (yaw 0, -60, ... degrees clockwise from the
    front, as the nuScenes view order), 70 degree horizontal field of view."""
    fx = image_w / 2 / np.tan(np.radians(35))
    k = np.array([[fx, 0, image_w / 2], [0, fx, image_h / 2], [0, 0, 1]], np.float32)
    mats = []
    for v in range(views):
        yaw = -2 * np.pi * v / max(views, 1)
        # camera axes in ego coordinates: x right, y down, z forward (rotated by yaw about ego z)
        fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        m = np.eye(4, dtype=np.float32)
        m[:3, :3] = np.stack([right, down, fwd], axis=1)
        m[:3, 3] = (1.0, 0.0, 1.5)
        mats.append(m)
    return {
        "intrinsics": np.tile(k, (batch, views, 1, 1)),
        "cam_to_ego": np.tile(np.stack(mats), (batch, 1, 1, 1)).astype(np.float32),
    }
