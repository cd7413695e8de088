"""A trained run, loaded for generation: the Python entry point under ``jaxdrive sample``,
``jaxdrive eval`` and ``jaxdrive demo``.

    wm = jaxdrive.WorldModel.from_run("jaxdrive-demo")            # EMA weights, codec, config
    g = wm.generate("validation", frames=33, strategy="rollout", route="left turn")
    g.video, g.latents, g.report                                  # [clips, V, F, H, W, 3] in [-1, 1]

:meth:`WorldModel.from_run` reads the run's ``config.json`` and the newest readable checkpoint's
weights (the EMA copy unless ``ema=False``) into the model's parameter shapes alone: no optimizer
moments, no training data pipeline, no train step. :meth:`WorldModel.generate` runs one of the
long-video strategies (:mod:`jaxdrive.generate.strategies`) from the given frames and per-frame
controls of dataset clips (a split's first clips, or clip records passed in), optionally along a
driven route, with classifier-free guidance per control, and returns the video, its latents and
the report; with ``out=DIR`` it also writes ``sample.mp4``, ``frames.png``, ``latents.npy`` and
``report.json`` there (:func:`jaxdrive.generate.long_video.sample_long`). Every check that can
fail does so before anything compiles, as a ``ValueError`` naming the argument.

A batch whose clips do not divide the mesh's batch shards (``data x fsdp``) is padded with
copies of its last clip, which are dropped from what comes back: one clip samples on any device
count.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import jax
import numpy as np

from jaxdrive.config import Config, override
from jaxdrive.config_checks import check_sections
from jaxdrive.generate.samples import Sampling
from jaxdrive.generate.strategies import NEEDS_FINE, STRATEGIES, Models, check_strategy, check_taps
from jaxdrive.generate.windows import WindowModel
from jaxdrive.models.latents import LatentCodec
from jaxdrive.train.common import (
    CONFIG_FILE,
    abstract_train_state,
    load_run_config,
    mesh_from_config,
    sampling_spec,
)
from jaxdrive.train.run import restore_latest_params
from jaxdrive.validate import check_choice, check_positive_int

logger = logging.getLogger(__name__)

# each strategy's own options (generate(..., **options)), as jaxdrive sample's flags name them
STRATEGY_OPTIONS = {
    "rollout": ("overlap",),
    "coarse-to-refine": ("overlap", "anchor_every"),
    "coarse-fine": ("segment_batch", "device_memory"),
    "window": (),
    "streaming": ("taps",),
}


@dataclasses.dataclass(frozen=True)
class Generation:
    """What :meth:`WorldModel.generate` returns: ``video [clips, V, F, H, W, 3]`` in [-1, 1]
    (None with ``keep_video=False``), ``latents [clips, V, F', h, w, C]``, the ``report`` (as
    ``report.json``: strategy, frames, sampler calls, seconds, peak device memory, guidance,
    quality against the recorded clip where there is one), ``recorded``: the dataset's own frames
    of the clips ``[clips, V, F, H, W, 3]`` (None along a driven route, which the log never drove)
    and ``out``: the folder written, if any."""

    video: np.ndarray | None
    latents: np.ndarray
    report: dict
    recorded: np.ndarray | None = None
    out: Path | None = None


def _check_run_dir(workdir, option: str, *, checkpoint: bool = True) -> Path:
    """``workdir`` as a run folder with its config and (``checkpoint``) at least one checkpoint,
    else a ``ValueError`` naming ``option``, the path and what is missing."""
    path = Path(workdir)
    if not path.is_dir():
        raise ValueError(f"{option}: expected a run directory, got {str(path)!r} (not a directory)")
    if not (path / CONFIG_FILE).is_file():
        raise ValueError(f"{option}: expected a run directory with {CONFIG_FILE}, got {str(path)!r} (no {CONFIG_FILE})")
    ckpts = path / "checkpoints"
    if checkpoint and (not ckpts.is_dir() or not any(p.name.isdigit() for p in ckpts.iterdir())):
        raise ValueError(
            f"{option}: expected a run directory with a checkpoint, got {str(path)!r} (nothing under {ckpts})"
        )
    return path


def _with_mesh(config: Config, mesh, devices):
    """``config`` with the mesh ``mesh`` (``"data=2,seq=4"``; None: the run's own when its size is
    the device count, else one device) and that mesh."""
    from jaxdrive.parallel import parse_mesh_spec

    devices = list(jax.devices() if devices is None else devices)
    if mesh is None:
        m = config.mesh
        size = int(np.prod([m.data, m.fsdp, m.seq, m.tensor]))
        if -1 in (m.data, m.fsdp, m.seq, m.tensor) or size == len(devices):
            return config, mesh_from_config(config, devices)
        logger.info("the run's mesh spans %d devices, this host has %d: sampling on one device", size, len(devices))
        mesh, devices = "data=1", devices[:1]
    sizes = parse_mesh_spec(mesh)
    for k in ("data", "fsdp", "seq", "tensor"):
        config = override(config, f"mesh.{k}={sizes.get(k, 1)}")
    return config, mesh_from_config(config, devices)


class WorldModel:
    """A run's model for generation: its :class:`jaxdrive.generate.samples.Sampling` (``spec``:
    the DiT's config, codec, mesh, dataset, flow settings), its parameters, the checkpoint step they
    come from, and optionally the fine model of LongDWM's coarse-fine strategy (``fine``)."""

    def __init__(
        self,
        config: Config,
        spec: Sampling,
        params,
        *,
        step: int,
        workdir=None,
        fine=None,
        ema: bool = True,
        option: str = "workdir",
    ):
        self.config, self.spec, self.params, self.step = config, spec, params, int(step)
        self.workdir = None if workdir is None else Path(workdir)
        self.fine, self.ema, self.option = fine, ema, option

    @classmethod
    def from_run(
        cls,
        workdir,
        *,
        ema: bool = True,
        fine_workdir=None,
        mesh: str | None = None,
        overrides: Sequence[str] = (),
        devices=None,
        option: str = "workdir",
        weights: bool = True,
    ) -> WorldModel:
        """The newest readable checkpoint of the run in ``workdir`` (its EMA weights unless ``ema``
        is False), its codec and config. ``fine_workdir``: the fine model's run (coarse-fine; an
        optional (Re)fine model of coarse-to-refine), on the same latents. ``mesh``: a spec such as
        ``"data=2,seq=4"`` (default: the run's own mesh when it spans this host's devices, else
        one device); ``overrides``: ``a.b=value`` config changes (sampling settings such as
        ``train.sample_steps``). A folder without the run's config or a checkpoint is a
        ``ValueError`` naming the path and what is missing. ``weights=False`` reads the config
        alone (the parameters are None: what :meth:`check` needs; :meth:`with_weights` reads them)."""
        path = _check_run_dir(workdir, option, checkpoint=weights)
        config = load_run_config(path)
        for s in overrides:
            config = override(config, s)
        check_sections(config)  # each section's values, named by their keys (sample.cfg, ...)
        config, mesh_ = _with_mesh(config, mesh, devices)
        codec = LatentCodec.from_config(config.latents)
        spec = sampling_spec(config, mesh_, codec)
        fine = None
        if fine_workdir is not None:
            fine = cls.from_run(
                fine_workdir,
                ema=ema,
                mesh=mesh,
                overrides=overrides,
                devices=devices,
                option="fine_workdir",
                weights=weights,
            )
            for name in ("channels", "spatial", "temporal"):
                a, b = getattr(codec, name), getattr(fine.spec.codec, name)
                if a != b:
                    raise ValueError(f"fine_workdir: expected latents like workdir's ({name} {a}), got {name} {b}")
        from jaxdrive import compile_cache

        compile_cache.enable(config.train.compile_cache)  # the run's own setting (default: on)
        model = cls(config, spec, None, step=-1, workdir=path, fine=fine, ema=ema, option=option)
        return model.with_weights() if weights else model

    def with_weights(self) -> WorldModel:
        """This model with the newest readable checkpoint of its run (its fine model's too)."""
        path, c = _check_run_dir(self.workdir, self.option), self.config
        abstract, _ = abstract_train_state(self.spec.model, c.optim, c.train.steps, self.mesh, seed=c.train.seed)
        step, params = restore_latest_params(
            abstract, path, keep=c.train.keep_checkpoints, ema=self.ema, option=self.option
        )
        logger.info("loaded %s step %d (%s weights)", path, step, "EMA" if self.ema else "trained")
        fine = self.fine.with_weights() if self.fine is not None and self.fine.params is None else self.fine
        return WorldModel(c, self.spec, params, step=step, workdir=path, fine=fine, ema=self.ema, option=self.option)

    @property
    def mesh(self):
        return self.spec.mesh

    def window_model(self, *, steps=None, cfg=None, cfg_boxes=None, cfg_route=None, params: bool = True) -> WindowModel:
        """The :class:`jaxdrive.generate.windows.WindowModel` the strategies run (``params=False``:
        its shapes only, what the checks need). ``cfg`` None: the run's ``sample.cfg``."""
        controls = self.guidance_controls(cfg=cfg, cfg_boxes=cfg_boxes, cfg_route=cfg_route)
        return WindowModel.from_sampling(
            self.spec, self.params if params else None, steps=steps, guidance=cfg, control_guidance=controls
        )

    def guidance_controls(self, *, cfg=None, cfg_boxes=None, cfg_route=None) -> dict:
        """The per-control guidance scales, checked against this model and its fine one:
        ``cfg_boxes`` on a model trained without boxes is a ``ValueError`` naming ``cfg_boxes``."""
        from jaxdrive.generate.guidance import check_controls, check_scale

        if cfg is not None:
            check_scale("cfg", cfg)
        controls = {"boxes": cfg_boxes, "route": cfg_route}
        for model in (self, self.fine):
            if model is not None:
                check_controls(model.spec.model, model.spec.data.drop_prob, controls, option=lambda c: f"cfg_{c}")
        return {k: v for k, v in controls.items() if v is not None}

    def models(self, **guidance) -> Models:
        """The :class:`jaxdrive.generate.strategies.Models` of this model (and its fine one)."""
        fine = None if self.fine is None else self.fine.window_model(**guidance)
        return Models(self.window_model(**guidance), fine)

    def generate(
        self,
        source=None,
        *,
        frames: int,
        strategy: str = "rollout",
        route=None,
        cfg: float | None = None,
        cfg_boxes: float | None = None,
        cfg_route: float | None = None,
        key=0,
        clips: int = 1,
        views=None,
        steps: int | None = None,
        cond_frames: int | None = None,
        predictor=None,
        controls: str = "recorded",
        allow_off_road: bool = False,
        out=None,
        keep_video: bool = True,
        **options,
    ) -> Generation:
        """``clips`` clips of ``frames`` pixel frames by ``strategy`` (one of
        :data:`jaxdrive.generate.strategies.STRATEGIES`), each continuing a clip of ``source``: a
        split name of the run's dataset (its first ``clips`` clips; None: the validation split,
        else the training one), or one clip record or a list
        of them (a dataset's records, as :func:`jaxdrive.data.synthetic.generate_clip` makes).
        ``route``: drive a manoeuvre (``"left turn"``, ``"right turn"``, ``"stop"``,
        ``"straight 10m/s"``) or a JSON / CSV route file instead of the recorded route
        (``allow_off_road``: a file may leave the road). ``cfg``: classifier-free guidance (None:
        the run's ``sample.cfg``), ``cfg_boxes`` / ``cfg_route``: those controls' own scales.
        ``key``: a ``jax.random`` key or an int seed. ``predictor``: a run of
        ``configs/predictor.py`` for the controls beyond the log (``controls="predicted"``: from
        the given frames on). ``options``: the strategy's own (:data:`STRATEGY_OPTIONS`: ``overlap``,
        ``anchor_every``, ``segment_batch``, ``device_memory``, ``taps``). ``out``: also write the
        files of :func:`jaxdrive.generate.long_video.sample_long` there."""
        from jaxdrive.generate.long_video import long_video

        plan = self.check(
            source,
            frames=frames,
            strategy=strategy,
            route=route,
            cfg=cfg,
            cfg_boxes=cfg_boxes,
            cfg_route=cfg_route,
            clips=clips,
            cond_frames=cond_frames,
            predictor=predictor,
            controls=controls,
            allow_off_road=allow_off_road,
            **options,
        )
        if self.params is None:
            raise ValueError("params: expected a model with its weights (from_run, or with_weights()), got none")
        models = self.models(steps=steps, cfg=cfg, cfg_boxes=cfg_boxes, cfg_route=cfg_route)
        run_options = self._strategy_options(strategy, models, options)
        spec = plan["spec"]
        padded = -(-clips // plan["shards"]) * plan["shards"]
        inputs, scene, routes = self._inputs(source, spec, frames, clips, padded, views, plan, key)
        codec = spec.codec
        first = first_latents(inputs, codec, models.main.window, plan["given"])
        from jaxdrive.generate.warps import warp_options  # LongDWM: each window's own frame warped

        run_options.update(warp_options(models, inputs, codec, depth=spec.data.warp_depth, frame=spec.data.warp_frame))
        # a driven route is not the recorded clip: its frames are no reference to score against
        recorded = np.asarray(inputs["video"]) if "video" in inputs and route is None else None
        fps = float(np.asarray(inputs["cond"].fps)[0]) if inputs["cond"].fps is not None else 12.0 / spec.frame_stride
        source_note = {
            "mode": controls,
            "predictor": None if predictor is None else str(predictor),
            "recorded_frames": scene["predicted_from"],
        }
        key = jax.random.key(key) if isinstance(key, int) else key
        with jax.set_mesh(self.mesh):
            report, latents, video = long_video(
                strategy,
                models,
                codec,
                inputs["cond"],
                first,
                plan["length"],
                out,
                key=key,
                mesh=self.mesh,
                fps=fps,
                recorded=None if recorded is None else recorded[0],
                route=next(iter(routes.values())).source if routes else None,
                control_source=source_note,
                scene=scene,
                keep=clips,
                keep_video=keep_video,
                **run_options,
            )
        if padded != clips:
            report["padded_clips"] = padded - clips
        return Generation(
            video,
            latents,
            report,
            None if recorded is None else recorded[:clips],
            None if out is None else Path(out),
        )

    def check(
        self,
        source=None,
        *,
        frames: int,
        strategy: str = "rollout",
        route=None,
        cfg=None,
        cfg_boxes=None,
        cfg_route=None,
        clips: int = 1,
        cond_frames=None,
        predictor=None,
        controls: str = "recorded",
        allow_off_road: bool = False,
        **options,
    ) -> dict:
        """Every check of :meth:`generate` that reads neither data nor weights: a ``ValueError``
        naming the argument (works on a model loaded with ``weights=False``)."""
        _source(source)
        plan = self._plan(strategy, frames, clips, cond_frames, options, controls, predictor, route, allow_off_road)
        self.guidance_controls(cfg=cfg, cfg_boxes=cfg_boxes, cfg_route=cfg_route)
        return plan

    # ---------------------------------------------------------------- the steps of generate
    def _plan(self, strategy, frames, clips, cond_frames, options, controls, predictor, route, allow_off_road):
        """Every check of :meth:`generate` that needs no data and no compiling."""
        check_choice("strategy", strategy, STRATEGIES)
        if strategy in NEEDS_FINE and self.fine is None:
            raise ValueError(f"fine_workdir: strategy {strategy!r} needs a fine model run, got none")
        frames = check_positive_int("frames", frames)
        check_positive_int("clips", clips)
        check_choice("controls", controls, ("recorded", "predicted"))
        if controls == "predicted" and predictor is None:
            raise ValueError("controls: 'predicted' needs predictor= (a run of configs/predictor.py), got none")
        if allow_off_road and route is None:
            raise ValueError("allow_off_road: expected with a route file to drive off the road, got no route")
        allowed = STRATEGY_OPTIONS[strategy]
        for name, value in options.items():
            if name not in {n for names in STRATEGY_OPTIONS.values() for n in names}:
                raise ValueError(
                    f"options: expected names from {sorted(set(sum(STRATEGY_OPTIONS.values(), ())))}, got {name!r}"
                )
            if value is not None and name not in allowed:
                raise ValueError(
                    f"{name}: not an option of strategy {strategy!r} (its options: {', '.join(allowed) or 'none'}), "
                    f"got {value}"
                )
        if route is not None:
            from jaxdrive.generate.route import load_route

            load_route(route, duration=1.0)  # a name or a file that parses, before anything compiles
        spec = (self.fine or self).spec
        shapes = Models(
            self.window_model(params=False), None if self.fine is None else self.fine.window_model(params=False)
        )
        length = spec.codec.latent_frames(frames)
        if spec.codec.temporal > 1 and (frames - 1) % spec.codec.temporal:
            raise ValueError(f"frames: expected 1 + {spec.codec.temporal}k frames for the causal VAE, got {frames}")
        given = shapes.main.cond_frames if cond_frames is None else check_positive_int("cond_frames", cond_frames)
        if strategy == "coarse-fine":
            given = min(given, shapes.fine.window - 1)
        check_strategy(strategy, shapes, length, given)
        if strategy == "streaming":
            check_taps(shapes, options.get("taps"))
        sizes = dict(zip(self.mesh.axis_names, self.mesh.axis_sizes))
        return {
            "spec": spec,
            "length": length,
            "given": given,
            "shards": sizes.get("data", 1) * sizes.get("fsdp", 1),
            "frames": frames,
            "controls": controls,
            "predictor": predictor,
            "route": route,
            "allow_off_road": allow_off_road,
        }

    @staticmethod
    def _strategy_options(strategy, models, options) -> dict:
        out = {k: v for k, v in options.items() if k in STRATEGY_OPTIONS[strategy]}
        if strategy == "coarse-fine":
            from jaxdrive.generate.segments import check_segment_batch
            from jaxdrive.parallel.memory import parse_bytes

            out["segment_batch"] = check_segment_batch(out.get("segment_batch"))
            if out.get("device_memory") is not None:
                out["device_memory"] = parse_bytes(out["device_memory"])
        return out

    def _inputs(self, source, spec, frames, clips, padded, views, plan, key):
        """The model inputs of the clips (padded to ``padded`` with copies of the last), the first
        clip's scene (the frame grid's BEV panels) and the routes loaded, by frame rate."""
        from jaxdrive.data.scene_map import bev_range_of
        from jaxdrive.data.tfds_io import dataset_info
        from jaxdrive.generate.samples import dataset_inputs

        predictor = plan["predictor"]
        if isinstance(predictor, (str, Path)):
            from jaxdrive.train.predictor_run import load_future_predictor

            predictor = load_future_predictor(predictor, option="predictor")
        bev_range = bev_range_of(dataset_info(spec.data.path)["metadata"])
        routes, drives, hook = {}, [], None
        if predictor is not None or plan["route"] is not None:
            hook = controls_hook(plan, bev_range, predictor, spec.codec.pixel_frames(plan["given"]), routes, drives)
        split, records = _source(source)
        seed = key if isinstance(key, int) else 0
        indices = list(range(clips)) + [clips - 1] * (padded - clips)
        inputs = dataset_inputs(
            spec,
            frames=frames,
            views=views,
            clips=padded,
            seed=seed,
            controls=hook,
            scene=True,
            split=split,
            records=records,
            indices=indices,
        )
        scene = inputs.pop("scene")
        if drives:
            scene["route_drive"] = drives[0]  # the first clip's: the one sample.mp4 and frames.png show
        scene["cell"] = tuple(r / n for r, n in zip(bev_range, scene["bev_map"].shape[1:3]))
        return inputs, scene, routes


def _source(source):
    """``(split, records)`` of :meth:`WorldModel.generate`'s ``source``."""
    if source is None or isinstance(source, str):
        return source, None
    if isinstance(source, Mapping):
        return None, [source]
    if isinstance(source, Sequence) and source and all(isinstance(r, Mapping) for r in source):
        return None, list(source)
    raise ValueError(f"source: expected a split name, a clip record or a list of them, got {type(source).__name__}")


def first_latents(inputs, codec, window: int, given: int):
    """The ``given`` latent frames every strategy starts from: the stored latents of a precomputed
    dataset, else the clip's first pixel frames encoded (a whole window, for a causal VAE)."""
    if "latents" in inputs:
        return np.asarray(inputs["latents"])[:, :, :given]
    pixels = np.asarray(inputs["video"])[:, :, : codec.pixel_frames(max(window, given))]
    return np.asarray(codec.encode(codec.params, pixels))[:, :, :given]


def controls_hook(plan: dict, bev_range, predictor, given_pixels: int, routes: dict, drives: list):
    """Each sampled clip's controls for ``plan["frames"]``: the route driven (``plan["route"]``,
    placed on and checked against the clip's scene map, ``allow_off_road``), and the predictor's
    beyond the recorded frames (from the given frames on with ``controls="predicted"`` or a
    route). ``routes`` collects the routes loaded, by frame rate; ``drives`` each clip's
    ``route_drive`` (:func:`jaxdrive.generate.route.drive_on_map`). A route's warnings come once
    per call, not once per clip."""
    from jaxdrive.generate.future import future_controls
    from jaxdrive.generate.route import load_route

    warned: set = set()
    frames, route_spec = plan["frames"], plan["route"]

    def hook(sample, clip, where):
        fps = float(sample["fps"])
        route = None
        if route_spec is not None:
            if fps not in routes:
                routes[fps] = load_route(route_spec, duration=(frames - 1) / fps)
            route = routes[fps]
        have = len(sample["ego_to_world"])
        keep = have
        if predictor is not None and (plan["controls"] == "predicted" or route is not None):
            keep = min(given_pixels, have)
        out = future_controls(
            sample,
            clip,
            frames=frames,
            keep=keep,
            predictor=predictor,
            route=route,
            bev_range=bev_range,
            where=where,
            allow_off_road=plan["allow_off_road"],
            warned=warned,
        )
        if "route_drive" in out:
            drives.append(out.pop("route_drive"))  # for the report, not a model input
        return out

    return hook
