"""The DiT train step on one TPU chip by XLA:TPU's cost model, compiled on this host with no TPU:
``jaxdrive bench train --topology NAME``. An estimate of the compiler's, never a measurement.

What ``compiled.cost_analysis()`` counts, and what this module corrects for (jax 0.10.2, libtpu
0.0.42.1; the experiments: docs/guides/plan.md, "What XLA:TPU's cost model counts"):

- a ``lax.scan`` body is counted once whatever its trip count, so the step is compiled with its
  layers unrolled at two depths, ``d = 1`` and ``d = 2``, and every figure extrapolated to the
  model's depth ``L``: ``c(L) = c(1) + (L - 1) (c(2) - c(1))`` (the layers are identical);
- a Pallas kernel without a ``CostEstimate`` (JAX's splash kernels) adds no FLOPs, and at the top
  level of a program it turns ``optimal_seconds`` into -1 plus the rest. The FLOPs of the
  attentions that run in splash are added from :func:`jaxdrive.bench.flops.step_flops`: the
  model's ``3 x 4 S_q S_k D`` a layer, times 1.5 for what a flash kernel executes (9 matmuls of
  ``S_q S_k D`` forward and backward against the model count's 6), at the chip's peak. Which
  attentions those are: the self-attention with ``attn_impl`` ``"auto"`` (splash on one chip) or
  ``"splash"``, the temporal attention with ``local_attn_impl="splash"``, the text
  cross-attention with ``cross_attn_impl`` (else ``local_attn_impl``) ``"splash"``; the others are
  XLA's own matmuls, which its count already has. ``optimal_seconds`` is reported per layer only,
  ``c(2) - c(1)``, where that marker cancels;
- collectives are costed as HBM traffic (this is a one-chip step: it has none).

The estimate: ``t = max(F / peak, B / HBM bandwidth)`` with ``F`` the extrapolated XLA FLOPs plus
the attention's, ``B`` the extrapolated bytes accessed: a roofline of the whole step (no overlap
lost, no kernel below its roofline), a lower bound on the step time. ``roofline_mfu`` = model FLOPs
/ (t x peak), against the dense bf16 peak of :data:`jaxdrive.bench.flops.PEAK_TFLOPS`.
"""

from __future__ import annotations

import time

from jaxdrive.bench.flops import peak_tflops, step_flops

# HBM bandwidth per chip, GB/s (Cloud TPU's published figures)
HBM_GBPS = {"v4": 1228.0, "v5e": 819.0, "v5p": 2765.0, "v6e": 1640.0}
# matmuls of S_q x S_k x D a flash kernel runs forward + backward (2 + dq's 3 + dkv's 4) against
# the model count's 3 x 2
FLASH_EXECUTED = 9 / 6
COSTS = ("flops", "bytes accessed", "optimal_seconds")


def compiled_costs(compiled) -> dict:
    """``{"flops", "bytes accessed", "optimal_seconds"}`` of a compiled program (0.0 where absent)."""
    cost = compiled.cost_analysis()
    cost = (cost[0] if isinstance(cost, (list, tuple)) else cost) or {}
    return {k: float(cost.get(k) or 0.0) for k in COSTS}


def extrapolate(one: dict, two: dict, depth: int) -> dict:
    """``one + (depth - 1) (two - one)`` for each cost: the program at ``depth`` identical layers
    from the programs at 1 and 2."""
    return {k: one[k] + (depth - 1) * (two[k] - one[k]) for k in one}


def _abstract_step(cfg, mesh, *, batch: int, frames: int, height: int, width: int):
    """The bench's train step (:mod:`jaxdrive.bench.train_steps`) lowered for ``mesh`` from shapes
    only: the state from ``jax.eval_shape``, the batch as ``ShapeDtypeStruct``\\ s."""
    import jax
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxdrive.bench.train_steps import SEED, VIEWS, LatentBatches, bench_inputs, bench_optim
    from jaxdrive.config import FlowConfig
    from jaxdrive.data.batches import stack_micro_batches
    from jaxdrive.train import flow_step
    from jaxdrive.train.common import abstract_train_state

    optim = bench_optim()
    state, optimizer = abstract_train_state(cfg, optim, 1000, mesh, seed=SEED)
    inputs = bench_inputs(cfg, batch, views=VIEWS, frames=frames, height=height, width=width)
    whole = NamedSharding(mesh, P())
    data = jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=whole), stack_micro_batches([inputs])
    )
    training = flow_step.FlowTraining(cfg, FlowConfig(), LatentBatches("space_to_depth", 1))
    shardings = jax.tree_util.tree_map(lambda x: x.sharding, state)
    with jax.set_mesh(mesh):
        step = flow_step.make_train_step(training, optimizer, optim.ema_decay, state_shardings=shardings)
        return step.lower(state, None, data)


def kernel_attention_kinds(cfg) -> tuple[str, ...]:
    """The attentions of ``cfg`` (:func:`jaxdrive.bench.flops.step_flops`'s kinds) that a one-chip TPU
    step runs in the splash kernel, whose FLOPs XLA:TPU's cost model does not count."""
    kernels = {"self": cfg.attn_impl in ("auto", "splash"), "temporal": cfg.local_attn_impl == "splash"}
    kernels["cross"] = cfg.cross_impl == "splash"
    return tuple(k for k, on in kernels.items() if on)


