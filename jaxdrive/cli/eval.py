"""``jaxdrive eval``: long-video strategies on the same validation clips, scored side by side.

    jaxdrive eval --workdir RUN [--fine-workdir RUN2] --strategies rollout,coarse-to-refine,...
                  --clips N --frames F [--buckets 2-12,13-24] [--inception FILE] [--i3d FILE] --out DIR

Every strategy starts from the same given frames and controls of the first N clips of the
validation split (:mod:`jaxdrive.eval.compare` scores them): PSNR / SSIM per horizon bucket
always, FID per view and over all views with ``--inception``, FVD on 16-frame windows with
``--i3d``. Writes ``DIR/eval.json``, ``DIR/eval.md`` and ``DIR/quality_vs_horizon.png`` and
prints the table. Every check that can fail does so before anything compiles.
"""

from __future__ import annotations

from pathlib import Path


def _eval(args, rest) -> int:
    from jaxdrive.cli.train import start_jax
    start_jax()
    import jax
    import numpy as np

    from jaxdrive.cli.sample import first_latents, load_runs
    from jaxdrive.eval.compare import parse_buckets, run_strategies, write_outputs
    from jaxdrive.generate.samples import dataset_inputs
    from jaxdrive.generate.strategies import NEEDS_FINE, STRATEGIES, Models, check_strategy
    from jaxdrive.validate import check_positive_int
    names = [s.strip() for s in args.strategies.split(",") if s.strip()]
    for name in names:
        if name not in STRATEGIES:
            raise ValueError(f"--strategies: expected names from {', '.join(STRATEGIES)}, got {name!r}")
        if name in NEEDS_FINE and not args.fine_workdir:
            raise ValueError(f"--fine-workdir: strategy {name!r} needs a fine model run, got none")
    if not names:
        raise ValueError(f"--strategies: expected a comma-separated list from {', '.join(STRATEGIES)}, got "
                         f"{args.strategies!r}")
    check_positive_int("--frames", args.frames)
    clips = check_positive_int("--clips", args.clips)
    if (args.inception or args.i3d) and clips < 2:
        raise ValueError(f"--clips: expected at least 2 with --inception / --i3d (FID and FVD fit a covariance, "
                         f"which needs 2 samples per set), got {clips}")
    args.cond_frames = None
    run, spec, fine_spec, load_main, load_fine, shapes, length = load_runs(args)
    horizon_spec = fine_spec or spec
    given = shapes.main.cond_frames
    if "coarse-fine" in names:
        given = min(given, shapes.fine.window - 1)          # one start for all: the smallest a strategy takes
    for name in names:
        check_strategy(name, shapes, length, given)
    sizes = dict(zip(run.mesh.axis_names, run.mesh.axis_sizes))
    shards = sizes.get("data", 1) * sizes.get("fsdp", 1)
    if clips % shards:
        raise ValueError(f"--clips: expected a multiple of the mesh's data x fsdp size {shards}, got {clips}")
    codec = horizon_spec.codec
    given_pixels = codec.pixel_frames(given)
    buckets = parse_buckets(args.buckets, given_pixels, args.frames)
    from jaxdrive.eval.features import extract
    features = {}
    if args.inception:
        from jaxdrive.eval.inception import load_fid_inception
        model, params = load_fid_inception(args.inception)
        features["fid_features"] = lambda x: extract(lambda p, b: model.features(p, b), params, x, mesh=run.mesh)
    if args.i3d:
        from jaxdrive.eval.i3d import load_i3d
        model3, params3 = load_i3d(args.i3d)
        features["fvd_features"] = lambda x: extract(lambda p, b: model3.logits(p, b), params3, x, batch_size=4,
                                                     mesh=run.mesh)
    try:
        inputs = dataset_inputs(horizon_spec, frames=args.frames, clips=clips, seed=args.seed)
    except ValueError as e:          # the clips are shorter than --frames (or the dataset is unreadable)
        raise ValueError(f"--{e}" if str(e).startswith("frames:") else f"--frames: {e}") from None
    models = Models(load_main(), load_fine() if load_fine else None)
    first = first_latents(inputs, codec, models.main.window, given)
    recorded = np.asarray(inputs["video"]) if "video" in inputs else np.asarray(
        codec.decode(codec.params, inputs["latents"][:, :, :length]))
    out = Path(args.out)
    with jax.set_mesh(run.mesh):
        results = run_strategies({n: {} for n in names}, models, codec, inputs["cond"], first, length, recorded,
                                 buckets, key=jax.random.key(args.seed), mesh=run.mesh, **features)
    paths = write_outputs(results, out, meta={"workdir": str(args.workdir), "fine_workdir": args.fine_workdir,
                                              "clips": clips, "frames": args.frames, "given_frames": given_pixels,
                                              "views": int(recorded.shape[1]), "inception": args.inception,
                                              "i3d": args.i3d})
    print(paths["table"])
    print(f"wrote {paths['json']}, {paths['md']}, {paths['plot']}")
    return 0


def add_commands(sub) -> None:
    from jaxdrive.cli.options import add_sampling
    ev = sub.add_parser("eval", help="score long-video strategies side by side on the same validation clips "
                                     "(PSNR / SSIM per horizon; FID / FVD with the weights files)")
    ev.add_argument("--workdir", required=True, help="the run to sample")
    ev.add_argument("--fine-workdir", help="the fine run (coarse-fine; coarse-to-refine's refiner)")
    ev.add_argument("--strategies", default="rollout", help="comma-separated: rollout, coarse-to-refine, "
                                                            "coarse-fine, window, streaming")
    ev.add_argument("--clips", type=int, default=2, help="validation clips (a multiple of the mesh's data x fsdp)")
    ev.add_argument("--frames", type=int, required=True, help="pixel frames per clip")
    ev.add_argument("--buckets", help="horizon buckets, inclusive output frame ranges after the given frames "
                                      "(default: the generated frames in thirds), e.g. 2-12,13-24")
    ev.add_argument("--inception", help="pytorch-fid's pt_inception-2015-12-05-6726825d.pth or its safetensors "
                                        "copy: FID")
    ev.add_argument("--i3d", help="cd-fvd's i3d_pretrained_400.pt or its safetensors copy: FVD")
    add_sampling(ev, cfg=1.0)
    ev.add_argument("--out", required=True, help="output directory")
    ev.set_defaults(run=_eval)
