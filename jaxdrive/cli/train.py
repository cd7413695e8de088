"""``jaxdrive train``, ``jaxdrive sample`` and ``jaxdrive demo``; each starts JAX with
:func:`jaxdrive.cli.options.start_jax`."""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from jaxdrive.cli import eval as eval_cli
from jaxdrive.cli.options import add_config, add_progress, add_sampling, load_config, start_jax

REPO_CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _train(args, rest) -> int:
    extra = []
    if args.steps is not None:
        extra.append(f"train.steps={args.steps}")
    if args.checkpoint_every is not None:
        extra.append(f"train.checkpoint_every={args.checkpoint_every}")
    config = load_config(args.config, args.mesh, args.set, extra)
    start_jax()
    from jaxdrive.config import PredictorRunConfig, SegmenterRunConfig

    if isinstance(config, PredictorRunConfig):  # configs/predictor.py: the future-controls predictor
        from jaxdrive.train.predictor_run import train_predictor as train
    elif isinstance(config, SegmenterRunConfig):  # configs/segmenter.py: the segmentation evaluator
        from jaxdrive.train.segmenter_run import train_segmenter as train
    else:
        from jaxdrive.train.run import train
    out = train(config, args.workdir, progress=not args.no_progress)
    print(f"{out['status']} at step {out['step']} (loss {out['loss']}); run directory {Path(args.workdir).absolute()}")
    return {"done": 0, "interrupted": 143, "diverged": 3, "save_failed": 4}[out["status"]]


def _sample(args, rest) -> int:
    start_jax()
    if args.strategy is not None:
        from jaxdrive.cli.sample import sample_strategy

        return sample_strategy(args)
    for name in (
        "fine_workdir",
        "anchor_every",
        "segment_batch",
        "device_memory",
        "overlap",
        "cond_frames",
        "route",
        "predictor",
    ):
        if getattr(args, name) is not None:
            raise ValueError(f"--{name.replace('_', '-')}: expected only with --strategy, got {getattr(args, name)}")
    if args.controls != "recorded":
        raise ValueError(f"--controls: expected only with --strategy, got {args.controls!r}")
    if args.allow_off_road:
        raise ValueError("--allow-off-road: expected only with --strategy and --route, got it without them")
    from jaxdrive.cli.options import guidance_options
    from jaxdrive.cli.sample import load_model
    from jaxdrive.generate.samples import write_samples

    model = load_model(args, weights=False)
    controls = guidance_options(args, [model.spec])  # before a weight is read or anything compiles
    model = model.with_weights()
    step, params = model.step, model.params
    views = None if args.views is None else [int(v) for v in args.views]
    out_dir = Path(args.out or Path(args.workdir) / "samples" / f"sample_{step:07d}")
    t = time.perf_counter()
    paths = write_samples(
        model.spec,
        params,
        out_dir,
        frames=args.frames,
        views=views,
        steps=args.steps,
        guidance=args.cfg,
        control_guidance=controls,
        seed=args.seed,
        progress=not args.no_progress,
    )
    if "quality" in paths:
        print(quality_lines(paths["quality"]))
    print(f"sampled from checkpoint {step} in {time.perf_counter() - t:.1f} s: {out_dir}")
    return 0


