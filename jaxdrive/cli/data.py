"""``jaxdrive data``: build and inspect datasets (TFDS in ArrayRecord format): synthetic scenes,
nuScenes, T5 caption embeddings, precomputed latent windows."""

from __future__ import annotations

from jaxdrive.cli.options import add_config, add_progress, load_config, start_jax


def _split_counts(scenes: int, val_fraction: float) -> tuple[int, int]:
    if scenes < 1:
        raise SystemExit(f"jaxdrive data synth: --scenes: expected an integer >= 1, got {scenes}")
    if not 0.0 <= val_fraction < 1.0:
        raise SystemExit(f"jaxdrive data synth: --val-fraction: expected a value in [0, 1), got {val_fraction}")
    # At least one validation scene whenever there are two scenes and a fraction is asked for.
    val = min(scenes - 1, max(1, round(scenes * val_fraction))) if scenes > 1 and val_fraction > 0 else 0
    return scenes - val, val


def _splits(train, validation, n_val):
    return {"train": train, "validation": validation} if n_val else {"train": train}


def _data_synth(args, rest) -> int:
    from jaxdrive.data.synthetic import COUNTERFACTUAL_START, read_counterfactuals, write_synthetic_dataset
    from jaxdrive.data.tfds_io import dataset_info

    n_train, n_val = _split_counts(args.scenes, args.val_fraction)
    cf_splits = [s.strip() for s in args.counterfactual_splits.split(",") if s.strip()]
    if not cf_splits or any(s not in ("train", "validation") for s in cf_splits):
        raise ValueError(
            f"--counterfactual-splits: expected 'train', 'validation' or both, comma-separated, "
            f"got {args.counterfactual_splits!r}"
        )
    if args.counterfactuals is not None and "validation" in cf_splits and not n_val:
        raise ValueError(
            f"--counterfactuals: expected a dataset with validation clips (--scenes >= 2 and "
            f"--val-fraction > 0), got {n_val} validation clips (or --counterfactual-splits train)"
        )
    routes = args.counterfactuals or ()
    path = write_synthetic_dataset(
        args.out,
        train=n_train,
        validation=n_val,
        seed=args.seed,
        overwrite=args.overwrite,
        views=args.views,
        frames=args.frames,
        height=args.height,
        width=args.width,
        counterfactuals=routes if "validation" in cf_splits else (),
        train_counterfactuals=routes if "train" in cf_splits else (),
        counterfactual_start=(COUNTERFACTUAL_START if args.counterfactual_start is None else args.counterfactual_start),
        skip_undrivable=args.skip_undrivable,
    )
    info = dataset_info(path)
    seconds = info["metadata"].get("synthesis_seconds", {})
    cf = read_counterfactuals(path)
    print(f"wrote {n_train} train and {n_val} validation clips to {path}")
    for split, row in info["splits"].items():
        of = {"routes": (n_val, "validation"), "train_routes": (n_train, "training")}
        route = next(
            (
                f" ({name}: {len(r['clips'])} of {of[key][0]} {of[key][1]} clips)"
                for key in of
                for name, r in cf.get(key, {}).items()
                if r["split"] == split
            ),
            "",
        )
        n, t = row["num_examples"], seconds.get(split, 0.0)
        print(
            f"  {split}{route}: {row['num_bytes'] / 2**20:.1f} MiB, rendered in {t:.1f} s"
            + (f" ({t / n:.2f} s a clip)" if n else "")
        )
    return 0


def _data_nuscenes(args, rest) -> int:
    import numpy as np

    from jaxdrive.data.nuscenes import load_tables, read_clips, scene_names
    from jaxdrive.data.tfds_io import write_dataset

    if (args.height is None) != (args.width is None):
        raise SystemExit(
            "jaxdrive data nuscenes: --height/--width: expected both or neither, "
            f"got height={args.height}, width={args.width}"
        )
    tables = load_tables(args.dataroot, args.version)
    names = scene_names(tables)
    n_train, n_val = _split_counts(len(names), args.val_fraction)
    image_hw = None if args.height is None else (args.height, args.width)
    skipped = []  # (scene, first frame, image file) of each clip left out

    def clips(scenes):
        for clip in read_clips(
            args.dataroot,
            args.version,
            frames=args.frames,
            stride=args.stride,
            image_hw=image_hw,
            scenes=scenes,
            tables=tables,
            skip_bad_records=args.skip_bad_records,
            skipped=skipped,
        ):
            meta = clip.pop("meta")  # keep what a dataset row can hold: names and arrays
            yield {**clip, "scene": meta["scene"], "timestamps": np.asarray(meta["timestamps"], np.int64)}

    path = write_dataset(
        args.out,
        _splits(clips(names[:n_train]), clips(names[n_train:]), n_val),
        name="jaxdrive_nuscenes",
        overwrite=args.overwrite,
        metadata={"source": "nuscenes", "version": args.version, "frames": args.frames, "stride": args.stride},
    )
    left_out = (
        (
            f"; {len(skipped)} clips left out for unreadable images ({len({f for _, _, f in skipped})} "
            f"files, named in the log)"
        )
        if args.skip_bad_records
        else ""
    )
    print(f"wrote nuScenes {args.version} ({n_train} train / {n_val} validation scenes) to {path}{left_out}")
    return 0


def _data_info(args, rest) -> int:
    import json

    from jaxdrive.data.tfds_io import dataset_info

    info = dataset_info(args.path)
    print(json.dumps(info, indent=2, default=str))
    return 0


