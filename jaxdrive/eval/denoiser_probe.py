"""Where a DiT loses to its baselines: its clean-data estimate per noise level, on training and on
held-out windows, against repeating the last given frame and (warp-guided models) the warp.

    python -m jaxdrive.eval.denoiser_probe --workdir RUN [--levels 1,0.7,0.4,0.1] [--batches 4]

A sample is decided by the model's estimate of the clean frames at each level it passes: at level
1 (pure noise) that estimate is the model's guess of the conditional mean, the PSNR-optimal
prediction, and a rollout that starts below a baseline there cannot end above it. The probe noises
each window's non-given frames to one level (the given frames as the sampler gives them: clean, or
noised to ``flow.given_noise_sample`` and told so), reads the estimate ``x_t - sigma v`` and scores
it in the latents against the window's own clean latents, beside the two baselines' scores. Two
splits: ``train`` (the training pipeline's windows, the route mix included: what the loss saw) and
``validation`` (held-out scenes): a model above its baselines on the first and below them on the
second generalises poorly; one below them on both lacks capacity or steps. No condition is dropped
(``data.drop_prob=0``).

PSNR is ``10 log10(4 / MSE)`` in the latents' units (a peak-to-peak range of 2: for the
space-to-depth codec it is the pixels' PSNR). :func:`latent_psnr` is the score;
:func:`probe_run` the measurement; the command line prints a table.

Beside each PSNR, the token grid each estimate draws: the decoded estimate's
:func:`jaxdrive.eval.token_grid.grid_contrast` at the token's footprint (1: none; the clean
windows' and the warp's own figures beside), so the level at which a model draws its token grid
into a sample shows: a grid in the estimate at a low level, whose input is nearly the clean
gridless frame, is the head redrawing its input (``DiTConfig.sigma_data`` lets it pass through); a
grid from pure noise is committed before the detail.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.eval.token_grid import grid_contrast
from jaxdrive.validate import check_positive_int

SPLITS = ("train", "validation")


def latent_psnr(estimate, target, mask) -> float:
    """PSNR (peak-to-peak 2) of ``estimate`` against ``target`` (``[B, V, F, h, w, C]``) over the
    frames where ``mask [B, F]`` is True: ``10 log10(4 / MSE)``. An exact estimate gives inf."""
    e, t, m = np.asarray(estimate, np.float64), np.asarray(target, np.float64), np.asarray(mask, bool)
    if e.shape != t.shape:
        raise ValueError(f"estimate: expected the target's shape {list(t.shape)}, got {list(e.shape)}")
    if m.shape != (t.shape[0], t.shape[2]):
        raise ValueError(f"mask: expected [B, F] = {[t.shape[0], t.shape[2]]}, got {list(m.shape)}")
    if not m.any():
        raise ValueError("mask: expected at least one frame to score, got none")
    return _psnr([_squared(e, t, m)])


def check_levels(levels) -> tuple[float, ...]:
    """``levels`` as a tuple of noise levels in (0, 1]; a ``ValueError`` naming ``levels`` else."""
    out = tuple(float(v) for v in levels)
    if not out or any(not 0 < v <= 1 for v in out):
        raise ValueError(f"levels: expected noise levels in (0, 1], got {list(out)}")
    return out


def _estimates(training, params, codec_params, inputs, level: float, given_level: float, key):
    """Clean-data estimates at ``level`` with their targets and baselines, in the latents."""
    from jaxdrive import flow

    m = training.model
    x = training.codec.encode(codec_params, inputs["video"])
    cond = inputs["cond"]
    warp = None
    if m.controls.warp:
        warp = training.codec.encode(codec_params, inputs["warp_video"])
        cond = cond.replace(warp=warp)
    b, nf = x.shape[0], x.shape[-4]
    k = training.flow.cond_frames
    given = jnp.broadcast_to(jnp.arange(nf) < k, (b, nf))
    levels = jnp.where(given, 0.0, level).astype(jnp.float32)
    k_noise, k_given = jax.random.split(key)
    x_t = flow.add_noise(x, jax.random.normal(k_noise, x.shape, jnp.float32), levels)
    if m.controls.cond_frames is not None:
        cond = cond.replace(cond_latents=x, cond_mask=given)
        if given_level > 0:
            noisy, cond_sigma = flow.noise_given_frames(
                x, jax.random.normal(k_given, x.shape, jnp.float32), given, jnp.full((b,), given_level)
            )
            cond = cond.replace(cond_latents=noisy, cond_sigma=cond_sigma)
    v = flow.velocity_from_output(
        training.dit.forward(params, x_t, levels, cond), x_t, levels, m.prediction, m.prediction_min_sigma
    )
    estimate = flow.data_from_velocity(x_t, v, levels)
    repeat = jnp.broadcast_to(x[:, :, k - 1 : k], x.shape)
    return x, ~given, estimate, repeat, warp


def probe_run(workdir, *, levels=(1.0, 0.7, 0.4, 0.1), batches: int = 4, splits=SPLITS, seed: int = 0) -> dict:
    """Per split and level, the PSNR of the model's clean-data estimate, of repeating the last
    given frame and (warp-guided) of the warp, over ``batches`` batches of the run's pipeline,
    with the token-grid contrast of each (decoded) estimate, of the clean windows and of the warp:
    ``{split: {"levels": {level: psnr}, "repeat": psnr, "warp": psnr or None, "windows": n,
    "grid": {level: contrast}, "grid_clean": contrast, "grid_warp": contrast or None}}``."""
    from jaxdrive.config import override
    from jaxdrive.train.common import load_run_config
    from jaxdrive.train.run import Run, restore_params

    levels = check_levels(levels)
    check_positive_int("batches", batches)
    for s in splits:
        if s not in SPLITS:
            raise ValueError(f"splits: expected names from {list(SPLITS)}, got {s!r}")
    config = override(load_run_config(workdir), "data.drop_prob=0.0")
    run = Run(config)
    _, params = restore_params(run, workdir)
    t = run.training
    if t.model.controls.cond_frames is None or config.flow.cond_frames < 1:
        raise ValueError(
            f"workdir: expected a model given frames (controls.cond_frames and flow.cond_frames >= 1), got "
            f"controls.cond_frames={t.model.controls.cond_frames!r}, flow.cond_frames={config.flow.cond_frames}"
        )
    if t.codec.temporal > 1:
        raise ValueError(f"workdir: expected frame-wise latents (temporal compression 1), got {t.codec.temporal}")
    # the pipeline's batch as a train step's one micro-batch, sharded over the run's mesh
    given_level = config.flow.given_noise_sample
    token = t.model.patch[-1] * t.model.vae_spatial  # the token's footprint in pixels
    decode = jax.jit(lambda c, z: t.codec.decode(c, z))

    def grid(z, mask) -> np.ndarray:  # per scored frame, the decoded latents' token grid
        with jax.set_mesh(run.mesh):
            video = np.asarray(jax.device_get(decode(run.codec.params, z)))  # [B, V, F, H, W, 3]
        per_frame = np.stack([grid_contrast(video[i], token) for i in range(video.shape[0])])  # [B, F]
        return per_frame[np.asarray(mask)]

    fn = jax.jit(
        lambda p, c, inp, level, key: _estimates(
            t, p, c, jax.tree_util.tree_map(lambda a: a[0], inp), level, given_level, key
        )
    )
    out = {}
    for split in splits:
        it = iter(run.dataset(split))
        sq: dict = {lv: [] for lv in levels}
        grids: dict = {lv: [] for lv in levels}
        base: dict = {"repeat": [], "warp": [], "grid_clean": [], "grid_warp": []}
        n = 0
        for i in range(batches):
            try:
                batch = next(it)
            except StopIteration:
                break
            inputs = run.global_batch([batch])
            inputs.pop("warp", None)
            for j, lv in enumerate(levels):
                with jax.set_mesh(run.mesh):
                    res = fn(params, run.codec.params, inputs, lv, jax.random.key(seed * 1000 + i * 17 + j))
                x, mask, est, rep, warp = jax.device_get(res)
                sq[lv].append(_squared(est, x, mask))
                grids[lv].append(grid(est, mask))
            base["repeat"].append(_squared(rep, x, mask))
            base["grid_clean"].append(grid(x, mask))
            if warp is not None:
                base["warp"].append(_squared(warp, x, mask))
                base["grid_warp"].append(grid(warp, mask))
            n += x.shape[0]
        if n == 0:
            raise ValueError(f"splits: the {split} split of {config.data.path} gave no window")
        out[split] = {
            "levels": {lv: _psnr(sq[lv]) for lv in levels},
            "repeat": _psnr(base["repeat"]),
            "warp": _psnr(base["warp"]) if base["warp"] else None,
            "windows": n,
            "grid": {lv: _mean(grids[lv]) for lv in levels},
            "grid_clean": _mean(base["grid_clean"]),
            "grid_warp": _mean(base["grid_warp"]) if base["grid_warp"] else None,
        }
    return out


def _squared(e, t, mask) -> np.ndarray:
    """Per scored frame, the mean squared error (``[N]``)."""
    return np.square(np.asarray(e, np.float64) - np.asarray(t, np.float64)).mean(axis=(1, 3, 4, 5))[np.asarray(mask)]


def _mean(chunks) -> float:
    return float(np.concatenate(chunks).mean())


def _psnr(chunks) -> float:
    mse = float(np.concatenate(chunks).mean())
    return float("inf") if mse == 0 else float(10 * np.log10(4.0 / mse))


def _print_table(res, levels, keys, fmt, labels) -> None:
    """One markdown row per split: the figure per level, then the two baselines ("-": none)."""
    per_level, first, second = keys
    print("| split | windows | " + " | ".join(f"level {lv:g}" for lv in levels) + f" | {' | '.join(labels)} |")
    print("|---|---|" + "---|" * (len(levels) + 2))
    for split, r in res.items():
        cells = [fmt.format(r[per_level][lv]) for lv in levels]
        cells += ["-" if r[k] is None else fmt.format(r[k]) for k in (first, second)]
        print(f"| {split} | {r['windows']} | " + " | ".join(cells) + " |")


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", required=True, help="a DiT run")
    ap.add_argument("--levels", default="1,0.7,0.4,0.1", help="noise levels in (0, 1], comma-separated")
    ap.add_argument("--batches", type=int, default=4, help="pipeline batches per split")
    ap.add_argument("--splits", default=",".join(SPLITS), help="train and/or validation")
    args = ap.parse_args(argv)
    try:
        levels = check_levels(float(v) for v in args.levels.split(","))
    except ValueError:
        raise ValueError(f"--levels: expected comma-separated noise levels in (0, 1], got {args.levels!r}") from None
    res = probe_run(args.workdir, levels=levels, batches=args.batches, splits=tuple(args.splits.split(",")))
    print("clean-data estimate, PSNR dB in the latents (non-given frames of each window):")
    _print_table(res, levels, ("levels", "repeat", "warp"), "{:.2f}", ("repeat", "warp"))
    print("\ntoken grid of the decoded estimate (grid contrast, 1: none; the clean windows' beside):")
    _print_table(res, levels, ("grid", "grid_clean", "grid_warp"), "{:.3f}", ("clean", "warp"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
