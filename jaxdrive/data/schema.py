"""The clip record every data source produces and every pipeline consumes.

One home for the names, classes and field layout shared by the synthetic world, the nuScenes
reader, the TFDS datasets and the grain pipelines. Geometry follows nuScenes: ego x forward,
y left, z up; camera x right, y down, z forward; boxes ``(x, y, z, length, width, height, yaw)``
in the ego frame of their own frame, (x, y, z) the box centre.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from jaxdrive.classes import BEV_CLASSES, OBJECT_CLASSES  # noqa: F401  (the record's class vocabularies)

# nuScenes camera channels in jaxdrive's view order (clockwise from the front).
CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")

CAPTION_TEMPLATE = (
    "This is a driving scene video captured by camera in {sensor} of a car at {location} during {season} {daytime}."
)


def caption(*, sensor: str, location: str, season: str, daytime: str) -> str:
    """MiLA's caption template (appendix B)."""
    return CAPTION_TEMPLATE.format(sensor=sensor, location=location, season=season, daytime=daytime)


# name -> (dtype, shape with symbolic sizes). V views, F frames, N box slots, H x W pixels,
# Hm x Wm BEV cells. Fields marked optional may be absent (nuScenes has no instance ids).
CLIP_FIELDS = {
    "video": (np.uint8, ("V", "F", "H", "W", 3)),
    "intrinsics": (np.float32, ("V", 3, 3)),
    "cam_to_ego": (np.float32, ("V", 4, 4)),
    "ego_to_world": (np.float64, ("F", 4, 4)),
    "boxes": (np.float32, ("F", "N", 7)),
    "box_classes": (np.int32, ("F", "N")),
    "box_ids": (np.int32, ("F", "N")),
    "box_valid": (np.bool_, ("F", "N")),
    "bev_map": (np.uint8, ("F", "Hm", "Wm", len(BEV_CLASSES))),
    "waypoints": (np.float32, ("F", 2)),
    "instance_ids": (np.int32, ("V", "F", "H", "W")),
}
OPTIONAL_FIELDS = ("instance_ids",)
SCALAR_FIELDS = {"fps": float, "caption": str}

# A latent window (``jaxdrive data encode``): one training sample of
# :func:`jaxdrive.data.pipeline.sample_clip` (F frames, already strided, resized and cropped) with
# ``video`` replaced by its scaled latents (L latent frames of h x w, C channels); ego_to_world is
# float32 as sample_clip returns it.
WINDOW_FIELDS = {
    "latents": (np.float32, ("V", "L", "h", "w", "C")),
    **{k: v for k, v in CLIP_FIELDS.items() if k not in ("video", "instance_ids")},
    "ego_to_world": (np.float32, ("F", 4, 4)),
}

# Record kinds a dataset can hold: name -> field table.
RECORD_FIELDS = {"clips": CLIP_FIELDS, "windows": WINDOW_FIELDS}


def check_clip(clip: Mapping, *, source: str = "clip", kind: str = "clips") -> dict:
    """Check a record against the field table of ``kind`` (:data:`CLIP_FIELDS` or
    :data:`WINDOW_FIELDS`); return the symbolic sizes it binds.

    Raises ``ValueError`` naming ``source``, the field, what was expected and what came.
    ``waypoints[f]`` is the ego position at frame f in the ego frame of frame 0 (x forward,
    y left), so ``waypoints[0] == (0, 0)``.
    """
    if kind not in RECORD_FIELDS:
        raise ValueError(f"kind: expected one of {sorted(RECORD_FIELDS)}, got {kind!r}")
    sizes: dict = {}
    for name, (dtype, spec) in RECORD_FIELDS[kind].items():
        if name not in clip:
            if name in OPTIONAL_FIELDS:
                continue
            raise ValueError(f"{source}: field {name!r} is missing (expected {np.dtype(dtype).name} {list(spec)})")
        value = np.asarray(clip[name])
        if value.dtype != np.dtype(dtype):
            raise ValueError(f"{source}: field {name!r}: expected dtype {np.dtype(dtype).name}, got {value.dtype}")
        if value.ndim != len(spec):
            raise ValueError(f"{source}: field {name!r}: expected shape {list(spec)}, got {list(value.shape)}")
        for sym, size in zip(spec, value.shape):
            if isinstance(sym, int):
                ok = size == sym
            else:
                ok = sizes.setdefault(sym, size) == size
            if not ok:
                want = sym if isinstance(sym, int) else f"{sym} = {sizes[sym]}"
                raise ValueError(
                    f"{source}: field {name!r}: expected shape {list(spec)} with {want}, got {list(value.shape)}"
                )
    for name, kind in SCALAR_FIELDS.items():
        if name not in clip:
            raise ValueError(f"{source}: field {name!r} is missing (expected {kind.__name__})")
        if not isinstance(clip[name], (kind, np.generic)) or (kind is float and not float(clip[name]) > 0):
            raise ValueError(
                f"{source}: field {name!r}: expected a {'positive ' if kind is float else ''}"
                f"{kind.__name__}, got {clip[name]!r}"
            )
    return sizes
