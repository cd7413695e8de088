"""``jaxdrive eval``: long-video strategies on the same validation clips, scored side by side.

    jaxdrive eval --workdir RUN [--fine-workdir RUN2] --strategies rollout,coarse-to-refine,...
                  --clips N --frames F [--buckets 2-12,13-24] [--inception FILE] [--i3d FILE]
                  [--segmenter RUN [--shuffle-boxes]] [--cfg 1,2,4] [--cfg-boxes S] [--cfg-route S] --out DIR
    jaxdrive eval --videos DIR --data PATH [...] --out DIR      # a folder of generated mp4s
    jaxdrive eval --merge OUT1,OUT2,... --out DIR               # strategies of different models, one table

Every strategy starts from the same given frames and controls of the first N clips of the
validation split (:mod:`jaxdrive.eval.compare` scores them): PSNR / SSIM per horizon bucket
always, FID per view and over all views with ``--inception``, FVD on 16-frame windows with
``--i3d``, controllability (the segmenter's mIoU against the class masks of the conditioning
boxes, and on the recorded frames, its ceiling) with ``--segmenter``. Writes ``DIR/eval.json``,
``DIR/eval.md`` and ``DIR/quality_vs_horizon.png`` and prints the table. Guidance: each run's
``sample.cfg`` unless ``--cfg`` gives scales; several (``--cfg 1,2,4``) score every strategy at
each, in rows named ``STRATEGY@cfgS``; ``--cfg-boxes`` / ``--cfg-route`` add those controls' own
scales (:mod:`jaxdrive.generate.guidance`); every row records its ``guidance``. Every check that
can fail does so before anything compiles.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path


def _eval(args, rest) -> int:
    if args.merge:
        return _merge(args)
    if bool(args.videos) == bool(args.workdir):
        raise ValueError(
            f"--workdir / --videos: expected one of them (a run to sample, or a folder of generated "
            f"mp4s), got {'both' if args.videos else 'neither'}"
        )
    from jaxdrive.cli.options import start_jax

    start_jax()
    if args.videos:
        return _eval_videos(args)
    return _eval_runs(args)


def _merge(args) -> int:
    """``--merge OUT1,OUT2,...``: the tables of several evaluations as one."""
    from jaxdrive.eval.compare import merge, write_outputs

    dirs = [d for d in args.merge.split(",") if d]
    if args.workdir or args.videos or len(dirs) < 2:
        raise ValueError(
            f"--merge: expected at least 2 output folders of jaxdrive eval, without --workdir or "
            f"--videos, got {args.merge!r}"
        )
    results, meta, ceiling, effects = merge(dirs)
    following = meta.pop("route_following_ceiling", None)
    paths = write_outputs(
        results, Path(args.out), meta=meta, ceiling=ceiling, effects=effects or None, following=following
    )
    print(paths["table"])
    print(f"wrote {paths['json']}, {paths['md']}, {paths['plot']}")
    return 0


def _eval_runs(args) -> int:
    """``--workdir``: the strategies of one run (or a coarse and a fine run), on the same clips."""
    from jaxdrive.cli.options import parse_scales
    from jaxdrive.cli.sample import load_runs
    from jaxdrive.eval.compare import parse_buckets
    from jaxdrive.generate.strategies import NEEDS_FINE, STRATEGIES, check_strategy
    from jaxdrive.validate import check_positive_int

    names = [s.strip() for s in args.strategies.split(",") if s.strip()]
    for name in names:
        if name not in STRATEGIES:
            raise ValueError(f"--strategies: expected names from {', '.join(STRATEGIES)}, got {name!r}")
        if name in NEEDS_FINE and not args.fine_workdir:
            raise ValueError(f"--fine-workdir: strategy {name!r} needs a fine model run, got none")
    if not names:
        raise ValueError(
            f"--strategies: expected a comma-separated list from {', '.join(STRATEGIES)}, got {args.strategies!r}"
        )
    if args.frames is None:
        raise ValueError(
            "--frames: required with --workdir (the pixel frames per clip to generate and score), got none"
        )
    check_positive_int("--frames", args.frames)
    scales = parse_scales(args.cfg)
    args.cfg = None  # the models load with their runs' sample.cfg; the sweep sets each
    clips = check_positive_int("--clips", args.clips)
    _check_common(args, clips)
    if args.ego_motion and not args.routes:
        raise ValueError(
            "--ego-motion: expected --routes (the estimated path is scored against each route's "
            "commanded one), got none"
        )
    if args.routes:
        from jaxdrive.eval.routes import parse_routes

        args.routes = parse_routes(args.routes)
        for option, value in (("--shuffle-boxes", args.shuffle_boxes), ("--split", args.split)):
            if value:
                raise ValueError(
                    f"{option}: expected none with --routes (each route has its own boxes; the routes "
                    f"are the validation clips'), got {value!r}"
                )
        if len(scales) > 1:
            raise ValueError(
                f"--cfg: expected one guidance scale with --routes (a route effect compares one "
                f"model's generations), got {len(scales)}"
            )
    args.cond_frames = None
    run, spec, fine_spec, load_main, load_fine, shapes, length = load_runs(args)
    horizon_spec = fine_spec or spec
    given = shapes.main.cond_frames
    if "coarse-fine" in names:
        given = min(given, shapes.fine.window - 1)  # one start for all: the smallest a strategy takes
    for name in names:
        check_strategy(name, shapes, length, given)
    sizes = dict(zip(run.mesh.axis_names, run.mesh.axis_sizes))
    shards = sizes.get("data", 1) * sizes.get("fsdp", 1)
    if clips % shards:
        raise ValueError(f"--clips: expected a multiple of the mesh's data x fsdp size {shards}, got {clips}")
    codec = horizon_spec.codec
    given_pixels = codec.pixel_frames(given)
    buckets = parse_buckets(args.buckets, given_pixels, args.frames)
    features = _feature_functions(args, run.mesh)
    segmenter = _load_segmenter(args, (horizon_spec.data.height, horizon_spec.data.width))
    if segmenter is not None and horizon_spec.precomputed:
        raise ValueError(
            "--segmenter: expected a run that reads clips (the class masks come from their instance "
            "ids), got one on precomputed latent windows"
        )
    if args.routes:
        return _eval_routes(
            args,
            names,
            run,
            horizon_spec,
            load_main,
            load_fine,
            codec,
            given,
            given_pixels,
            length,
            buckets,
            features,
            segmenter,
            clips,
            scales[0],
        )
    return _eval_recorded(
        args,
        names,
        run,
        horizon_spec,
        load_main,
        load_fine,
        codec,
        given,
        length,
        buckets,
        features,
        segmenter,
        clips,
        scales,
    )


def _eval_recorded(
    args,
    names,
    run,
    horizon_spec,
    load_main,
    load_fine,
    codec,
    given,
    length,
    buckets,
    features,
    segmenter,
    clips,
    scales,
) -> int:
    """Every strategy (at every ``--cfg`` scale) on the recorded clips, beside ``repeat``."""
    import jax
    import numpy as np

    from jaxdrive.eval.compare import repeat_baseline, repeat_name, run_strategies, write_outputs
    from jaxdrive.generate.guidance import describe
    from jaxdrive.generate.samples import dataset_inputs
    from jaxdrive.generate.strategies import Models
    from jaxdrive.generate.warps import warp_options
    from jaxdrive.world_model import first_latents

    given_pixels = codec.pixel_frames(given)
    try:
        inputs = dataset_inputs(
            horizon_spec,
            frames=args.frames,
            clips=clips,
            seed=args.seed,
            split=args.split,
            masks=segmenter is not None,
            shuffle_boxes=args.shuffle_boxes,
        )
    except ValueError as e:  # the clips are shorter than --frames (or the dataset is unreadable)
        raise ValueError(f"--{e}" if str(e).startswith("frames:") else f"--frames: {e}") from None
    models = Models(load_main(), load_fine() if load_fine else None)
    first = first_latents(inputs, codec, models.main.window, given)
    recorded = (
        np.asarray(inputs["video"])
        if "video" in inputs
        else np.asarray(codec.decode(codec.params, inputs["latents"][:, :, :length]))
    )
    ceiling = None
    if segmenter is not None:
        from jaxdrive.eval.compare import controllability

        features["segment"] = lambda frames: segmenter.classes(frames, mesh=run.mesh)
        features["masks"] = inputs.get("box_class_masks", inputs["class_masks"])
        ceiling = controllability(features["segment"], recorded, inputs["class_masks"], buckets)
    # a warp-guided model warps along the clips' recorded poses
    opts = warp_options(models, inputs, codec, depth=horizon_spec.data.warp_depth, frame=horizon_spec.data.warp_frame)
    out = Path(args.out)
    results = {}
    for scale in scales:
        guided = (
            models
            if scale is None
            else Models(
                *(None if m is None else dataclasses.replace(m, guidance=scale) for m in (models.main, models.fine))
            )
        )
        suffix = "" if len(scales) == 1 else f"@cfg{scale:g}"
        with jax.set_mesh(run.mesh):
            rows = run_strategies(
                {n: dict(opts) for n in names},
                guided,
                codec,
                inputs["cond"],
                first,
                length,
                recorded,
                buckets,
                key=jax.random.key(args.seed),
                mesh=run.mesh,
                **features,
            )
        for name, row in rows.items():
            results[name + suffix] = {**row, "guidance": describe(guided.main.guidance, guided.main.control_guidance)}
    results[repeat_name(given_pixels)] = repeat_baseline(recorded, given_pixels, buckets, **features)
    paths = write_outputs(
        results,
        out,
        ceiling=ceiling,
        meta=_meta(
            args,
            clips,
            given_pixels,
            int(recorded.shape[1]),
            shuffle_boxes=bool(args.shuffle_boxes),
            split=args.split,
            cfg=[models.main.guidance if s is None else s for s in scales],
        ),
    )
    print(paths["table"])
    print(f"wrote {paths['json']}, {paths['md']}, {paths['plot']}")
    return 0


def _eval_routes(
    args,
    names,
    run,
    spec,
    load_main,
    load_fine,
    codec,
    given,
    given_pixels,
    length,
    buckets,
    features,
    segmenter,
    clips,
    scale,
) -> int:
    """``--routes``: every strategy under every route, against each route's render
    (:mod:`jaxdrive.eval.routes`)."""
    import jax

    from jaxdrive.eval.compare import write_outputs
    from jaxdrive.eval.routes import evaluate_routes, route_clips
    from jaxdrive.generate.samples import dataset_inputs
    from jaxdrive.generate.strategies import Models
    from jaxdrive.world_model import first_latents

    if spec.precomputed:
        raise ValueError(
            "--routes: expected a run that reads clips (each route's controls come from its render), got "
            "one on precomputed latent windows"
        )
    plan = route_clips(spec.data.path, args.routes, clips, given_pixels, spec.frame_stride)

    def load_inputs(split, indices):
        try:
            return dataset_inputs(
                spec,
                frames=args.frames,
                clips=len(indices),
                seed=args.seed,
                split=split or "validation",
                indices=indices,
                poses=True,
                masks=segmenter is not None,
            )
        except ValueError as e:  # the clips are shorter than --frames
            raise ValueError(f"--{e}" if str(e).startswith("frames:") else f"--frames: {e}") from None

    models = Models(load_main(), load_fine() if load_fine else None)
    if scale is not None:  # --cfg; else each run's sample.cfg
        models = Models(
            *(None if m is None else dataclasses.replace(m, guidance=scale) for m in (models.main, models.fine))
        )
    segment = None
    if segmenter is not None:
        segment = lambda frames: segmenter.classes(frames, mesh=run.mesh)
    boxes = "boxes" in spec.model.controls.enabled()
    with jax.set_mesh(run.mesh):
        results, effects, rows, following = evaluate_routes(
            args.routes,
            plan,
            load_inputs=load_inputs,
            strategies=names,
            models=models,
            codec=codec,
            length=length,
            first_latents=lambda inp: first_latents(inp, codec, models.main.window, given),
            buckets=buckets,
            key=jax.random.key(args.seed),
            given=given_pixels,
            depth=spec.data.warp_depth,
            warp_frame=spec.data.warp_frame,
            mesh=run.mesh,
            segment=segment,
            without_boxes=boxes,
            ego_motion=args.ego_motion,
            fps=12.0 / spec.frame_stride,  # the synthetic world's 12 fps, as sampled
            **features,
        )
    from jaxdrive.media import write_route_grid

    grid = write_route_grid(Path(args.out) / "routes.png", rows)
    paths = write_outputs(
        results,
        Path(args.out),
        effects=effects,
        following=following,
        meta=_meta(
            args,
            clips,
            given_pixels,
            spec.data.views,
            shuffle_boxes=False,
            split="validation",
            routes=args.routes,
            route_clips=plan["indices"],
            cfg=[models.main.guidance],
        ),
    )
    print(paths["table"])
    print(f"wrote {paths['json']}, {paths['md']}, {paths['plot']}, {grid}")
    return 0


def _meta(args, clips: int, given_pixels: int, views: int, **extra) -> dict:
    """``eval.json``'s ``meta`` of an evaluation of ``--workdir`` (the keys in their order)."""
    keys = ("shuffle_boxes", "split", "routes", "route_clips", "cfg")
    return {
        "workdir": str(args.workdir),
        "fine_workdir": args.fine_workdir,
        "clips": clips,
        "frames": args.frames,
        "given_frames": given_pixels,
        "views": views,
        "inception": args.inception,
        "i3d": args.i3d,
        "segmenter": args.segmenter,
        **{k: extra[k] for k in keys if k in extra},
        "cfg_boxes": args.cfg_boxes,
        "cfg_route": args.cfg_route,
    }


