"""The jitted sampling loop: compile time and memory flat in the step count, and the cost of
driving the same steps from a Python loop instead of one ``lax.scan``.

    python -m jaxdrive.bench.sampler [--steps 10 50] [--shape 1 6 8 16 28 16] [--hidden 256]

The model is a stand-in of fixed cost (a per-token MLP modulated by the per-frame noise level),
so the figures isolate the sampler's own overhead.
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import jax.numpy as jnp

from jaxdrive import flow
from jaxdrive.bench.report import best_time, emit, table, temp_bytes

NAME = "sampler"


def _toy_model(params, x, sigma, cond):
    s = flow.expand_per_frame(sigma, x)
    h = jax.nn.gelu(x @ params["w1"]) * (1.0 + s)
    return h @ params["w2"]


def _init(key, channels, hidden):
    k1, k2 = jax.random.split(key)
    return {"w1": jax.random.normal(k1, (channels, hidden)) / channels ** 0.5,
            "w2": jax.random.normal(k2, (hidden, channels)) / hidden ** 0.5}


def run(steps_list, shape, hidden, method):
    key = jax.random.PRNGKey(0)
    params = _init(key, shape[-1], hidden)
    x = jax.random.normal(key, shape)
    cond_mask = jnp.zeros((shape[0], shape[-4]), bool).at[:, 0].set(True)
    rows = []
    for steps in steps_list:
        sched = flow.frame_schedule(flow.sampling_sigmas(steps), cond_mask, tpd=True)
        velocity = functools.partial(_toy_model, params)
        sampler = jax.jit(functools.partial(flow.sample, velocity, cond_mask=cond_mask, method=method))
        t0 = time.perf_counter()
        compiled = sampler.lower(x, sched).compile()
        compile_s = time.perf_counter() - t0
        scan_s = best_time(lambda: compiled(x, sched), repeats=3)

        # The same steps driven from Python, one jitted step per call.
        one_step = jax.jit(lambda x, pair: flow.sample(velocity, x, jnp.stack(pair), cond_mask=cond_mask,
                                                        method=method))

        pairs = [(sched[i], sched[i + 1]) for i in range(steps)]

        def python_loop():
            state = x
            for pair in pairs:
                state = one_step(state, pair)
            return state
        loop_s = best_time(python_loop, repeats=3)
        row = dict(steps=steps, method=method, compile_s=round(compile_s, 3),
                   scan_ms_per_step=round(1e3 * scan_s / steps, 3),
                   loop_ms_per_step=round(1e3 * loop_s / steps, 3),
                   temp_mib=None if temp_bytes(compiled) is None else round(temp_bytes(compiled) / 2**20, 2))
        rows.append(row)
        ctx = dict(steps=steps, method=method, shape=list(shape), backend=jax.default_backend())
        emit(NAME, "compile_time", row["compile_s"], "s", **ctx)
        emit(NAME, "scan_time_per_step", row["scan_ms_per_step"], "ms", **ctx)
        emit(NAME, "python_loop_time_per_step", row["loop_ms_per_step"], "ms", **ctx)
        emit(NAME, "temp_memory", row["temp_mib"], "MiB", **ctx)
    print(table(rows, ["steps", "method", "compile_s", "scan_ms_per_step", "loop_ms_per_step", "temp_mib"]))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench sampler", description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[10, 50])
    parser.add_argument("--shape", type=int, nargs="+", default=[1, 6, 8, 16, 28, 16],
                        help="latent shape [B, V, F, h, w, C]")
    parser.add_argument("--hidden", type=int, default=256)
    parser.add_argument("--method", choices=flow.sampler.METHODS, default="euler")
    args = parser.parse_args(argv)
    if len(args.shape) < 5:
        parser.error(f"--shape: expected [B, ..., F, h, w, C] (5 or more sizes), got {args.shape}")
    return run(args.steps, tuple(args.shape), args.hidden, args.method)


if __name__ == "__main__":
    main()
