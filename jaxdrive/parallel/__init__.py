"""Meshes, logical-axis sharding rules, host-to-global arrays and sequence-sharded attention.

``rules.py`` is the only place that maps logical axis names to the mesh axes ``data``, ``fsdp``,
``seq`` and ``tensor``.
"""
