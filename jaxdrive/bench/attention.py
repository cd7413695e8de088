"""Attention memory and speed: dense against blockwise on one device, and the per-device memory
of ring and all-to-all attention as the ``seq`` axis grows.

    python -m jaxdrive.bench.attention [--lengths 4096 ... 65536] [--seq 1 2 4 8] [--time-max 8192]

Memory is the compiled program's temporary memory (``memory_analysis()``, per device for the
sharded programs) of a forward + backward pass; it needs no run, so it is reported at every
length. Times are measured only up to ``--time-max`` tokens (dense attention at 64k tokens needs
tens of GB). On a CPU host the sharded figures use fake devices, which the benchmark creates.
"""

from __future__ import annotations

import argparse


def _grad_fn(impl, mesh=None, **kw):
    import jax

    from jaxdrive.models.attention import attention

    def loss(q, k, v):
        return attention(q, k, v, impl=impl, mesh=mesh, **kw).astype("float32").sum()
    return jax.jit(jax.grad(loss, argnums=(0, 1, 2)))


def run(lengths, seq_sizes, time_max, heads, dim, block):
    import jax
    import jax.numpy as jnp
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxdrive.bench.report import best_time, emit, table, temp_bytes

    name = "attention"
    mib = lambda b: None if b is None else round(b / 2**20, 2)
    rows = []
    for length in lengths:
        shape = jax.ShapeDtypeStruct((1, length, heads, dim), jnp.float32)
        row = dict(tokens=length)
        for impl in ("xla", "blockwise"):
            fn = _grad_fn(impl, block_q=block, block_k=block) if impl == "blockwise" else _grad_fn(impl)
            compiled = fn.lower(shape, shape, shape).compile()
            row[f"{impl}_temp_mib"] = mib(temp_bytes(compiled))
            emit(name, "temp_memory", row[f"{impl}_temp_mib"], "MiB", impl=impl, tokens=length, heads=heads,
                 dim=dim, backend=jax.default_backend())
            if length <= time_max:
                x = jax.random.normal(jax.random.PRNGKey(0), shape.shape, jnp.float32)
                row[f"{impl}_ms"] = round(1e3 * best_time(lambda: compiled(x, x, x), repeats=2), 1)
                emit(name, "fwd_bwd_time", row[f"{impl}_ms"], "ms", impl=impl, tokens=length, heads=heads,
                     dim=dim, backend=jax.default_backend())
        if row["xla_temp_mib"]:
            row["blockwise_vs_xla"] = round(row["blockwise_temp_mib"] / row["xla_temp_mib"], 4)
            emit(name, "blockwise_temp_fraction_of_dense", row["blockwise_vs_xla"], "ratio", tokens=length)
        for impl in ("ring", "ulysses"):
            for n in seq_sizes:
                if n > len(jax.devices()):
                    continue
                mesh = jax.make_mesh((1, 1, n, 1), ("data", "fsdp", "seq", "tensor"),
                                     axis_types=(AxisType.Explicit,) * 4, devices=jax.devices()[:n])
                sharded = jax.ShapeDtypeStruct(shape.shape, jnp.float32,
                                               sharding=NamedSharding(mesh, P(None, "seq", None, None)))
                compiled = _grad_fn(impl, mesh=mesh).lower(sharded, sharded, sharded).compile()
                row[f"{impl}_seq{n}_mib"] = mib(temp_bytes(compiled))
                emit(name, "per_device_temp_memory", row[f"{impl}_seq{n}_mib"], "MiB", impl=impl,
                     seq=n, tokens=length, heads=heads, dim=dim)
            first, last = row.get(f"{impl}_seq{seq_sizes[0]}_mib"), row.get(f"{impl}_seq{seq_sizes[-1]}_mib")
            if first and last:
                row[f"{impl}_ratio"] = round(last / first, 4)
                emit(name, "per_device_memory_ratio", row[f"{impl}_ratio"], "ratio", impl=impl,
                     seq_from=seq_sizes[0], seq_to=seq_sizes[-1], tokens=length)
        rows.append(row)
    columns = ["tokens", "xla_temp_mib", "blockwise_temp_mib", "blockwise_vs_xla", "xla_ms", "blockwise_ms"]
    columns += [f"{impl}_seq{n}_mib" for impl in ("ring", "ulysses") for n in seq_sizes]
    print(table(rows, columns))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench attention", description=__doc__.split("\n\n")[0])
    parser.add_argument("--lengths", type=int, nargs="+", default=[4096, 8192, 16384, 32768, 65536])
    parser.add_argument("--seq", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--time-max", type=int, default=8192, help="time only lengths up to this")
    parser.add_argument("--heads", type=int, default=8)
    parser.add_argument("--dim", type=int, default=64)
    parser.add_argument("--block", type=int, default=512)
    args = parser.parse_args(argv)
    from jaxdrive.bench.report import ensure_devices
    ensure_devices(max(args.seq))
    return run(args.lengths, args.seq, args.time_max, args.heads, args.dim, args.block)


if __name__ == "__main__":
    main()
