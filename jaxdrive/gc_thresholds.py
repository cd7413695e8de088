"""Python's cyclic garbage collector, run less often while JAX traces and compiles.

Tracing a model builds tens of thousands of short-lived container objects (jaxpr equations,
tracers, pytree nodes), and CPython's default thresholds, ``(700, 10, 10)``, start a collection
every 700 net allocations: tracing and lowering MagicDrive-V2's tiny stage-1 train step ran
about 1,260 collections that took 1.2-1.5 s of a 17 s ``jaxdrive train`` process, and two test
workers running ``tests/test_dit.py`` and ``tests/test_vae.py`` spent 8 s of 90 CPU-seconds in
them. Almost all of these objects die by reference counting, so the collections find little;
with :data:`THRESHOLDS` the same run collects 6-13 times (0.2 s) and its peak memory stays
the same (970-990 MB either way). mypy raises its threshold for the same reason.

The thresholds only make the collector run less often; it still runs, so cyclic garbage is
freed, later. :func:`relaxed_gc` sets them for a block and puts the previous ones back:
``jaxdrive``'s commands run in it (:func:`jaxdrive.cli.main`), and the test suite sets them for
its processes (``tests/conftest.py``). A library user's own process keeps its own settings.
"""

from __future__ import annotations

import contextlib
import gc

# generation 0 every 50,000 net allocations (CPython: 700); generations 1 and 2 after 20
# collections of the younger one (CPython: 10)
THRESHOLDS = (50_000, 20, 20)


@contextlib.contextmanager
def relaxed_gc(thresholds: tuple[int, int, int] = THRESHOLDS):
    """``gc.set_threshold(*thresholds)`` while the block runs (the module docstring says why), the
    previous thresholds afterwards, also when the block raises."""
    ok = isinstance(thresholds, tuple) and len(thresholds) == 3
    if not ok or not all(isinstance(t, int) and not isinstance(t, bool) and t > 0 for t in thresholds):
        raise ValueError(f"thresholds: expected a tuple of three positive ints, got {thresholds!r}")
    before = gc.get_threshold()
    gc.set_threshold(*thresholds)
    try:
        yield
    finally:
        gc.set_threshold(*before)
