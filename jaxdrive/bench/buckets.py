"""Mixed resolution / length training: the step time of every bucket of a config and how well the
buckets' batch sizes balance them (MagicDrive-V2 [2411.13807v3] appendix B: each bucket's batch is chosen so
that every step takes about the same time; goal max / min <= 1.25).

    python -m jaxdrive.bench.buckets [--config configs/magicdrive_v2.py:size=tiny,stage=3]
                                     [--devices 8] [--repeats 3] [--views 1] [--set KEY=VALUE ...]

It writes a synthetic dataset long enough for every bucket (one view by default, to keep the
rendering short), draws one batch of each bucket from the run's own pipeline, and times the
run's jitted train step on it (the median of ``--repeats`` steps after one compiling step, each
blocked on its outputs) on the config's mesh over ``--devices`` fake CPU devices. The figures:
seconds per step, steps/s and tokens/s of each bucket, and ``balance`` = the slowest bucket's step
time over the fastest's.

With ``--rebalance`` it then does what the paper did by hand: it times each bucket at a second
batch size (twice its own), and for up to ``--rounds`` rounds fits the line ``step time = a + c *
batch`` through all of each bucket's measured points (least squares), picks the batch (a
multiple of the data-parallel groups, at most ``--max-batch``) that the line puts at the slowest
bucket's configured step time, and times the buckets at those batches; it stops at balance 1.25
and prints the balance of each round and the ``data.buckets`` value of the best round
(probabilities proportional to the batches, so every bucket gets about the same number of
batches an epoch). Batches are made by repeating the drawn samples.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from jaxdrive.bench.report import emit, ensure_devices, table

NAME = "buckets"
DEFAULT = Path(__file__).resolve().parents[2] / "configs" / "magicdrive_v2.py"


def run(
    config_arg: str, sets, repeats: int, views: int, rebalance: bool = False, max_batch: int = 0, rounds: int = 3
) -> dict:
    import jax

    from jaxdrive.config import load_config
    from jaxdrive.data.synthetic import write_synthetic_dataset
    from jaxdrive.train.run import Run

    data = Path(tempfile.mkdtemp(prefix="jaxdrive-bench-buckets-")) / "data"
    config = load_config(config_arg, [f"data.path={data}", f"data.views={views}", *sets])
    run = Run(config)  # checks the buckets; the dataset comes next
    longest = max(b.frames for b in run.buckets)
    write_synthetic_dataset(
        data, train=64, validation=1, views=views, frames=longest * config.data.stride, overwrite=True
    )
    state, optimizer, shardings = run.init_state()
    step, frozen = run.step_fn(optimizer, shardings), run.frozen_params()
    groups = _groups(run)
    batches, it = {}, iter(_drawing_run(config, groups).dataset())
    while len(batches) < len(run.buckets):
        b = next(it)
        key = (b["video"].shape[3], b["video"].shape[4], b["video"].shape[2])
        batches.setdefault(key, b)

    def measure(sizes: dict) -> list[dict]:
        nonlocal state
        jax.clear_caches()  # each round compiles new shapes: the old programs' code pages add up
        rows = []
        with jax.set_mesh(run.mesh):
            for bucket in run.buckets:
                size = sizes[bucket.key]
                batch = run.global_batch([_resize_batch(batches[bucket.key], size // jax.process_count())])
                state, metrics = step(state, frozen, batch)  # compiles this bucket's program
                jax.block_until_ready(metrics)
                times = []
                for _ in range(repeats):
                    t = time.perf_counter()
                    state, metrics = step(state, frozen, batch)
                    jax.block_until_ready(metrics)
                    times.append(time.perf_counter() - t)
                sec = statistics.median(times)
                tokens = run.batch_tokens(batch)
                rows.append(
                    dict(
                        bucket="x".join(map(str, bucket.key)),
                        batch=size,
                        tokens=tokens,
                        step_s=round(sec, 4),
                        steps_per_s=round(1 / sec, 2),
                        tokens_per_s=round(tokens / sec),
                    )
                )
        return rows

    def report(rows, label):
        ctx0 = dict(
            config=config_arg, views=views, backend=jax.default_backend(), devices=jax.device_count(), batches=label
        )
        for r in rows:
            emit(NAME, "step_time", r["step_s"], "s", bucket=r["bucket"], batch=r["batch"], **ctx0)
            emit(NAME, "tokens_per_s", r["tokens_per_s"], "tokens/s", bucket=r["bucket"], batch=r["batch"], **ctx0)
        print(table(rows, ["bucket", "batch", "tokens", "step_s", "steps_per_s", "tokens_per_s"]))
        times = [r["step_s"] for r in rows]
        balance = max(times) / min(times)
        emit(NAME, "balance", round(balance, 2), "max/min step time", buckets=len(rows), **ctx0)
        print(f"balance ({label} batches; slowest / fastest step): {balance:.2f} (goal <= 1.25)")
        return balance

    given = {b.key: b.batch_size for b in run.buckets}
    rows = measure(given)
    out = {"rows": rows, "balance": report(rows, "configured")}
    if not rebalance:
        return out
    # each bucket's time-versus-batch line, refitted through all its points after every round
    points = {b.key: [(r["batch"], r["step_s"])] for b, r in zip(run.buckets, rows)}
    for b, r in zip(run.buckets, measure({k: 2 * v for k, v in given.items()})):
        points[b.key].append((r["batch"], r["step_s"]))
    target = max(r["step_s"] for r in rows)
    best = (out["balance"], given)
    for i in range(rounds):
        sizes = {b.key: _fit_batch(points[b.key], target, groups, max_batch) for b in run.buckets}
        last = measure(sizes)
        for b, r in zip(run.buckets, last):
            points[b.key].append((r["batch"], r["step_s"]))
        balance = report(last, f"rebalanced (round {i + 1})")
        if balance < best[0]:
            best = (balance, sizes)
            out.update(rebalanced=last, rebalanced_balance=balance)
        if balance <= 1.25:
            break
    balance, sizes = best
    print(f"best balance {balance:.2f} with")
    spec = ",".join(f"{'x'.join(map(str, k))}:{v}:{v // groups}" for k, v in sizes.items())
    print(f"data.buckets={spec}")
    return out


def _fit_batch(points, target: float, groups: int, max_batch: int) -> int:
    """The batch (a multiple of ``groups``, at most ``max_batch``) that the least-squares line
    ``step time = a + c * batch`` through a bucket's measured ``points`` puts at ``target``
    seconds (through the origin while only one batch size is measured). All points, not the
    last two: a CPU's step times jitter by 10-20%, and a secant through two noisy points can
    slope the wrong way (round 4 of a 9-bucket run sent a bucket from batch 120 to 2). The
    slope is kept at least a fifth of the proportional one (time / batch)."""
    import numpy as np

    b, t = (np.asarray(v, float) for v in zip(*points))
    proportional = t.mean() / b.mean()
    slope = proportional  # one batch size measured: time ~ batch
    if np.ptp(b) > 0:
        slope = max(float(np.polyfit(b, t, 1)[0]), 0.2 * proportional)
    a = t.mean() - slope * b.mean()
    want = (target - a) / slope
    return int(min(max(1, round(want / groups)) * groups, max_batch or 1 << 30))


def _drawing_run(config, groups: int):
    """A run like ``config``'s whose buckets draw ``groups`` clips a batch: one batch of each is
    all the bench needs (it repeats its samples to any batch), and a large configured batch would
    need that many clips of the bucket in the synthetic dataset (equal shares, whatever the
    configured probabilities)."""
    import dataclasses

    from jaxdrive.data.buckets import parse_bucket_specs
    from jaxdrive.train.run import Run

    if not config.data.buckets:
        return Run(config)
    specs = parse_bucket_specs(config.data.buckets)
    small = tuple(f"{h}x{w}x{f}:{groups}:1" for h, w, f in specs)  # equal shares: each fills
    return Run(dataclasses.replace(config, data=dataclasses.replace(config.data, buckets=small)))


def _groups(run) -> int:
    """Data-parallel groups of the run's mesh (``data x fsdp``): batches are multiples of it."""
    sizes = dict(zip(run.mesh.axis_names, run.mesh.axis_sizes))
    return sizes.get("data", 1) * sizes.get("fsdp", 1)