def _eval_videos(args) -> int:
    """``--videos DIR --data PATH``: every mp4 under DIR (sorted by path; view mosaics as
    ``jaxdrive sample`` writes them) against the clip of the same rank in the split."""
    import numpy as np

    from jaxdrive.data.class_masks import class_masks_of
    from jaxdrive.data.tfds_io import open_source
    from jaxdrive.data.transforms import sample_clip
    from jaxdrive.eval.compare import controllability, parse_buckets, repeat_baseline, repeat_name, score, write_outputs
    from jaxdrive.media import read_mp4
    from jaxdrive.validate import check_positive_int

    for name in ("strategies", "fine_workdir", "frames", "routes", "cfg", "cfg_boxes", "cfg_route"):
        if getattr(args, name) not in (None, "rollout"):
            raise ValueError(f"--{name.replace('_', '-')}: expected only with --workdir, got {getattr(args, name)!r}")
    if not args.data:
        raise ValueError("--data: expected the dataset the videos continue (with --videos), got none")
    check_positive_int("--views", args.views)
    check_positive_int("--stride", args.stride)
    given = check_positive_int("--given", args.given, minimum=0)
    folder = Path(args.videos)
    files = sorted(folder.rglob("*.mp4")) if folder.is_dir() else []
    if not files:
        raise ValueError(f"--videos: expected a folder with .mp4 files, got {str(folder)!r} (none found)")
    _check_common(args, len(files))
    if args.shuffle_boxes:
        raise ValueError(
            "--shuffle-boxes: expected with --workdir (generated videos have their boxes already), got --videos"
        )
    videos = [read_mp4(f, args.views) for f in files]
    shapes = sorted({v.shape for v in videos})
    if len(shapes) > 1:
        raise ValueError(f"--videos: expected videos of one shape [V, F, H, W, 3], got {[list(x) for x in shapes]}")
    _, frames, height, width, _ = shapes[0]
    source = open_source(args.data, args.split or "validation")
    if len(files) > len(source):
        raise ValueError(
            f"--videos: expected at most {len(source)} videos (the clips of split {source.split!r}, "
            f"matched in order), got {len(files)}"
        )
    if given >= frames:
        raise ValueError(f"--given: expected fewer than the videos' {frames} frames, got {given}")
    buckets = parse_buckets(args.buckets, given, frames)
    segmenter = _load_segmenter(args, (height, width))
    recorded, masks = [], []
    for i in range(len(files)):
        s = sample_clip(
            source[i],
            size=(height, width),
            frames=frames,
            stride=args.stride,
            views=list(range(args.views)),
            instances=segmenter is not None,
            where=f"--videos: {files[i].name} against {source.split} clip {i}",
        )
        recorded.append(s["video"])
        if segmenter is not None:
            masks.append(class_masks_of(s))
    recorded = np.stack(recorded)
    video = np.stack(videos).astype(np.float32) / 127.5 - 1.0
    features = _feature_functions(args, None)
    ceiling = None
    if segmenter is not None:
        features.update(segment=segmenter.classes, masks=np.stack(masks))
        ceiling = controllability(segmenter.classes, recorded, features["masks"], buckets)
    results = {
        "videos": {
            "seconds": None,
            "peak_device_bytes": None,
            "files": [str(f) for f in files],
            "buckets": score(video, recorded, buckets, **features),
        }
    }
    if given:
        results[repeat_name(given)] = repeat_baseline(recorded, given, buckets, **features)
    paths = write_outputs(
        results,
        Path(args.out),
        ceiling=ceiling,
        meta={
            "videos": str(folder),
            "data": args.data,
            "split": source.split,
            "clips": len(files),
            "frames": int(frames),
            "given_frames": given,
            "views": args.views,
            "inception": args.inception,
            "i3d": args.i3d,
            "segmenter": args.segmenter,
        },
    )
    print(paths["table"])
    print(f"wrote {paths['json']}, {paths['md']}, {paths['plot']}")
    return 0


