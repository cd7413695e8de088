"""``jaxdrive sample --strategy NAME``: a long video from one run (or a coarse and a fine run).

    jaxdrive sample --workdir RUN [--fine-workdir RUN2] --strategy {rollout, coarse-to-refine,
                    coarse-fine, window, streaming} --frames N [--taps=-1,-5,-10] --out DIR

Loads each run's latest checkpoint (EMA parameters unless ``--no-ema``), takes the first frames
and the per-frame controls of a dataset clip at the output rate (the fine run's dataset and frame
stride when one is given, else the run's own) and writes what
:func:`jaxdrive.generate.long_video.sample_long` writes. Every check that can fail does so before
anything compiles.
"""

from __future__ import annotations

from pathlib import Path


def _load(workdir, sets, mesh, *, role: str):
    from jaxdrive.cli.options import config_with_mesh
    from jaxdrive.config import override
    from jaxdrive.train.run import Run, load_run_config

    if not (Path(workdir) / "config.json").is_file():
        raise ValueError(f"{role}: expected a run directory with config.json, got {str(workdir)!r}")
    config = load_run_config(workdir)
    for s in sets or []:
        config = override(config, s)
    config = config_with_mesh(config, mesh) if mesh else config
    run = Run(config)
    return run, run.sampling()


def load_runs(args):
    """The runs of ``--workdir`` (and ``--fine-workdir``) for a strategy: ``(run, spec, fine_spec,
    load_main, load_fine, shapes, length)``; ``shapes`` are the :class:`Models` known from the
    configs alone (what every check needs, before any parameter is read), ``length`` the latent
    frames of ``--frames``. Guidance: ``--cfg`` (None: each run's ``sample.cfg``), ``--cfg-boxes``,
    ``--cfg-route``, checked against both runs here."""
    from jaxdrive.cli.options import guidance_options
    from jaxdrive.generate.strategies import Models
    from jaxdrive.generate.windows import WindowModel
    from jaxdrive.train.run import restore_params

    ema = not args.no_ema
    run, spec = _load(args.workdir, args.set, args.mesh, role="--workdir")
    from jaxdrive import compile_cache

    compile_cache.enable(run.config.train.compile_cache)  # the run's own setting (default: on)
    fine_run = fine_spec = load_fine = None
    if args.fine_workdir:
        fine_run, fine_spec = _load(args.fine_workdir, args.set, args.mesh, role="--fine-workdir")
        for name in ("channels", "spatial", "temporal"):
            a, b = getattr(spec.codec, name), getattr(fine_spec.codec, name)
            if a != b:
                raise ValueError(f"--fine-workdir: expected latents like --workdir's ({name} {a}), got {name} {b}")
    controls = guidance_options(args, (spec, fine_spec))

    def model(s, r=None, workdir=None, option="workdir"):
        params = None if r is None else restore_params(r, workdir, ema=ema, option=option)[1]
        return WindowModel.from_sampling(s, params, steps=args.steps, guidance=args.cfg, control_guidance=controls)

    load_main = lambda: model(spec, run, args.workdir)
    if fine_spec is not None:
        load_fine = lambda: model(fine_spec, fine_run, args.fine_workdir, "fine_workdir")
    horizon_spec = fine_spec or spec
    length = horizon_spec.codec.latent_frames(args.frames)
    if horizon_spec.codec.temporal > 1 and (args.frames - 1) % horizon_spec.codec.temporal:
        raise ValueError(
            f"--frames: expected 1 + {horizon_spec.codec.temporal}k frames for the causal VAE, got {args.frames}"
        )
    shapes = Models(model(spec), model(fine_spec) if fine_spec else None)
    return run, spec, fine_spec, load_main, load_fine, shapes, length


def first_latents(inputs, codec, window: int, given: int):
    """The ``given`` latent frames every strategy starts from: the stored latents of a precomputed
    dataset, else the clip's first pixel frames encoded (a whole window, for a causal VAE)."""
    import numpy as np

    if "latents" in inputs:
        return np.asarray(inputs["latents"])[:, :, :given]
    pixels = np.asarray(inputs["video"])[:, :, : codec.pixel_frames(max(window, given))]
    return np.asarray(codec.encode(codec.params, pixels))[:, :, :given]


