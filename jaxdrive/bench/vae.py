"""The 3D causal VAE: memory flat in the video length when chunked, and encode/decode speed.

    python -m jaxdrive.bench.vae [--frames 33 241] [--size 480 720] [--speed-size 64 112]

Memory is read from the compiled programs (``memory_analysis()``; nothing runs), for the
CogVideoX-2B architecture at ``--size``: decoding (and encoding) clips of ``--frames`` frames,
chunked and as one whole-clip pass. ``temp`` is the scratch memory of the program; the output
(the video itself) grows with the length whatever the method, so the flatness target -- the
longest clip's figure at most 1.1x the shortest's -- is checked on ``temp``. Speed (frames/s) is
measured on this machine with random weights of the same architecture at ``--speed-size``.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

from jaxdrive.bench.report import best_time, emit, table, temp_bytes

NAME = "vae"


def _memory(compiled):
    a = compiled.memory_analysis()
    if a is None:
        return None, None
    return a.temp_size_in_bytes, a.output_size_in_bytes


def run(frames_list, size, speed_size, speed_frames, mode_list):
    from jaxdrive.models.vae import CausalVAE, VAEConfig

    vae = CausalVAE(VAEConfig())
    c = vae.config
    abstract = jax.eval_shape(vae.init, jax.random.PRNGKey(0))
    mib = lambda b: None if b is None else round(b / 2**20, 1)
    rows = []
    h, w = size
    for mode in mode_list:
        for frames in frames_list:
            latents = vae.latent_frames(frames)
            z = jax.ShapeDtypeStruct((1, latents, h // c.spatial_compression, w // c.spatial_compression,
                                      c.latent_channels), jnp.float32)
            x = jax.ShapeDtypeStruct((1, frames, h, w, 3), jnp.float32)
            dec = jax.jit(lambda p, z: vae.decode(p, z, mode=mode)).lower(abstract, z).compile()
            enc = jax.jit(lambda p, x: vae.encode(p, x, mode=mode)).lower(abstract, x).compile()
            (dt, do), (et, eo) = _memory(dec), _memory(enc)
            row = dict(mode=mode, frames=frames, latent_frames=latents, decode_temp_mib=mib(dt),
                       decode_output_mib=mib(do), encode_temp_mib=mib(et), encode_output_mib=mib(eo))
            rows.append(row)
            ctx = dict(mode=mode, frames=frames, height=h, width=w, config="cogvideox-2b")
            emit(NAME, "decode_temp_memory", row["decode_temp_mib"], "MiB", **ctx)
            emit(NAME, "decode_output_memory", row["decode_output_mib"], "MiB", **ctx)
            emit(NAME, "encode_temp_memory", row["encode_temp_mib"], "MiB", **ctx)
    for mode in mode_list:
        first, last = [r for r in rows if r["mode"] == mode][0], [r for r in rows if r["mode"] == mode][-1]
        if first["decode_temp_mib"] and last["decode_temp_mib"]:
            for kind in ("decode", "encode"):
                ratio = round(last[f"{kind}_temp_mib"] / first[f"{kind}_temp_mib"], 3)
                emit(NAME, f"{kind}_temp_ratio", ratio, "ratio", mode=mode, frames_from=first["frames"],
                     frames_to=last["frames"], height=h, width=w, target="<= 1.1 (chunked)")
    print(table(rows, ["mode", "frames", "latent_frames", "decode_temp_mib", "decode_output_mib",
                       "encode_temp_mib", "encode_output_mib"]))

    # Speed: random weights of the same architecture (no download); chunked, the default.
    params = vae.init(jax.random.PRNGKey(0))
    sh, sw = speed_size
    x = jnp.tanh(jax.random.normal(jax.random.PRNGKey(1), (1, speed_frames, sh, sw, 3)))
    encode = jax.jit(vae.encode)
    z = encode(params, x)
    decode = jax.jit(vae.decode)
    speed = []
    for kind, fn, arg in (("encode", encode, x), ("decode", decode, z)):
        seconds = best_time(lambda: fn(params, arg), repeats=2)
        fps = round(speed_frames / seconds, 2)
        speed.append(dict(op=kind, frames=speed_frames, height=sh, width=sw, seconds=round(seconds, 3),
                          frames_per_s=fps))
        emit(NAME, f"{kind}_frames_per_s", fps, "frames/s", frames=speed_frames, height=sh, width=sw,
             config="cogvideox-2b", backend=jax.default_backend(), device=str(jax.devices()[0].device_kind))
    print(table(speed, ["op", "frames", "height", "width", "seconds", "frames_per_s"]))
    return rows, speed


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench vae", description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[33, 241],
                        help="clip lengths (1 + 4k) for the memory figures")
    parser.add_argument("--size", type=int, nargs=2, default=[480, 720], metavar=("H", "W"))
    parser.add_argument("--modes", nargs="+", default=["chunked", "whole"], choices=["chunked", "whole"])
    parser.add_argument("--speed-size", type=int, nargs=2, default=[64, 112], metavar=("H", "W"))
    parser.add_argument("--speed-frames", type=int, default=17)
    args = parser.parse_args(argv)
    for f in args.frames + [args.speed_frames]:
        if f < 1 or (f - 1) % 4:
            parser.error(f"--frames/--speed-frames: expected 1 + 4k frames, got {f}")
    return run(args.frames, tuple(args.size), tuple(args.speed_size), args.speed_frames, args.modes)


if __name__ == "__main__":
    main()
