"""``jaxdrive plan``: will a config's train step fit, per device, on a mesh (fake CPU devices, or a
TPU topology's compile-only chips with ``--topology``; nothing is allocated,
:mod:`jaxdrive.train.plan`)."""

from __future__ import annotations

import json
import math

from jaxdrive.cli.options import add_config

# (column, per_device key, what it holds)
COLUMNS = (
    ("params", "params", "parameters (float32)"),
    ("optimizer", "opt_state", "optimizer state"),
    ("ema", "ema", "EMA parameters"),
    ("frozen", "frozen", "parameters read, not trained (the VAE)"),
    ("batch", "batch", "the step's input batch"),
    ("temp", "temp", "activations kept for the backward pass and scratch"),
    ("total", "total", "all of it while the step runs (state + frozen + batch + temp + outputs - donated)"),
)


def gib(n) -> str:
    return "-" if n is None else f"{n / 2**30:.2f}"


def _start_cpu_devices(n: int) -> None:
    """``n`` fake CPU devices, before JAX starts its backend; where it has started (a caller
    in-process, e.g. the tests), the devices there are must be enough."""
    import jax

    try:
        jax.config.update("jax_platforms", "cpu")
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:
        pass
    if len(jax.devices()) < n:
        raise ValueError(
            f"--mesh: expected at most the {len(jax.devices())} devices this process started with, got a mesh of {n}"
        )


def _plan(args, rest) -> int:
    from jaxdrive.config import load_config
    from jaxdrive.train.plan import largest_fit, parse_bytes, parse_mesh, plan_memory

    memory = None if args.device_memory is None else parse_bytes(args.device_memory)
    try:
        scales = tuple(float(s) for s in args.scales.split(","))
    except ValueError:
        scales = ()
    if not scales or not all(math.isfinite(s) and s > 0 for s in scales):
        raise ValueError(f"--scales: expected positive numbers separated by commas, e.g. 0.5,1,2, got {args.scales!r}")
    if args.devices is not None and args.devices < 1:
        raise ValueError(f"--devices: expected a positive integer, got {args.devices}")
    if args.slices < 1:
        raise ValueError(f"--slices: expected a positive integer, got {args.slices}")
    target = dict(topology=args.topology, slices=args.slices)
    if args.topology is None:
        if args.slices != 1:
            raise ValueError(f"--slices: expected 1 without --topology (slices of a TPU topology), got {args.slices}")
        sizes = parse_mesh(args.mesh, args.devices)
        _start_cpu_devices(math.prod(sizes.values()))
        mesh: str | dict = sizes
    else:
        if args.devices is not None:
            raise ValueError(
                f"--devices: expected none with --topology (its chips are the devices), got {args.devices}"
            )
        # the host runs nothing: the TPU devices are the topology's, compile-only; JAX's own backend
        # stays the CPU (with libtpu installed it would otherwise look for a TPU on this host)
        try:
            import jax

            jax.config.update("jax_platforms", "cpu")
        except RuntimeError:
            pass
        mesh = args.mesh
    config = load_config(args.config, args.set or [])
    plan = plan_memory(config, mesh, device_memory=memory, compile_step=not args.no_compile, **target)
    out = {"config": args.config, "sets": args.set or [], "compute_dtype": config.train.compute_dtype, **plan}
    memory = plan["device_memory"]  # a topology's chip memory when none was given
    if memory is not None and not (args.no_fit or args.no_compile):
        out["fit"] = largest_fit(config, plan["mesh"], memory, scales=scales, **target)
    if args.json:
        print(json.dumps(out))
        return 0
    print(table(out))
    return 0


