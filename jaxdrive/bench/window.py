"""One-shot long windows (``--strategy window``, MagicDrive-V2): the longest window that fits a fixed
per-device memory budget when its tokens are sharded over ``seq`` = 1, 2, 4, 8 devices. It should
grow about linearly with ``seq``: the length is bounded by the mesh, not by one device.

    python -m jaxdrive.bench.window [--seq 1 2 4 8] [--views 6] [--budget-frames 33] [--budget-mib M]

The model is the tiny recipe's DiT (random weights) on latents of 32 x 64 pixels (8 x 16
space-to-depth latents, 32 tokens a frame and view, so every ``seq`` divides them). For each
``seq`` the jitted sampler of one window (:func:`jaxdrive.generate.windows.sample_window`, the
program ``--strategy window`` runs) is compiled for a growing number of latent frames, and its
per-device footprint read from ``compiled.memory_analysis()`` (arguments + outputs + temporaries,
deterministic: nothing runs). The budget is ``--budget-mib``, or by default the footprint of
``--budget-frames`` frames on one device. The longest window under it is found by doubling, then
bisection.
"""

from __future__ import annotations

import argparse
import dataclasses

from jaxdrive.bench.report import emit, ensure_devices, footprint_bytes, table

NAME = "window"
H, W, C = 8, 16, 48


def _model(views: int):
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    from jaxdrive.generate.windows import WindowModel
    from jaxdrive.models.dit.model import DiT
    from jaxdrive.models.dit.presets import preset

    cfg = preset(
        "tiny",
        in_channels=C,
        vae_spatial=4,
        vae_temporal=1,
        patch=(1, 2, 2),
        prediction="data",
        final_conv=32,
        controls=dict(text=None, waypoints=True, fps=True, cond_frames="replace", reference_frame="residual"),
    )
    dit = DiT(cfg)
    params = jax.tree_util.tree_map(
        jnp.asarray, nn.unbox(dit.init_params(0, batch=1, views=views, frames=2, height=H, width=W))
    )
    return WindowModel(dit, params, window=2, cond_frames=2, steps=2, lengths=(1, 2))


def footprint(model, mesh, frames: int, views: int) -> int:
    """Per-device bytes of the compiled one-window sampler for ``frames`` latent frames on ``mesh``."""
    import jax
    import numpy as np

    from jaxdrive.generate.windows import jitted_sample_window, to_mesh
    from jaxdrive.models.dit.conditions import Conditions

    m = dataclasses.replace(model, window=frames)
    x = np.zeros((1, views, frames, H, W, C), np.float32)
    cond = np.zeros((1, frames), bool)
    cond[:, :2] = True
    controls = Conditions(waypoints=np.zeros((1, frames, 2), np.float32), fps=np.full((1,), 12.0, np.float32))
    with jax.set_mesh(mesh):
        args = to_mesh((model.params, x, cond, controls), mesh)
        compiled = jitted_sample_window.lower(m, *args, jax.random.key(0)).compile()
    return footprint_bytes(compiled)


def longest(model, mesh, views: int, budget: int, start: int = 4) -> int:
    """The most latent frames whose window fits ``budget`` bytes per device (0 if none does)."""
    lo, hi = 0, start
    while footprint(model, mesh, hi, views) <= budget:
        lo, hi = hi, hi * 2
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if footprint(model, mesh, mid, views) <= budget else (lo, mid)
    return lo


def run(seqs, views: int, budget_frames: int, budget_mib: float | None):
    import jax

    from jaxdrive.parallel import make_mesh

    model = _model(views)
    one = make_mesh(seq=1, devices=jax.devices()[:1])
    budget = int(budget_mib * 2**20) if budget_mib else footprint(model, one, budget_frames, views)
    rows = []
    for seq in seqs:
        mesh = make_mesh(seq=seq, devices=jax.devices()[:seq])
        frames = longest(model, mesh, views, budget)
        rows.append(
            dict(
                seq=seq,
                longest_latent_frames=frames,
                per_device_mib=round(footprint(model, mesh, frames, views) / 2**20, 1),
                budget_mib=round(budget / 2**20, 1),
            )
        )
        emit(
            NAME,
            "longest_window",
            frames,
            "latent frames",
            seq=seq,
            views=views,
            budget_mib=rows[-1]["budget_mib"],
            backend=jax.default_backend(),
        )
    base = rows[0]["longest_latent_frames"] or 1
    for r in rows:
        r["x_seq1"] = round(r["longest_latent_frames"] / base, 2)
    print(table(rows, ["seq", "longest_latent_frames", "x_seq1", "per_device_mib", "budget_mib"]))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench window", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seq", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--views", type=int, default=6)
    parser.add_argument(
        "--budget-frames", type=int, default=33, help="budget: the footprint of this many frames on one device"
    )
    parser.add_argument("--budget-mib", type=float, help="budget in MiB per device (overrides --budget-frames)")
    args = parser.parse_args(argv)
    bad = [s for s in args.seq if s < 1 or 32 % s]
    if bad:
        parser.error(f"--seq: expected divisors of the 32 tokens a frame, got {bad}")
    ensure_devices(max(args.seq))
    return run(args.seq, args.views, args.budget_frames, args.budget_mib)


if __name__ == "__main__":
    main()
