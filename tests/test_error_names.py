"""Errors name what the caller typed: library functions name their own arguments
(``segment_batch: ...``), and the ``jaxdrive`` command turns that name into the option that set
it (``--segment-batch: ...``)."""

import ast
from pathlib import Path

import pytest

from jaxdrive.cli import build_parser, command_parser, main
from jaxdrive.cli.options import as_flags

PACKAGE = Path(__file__).resolve().parents[1] / "jaxdrive"


@pytest.mark.parametrize(
    "command, message, expected",
    [
        ("sample", "segment_batch: expected 'auto'", "--segment-batch: expected 'auto'"),
        ("sample", "device_memory: expected a positive size", "--device-memory: expected a positive size"),
        ("sample", "models.fine: strategy 'coarse-fine' needs", "--fine-workdir: strategy 'coarse-fine' needs"),
        ("sample", "models.main: 'streaming' needs", "--workdir: 'streaming' needs"),
        ("sample", "override model.depht: unknown key", "--set model.depht: unknown key"),
        ("sample", "taps: expected offsets", "--taps: expected offsets"),
        ("eval", "buckets: expected ranges like 2-12", "--buckets: expected ranges like 2-12"),
        ("eval", "inception /w/x.pth: expected the FID tensor", "--inception /w/x.pth: expected the FID tensor"),
        ("data", "counterfactuals: expected a dataset", "--counterfactuals: expected a dataset"),  # a sub-command's
        ("sample", "flow.jdc_slope: expected >= 0.5", "flow.jdc_slope: expected >= 0.5"),  # a config key stays
        ("sample", "buckets: not an option here", "buckets: not an option here"),  # eval's, not sample's
        ("sample", "expected one of them, got none", "expected one of them, got none"),
        ("sample", "frames must be: odd", "frames must be: odd"),  # not a leading name
    ],
)
def test_a_library_argument_becomes_the_commands_option(command, message, expected):
    assert as_flags(message, command_parser(build_parser(), command)) == expected


def test_the_command_prints_the_option_for_a_library_error(capsys):
    config = PACKAGE.parent / "configs" / "tiny.py"
    assert main(["plan", "--config", str(config), "--mesh", "data=1", "--set", "model.depht=2"]) == 2
    err = capsys.readouterr().err
    assert "jaxdrive plan: error: --set model.depht: unknown key 'depht' in model" in err, err


def _raised_flags(path: Path) -> list[str]:
    """``raise X("--flag: ...")`` / ``raise X(f"--flag ...")`` in ``path``: (line, text) of each."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call) and node.exc.args:
            first = node.exc.args[0]
            head = first.values[0] if isinstance(first, ast.JoinedStr) and first.values else first
            if isinstance(head, ast.Constant) and isinstance(head.value, str) and head.value.startswith("--"):
                found.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {head.value[:40]!r}")
    return found


def test_library_errors_name_arguments_not_command_line_flags():
    """Only the command line names flags: ``jaxdrive/cli`` and the modules that are their own
    command-line programs (an ``argparse`` parser of their own, e.g. ``jaxdrive/bench``)."""
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "cli" in path.relative_to(PACKAGE).parts or "ArgumentParser(" in path.read_text():
            continue
        offenders += _raised_flags(path)
    assert not offenders, "library errors that name command-line flags:\n" + "\n".join(offenders)
    assert _raised_flags(PACKAGE / "cli" / "eval.py"), "the scan finds nothing: it cannot fail"
