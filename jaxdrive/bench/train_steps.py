"""The two train steps ``jaxdrive bench train`` times (its module docstring says how): the
library's jitted rectified-flow step, and diffusers' PyTorch CogVideoX step at the same size."""

from __future__ import annotations

import dataclasses
import statistics
import sys
import time

from jaxdrive.bench.fit import OOM_BACKOFF, PROBE_OPTIONS, is_oom, largest_batch
from jaxdrive.bench.flops import step_flops
from jaxdrive.models.latents import LatentCodec

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


def bench_optim():
    from jaxdrive.config import OptimConfig

    return OptimConfig(ema_decay=0.0)


def bench_inputs(cfg, batch: int, *, views: int, frames: int, height: int, width: int) -> dict:
    """One micro-batch of the bench step's host inputs: latents and random text; the step draws
    the levels and supplies the condition frames."""
    from jaxdrive.models.dit.inputs import example_inputs

    ex = example_inputs(
        cfg, batch=batch, views=views, frames=frames, height=height, width=width, text_len=cfg.text_len, seed=SEED
    )
    return {"video": ex["latents"], "cond": ex["cond"].replace(cond_latents=None, cond_mask=None, drop={})}


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
    from jaxdrive.models.dit.model import DiT
    from jaxdrive.models.params import count_params
    from jaxdrive.train import flow_step
    from jaxdrive.train.run import global_micro_batches, sharded_state

    shapes = dict(views=VIEWS, frames=frames, height=height, width=width)
    dit, optim = DiT(cfg), bench_optim()
    codec = LatentBatches("space_to_depth", 1)
    training = flow_step.FlowTraining(cfg, FlowConfig(), codec)

    def fresh_state():
        boxed = dit.init_params(SEED, boxed=True, batch=1, **shapes)
        shapes_only = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), nn.unbox(boxed))
        return sharded_state(boxed, mesh, optim, 1000, SEED), shapes_only

    def data(b):
        return global_micro_batches([bench_inputs(cfg, b, **shapes)], mesh)

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
                if attempt + 1 == attempts or not is_oom(err):
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
    optim = bench_optim()
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