def _data_text_embed(args, rest) -> int:
    import numpy as np

    from jaxdrive.data.text import precompute_t5
    from jaxdrive.data.tfds_io import open_source

    captions = []
    for split in args.split:
        src = open_source(args.dataset, split)
        captions += [src[i]["caption"] for i in range(len(src))]
    unique = sorted(set(captions))
    emb, mask = precompute_t5(unique, args.encoder, max_length=args.max_length, batch_size=args.batch_size)
    np.savez(args.out, captions=np.asarray(unique), embeddings=emb, mask=mask)
    print(f"wrote T5 embeddings {list(emb.shape)} of {len(unique)} captions to {args.out}")
    return 0


def _data_encode(args, rest) -> int:
    from jaxdrive.train.encode import encode_dataset

    config = load_config(args.config, args.mesh, args.set)
    start_jax()  # several processes (launch/local.py, SLURM, a TPU pod) share the work
    path = encode_dataset(
        config,
        args.out,
        splits=args.split,
        every=args.every,
        batch=args.batch,
        overwrite=args.overwrite,
        progress=not args.no_progress,
    )
    print(
        f"wrote the latent windows of {config.data.path} to {path}; train on them with "
        f"--set data.path={path} --set latents.precomputed=true"
    )
    return 0


def add_commands(sub) -> None:
    data = sub.add_parser("data", help="build and inspect datasets (TFDS, ArrayRecord)")
    dsub = data.add_subparsers(dest="data_command", metavar="DATA_COMMAND", required=True)
    synth = dsub.add_parser("synth", help="write a synthetic multi-view driving dataset")
    synth.add_argument("--out", required=True, help="dataset directory to create")
    synth.add_argument("--scenes", type=int, default=16)
    synth.add_argument("--views", type=int, default=6, choices=[1, 6])
    synth.add_argument("--frames", type=int, default=33)
    synth.add_argument("--height", type=int, default=64)
    synth.add_argument("--width", type=int, default=112)
    synth.add_argument("--val-fraction", type=float, default=0.125)
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument("--overwrite", action="store_true")
    synth.add_argument(
        "--counterfactuals",
        metavar="ROUTES",
        help="store each clip's re-render along these routes (comma-separated: stop, slower, faster, "
        "lane-left, lane-right, branch) in splits train_route_<route> and validation_route_<route>; a "
        "training scene that cannot drive a route is left out of it (data.routes trains on them)",
    )
    synth.add_argument(
        "--counterfactual-splits",
        default="train,validation",
        help="which splits --counterfactuals re-renders (default train,validation; validation alone for "
        "evaluation only)",
    )
    synth.add_argument(
        "--counterfactual-start",
        type=int,
        default=None,
        help="the first frame a counterfactual route changes (default 8: after the given frames)",
    )
    synth.add_argument(
        "--skip-undrivable",
        action="store_true",
        help="leave out a validation clip that cannot drive a route (off the road, into an agent, "
        "no intersection to branch at) instead of stopping with an error naming it (training "
        "clips are always left out)",
    )
    synth.set_defaults(run=_data_synth)
    nus = dsub.add_parser("nuscenes", help="convert a local nuScenes dataroot")
    nus.add_argument("--dataroot", required=True)
    nus.add_argument("--out", required=True)
    nus.add_argument("--version", default="v1.0-mini", help="v1.0-mini or v1.0-trainval")
    nus.add_argument("--frames", type=int, default=33)
    nus.add_argument("--stride", type=int, default=1)
    nus.add_argument("--height", type=int, default=None, help="resize images (with --width)")
    nus.add_argument("--width", type=int, default=None)
    nus.add_argument("--val-fraction", type=float, default=0.15)
    nus.add_argument("--overwrite", action="store_true")
    nus.add_argument(
        "--skip-bad-records",
        action="store_true",
        help="leave out a clip whose camera image is missing or unreadable (each file named once in "
        "the log, the count in the summary) instead of stopping with an error naming it",
    )
    nus.set_defaults(run=_data_nuscenes)
    text = dsub.add_parser(
        "text-embed",
        help="precompute T5 embeddings of a dataset's captions "
        '(needs the t5 extra, pip install "jaxdrive[t5]", and local T5 '
        "weights)",
    )
    text.add_argument("--dataset", required=True, help="TFDS dataset directory")
    text.add_argument("--encoder", required=True, help="folder of a T5 encoder (safetensors) and tokenizer")
    text.add_argument("--out", required=True, help="output .npz: captions, embeddings [N, L, D], mask [N, L]")
    text.add_argument("--split", nargs="+", default=["train"])
    text.add_argument("--max-length", type=int, default=300)
    text.add_argument("--batch-size", type=int, default=8)
    text.set_defaults(run=_data_text_embed)
    enc = dsub.add_parser(
        "encode",
        help="precompute the latents of a config's training windows (train on them with latents.precomputed=true)",
    )
    add_config(enc, "the training config: data.path, frames, stride, views, height, width and the latents codec")
    enc.add_argument("--out", required=True, help="dataset directory to create")
    enc.add_argument("--split", nargs="+", help="splits to encode (default: all of the dataset's)")
    enc.add_argument(
        "--every", type=int, help="source frames between window starts (default: the window's span, no overlap)"
    )
    enc.add_argument(
        "--batch",
        type=int,
        default=8,
        help="windows per encoder call, all processes together (a multiple of the mesh's batch axes data x fsdp)",
    )
    enc.add_argument(
        "--mesh",
        help="mesh axis sizes, e.g. data=8 (default: the config's mesh; the batch is sharded over data and fsdp)",
    )
    enc.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config field (repeatable)")
    enc.add_argument("--overwrite", action="store_true")
    add_progress(enc, "the encoded windows")
    enc.set_defaults(run=_data_encode)
    info = dsub.add_parser("info", help="print what a dataset holds")
    info.add_argument("path")
    info.set_defaults(run=_data_info)
