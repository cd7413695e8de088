"""Checks of the DiT's inputs and example inputs for initialisation, parameter counts and tests.

Every check raises ``ValueError`` naming the argument, the expected and the actual value, before
anything is traced. Value ranges (sigma in [0, 1]) are checked when the values are concrete.
"""

from __future__ import annotations

from collections.abc import Mapping

import jax.numpy as jnp
import numpy as np

from jaxdrive.models.dit_config import CONDITIONS, DiTConfig
from jaxdrive.models.dit_controls import frame_mode
from jaxdrive.parallel.mesh import mesh_axis_size
from jaxdrive.validate import check_range, check_shape

# Inputs that belong to a control; given while the control is off they are an error.
CONTROL_OF = {"fps": "fps", "intrinsics": "camera", "cam_to_ego": "camera", "waypoints": "waypoints",
              "ego_to_world": "trajectory", "boxes": "boxes", "box_classes": "boxes",
              "box_valid": "boxes", "bev_map": "map", "warp": "warp"}
# Inputs with a (pixel or latent) frame axis at 1; the others are per clip or per view.
PER_FRAME_INPUTS = ("waypoints", "ego_to_world", "boxes", "box_classes", "box_valid", "bev_map")


def _shape(x):
    return list(np.shape(x))


def _check_bool(name, x):
    if x is not None and jnp.result_type(x) != jnp.bool_:
        raise ValueError(f"{name}: expected dtype bool, got {jnp.result_type(x)}")


def check_inputs(cfg: DiTConfig, latents, sigma, text, kw: Mapping) -> None:
    """Validate the arguments of :meth:`jaxdrive.models.dit.DiT.__call__` against ``cfg``."""
    c = cfg.controls
    if np.ndim(latents) != 6:
        raise ValueError(f"latents: expected shape [B, V, F', h, w, C], got {_shape(latents)}")
    b, nv, nf, h, w, ch = np.shape(latents)
    pt, ph, pw = cfg.patch
    if ch != cfg.in_channels:
        raise ValueError(f"latents: expected {cfg.in_channels} channels (in_channels), got shape "
                         f"{_shape(latents)}")
    if h % ph or w % pw or nf % pt:
        raise ValueError(f"latents: expected F', h, w divisible by the patch {cfg.patch}, got shape "
                         f"{_shape(latents)}")
    if np.ndim(sigma) == 1:
        check_shape("sigma", sigma, [b])
    elif np.ndim(sigma) == 2:
        if tuple(np.shape(sigma)) != (b, nf):
            raise ValueError(f"sigma: expected shape [B] = [{b}] or [B, F'] = [{b}, {nf}], got "
                             f"{_shape(sigma)}")
    else:
        raise ValueError(f"sigma: expected shape [B] = [{b}] or [B, F'] = [{b}, {nf}], got {_shape(sigma)}")
    check_range("sigma", sigma, 0.0, 1.0)
    tensor = mesh_axis_size("tensor")
    if cfg.heads % tensor:
        raise ValueError(f"heads: expected a multiple of the mesh axis 'tensor' (size {tensor}), "
                         f"got {cfg.heads}")
    _check_text(cfg, b, text, kw.get("text_mask"))
    for name, control in CONTROL_OF.items():
        if control == "camera" and c.boxes and c.box_per_view:
            continue                                     # per-view boxes use the cameras too
        if kw.get(name) is not None and not getattr(c, control):
            raise ValueError(f"{name}: this DiT takes no {control} (controls.{control} is False), "
                             f"got an array of shape {_shape(kw[name])}")
    if kw.get("fps") is not None:
        check_shape("fps", kw["fps"], [b])
    cams = [kw.get("intrinsics"), kw.get("cam_to_ego")]
    if (cams[0] is None) != (cams[1] is None):
        raise ValueError("intrinsics, cam_to_ego: expected both or neither, got only "
                         f"{'intrinsics' if cams[1] is None else 'cam_to_ego'}")
    if cams[0] is not None:
        check_shape("intrinsics", cams[0], [b, nv, 3, 3])
        check_shape("cam_to_ego", cams[1], [b, nv, 4, 4])
    r = cfg.vae_temporal
    if kw.get("waypoints") is not None:
        check_shape("waypoints", kw["waypoints"], [b, None, 2])
        frame_mode("waypoints", np.shape(kw["waypoints"])[1], nf, r)
    if kw.get("ego_to_world") is not None:
        check_shape("ego_to_world", kw["ego_to_world"], [b, None, 4, 4])
        frame_mode("ego_to_world", np.shape(kw["ego_to_world"])[1], nf, r)
    _check_boxes(cfg, b, nf, cams[0], kw)
    if kw.get("bev_map") is not None:
        check_shape("bev_map", kw["bev_map"], [b, None, None, None, c.map_channels])
        frame_mode("bev_map", np.shape(kw["bev_map"])[1], nf, r)
    for name in ("cond_latents", "cond_mask"):
        if kw.get(name) is not None and c.cond_frames is None:
            raise ValueError(f"{name}: this DiT takes no condition frames (controls.cond_frames is None)")
    if (kw.get("cond_latents") is None) != (kw.get("cond_mask") is None):
        raise ValueError("cond_latents, cond_mask: expected both or neither")
    if kw.get("cond_latents") is not None:
        check_shape("cond_latents", kw["cond_latents"], list(np.shape(latents)))
        check_shape("cond_mask", kw["cond_mask"], [b, nf])
        _check_bool("cond_mask", kw["cond_mask"])
    if kw.get("warp") is not None:
        check_shape("warp", kw["warp"], list(np.shape(latents)))
    _check_features(cfg, b, latents, kw.get("features"), kw.get("features_mask"))
    drop = kw.get("drop") or {}
    for name, value in drop.items():
        if name not in CONDITIONS:
            raise ValueError(f"drop: expected condition names from {list(CONDITIONS)}, got {name!r}")
        check_shape(f"drop[{name!r}]", value, [b])
        _check_bool(f"drop[{name!r}]", value)
    if kw.get("ofs") is not None:
        if cfg.ofs_embed_dim is None:
            raise ValueError("ofs: this DiT has no ofs embedding (ofs_embed_dim is None)")
        check_shape("ofs", kw["ofs"], [b])


