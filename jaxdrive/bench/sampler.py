"""The jitted sampling loop: compile time and memory flat in the step count, and the cost of
driving the same steps from a Python loop instead of one ``lax.scan``; with ``--model``, the
full DiT's denoising step against diffusers' PyTorch forward.

    python -m jaxdrive.bench.sampler [--steps 10 50] [--shape 1 6 8 16 28 16] [--hidden 256]
    python -m jaxdrive.bench.sampler --model tiny-full small-full [--steps 10] [--frames 5]
                                     [--height 16] [--width 16] [--repeats 5] [--torch-threads N]

Without ``--model`` the model is a stand-in of fixed cost (a per-token MLP modulated by the
per-frame noise level), so the figures isolate the sampler's own overhead.

With ``--model`` (full-layout presets) the sizes become a diffusers ``CogVideoXTransformer3DModel``
config and jaxdrive builds the same network from it (parameter counts checked equal, as in
:mod:`jaxdrive.bench.train`). Per preset it times, as medians over ``--repeats``:

- ``forward``: one jitted ``DiT.forward`` (a bare denoising step's model call, ms per call);
- ``loop``: :func:`jaxdrive.flow.sample` over ``--steps`` Euler steps in one jitted ``lax.scan``
  with that forward as the velocity, in ms per step; ``loop_overhead`` = loop per step / forward
  - 1, the loop's own cost (the Euler update, the schedule, the carry). The forward figure holds
  one call's dispatch, which the loop pays once, so the overhead can come out negative;
- ``torch``: the diffusers forward under ``torch.no_grad()`` on the same inputs and threads;
  ``ratio_to_torch`` = PyTorch ms / jaxdrive forward ms (above 1: jaxdrive is faster).
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import jax.numpy as jnp

from jaxdrive import flow
from jaxdrive.bench.report import best_time, emit, median_time, table, temp_bytes

NAME = "sampler"


def _toy_model(params, x, sigma, cond):
    s = flow.expand_per_frame(sigma, x)
    h = jax.nn.gelu(x @ params["w1"]) * (1.0 + s)
    return h @ params["w2"]


def _init(key, channels, hidden):
    k1, k2 = jax.random.split(key)
    return {
        "w1": jax.random.normal(k1, (channels, hidden)) / channels**0.5,
        "w2": jax.random.normal(k2, (hidden, channels)) / hidden**0.5,
    }


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
        one_step = jax.jit(
            lambda x, pair: flow.sample(velocity, x, jnp.stack(pair), cond_mask=cond_mask, method=method)
        )

        pairs = [(sched[i], sched[i + 1]) for i in range(steps)]

        def python_loop():
            state = x
            for pair in pairs:
                state = one_step(state, pair)
            return state

        loop_s = best_time(python_loop, repeats=3)
        row = dict(
            steps=steps,
            method=method,
            compile_s=round(compile_s, 3),
            scan_ms_per_step=round(1e3 * scan_s / steps, 3),
            loop_ms_per_step=round(1e3 * loop_s / steps, 3),
            temp_mib=None if temp_bytes(compiled) is None else round(temp_bytes(compiled) / 2**20, 2),
        )
        rows.append(row)
        ctx = dict(steps=steps, method=method, shape=list(shape), backend=jax.default_backend())
        emit(NAME, "compile_time", row["compile_s"], "s", **ctx)
        emit(NAME, "scan_time_per_step", row["scan_ms_per_step"], "ms", **ctx)
        emit(NAME, "python_loop_time_per_step", row["loop_ms_per_step"], "ms", **ctx)
        emit(NAME, "temp_memory", row["temp_mib"], "MiB", **ctx)
    print(table(rows, ["steps", "method", "compile_s", "scan_ms_per_step", "loop_ms_per_step", "temp_mib"]))
    return rows


def model_rows(
    presets, *, steps: int, frames: int, height: int, width: int, repeats: int, threads: int | None = None
) -> list[dict]:
    """The ``--model`` comparison (module docstring), one row per preset."""
    import diffusers
    import numpy as np
    import torch

    from jaxdrive.bench.cpus import cpu_count
    from jaxdrive.bench.train_steps import diffusers_config
    from jaxdrive.convert.diffusers_dit import config_from_diffusers
    from jaxdrive.models.dit.inputs import example_inputs
    from jaxdrive.models.dit.model import DiT
    from jaxdrive.models.dit.presets import preset
    from jaxdrive.models.params import count_params

    threads = threads or cpu_count()
    torch.set_num_threads(threads)

    rows = []
    for name in presets:
        if preset(name).layout != "full":
            raise ValueError(f"--model: expected full-layout presets (the diffusers model's layout), got {name!r}")
        dcfg = diffusers_config(preset(name), frames=frames, height=height, width=width)
        cfg = config_from_diffusers(dcfg)
        dit = DiT(cfg)
        shapes = dict(views=1, frames=frames, height=height, width=width)
        params = dit.init_params(0, batch=1, **shapes)
        ex = example_inputs(cfg, batch=1, text_len=cfg.text_len, seed=0, **shapes)
        x, sigma, cond = ex["latents"], jnp.full((1, frames), 0.5, jnp.float32), ex["cond"]
        forward = jax.jit(lambda x, s, c: dit.forward(params, x, s, c))
        sched = flow.frame_schedule(flow.sampling_sigmas(steps), jnp.zeros((1, frames), bool))
        loop = jax.jit(lambda x, sched, c: flow.sample(lambda x, s, c: dit.forward(params, x, s, c), x, sched, cond=c))
        t0 = time.perf_counter()
        compiled = loop.lower(x, sched, cond).compile()
        compile_s = time.perf_counter() - t0
        fwd_s = median_time(lambda: jax.block_until_ready(forward(x, sigma, cond)), repeats=repeats)
        loop_s = median_time(lambda: jax.block_until_ready(compiled(x, sched, cond)), repeats=repeats) / steps

        torch.manual_seed(0)
        model = diffusers.CogVideoXTransformer3DModel(**dcfg).eval()
        if sum(p.numel() for p in model.parameters()) != count_params(params):
            raise RuntimeError(f"{name}: expected the same parameter count in jaxdrive and diffusers")
        hidden = torch.from_numpy(np.asarray(x)[:, 0]).permute(0, 1, 4, 2, 3).contiguous()  # [B, F, C, h, w]
        text = torch.randn(1, dcfg["max_text_seq_length"], dcfg["text_embed_dim"])
        t = torch.full((1,), 500.0)
        with torch.no_grad():
            torch_s = median_time(lambda: model(hidden, text, t, return_dict=False)[0], repeats=repeats)
        row = dict(
            model=f"{name}/diffusers",
            steps=steps,
            params=count_params(params),
            compile_s=round(compile_s, 1),
            forward_ms=round(1e3 * fwd_s, 2),
            loop_ms_per_step=round(1e3 * loop_s, 2),
            loop_overhead=round(loop_s / fwd_s - 1, 4),
            torch_forward_ms=round(1e3 * torch_s, 2),
            ratio_to_torch=round(torch_s / fwd_s, 3),
            torch_threads=threads,
            backend=jax.default_backend(),
        )
        rows.append(row)
        for key, unit in (
            ("forward_ms", "ms"),
            ("loop_ms_per_step", "ms"),
            ("loop_overhead", "fraction"),
            ("torch_forward_ms", "ms"),
            ("ratio_to_torch", "x"),
        ):
            emit(NAME, key, row[key], unit, **{k: v for k, v in row.items() if k not in (key,)})
    print(
        table(
            rows,
            [
                "model",
                "params",
                "steps",
                "compile_s",
                "forward_ms",
                "loop_ms_per_step",
                "loop_overhead",
                "torch_forward_ms",
                "ratio_to_torch",
            ],
        )
    )
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench sampler", description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, nargs="+", default=None, help="default: 10 50; 10 with --model")
    parser.add_argument(
        "--shape", type=int, nargs="+", default=[1, 6, 8, 16, 28, 16], help="latent shape [B, V, F, h, w, C]"
    )
    parser.add_argument("--hidden", type=int, default=256)
    parser.add_argument("--method", choices=flow.sampler.METHODS, default="euler")
    parser.add_argument(
        "--model",
        nargs="+",
        default=None,
        metavar="PRESET",
        help="full-layout DiT presets to compare with diffusers' forward (e.g. tiny-full small-full)",
    )
    parser.add_argument("--frames", type=int, default=5, help="--model: latent frames")
    parser.add_argument("--height", type=int, default=16, help="--model: latent height")
    parser.add_argument("--width", type=int, default=16, help="--model: latent width")
    parser.add_argument("--repeats", type=int, default=5, help="--model: timed calls per figure")
    parser.add_argument("--torch-threads", type=int, default=None, help="--model: PyTorch threads (default: the CPUs)")
    args = parser.parse_args(argv)
    for name in ("frames", "height", "width", "repeats", "torch_threads"):
        value = getattr(args, name)
        if value is not None and value < 1:
            parser.error(f"--{name.replace('_', '-')}: expected an integer >= 1, got {value}")
    if args.steps is None:
        args.steps = [10] if args.model else [10, 50]
    if args.model:
        if len(args.steps) != 1:
            parser.error(f"--steps: expected one step count with --model, got {args.steps}")
        return model_rows(
            args.model,
            steps=args.steps[0],
            frames=args.frames,
            height=args.height,
            width=args.width,
            repeats=args.repeats,
            threads=args.torch_threads,
        )
    if len(args.shape) < 5:
        parser.error(f"--shape: expected [B, ..., F, h, w, C] (5 or more sizes), got {args.shape}")
    return run(args.steps, tuple(args.shape), args.hidden, args.method)


if __name__ == "__main__":
    main()