def parse_taps(text):
    """``--taps``: ``"-1,-5,-10"`` -> ``(-1, -5, -10)``; ``"none"`` -> ``()``; None stays None."""
    if text is None:
        return None
    if text.strip().lower() in ("none", ""):
        return ()
    try:
        return tuple(int(t) for t in text.split(","))
    except ValueError:
        raise ValueError(
            f"--taps: expected comma-separated negative offsets like -1,-5,-10 (or none), got {text!r}"
        ) from None


def sample_strategy(args) -> int:
    """The ``--strategy`` path of ``jaxdrive sample`` (module docstring)."""
    import jax
    import numpy as np

    from jaxdrive.generate.long_video import sample_long
    from jaxdrive.generate.samples import dataset_inputs
    from jaxdrive.generate.strategies import NEEDS_FINE, STRATEGIES, Models, check_strategy, check_taps
    from jaxdrive.validate import check_choice, check_positive_int

    check_choice("--strategy", args.strategy, STRATEGIES)
    if args.strategy in NEEDS_FINE and not args.fine_workdir:
        raise ValueError(f"--fine-workdir: strategy {args.strategy!r} needs a fine model run, got none")
    if args.frames is None:
        raise ValueError("--frames: expected the number of frames to generate with --strategy, got none")
    check_positive_int("--frames", args.frames)
    run, spec, fine_spec, load_main, load_fine, shapes, length = load_runs(args)
    horizon_spec = fine_spec or spec
    given = shapes.main.cond_frames if args.cond_frames is None else args.cond_frames
    if args.strategy == "coarse-fine":
        given = min(given, shapes.fine.window - 1)
    check_strategy(args.strategy, shapes, length, given)
    options = {
        "anchor_every": args.anchor_every,
        "segment_batch": args.segment_batch,
        "overlap": args.overlap,
        "taps": parse_taps(args.taps),
        "device_memory": args.device_memory,
    }
    allowed = {
        "rollout": ("overlap",),
        "coarse-to-refine": ("overlap", "anchor_every"),
        "coarse-fine": ("segment_batch", "device_memory"),
        "window": (),
        "streaming": ("taps",),
    }[args.strategy]
    for name, value in options.items():
        if value is not None and name not in allowed:
            raise ValueError(
                f"--{name.replace('_', '-')}: not an option of strategy {args.strategy!r} "
                f"(its options: {', '.join('--' + a.replace('_', '-') for a in allowed)}), got {value}"
            )
    options = {k: v for k, v in options.items() if k in allowed}
    if args.strategy == "streaming":
        check_taps(shapes, options.get("taps"))
    if args.strategy == "coarse-fine":  # before anything loads or compiles
        from jaxdrive.generate.segments import check_segment_batch
        from jaxdrive.parallel.memory import parse_bytes

        options["segment_batch"] = check_segment_batch(options.get("segment_batch"))
        if options.get("device_memory") is not None:
            options["device_memory"] = parse_bytes(options["device_memory"])
    models = Models(load_main(), load_fine() if load_fine else None)
    views = None if args.views is None else [int(v) for v in args.views]
    sizes = dict(zip(run.mesh.axis_names, run.mesh.axis_sizes))
    shards = sizes.get("data", 1) * sizes.get("fsdp", 1)
    clips = shards if args.clips is None else check_positive_int("--clips", args.clips)
    if clips % shards:
        raise ValueError(f"--clips: expected a multiple of the mesh's data x fsdp size {shards}, got {clips}")
    check_choice("--controls", args.controls, ("recorded", "predicted"))
    predictor = None
    if args.predictor:
        from jaxdrive.train.predictor_run import load_future_predictor

        predictor = load_future_predictor(args.predictor, option="predictor")
    elif args.controls == "predicted":
        raise ValueError("--controls: 'predicted' needs --predictor RUN (a run of configs/predictor.py), got none")
    from jaxdrive.data.scene_map import bev_range_of
    from jaxdrive.data.tfds_io import dataset_info

    bev_range = bev_range_of(dataset_info(horizon_spec.data.path)["metadata"])
    if args.allow_off_road and not args.route:
        raise ValueError("--allow-off-road: expected with a --route file to drive off the road, got no --route")
    hook, routes, drives = None, {}, []
    if predictor is not None or args.route:
        hook = _controls_hook(args, bev_range, predictor, horizon_spec.codec.pixel_frames(given), routes, drives)
    inputs = dataset_inputs(
        horizon_spec, frames=args.frames, views=views, clips=clips, seed=args.seed, controls=hook, scene=True
    )
    scene = inputs.pop("scene")
    if drives:
        scene["route_drive"] = drives[0]  # the first clip's: the one sample.mp4 and frames.png show
    scene["cell"] = tuple(r / n for r, n in zip(bev_range, scene["bev_map"].shape[1:3]))
    codec = horizon_spec.codec
    first = first_latents(inputs, codec, models.main.window, given)
    if any(m is not None and m.dit.config.controls.warp for m in (shapes.main, shapes.fine)):
        from jaxdrive.generate.warps import WarpGuide  # LongDWM: each window's first frame warped

        options["warp"] = WarpGuide.from_inputs(inputs, codec, depth=horizon_spec.data.warp_depth)
    # a driven route is not the recorded clip: its frames are no reference to score against
    recorded = np.asarray(inputs["video"][0]) if "video" in inputs and not args.route else None
    fps = (
        float(np.asarray(inputs["cond"].fps)[0]) if inputs["cond"].fps is not None else 12.0 / horizon_spec.frame_stride
    )
    out = Path(args.out or Path(args.workdir) / "samples" / args.strategy)
    controls = {
        "mode": args.controls,
        "predictor": str(args.predictor) if args.predictor else None,
        "recorded_frames": scene["predicted_from"],
    }
    with jax.set_mesh(run.mesh):
        report = sample_long(
            args.strategy,
            models,
            codec,
            inputs["cond"],
            first,
            length,
            out,
            key=jax.random.key(args.seed),
            mesh=run.mesh,
            fps=fps,
            recorded=recorded,
            route=next(iter(routes.values())).source if routes else None,
            control_source=controls,
            scene=scene,
            **options,
        )
    print(
        f"report: {out / 'report.json'} ({report['sequential_sampler_calls']} sequential sampler calls, "
        f"{report['seconds']:.1f} s, peak device memory {report['peak_device_bytes'] / 2**20:.1f} MiB)"
    )
    return 0


