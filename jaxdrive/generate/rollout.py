"""Rolling a dataset clip's first frames out to a long video, window by window.

One window is :func:`jaxdrive.generate.windows.sample_window` (the jitted sampler: clean
condition frames pinned at level 0, the others from noise along
:func:`jaxdrive.flow.frame_schedule`, classifier-free guidance against the learned nulls).
:func:`rollout` reaches clips longer than the training window autoregressively (the streaming of
STAGE / MiLA's continuation): each next window overlaps the last ``overlap`` generated latent
frames, which it takes as its condition frames, and reads the per-frame controls (waypoints,
poses, boxes, map) of its own frames. Every window has the training window's length, so the
sampler compiles once; a last window that would run past the end starts earlier and conditions
on all frames it overlaps. It is the ``rollout`` strategy of
:mod:`jaxdrive.generate.strategies` on the inputs of a dataset batch.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.generate.windows import WindowModel, window_starts
from jaxdrive.models.dit.model import DiT
from jaxdrive.progress import Progress
from jaxdrive.validate import check_positive_int


def rollout(
    dit: DiT,
    codec,
    params,
    codec_params,
    inputs: dict,
    *,
    total_frames: int,
    window: int,
    overlap: int,
    cond_frames: int,
    steps: int,
    guidance: float,
    key,
    shift: float = 1.0,
    tpd: bool = False,
    tpd_omega: float = np.pi / 2,
    progress: bool = False,
    mesh=None,
    control_guidance: tuple[tuple[str, float], ...] = (),
):
    """Latents ``[B, V, total_frames, h, w, C]`` (NumPy) generated window by window (module
    docstring): the ``rollout`` strategy of :mod:`jaxdrive.generate.strategies` on a dataset
    batch; ``progress``: the progress over the windows, on process 0 (a tqdm bar when stderr is a
    terminal, else a ``jaxdrive.progress`` log line per window: :mod:`jaxdrive.progress`);
    ``mesh``: where the windows run (their batch over ``data``/``fsdp``).

    ``inputs``: :func:`jaxdrive.data.batches.model_inputs` of clips that cover the whole
    length (per-frame controls in ``cond`` for every frame; ``video`` needs only the first ``cond_frames``
    latent frames' pixels; a precomputed dataset gives ``latents`` instead, of at least ``window``
    frames). ``window``: latent frames per window (the training length);
    ``overlap``: frames each next window conditions on (``1 <= overlap < window``); ``guidance``,
    ``control_guidance``: as :class:`jaxdrive.generate.windows.WindowModel` takes them."""
    from jaxdrive.generate.strategies import Models
    from jaxdrive.generate.strategies import rollout as rollout_strategy

    check_positive_int("total_frames", total_frames)
    check_positive_int("window", window)
    check_positive_int("overlap", overlap)
    if overlap >= window:
        raise ValueError(f"overlap: expected fewer than window = {window} frames, got {overlap}")
    if not 0 <= cond_frames < min(window, total_frames):
        raise ValueError(f"cond_frames: expected in [0, {min(window, total_frames)}), got {cond_frames}")
    window = min(window, total_frames)
    controls = jax.tree_util.tree_map(np.asarray, inputs["cond"])
    if "latents" in inputs:  # stored (latents.precomputed)
        first = np.asarray(inputs["latents"])[:, :, :cond_frames]
    else:  # encoded as a whole window, as training encodes its clips
        video = jnp.asarray(inputs["video"])[:, :, : codec.pixel_frames(window)]
        first = np.asarray(codec.encode(codec_params, video))[:, :, :cond_frames]
    model = WindowModel(
        dit,
        params,
        window=window,
        cond_frames=cond_frames,
        steps=steps,
        guidance=guidance,
        control_guidance=tuple(control_guidance),
        shift=shift,
        tpd=tpd,
        tpd_omega=tpd_omega,
        temporal=codec.temporal,
        value_range=codec.value_range,
    )
    parts = rollout_strategy(Models(model), controls, first, total_frames, key=key, mesh=mesh, overlap=overlap)
    total = len(window_starts(total_frames, window, overlap))
    with Progress(total, unit="window", enabled=progress and jax.process_index() == 0) as bar:
        return np.concatenate([first[:, :, :0]] + list(bar.iterate(parts)), axis=2)


def to_numpy_video(codec, codec_params, latents) -> np.ndarray:
    """Decoded video ``[B, V, F, H, W, 3]`` in [-1, 1] as NumPy."""
    return np.asarray(jax.jit(codec.decode)(codec_params, latents))