def _check_text(cfg, b, text, text_mask):
    kind = cfg.controls.text
    if kind is None:
        if text is not None or text_mask is not None:
            raise ValueError(f"text: this DiT takes no text (controls.text is None), got shape {_shape(text)}")
        return
    if text is None:
        if not cfg.controls.text_null:
            raise ValueError("text: required, this DiT has no learned null text (controls.text_null is False)")
        if text_mask is not None:
            raise ValueError("text_mask: given without text")
        return
    if kind == "embeddings":
        check_shape("text", text, [b, None, cfg.text_dim])
    else:
        check_shape("text", text, [b, None])
        if not jnp.issubdtype(jnp.result_type(text), jnp.integer):
            raise ValueError(f"text: the caption encoder takes integer token ids, got {jnp.result_type(text)}")
    if np.shape(text)[1] > cfg.text_len:
        raise ValueError(f"text: expected at most text_len = {cfg.text_len} tokens, got {np.shape(text)[1]}")
    if text_mask is not None:
        check_shape("text_mask", text_mask, list(np.shape(text))[:2])
        _check_bool("text_mask", text_mask)


def _check_boxes(cfg, b, nf, intrinsics, kw):
    names = ("boxes", "box_classes", "box_valid")
    given = [kw.get(n) is not None for n in names]
    if any(given) and not all(given):
        raise ValueError(f"boxes, box_classes, box_valid: expected all three or none, got "
                         f"{[n for n, g in zip(names, given) if g]}")
    if not all(given):
        return
    check_shape("boxes", kw["boxes"], [b, None, None, 7])
    fb, n = np.shape(kw["boxes"])[1:3]
    frame_mode("boxes", fb, nf, cfg.vae_temporal)
    check_shape("box_classes", kw["box_classes"], [b, fb, n])
    check_shape("box_valid", kw["box_valid"], [b, fb, n])
    _check_bool("box_valid", kw["box_valid"])
    if cfg.controls.box_per_view and intrinsics is None:
        raise ValueError("intrinsics: per-view boxes (controls.box_per_view) need intrinsics and "
                         "cam_to_ego, got none")


