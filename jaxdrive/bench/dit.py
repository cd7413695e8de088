"""The diffusion transformer under sequence parallelism: forward + backward time, tokens per second
and compiled memory per device as the ``seq`` axis grows.

    python -m jaxdrive.bench.dit [--presets tiny small] [--seq 1 2 4 8] [--repeats 2]

For each preset and each ``seq`` size the benchmark compiles one training-style step (the gradient
of a loss on the network output w.r.t. the parameters) on a mesh ``seq = n`` of the first n
devices, with the spatial patches sharded over ``seq`` (spatial attention runs as ring attention,
temporal and cross-attention stay local). Memory is the compiled program's per-device temporary
and argument memory (``memory_analysis()``); time is the best of ``--repeats`` runs after a warm-up.
On a CPU host the devices are fake (one process, shared cores), so times measure overhead and
scaling of the program, not a speed-up; memory per device is what sharding buys.
"""

from __future__ import annotations

import argparse

# shapes per preset: (batch, views, latent frames, latent height, latent width)
SHAPES = {
    "tiny": (1, 2, 4, 16, 16),
    "small": (1, 6, 4, 16, 32),
    "tiny-full": (1, 2, 4, 16, 16),
    "small-full": (1, 6, 4, 16, 32),
}


def run(presets, seq_sizes, repeats):
    import time

    import jax
    import jax.numpy as jnp

    from jaxdrive.bench.report import best_time, emit, table
    from jaxdrive.models.dit.inputs import example_inputs
    from jaxdrive.models.dit.model import DiT, param_count
    from jaxdrive.models.dit.presets import preset
    from jaxdrive.parallel import make_mesh, shard_params

    name = "dit"
    mib = lambda b: None if b is None else round(b / 2**20, 2)
    rows = []
    for pname in presets:
        cfg = preset(pname)
        b, v, f, h, w = SHAPES.get(pname, SHAPES["tiny"])
        dit = DiT(cfg)
        shapes = dict(batch=b, views=v, frames=f, height=h, width=w)
        boxed = dit.init_params(0, boxed=True, **shapes)
        ex = example_inputs(cfg, **shapes)
        lat, sig, cond = ex["latents"], ex["sigma"], ex["cond"]
        tokens = f // cfg.patch[0] * (h // cfg.patch[1]) * (w // cfg.patch[2]) * v * b

        def loss(params, lat, sig, cond):
            return jnp.mean(jnp.square(dit.forward(params, lat, sig, cond) - lat))

        grad = jax.jit(jax.grad(loss))
        n_params = param_count(cfg)
        for n in seq_sizes:
            if n > len(jax.devices()):
                continue
            mesh = make_mesh(seq=n, devices=jax.devices()[:n])
            with jax.set_mesh(mesh):
                params = shard_params(boxed, mesh)
                t0 = time.perf_counter()
                compiled = grad.lower(params, lat, sig, cond).compile()
                compile_s = time.perf_counter() - t0
                step = best_time(lambda: compiled(params, lat, sig, cond), repeats=repeats)
            mem = compiled.memory_analysis()
            row = dict(
                preset=pname,
                params=n_params,
                tokens=tokens,
                seq=n,
                compile_s=round(compile_s, 1),
                fwd_bwd_ms=round(1e3 * step, 1),
                tokens_per_s=round(tokens / step),
                temp_mib=mib(getattr(mem, "temp_size_in_bytes", None)),
                args_mib=mib(getattr(mem, "argument_size_in_bytes", None)),
            )
            ctx = dict(preset=pname, seq=n, tokens=tokens, shape=[b, v, f, h, w], backend=jax.default_backend())
            emit(name, "fwd_bwd_time", row["fwd_bwd_ms"], "ms", **ctx)
            emit(name, "tokens_per_s", row["tokens_per_s"], "tokens/s", **ctx)
            emit(name, "per_device_temp_memory", row["temp_mib"], "MiB", **ctx)
            emit(name, "per_device_argument_memory", row["args_mib"], "MiB", **ctx)
            emit(name, "compile_time", row["compile_s"], "s", **ctx)
            rows.append(row)
        first = next((r for r in rows if r["preset"] == pname and r["seq"] == seq_sizes[0]), None)
        last = next((r for r in rows if r["preset"] == pname and r["seq"] == seq_sizes[-1]), None)
        if first and last and first["temp_mib"]:
            emit(
                name,
                "per_device_temp_memory_ratio",
                round(last["temp_mib"] / first["temp_mib"], 4),
                "ratio",
                preset=pname,
                seq_from=seq_sizes[0],
                seq_to=seq_sizes[-1],
            )
    print(
        table(
            rows,
            ["preset", "params", "tokens", "seq", "compile_s", "fwd_bwd_ms", "tokens_per_s", "temp_mib", "args_mib"],
        )
    )
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench dit", description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", nargs="+", default=["tiny", "small"])
    parser.add_argument("--seq", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args(argv)
    from jaxdrive.bench.report import ensure_devices

    ensure_devices(max(args.seq))
    return run(args.presets, args.seq, args.repeats)


if __name__ == "__main__":
    main()
