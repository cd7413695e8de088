"""The ``jaxdrive`` command: the parser and :func:`main`; one module per command group
(:mod:`.train` for train / sample / demo, :mod:`.data`, :mod:`.convert`, :mod:`.bench`, :mod:`.plan`).
Subcommands appear here as the parts behind them land."""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys

import jaxdrive
from jaxdrive.cli import bench, convert, data, plan, train
from jaxdrive.cli import eval as eval_cli
from jaxdrive.cli.options import as_flags
from jaxdrive.gc_thresholds import relaxed_gc


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxdrive", description="Long-horizon multi-view driving world models in JAX/Flax."
    )
    parser.add_argument("--version", action="version", version=f"jaxdrive {jaxdrive.__version__}")
    parser.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="log warnings and errors only (default: jaxdrive's INFO messages too, on stderr)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench.add_commands(sub)
    data.add_commands(sub)
    convert.add_commands(sub)
    train.add_commands(sub)
    eval_cli.add_commands(sub)
    plan.add_commands(sub)
    return parser


class _AfterStdout(logging.StreamHandler):
    """A stderr handler that flushes stdout before each record, so that the command's printed
    lines and its log lines keep their order also when both streams go to one file."""

    def emit(self, record: logging.LogRecord) -> None:
        sys.stdout.flush()
        super().emit(record)


@contextlib.contextmanager
def stderr_logging(*, quiet: bool = False):
    """jaxdrive's loggers to stderr at INFO (WARNING when ``quiet``) while the block runs: the
    library logs and never prints (:mod:`jaxdrive.logs`), and this is the one place where its
    messages (a resumed checkpoint, the first step's time, ``encode_dataset``'s files, a damaged
    checkpoint skipped) are shown. Only the ``jaxdrive`` logger: other
    libraries keep their own levels; the handler goes again afterwards (``main`` may run many
    times in one process, e.g. in tests, with ``sys.stderr`` replaced in between)."""
    logger = logging.getLogger("jaxdrive")
    handler = _AfterStdout(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    level, propagate = logger.level, logger.propagate
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING if quiet else logging.INFO)
    logger.propagate = False  # a dependency may configure the root logger: print each message once
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.propagate = propagate


def command_parser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    """The sub-parser of ``command`` (its options name the library's arguments in errors)."""
    group = next(a for a in parser._actions if isinstance(a.choices, dict))  # no public accessor
    return group.choices[command]


def main(argv=None) -> int:
    from jaxdrive.xla_flags import deterministic_cpu

    deterministic_cpu()  # before JAX starts its backend (jaxdrive.xla_flags says why)
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    if rest and args.command != "bench":
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    # the collector less often while the command traces and compiles (jaxdrive.gc_thresholds)
    with stderr_logging(quiet=args.quiet), relaxed_gc():
        try:
            return args.run(args, rest)
        except ValueError as e:  # bad input: one line that names the option, not a traceback
            print(
                f"jaxdrive {args.command}: error: {as_flags(str(e), command_parser(parser, args.command))}",
                file=sys.stderr,
            )
            return 2
