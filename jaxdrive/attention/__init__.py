"""Softmax attention: the one entry point :func:`attention` and the kernels it dispatches to.

- ``dispatch.py``: :func:`attention` (``impl`` in :data:`IMPLS`), input checks, the ``"auto"`` rule;
- ``softmax_blocks.py``: one (query block, key block) pair and the exact online-softmax merge;
- ``blockwise.py``: O(L) memory on one device (custom VJP);
- ``ring.py``, ``ulysses.py``: the sequence sharded over the mesh axis ``seq``, with their shared
  plumbing in ``seq_shard.py``;
- ``splash.py``: JAX's Pallas splash kernel on TPUs.

Layering: models import this package; it imports :mod:`jaxdrive.parallel` (meshes, rules), never
the other way round.
"""

from .dispatch import IMPLS, attention

__all__ = ["IMPLS", "attention"]
