"""The DiT's rectified-flow train step: tokens per second, model FLOPs utilisation, and the
diffusers PyTorch ``CogVideoXTransformer3DModel`` train step on the same CPU at the same size.

    python -m jaxdrive.bench.train [--presets tiny small] [--batch 1 | --batch auto] [--frames 5] [--height 16]
                                   [--width 16] [--repeats 10] [--no-torch | --compare-only]
                                   [--torch-threads N] [--peak-tflops T] [--no-ops] [--json]
                                   [--measure-peak 8192] [--profile DIR] [--dtype bfloat16] [--remat dots]
                                   [--attn-impl cudnn] [--scan-layers] [--topology v5p-8]

For each preset the benchmark jits the library's step (:func:`jaxdrive.train.flow_step.make_train_step`:
noise levels and condition frames, the DiT forward, the flow loss, the backward, global-norm
clipping at 1.0 and AdamW; no EMA) on a one-device mesh, with a batch of latents (the codec is the
identity: ``height``/``width`` are latent sizes, one view) and random text embeddings of the
preset's text length. It reports the compile time (``lower().compile()``) apart from the step
time, the median of ``--repeats`` steps after one warm-up step, each blocked on its outputs. The
mesh is :func:`jaxdrive.parallel.make_mesh`'s (Explicit axes, as in training).

The comparison with PyTorch (diffusers) uses the full-layout partner of a preset (``tiny`` ->
``tiny-full``, ``small`` -> ``small-full``; a full-layout preset is its own partner): the sizes of
that preset become a diffusers CogVideoX config (3D sin-cos positions, no RoPE; sample size = the
benchmark's latent size), diffusers builds its ``CogVideoXTransformer3DModel`` from it and jaxdrive
its :class:`DiT` with :func:`jaxdrive.convert.diffusers_dit.config_from_diffusers`, so both run
the same network (the parameter counts are checked equal). The PyTorch step is what a diffusers
training loop does: draw levels, noise, forward, MSE to the velocity ``noise - x``, backward,
``clip_grad_norm_(1.0)``, ``AdamW.step()`` with the same hyper-parameters. PyTorch runs with as many
threads as XLA:CPU uses (the CPUs this process may run on; ``--torch-threads`` to change it).
``ratio_to_torch`` = jaxdrive tokens/s / PyTorch tokens/s (above 1: jaxdrive is faster). After
each comparison, single operations at the comparison model's width and token count are timed in
both (:mod:`jaxdrive.bench.ops`: matmuls, a bias-gradient sum, a transpose, layer norm and softmax
forward + backward) so that the step's ratio can be read against XLA:CPU's own per-op ratios
(``--no-ops`` skips them). ``--json`` prints one JSON object per row (``model``, ``impl``,
``step_ms``, ``tokens_per_s``, ``ratio_to_torch``, ...) instead of the figures and the table. Run it on
an otherwise idle machine: when other processes hold the cores, PyTorch's spinning OpenMP threads
lose far more than XLA's pool (seen: 10-30x slower steps on 2 busy cores). Every timed figure
carries ``busy_cpus``, the CPUs other processes kept busy in the half second before it was
measured (Linux), and a note is printed when that exceeds half a CPU.

Model FLOPs and MFU: :mod:`jaxdrive.bench.flops`. ``--topology NAME`` times nothing: it compiles
each preset's step for one chip of that Cloud TPU slice on this host and prints XLA:TPU's
roofline estimate, corrected for what its cost model leaves out (:mod:`jaxdrive.bench.roofline`).

On an accelerator (``--no-torch``): ``--batch auto`` times the largest batch whose compiled step fits
``--memory-fraction`` of the device's memory (the allocator's limit, or ``--device-memory``):
:func:`jaxdrive.bench.fit.largest_batch` predicts it from two probe compiles (batches 1 and 2, side by side, without
GPU autotuning) and checks the prediction's compile, and an out-of-memory at run time retries once
at 85% of the batch. ``--profile DIR`` traces ``--profile-steps`` more steps with ``jax.profiler``
and names the largest device costs (:func:`jaxdrive.bench.report.trace_costs`, ``profile_cost``
figures); the device's peak memory is printed (``peak_device_memory``; null on a CPU).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from jaxdrive.bench.cpus import busy_cpus, cpu_count
from jaxdrive.bench.flops import measured_peak_tflops, peak_tflops
from jaxdrive.bench.train_steps import VIEWS, diffusers_config, jax_step, torch_step

BENCH = "train"
DEFAULTS = dict(batch=1, frames=5, height=16, width=16)


def device_memory_limit(device, given: int | None, fraction: float) -> tuple[int, str]:
    """``(bytes a step may use, where that comes from)``: ``given`` (``--device-memory``), else
    ``fraction`` of the device allocator's limit (``memory_stats()["bytes_limit"]``)."""
    if given is not None:
        return int(given * fraction), f"--device-memory x {fraction}"
    stats = device.memory_stats() if hasattr(device, "memory_stats") else None
    if not stats or "bytes_limit" not in stats:
        raise ValueError(
            f"--batch auto: the {device.platform} device reports no memory limit; expected "
            f"--device-memory (e.g. 2GiB), got none"
        )
    return int(stats["bytes_limit"] * fraction), f"{fraction} x the allocator's bytes_limit"