def _check_features(cfg, b, latents, features, mask):
    if features is None:
        if mask is not None:
            raise ValueError("features_mask: given without features")
        return
    if not cfg.htft_layers:
        raise ValueError("features: this DiT fuses no features (htft_layers is empty)")
    if set(features) != set(cfg.htft_layers):
        raise ValueError(f"features: expected a mapping with the layers {sorted(cfg.htft_layers)}, "
                         f"got {sorted(features)}")
    _, nv, _, h, w, _ = np.shape(latents)
    pt, ph, pw = cfg.patch
    k = None
    for layer, f in features.items():
        check_shape(f"features[{layer}]", f, [b, None, (h // ph) * (w // pw), nv, cfg.width])
        k = np.shape(f)[1] if k is None else k
        check_shape(f"features[{layer}]", f, [b, k, (h // ph) * (w // pw), nv, cfg.width])
    if mask is not None:
        check_shape("features_mask", mask, [b, k])
        _check_bool("features_mask", mask)


def example_inputs(cfg: DiTConfig, *, batch: int = 1, views: int = 1, frames: int = 1, height: int | None = None,
                   width: int | None = None, text_len: int = 4, boxes: int = 2, pixel_frames: bool = True,
                   past: int = 1, map_hw: tuple[int, int] = (16, 16), seed: int = 0) -> dict:
    """Keyword arguments for ``DiT.init`` / ``DiT.__call__`` with every input ``cfg`` takes:
    latents ``[batch, views, frames, height, width, C]`` (height/width default to one patch grid
    of 2 x 2 tokens), sigma ``[batch, frames]``, and each enabled control (per-frame controls per
    pixel frame when ``pixel_frames``). Random values, deterministic in ``seed``."""
    rng = np.random.default_rng(seed)
    pt, ph, pw = cfg.patch
    frames = max(frames, pt)
    height = 2 * ph if height is None else height
    width = 2 * pw if width is None else width
    c = cfg.controls
    f32 = lambda *s: rng.standard_normal(s).astype(np.float32)
    out = {"latents": f32(batch, views, frames, height, width, cfg.in_channels),
           "sigma": rng.uniform(0, 1, (batch, frames)).astype(np.float32)}
    fc = 1 + cfg.vae_temporal * (frames - 1) if pixel_frames else frames
    if c.text == "embeddings":
        out["text"] = f32(batch, text_len, cfg.text_dim)
        out["text_mask"] = np.ones((batch, text_len), bool)
    elif c.text == "caption":
        out["text"] = rng.integers(1, c.caption_vocab, (batch, text_len)).astype(np.int32)
        out["text_mask"] = np.ones((batch, text_len), bool)
    if c.fps:
        out["fps"] = rng.uniform(2, 12, (batch,)).astype(np.float32)
    if c.camera or (c.boxes and c.box_per_view):
        out.update(example_cameras(batch, views, height * cfg.vae_spatial, width * cfg.vae_spatial))
    if c.waypoints:
        out["waypoints"] = np.cumsum(np.abs(f32(batch, fc, 2)), axis=1)
    if c.trajectory:
        poses = np.tile(np.eye(4, dtype=np.float32), (batch, fc, 1, 1))
        poses[:, :, 0, 3] = np.arange(fc) * 0.5
        out["ego_to_world"] = poses
    if c.boxes:
        b = np.zeros((batch, fc, boxes, 7), np.float32)
        b[..., 0] = rng.uniform(-20, 20, (batch, fc, boxes))
        b[..., 1] = rng.uniform(-20, 20, (batch, fc, boxes))
        b[..., 3:6] = (4.0, 2.0, 1.6)
        b[..., 6] = rng.uniform(-3, 3, (batch, fc, boxes))
        out["boxes"] = b
        out["box_classes"] = rng.integers(0, c.num_classes, (batch, fc, boxes)).astype(np.int32)
        out["box_valid"] = rng.uniform(0, 1, (batch, fc, boxes)) < 0.8
    if c.map:
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
    return out


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
    return {"intrinsics": np.tile(k, (batch, views, 1, 1)),
            "cam_to_ego": np.tile(np.stack(mats), (batch, 1, 1, 1)).astype(np.float32)}
