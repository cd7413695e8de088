"""The memory planner (:mod:`jaxdrive.train.plan`) against a real train step on one CPU device.

    python -m jaxdrive.bench.plan [--config configs/tiny.py] [--set KEY=VALUE ...]

It plans the config on a one-device mesh, then makes what the plan only shaped: the train state
(:meth:`Run.init_state`), the VAE's parameters (random, CogVideoX-2B's architecture where the config
encodes on the fly and ``latents.vae_path`` holds no saved VAE) and a zero batch of the planned
bucket, and runs the compiled step once. Measured: the bytes of every live ``jax.Array`` before the
step (against the plan's state + frozen + batch) and the step's transient memory, the growth of
the process's peak resident memory while the step runs (Linux ``VmHWM`` after resetting it through
``/proc/self/clear_refs``), against the plan's temporaries plus the outputs that do not reuse the
donated state. Pages of a temporary buffer that the step never touches are not resident, so the
measured transient can sit below the plan.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from jaxdrive.bench.report import emit, ensure_devices, table

NAME = "plan"
DEFAULT = Path(__file__).resolve().parents[2] / "configs" / "tiny.py"


def _vm(key: str) -> int:
    """``VmRSS`` / ``VmHWM`` of this process in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise ValueError(f"/proc/self/status: expected a {key} line, got none")


def _real_codec(latents):
    """The codec of ``latents`` with parameters to run: a saved VAE, or CogVideoX-2B's at random."""
    import jax

    from jaxdrive.models.latents import LatentCodec
    from jaxdrive.models.vae.model import CausalVAE, VAEConfig
    from jaxdrive.train.plan import abstract_codec

    _, what = abstract_codec(latents)
    if latents.source != "vae" or "has none" not in what:
        return LatentCodec.from_config(latents)
    vae = CausalVAE(
        VAEConfig(mode=latents.vae_mode, frame_wise_batch=latents.vae_frame_batch, clip_batch=latents.vae_clip_batch)
    )
    return LatentCodec("vae", 1, 1.0, vae, vae.init(jax.random.PRNGKey(0)))


def measure(config) -> dict:
    """Planned and measured bytes of ``config``'s train step on one device (module docstring)."""
    import jax
    import jax.numpy as jnp

    from jaxdrive.config import MeshConfig
    from jaxdrive.train.plan import (
        abstract_batch,
        accelerator_attention,
        plan_memory,
        planned_bucket,
        resident_bytes,
        transient_bytes,
    )
    from jaxdrive.train.run import Run

    config = accelerator_attention(dataclasses.replace(config, mesh=MeshConfig(data=1)), {})
    device = jax.devices()[:1]
    plan = plan_memory(config, {"data": 1}, devices=device, compile_step=False)["per_device"]
    run = Run(config, devices=device, codec=_real_codec(config.latents), check_data=False)
    state, optimizer, shardings = run.init_state()
    batch = jax.tree_util.tree_map(
        lambda s: jnp.zeros(s.shape, s.dtype, device=s.sharding), abstract_batch(run, planned_bucket(run))
    )
    frozen = run.frozen_params()
    with jax.set_mesh(run.mesh):
        compiled = run.step_fn(optimizer, shardings).lower(state, frozen, batch).compile()
        a = compiled.memory_analysis()
        resident = sum(x.nbytes for x in jax.live_arrays())
        before = _vm("VmRSS")
        Path("/proc/self/clear_refs").write_text("5")  # VmHWM := VmRSS
        jax.block_until_ready(compiled(state, frozen, batch))
        transient = _vm("VmHWM") - before
    planned = {"resident": resident_bytes(plan), "transient": transient_bytes(a)}
    return {
        "planned_resident": planned["resident"],
        "measured_resident": resident,
        "planned_transient": planned["transient"],
        "measured_transient": transient,
        "planned_total": sum(planned.values()),
        "measured_total": resident + transient,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m jaxdrive.bench.plan", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=str(DEFAULT))
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args(argv)
    ensure_devices(1)
    from jaxdrive.config import load_config

    out = measure(load_config(args.config, args.set))
    rows = []
    for part in ("resident", "transient", "total"):
        p, m = out[f"planned_{part}"], out[f"measured_{part}"]
        emit(NAME, part, m, "bytes", planned=p, config=args.config, sets=args.set)
        rows.append(
            {
                "part": part,
                "planned MiB": f"{p / 2**20:.1f}",
                "measured MiB": f"{m / 2**20:.1f}",
                "measured / planned": f"{m / p:.2f}",
            }
        )
    print(table(rows, ["part", "planned MiB", "measured MiB", "measured / planned"]))
    return out


if __name__ == "__main__":
    main()
