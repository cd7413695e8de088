"""Long-video strategies on one interface: ``(models, controls, first, length) -> latent parts``.

Each strategy is a generator that yields the output clip's latents ``[B, V, n, h, w, C]`` (NumPy,
on the host) part by part, in frame order, as they are finished, so the caller can decode and
write each part while the next is sampled (:mod:`jaxdrive.generate.long_video`). ``models`` is a
:class:`Models` (the run's model and, for the two-model strategies, the fine one); ``controls``
the horizon's conditions on the host, per frame of the output rate; ``first`` the given latent
frames ``[B, V, k, h, w, C]``; ``length`` the latent frames to produce (the given ones included).

- ``rollout``: windows of the model's length, each conditioned on the last ``overlap`` frames of
  the previous one (the recurrent baseline both papers beat; its errors accumulate and its
  sequential calls grow with the length).
- ``coarse-to-refine`` (MiLA [2503.15875v1] sec. 3.2-3.3): a coarse pass draws low-fps anchors every
  ``anchor_every`` frames over the whole horizon (windowed when it exceeds one window, the model
  told the lower frame rate); the (Re)fine pass is recurrent at the full rate: each window
  conditions on the last frames of the previous one and on the anchors inside it, which are
  re-noised by JDC (eq. 8-12) and denoised jointly with the frames between them (TPD, eq.
  13-14), so the output's anchors are the corrected ones. Without anchors it is ``rollout``.
- ``coarse-fine`` (LongDWM [2506.01546v1] sec. 3.2 and inference): the coarse model draws keyframes every
  ``K - 1`` frames (``K`` the fine model's window); the fine model then fills every segment
  between consecutive keyframes in one batched sampler call (segments stacked on the batch axis,
  sharded over ``data``), both ends pinned. Sequential sampler calls: the coarse windows + 1
  (+ more when ``segment_batch`` caps the segments per call, which keeps device memory flat).
- ``window`` (MagicDrive-V2 [2411.13807v3] sec. 4.5, 6): the whole length in one sampler call, for a model
  trained on several lengths (``data.buckets``), which extrapolates past them; its tokens are
  sharded over the mesh's ``seq`` axis, so the length is bounded by the mesh, not by one
  device. One sequential call; device memory grows with the length.
- ``streaming`` (STAGE, :mod:`jaxdrive.generate.streaming`): frame by frame, each new frame from
  the anchor (first) frame and the frame before it, with the HTFT buffer of the past frames'
  features at every denoising step; one sequential call per frame, device memory flat.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator

import jax
import numpy as np

from jaxdrive import flow
from jaxdrive.generate.segments import AUTO, check_segment_batch, choose_segment_batch, fine_group
from jaxdrive.generate.streaming import check_taps, streaming  # noqa: F401  (check_taps: its old home)
from jaxdrive.generate.windows import Horizon, Tracker, WindowModel, to_mesh, window_controls, window_starts
from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.validate import check_choice, check_positive_int

STRATEGIES = ("rollout", "coarse-to-refine", "coarse-fine", "window", "streaming")
NEEDS_FINE = ("coarse-fine",)


@dataclasses.dataclass(frozen=True)
class Models:
    """The models a strategy runs: ``main`` (``--workdir``: the rollout model, MiLA's model for
    both passes, LongDWM's coarse DiT) and ``fine`` (``--fine-workdir``: LongDWM's fine DiT, or a
    separate (Re)fine model for ``coarse-to-refine``)."""

    main: WindowModel
    fine: WindowModel | None = None


def _pass(
    model: WindowModel,
    horizon: Horizon,
    positions,
    controls: Conditions,
    key,
    tracker: Tracker,
    mesh,
    *,
    given: int,
    overlap: int,
    fps_scale: float = 1.0,
    anchors: bool = False,
    warp=None,
):
    """Windows of ``model`` over the horizon ``positions`` (:func:`window_starts`): the first
    conditions on its ``given`` known frames, each next on the ``overlap`` frames before it; with
    ``anchors``, known frames inside a window that are not given are JDC anchors; ``warp``: the
    warped frames' guide of a model trained with them. Results go back into ``horizon``. A generator:
    yields the number of positions finished after each window, returns the next random key."""
    positions = np.asarray(positions)
    window = min(model.window, len(positions))
    b = horizon.latents.shape[0]
    done = 0
    for start in window_starts(len(positions), window, overlap):
        idx = positions[start : start + window]
        n_cond = given if done == 0 else done - start
        cond = np.broadcast_to(np.asarray(flow.pattern_masks("prefix", window, n_cond)[0]), (b, window))
        anchor = None
        if anchors:
            anchor = np.broadcast_to(horizon.known[idx][None], (b, window)) & ~cond
            anchor = anchor if anchor.any() else None
        key, sub = jax.random.split(key)
        args = to_mesh(
            (
                model.params,
                horizon.latents[:, :, idx],
                cond,
                window_controls(model, horizon, idx, controls, fps_scale=fps_scale, warp=warp),
            ),
            mesh,
        )
        z = tracker.call(model, *args, sub, *(() if anchor is None else (to_mesh(anchor, mesh),)))
        horizon.put(idx, np.asarray(z))
        del z, args
        done = start + window
        yield done
    return key


def _drain(gen):
    """Run a pass to its end; its return value (the next key)."""
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value


class _Emitter:
    """Yields the horizon's frames ``[sent, upto)`` once they are final."""

    def __init__(self, horizon: Horizon):
        self.horizon, self.sent = horizon, 0

    def upto(self, end: int):
        if end > self.sent:
            part = self.horizon.latents[:, :, self.sent : end].copy()
            self.sent = end
            return part
        return None