def _feature_functions(args, mesh) -> dict:
    """FID / FVD feature functions of ``--inception`` / ``--i3d`` (batch-sharded over ``mesh``)."""
    from jaxdrive.parallel.batches import extract

    features = {}
    if args.inception:
        from jaxdrive.eval.inception import load_fid_inception

        model, params = load_fid_inception(args.inception, option="inception")
        features["fid_features"] = lambda x: extract(lambda p, b: model.features(p, b), params, x, mesh=mesh)
    if args.i3d:
        from jaxdrive.eval.i3d import load_i3d

        model3, params3 = load_i3d(args.i3d, option="i3d")
        features["fvd_features"] = lambda x: extract(
            lambda p, b: model3.logits(p, b), params3, x, batch_size=4, mesh=mesh
        )
    return features


def _load_segmenter(args, size):
    """``--segmenter``'s run, checked against the frame ``size`` it will score (None without one)."""
    if not args.segmenter:
        return None
    from jaxdrive.eval.segmenter import load_segmenter

    segmenter = load_segmenter(args.segmenter, option="segmenter")
    if segmenter.size != tuple(size):
        raise ValueError(
            f"--segmenter: expected a segmenter trained at the frame size {size[0]} x {size[1]}, got "
            f"one trained at {segmenter.size[0]} x {segmenter.size[1]}"
        )
    return segmenter


