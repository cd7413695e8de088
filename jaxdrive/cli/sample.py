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
    """The ``--strategy`` path of ``jaxdrive sample`` (module docstring): the flags as
    :meth:`jaxdrive.world_model.WorldModel.generate`'s arguments, whose errors name them."""
    from jaxdrive.generate.strategies import NEEDS_FINE, STRATEGIES
    from jaxdrive.validate import check_choice, check_positive_int

    check_choice("--strategy", args.strategy, STRATEGIES)
    if args.strategy in NEEDS_FINE and not args.fine_workdir:
        raise ValueError(f"--fine-workdir: strategy {args.strategy!r} needs a fine model run, got none")
    if args.frames is None:
        raise ValueError("--frames: expected the number of frames to generate with --strategy, got none")
    check_positive_int("--frames", args.frames)
    options = {
        "anchor_every": args.anchor_every,
        "segment_batch": args.segment_batch,
        "overlap": args.overlap,
        "taps": parse_taps(args.taps),
        "device_memory": args.device_memory,
    }
    if args.controls == "predicted" and not args.predictor:
        raise ValueError("--controls: 'predicted' needs --predictor RUN (a run of configs/predictor.py), got none")
    model = load_model(args, weights=False)
    sizes = dict(zip(model.mesh.axis_names, model.mesh.axis_sizes))
    clips = sizes.get("data", 1) * sizes.get("fsdp", 1) if args.clips is None else args.clips
    out = Path(args.out or Path(args.workdir) / "samples" / args.strategy)
    request = dict(
        frames=args.frames,
        strategy=args.strategy,
        route=args.route,
        cfg=args.cfg,
        cfg_boxes=args.cfg_boxes,
        cfg_route=args.cfg_route,
        key=args.seed,
        clips=clips,
        views=None if args.views is None else [int(v) for v in args.views],
        steps=args.steps,
        cond_frames=args.cond_frames,
        predictor=args.predictor,
        controls=args.controls,
        allow_off_road=args.allow_off_road,
        **{k: v for k, v in options.items() if v is not None},
    )
    model.check(None, **{k: v for k, v in request.items() if k not in ("key", "views", "steps")})
    # None: the validation split, else the training one; the weights are read after every check
    report = model.with_weights().generate(None, **request, out=out, keep_video=False).report
    print(
        f"report: {out / 'report.json'} ({report['sequential_sampler_calls']} sequential sampler calls, "
        f"{report['seconds']:.1f} s, peak device memory {report['peak_device_bytes'] / 2**20:.1f} MiB)"
    )
    return 0


def load_model(args, *, weights: bool = True):
    """The :class:`jaxdrive.world_model.WorldModel` of ``--workdir`` (and ``--fine-workdir``),
    ``--mesh`` and ``--set`` (EMA weights unless ``--no-ema``; ``weights=False``: none yet)."""
    from jaxdrive.world_model import WorldModel

    return WorldModel.from_run(
        args.workdir,
        ema=not args.no_ema,
        fine_workdir=args.fine_workdir or None,
        mesh=args.mesh,
        overrides=args.set or [],
        weights=weights,
    )


def load_runs(args):
    """What ``jaxdrive eval`` needs of ``--workdir`` (and ``--fine-workdir``): ``(model, spec,
    fine_spec, load_main, load_fine, shapes, length)``: the :class:`jaxdrive.world_model.WorldModel`
    (its ``mesh``), each run's :class:`jaxdrive.generate.samples.Sampling`, the window models'
    loaders, their shapes (what every check needs, no parameter read) and the latent frames of
    ``--frames``. Guidance: ``--cfg`` (None: each run's ``sample.cfg``), ``--cfg-boxes``,
    ``--cfg-route``, checked against both runs here."""
    from jaxdrive.generate.strategies import Models

    model = load_model(args, weights=False)
    guidance = dict(steps=args.steps, cfg=args.cfg, cfg_boxes=args.cfg_boxes, cfg_route=args.cfg_route)
    fine = model.fine
    shapes = Models(model.window_model(params=False, **guidance), fine and fine.window_model(params=False, **guidance))
    horizon = (fine or model).spec
    if horizon.codec.temporal > 1 and (args.frames - 1) % horizon.codec.temporal:
        raise ValueError(
            f"--frames: expected 1 + {horizon.codec.temporal}k frames for the causal VAE, got {args.frames}"
        )
    loaded: list = []  # the weights, read once when the first loader asks (every check comes before)
    weighted = lambda: loaded[0] if loaded else loaded.append(model.with_weights()) or loaded[0]
    load_main = lambda: weighted().window_model(**guidance)
    load_fine = (lambda: weighted().fine.window_model(**guidance)) if fine is not None else None
    spec = model.spec
    return (
        model,
        spec,
        None if fine is None else fine.spec,
        load_main,
        load_fine,
        shapes,
        horizon.codec.latent_frames(args.frames),
    )
