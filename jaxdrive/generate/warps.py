"""LongDWM's warped frames in sampling (sec. 3.4): every window of a model trained with
``controls.warp`` gets, as its ``warp`` condition, one of its frames (the first, LongDWM's, or the
run's ``data.warp_frame``: the world recipe's last given frame) warped along the poses of the
window's frames (relative to that frame's) at one depth, holes inpainted, encoded like the
latents: what training gives it (:func:`jaxdrive.data.transforms.clip_warp`). That frame is
whatever the horizon holds there (a given frame, or one the strategy generated: each window of a
rollout warps from its own), decoded to pixels; the poses are the clip's recorded ones or a user's
route.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np

from jaxdrive.validate import check_trailing_shape


@dataclasses.dataclass(frozen=True)
class WarpGuide:
    """What warping a window needs: the ``codec`` (and ``codec_params``) to decode its first frame
    and encode the warped clip, every output pixel frame's ego pose ``poses [B, P, 4, 4]`` (in
    any one world frame), the cameras ``intrinsics [B, V, 3, 3]`` / ``cam_to_ego [B, V, 4, 4]`` and
    the plane ``depth`` in metres (the run's ``data.warp_depth``); ``frame``: the window's latent
    frame warped (the run's ``data.warp_frame``)."""

    codec: Any
    codec_params: Any
    poses: np.ndarray
    intrinsics: np.ndarray
    cam_to_ego: np.ndarray
    depth: float
    frame: int = 0

    def __post_init__(self):
        check_trailing_shape("poses", self.poses, (None, 4, 4), "[B, P, 4, 4]")
        check_trailing_shape("intrinsics", self.intrinsics, (None, 3, 3), "[B, V, 3, 3]")
        check_trailing_shape("cam_to_ego", self.cam_to_ego, (None, 4, 4), "[B, V, 4, 4]")
        if not (np.isfinite(self.depth) and self.depth > 0):
            raise ValueError(f"depth: expected a positive plane depth in metres, got {self.depth}")

    @classmethod
    def from_inputs(cls, inputs: dict, codec, depth: float, frame: int = 0) -> WarpGuide:
        """From :func:`jaxdrive.data.batches.model_inputs` of a model with ``controls.warp`` (its
        ``warp`` entry: the clips' poses and cameras)."""
        w = inputs["warp"]
        return cls(
            codec,
            codec.params,
            np.asarray(w["poses"], np.float32),
            np.asarray(w["intrinsics"], np.float32),
            np.asarray(w["cam_to_ego"], np.float32),
            float(depth),
            int(frame),
        )

    def window(self, first, pixel_frames) -> np.ndarray:
        """The ``warp`` latents ``[B, V, F', h, w, C]`` of a window whose latent frame
        :attr:`frame` is ``first [B, V, 1, h, w, C]`` and whose pixel frames are ``pixel_frames``
        (output pixel frames; with ``frame > 0`` the latents are frame-wise, pixel frame
        ``frame`` of the window is that latent frame)."""
        from jaxdrive.warp import warp_views

        frames = np.asarray(pixel_frames)
        if int(frames.max()) >= self.poses.shape[1]:
            raise ValueError(
                f"poses: expected a pose for pixel frame {int(frames.max())} of the horizon, got "
                f"{self.poses.shape[1]} poses"
            )
        pixels = np.asarray(_DECODE(self.codec, self.codec_params, first))[:, :, 0]  # [B, V, H, W, 3]
        p = self.poses[:, frames].astype(np.float64)
        rel = (np.linalg.inv(p[:, self.frame : self.frame + 1]) @ p).astype(np.float32)  # [B, n, 4, 4]
        video = np.stack(
            [
                warp_views(pixels[b], self.intrinsics[b], self.cam_to_ego[b], rel[b], self.depth)
                for b in range(pixels.shape[0])
            ]
        )
        return np.asarray(_ENCODE(self.codec, self.codec_params, video))


# compiled once per codec and shape (the codec is static: its parameters are an argument)
_DECODE = jax.jit(lambda codec, params, x: codec.decode(params, x), static_argnums=0)
_ENCODE = jax.jit(lambda codec, params, x: codec.encode(params, x), static_argnums=0)


def warp_options(models, inputs: dict, codec, *, depth: float, frame: int = 0) -> dict:
    """The strategy options of ``models`` (:class:`jaxdrive.generate.strategies.Models`) for
    ``inputs``: ``{"warp": WarpGuide}`` along their poses when the main or the fine model was
    trained with ``controls.warp`` (every window warps its own frame), else ``{}``."""
    if any(m is not None and m.dit.config.controls.warp for m in (models.main, models.fine)):
        return {"warp": WarpGuide.from_inputs(inputs, codec, depth=depth, frame=frame)}
    return {}
