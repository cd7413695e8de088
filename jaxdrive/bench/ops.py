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

from jaxdrive.bench.report import median_time


def _layer_norm(x, eps=1e-5):
    import jax.numpy as jnp
    mean = jnp.mean(x, -1, keepdims=True)
    var = jnp.mean(jnp.square(x - mean), -1, keepdims=True)
    return (x - mean) / jnp.sqrt(var + eps)


def _jax_ops(w: int, heads: int, t: int):
    """``{name: (fn, args, flops)}``: jitted JAX versions of the module docstring's operations."""
    import jax
    import jax.numpy as jnp

    keys = iter(jax.random.split(jax.random.key(0), 8))
    x = jax.random.normal(next(keys), (t, w))
    w1 = jax.random.normal(next(keys), (w, 4 * w))
    dy = jax.random.normal(next(keys), (t, 4 * w))
    s = jax.random.normal(next(keys), (heads, t, t))
    ds = jax.random.normal(next(keys), (heads, t, t))
    dx = jax.random.normal(next(keys), (t, w))
    grad = lambda f: (lambda a, ct: jax.vjp(f, a)[1](ct)[0])
    return {
        f"matmul {t}x{w}x{4 * w}": (jax.jit(jnp.matmul), (x, w1), 2 * t * w * 4 * w),
        f"matmul x^T dy {w}x{t}x{4 * w}": (jax.jit(lambda a, b: a.T @ b), (x, dy), 2 * t * w * 4 * w),
        f"token sum {t}x{4 * w}": (jax.jit(lambda a: jnp.sum(a, 0)), (dy,), None),
        f"transpose {t}x{4 * w}": (jax.jit(jnp.transpose), (dy,), None),
        f"layer norm fwd+bwd {t}x{w}": (jax.jit(grad(_layer_norm)), (x, dx), None),
        f"softmax fwd+bwd {heads}x{t}x{t}": (jax.jit(grad(lambda a: jax.nn.softmax(a, -1))), (s, ds), None),
    }


def _torch_ops(w: int, heads: int, t: int):
    import torch

    g = torch.Generator().manual_seed(0)
    r = lambda *shape: torch.randn(*shape, generator=g)
    x, w1, dy, s, ds, dx = r(t, w), r(w, 4 * w), r(t, 4 * w), r(heads, t, t), r(heads, t, t), r(t, w)

    def grad(f, a, ct):
        a = a.detach().requires_grad_(True)
        return torch.autograd.grad(f(a), a, ct)[0]

    layer_norm = lambda a: torch.nn.functional.layer_norm(a, (w,), eps=1e-5)
    return [lambda: torch.mm(x, w1), lambda: torch.mm(x.t(), dy), lambda: dy.sum(0),
            lambda: dy.t().contiguous(), lambda: grad(layer_norm, x, dx),
            lambda: grad(lambda a: torch.softmax(a, -1), s, ds)]


def op_rows(cfg, *, tokens: int, threads: int, repeats: int) -> list[dict]:
    """One row per operation and implementation (``model`` = ``"op: <name>"``, ``impl``,
    ``step_ms``, ``gflops`` for the matmuls, ``ratio_to_torch``) at ``cfg``'s width and heads."""
    import jax
    import torch

    torch.set_num_threads(threads)
    w, heads = cfg.width, cfg.heads
    rows = []
    with torch.no_grad():
        torch_fns = _torch_ops(w, heads, tokens)
    jax_ops = _jax_ops(w, heads, tokens)
    # every XLA op first, then every PyTorch op: PyTorch's OpenMP threads spin for a while after
    # each call and would take cores from an XLA op timed right after
    jax_times = [median_time(lambda: jax.block_until_ready(fn(*args)), repeats=repeats)
                 for fn, args, _ in jax_ops.values()]
    torch_times = []
    for name, torch_fn in zip(jax_ops, torch_fns):
        with torch.no_grad() if "bwd" not in name else torch.enable_grad():
            torch_times.append(median_time(torch_fn, repeats=repeats))
    for (name, (_, _, flops)), jax_s, torch_s in zip(jax_ops.items(), jax_times, torch_times):
        for impl, sec in (("jaxdrive", jax_s), ("torch", torch_s)):
            rows.append(dict(model=f"op: {name}", impl=impl, tokens=tokens, step_ms=round(1e3 * sec, 4),
                             gflops=None if flops is None else round(flops / sec / 1e9, 1),
                             ratio_to_torch=round(torch_s / jax_s, 3), torch_threads=threads))
    return rows