def _resize_batch(batch, n: int):
    """A pipeline batch with ``n`` samples: its own, repeated (or cut) along the batch axis."""
    import numpy as np

    b = len(batch["index"])

    def fit(v):
        if isinstance(v, dict):
            return {k: fit(x) for k, x in v.items()}
        if isinstance(v, list) and len(v) == b:
            return [v[i % b] for i in range(n)]
        if isinstance(v, np.ndarray) and v.ndim and v.shape[0] == b:
            return v[np.arange(n) % b]
        return v

    return fit(batch)


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench buckets", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=f"{DEFAULT}:size=tiny,stage=3")
    parser.add_argument("--devices", type=int, default=8, help="fake CPU devices (the config's mesh must fit)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--views", type=int, default=1, choices=(1, 6))
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument(
        "--rebalance",
        action="store_true",
        help="fit each bucket's step time to its batch and re-time the buckets at batches that match the slowest one",
    )
    parser.add_argument("--max-batch", type=int, default=64, help="--rebalance: the largest batch it proposes")
    parser.add_argument("--rounds", type=int, default=3, help="--rebalance: refits at most (stops at balance 1.25)")
    args = parser.parse_args(argv)
    ensure_devices(args.devices)
    return run(args.config, args.set, args.repeats, args.views, args.rebalance, args.max_batch, args.rounds)


if __name__ == "__main__":
    main()