def _demo_mesh(config, sets):
    """The demo runs on whatever devices the host has: unless ``--set mesh.*`` says otherwise, the
    batch goes over ``data = gcd(data.batch_size, devices)`` and the rest of the devices split the
    sequence (``seq``), so 1, 2, 8 or 6 devices all divide the tiny batch."""
    import math

    import jax

    from jaxdrive.config import override

    if any(s.split("=", 1)[0].strip().startswith("mesh.") for s in sets or []):
        return config
    devices = jax.device_count()
    data = math.gcd(config.data.batch_size, devices)
    print(f"mesh: data={data} x seq={devices // data} over the {devices} {jax.default_backend()} devices")
    for key, value in (("data", data), ("fsdp", 1), ("seq", devices // data), ("tensor", 1)):
        config = override(config, f"mesh.{key}={value}")
    return config


def _demo(args, rest) -> int:
    """Synthesise a dataset, train the world recipe (``configs/world.py``: the tiny DiT with the
    controls ``jaxdrive bench controls`` found learnable) on frame-wise latents, sample a long clip,
    then the validation scene along its recorded route and a counterfactual one."""
    workdir = Path(args.workdir)
    from jaxdrive.config import split_config_path

    config_path = args.config or str(REPO_CONFIGS / "world.py") + ":control=warp"
    if not split_config_path(config_path)[0].is_file():
        raise ValueError(
            f"config: expected the world config at {config_path!r} (run from a checkout, or "
            f"pass --config), got a missing file"
        )
    data = workdir / "data"
    extra = [f"data.path={data}", f"train.steps={args.steps}"]
    config = load_config(config_path, None, args.set, extra)
    if args.cfg is not None:
        from jaxdrive.generate.guidance import check_scale

        check_scale("--cfg", args.cfg)
    if args.scenes < config.data.batch_size + 1:
        raise ValueError(
            f"--scenes: expected at least data.batch_size + 1 = {config.data.batch_size + 1} "
            f"(a batch of training scenes and one for validation), got {args.scenes}"
        )
    start_jax()
    config = _demo_mesh(config, args.set)
    from jaxdrive.data.synth_routes import parse_routes

    routes = [] if args.routes.strip().lower() == "none" else parse_routes(args.routes, "--routes", recorded=False)
    train_routes = _demo_train_route_names(config, args.train_routes)
    validation = config.mesh.data  # eval samples a multiple of the batch shards
    if args.scenes < config.data.batch_size + validation:
        raise ValueError(
            f"--scenes: expected at least data.batch_size + {validation} = "
            f"{config.data.batch_size + validation} (a batch of training scenes and {validation} for "
            f"validation on this mesh), got {args.scenes}"
        )
    t0 = time.perf_counter()
    if not data.exists():
        from jaxdrive.data.synthetic import drivable_clips, write_synthetic_dataset

        d = config.data
        frames = max(args.frames, d.frames)
        # the comparison needs a route every validation scene drives (on 1 device there is one
        # scene, and a route it cannot drive would stop the synthesis)
        rows = drivable_clips(
            routes, args.scenes - validation, validation, views=6, frames=frames, height=2 * d.height, width=2 * d.width
        )
        skipped = [r for r in routes if len(rows[r]) < validation]
        if skipped:
            print(f"routes the validation scenes cannot all drive, left out: {', '.join(skipped)}")
        routes = [r for r in routes if r not in skipped]
        size = {"frames": frames, "height": 2 * d.height, "width": 2 * d.width}
        trained = _demo_train_routes(train_routes, args.scenes - validation, **size)
        print(
            f"[1/3] synthesising {args.scenes} driving scenes ({d.views} views x {frames} frames) in {data}"
            + (f", the validation scenes also along {', '.join(routes)}" if routes else "")
            + (f", the training scenes along {', '.join(trained)}" if trained else "")
        )
        write_synthetic_dataset(
            data,
            train=args.scenes - validation,
            validation=validation,
            overwrite=True,
            views=6,
            frames=frames,
            height=2 * d.height,
            width=2 * d.width,
            counterfactuals=routes,
            train_counterfactuals=trained,
            skip_undrivable=True,
            drivable={r: rows[r] for r in routes},  # driven once, above
        )
    config = _demo_route_mix(config, data)
    from jaxdrive.media import plot_losses
    from jaxdrive.train.metrics import read_metrics
    from jaxdrive.train.run import train

    print(
        f"[2/3] training the tiny DiT ({split_config_path(config_path)[0].name}) for {config.train.steps} steps "
        f"in {workdir}"
    )
    out = train(config, workdir, progress=not args.no_progress)
    if out["status"] != "done":
        print(f"training {out['status']} at step {out['step']}; run 'jaxdrive demo' again to resume")
        return 1
    rows = read_metrics(workdir)
    plot = plot_losses(workdir / "loss.png", [r["step"] for r in rows], [r["loss"] for r in rows])
    from jaxdrive.world_model import WorldModel

    print(
        f"[3/3] sampling a {args.frames}-frame, {config.data.views}-view clip "
        f"(rollout: windows of {config.data.frames} frames, jaxdrive.WorldModel)"
    )
    model = WorldModel.from_run(workdir)  # as a user loads it: the EMA weights of the last checkpoint
    out_dir = workdir / "samples" / "demo"
    g = model.generate(
        frames=args.frames, strategy="rollout", cfg=args.cfg, steps=config.train.sample_steps, out=out_dir
    )
    paths = {
        "quality": g.report["quality"],
        "video": out_dir / "sample.mp4",
        "grid": out_dir / "frames.png",
        "quality_json": out_dir / "quality.json",
    }
    print(quality_lines(paths["quality"]))
    grid = _demo_routes(workdir, data, routes, validation, args, config)
    print(
        f"done in {time.perf_counter() - t0:.0f} s:\n  video      {paths.get('video')}\n"
        f"  frame grid {paths.get('grid')} (recorded | generated)\n  quality    {paths.get('quality_json')}\n"
        + (
            f"  routes     {grid} (render | generated: the recorded route, a counterfactual one, the recorded "
            f"route without its boxes)\n"
            if grid
            else ""
        )
        + f"  loss plot  {plot}\n  metrics    {workdir / 'metrics.jsonl'}"
    )
    return 0


# the demo's training futures: a stop, a lane change and a turn (slower and faster, the rest of
# world.py:control=warp's mix, would add 45 s of rendering to a 10-minute budget)
DEMO_TRAIN_ROUTES = ("stop", "lane-left", "branch")


def _demo_train_route_names(config, text: str | None) -> list[str]:
    """``--train-routes`` (``text``; None: :data:`DEMO_TRAIN_ROUTES` of the mix): counterfactual
    routes of the config's ``data.routes``."""
    from jaxdrive.data.route_mix import parse_route_mix
    from jaxdrive.data.synth_routes import parse_routes

    mix = [r for r in parse_route_mix(config.data.routes) if r != "recorded"] if config.data.routes else []
    if text is None:
        return [r for r in DEMO_TRAIN_ROUTES if r in mix]
    wanted = [] if text.strip().lower() == "none" else parse_routes(text, "--train-routes", recorded=False)
    extra = [r for r in wanted if r not in mix]
    if extra:
        raise ValueError(
            f"--train-routes: expected routes of the config's data.routes ({', '.join(mix) or 'none'}), "
            f"got {', '.join(extra)}"
        )
    return wanted


def _demo_train_routes(wanted: list[str], scenes: int, **clip_kwargs) -> list[str]:
    """The routes of ``wanted`` that at least one of the ``scenes`` training scenes can drive
    (their renders are the futures the model learns to follow)."""
    from jaxdrive.data.synthetic import drivable_clips

    rows = drivable_clips(wanted, 0, scenes, views=6, **clip_kwargs) if wanted else {}
    return [r for r in wanted if rows[r]]


def _demo_route_mix(config, data: Path):
    """``data.routes`` cut to the routes the demo's training split holds (a small town has scenes
    none of which drives some route: ``branch`` needs an intersection ahead)."""
    if not config.data.routes:
        return config
    from jaxdrive.data.route_mix import parse_route_mix
    from jaxdrive.data.synthetic import read_counterfactuals

    held = {"recorded", *read_counterfactuals(data).get("train_routes", {})}
    mix = parse_route_mix(config.data.routes)
    kept = {r: w for r, w in mix.items() if r in held}
    if len(kept) < len(mix):
        print(f"data.routes: the training scenes are not rendered along {', '.join(r for r in mix if r not in held)}")
    routes = () if list(kept) in ([], ["recorded"]) else tuple(f"{r}:{w:g}" for r, w in kept.items())
    return dataclasses.replace(config, data=dataclasses.replace(config.data, routes=routes))


def _demo_routes(workdir: Path, data: Path, routes, clips: int, args, config):
    """Control, shown: ``jaxdrive eval --routes recorded,ROUTE`` on the validation scenes, ROUTE
    the first of ``routes`` that every one of them can drive; returns its ``routes.png``."""
    from jaxdrive.data.synthetic import read_counterfactuals

    meta = read_counterfactuals(data)
    stored = meta.get("routes", {})
    drivable = [r for r in routes if r in stored and len(stored[r]["clips"]) >= clips]
    if not drivable:
        print(
            f"no route comparison: the validation scenes of {data} drive none of {', '.join(routes) or '(none)'}"
            if routes
            else "no route comparison (--routes none)"
        )
        return None
    out = workdir / "samples" / "routes"
    print(
        f"[3/3] and the same given frames along the recorded route and along '{drivable[0]}', scored against the "
        f"world's render of each (jaxdrive eval --routes)"
    )
    argv = [
        "eval",
        "--workdir",
        str(workdir),
        "--strategies",
        "rollout",
        "--clips",
        str(clips),
        "--frames",
        str(args.frames),
        "--routes",
        f"recorded,{drivable[0]}",
        "--steps",
        str(config.train.sample_steps),
        "--out",
        str(out),
    ]
    start = meta["start"]
    if args.frames > start + 1:  # the route following, read from the pixels: a motion after the route's start
        argv.append("--ego-motion")
    else:
        print(f"no route following: a clip of {args.frames} frames ends within a frame of the route's start ({start})")
    if args.cfg is not None:
        argv += ["--cfg", str(args.cfg)]
    parser = argparse.ArgumentParser(prog="jaxdrive")  # the eval command's own options, as jaxdrive's
    eval_cli.add_commands(parser.add_subparsers(dest="command"))
    ev = parser.parse_args(argv)
    ev.run(ev, [])
    return out / "routes.png"


def quality_lines(q: dict) -> str:
    """The quality report's summaries as a small table (``quality.json`` of a sample)."""
    lines = [
        f"quality against the recorded clip ({q['views']} views; {q['cond_frames']} given frames):",
        f"  {'':24s} {'PSNR dB':>8s} {'SSIM':>6s}",
    ]
    for key, title in (("first_window", "first window"), ("all_generated", "all generated")):
        s = q[key]
        span = f"{title} ({s['frames'][0]}-{s['frames'][-1]})"
        lines += [
            f"  {span:24s} {s['psnr']:8.2f} {s['ssim']:6.3f}",
            f"  {'  repeat last given':24s} {s['repeat_psnr']:8.2f} {s['repeat_ssim']:6.3f}",
            f"  {'  noise':24s} {s['noise_psnr']:8.2f} {s['noise_ssim']:6.3f}",
        ]
    return "\n".join(lines)


def add_commands(sub) -> None:
    train = sub.add_parser("train", help="train the DiT (resumes from the last checkpoint in --workdir)")
    add_config(train, "a config file, e.g. configs/tiny.py")
    train.add_argument("--workdir", required=True, help="run directory: checkpoints, metrics, samples")
    train.add_argument("--steps", type=int, help="total steps (train.steps)")
    train.add_argument("--checkpoint-every", type=int, help="steps between checkpoints (train.checkpoint_every)")
    train.add_argument("--mesh", help="mesh axis sizes, e.g. data=2,seq=4 (product = device count)")
    train.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config field (repeatable)")
    add_progress(train, "the steps")
    train.set_defaults(run=_train)

    sample = sub.add_parser("sample", help="generate a clip from a run's latest checkpoint (mp4 + frame grid)")
    sample.add_argument("--workdir", required=True)
    sample.add_argument("--frames", type=int, help="pixel frames (longer than training: rolled out in windows)")
    sample.add_argument("--views", nargs="+", help="camera indices (default: the training views)")
    add_sampling(sample)
    sample.add_argument("--out", help="output directory (default WORKDIR/samples/sample_STEP)")
    sample.add_argument(
        "--strategy",
        help="long-video strategy: rollout, coarse-to-refine (MiLA), coarse-fine "
        "(LongDWM), window (MagicDrive-V2: one window, models trained on "
        "several lengths) or streaming (STAGE: frame by frame with the HTFT "
        "buffer); writes sample.mp4, frames.png, latents.npy, report.json",
    )
    sample.add_argument(
        "--fine-workdir", help="the fine model's run (coarse-fine; optional (Re)fine model of coarse-to-refine)"
    )
    sample.add_argument("--cond-frames", type=int, help="given latent frames (default: the run's flow.cond_frames)")
    sample.add_argument("--overlap", type=int, help="rollout / refine windows: frames each next window conditions on")
    sample.add_argument(
        "--anchor-every",
        type=int,
        help="coarse-to-refine: latent frames between anchors (default: the model's training spacing; 0: no anchors)",
    )
    sample.add_argument(
        "--segment-batch",
        help="coarse-fine: segments per fine sampler call, or auto (default: the "
        "largest group whose compiled call fits --device-memory; on a CPU "
        "without it, one segment a call)",
    )
    sample.add_argument(
        "--device-memory",
        help="coarse-fine: per-device memory budget of --segment-batch auto, "
        "e.g. 16GiB (default: the device's free memory)",
    )
    sample.add_argument(
        "--taps",
        help="streaming: the past frames HTFT fuses, e.g. --taps=-1,-5,-10 (default: the "
        "run's stream.taps; 'none': HTFT off)",
    )
    sample.add_argument(
        "--route",
        help="drive this route instead of the recorded one (--strategy): a JSON or CSV "
        "file of ego waypoints (x, y[, t]) or a manoeuvre: 'straight 10m/s', "
        "'left turn', 'right turn', 'stop'; a turn starts at the next "
        "intersection on the scene's map within the frames generated",
    )
    sample.add_argument(
        "--allow-off-road",
        action="store_true",
        help="drive a --route file even where it leaves the road of the scene's map or the map "
        "itself (refused otherwise when more than a few metres of it are off the road, or "
        "any point is beyond the map)",
    )
    sample.add_argument(
        "--predictor",
        help="a run of configs/predictor.py: predicts the controls past the end of "
        "the clip's recorded ones (--frames may exceed the clip), and the other "
        "agents along a --route",
    )
    sample.add_argument(
        "--controls",
        default="recorded",
        help="recorded (default: predicted only beyond the log) or predicted (from the given frames on)",
    )
    sample.add_argument(
        "--clips", type=int, help="clips sampled side by side (--strategy; default: the mesh's data x fsdp size)"
    )
    add_progress(sample, "the sampled windows")
    sample.set_defaults(run=_sample)

    demo = sub.add_parser(
        "demo",
        help="synthesise data, train a tiny DiT with controls, sample a long multi-view "
        "clip and a counterfactual route",
    )
    demo.add_argument("--workdir", default="jaxdrive-demo")
    add_config(demo, "default: configs/world.py of this checkout", required=False)
    demo.add_argument("--steps", type=int, default=450)
    demo.add_argument("--scenes", type=int, default=24, help="synthetic scenes (one kept for validation)")
    demo.add_argument("--frames", type=int, default=33, help="frames of the sampled clip")
    demo.add_argument(
        "--cfg",
        type=float,
        help="classifier-free guidance (1: none; default: the config's "
        "sample.cfg, 1 for configs/tiny.py, whose model scores best without)",
    )
    demo.add_argument(
        "--routes",
        default="branch,lane-left,lane-right,stop",
        help="counterfactual routes to render for the validation scenes; the first one they can all "
        "drive is generated beside the recorded route (none: skip; a turn or a lane change first: "
        "the front camera shows them apart)",
    )
    demo.add_argument(
        "--train-routes",
        help="counterfactual routes of the config's data.routes to render the training scenes along "
        f"(default: those of {','.join(DEMO_TRAIN_ROUTES)} it has; none: the recorded drives only); "
        "each costs about a second a scene to render",
    )
    demo.add_argument("--set", action="append", metavar="KEY=VALUE")
    add_progress(demo, "the training steps and the sampled windows")
    demo.set_defaults(run=_demo)
