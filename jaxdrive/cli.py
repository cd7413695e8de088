"""The ``jaxdrive`` command. Subcommands appear here as the parts behind them land."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import jaxdrive


def _benchmarks() -> list[str]:
    import jaxdrive.bench as bench
    return sorted(m.name for m in pkgutil.iter_modules(bench.__path__)
                  if not m.name.startswith("_") and m.name != "report")


def _bench(args, rest) -> int:
    names = _benchmarks()
    if args.name is None:
        print("benchmarks: " + ", ".join(names))
        return 0
    if args.name not in names:
        raise SystemExit(f"jaxdrive bench: name: expected one of {names}, got {args.name!r}")
    importlib.import_module(f"jaxdrive.bench.{args.name}").main(rest)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxdrive",
        description="Long-horizon multi-view driving world models in JAX/Flax.")
    parser.add_argument("--version", action="version", version=f"jaxdrive {jaxdrive.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench = sub.add_parser("bench", help="run a benchmark (no name: list them); "
                                         "arguments after the name go to the benchmark",
                           add_help=True)
    bench.add_argument("name", nargs="?", help="benchmark name, e.g. sampler")
    bench.set_defaults(run=_bench)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    if rest and args.command != "bench":
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    return args.run(args, rest)


if __name__ == "__main__":
    sys.exit(main())
