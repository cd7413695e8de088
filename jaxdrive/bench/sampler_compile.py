"""The samplers of a config compiled for one TPU chip, compile only: XLA:TPU's memory of one
window of :func:`jaxdrive.generate.windows.sample_window` (the whole jitted denoising loop), the
VAE decode of that window and, for a model trained frame by frame (STAGE), one streaming frame
with its HTFT buffer (:func:`jaxdrive.generate.streaming.stream_frame`).

    jaxdrive bench sampler_compile --config configs/mila.py:stage=1 --topology v5p-8
    jaxdrive bench sampler_compile --config configs/stage.py:stage=3 --topology v5p-8 --set data.views=6

A sampler runs on one chip per clip (the batch of one window, no mesh to split it over), so the
figure that matters is whether one window fits one chip. The parameters are shapes only (a
paper-size model needs no checkpoint) and the latents the window's; ``--topology`` takes the
accelerator types of ``jaxdrive plan`` and the first chip of the slice is the target.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

GiB = 1 << 30


def _abstract(tree):
    import jax
    import numpy as np

    return jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(np.shape(a), np.asarray(a).dtype), tree)


def compile_samplers(config, topology: str) -> dict:
    """``{"device", "window", "sample_window", "vae_decode", "streaming"}`` of ``config`` on one chip
    of ``topology``: each compiled program's ``compile_seconds``, ``argument_gib``, ``temp_gib``,
    ``output_gib`` and ``mosaic_kernels`` (``streaming`` None unless the model streams)."""
    import jax
    import jax.numpy as jnp

    from jaxdrive.generate.windows import WindowModel, sample_window
    from jaxdrive.models.dit.inputs import example_inputs
    from jaxdrive.parallel.topology import topology_devices
    from jaxdrive.train.plan import abstract_codec
    from jaxdrive.train.run import Run

    devices = topology_devices(topology)[:1]
    config = dataclasses.replace(config, mesh=dataclasses.replace(config.mesh, data=1, fsdp=1, seq=1, tensor=1))
    codec, what = abstract_codec(config.latents)
    run = Run(config, devices=devices, codec=codec, check_data=False)
    abstract, _ = run.abstract_state()
    params = abstract.ema if abstract.ema is not None else abstract.params
    model = dataclasses.replace(WindowModel.from_sampling(run.sampling(), None), params=None)
    d, nf = config.data, run.sampling().latent_window
    h, w = d.height // codec.spatial, d.width // codec.spatial
    loose = dict(cond_latents=None, cond_mask=None, warp=None, features=None, features_mask=None, drop=None)

    def controls(frames):
        ex = example_inputs(model.dit.config, batch=1, views=d.views, frames=frames, height=h, width=w)
        return _abstract(ex["cond"].replace(**loose))

    def figures(lowered, started):
        c = lowered.compile()
        m = c.memory_analysis()
        return {
            "compile_seconds": round(time.perf_counter() - started, 1),
            "argument_gib": m.argument_size_in_bytes / GiB,
            "temp_gib": m.temp_size_in_bytes / GiB,
            "output_gib": m.output_size_in_bytes / GiB,
            "mosaic_kernels": c.as_text().count("tpu_custom_call"),
        }

    x = jax.ShapeDtypeStruct((1, d.views, nf, h, w, codec.channels), jnp.float32)
    mask, key = jax.ShapeDtypeStruct((1, nf), jnp.bool_), jax.random.key(0)
    out = {"device": devices[0].device_kind, "window": {"latent_frames": nf, "views": d.views, "latent_hw": [h, w]}}
    with jax.set_mesh(run.mesh):
        t = time.perf_counter()
        lowered = jax.jit(sample_window, static_argnums=0).lower(model, params, x, mask, controls(nf), key)
        out["sample_window"] = figures(lowered, t)
        t = time.perf_counter()
        out["vae_decode"] = {"codec": what, **figures(jax.jit(codec.decode).lower(codec.params, x), t)}
        out["streaming"] = None
        if model.streaming:
            from jaxdrive.generate.streaming import new_buffer, stream_frame

            one = jax.ShapeDtypeStruct((1, d.views, 1, h, w, codec.channels), jnp.float32)
            buf = jax.eval_shape(lambda: new_buffer(model, 1, d.views, (h, w)))
            t = time.perf_counter()
            lowered = jax.jit(stream_frame, static_argnums=(0, 1)).lower(
                model, model.stream_taps, params, one, one, controls(3), key, buf
            )
            out["streaming"] = {"taps": list(model.stream_taps), **figures(lowered, t)}
    return out


def main(argv=None) -> dict:
    from jaxdrive.config import load_config
    from jaxdrive.parallel.topology import topology

    p = argparse.ArgumentParser(prog="jaxdrive bench sampler_compile", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", required=True, help="a config, e.g. configs/mila.py:stage=1")
    p.add_argument("--topology", default="v5e-1", help="a Cloud TPU accelerator type; its first chip is the target")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config field (repeatable)")
    args = p.parse_args(argv)
    topology(args.topology)  # an unknown name is a ValueError listing the known ones
    config = load_config(args.config, list(args.set or []))
    out = compile_samplers(config, args.topology)
    win = out["window"]
    print(
        f"{args.config} on one {out['device']} chip: a window of {win['latent_frames']} latent frames x "
        f"{win['views']} views of {win['latent_hw'][0]}x{win['latent_hw'][1]} latents (compile only, XLA:TPU)"
    )
    for name in ("sample_window", "vae_decode", "streaming"):
        f = out[name]
        if f is not None:
            print(
                f"  {name}: {f['argument_gib']:.2f} GiB arguments, {f['temp_gib']:.2f} GiB temporaries, "
                f"{f['output_gib']:.3f} GiB out; {f['mosaic_kernels']} Mosaic kernels; "
                f"compiled in {f['compile_seconds']} s"
            )
    return out