def run(
    presets,
    *,
    batch: int,
    frames: int,
    height: int,
    width: int,
    repeats: int,
    use_torch: bool = True,
    compare_only: bool = False,
    peak: float | None = None,
    torch_threads: int | None = None,
    micro: bool = True,
    as_json: bool = False,
    overrides: dict | None = None,
    peak_size: int | None = None,
    fit: dict | None = None,
    profile: str | None = None,
    profile_steps: int = 2,
) -> list[dict]:
    """Measure ``presets`` (module docstring); returns the rows. ``as_json``: print one JSON object
    per row instead of the figures and the table. ``overrides``: DiT config fields set on every
    jaxdrive model (``dtype``, ``remat``, ``attn_impl``, ``scan_layers``); ``peak_size``: also
    measure the bf16 matmul peak at that size and give the MFU against it (``mfu_measured``).
    ``batch=None``: the largest batch that fits ``fit`` (``{"limit": bytes, "max_batch": N}``,
    :func:`jaxdrive.bench.fit.largest_batch`); ``profile``: a directory for a ``jax.profiler`` trace of
    ``profile_steps`` steps of each jaxdrive model (a subdirectory per preset) and its largest
    device costs (``profile_cost`` figures)."""
    import jax

    from jaxdrive.bench.ops import op_rows
    from jaxdrive.bench.report import emit, table

    def figure(*args, **kwargs):
        return None if as_json else emit(*args, **kwargs)

    from jaxdrive.convert.diffusers_dit import config_from_diffusers
    from jaxdrive.models.dit.presets import PRESETS, preset
    from jaxdrive.parallel import make_mesh

    device = jax.devices()[0]
    mesh = make_mesh(devices=[device])
    peak_t, peak_note = peak_tflops(device, peak)
    measured = None
    if peak_size:
        measured = measured_peak_tflops(peak_size)
        figure(
            BENCH,
            "measured_peak_tflops",
            round(measured, 3),
            "TFLOP/s",
            size=peak_size,
            dtype="bfloat16",
            device_kind=str(device.device_kind),
        )
    overrides = overrides or {}
    shapes = dict(batch=batch, frames=frames, height=height, width=width)
    shape = [batch or "auto", VIEWS, frames, height, width]
    cpus = cpu_count()
    base = dict(shape=shape, backend=jax.default_backend(), device_kind=str(device.device_kind), cpus=cpus)
    rows = []

    def idle_check(what):
        busy = busy_cpus()
        if busy is not None and busy > 0.5:
            print(
                f"note: other processes kept {busy} of {os.cpu_count()} CPUs busy just before timing {what}: "
                f"its timings (PyTorch's especially) are not those of an idle machine",
                file=sys.stderr,
                flush=True,
            )
        return busy

    def report(r, ctx, impl):
        tps = r["video_tokens"] / r["step_s"]
        achieved = None if r["flops"] is None else r["flops"] / r["step_s"] / 1e12
        ctx = dict(ctx, impl=impl, tokens=r["video_tokens"])
        if "batch" in r:
            ctx["shape"] = [r["batch"], *ctx["shape"][1:]]
        figure(BENCH, "params", r["params"], "parameters", **ctx)
        figure(BENCH, "step_time", round(1e3 * r["step_s"], 2), "ms", **ctx)
        figure(BENCH, "tokens_per_s", round(tps, 1), "tokens/s", **ctx)
        figure(BENCH, "achieved_tflops", None if achieved is None else round(achieved, 6), "TFLOP/s", **ctx)
        row = dict(
            model=ctx["model"],
            impl=impl,
            params=r["params"],
            tokens=r["video_tokens"],
            compile_s=round(r["compile_s"], 1) if "compile_s" in r else "",
            step_ms=round(1e3 * r["step_s"], 1),
            # 4 significant digits, not a whole number: a tiny model's few tokens/s would lose the
            # precision its ratio_to_torch is computed with
            tokens_per_s=float(f"{tps:.4g}"),
            tflops=None if achieved is None else float(f"{achieved:.4g}"),
            preset=ctx["preset"],
            busy_cpus=ctx.get("busy_cpus"),
            **base,
        )
        if "torch_threads" in ctx:
            row["torch_threads"] = ctx["torch_threads"]
        if impl == "jaxdrive":
            figure(BENCH, "compile_time", round(r["compile_s"], 2), "s", **ctx)
            figure(
                BENCH,
                "model_flops_per_step",
                r["flops"],
                "FLOP",
                block_params=r["block_params"],
                matmul_flops=r["matmul_flops"],
                attention_flops=r["attention_flops"],
                text_tokens=r["text_tokens"],
                **ctx,
            )
            figure(BENCH, "xla_flops_per_step", r["xla_flops"], "FLOP", **ctx)
            figure(BENCH, "step_memory", None if r["memory"] is None else round(r["memory"] / 2**20, 2), "MiB", **ctx)
            figure(
                BENCH,
                "batch",
                r["batch"],
                "clips",
                **ctx,
                **(
                    {"probes": r["probes"], "search_s": round(r["batch_search_s"], 1), "limit": fit["limit"]}
                    if "probes" in r
                    else {}
                ),
                **({"oom_backoff": True} if r.get("oom_backoff") else {}),
            )
            figure(
                BENCH,
                "peak_device_memory",
                None if r["peak_bytes"] is None else round(r["peak_bytes"] / 2**20, 1),
                "MiB",
                **ctx,
            )
            row.update(batch=r["batch"], peak_mib=None if r["peak_bytes"] is None else round(r["peak_bytes"] / 2**20))
            for rank, cost in enumerate((r.get("profile") or {}).get("top", []), 1):
                figure(
                    BENCH,
                    "profile_cost",
                    cost["ms_per_step"],
                    "ms",
                    rank=rank,
                    **{k: v for k, v in cost.items() if k != "ms_per_step"},
                    trace=r["profile"]["trace"],
                    device_ms_per_step=r["profile"]["device_ms_per_step"],
                    **ctx,
                )
            if achieved is None or peak_t is None:
                why = peak_note if peak_t is None else "no analytic FLOPs for this layout"
                figure(BENCH, "mfu", None, "fraction", reason=why, **ctx)
                row["mfu"] = None
            else:
                row["mfu"] = round(achieved / peak_t, 4)
                figure(BENCH, "mfu", row["mfu"], "fraction", peak_tflops=peak_t, peak_source=peak_note, **ctx)
            if measured is not None and achieved is not None:
                row.update(
                    mfu_measured=float(f"{achieved / measured:.4g}"), measured_peak_tflops=float(f"{measured:.4g}")
                )
                figure(
                    BENCH,
                    "mfu_measured",
                    row["mfu_measured"],
                    "fraction",
                    peak_tflops=row["measured_peak_tflops"],
                    peak_source=f"measured bf16 {peak_size}^3 matmul",
                    **ctx,
                )
        rows.append(row)
        return tps

    def measure(cfg, what, **extra):
        busy = idle_check(what)
        return jax_step(cfg, mesh, repeats=repeats, **shapes, **extra), {"busy_cpus": busy}

    for name in presets:
        cfg = preset(name, **overrides)
        partner = name if cfg.layout == "full" else f"{name}-full"
        if compare_only and partner not in PRESETS:
            raise ValueError(
                f"--presets: expected presets with a full-layout partner for --compare-only, got "
                f"{name!r} (no {partner!r})"
            )
        if not compare_only:
            r, how = measure(
                cfg,
                name,
                fit=fit,
                profile_steps=profile_steps,
                profile=None if profile is None else os.path.join(profile, name.replace("/", "_")),
            )
            report(r, dict(base, preset=name, model=name, layout=cfg.layout, **how), "jaxdrive")
        if not use_torch or partner not in PRESETS:
            continue
        dcfg = diffusers_config(preset(partner), frames=frames, height=height, width=width)
        jcfg = config_from_diffusers(dcfg).replace(**overrides)
        rj, how = measure(jcfg, f"{partner}/diffusers (jaxdrive)")
        ctx = dict(base, preset=name, model=f"{partner}/diffusers", layout="full")
        rj_ctx = dict(ctx, **how)
        busy = idle_check(f"{partner}/diffusers (torch)")
        rt = torch_step(dcfg, repeats=repeats, threads=torch_threads or cpus, **shapes)
        if rt["params"] != rj["params"]:
            raise RuntimeError(
                f"{partner}: expected the same parameter count in jaxdrive and diffusers, got "
                f"{rj['params']} and {rt['params']}"
            )
        rt = dict(rt, **{k: rj[k] for k in ("flops", "video_tokens")})
        jax_tps = report(rj, rj_ctx, "jaxdrive")
        torch_tps = report(rt, dict(ctx, torch_threads=rt["threads"], busy_cpus=busy), "torch")
        rows[-1]["ratio_to_torch"] = rows[-2]["ratio_to_torch"] = round(jax_tps / torch_tps, 3)
        figure(
            BENCH,
            "torch_ratio",
            round(jax_tps / torch_tps, 4),
            "x",
            preset=name,
            model=ctx["model"],
            params=rj["params"],
            torch_threads=rt["threads"],
            diffusers_config=dcfg,
            meaning="jaxdrive tokens/s / diffusers PyTorch tokens/s",
            **base,
        )
        if micro:
            for row in op_rows(
                preset(partner),
                tokens=batch * (rj["video_tokens"] // batch + dcfg["max_text_seq_length"]),
                threads=rt["threads"],
                repeats=max(20, 4 * repeats),
            ):
                rows.append(dict(row, preset=name, **base))
                figure(BENCH, "op_time", row["step_ms"], "ms", **{k: v for k, v in rows[-1].items() if k != "step_ms"})
    if as_json:
        for row in rows:
            print(json.dumps(row, sort_keys=True), flush=True)
        return rows
    print(
        table(
            rows,
            [
                "model",
                "impl",
                "params",
                "batch",
                "tokens",
                "compile_s",
                "step_ms",
                "tokens_per_s",
                "tflops",
                "mfu",
                "mfu_measured",
                "peak_mib",
                "ratio_to_torch",
            ],
        )
    )
    if peak_t is None:
        print(f"MFU: {peak_note}")
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench train", description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", nargs="+", default=["tiny", "small"])
    parser.add_argument(
        "--batch",
        default=str(DEFAULTS["batch"]),
        help="clips per step, or 'auto': the largest that fits the device's memory (--no-torch)",
    )
    parser.add_argument("--max-batch", type=int, default=64, help="--batch auto: the largest batch tried")
    parser.add_argument(
        "--memory-fraction",
        type=float,
        default=0.95,
        help="--batch auto: the fraction of the device's memory a step may use",
    )
    parser.add_argument(
        "--device-memory",
        default=None,
        help="--batch auto: the device's memory (e.g. 80GiB; default: its allocator's limit)",
    )
    parser.add_argument(
        "--profile",
        default=None,
        metavar="DIR",
        help="trace --profile-steps steps of each jaxdrive model with jax.profiler into DIR and "
        "print their largest device costs",
    )
    parser.add_argument("--profile-steps", type=int, default=2)
    parser.add_argument("--frames", type=int, default=DEFAULTS["frames"], help="latent frames")
    parser.add_argument("--height", type=int, default=DEFAULTS["height"], help="latent height")
    parser.add_argument("--width", type=int, default=DEFAULTS["width"], help="latent width")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--no-torch", action="store_true", help="skip the diffusers PyTorch comparison")
    parser.add_argument(
        "--compare-only",
        action="store_true",
        help="only the comparison with PyTorch (the full-layout partners), not the presets",
    )
    parser.add_argument(
        "--torch-threads",
        type=int,
        default=None,
        help="PyTorch intra-op threads (default: the CPUs XLA:CPU uses, those of this process)",
    )
    parser.add_argument(
        "--peak-tflops",
        type=float,
        default=None,
        help="peak TFLOP/s of the device for the MFU (default: known accelerators only)",
    )
    parser.add_argument(
        "--dtype",
        choices=("float32", "bfloat16"),
        default=None,
        help="compute dtype of the jaxdrive models (params stay float32)",
    )
    parser.add_argument("--remat", default=None, help="remat policy of the jaxdrive models (DiTConfig.remat)")
    parser.add_argument("--attn-impl", default=None, help="attention implementation (DiTConfig.attn_impl)")
    parser.add_argument(
        "--local-attn-impl", default=None, help="temporal and cross-attention kernel (DiTConfig.local_attn_impl)"
    )
    parser.add_argument(
        "--cross-attn-impl", default=None, help="text / control cross-attention kernel (DiTConfig.cross_attn_impl)"
    )
    parser.add_argument("--scan-layers", action="store_true", help="lax.scan over the jaxdrive models' layers")
    parser.add_argument(
        "--measure-peak",
        type=int,
        nargs="?",
        const=8192,
        default=None,
        metavar="N",
        help="time an N^3 bf16 matmul (default 8192) and give the MFU against it too",
    )
    parser.add_argument(
        "--topology",
        default=None,
        help='compile only, for one chip of a Cloud TPU slice (e.g. v5p-8; pip install -e ".[tpu]"), and '
        "print XLA:TPU's roofline estimate of each preset's step instead of timing it (jaxdrive.bench.roofline)",
    )
    parser.add_argument(
        "--no-ops", action="store_true", help="skip the single-operation comparison with PyTorch (jaxdrive.bench.ops)"
    )
    parser.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object per row (model, impl, step_ms, tokens_per_s, ratio_to_torch, "
        "...) instead of the figures and the table",
    )
    args = parser.parse_args(argv)
    if args.batch == "auto":
        args.batch = None
        if not args.no_torch:
            parser.error("--batch: 'auto' searches the jaxdrive step alone; expected --no-torch with it")
    else:
        try:
            args.batch = int(args.batch)
        except ValueError:
            parser.error(f"--batch: expected an integer >= 1 or 'auto', got {args.batch!r}")
    if not 0.0 < args.memory_fraction <= 1.0:
        parser.error(f"--memory-fraction: expected a fraction in (0, 1], got {args.memory_fraction}")
    if args.no_torch and args.compare_only:
        parser.error("--no-torch, --compare-only: expected at most one of them, got both")
    for name in ("batch", "max_batch", "frames", "height", "width", "repeats", "torch_threads", "profile_steps"):
        value = getattr(args, name)
        if value is not None and value < 1:
            parser.error(f"--{name.replace('_', '-')}: expected an integer >= 1, got {value}")
    overrides = {
        k: v
        for k, v in (
            ("dtype", args.dtype),
            ("remat", args.remat),
            ("attn_impl", args.attn_impl),
            ("local_attn_impl", args.local_attn_impl),
            ("cross_attn_impl", args.cross_attn_impl),
            ("scan_layers", args.scan_layers or None),
        )
        if v is not None
    }
    if overrides.get("dtype", "float32") != "float32" and not args.no_torch and args.topology is None:
        parser.error(f"--dtype: the PyTorch comparison runs float32; expected float32 or --no-torch, got {args.dtype}")
    if args.measure_peak is not None and args.measure_peak < 1:
        parser.error(f"--measure-peak: expected an integer >= 1, got {args.measure_peak}")
    if args.topology is not None:
        for flag, given in (
            ("--batch auto", args.batch is None),
            ("--compare-only", args.compare_only),
            ("--profile", args.profile is not None),
            ("--measure-peak", args.measure_peak is not None),
        ):
            if given:
                parser.error(f"--topology: compiles only; expected no {flag} with it, got {flag}")
        from jaxdrive.bench import roofline

        return roofline.run(
            args.presets,
            args.topology,
            batch=args.batch,
            frames=args.frames,
            height=args.height,
            width=args.width,
            overrides=overrides,
            as_json=args.json,
        )
    fit = None
    if args.batch is None:
        import jax

        from jaxdrive.train.plan import parse_bytes

        try:
            given = None if args.device_memory is None else parse_bytes(args.device_memory)
            limit, source = device_memory_limit(jax.devices()[0], given, args.memory_fraction)
        except ValueError as err:
            parser.error(str(err))
        fit = {"limit": limit, "max_batch": args.max_batch, "source": source}
    return run(
        args.presets,
        batch=args.batch,
        frames=args.frames,
        height=args.height,
        width=args.width,
        repeats=args.repeats,
        use_torch=not args.no_torch,
        compare_only=args.compare_only,
        peak=args.peak_tflops,
        torch_threads=args.torch_threads,
        micro=not args.no_ops,
        as_json=args.json,
        overrides=overrides,
        peak_size=args.measure_peak,
        fit=fit,
        profile=args.profile,
        profile_steps=args.profile_steps,
    )


if __name__ == "__main__":
    main()
