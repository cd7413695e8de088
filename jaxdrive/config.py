"""The one configuration schema of jaxdrive: typed dataclasses, built by python files in
``configs/`` and changed from the command line with ``--set a.b=value``.

A config file defines ``get_config() -> Config``. :func:`load_config` runs it and applies the
overrides; every override is checked against the schema before anything compiles: an unknown key
names the section and lists the keys it has, and a value that does not parse as the field's type
names the field, the type and the value.

The config argument (big_vision's convention): ``--config configs/x.py:size=tiny,stage=2`` passes
the text after the colon to ``get_config(arg)``; the file reads it with :func:`parse_arg`, which
checks the keys and converts the values to the types of its defaults. Files that take no argument
keep ``get_config()``.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib.util
import inspect
import os
import types
import typing
from pathlib import Path
from typing import Any

from jaxdrive.models.dit.config import DiTConfig
from jaxdrive.models.predictor import PredictorConfig
from jaxdrive.models.segmenter import SegmenterConfig


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Training clips from a TFDS dataset written by ``jaxdrive data synth`` / ``data nuscenes``."""

    path: str = "data/synth"
    split: str = "train"
    frames: int = 9  # pixel frames per clip, 1 + 4k for the 3D VAE
    height: int = 32
    width: int = 56
    views: int = 6  # the first V cameras in nuScenes order
    stride: int = 1  # frame stride when sampling a clip
    rate_head: int = 0  # mixed rates: the first frames of a clip at `stride` (condition frames)
    rate_strides: tuple[int, ...] = ()  # ... the rest at a stride drawn per clip from these; (): `stride` throughout
    batch_size: int = 2  # global batch; every process loads batch_size / processes
    drop_prob: float = 0.15  # classifier-free-guidance drop per condition
    shuffle_seed: int = 0
    threads: int = 0  # grain read threads (0: in the main thread)
    text_embeddings: str = ""  # .npz of 'jaxdrive data text-embed' (models with text='embeddings')
    # mixed resolution / length training (MagicDrive-V2 [2411.13807v3] appendix B): "HxWxF:batch[:prob[:repeat]]"
    # each, the batch global; F = 1 is an image bucket; repeat (default auto) repeats scarce clips
    # within an epoch (jaxdrive.data.pipeline). (): one bucket, height x width x frames at batch_size
    buckets: tuple[str, ...] = ()
    # LongDWM's warp-guided control (models with controls.warp): the one depth, in metres, at which
    # the first frame is warped along the clip's poses (jaxdrive.warp); beyond the clip's travel
    warp_depth: float = 20.0
    # ... warped from this frame of the sample / window: 0 (LongDWM: the first) or, with frame-wise
    # latents, the last given one (flow.cond_frames - 1: the world recipe, the freshest view)
    warp_frame: int = 0
    # counterfactual futures (jaxdrive.data.route_mix): each training scene read along one of the
    # routes it has, drawn per clip and epoch with these weights, "route" or "route:weight" each
    # (recorded: the train split; the others: 'jaxdrive data synth --counterfactuals'); (): recorded only
    routes: tuple[str, ...] = ()
    # the share of counterfactual samples whose window starts with all its given frames before the
    # routes part (the same past, different futures inside one window); 0: uniform starts, where most
    # windows of a 33-frame clip parting at frame 8 show a route already taken (jaxdrive.data.pipeline)
    route_parting: float = 0.0
    # an unreadable clip (corrupt or truncated ArrayRecord shard): False raises a ValueError naming the
    # shard file; True fills its slot with another clip of the shard's plan, logs the file once and
    # counts it (bad_records in metrics.jsonl; jaxdrive.data.pipeline says how)
    skip_bad_records: bool = False


