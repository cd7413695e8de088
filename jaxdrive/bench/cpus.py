"""The CPUs a CPU benchmark runs on, and how many of them other processes keep busy."""

from __future__ import annotations

import os
import time


def busy_cpus(interval: float = 0.5) -> float | None:
    """CPUs kept busy over ``interval`` seconds while this process waits (``/proc/stat``; None
    where there is none): what other processes take from the benchmark."""

    def read():
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        return sum(v), v[3] + (v[4] if len(v) > 4 else 0)  # total, idle + iowait

    try:
        t0, i0 = read()
        time.sleep(interval)
        t1, i1 = read()
    except (OSError, ValueError, IndexError):
        return None
    total = t1 - t0
    return None if total <= 0 else round((total - (i1 - i0)) / total * (os.cpu_count() or 1), 2)


def cpu_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1
