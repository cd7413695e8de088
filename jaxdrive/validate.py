"""Input checks shared by every public entry point.

Each check raises ``ValueError`` naming the argument, what was expected and what came.
Value checks (ranges) run only when the value is known at trace time: Python numbers, NumPy
arrays and concrete JAX arrays. Inside ``jax.jit`` a traced value cannot be inspected without a
host round trip, so for traced values the caller's docstring states the contract instead.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np


def is_concrete(x) -> bool:
    """True when ``x`` holds values we can read now (not a tracer under jit/vmap/grad)."""
    leaves = jax.tree_util.tree_leaves(x)
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in leaves)


def _interval(lo, hi, lo_open, hi_open) -> str:
    return f"{'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"


def check_range(name: str, x, lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = False) -> None:
    """Raise if a concrete ``x`` has a value outside the interval; traced values pass."""
    if x is None or not is_concrete(x):
        return
    a = np.asarray(x, dtype=np.float64)
    if a.size == 0:
        return
    if np.isnan(a).any():
        raise ValueError(f"{name}: expected values in {_interval(lo, hi, lo_open, hi_open)}, got NaN")
    vmin, vmax = float(a.min()), float(a.max())
    bad_lo = vmin <= lo if lo_open else vmin < lo
    bad_hi = vmax >= hi if hi_open else vmax > hi
    if bad_lo or bad_hi:
        got = f"{vmin:g}" if a.size == 1 else f"values in [{vmin:g}, {vmax:g}]"
        raise ValueError(f"{name}: expected values in {_interval(lo, hi, lo_open, hi_open)}, got {got}")


def check_probability(name: str, p) -> float:
    """``p`` as a float when it is a real number in [0, 1]; a bool, a string or anything else is a
    ``ValueError`` naming ``name`` (``True`` is not a probability, though Python compares it as 1)."""
    if isinstance(p, bool) or not isinstance(p, (int, float, np.integer, np.floating)) or not 0 <= p <= 1:
        raise ValueError(f"{name}: expected a probability in [0, 1], got {p!r}")
    return float(p)


def check_ndim(name: str, x, ndims: int | Sequence[int]) -> None:
    allowed = (ndims,) if isinstance(ndims, int) else tuple(ndims)
    nd = np.ndim(x)
    if nd not in allowed:
        want = " or ".join(str(n) for n in allowed)
        raise ValueError(f"{name}: expected {want} dimensions, got shape {tuple(np.shape(x))}")


def check_shape(name: str, x, expected: Sequence[int | None]) -> None:
    """``expected`` may hold ``None`` for axes of any size."""
    shape = tuple(np.shape(x))
    ok = len(shape) == len(expected) and all(e is None or e == s for e, s in zip(expected, shape))
    if not ok:
        want = "[" + ", ".join("*" if e is None else str(e) for e in expected) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {list(shape)}")


def check_trailing_shape(name: str, x, trailing: Sequence[int | None], label: str) -> None:
    """Raise unless ``x`` has shape ``[..., *trailing]`` (``None`` = any size); ``label`` is the
    expected shape as the docstring writes it, e.g. ``"[..., P, 3]"``."""
    shape = tuple(np.shape(x))
    tail = shape[len(shape) - len(trailing) :]
    if len(shape) < len(trailing) or any(t is not None and t != s for t, s in zip(trailing, tail)):
        raise ValueError(f"{name}: expected shape {label}, got {list(shape)}")


def check_positive_int(name: str, n, *, minimum: int = 1) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {n!r}")
    return int(n)


def check_choice(name: str, value, choices: Sequence) -> None:
    if value not in choices:
        raise ValueError(f"{name}: expected one of {list(choices)}, got {value!r}")


def check_same_shape(name: str, x, ref_name: str, ref) -> None:
    if tuple(np.shape(x)) != tuple(np.shape(ref)):
        raise ValueError(f"{name}: expected the shape of {ref_name} {list(np.shape(ref))}, got {list(np.shape(x))}")
