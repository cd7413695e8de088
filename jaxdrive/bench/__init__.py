"""Benchmarks, each runnable as ``python -m jaxdrive.bench.<name>`` or ``jaxdrive bench <name>``.

Every benchmark prints a table for people and one JSON line per figure for machines
(:func:`jaxdrive.bench.report.emit`), measures compared variants side by side in one run, and
reads memory from the compiled program (``compiled.memory_analysis()``).
"""