def roofline(cfg, topology: str, *, batch: int, frames: int, height: int, width: int) -> dict:
    """The roofline estimate of ``cfg``'s bench train step on one chip of ``topology`` (module
    docstring). Returns the model FLOPs, the corrected XLA FLOPs and bytes, the compute and memory
    times, ``step_s`` (their max), ``roofline_mfu``, ``layer_optimal_s`` (XLA's per-layer
    ``optimal_seconds``), ``per_depth`` (the raw costs at depths 1 and 2) and ``compile_s``."""
    import flax.linen as nn

    from jaxdrive.bench.train_steps import VIEWS
    from jaxdrive.models.dit.model import DiT, param_trace_shapes
    from jaxdrive.parallel import make_mesh
    from jaxdrive.parallel.topology import topology as find_topology
    from jaxdrive.parallel.topology import topology_devices

    top = find_topology(topology)
    device = topology_devices(topology)[0]
    mesh = make_mesh(devices=[device])
    peak, peak_note = peak_tflops(device, None)
    if peak is None:
        raise ValueError(f"topology: expected a TPU whose bf16 peak is known, got {topology!r} ({peak_note})")
    depth = cfg.depth
    per_depth, compile_s = {}, 0.0
    for d in (1, 2):
        lowered = _abstract_step(
            cfg.replace(depth=d, scan_layers=False), mesh, batch=batch, frames=frames, height=height, width=width
        )
        t = time.perf_counter()
        per_depth[d] = compiled_costs(lowered.compile())
        compile_s += time.perf_counter() - t
    xla = extrapolate(per_depth[1], per_depth[2], depth)
    params = nn.unbox(DiT(cfg).abstract_params(**param_trace_shapes(cfg)))
    model = step_flops(cfg, params, batch=batch, views=VIEWS, frames=frames, height=height, width=width)
    by_kind = model["attention_flops_by_kind"]
    attention = FLASH_EXECUTED * sum(by_kind[k] for k in kernel_attention_kinds(cfg))
    flops = xla["flops"] + attention
    bandwidth = HBM_GBPS[top.generation] * 1e9
    compute_s, memory_s = flops / (peak * 1e12), xla["bytes accessed"] / bandwidth
    step_s = max(compute_s, memory_s)
    layer = {k: per_depth[2][k] - per_depth[1][k] for k in COSTS}
    return dict(
        topology=topology,
        device_kind=str(device.device_kind),
        peak_tflops=peak,
        hbm_gbps=HBM_GBPS[top.generation],
        depth=depth,
        model_flops=model["flops"],
        xla_flops=xla["flops"],
        attention_kernel_flops=attention,
        bytes_accessed=xla["bytes accessed"],
        compute_s=compute_s,
        memory_s=memory_s,
        step_s=step_s,
        roofline_mfu=None if model["flops"] is None else model["flops"] / (step_s * peak * 1e12),
        layer_optimal_s=layer["optimal_seconds"],
        layer_attention_s=attention / depth / (peak * 1e12),
        per_depth={str(d): c for d, c in per_depth.items()},
        compile_s=compile_s,
    )


def run(presets, topology: str, *, batch: int, frames: int, height: int, width: int, overrides: dict, as_json: bool):
    """``jaxdrive bench train --topology``: each preset's :func:`roofline`, printed as figures (one
    JSON line each, ``estimate: "XLA:TPU cost model"``) or with ``as_json`` one row a preset."""
    import json

    from jaxdrive.bench.report import emit, table
    from jaxdrive.models.dit.presets import preset

    try:  # the host runs nothing: JAX's own backend stays the CPU beside libtpu's compile-only devices
        import jax

        jax.config.update("jax_platforms", "cpu")
    except RuntimeError:
        pass
    rows = []
    for name in presets:
        cfg = preset(name, **overrides)
        r = {"model": name, **roofline(cfg, topology, batch=batch, frames=frames, height=height, width=width)}
        r["shape"] = [batch, 1, frames, height, width]
        rows.append(r)
        if as_json:
            print(json.dumps(r, sort_keys=True), flush=True)
            continue
        ctx = dict(model=name, topology=topology, shape=r["shape"], estimate="XLA:TPU cost model, not a measurement")
        emit("train", "roofline_step_ms", round(r["step_s"] * 1e3, 3), "ms", **ctx)
        if r["roofline_mfu"] is not None:
            emit(
                "train",
                "roofline_mfu",
                round(r["roofline_mfu"], 4),
                "fraction of peak",
                peak_tflops=r["peak_tflops"],
                **ctx,
            )
        emit("train", "layer_optimal_ms", round(r["layer_optimal_s"] * 1e3, 3), "ms", **ctx)
    if not as_json:
        for r in rows:
            r.update(
                step_ms=round(r["step_s"] * 1e3, 2),
                compute_ms=round(r["compute_s"] * 1e3, 2),
                memory_ms=round(r["memory_s"] * 1e3, 2),
                mfu=None if r["roofline_mfu"] is None else f"{100 * r['roofline_mfu']:.1f}%",
                layer_ms=round(r["layer_optimal_s"] * 1e3, 3),
            )
        print(f"\nXLA:TPU's roofline estimate on one {topology} chip (compile only, not a measurement):")
        print(table(rows, ["model", "shape", "compute_ms", "memory_ms", "step_ms", "mfu", "layer_ms", "compile_s"]))
    return rows