def _controls_hook(args, bev_range, predictor, given_pixels: int, routes: dict, drives: list):
    """Each sampled clip's controls for ``--frames``: the route driven (``--route``, placed on and
    checked against the clip's scene map, ``--allow-off-road``), and the predictor's beyond the
    recorded frames (``--predictor``; from the given frames on with ``--controls predicted`` or a
    route). ``routes`` collects the routes loaded, by frame rate; ``drives`` each clip's
    ``route_drive`` (:func:`jaxdrive.generate.route.drive_on_map`). A route's warnings come once
    per run, not once per clip."""
    from jaxdrive.generate.future import future_controls
    from jaxdrive.generate.route import load_route

    warned = set()

    def hook(sample, clip, where):
        fps = float(sample["fps"])
        route = None
        if args.route:
            if fps not in routes:
                routes[fps] = load_route(args.route, duration=(args.frames - 1) / fps)
            route = routes[fps]
        have = len(sample["ego_to_world"])
        keep = have
        if predictor is not None and (args.controls == "predicted" or route is not None):
            keep = min(given_pixels, have)
        out = future_controls(
            sample,
            clip,
            frames=args.frames,
            keep=keep,
            predictor=predictor,
            route=route,
            bev_range=bev_range,
            where=where,
            allow_off_road=args.allow_off_road,
            warned=warned,
        )
        if "route_drive" in out:
            drives.append(out.pop("route_drive"))  # for report.json, not a model input
        return out

    return hook
