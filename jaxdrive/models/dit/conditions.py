"""The DiT's conditions: one typed pytree, built once from a batch, checked once, passed whole.

    cond = Conditions.from_batch(batch, dit_config, text=ids, text_mask=mask)
    out = dit.forward(params, latents, sigma, cond)

Every field is optional (None: not given) and each belongs to a control of
:class:`jaxdrive.models.dit.config.Controls` (:data:`CONTROL_OF`); a field given while its
control is off is an error. Per-frame fields (:data:`PER_FRAME`) are per latent frame ``F'`` or
per pixel frame ``1 + vae_temporal (F' - 1)``:

- ``text [B, L, text_dim]`` (or token ids ``[B, L]`` for the caption encoder) with
  ``text_mask [B, L]``; ``fps [B]``; ``ofs [B]`` (CogVideoX 1.5 I2V);
- ``intrinsics [B, V, 3, 3]`` + ``cam_to_ego [B, V, 4, 4]``; ``waypoints [B, F, 2]``;
  ``ego_to_world [B, F, 4, 4]`` (trajectory); ``frame_times [B, F]`` (seconds; only differences
  matter); ``boxes [B, F, N, 7]``, ``box_classes``,
  ``box_valid [B, F, N]``; ``bev_map [B, F, Hm, Wm, C_map]``;
- ``cond_latents`` (like the latents) + ``cond_mask [B, F']``: clean condition frames;
  ``warp`` (warped-frame latents, like the latents);
- ``features {layer: [B, K, S, V, D]}`` + ``features_mask [B, K]`` (STAGE's HTFT);
- ``drop {condition: [B] bool}``: classifier-free-guidance drops (names from
  :data:`jaxdrive.models.dit.config.CONDITIONS`).

A :func:`flax.struct.dataclass`, so it is a pytree: it goes through ``jax.jit``, ``lax.scan`` and
``tree_map`` (stacking micro-batches, sharding a batch) as a whole; ``cond.replace(...)`` changes
fields.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxdrive.models.dit.config import CONDITIONS, DiTConfig
from jaxdrive.models.dit.controls import frame_mode
from jaxdrive.parallel.mesh import mesh_axis_size
from jaxdrive.validate import check_range, check_shape

# Fields that belong to a control; given while the control is off they are an error.
CONTROL_OF = {
    "fps": "fps",
    "intrinsics": "camera",
    "cam_to_ego": "camera",
    "waypoints": "waypoints",
    "ego_to_world": "trajectory",
    "boxes": "boxes",
    "box_classes": "boxes",
    "box_valid": "boxes",
    "bev_map": "map",
    "warp": "warp",
    "frame_times": "frame_time",
}
# Fields the projected layout (controls.layout) reads besides those of its own controls.
LAYOUT_FIELDS = ("intrinsics", "cam_to_ego", "bev_map")
# Fields with a (pixel or latent) frame axis at 1; the others are per clip or per view.
PER_FRAME = ("waypoints", "ego_to_world", "boxes", "box_classes", "box_valid", "bev_map", "frame_times")
# The data pipeline's drop names (jaxdrive.data.pipeline.CONDITIONS) -> the DiT conditions they drop.
BATCH_DROPS = {
    "text": ("text",),
    "camera": ("camera",),
    "trajectory": ("trajectory", "waypoints", "warp"),
    "boxes": ("boxes",),
    "map": ("map",),
}


@struct.dataclass
class Conditions:
    """What the DiT is conditioned on besides the noisy latents and their levels (see the module
    docstring)."""

    text: Any = None
    text_mask: Any = None
    fps: Any = None
    intrinsics: Any = None
    cam_to_ego: Any = None
    waypoints: Any = None
    ego_to_world: Any = None
    boxes: Any = None
    box_classes: Any = None
    box_valid: Any = None
    bev_map: Any = None
    cond_latents: Any = None
    cond_mask: Any = None
    cond_sigma: Any = None
    warp: Any = None
    features: Any = None
    features_mask: Any = None
    drop: Any = None
    ofs: Any = None
    frame_times: Any = None

    @classmethod
    def from_batch(cls, batch: Mapping, cfg: DiTConfig, *, text=None, text_mask=None) -> Conditions:
        """The conditions ``cfg``'s controls read from a data-pipeline batch
        (:mod:`jaxdrive.data.pipeline`: NumPy arrays in the dataset's layouts), as float32 /
        bool arrays; ``text``/``text_mask`` come prepared (token ids or embeddings, see
        :func:`jaxdrive.data.batches.text_inputs`); the batch's ``drop`` (pipeline names) becomes
        the drops of the DiT conditions that are on (:data:`BATCH_DROPS`). The BEV map's uint8
        classes become [0, 1]."""
        on = set(cfg.controls.enabled())
        f32 = lambda k: np.asarray(batch[k], np.float32)
        kw = {}
        if "text" in on and text is not None:
            kw["text"], kw["text_mask"] = text, text_mask
        if "fps" in on:
            kw["fps"] = f32("fps")
        layout = cfg.controls.layout
        if "camera" in on or ("boxes" in on and cfg.controls.box_per_view) or layout:
            kw["intrinsics"], kw["cam_to_ego"] = f32("intrinsics"), f32("cam_to_ego")
        if "waypoints" in on:
            kw["waypoints"] = f32("waypoints")
        if "trajectory" in on:
            kw["ego_to_world"] = f32("ego_to_world")
        if "boxes" in on:
            kw.update({k: np.asarray(batch[k]) for k in ("boxes", "box_classes", "box_valid")})
        if "map" in on or layout:
            kw["bev_map"] = f32("bev_map")  # the schema's classes are 0 / 1 already
        if "frame_time" in on:
            kw["frame_times"] = f32("frame_times")
        kw["drop"] = {
            t: np.asarray(batch["drop"][name], bool)
            for name, targets in BATCH_DROPS.items()
            if name in batch.get("drop", {})
            for t in targets
            if t in on
        }
        return cls(**kw)

    def check(self, cfg: DiTConfig, latents, sigma) -> Conditions:
        """Validate against ``cfg`` and the latents ``[B, V, F', h, w, C]`` / levels ``[B]`` or
        ``[B, F']``; ``ValueError`` naming the field, the expected and the actual value, before
        anything is traced (value ranges only when concrete). Returns ``self``."""
        _check(cfg, latents, sigma, self)
        return self

    def per_frame(self, fn: Callable[[str, Any], Any]) -> Conditions:
        """A copy with every given per-frame field ``k`` replaced by ``fn(k, value)`` (windows,
        segments and coarse frames of a clip)."""
        # flax.struct.dataclass adds .replace at runtime; its stub does not declare it
        return self.replace(  # type: ignore[attr-defined]
            **{k: fn(k, getattr(self, k)) for k in PER_FRAME if getattr(self, k) is not None}
        )

    def with_drops(self, names, value: bool, batch: int) -> Conditions:
        """A copy whose ``drop`` sets each of ``names`` to ``value`` for all ``batch`` clips
        (classifier-free guidance: all kept, or all nulls)."""
        # flax.struct.dataclass adds .replace at runtime; its stub does not declare it
        return self.replace(drop={n: jnp.full((batch,), value, bool) for n in names})  # type: ignore[attr-defined]

    def given(self) -> dict:
        """The fields that are given, by name."""
        return {f.name: v for f in dataclasses.fields(self) if (v := getattr(self, f.name)) is not None}


# ------------------------------------------------------------------------------ checks
def _shape(x):
    return list(np.shape(x))


def _check_bool(name, x):
    if x is not None and jnp.result_type(x) != jnp.bool_:
        raise ValueError(f"{name}: expected dtype bool, got {jnp.result_type(x)}")


def _check(cfg: DiTConfig, latents, sigma, cond: Conditions) -> None:
    c = cfg.controls
    kw, text = cond.given(), cond.text
    if np.ndim(latents) != 6:
        raise ValueError(f"latents: expected shape [B, V, F', h, w, C], got {_shape(latents)}")
    b, nv, nf, h, w, ch = np.shape(latents)
    pt, ph, pw = cfg.patch
    if ch != cfg.in_channels:
        raise ValueError(f"latents: expected {cfg.in_channels} channels (in_channels), got shape {_shape(latents)}")
    if h % ph or w % pw or nf % pt:
        raise ValueError(f"latents: expected F', h, w divisible by the patch {cfg.patch}, got shape {_shape(latents)}")
    if np.ndim(sigma) == 1:
        check_shape("sigma", sigma, [b])
    elif np.ndim(sigma) == 2:
        if tuple(np.shape(sigma)) != (b, nf):
            raise ValueError(f"sigma: expected shape [B] = [{b}] or [B, F'] = [{b}, {nf}], got {_shape(sigma)}")
    else:
        raise ValueError(f"sigma: expected shape [B] = [{b}] or [B, F'] = [{b}, {nf}], got {_shape(sigma)}")
    check_range("sigma", sigma, 0.0, 1.0)
    tensor = mesh_axis_size("tensor")
    if cfg.heads % tensor:
        raise ValueError(f"heads: expected a multiple of the mesh axis 'tensor' (size {tensor}), got {cfg.heads}")
    _check_text(cfg, b, text, kw.get("text_mask"))
    on = c.enabled()
    for name, control in CONTROL_OF.items():
        if control == "camera" and c.boxes and c.box_per_view:
            continue  # per-view boxes use the cameras too
        if c.layout and name in LAYOUT_FIELDS:
            continue  # the layout draws the map with the cameras
        if kw.get(name) is not None and control not in on:
            raise ValueError(
                f"{name}: this DiT takes no {control} (controls.{control} is False), "
                f"got an array of shape {_shape(kw[name])}"
            )
    if kw.get("fps") is not None:
        check_shape("fps", kw["fps"], [b])
    cams = [kw.get("intrinsics"), kw.get("cam_to_ego")]
    if (cams[0] is None) != (cams[1] is None):
        raise ValueError(
            "intrinsics, cam_to_ego: expected both or neither, got only "
            f"{'intrinsics' if cams[1] is None else 'cam_to_ego'}"
        )
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
    if kw.get("frame_times") is not None:
        check_shape("frame_times", kw["frame_times"], [b, None])
        frame_mode("frame_times", np.shape(kw["frame_times"])[1], nf, r)
    _check_boxes(cfg, b, nf, cams[0], kw)
    if kw.get("bev_map") is not None:
        check_shape("bev_map", kw["bev_map"], [b, None, None, None, c.map_channels])
        frame_mode("bev_map", np.shape(kw["bev_map"])[1], nf, r)
        boxes = kw.get("boxes")
        fb, fm = (() if boxes is None else np.shape(boxes)[1:2]), np.shape(kw["bev_map"])[1]
        if c.layout and fb and fb[0] != fm:
            raise ValueError(
                f"bev_map: the layout (controls.layout) draws each frame's boxes and map together, "
                f"expected {fb[0]} frames as the boxes, got {fm}"
            )
    for name in ("cond_latents", "cond_mask"):
        if kw.get(name) is not None and c.cond_frames is None:
            raise ValueError(f"{name}: this DiT takes no condition frames (controls.cond_frames is None)")
    if (kw.get("cond_latents") is None) != (kw.get("cond_mask") is None):
        raise ValueError("cond_latents, cond_mask: expected both or neither")
    if kw.get("cond_latents") is not None:
        check_shape("cond_latents", kw["cond_latents"], list(np.shape(latents)))
        check_shape("cond_mask", kw["cond_mask"], [b, nf])
        _check_bool("cond_mask", kw["cond_mask"])
    if kw.get("cond_sigma") is not None:
        if kw.get("cond_latents") is None or c.cond_frames != "replace":
            raise ValueError(
                "cond_sigma: the given frames' noise level needs cond_latents and controls.cond_frames "
                f"'replace', got cond_latents={'set' if kw.get('cond_latents') is not None else None}, "
                f"cond_frames={c.cond_frames!r}"
            )
        check_shape("cond_sigma", kw["cond_sigma"], [b, nf])
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
        raise ValueError(
            f"boxes, box_classes, box_valid: expected all three or none, got {[n for n, g in zip(names, given) if g]}"
        )
    if not all(given):
        return
    check_shape("boxes", kw["boxes"], [b, None, None, 7])
    fb, n = np.shape(kw["boxes"])[1:3]
    frame_mode("boxes", fb, nf, cfg.vae_temporal)
    check_shape("box_classes", kw["box_classes"], [b, fb, n])
    check_shape("box_valid", kw["box_valid"], [b, fb, n])
    _check_bool("box_valid", kw["box_valid"])
    if cfg.controls.boxes and cfg.controls.box_per_view and intrinsics is None:
        raise ValueError("intrinsics: per-view boxes (controls.box_per_view) need intrinsics and cam_to_ego, got none")
    if cfg.controls.layout and intrinsics is None:
        raise ValueError(
            "intrinsics: the projected layout (controls.layout) draws the boxes with the cameras, "
            "expected intrinsics and cam_to_ego, got none"
        )


def _check_features(cfg, b, latents, features, mask):
    if features is None:
        if mask is not None:
            raise ValueError("features_mask: given without features")
        return
    if not cfg.htft_layers:
        raise ValueError("features: this DiT fuses no features (htft_layers is empty)")
    if set(features) != set(cfg.htft_layers):
        raise ValueError(
            f"features: expected a mapping with the layers {sorted(cfg.htft_layers)}, got {sorted(features)}"
        )
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
