"""Run a long-video strategy to files, with device memory flat in the length.

:func:`sample_long` takes a strategy's latent parts (:mod:`jaxdrive.generate.strategies`) as
they are finished, decodes each at once with the codec's streaming decoder (a causal VAE's
decode cache carries across parts, so the video equals a whole-clip decode of the same latents)
and appends it to the mp4. It writes under ``out``:

- ``sample.mp4``: the first clip, views tiled;
- ``frames.png``: six frames spread over the horizon (with the recorded frames on the left when
  the dataset clip covers them);
- ``latents.npy``: all latents ``[B, V, F', h, w, C]``;
- ``report.json``: ``strategy``, ``frames``, ``latent_frames``, ``views``, ``clips``,
  ``sequential_sampler_calls``, ``seconds``, ``peak_device_bytes`` (and the models' windows and
  the options the strategy ran with, ``compiled_programs``; ``guidance``: each model's scales,
  :func:`jaxdrive.generate.guidance.describe`; ``stream`` for ``streaming``: the HTFT
  buffer's frames, taps and fixed ``buffer_bytes``); with a driven route, ``route`` (where it came
  from) and ``route_drive`` (the first clip's, :func:`jaxdrive.generate.route.drive_on_map`: where
  the manoeuvre started, whether and how far it left the road); when the recorded clip covers the horizon, ``quality``:
  PSNR / SSIM of the first clip against it, beside the repeat and noise baselines, over the
  first window, all generated frames and each second (``horizon``), scored part by part as the
  frames are decoded (:class:`jaxdrive.generate.quality.FrameScores`);
- ``quality.json``: the same scores with one row per frame.

What it wrote, and the quality over all generated frames, is logged at INFO.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import jax
import numpy as np

from jaxdrive.generate.guidance import describe
from jaxdrive.generate.strategies import Models, run_strategy
from jaxdrive.generate.windows import Tracker
from jaxdrive.logs import deprecated_log
from jaxdrive.models.dit.conditions import Conditions

logger = logging.getLogger(__name__)

GRID_FRAMES = 6


@deprecated_log
def sample_long(strategy: str, models: Models, codec, controls: Conditions, first, length: int, out, **kwargs) -> dict:
    """:func:`long_video` writing its files under ``out`` (``kwargs`` as there); returns the report."""
    return long_video(strategy, models, codec, controls, first, length, out, **kwargs)[0]


def long_video(
    strategy: str,
    models: Models,
    codec,
    controls: Conditions,
    first,
    length: int,
    out=None,
    *,
    key,
    mesh=None,
    fps: float = 12.0,
    recorded=None,
    route: str | None = None,
    control_source: dict | None = None,
    scene: dict | None = None,
    keep: int | None = None,
    keep_video: bool = False,
    **options,
):
    """Run ``strategy`` for ``length`` latent frames and write the files of the module docstring;
    returns the report (a dict). ``recorded``: the dataset's own pixel frames ``[V, F, H, W, 3]``
    of the first clip (for the frame grid), when it covers the horizon; ``options`` go to the
    strategy (``overlap``, ``anchor_every``, ``segment_batch``, ``warp``); ``route``: where the
    driven route came from (``jaxdrive sample --route``), for the report; ``control_source``: where the
    controls came from (recorded, predicted), for the report; ``scene``: the first clip's
    ``bev_map``, ``ego_to_world``, ``boxes``, ``box_valid`` per frame, ``predicted_from`` (the
    first frame not recorded) and optionally ``route_drive`` (for the report): each frame-grid row
    then starts with its BEV map, the ego's path drawn on it (:func:`jaxdrive.media.bev_image`).
    ``log=`` is deprecated (:func:`jaxdrive.logs.deprecated_log`). Returns ``(report, latents,
    video)``: ``out`` None writes nothing; ``keep``: the first clips kept (the rest padded a batch
    to the mesh's batch shards); ``keep_video``: also the decoded video of those clips ``[clips,
    V, F, H, W, 3]`` (else None: a minute of paper-size video is tens of GB on the host)."""
    tracker = Tracker()
    start = time.perf_counter()
    parts = run_strategy(strategy, models, controls, first, length, key=key, tracker=tracker, mesh=mesh, **options)
    out = None if out is None else Path(out)
    frames = codec.pixel_frames(length)
    picks = np.unique(np.linspace(0, frames - 1, min(GRID_FRAMES, frames)).round().astype(int))
    decoder = codec.stream_decoder(length)
    latents, grid, written = [], {}, 0
    scores = None
    if recorded is not None and np.shape(recorded)[1] >= frames:
        from jaxdrive.generate.quality import FrameScores

        given = codec.pixel_frames(np.shape(first)[2])
        scores = FrameScores(np.asarray(recorded)[:, :frames], cond_frames=given)
    writer, videos = None, []
    if jax.process_index() == 0 and out is not None:
        from jaxdrive.media import Mp4Writer

        writer = Mp4Writer(out / "sample.mp4", fps=fps)

    def emit(video):
        nonlocal written
        if video is None or not video.shape[2]:
            return
        if keep_video:
            videos.append(np.asarray(video[:keep]))
        clip = np.asarray(video[0])  # [V, n, H, W, 3]
        for p in picks[(picks >= written) & (picks < written + clip.shape[1])]:
            grid[int(p)] = np.array(clip[:, p - written])  # a copy, not a view of the part
        if scores is not None:
            scores.add(clip)
        if writer is not None:
            writer.write(clip)
        written += clip.shape[1]

    try:
        for part in parts:
            latents.append(part)
            emit(decoder.push(part))
            tracker.observe()
        emit(decoder.flush())
    finally:
        if writer is not None:
            writer.close()
    seconds = time.perf_counter() - start
    latents = np.concatenate(latents, axis=2)[:keep]
    report = {
        "strategy": strategy,
        "frames": int(frames),
        "latent_frames": int(length),
        "views": int(latents.shape[1]),
        "clips": int(latents.shape[0]),
        "sequential_sampler_calls": tracker.calls,
        "seconds": round(seconds, 3),
        "peak_device_bytes": int(tracker.peak_bytes),
        "fps": fps,
        "given_latent_frames": int(np.shape(first)[2]),
        "windows": {"main": models.main.window, **({"fine": models.fine.window} if models.fine else {})},
        "options": {k: v for k, v in options.items() if v is not None and k != "warp"},
        "compiled_programs": tracker.programs,
        "guidance": {
            k: describe(m.guidance, m.control_guidance)
            for k, m in (("main", models.main), ("fine", models.fine))
            if m is not None
        },
        **tracker.notes,
    }
    if options.get("warp") is not None:  # LongDWM's warped frames: the plane depth they used
        report["warp"] = {"depth": options["warp"].depth, "frame": options["warp"].frame}
    if route is not None:
        report["route"] = route
    if scene is not None and scene.get("route_drive") is not None:
        report["route_drive"] = scene["route_drive"]  # where the manoeuvre began, whether it left the road
    if control_source is not None:
        report["controls"] = control_source
    quality = None
    if scores is not None:
        window = codec.pixel_frames((models.fine or models.main).window)
        quality = scores.result(window=window, every=max(int(round(fps)), 1))
        report["quality"] = {k: v for k, v in quality.items() if k != "per_frame"}
    kept = np.concatenate(videos, axis=2) if keep_video else None
    if out is None:
        return report, latents, kept
    if jax.process_index() == 0:
        from jaxdrive.media import write_frame_grid

        out.mkdir(parents=True, exist_ok=True)
        np.save(out / "latents.npy", latents)
        video = np.stack([grid[int(p)] for p in picks], axis=1)  # [V, picks, H, W, 3]
        reference = None
        if recorded is not None and np.shape(recorded)[1] >= frames:
            reference = np.asarray(recorded)[:, picks]
        side = None if scene is None else _bev_panels(scene, picks, route is not None)
        write_frame_grid(out / "frames.png", video, num_frames=len(picks), reference=reference, side=side)
        (out / "report.json").write_text(json.dumps(report, indent=1))
        if quality is not None:
            (out / "quality.json").write_text(json.dumps(quality, indent=1))
        logger.info(
            "%s: %d frames x %d views in %.1f s, %d sequential sampler calls, peak device memory %.1f MiB: %s",
            strategy,
            frames,
            report["views"],
            seconds,
            tracker.calls,
            tracker.peak_bytes / 2**20,
            out,
        )
        if quality is not None:
            a = quality["all_generated"]
            logger.info(
                "all generated frames against the recorded clip: PSNR %.2f dB, SSIM %.3f (repeat the last "
                "given frame: %.2f dB, %.3f)",
                a["psnr"],
                a["ssim"],
                a["repeat_psnr"],
                a["repeat_ssim"],
            )
    return report, latents, kept


def _bev_panels(scene: dict, picks, routed: bool) -> np.ndarray:
    """One BEV panel per picked frame: its map, the agents, the ego's whole path in its ego frame
    (red where driven by a route or predicted, blue where recorded)."""
    from jaxdrive.media import bev_image

    e2w = np.asarray(scene["ego_to_world"], np.float64)
    bev = np.asarray(scene["bev_map"])
    cell = scene.get("cell", tuple(100.0 / n for n in bev.shape[1:3]))  # default: a 100 m square
    split = 1 if routed else int(scene.get("predicted_from", len(e2w)))
    panels = []
    for p in picks:
        p = min(int(p), len(e2w) - 1)
        path = (np.linalg.inv(e2w[p]) @ e2w)[:, :2, 3]
        panels.append(
            bev_image(bev[p], cell=cell, path=path, split=split, boxes=scene["boxes"][p], valid=scene["box_valid"][p])
        )
    return np.stack(panels)
