"""The DiT's rectified-flow train step: tokens per second, model FLOPs utilisation, and the
diffusers PyTorch ``CogVideoXTransformer3DModel`` train step on the same CPU at the same size.

    python -m jaxdrive.bench.train [--presets tiny small] [--batch 1 | --batch auto] [--frames 5] [--height 16]
                                   [--width 16] [--repeats 10] [--no-torch | --compare-only]
                                   [--torch-threads N] [--peak-tflops T] [--no-ops] [--json]
                                   [--measure-peak 8192] [--profile DIR] [--dtype bfloat16] [--remat dots]
                                   [--attn-impl cudnn] [--scan-layers]

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

Model FLOPs and MFU: :mod:`jaxdrive.bench.flops`.

On an accelerator (``--no-torch``): ``--batch auto`` times the largest batch whose compiled step fits
``--memory-fraction`` of the device's memory (the allocator's limit, or ``--device-memory``):
:func:`largest_batch` predicts it from two probe compiles (batches 1 and 2, side by side, without
GPU autotuning) and checks the prediction's compile, and an out-of-memory at run time retries once
at 85% of the batch. ``--profile DIR`` traces ``--profile-steps`` more steps with ``jax.profiler``
and names the largest device costs (:func:`jaxdrive.bench.report.trace_costs`, ``profile_cost``
figures); the device's peak memory is printed (``peak_device_memory``; null on a CPU).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import time

from jaxdrive.bench.flops import measured_peak_tflops, peak_tflops, step_flops
from jaxdrive.models.latents import LatentCodec

BENCH = "train"
DEFAULTS = dict(batch=1, frames=5, height=16, width=16)
VIEWS = 1
SEED = 0


@dataclasses.dataclass(frozen=True)
class LatentBatches(LatentCodec):
    """A codec whose "video" already is the latents: the benchmark feeds latents of any channel
    count (space-to-depth only makes ``3 f^2`` channels) and times the DiT step, not a VAE."""

    def encode(self, params, video):
        import jax.numpy as jnp

        return jnp.asarray(video, jnp.float32)


def diffusers_config(cfg, *, frames: int, height: int, width: int) -> dict:
    """A diffusers ``CogVideoXTransformer3DModel`` config with the sizes of the full-layout ``cfg``
    (3D sin-cos positions; the sample size is the benchmark's latent size)."""
    return dict(
        num_layers=cfg.depth,
        num_attention_heads=cfg.heads,
        attention_head_dim=cfg.head_dim,
        in_channels=cfg.in_channels,
        out_channels=cfg.out_dim,
        time_embed_dim=cfg.t_dim,
        text_embed_dim=cfg.text_dim,
        max_text_seq_length=cfg.text_len,
        patch_size=cfg.patch[1],
        sample_height=height,
        sample_width=width,
        sample_frames=(frames - 1) * 4 + 1,
        temporal_compression_ratio=4,
        use_rotary_positional_embeddings=False,
    )


def _optim():
    from jaxdrive.config import OptimConfig

    return OptimConfig(ema_decay=0.0)


# Probe compiles of the batch search skip autotuning (much faster on a GPU; the buffer sizes hardly
# depend on the kernels chosen): only the batch that is timed is compiled with the full options.
PROBE_OPTIONS = {"xla_gpu_autotune_level": 0}
OOM_BACKOFF = 0.85  # an out-of-memory at the searched batch retries once at this fraction of it


def largest_batch(footprints, limit: int, max_batch: int, *, final=None, max_final: int = 3) -> tuple[int, list]:
    """The largest batch ``<= max_batch`` whose step needs at most ``limit`` bytes, from few compiles.

    ``footprints(batches) -> [bytes, ...]`` compiles the probes (batches 1 and 2, together); the
    step's memory is linear in the batch (state + batch x activations), so the line through them
    predicts the batch at ``limit``. ``final(batch) -> bytes`` (default: ``footprints``) then
    compiles that batch; where it is over ``limit`` the line through the two nearest measured
    batches predicts again (at most ``max_final`` compiles). Returns ``(batch, [(batch, bytes),
    ...] in compile order)``; ``ValueError`` when not even a batch of 1 fits."""
    if limit <= 0:
        raise ValueError(f"limit: expected a positive number of bytes, got {limit}")
    if max_batch < 1:
        raise ValueError(f"max_batch: expected an integer >= 1, got {max_batch}")
    final = final or (lambda b: footprints([b])[0])
    first = [1, 2] if max_batch >= 2 else [1]
    known = dict(zip(first, footprints(first)))
    seen = list(known.items())
    if known[1] > limit:
        raise ValueError(
            f"batch: not even a batch of 1 fits: expected at most {limit} bytes per device, the step needs {known[1]}"
        )
    for _ in range(max_final):
        lo = max(b for b, f in known.items() if f <= limit)
        over = [b for b, f in known.items() if f > limit]
        hi = min(over) if over else max_batch + 1
        below = [b for b in known if b < lo]
        b0, b1 = (lo, hi) if over else ((max(below), lo) if below else (lo, lo))
        slope = (known[b1] - known[b0]) / (b1 - b0) if b1 != b0 else 0.0
        guess = max_batch if slope <= 0 else lo + int((limit - known[lo]) // slope)
        guess = min(guess, max_batch, hi - 1)
        if guess <= lo:
            break
        known[guess] = final(guess)
        seen.append((guess, known[guess]))
        if known[guess] <= limit:
            break
    return max(b for b, f in known.items() if f <= limit), seen


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


def _is_oom(err: Exception) -> bool:
    return "RESOURCE_EXHAUSTED" in str(err) or "out of memory" in str(err).lower()


def jax_step(
    cfg,
    mesh,
    *,
    batch: int | None,
    frames: int,
    height: int,
    width: int,
    repeats: int,
    fit: dict | None = None,
    profile: str | None = None,
    profile_steps: int = 2,
) -> dict:
    """Compile and time the library's train step for ``cfg``. ``batch=None``: the largest batch that
    fits (``fit = {"limit": bytes, "max_batch": N}``, :func:`largest_batch`); ``profile``: after
    timing, trace ``profile_steps`` steps into that directory with ``jax.profiler`` and add their
    largest device costs (:func:`jaxdrive.bench.report.trace_costs`)."""
    import concurrent.futures

    import flax.linen as nn
    import jax

    from jaxdrive.bench.report import footprint_bytes, peak_device_bytes, trace_costs
    from jaxdrive.config import FlowConfig
    from jaxdrive.models.dit.inputs import example_inputs
    from jaxdrive.models.dit.model import DiT
    from jaxdrive.models.params import count_params
    from jaxdrive.train import flow_step
    from jaxdrive.train.run import global_micro_batches, sharded_state

    shapes = dict(views=VIEWS, frames=frames, height=height, width=width)
    dit, optim = DiT(cfg), _optim()
    codec = LatentBatches("space_to_depth", 1)
    training = flow_step.FlowTraining(cfg, FlowConfig(), codec)

    def fresh_state():
        boxed = dit.init_params(SEED, boxed=True, batch=1, **shapes)
        shapes_only = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), nn.unbox(boxed))
        return sharded_state(boxed, mesh, optim, 1000, SEED), shapes_only

    def data(b):
        ex = example_inputs(cfg, batch=b, text_len=cfg.text_len, seed=SEED, **shapes)
        # the step draws the levels and supplies the condition frames
        inputs = {"video": ex["latents"], "cond": ex["cond"].replace(cond_latents=None, cond_mask=None, drop={})}
        return global_micro_batches([inputs], mesh)

    (state, optimizer), params_tree = fresh_state()
    shardings = jax.tree_util.tree_map(lambda x: x.sharding, state)
    device = mesh.devices.flat[0]
    out = {}
    with jax.set_mesh(mesh):
        step = flow_step.make_train_step(training, optimizer, optim.ema_decay, state_shardings=shardings)
        compiled_at = {}

        # elsewhere the probe options change nothing, and a probe's program is the one to time
        probe_options = PROBE_OPTIONS if device.platform in ("gpu", "cuda", "rocm") else None

        def compile_at(b):
            if b not in compiled_at:
                t0 = time.perf_counter()
                compiled_at[b] = step.lower(state, None, data(b)).compile()
                out["compile_s"] = time.perf_counter() - t0
            return footprint_bytes(compiled_at[b])

        if batch is None:
            t0 = time.perf_counter()

            def footprints(bs):  # the probes compile side by side
                lowered = [step.lower(state, None, data(b)) for b in bs]
                t1 = time.perf_counter()
                with concurrent.futures.ThreadPoolExecutor(len(bs)) as pool:
                    done = list(pool.map(lambda low: low.compile(probe_options), lowered))
                if probe_options is None:
                    compiled_at.update(zip(bs, done))
                    out["compile_s"] = time.perf_counter() - t1
                return [footprint_bytes(c) for c in done]

            batch, probes = largest_batch(footprints, fit["limit"], fit["max_batch"], final=compile_at)
            out.update(batch_search_s=time.perf_counter() - t0, probes=probes)
            print(
                f"note: batch {batch} fits {fit['limit'] / 2**30:.2f} GiB (batch, bytes: {probes}; "
                f"{out['batch_search_s']:.0f} s)",
                file=sys.stderr,
                flush=True,
            )
        attempts = 2 if fit else 1
        for attempt in range(attempts):
            compiled = compiled_at.pop(batch, None)
            if compiled is None:
                compile_at(batch)
                compiled = compiled_at.pop(batch)
            compiled_at.clear()
            batch_data = data(batch)
            try:
                state, metrics = compiled(state, None, batch_data)  # warm-up
                jax.block_until_ready((state, metrics))
                break
            except jax.errors.JaxRuntimeError as err:
                if attempt + 1 == attempts or not _is_oom(err):
                    raise
                print(
                    f"note: batch {batch} ran out of device memory; again at {max(1, int(batch * OOM_BACKOFF))}",
                    file=sys.stderr,
                    flush=True,
                )
                batch = max(1, int(batch * OOM_BACKOFF))
                out["oom_backoff"] = True
                if any(x.is_deleted() for x in jax.tree_util.tree_leaves(state)):  # donated to the failed call
                    (state, optimizer), _ = fresh_state()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            state, metrics = compiled(state, None, batch_data)
            jax.block_until_ready((state, metrics))
            times.append(time.perf_counter() - t0)
        if profile:
            try:  # the timed figures stand even where the profiler fails
                with jax.profiler.trace(profile, create_perfetto_trace=True):
                    for _ in range(profile_steps):
                        state, metrics = compiled(state, None, batch_data)
                        jax.block_until_ready((state, metrics))
                out["profile"] = trace_costs(profile, steps=profile_steps)
            except Exception as err:  # noqa: BLE001 (reported)
                print(f"note: the profile failed: {type(err).__name__}: {err}", file=sys.stderr, flush=True)
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    xla_flops = (cost or {}).get("flops")
    params = count_params(state.params)
    flops = step_flops(cfg, params_tree, batch=batch, **shapes)
    return dict(
        out,
        batch=batch,
        step_s=statistics.median(times),
        params=params,
        xla_flops=None if xla_flops is None else float(xla_flops),
        memory=footprint_bytes(compiled),
        peak_bytes=peak_device_bytes(device),
        loss=float(metrics["loss"]),
        skipped=int(metrics["skipped"]),
        **flops,
    )