def rollout(
    models: Models,
    controls: Conditions,
    first,
    length: int,
    *,
    key,
    tracker: Tracker | None = None,
    mesh=None,
    overlap: int | None = None,
    warp=None,
) -> Iterator[np.ndarray]:
    """The recurrent baseline (module docstring); ``overlap`` defaults to the given frames."""
    yield from coarse_to_refine(
        models, controls, first, length, key=key, tracker=tracker, mesh=mesh, overlap=overlap, anchor_every=0, warp=warp
    )


def coarse_anchors(
    models: Models,
    controls: Conditions,
    first,
    length: int,
    *,
    key,
    tracker: Tracker | None = None,
    mesh=None,
    anchor_every: int | None = None,
    warp=None,
):
    """The coarse pass of :func:`coarse_to_refine`: ``(horizon, key)`` with the given frames and
    the anchors at positions ``given - 1 + j * anchor_every`` (``j >= 1``) known, drawn by
    ``models.main`` over the given frames + the anchors at ``1 / anchor_every`` of the rate
    (windowed when they exceed its window)."""
    tracker = tracker or Tracker()
    coarse, refine = models.main, models.fine or models.main
    first = np.asarray(first, np.float32)
    given = first.shape[2]
    spacing = anchor_spacing(refine, given) if anchor_every is None else anchor_every
    horizon = Horizon.start(first, length)
    anchors = list(range(given - 1 + spacing, length, spacing)) if spacing else []
    if anchors:
        key = _drain(
            _pass(
                coarse,
                horizon,
                list(range(given)) + anchors,
                controls,
                key,
                tracker,
                mesh,
                given=given,
                overlap=min(given, coarse.window - 1),
                fps_scale=spacing,
                warp=warp,
            )
        )
    return horizon, key


def coarse_to_refine(
    models: Models,
    controls: Conditions,
    first,
    length: int,
    *,
    key,
    tracker: Tracker | None = None,
    mesh=None,
    overlap: int | None = None,
    anchor_every: int | None = None,
    warp=None,
) -> Iterator[np.ndarray]:
    """MiLA's Coarse-to-(Re)fine (module docstring). ``models.main`` draws the anchors
    (:func:`coarse_anchors`) and refines them unless ``models.fine`` is given; ``anchor_every``
    (latent frames between anchors) defaults to the refine model's training spacing
    (``flow.anchor_every``, else its window minus its given frames: MiLA's tail anchor); 0 turns
    the anchors off, which is ``rollout``."""
    tracker = tracker or Tracker()
    refine = models.fine or models.main
    given = np.shape(first)[2]
    overlap = given if overlap is None else overlap
    horizon, key = coarse_anchors(
        models, controls, first, length, key=key, tracker=tracker, mesh=mesh, anchor_every=anchor_every, warp=warp
    )
    emit = _Emitter(horizon)
    refine_pass = _pass(
        refine,
        horizon,
        np.arange(length),
        controls,
        key,
        tracker,
        mesh,
        given=given,
        overlap=overlap,
        anchors=bool(horizon.known[given:].any()),
        warp=warp,
    )
    for done in refine_pass:  # each finished window goes out before the next is sampled
        part = emit.upto(done)
        if part is not None:
            yield part