@dataclasses.dataclass(frozen=True)
class LatentConfig:
    """Where the DiT's latents come from.

    ``"vae"``: a saved jaxdrive VAE (``vae_path``, see ``jaxdrive convert vae``), encoding on the
    fly in ``vae_mode`` (``"frame_wise"``: ``vae_frame_batch`` frames of every clip at a time, the
    VAE's ``frame_wise_batch``, which bounds the step's encoder temporaries; 0: all at once; in any
    mode ``vae_clip_batch`` clips of every device at a time, the VAE's ``clip_batch``).
    ``"space_to_depth"``: frame-wise pixel latents, each ``factor x factor`` patch folded into
    channels (exact and parameter-free: the CPU demo uses it so that it needs no VAE training).

    ``precomputed``: ``data.path`` holds latent windows written by ``jaxdrive data encode`` (the
    train step encodes nothing); the fields above still describe the codec that made them (it
    decodes samples) and must match what the dataset's metadata records."""

    source: str = "space_to_depth"
    vae_path: str = ""
    vae_mode: str = "chunked"
    vae_frame_batch: int = 0  # vae_mode frame_wise: frames of each clip encoded per step (0: all at once)
    vae_clip_batch: int = 0  # clips (x views) each device encodes per step, any mode (0: all at once)
    factor: int = 4
    scale: float = 1.0  # space_to_depth latents are multiplied by this (a VAE uses its scaling factor)
    precomputed: bool = False


@dataclasses.dataclass(frozen=True)
class FlowConfig:
    """Per-frame noise levels and losses of the rectified-flow step (``jaxdrive.flow``)."""

    sigma_sampling: str = "logit_normal"  # or "uniform"
    logit_loc: float = 0.0
    logit_scale: float = 1.0
    shift: float = 1.0  # SD3 / Open-Sora shift; 0: the resolution/length rule
    cond_frames: int = 1  # clean latent condition frames at the start (max)
    cond_frames_random: bool = True  # draw 0..cond_frames per clip (unconditional too)
    # GameNGen's noise on the given frames (jaxdrive.flow.noise_given_frames): in training a level
    # drawn per clip uniformly in [0, given_noise_max], at sampling given_noise_sample; the model
    # reads it as those frames' noise level (controls.cond_frames "replace")
    given_noise_max: float = 0.0
    given_noise_sample: float = 0.0
    # training windows whose given frames are the model's own output (jaxdrive.train.self_rollout):
    # the share of steps that train a rollout's second window, and the Euler steps of its first
    self_rollout_rate: float = 0.0
    self_rollout_steps: int = 4
    # the share of clips whose generated frames are noised from their warp instead of their future
    # (jaxdrive.flow.warp_path): the path sample.warp_start samples on; needs model.controls.warp
    warp_path_rate: float = 0.0
    tpd: bool = False  # MiLA's temporal progressive denoising levels
    tpd_omega: float = 1.5707963267948966
    patterns: tuple[str, ...] = ("prefix",)  # where given frames sit: prefix / ends / anchors (flow.patterns)
    pattern_rates: tuple[float, ...] = ()  # each pattern's share of the clips; empty: equal shares
    anchor_every: int = 0  # "anchors": an anchor every S frames from the last given one
    jdc_anchor_rate: float = 0.0  # fraction of clips whose anchor candidates are JDC anchors
    jdc_slope: float = 0.5
    jdc_alpha1: float = 0.1
    structure_weight: float = 0.0  # LongDWM's structure-preservation loss weight
    structure_cutoff: float = 0.25  # its high-pass cutoff, a fraction of Nyquist
    foreground_k: float = 0.0  # STAGE's W_aux foreground constant k; 0: no weighting
    foreground_c: float = 0.5  # STAGE's W_aux size exponent c
    distill_teacher: str = ""  # LongDWM fine-to-coarse distillation: the fine model's run dir
    distill_weight: float = 1.0  # weight of the distillation loss (eq. 8)
    distill_segment_len: int = 13  # K: frames per fine segment (eq. 7)
    distill_boundary: str = "mean"  # which prediction an interior coarse frame takes


