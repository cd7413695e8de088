"""The control pathways' toy runs (:func:`jaxdrive.bench.controls.measure`), each trained once per
test process and shared by the tests that read them."""

from __future__ import annotations

import functools

from jaxdrive.bench import controls

# Adam steps of the tests' runs: the fewest that still separate every pathway (margins in
# tests/test_bench_controls.py).
STEPS = 30


@functools.cache
def measured(pathway: str) -> dict:
    return controls.measure(pathway, steps=STEPS)
