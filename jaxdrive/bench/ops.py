"""Single operations of a DiT train step, XLA:CPU (jitted JAX) against PyTorch eager on the same
CPU with the same threads: what explains :mod:`jaxdrive.bench.train`'s ratio to PyTorch.

For a model width ``W``, ``H`` heads and ``T`` tokens (text + video of the comparison model):

- ``matmul``: ``[T, W] @ [W, 4W]``, the MLP's first matrix (forward, and the input gradient's shape);
- ``matmul x^T dy``: ``[W, T] @ [T, 4W]`` from a token-major ``x``, the weight gradient;
- ``token sum``: ``[T, 4W]`` summed over tokens, a bias gradient;
- ``transpose``: ``[T, 4W]`` -> ``[4W, T]`` materialised;
- ``layer norm fwd+bwd``: ``[T, W]``, no affine, the input gradient for a given cotangent;
- ``softmax fwd+bwd``: ``[H, T, T]`` over the last axis, the input gradient for a given cotangent.

Each is timed as the median of ``repeats`` calls after a warm-up, blocked on its result.
``ratio_to_torch`` = PyTorch time / jaxdrive time (above 1: XLA is faster).
"""

from __future__ import annotations

import numpy as np

from jaxdrive.bench.report import median_time


def _layer_norm(x, eps=1e-5):
    import jax.numpy as jnp

    mean = jnp.mean(x, -1, keepdims=True)
    var = jnp.mean(jnp.square(x - mean), -1, keepdims=True)
    return (x - mean) / jnp.sqrt(var + eps)


def _operations(w: int, heads: int, t: int) -> list[tuple[str, int | None, object, object]]:
    """``(name, matmul FLOPs or None, jax_call, torch_call)`` of the module docstring's operations;
    each call runs the operation once on fixed random inputs and returns when it is done."""
    import jax
    import jax.numpy as jnp
    import torch

    keys = iter(jax.random.split(jax.random.key(0), 6))
    x, w1, dy, s, ds, dx = (
        jax.random.normal(next(keys), shape)
        for shape in ((t, w), (w, 4 * w), (t, 4 * w), (heads, t, t), (heads, t, t), (t, w))
    )
    tx, tw1, tdy, ts, tds, tdx = (torch.from_numpy(np.asarray(a)) for a in (x, w1, dy, s, ds, dx))
    vjp = lambda f: jax.jit(lambda a, ct: jax.vjp(f, a)[1](ct)[0])

    def torch_vjp(f, a, ct):
        a = a.detach().requires_grad_(True)
        return torch.autograd.grad(f(a), a, ct)[0]

    def jax_call(fn, *args):
        return lambda: jax.block_until_ready(fn(*args))

    def torch_call(fn, *args, grad=False):
        def call():
            with torch.enable_grad() if grad else torch.no_grad():
                return fn(*args)

        return call

    layer_norm = lambda a: torch.nn.functional.layer_norm(a, (w,), eps=1e-5)
    mm = 2 * t * w * 4 * w
    return [
        (f"matmul {t}x{w}x{4 * w}", mm, jax_call(jax.jit(jnp.matmul), x, w1), torch_call(torch.mm, tx, tw1)),
        (
            f"matmul x^T dy {w}x{t}x{4 * w}",
            mm,
            jax_call(jax.jit(lambda a, b: a.T @ b), x, dy),
            torch_call(lambda a, b: torch.mm(a.t(), b), tx, tdy),
        ),
        (
            f"token sum {t}x{4 * w}",
            None,
            jax_call(jax.jit(lambda a: jnp.sum(a, 0)), dy),
            torch_call(lambda a: a.sum(0), tdy),
        ),
        (
            f"transpose {t}x{4 * w}",
            None,
            jax_call(jax.jit(jnp.transpose), dy),
            torch_call(lambda a: a.t().contiguous(), tdy),
        ),
        (
            f"layer norm fwd+bwd {t}x{w}",
            None,
            jax_call(vjp(_layer_norm), x, dx),
            torch_call(torch_vjp, layer_norm, tx, tdx, grad=True),
        ),
        (
            f"softmax fwd+bwd {heads}x{t}x{t}",
            None,
            jax_call(vjp(lambda a: jax.nn.softmax(a, -1)), s, ds),
            torch_call(torch_vjp, lambda a: torch.softmax(a, -1), ts, tds, grad=True),
        ),
    ]


def op_rows(cfg, *, tokens: int, threads: int, repeats: int) -> list[dict]:
    """One row per operation and implementation (``model`` = ``"op: <name>"``, ``impl``,
    ``step_ms``, ``gflops`` for the matmuls, ``ratio_to_torch``) at ``cfg``'s width and heads."""
    import torch

    torch.set_num_threads(threads)
    ops = _operations(cfg.width, cfg.heads, tokens)
    # every XLA op first, then every PyTorch op: PyTorch's OpenMP threads spin for a while after
    # each call and would take cores from an XLA op timed right after
    jax_times = [median_time(jax_call, repeats=repeats) for _, _, jax_call, _ in ops]
    torch_times = [median_time(torch_call, repeats=repeats) for _, _, _, torch_call in ops]
    rows = []
    for (name, flops, _, _), jax_s, torch_s in zip(ops, jax_times, torch_times):
        for impl, sec in (("jaxdrive", jax_s), ("torch", torch_s)):
            rows.append(
                dict(
                    model=f"op: {name}",
                    impl=impl,
                    tokens=tokens,
                    step_ms=round(1e3 * sec, 4),
                    gflops=None if flops is None else round(flops / sec / 1e9, 1),
                    ratio_to_torch=round(torch_s / jax_s, 3),
                    torch_threads=threads,
                )
            )
    return rows