@dataclasses.dataclass(frozen=True)
class StreamConfig:
    """STAGE's streaming, frame by frame (``jaxdrive.train.stream_step``, ``--strategy streaming``).

    With ``enabled`` every training example is one window ``[anchor, condition, new]`` (the first
    frame of the clip, the frame before the new one, the new one) cut from a clip of ``data.frames``
    latent frames; the HTFT buffer holds the last ``buffer`` frames' features and ``taps`` says which
    are fused (STAGE [2506.13138v1] sec. 4B: N = 10, S = {-1, -5, -10}); HTFT is on where the model has
    ``htft_layers`` and ``taps`` is not empty. ``self_rollout`` (stage 3) makes the condition frames
    the model's own streaming rollout of the clip (``rollout_steps`` sampling steps, once per clip),
    ``degrade_rate`` of them DCT low-passed to ``degrade_keep`` of their frequencies and all of them
    noised with std ``cond_noise`` (STAGE's augmentation)."""

    enabled: bool = False
    buffer: int = 10
    taps: tuple[int, ...] = (-1, -5, -10)
    self_rollout: bool = False
    rollout_steps: int = 4
    degrade_rate: float = 0.0
    degrade_keep: float = 0.5
    cond_noise: float = 0.0


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    """AdamW with warmup and a schedule, clipping, accumulation, EMA and partial training."""

    lr: float = 1e-4
    warmup_steps: int = 100
    schedule: str = "cosine"  # "cosine", "linear" or "constant" after warmup
    min_lr_ratio: float = 0.1
    weight_decay: float = 0.0
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    clip_norm: float = 1.0  # 0: no clipping
    grad_accum: int = 1  # micro-batches per update (data.batch_size split; a lax.scan in the step)
    ema_decay: float = 0.9999  # 0: no EMA
    trainable: tuple[str, ...] = ()  # regexes over "a/b/kernel" paths ("{last}": the last layer); empty: all


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    steps: int = 1000
    seed: int = 0
    log_every: int = 10
    checkpoint_every: int = 500
    keep_checkpoints: int = 3
    sample_every: int = 0  # 0: no periodic sample videos
    sample_steps: int = 20
    max_bad_steps: int = 5  # NaN/Inf losses in a row that stop the run
    # a checkpoint that cannot be written (disk full, lost mount): "continue" training (the next
    # save tries again) or "stop" with the previous checkpoint as the last one
    on_save_error: str = "continue"
    compute_dtype: str = "float32"  # bfloat16 on accelerators
    init_from: str = ""  # a run directory or diffusers folder to start from (train/init_from.py)
    init_from_ema: bool = True  # its EMA parameters (False: the raw ones)
    init_map: tuple[str, ...] = ()  # "regex=replacement" renames of the source's parameter paths
    # JAX's persistent compilation cache (jaxdrive.compile_cache): "default" (under the user's cache
    # directory), a folder, or "off"
    compile_cache: str = "default"


@dataclasses.dataclass(frozen=True)
class SampleConfig:
    """How the run's model is sampled unless the command line says otherwise (``jaxdrive sample``,
    ``eval`` and ``demo`` without ``--cfg``, and the training loop's periodic samples).

    ``cfg``: the classifier-free guidance scale, ``v = v_null + cfg (v_c - v_null)``
    (:mod:`jaxdrive.flow.sampler`): 1 is none (one forward per step), 0 the unconditional model,
    above 1 the controls amplified; each recipe in ``configs/`` sets its paper's value.

    ``warp_start``: the noise level a warp-guided model's generated frames start from, noised from
    their warp (SDEdit, Meng et al. 2022, sec. 3: ``x_s = (1 - s) warp + s noise``, then the flow
    from ``s`` to 0 in the run's sampler steps); 1 is pure noise, the warp only a condition."""

    cfg: float = 1.0
    warp_start: float = 1.0


@dataclasses.dataclass(frozen=True)
class MeshConfig:
    data: int = -1  # -1: the devices left over
    fsdp: int = 1
    seq: int = 1
    tensor: int = 1


@dataclasses.dataclass(frozen=True)
class Config:
    """A whole run: the DiT (``model``, e.g. a :func:`jaxdrive.models.dit.presets.preset`) and
    the sections above. ``--set model.depth=4`` and ``--set model.controls.fps=false`` work too."""

    model: DiTConfig = DiTConfig()
    data: DataConfig = DataConfig()
    latents: LatentConfig = LatentConfig()
    flow: FlowConfig = FlowConfig()
    optim: OptimConfig = OptimConfig()
    train: TrainConfig = TrainConfig()
    mesh: MeshConfig = MeshConfig()
    stream: StreamConfig = StreamConfig()
    sample: SampleConfig = SampleConfig()


