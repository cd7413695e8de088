"""The building block of every long-video strategy: a trained model (:class:`WindowModel`) run
window by window over any list of frame positions, with the horizon's latents on the host.

A strategy never holds the whole horizon on the device. The latents live in a host buffer
(:class:`Horizon`); a sampler call gets only its window (or its stacked segments), sharded over
the mesh's batch axes, and its result goes back to the host at once. :class:`Tracker` counts the
sequential sampler calls and keeps the peak device memory they needed (``report.json``).

Positions are latent frames of the output clip at its own rate. A pass over a subset of them
(MiLA's low-fps anchors, LongDWM's keyframes) gives the model the per-frame controls at those
positions and the frame rate they imply; it needs a frame-wise codec (a latent frame per pixel
frame), since a causal VAE's latent frame summarises 4 consecutive pixel frames.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive import flow
from jaxdrive.config_checks import check_warp_start
from jaxdrive.flow.jdc import DEFAULT_ALPHA1, DEFAULT_ANCHOR_SLOPE
from jaxdrive.generate.guidance import check_controls, check_scale, sampler_guidance
from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.models.dit.model import DiT
from jaxdrive.parallel.memory import live_device_bytes, temp_bytes
from jaxdrive.parallel.mesh import batch_axes, batch_shards
from jaxdrive.validate import check_positive_int

# the latent frames of one streaming sampler call (STAGE, :mod:`jaxdrive.generate.streaming`):
# anchor, condition, new; here because every window-sized model reads it, the streaming one included
STREAM_WINDOW = 3


@dataclasses.dataclass(frozen=True)
class WindowModel:
    """A trained DiT and how to sample it: its ``window`` (latent frames per sampler call), the
    given frames it was trained with (``cond_frames``), the flow settings of its training (shift,
    TPD, JDC slope and alpha1, the condition ``patterns`` and ``anchor_every``), the sampling
    ``steps``, the plain guidance scale ``guidance`` and the per-control ones ``control_guidance``
    (``((control, scale), ...)``, :mod:`jaxdrive.generate.guidance`). ``stride``: source frames
    between its training frames (a coarse model's low rate). ``streaming``: trained frame by frame
    (STAGE, ``stream.enabled``), with an HTFT buffer of ``stream_buffer`` frames fusing
    ``stream_taps`` (empty: HTFT off). ``value_range``: the interval its codec's latents lie in
    (``LatentCodec.value_range``), or None. ``given_noise``: the level its given frames are
    noised to before each call (``flow.given_noise_sample``, :func:`jaxdrive.flow.noise_given_frames`).
    ``warp_start``: the level a warp-guided model's generated frames start from, their warp noised
    to it (``sample.warp_start``, SDEdit; 1: pure noise)."""

    dit: DiT
    params: Any = dataclasses.field(compare=False, hash=False, repr=False)
    window: int = 9
    cond_frames: int = 1
    steps: int = 20
    guidance: float = 1.0
    control_guidance: tuple[tuple[str, float], ...] = ()
    shift: float = 1.0
    tpd: bool = False
    tpd_omega: float = math.pi / 2
    jdc_slope: float = DEFAULT_ANCHOR_SLOPE
    jdc_alpha1: float = DEFAULT_ALPHA1
    patterns: tuple[str, ...] = ("prefix",)
    anchor_every: int = 0
    jdc_anchor_rate: float = 0.0
    stride: int = 1
    temporal: int = 1
    lengths: tuple[int, ...] = ()
    streaming: bool = False
    stream_buffer: int = 10
    stream_taps: tuple[int, ...] = ()
    value_range: tuple[float, float] | None = None
    given_noise: float = 0.0
    warp_start: float = 1.0

    def __post_init__(self):
        check_scale("guidance", self.guidance)
        check_warp_start(self.warp_start, self.dit.config)
        for control, scale in self.control_guidance:
            check_scale(f"control_guidance[{control!r}]", scale)

    @classmethod
    def from_sampling(
        cls,
        spec,
        params,
        *,
        steps: int | None = None,
        guidance: float | None = None,
        control_guidance: Mapping[str, float | None] | None = None,
    ) -> WindowModel:
        """From a run's :class:`jaxdrive.generate.samples.Sampling` and its parameters; ``lengths``:
        the latent frame counts it trained on (several with ``data.buckets`` of several lengths).
        ``guidance`` None: the run's (``sample.cfg``); ``control_guidance``: control -> scale,
        checked against the model (:func:`jaxdrive.generate.guidance.check_controls`)."""
        from jaxdrive.data.buckets import parse_bucket_specs

        guidance = spec.guidance if guidance is None else guidance
        controls = check_controls(spec.model, spec.data.drop_prob, control_guidance or {})
        d, f = spec.data, spec.flow
        lengths = {spec.latent_window}
        if d.buckets:
            lengths = {spec.codec.latent_frames(k[2]) for k in parse_bucket_specs(d.buckets)}
        # the resolution rule counts the frames one sampler call denoises: a streaming model's
        # window is [anchor, condition, new] (as its training step counts it), not data.frames
        shift = (
            f.shift
            if f.shift > 0
            else flow.resolution_shift(d.height, d.width, STREAM_WINDOW if spec.stream.enabled else spec.latent_window)
        )
        return cls(
            DiT(spec.model),
            params,
            window=spec.latent_window,
            cond_frames=max(1, f.cond_frames),
            steps=spec.steps if steps is None else check_positive_int("steps", steps),
            guidance=guidance,
            control_guidance=controls,
            shift=shift,
            tpd=f.tpd,
            tpd_omega=f.tpd_omega,
            jdc_slope=f.jdc_slope,
            jdc_alpha1=f.jdc_alpha1,
            patterns=tuple(f.patterns),
            anchor_every=f.anchor_every,
            jdc_anchor_rate=f.jdc_anchor_rate,
            stride=spec.frame_stride,
            temporal=spec.codec.temporal,
            lengths=tuple(sorted(lengths)),
            streaming=spec.stream.enabled,
            stream_buffer=spec.stream.buffer,
            stream_taps=tuple(spec.stream.taps) if spec.model.htft_layers else (),
            value_range=spec.codec.value_range,
            given_noise=f.given_noise_sample,
            warp_start=spec.warp_start,
        )

    def in_range(self, latents):
        """``latents`` clipped to :attr:`value_range` (unchanged when None). Every sampled frame
        may become the condition frame of a later call (a rollout's next window, a stream's next
        frame): a value no encoded frame can have is an error the next call builds on (measured on
        the tiny recipe: without the clip its streamed latents leave [-1, 1] within a second and
        grow without bound, 1000x by frame 100)."""
        if self.value_range is None:
            return latents
        return jnp.clip(latents, *self.value_range)

    @property
    def trained_anchors(self) -> bool:
        """Whether it learnt to correct JDC anchors (MiLA stage 3)."""
        return self.jdc_anchor_rate > 0


KEEP_PROGRAMS = 16
_PROGRAMS: dict = {}  # compiled sampler programs of this process, least recently used first


class Tracker:
    """Sequential sampler calls, their seconds, and the peak device bytes: on GPU/TPU the
    device's own peak (``memory_stats``); on CPU the largest sum of live device arrays after a
    call plus the temporaries of the compiled program it ran (``memory_analysis``). ``notes``:
    what a strategy adds to ``report.json`` (the streaming buffer's size)."""

    def __init__(self):
        self.calls = 0
        self.peak_bytes = 0
        self.notes: dict = {}
        self._used: set = set()

    @property
    def programs(self) -> int:
        """Distinct programs this tracker's calls ran (one per function and input shapes)."""
        return len(self._used)

    def compiled(self, model: WindowModel, *args, fn=None, static=(), probe: bool = False):
        """``fn`` (default :func:`sample_window`, jitted with ``model`` and then ``static`` as
        static arguments) compiled for ``args``' shapes (arrays or ``jax.ShapeDtypeStruct``),
        once per shape and process (the last :data:`KEEP_PROGRAMS` are kept: a second run of a
        strategy compiles nothing). ``probe``: compiled to read its memory, not counted among the
        programs the run used."""
        fn = jitted_sample_window if fn is None else fn
        leaves, tree = jax.tree_util.tree_flatten(args)
        key = (fn, model, static, tree) + tuple((x.shape, str(x.dtype), getattr(x, "sharding", None)) for x in leaves)
        if not probe:
            self._used.add(key)
        if key in _PROGRAMS:
            _PROGRAMS[key] = _PROGRAMS.pop(key)  # most recently used last
        else:
            _PROGRAMS[key] = fn.lower(model, *static, *args).compile()
            while len(_PROGRAMS) > KEEP_PROGRAMS:
                _PROGRAMS.pop(next(iter(_PROGRAMS)))
        return _PROGRAMS[key]

    def call(self, model: WindowModel, *args, fn=None, static=()):
        """One sequential sampler call, ``fn(model, *static, *args)`` (default
        :func:`sample_window`); returns its output."""
        compiled = self.compiled(model, *args, fn=fn, static=static)
        out = jax.block_until_ready(compiled(*args))
        self.calls += 1
        self.observe(compiled)
        return out

    def observe(self, compiled=None):
        """Fold the current device memory (and ``compiled``'s temporaries) into the peak."""
        stats = [d.memory_stats() for d in jax.local_devices() if d.platform != "cpu"]
        stats = [s for s in stats if s and "peak_bytes_in_use" in s]
        if stats:
            self.peak_bytes = max(self.peak_bytes, sum(s["peak_bytes_in_use"] for s in stats))
            return
        temp = temp_bytes(compiled) if compiled is not None else 0
        self.peak_bytes = max(self.peak_bytes, live_device_bytes() + temp)


def _placement(mesh, shape):
    """Where an array of ``shape`` goes: its batch (axis 0) over the mesh's ``data``/``fsdp``
    axes when they divide it, else replicated (without a mesh: the default device)."""
    if mesh is None:
        return jax.sharding.SingleDeviceSharding(jax.devices()[0])
    divides = len(shape) and shape[0] % batch_shards(mesh) == 0
    return NamedSharding(mesh, P(batch_axes(mesh) or None) if divides else P())


def to_mesh(tree, mesh):
    """Host arrays -> device arrays with the batch (axis 0) over the mesh's ``data``/``fsdp`` axes
    when it divides evenly, else replicated."""
    if mesh is None:
        return jax.tree_util.tree_map(jnp.asarray, tree)

    def put(x):
        x = np.asarray(x)
        return jax.device_put(x, _placement(mesh, x.shape))

    return jax.tree_util.tree_map(put, tree)


def abstract_on_mesh(tree, mesh, *, batch: int = 1):
    """What :func:`to_mesh` would make of ``tree`` with every array's batch axis ``batch`` times
    as long, as shapes only (``jax.ShapeDtypeStruct``, same dtype and placement): to compile a
    call for a batch without building it."""

    def abstract(x):
        x = np.asarray(x)
        shape = (x.shape[0] * batch,) + x.shape[1:] if x.ndim else ()
        return jax.ShapeDtypeStruct(shape, jax.dtypes.canonicalize_dtype(x.dtype), sharding=_placement(mesh, shape))

    return jax.tree_util.tree_map(abstract, tree)


def pixel_frames(positions, temporal: int) -> np.ndarray:
    """The output pixel frames of the latent frames at ``positions``: the positions themselves for
    a frame-wise codec; ``1 + temporal (n - 1)`` frames from ``temporal * positions[0]`` for a
    contiguous window of a causal VAE (spaced positions need a frame-wise codec)."""
    pos = np.asarray(positions)
    if temporal == 1:
        return pos
    if not bool(np.all(np.diff(pos) == 1)):
        raise ValueError(
            f"positions: a pass over spaced frames needs a frame-wise codec (temporal compression 1), "
            f"got temporal compression {temporal}"
        )
    lo = int(pos[0]) * temporal
    return np.arange(lo, lo + 1 + temporal * (len(pos) - 1))


def controls_at(controls: Conditions, positions, temporal: int, *, fps_scale: float = 1.0) -> Conditions:
    """The conditions of the latent frames at ``positions`` (output positions at its own rate):
    per-frame fields taken at those frames (per pixel frame: ``1 + temporal (n - 1)`` frames of
    a contiguous window when ``temporal > 1``), ``fps`` divided by ``fps_scale`` (a pass that
    samples every S-th frame runs at 1 / S of the rate)."""
    frames = pixel_frames(positions, temporal)

    def take(name, value):
        value = np.asarray(value)
        if temporal > 1:
            return value[:, frames[0] : frames[-1] + 1]
        if value.shape[1] <= int(frames.max()):
            raise ValueError(
                f"controls.{name}: expected at least {int(frames.max()) + 1} frames for the "
                f"positions sampled, got {value.shape[1]}"
            )
        return value[:, frames]

    out = controls.per_frame(take)
    if fps_scale != 1.0 and out.fps is not None:
        out = out.replace(fps=np.asarray(out.fps, np.float32) / fps_scale)
    return out


def window_controls(
    model: WindowModel, horizon: Horizon, idx, controls: Conditions, *, fps_scale: float = 1.0, warp=None
) -> Conditions:
    """The conditions of ``model``'s window at horizon positions ``idx``: the per-frame controls
    there and, for a model trained with warps (LongDWM, ``controls.warp``), the window's frame
    ``warp.frame`` warped along its frames' poses (``warp``: a :class:`jaxdrive.generate.warps.WarpGuide`)."""
    ctrl = controls_at(controls, idx, model.temporal, fps_scale=fps_scale)
    if model.dit.config.controls.warp:
        source = horizon.latents[:, :, idx[warp.frame : warp.frame + 1]]
        ctrl = ctrl.replace(warp=warp.window(source, pixel_frames(idx, model.temporal)))
    return ctrl


def window_starts(total_frames: int, window: int, overlap: int) -> list[int]:
    """The first latent frame of each window of a rollout: 0, then each next window overlaps the
    last ``overlap`` generated frames, and the last one ends at ``total_frames``."""
    for name, value in (("total_frames", total_frames), ("window", window), ("overlap", overlap)):
        check_positive_int(name, value)
    if total_frames > window and overlap >= window:  # the windows would not advance
        raise ValueError(f"overlap: expected fewer than window = {window} frames, got {overlap}")
    starts, done = [0], window
    while done < total_frames:
        starts.append(min(done - overlap, total_frames - window))
        done = starts[-1] + window
    return starts


@dataclasses.dataclass
class Horizon:
    """The output clip's latents on the host, ``[B, V, T, h, w, C]``, and which frames hold a
    value (``known``): given frames, finished frames, and anchors or keyframes that a later pass
    conditions on."""

    latents: np.ndarray
    known: np.ndarray

    @classmethod
    def start(cls, first: np.ndarray, length: int) -> Horizon:
        first = np.asarray(first, np.float32)
        shape = first.shape[:2] + (length,) + first.shape[3:]
        latents = np.zeros(shape, np.float32)
        latents[:, :, : first.shape[2]] = first
        known = np.zeros(length, bool)
        known[: first.shape[2]] = True
        return cls(latents, known)

    def put(self, positions, values) -> None:
        self.latents[:, :, np.asarray(positions)] = np.asarray(values)
        self.known[np.asarray(positions)] = True


def sample_window(model: WindowModel, params, x_cond, cond_mask, controls: Conditions, key, anchor_mask=None):
    """One window ``[B, V, F', h, w, C]`` of ``model`` with ``params`` (pure; ``model`` is static
    under jit, its own ``params`` field is not read, so they stay a traced input): ``x_cond``
    holds the clean given frames where ``cond_mask [B, F']`` is set and, where ``anchor_mask`` is
    set, predicted anchors, which start at the JDC level ``g = jdc_slope * sigma_max`` by
    :func:`jaxdrive.flow.jdc_renoise` (MiLA [2503.15875v1] eq. 8-12) and are denoised jointly with the frames
    between them (their output is the corrected anchor). The per-frame schedule is
    :func:`jaxdrive.flow.frame_schedule`'s (TPD when the model trained with it, MiLA [2503.15875v1] eq. 13-14).
    ``controls.drop`` (``{condition: [B] bool}``) names the conditions guidance drops (against
    learned nulls: all at once for ``model.guidance``, one control at a time for
    ``model.control_guidance``) and its values are each clip's own drops: a clip whose value is
    True is sampled without that condition in every branch, so guidance leaves that clip's
    condition out rather than pushing along it (:func:`jaxdrive.generate.guidance.sampler_guidance`;
    all False: every clip guided). The sampled frames come out clipped to the latents'
    range (:meth:`WindowModel.in_range`); the given frames bit for bit as ``x_cond``. With
    ``model.warp_start`` below 1 and a warp in ``controls``, the generated frames start from
    their warp noised to that level and the schedule runs from it to 0
    (:func:`jaxdrive.flow.sampling_sigmas` with ``sigma_max=warp_start``)."""
    m = model.dit.config
    drop = controls.drop or {}
    cond = controls.replace(drop=None)
    if m.controls.cond_frames is not None:
        cond = cond.replace(cond_latents=x_cond, cond_mask=cond_mask)
        if model.given_noise > 0:  # as trained (GameNGen); the returned given frames stay clean
            k_given = jax.random.fold_in(key, 2)
            level = jnp.full((x_cond.shape[0],), model.given_noise, jnp.float32)
            noisy, cond_sigma = flow.noise_given_frames(
                x_cond, jax.random.normal(k_given, x_cond.shape, jnp.float32), cond_mask, level
            )
            cond = cond.replace(cond_latents=noisy, cond_sigma=cond_sigma)
    guidance = sampler_guidance(cond, drop, x_cond.shape[0], model.guidance, model.control_guidance)
    start = model.warp_start if controls.warp is not None else 1.0
    schedule = flow.frame_schedule(
        flow.sampling_sigmas(model.steps, shift=model.shift, sigma_max=start),
        cond_mask,
        anchor_mask=anchor_mask,
        tpd=model.tpd,
        omega=model.tpd_omega,
        anchor_slope=model.jdc_slope,
    )
    # the noise comes from ``key`` itself, as it always has (a strategy without anchors draws the
    # same windows as before anchors existed); the anchors' JDC noise from a key folded off it
    noise = jax.random.normal(key, x_cond.shape, jnp.float32)
    k_anchor = jax.random.fold_in(key, 1)
    keep = cond_mask[:, None, :, None, None, None]
    if start < 1.0:  # SDEdit (Meng et al. 2022, sec. 3) from the warp: x_s = (1 - s) warp + s noise
        noise = flow.add_noise(jnp.asarray(controls.warp, jnp.float32), noise, jnp.full(x_cond.shape[:1], start))
    x0 = jnp.where(keep, x_cond, noise)
    if anchor_mask is not None:
        anchors = anchor_mask[:, None, :, None, None, None]
        g0 = jnp.where(anchor_mask, schedule[0], 1.0)  # other frames: any legal level, unused
        x0 = jnp.where(anchors, flow.jdc_renoise(k_anchor, x_cond, g0, model.jdc_alpha1), x0)

    def velocity(x, sigma, c):
        out = model.dit.forward(params, x, sigma, c)
        return flow.velocity_from_output(out, x, sigma, m.prediction, m.prediction_min_sigma)

    out = flow.sample(velocity, x0, schedule, cond_mask=cond_mask, **guidance)
    return jnp.where(keep, out, model.in_range(out))


jitted_sample_window = jax.jit(sample_window, static_argnums=(0,))