def torch_step(dcfg: dict, *, batch: int, frames: int, height: int, width: int, repeats: int, threads: int) -> dict:
    """Time diffusers' CogVideoX train step (module docstring) for the config ``dcfg``."""
    import diffusers
    import torch

    torch.set_num_threads(threads)
    torch.manual_seed(SEED)
    optim = _optim()
    model = diffusers.CogVideoXTransformer3DModel(**dcfg).train()
    params = sum(p.numel() for p in model.parameters())
    opt = torch.optim.AdamW(
        model.parameters(), lr=optim.lr, betas=(optim.b1, optim.b2), eps=optim.eps, weight_decay=optim.weight_decay
    )
    x = torch.randn(batch, frames, dcfg["in_channels"], height, width)
    text = torch.randn(batch, dcfg["max_text_seq_length"], dcfg["text_embed_dim"])

    def step():
        sigma = torch.sigmoid(torch.randn(batch))  # logit-normal levels
        noise = torch.randn_like(x)
        s = sigma.view(batch, 1, 1, 1, 1)
        v = model((1 - s) * x + s * noise, text, sigma * 1000, return_dict=False)[0]
        loss = torch.nn.functional.mse_loss(v, noise - x)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), optim.clip_norm)
        opt.step()
        return loss.item()  # waits for the step

    step()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        loss = step()
        times.append(time.perf_counter() - t0)
    return dict(step_s=statistics.median(times), params=params, loss=loss, threads=torch.get_num_threads())


def busy_cpus(interval: float = 0.5) -> float | None:
    """CPUs kept busy over ``interval`` seconds while this process waits (``/proc/stat``; None
    where there is none): what other processes take from the benchmark."""

    def read():
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        return sum(v), v[3] + (v[4] if len(v) > 4 else 0)  # total, idle + iowait

    try:
        t0, i0 = read()
        time.sleep(interval)
        t1, i1 = read()
    except (OSError, ValueError, IndexError):
        return None
    total = t1 - t0
    return None if total <= 0 else round((total - (i1 - i0)) / total * (os.cpu_count() or 1), 2)


def cpu_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


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
    :func:`largest_batch`); ``profile``: a directory for a ``jax.profiler`` trace of
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
            ("scan_layers", args.scan_layers or None),
        )
        if v is not None
    }
    if overrides.get("dtype", "float32") != "float32" and not args.no_torch:
        parser.error(f"--dtype: the PyTorch comparison runs float32; expected float32 or --no-torch, got {args.dtype}")
    if args.measure_peak is not None and args.measure_peak < 1:
        parser.error(f"--measure-peak: expected an integer >= 1, got {args.measure_peak}")
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