@dataclasses.dataclass(frozen=True)
class PredictorRunConfig:
    """A predictor's training run (``jaxdrive train --config configs/predictor.py:size=tiny``):
    ``data`` reads ``path``, ``split``, ``batch_size`` (windows per step) and ``shuffle_seed``;
    the validation split, when there is one, gives ADE / FDE at the end of training."""

    predictor: PredictorConfig = PredictorConfig()
    data: DataConfig = DataConfig()
    optim: OptimConfig = OptimConfig()
    train: TrainConfig = TrainConfig()


@dataclasses.dataclass(frozen=True)
class SegmenterRunConfig:
    """A segmenter's training run (``jaxdrive train --config configs/segmenter.py:size=tiny``):
    ``data`` reads ``path``, ``split``, ``height`` x ``width`` (the DiT's frame size: the
    segmenter scores frames of that size), ``views``, ``stride`` (every n-th frame of a clip),
    ``batch_size`` (frames per step) and ``shuffle_seed``; the validation split, when there is
    one, gives the ceiling mIoU at the end of training."""

    segmenter: SegmenterConfig = SegmenterConfig()
    data: DataConfig = DataConfig()
    optim: OptimConfig = OptimConfig()
    train: TrainConfig = TrainConfig()


# ------------------------------------------------------------------------------------ overrides
def _field_types(cls) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _parse(name: str, text: str, tp) -> Any:
    """``text`` as a value of type ``tp`` (int, float, bool, str, tuples of those, optionals)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if text in ("None", "none", "null") and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _parse(name, text, arg)
            except ValueError as e:
                errors.append(str(e))
        raise ValueError(errors[0])
    if tp is bool:
        if text.lower() in ("true", "1", "yes"):
            return True
        if text.lower() in ("false", "0", "no"):
            return False
        raise ValueError(f"{name}: expected a bool (true/false), got {text!r}")
    if tp in (int, float):
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            value = None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (tp is int and not isinstance(value, int)):
            raise ValueError(f"{name}: expected {tp.__name__}, got {text!r}")
        return tp(value)
    if tp is str:
        return text
    if origin is tuple:
        inner = args[0] if args else str
        parts = [p.strip() for p in text.strip("()[] ").split(",") if p.strip()]
        return tuple(_parse(name, p, inner) for p in parts)
    raise ValueError(f"{name}: cannot be set from the command line (type {tp})")


def override(config, assignment: str):
    """``config`` with ``"a.b=value"`` applied (a new frozen dataclass; ``config`` is unchanged)."""
    if "=" not in assignment:
        raise ValueError(f"override: expected key=value, got {assignment!r}")
    key, text = assignment.split("=", 1)
    path = key.strip().split(".")

    def apply(node, prefix, rest):
        if not dataclasses.is_dataclass(node):
            raise ValueError(f"override {key}: {'.'.join(prefix) or 'config'} is not a section")
        fields = _field_types(type(node))
        if rest[0] not in fields:
            where = ".".join(prefix) or "config"
            raise ValueError(f"override {key}: unknown key {rest[0]!r} in {where}; expected one of {sorted(fields)}")
        name = ".".join(prefix + [rest[0]])
        if len(rest) == 1:
            value = _parse(name, text.strip(), fields[rest[0]])
        else:
            value = apply(getattr(node, rest[0]), prefix + [rest[0]], rest[1:])
        return dataclasses.replace(node, **{rest[0]: value})

    return apply(config, [], path)


def parse_arg(arg: str | None, **defaults) -> types.SimpleNamespace:
    """The config argument ``"key=value,..."`` as a namespace of ``defaults`` updated by it.

    Each value is parsed as the type of its default: ``bool`` (true/false; a bare ``key`` is
    true), ``int``, ``float``, ``str``, or a string or None where the default is None. Values
    cannot hold commas. ``arg`` None or empty gives the defaults. An unknown key, a repeated key
    or a value of the wrong type raises ``ValueError`` naming the key::

        def get_config(arg=None):
            a = parse_arg(arg, size="small", stage=1)      # "size=tiny,stage=2"
    """
    for key, default in defaults.items():
        if default is not None and type(default) not in (bool, int, float, str):
            raise ValueError(
                f"parse_arg: default of {key!r}: expected a bool, int, float, str or None, got {type(default).__name__}"
            )
    if arg is not None and not isinstance(arg, str):
        raise ValueError(f"config argument: expected a string key=value,..., got {type(arg).__name__}")
    values, given = dict(defaults), set()
    for item in (arg or "").split(","):
        if not item.strip():
            continue
        key, eq, text = (part.strip() for part in item.partition("="))
        if key not in defaults:
            raise ValueError(f"config argument: unknown key {key!r}; expected one of {sorted(defaults)}, got {arg!r}")
        if key in given:
            raise ValueError(f"config argument: key {key!r} given twice in {arg!r}")
        given.add(key)
        default = defaults[key]
        if not eq and type(default) is not bool:
            raise ValueError(f"config argument {key}: expected {key}=value, got {item.strip()!r}")
        tp = str | None if default is None else type(default)
        values[key] = _parse(f"config argument {key}", text, tp) if eq else True
    return types.SimpleNamespace(**values)


def check_arg(key: str, value, choices) -> None:
    """``ValueError`` unless the config argument ``key`` is one of ``choices`` (a config's
    ``get_config`` after :func:`parse_arg`)."""
    if value not in choices:
        want = (
            ", ".join(repr(c) for c in choices[:-1]) + f" or {choices[-1]!r}" if len(choices) > 1 else repr(choices[0])
        )
        raise ValueError(f"config argument {key}: expected {want}, got {value!r}")


def split_config_path(spec) -> tuple[Path, str | None]:
    """``"configs/x.py:a=1,b=2"`` -> ``(Path("configs/x.py"), "a=1,b=2")``; a path without an
    argument gives ``(path, None)``. The argument starts at the first colon after ``.py``, so its
    values may hold colons (``data=gs://...``)."""
    if not isinstance(spec, (str, os.PathLike)):
        raise ValueError(f"config: expected a path FILE.py[:key=value,...], got {type(spec).__name__}")
    text = os.fspath(spec)
    cut = text.find(".py:")
    return (Path(text), None) if cut < 0 else (Path(text[: cut + 3]), text[cut + 4 :])


def load_config(path, overrides=()):
    """Run the config file ``path`` and apply ``overrides`` (``"a.b=v"``). ``path`` is
    ``FILE.py`` (``get_config()``) or ``FILE.py:ARG`` (``get_config(ARG)``, module docstring)."""
    path, arg = split_config_path(path)
    if not path.is_file():
        raise ValueError(f"config: expected a python config file, got {str(path)!r} (not found)")
    spec = importlib.util.spec_from_file_location(f"jaxdrive_config_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if not hasattr(module, "get_config"):
        raise ValueError(f"{path}: expected a function get_config() returning the config")
    params = list(inspect.signature(module.get_config).parameters.values())
    if arg is None:
        if params and params[0].default is inspect.Parameter.empty:
            raise ValueError(
                f"config: expected {path}:key=value,... (its get_config takes an argument), got {str(path)!r}"
            )
        config = module.get_config()
    else:
        if not params:
            raise ValueError(
                f"config: expected {str(path)!r} without ':...' (its get_config() takes no "
                f"argument), got the argument {arg!r}"
            )
        config = module.get_config(arg)
    for assignment in overrides:
        config = override(config, assignment)
    return config


def to_dict(config) -> dict:
    """The config as plain JSON-able data (saved next to checkpoints)."""
    return dataclasses.asdict(config)


def from_dict(cls, data: dict):
    """Inverse of :func:`to_dict`: nested dataclasses from plain data (lists become tuples)."""
    hints = _field_types(cls)
    kwargs = {}
    for name, value in data.items():
        if name not in hints:
            raise ValueError(f"config: unknown key {name!r} in {cls.__name__}; expected one of {sorted(hints)}")
        tp = hints[name]
        if dataclasses.is_dataclass(tp) and isinstance(value, dict):
            value = from_dict(tp, value)
        elif isinstance(value, list):
            value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
        kwargs[name] = value
    return cls(**kwargs)
