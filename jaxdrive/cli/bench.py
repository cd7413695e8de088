"""``jaxdrive bench NAME [ARGS...]``: the benchmarks of :mod:`jaxdrive.bench`, each with its own
arguments (``jaxdrive bench NAME --help``)."""

from __future__ import annotations

import importlib
import pkgutil


def _benchmarks() -> list[str]:
    import jaxdrive.bench as bench

    return sorted(
        m.name for m in pkgutil.iter_modules(bench.__path__) if not m.name.startswith("_") and m.name != "report"
    )


def _bench(args, rest) -> int:
    names = _benchmarks()
    if args.name is None or args.name in ("-h", "--help"):
        print("usage: jaxdrive bench NAME [ARGS...]   (jaxdrive bench NAME --help for its options)")
        print("benchmarks: " + ", ".join(names))
        return 0
    if args.name not in names:
        raise SystemExit(f"jaxdrive bench: name: expected one of {names}, got {args.name!r}")
    importlib.import_module(f"jaxdrive.bench.{args.name}").main(rest)
    return 0


def add_commands(sub) -> None:
    bench = sub.add_parser(
        "bench",
        help="run a benchmark (no name: list them); arguments after the name go to the benchmark",
        add_help=False,
    )  # so `jaxdrive bench NAME --help` reaches the benchmark
    bench.add_argument("name", nargs="?", help="benchmark name, e.g. sampler")
    bench.set_defaults(run=_bench)