def _check_common(args, clips: int) -> None:
    if args.shuffle_boxes and not args.segmenter:
        raise ValueError(
            "--shuffle-boxes: expected with --segmenter (it is the controllability control), got no --segmenter"
        )
    if args.shuffle_boxes and clips < 2:
        raise ValueError(
            f"--clips: expected at least 2 with --shuffle-boxes (each clip gets the next one's boxes), got {clips}"
        )
    if (args.inception or args.i3d) and clips < 2:
        raise ValueError(
            f"--clips: expected at least 2 with --inception / --i3d (FID and FVD fit a covariance, "
            f"which needs 2 samples per set), got {clips}"
        )


def add_commands(sub) -> None:
    from jaxdrive.cli.options import add_sampling

    ev = sub.add_parser(
        "eval",
        help="score long-video strategies side by side on the same validation clips "
        "(PSNR / SSIM per horizon; FID / FVD with the weights files)",
    )
    ev.add_argument("--workdir", help="the run to sample (or --videos)")
    ev.add_argument("--fine-workdir", help="the fine run (coarse-fine; coarse-to-refine's refiner)")
    ev.add_argument(
        "--strategies",
        default="rollout",
        help="comma-separated: rollout, coarse-to-refine, coarse-fine, window, streaming",
    )
    ev.add_argument("--split", help="the dataset split the clips come from (default: validation, else the run's)")
    ev.add_argument("--clips", type=int, default=2, help="validation clips (a multiple of the mesh's data x fsdp)")
    ev.add_argument("--frames", type=int, help="pixel frames per clip (with --workdir)")
    ev.add_argument(
        "--videos",
        help="instead of sampling a run: a folder of generated mp4s (view mosaics, as jaxdrive "
        "sample writes them), scored in path order against the split's clips",
    )
    ev.add_argument("--data", help="with --videos: the dataset they continue")
    ev.add_argument(
        "--merge",
        help="instead: comma-separated output folders of earlier jaxdrive eval runs on the "
        "same clips (strategies of different models), merged into one table",
    )
    ev.add_argument("--views", type=int, default=6, help="with --videos: views per mosaic (default 6)")
    ev.add_argument("--stride", type=int, default=1, help="with --videos: the clips' frame stride (default 1)")
    ev.add_argument(
        "--given",
        type=int,
        default=1,
        help="with --videos: the given frames each starts with, left out of the default buckets (default 1)",
    )
    ev.add_argument(
        "--buckets",
        help="horizon buckets, inclusive output frame ranges after the given frames "
        "(default: the generated frames in thirds), e.g. 2-12,13-24",
    )
    ev.add_argument(
        "--inception", help="pytorch-fid's pt_inception-2015-12-05-6726825d.pth or its safetensors copy: FID"
    )
    ev.add_argument("--i3d", help="cd-fvd's i3d_pretrained_400.pt or its safetensors copy: FVD")
    ev.add_argument(
        "--segmenter",
        help="a segmenter run (configs/segmenter.py): controllability mIoU against the "
        "class masks of the conditioning boxes (synthetic data)",
    )
    ev.add_argument(
        "--shuffle-boxes",
        action="store_true",
        help="the control: condition each clip on the next clip's boxes (and score against their masks)",
    )
    ev.add_argument(
        "--routes",
        help="score control on a dataset with counterfactual routes (jaxdrive data synth "
        "--counterfactuals): comma-separated, e.g. recorded,stop,lane-left; every "
        "strategy under each route against that route's render, with repeat and warp "
        "rows and the route effect",
    )
    ev.add_argument(
        "--ego-motion",
        action="store_true",
        help="with --routes: read the ego's path from every generated clip (and each route's render, "
        "the estimator's own error) and score it against the route's: ADE, FDE, manoeuvre recognised",
    )
    add_sampling(ev, sweep=True)
    ev.add_argument("--out", required=True, help="output directory")
    ev.set_defaults(run=_eval)