def table(out: dict) -> str:
    """The plan as text: one row of per-device GiB, then the largest clips that fit."""
    mesh = ",".join(f"{k}={v}" for k, v in out["mesh"].items() if v > 1) or "one device"
    pd = out["per_device"]
    head = f"{'mesh':20s} {'bucket':14s} {'batch':>5s} " + " ".join(f"{c:>9s}" for c, _, _ in COLUMNS)
    row = f"{mesh:20s} {out['bucket']:14s} {out['batch']:5d} " + " ".join(f"{gib(pd[k]):>9s}" for _, k, _ in COLUMNS)
    compiled = "not compiled" if out["compile_seconds"] is None else f"compiled in {out['compile_seconds']} s"
    lines = [
        f"{out['config']}: per-device GiB of one train step on {out['target']} (latents: {out['codec']}; {compiled})",
        head,
        row,
    ]
    if out.get("exhausted"):
        needs = pd["total"]
        lines.append(
            f"does not fit: needs {gib(needs) + ' GiB' if needs is not None else 'more than the chip has'} "
            f"(the compiler: {out['exhausted']})"
        )
    elif out["fits"] is not None:
        verdict = "fits" if out["fits"] else "does NOT fit"
        lines.append(f"{verdict} in {gib(out['device_memory'])} GiB per device")
    split = out.get("seq_split")
    if split and not split["divides"]:
        lines.append(
            f"seq={split['seq']} does not divide the {split['frame_tokens']} tokens of a frame (a clip: "
            f"{split['clip_tokens']}): they stay unsharded over seq, so the axis saves no activation memory; "
            f"seq sizes that divide them: {', '.join(map(str, split['dividing'])) or 'none up to 64'}"
        )
    program = out.get("program")
    if program:
        from jaxdrive.train.program import unlisted_f32_dots

        dots = program["f32_dots"]
        lines.append(
            f"program: {program['mosaic_kernels']} Mosaic kernels, {program['collective_permutes']} "
            f"collective-permutes, {program['all_gathers']} all-gathers, {program['all_reduces']} all-reduces; "
            f"{len(dots)} dots / convolutions with a float32 operand "
            + (
                "(a float32 step)"  # the allow-list is for low-precision steps
                if out.get("compute_dtype", "float32") == "float32"
                else f"({len(unlisted_f32_dots(dots))} not on the allow-list)"
            )
        )
    if "fit" in out:
        lines.append(f"longest clip that fits {gib(out['device_memory'])} GiB at batch {out['fit']['bucket_batch']}:")
        for r in out["fit"]["resolutions"]:
            frames = "none" if r["frames"] is None else f"{r['frames']}{'+' if r['capped'] else ''} frames"
            why = f"; the shortest tried was refused: {r['refused']}" if r.get("refused") else ""
            lines.append(f"  {r['height']}x{r['width']}: {frames} ({gib(r['total'])} GiB; {r['probes']} compiles{why})")
    lines.append("columns: " + "; ".join(f"{c} = {what}" for c, _, what in COLUMNS))
    return "\n".join(lines)


def add_commands(sub) -> None:
    plan = sub.add_parser(
        "plan",
        help="per-device memory of a config's train step on a mesh, and the longest "
        "clip that fits a device (fake CPU devices, nothing allocated)",
    )
    add_config(plan, "the config to plan, e.g. configs/mila.py")
    plan.add_argument(
        "--mesh",
        required=True,
        help="mesh axis sizes, e.g. data=2,fsdp=4,seq=8,tensor=1 (missing "
        "axes are 1; the product is the fake device count, or with --topology its chips x slices, one axis -1 "
        "for the rest)",
    )
    plan.add_argument("--devices", type=int, help="device count the mesh must multiply to (allows one -1 axis)")
    plan.add_argument(
        "--topology",
        help="compile for a Cloud TPU slice instead of fake CPU devices (XLA:TPU on this host, no TPU needed; "
        'pip install -e ".[tpu]"): an accelerator type, e.g. v5e-4, v5e-256, v5p-64, v6e-64, v4-8 '
        "(v5p and v4 count TensorCores, two a chip); its chip memory is the default --device-memory",
    )
    plan.add_argument(
        "--slices", type=int, default=1, help="with --topology: that many slices (the data axis runs across them)"
    )
    plan.add_argument(
        "--device-memory",
        help="memory per device, e.g. 80GiB, 16GB, 512MiB: says whether it "
        "fits and searches the longest clip that does",
    )
    plan.add_argument(
        "--scales",
        default="1",
        help="resolutions searched with --device-memory: the planned "
        "bucket's height x width times each scale (default 1)",
    )
    plan.add_argument("--no-fit", action="store_true", help="with --device-memory: only say whether it fits")
    plan.add_argument(
        "--no-compile",
        action="store_true",
        help="the state and batch only (seconds at any size): no temp / total, no fit",
    )
    plan.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config field (repeatable)")
    plan.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    plan.set_defaults(run=_plan)
