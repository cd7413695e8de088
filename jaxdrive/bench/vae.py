"""The 3D causal VAE: memory flat in the video length when chunked, and encode/decode speed.

    python -m jaxdrive.bench.vae [--frames 33 241] [--size 480 720] [--speed-size 64 112]
                                 [--speed-frames 17] [--speed-modes chunked whole] [--speed-ops decode]
                                 [--speed-repeats 2] [--dtype bfloat16] [--arch tiny] [--no-memory]

Memory is read from the compiled programs (``memory_analysis()``; nothing runs), for the
CogVideoX-2B architecture at ``--size``: decoding (and encoding) clips of ``--frames`` frames,
chunked and as one whole-clip pass. ``temp`` is the scratch memory of the program; the output
(the video itself) grows with the length whatever the method, so the flatness target -- the
longest clip's figure at most 1.1x the shortest's -- is checked on ``temp`` (``--no-memory``
skips these compiles). Speed is measured on this machine with random weights of the same
architecture (``--arch tiny``: a small one, for a quick check) in ``--dtype`` at ``--speed-size``,
for each of ``--speed-modes`` and ``--speed-ops`` (decode runs on random latents when encode is not
measured): seconds (the best of ``--speed-repeats`` after a warm-up call), frames/s, the compile
time, the compiled program's scratch memory and, on an accelerator, the device's peak memory so far
in the process (``memory_stats``; it never goes down, so give each measurement a process of its
own for a figure of its own).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from jaxdrive.bench.report import best_time, emit, peak_device_bytes, table, temp_bytes

NAME = "vae"
# --arch: the architecture timed (random weights); "tiny" is a small one for a quick run
ARCHS = {
    "cogvideox-2b": {},
    "tiny": dict(block_out_channels=(8, 8, 16), layers_per_block=1, latent_channels=4, norm_num_groups=4),
}


def _memory(compiled):
    a = compiled.memory_analysis()
    if a is None:
        return None, None
    return a.temp_size_in_bytes, a.output_size_in_bytes


def run(
    frames_list,
    size,
    speed_size,
    speed_frames,
    mode_list,
    *,
    speed_modes=("chunked",),
    speed_ops=("encode", "decode"),
    speed_repeats: int = 2,
    dtype: str = "float32",
    arch: str = "cogvideox-2b",
    memory: bool = True,
):
    from jaxdrive.models.vae.model import CausalVAE, VAEConfig

    vae = CausalVAE(VAEConfig(dtype=dtype, **ARCHS[arch]))
    c = vae.config
    abstract = jax.eval_shape(vae.init, jax.random.PRNGKey(0))
    mib = lambda b: None if b is None else round(b / 2**20, 1)
    rows = []
    h, w = size
    for mode in mode_list if memory else ():
        for frames in frames_list:
            latents = vae.latent_frames(frames)
            z = jax.ShapeDtypeStruct(
                (1, latents, h // c.spatial_compression, w // c.spatial_compression, c.latent_channels), jnp.float32
            )
            x = jax.ShapeDtypeStruct((1, frames, h, w, 3), jnp.float32)
            dec = jax.jit(lambda p, z: vae.decode(p, z, mode=mode)).lower(abstract, z).compile()
            enc = jax.jit(lambda p, x: vae.encode(p, x, mode=mode)).lower(abstract, x).compile()
            (dt, do), (et, eo) = _memory(dec), _memory(enc)
            row = dict(
                mode=mode,
                frames=frames,
                latent_frames=latents,
                decode_temp_mib=mib(dt),
                decode_output_mib=mib(do),
                encode_temp_mib=mib(et),
                encode_output_mib=mib(eo),
            )
            rows.append(row)
            ctx = dict(mode=mode, frames=frames, height=h, width=w, config=arch, dtype=dtype)
            emit(NAME, "decode_temp_memory", row["decode_temp_mib"], "MiB", **ctx)
            emit(NAME, "decode_output_memory", row["decode_output_mib"], "MiB", **ctx)
            emit(NAME, "encode_temp_memory", row["encode_temp_mib"], "MiB", **ctx)
    for mode in mode_list if rows else ():
        first, last = [r for r in rows if r["mode"] == mode][0], [r for r in rows if r["mode"] == mode][-1]
        if first["decode_temp_mib"] and last["decode_temp_mib"]:
            for kind in ("decode", "encode"):
                ratio = round(last[f"{kind}_temp_mib"] / first[f"{kind}_temp_mib"], 3)
                emit(
                    NAME,
                    f"{kind}_temp_ratio",
                    ratio,
                    "ratio",
                    mode=mode,
                    frames_from=first["frames"],
                    frames_to=last["frames"],
                    height=h,
                    width=w,
                    target="<= 1.1 (chunked)",
                )
    if rows:
        print(
            table(
                rows,
                [
                    "mode",
                    "frames",
                    "latent_frames",
                    "decode_temp_mib",
                    "decode_output_mib",
                    "encode_temp_mib",
                    "encode_output_mib",
                ],
            )
        )

    # Speed: random weights of the same architecture (no download).
    params = vae.init(jax.random.PRNGKey(0))
    sh, sw = speed_size
    s = c.spatial_compression
    x = jnp.tanh(jax.random.normal(jax.random.PRNGKey(1), (1, speed_frames, sh, sw, 3)))
    z = jax.random.normal(
        jax.random.PRNGKey(2), (1, vae.latent_frames(speed_frames), sh // s, sw // s, c.latent_channels)
    )
    mib = lambda b: None if b is None else round(b / 2**20, 1)
    speed = []
    for mode in speed_modes:
        for kind in speed_ops:
            fn = vae.encode if kind == "encode" else vae.decode
            arg = x if kind == "encode" else z
            t0 = time.perf_counter()
            compiled = jax.jit(lambda p, a, fn=fn, mode=mode: fn(p, a, mode=mode)).lower(params, arg).compile()
            compile_s = time.perf_counter() - t0
            seconds = best_time(lambda: compiled(params, arg), repeats=speed_repeats)
            if kind == "encode" and "decode" in speed_ops:
                z = compiled(params, x)  # decode what was encoded
            fps = round(speed_frames / seconds, 2)
            peak = mib(peak_device_bytes())
            speed.append(
                dict(
                    op=kind,
                    mode=mode,
                    frames=speed_frames,
                    height=sh,
                    width=sw,
                    seconds=round(seconds, 3),
                    frames_per_s=fps,
                    compile_s=round(compile_s, 1),
                    temp_mib=mib(temp_bytes(compiled)),
                    peak_mib=peak,
                )
            )
            ctx = dict(
                mode=mode,
                frames=speed_frames,
                height=sh,
                width=sw,
                config=arch,
                dtype=dtype,
                backend=jax.default_backend(),
                device=str(jax.devices()[0].device_kind),
            )
            emit(NAME, f"{kind}_seconds", round(seconds, 4), "s", **ctx)
            emit(NAME, f"{kind}_frames_per_s", fps, "frames/s", **ctx)
            emit(NAME, f"{kind}_compile_time", round(compile_s, 2), "s", **ctx)
            emit(NAME, f"{kind}_compiled_temp_memory", mib(temp_bytes(compiled)), "MiB", **ctx)
            emit(NAME, f"{kind}_peak_device_memory", peak, "MiB", note="the process's peak so far", **ctx)
    print(
        table(
            speed,
            ["op", "mode", "frames", "height", "width", "seconds", "frames_per_s", "compile_s", "temp_mib", "peak_mib"],
        )
    )
    return rows, speed


def main(argv=None):
    from jaxdrive.models.vae.model import VAEConfig

    parser = argparse.ArgumentParser(prog="jaxdrive bench vae", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--frames", type=int, nargs="+", default=[33, 241], help="clip lengths (1 + 4k) for the memory figures"
    )
    parser.add_argument("--size", type=int, nargs=2, default=[480, 720], metavar=("H", "W"))
    parser.add_argument("--modes", nargs="+", default=["chunked", "whole"], choices=["chunked", "whole"])
    parser.add_argument("--speed-size", type=int, nargs=2, default=[64, 112], metavar=("H", "W"))
    parser.add_argument("--speed-frames", type=int, default=17)
    parser.add_argument("--speed-modes", nargs="+", default=["chunked"], choices=["chunked", "whole"])
    parser.add_argument("--speed-ops", nargs="+", default=["encode", "decode"], choices=["encode", "decode"])
    parser.add_argument("--speed-repeats", type=int, default=2, help="timed calls after the warm-up (best of)")
    parser.add_argument("--dtype", default="float32", choices=["float32", "bfloat16"], help="compute dtype")
    parser.add_argument("--arch", default="cogvideox-2b", choices=sorted(ARCHS))
    parser.add_argument("--no-memory", action="store_true", help="skip the compiled-memory table (--frames)")
    args = parser.parse_args(argv)
    for f in args.frames + [args.speed_frames]:
        if f < 1 or (f - 1) % 4:
            parser.error(f"--frames/--speed-frames: expected 1 + 4k frames, got {f}")
    if args.speed_repeats < 1:
        parser.error(f"--speed-repeats: expected an integer >= 1, got {args.speed_repeats}")
    s = VAEConfig(**ARCHS[args.arch]).spatial_compression
    for name, (h, w) in (("--size", args.size), ("--speed-size", args.speed_size)):
        if h < 1 or w < 1 or h % s or w % s:
            parser.error(f"{name}: expected positive multiples of the spatial compression {s}, got {h} {w}")
    return run(
        args.frames,
        tuple(args.size),
        tuple(args.speed_size),
        args.speed_frames,
        args.modes,
        speed_modes=args.speed_modes,
        speed_ops=args.speed_ops,
        speed_repeats=args.speed_repeats,
        dtype=args.dtype,
        arch=args.arch,
        memory=not args.no_memory,
    )


if __name__ == "__main__":
    main()