def coarse_fine(
    models: Models,
    controls: Conditions,
    first,
    length: int,
    *,
    key,
    tracker: Tracker | None = None,
    mesh=None,
    segment_batch="auto",
    device_memory=None,
    warp=None,
) -> Iterator[np.ndarray]:
    """LongDWM's coarse keyframes + parallel fine interpolation (module docstring).
    ``segment_batch``: segments per fine sampler call, or ``"auto"`` (the default): the largest
    group whose compiled call fits ``device_memory`` bytes per device (default: the device's free
    memory, :mod:`jaxdrive.generate.segments`), chosen before the coarse pass runs and written to
    ``report.json`` (``segment_batch``)."""
    tracker = tracker or Tracker()
    coarse, fine = models.main, models.fine
    first = np.asarray(first, np.float32)
    given = first.shape[2]
    seg = fine.window - 1
    keys = list(range(0, length, seg))
    horizon = Horizon.start(first, length)
    emit = _Emitter(horizon)
    segments = len(keys) - 1
    per_call = check_segment_batch(segment_batch)
    if per_call == AUTO:
        choice = choose_segment_batch(
            fine,
            horizon,
            controls,
            segments,
            given=given,
            key=key,
            tracker=tracker,
            mesh=mesh,
            warp=warp,
            device_memory=device_memory,
        )
        per_call = choice["segment_batch"]
        tracker.notes["segment_batch"] = choice
    coarse_positions = sorted(set(range(given)) | set(keys))
    key = _drain(
        _pass(
            coarse,
            horizon,
            coarse_positions,
            controls,
            key,
            tracker,
            mesh,
            given=given,
            overlap=min(given, coarse.window - 1),
            fps_scale=seg,
            warp=warp,
        )
    )
    b = first.shape[0]
    for lo in range(0, segments, per_call):
        idx, args = fine_group(fine, horizon, range(lo, min(lo + per_call, segments)), controls, given=given, warp=warp)
        key, sub = jax.random.split(key)
        z = np.asarray(tracker.call(fine, *to_mesh((fine.params, *args), mesh), sub))
        for j, i in enumerate(idx):
            horizon.put(i, z[j * b : (j + 1) * b])
        del z  # on a CPU the array may be a view of the device buffer: free it now
        part = emit.upto(idx[-1][-1] + 1)
        if part is not None:
            yield part


def window(
    models: Models,
    controls: Conditions,
    first,
    length: int,
    *,
    key,
    tracker: Tracker | None = None,
    mesh=None,
    warp=None,
) -> Iterator[np.ndarray]:
    """MagicDrive-V2's one-shot long window (module docstring): ``models.main`` over all
    ``length`` latent frames in one sampler call, the given frames pinned."""
    tracker = tracker or Tracker()
    first = np.asarray(first, np.float32)
    given = first.shape[2]
    horizon = Horizon.start(first, length)
    whole = dataclasses.replace(models.main, window=length)
    _drain(
        _pass(whole, horizon, np.arange(length), controls, key, tracker, mesh, given=given, overlap=given, warp=warp)
    )
    yield horizon.latents.copy()


def anchor_spacing(model: WindowModel, given: int) -> int:
    """Latent frames between (Re)fine anchors: the model's ``anchor_every`` or, trained with
    MiLA's tail anchor only, its window minus the given frames."""
    return model.anchor_every or max(model.window - given, 1)


