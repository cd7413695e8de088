"""The ``jaxdrive`` command: the parser and :func:`main`; one module per command group
(:mod:`.train` for train / sample / demo, :mod:`.data`, :mod:`.convert`, :mod:`.bench`).
Subcommands appear here as the parts behind them land."""

from __future__ import annotations

import argparse
import sys

import jaxdrive
from jaxdrive.cli import bench, convert, data, train


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxdrive",
        description="Long-horizon multi-view driving world models in JAX/Flax.")
    parser.add_argument("--version", action="version", version=f"jaxdrive {jaxdrive.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench.add_commands(sub)
    data.add_commands(sub)
    convert.add_commands(sub)
    train.add_commands(sub)
    return parser


def main(argv=None) -> int:
    from jaxdrive.xla_flags import deterministic_cpu
    deterministic_cpu()                 # before JAX starts its backend (jaxdrive.xla_flags says why)
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    if rest and args.command != "bench":
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    try:
        return args.run(args, rest)
    except ValueError as e:  # bad input: one line that names the argument, not a traceback
        print(f"jaxdrive {args.command}: error: {e}", file=sys.stderr)
        return 2
