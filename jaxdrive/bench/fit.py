"""The largest train-step batch that fits a device (``jaxdrive bench train --batch auto``): the
step's memory is linear in the batch, so two probe compiles predict it and one more checks it."""

from __future__ import annotations

# Probe compiles of the batch search skip autotuning (much faster on a GPU; the buffer sizes hardly
# depend on the kernels chosen): only the batch that is timed is compiled with the full options.
PROBE_OPTIONS = {"xla_gpu_autotune_level": 0}
OOM_BACKOFF = 0.85  # an out-of-memory at the searched batch retries once at this fraction of it


def largest_batch(footprints, limit: int, max_batch: int, *, final=None, max_final: int = 3) -> tuple[int, list]:
    """The largest batch ``<= max_batch`` whose step needs at most ``limit`` bytes, from few compiles.

    ``footprints(batches) -> [bytes, ...]`` compiles the probes (batches 1 and 2, together); the
    step's memory is linear in the batch (state + batch x activations), so the line through them
    predicts the batch at ``limit``. ``final(batch) -> bytes`` (default: ``footprints``) then
    compiles that batch; where it is over ``limit`` the line through the two nearest measured
    batches predicts again (at most ``max_final`` compiles). Returns ``(batch, [(batch, bytes),
    ...] in compile order)``; ``ValueError`` when not even a batch of 1 fits."""
    if limit <= 0:
        raise ValueError(f"limit: expected a positive number of bytes, got {limit}")
    if max_batch < 1:
        raise ValueError(f"max_batch: expected an integer >= 1, got {max_batch}")
    final = final or (lambda b: footprints([b])[0])
    first = [1, 2] if max_batch >= 2 else [1]
    known = dict(zip(first, footprints(first)))
    seen = list(known.items())
    if known[1] > limit:
        raise ValueError(
            f"batch: not even a batch of 1 fits: expected at most {limit} bytes per device, the step needs {known[1]}"
        )
    for _ in range(max_final):
        lo = max(b for b, f in known.items() if f <= limit)
        over = [b for b, f in known.items() if f > limit]
        hi = min(over) if over else max_batch + 1
        below = [b for b in known if b < lo]
        b0, b1 = (lo, hi) if over else ((max(below), lo) if below else (lo, lo))
        slope = (known[b1] - known[b0]) / (b1 - b0) if b1 != b0 else 0.0
        guess = max_batch if slope <= 0 else lo + int((limit - known[lo]) // slope)
        guess = min(guess, max_batch, hi - 1)
        if guess <= lo:
            break
        known[guess] = final(guess)
        seen.append((guess, known[guess]))
        if known[guess] <= limit:
            break
    return max(b for b, f in known.items() if f <= limit), seen


def is_oom(err: Exception) -> bool:
    return "RESOURCE_EXHAUSTED" in str(err) or "out of memory" in str(err).lower()