def check_strategy(name: str, models: Models, length: int, given: int) -> None:
    """Reject, before anything compiles, a strategy its models or the length cannot serve:
    ``ValueError`` naming the option."""
    check_choice("strategy", name, STRATEGIES)
    check_positive_int("frames", length)
    if given < (0 if name == "rollout" else 1) or given >= length:
        raise ValueError(f"frames: expected more latent frames than the {given} given ones, got {length}")
    main, fine = models.main, models.fine
    if name in NEEDS_FINE and fine is None:
        raise ValueError(f"models.fine: strategy {name!r} needs a fine model run, got none")
    if name == "coarse-fine":
        if "ends" not in fine.patterns:
            raise ValueError(
                f"models.fine: expected a model trained for interpolation (flow.patterns with 'ends', "
                f"LongDWM's fine DiT), got one trained with patterns {list(fine.patterns)}"
            )
        seg = fine.window - 1
        if (length - 1) % seg:
            lo = 1 + (length - 1) // seg * seg
            raise ValueError(
                f"frames: coarse-fine reaches 1 + n * {seg} latent frames (keyframes every fine window "
                f"- 1 = {seg}), got {length}; e.g. {lo} or {lo + seg}"
            )
        if given > fine.window - 1:
            raise ValueError(
                f"frames: expected at most {fine.window - 1} given frames for a fine window of "
                f"{fine.window}, got {given}"
            )
        for role, m in (("models.main", main), ("models.fine", fine)):
            if m.temporal != 1:
                raise ValueError(
                    f"{role}: coarse-fine needs frame-wise latents (keyframes are single latent "
                    f"frames), got temporal compression {m.temporal}"
                )
    if name == "coarse-to-refine":
        refine = fine or main
        if main.temporal != 1:
            raise ValueError(
                f"models.main: coarse-to-refine draws spaced anchors, which needs frame-wise latents, "
                f"got temporal compression {main.temporal}"
            )
        if not refine.trained_anchors:
            raise ValueError(
                f"models.{'fine' if fine else 'main'}: coarse-to-refine needs a model trained to correct "
                f"JDC anchors (flow.jdc_anchor_rate > 0, MiLA stage 3), got jdc_anchor_rate = 0"
            )
        if refine.jdc_slope < refine.jdc_alpha1:
            raise ValueError(
                f"flow.jdc_slope: expected >= flow.jdc_alpha1 = {refine.jdc_alpha1} (JDC re-noises "
                f"anchors to g = slope * sigma_max >= alpha1), got {refine.jdc_slope}"
            )
    if name == "streaming" and not main.streaming:
        raise ValueError(
            "models.main: 'streaming' needs a model trained frame by frame (stream.enabled, STAGE's "
            f"configs/stage.py), got one trained on windows of {main.window} latent frames"
        )
    if name != "streaming" and main.streaming:
        raise ValueError(
            f"strategy: a model trained frame by frame (stream.enabled) samples with 'streaming', got {name!r}"
        )
    if name == "window" and len(main.lengths) < 2:
        raise ValueError(
            f"strategy: 'window' samples the whole length at once, which needs a model trained on "
            f"several lengths (data.buckets, MagicDrive-V2), got one trained on "
            f"{list(main.lengths) or [main.window]} latent frames only"
        )
    if main.window < 2 or (fine is not None and fine.window < 2):
        raise ValueError("window: expected models of at least 2 latent frames")


def run_strategy(
    name: str,
    models: Models,
    controls: Conditions,
    first,
    length: int,
    *,
    key,
    tracker: Tracker | None = None,
    mesh=None,
    **options,
) -> Iterator[np.ndarray]:
    """Check, then run the strategy ``name`` (its generator of latent parts)."""
    first = np.asarray(first)
    check_strategy(name, models, length, first.shape[2])
    warped = [m for m in (models.main, models.fine) if m is not None and m.dit.config.controls.warp]
    if warped and name == "streaming":
        raise ValueError(
            "strategy: a model trained with warped frames (controls.warp) samples windows, got 'streaming'"
        )
    if warped and options.get("warp") is None:
        raise ValueError(
            "warp: a model trained with warped frames (controls.warp) needs the poses to warp along "
            "(a WarpGuide: the clip's recorded poses or a route), got none"
        )
    fn = {
        "rollout": rollout,
        "coarse-to-refine": coarse_to_refine,
        "coarse-fine": coarse_fine,
        "window": window,
        "streaming": streaming,
    }[name]
    return fn(models, controls, first, length, key=key, tracker=tracker, mesh=mesh, **options)


def sequential_calls(name: str, models: Models, length: int, given: int, **options) -> int:
    """The sampler calls ``name`` makes one after another (without running it)."""
    main, fine = models.main, models.fine
    if name == "window":
        return 1
    if name == "streaming":  # the given frames after the anchor are observed into the buffer
        taps = main.stream_taps if options.get("taps") is None else options["taps"]
        return length - given + (given - 1 if taps else 0)
    coarse_windows = lambda n: len(window_starts(n, min(main.window, n), min(given, main.window - 1)))
    if name == "coarse-fine":
        seg = fine.window - 1
        segments = (length - 1) // seg
        per_call = options.get("segment_batch") or AUTO
        per_call = segments if per_call == AUTO else per_call  # auto: at most all of them
        return coarse_windows(len(set(range(given)) | set(range(0, length, seg)))) + math.ceil(segments / per_call)
    refine = fine or main
    overlap = options.get("overlap") or given
    calls = len(window_starts(length, min(refine.window, length), overlap))
    spacing = options.get("anchor_every")
    spacing = anchor_spacing(refine, given) if spacing is None and name == "coarse-to-refine" else (spacing or 0)
    if name == "coarse-to-refine" and spacing and given - 1 + spacing < length:
        calls += coarse_windows(given + len(range(given - 1 + spacing, length, spacing)))
    return calls
