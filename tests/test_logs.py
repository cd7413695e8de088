"""jaxdrive's messages (jaxdrive.logs): library code logs, the command shows the log on stderr in
order with what it prints, and the deprecated ``log=`` callables still get the messages."""

import logging
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from jaxdrive.generate.long_video import sample_long
from jaxdrive.logs import deprecated_log
from jaxdrive.train.run import Run, restore_params, train

ROOT = Path(__file__).resolve().parents[1]
logger = logging.getLogger("jaxdrive.test_logs")


@deprecated_log
def work(x, *, scale=1):
    logger.info("working on %d", x)
    logger.debug("a detail")
    logger.warning("%d looks odd", x * scale)
    return x * scale


def test_without_log_nothing_is_deprecated_and_the_messages_go_to_the_log(caplog):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with caplog.at_level(logging.INFO, logger="jaxdrive"):
            assert work(3, scale=2) == 6
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.INFO, "working on 3"),
        (logging.WARNING, "6 looks odd"),
    ]


def test_a_log_callable_still_gets_the_messages_with_a_deprecation_warning(caplog):
    root = logging.getLogger("jaxdrive")
    level, handlers = root.level, list(root.handlers)
    messages = []
    with pytest.warns(DeprecationWarning, match=r"test_logs\.work\(log=\.\.\.\) is deprecated") as caught:
        assert work(3, log=messages.append) == 3
    assert caught[0].filename == __file__  # the warning points at the caller
    assert messages == ["working on 3", "3 looks odd"]  # INFO and above, as before, not DEBUG
    assert (root.level, root.handlers) == (level, handlers)  # the forwarding is gone again
    assert work(4) == 4 and messages == ["working on 3", "3 looks odd"]


def test_the_documented_entry_points_take_the_deprecated_keyword():
    for fn in (train, restore_params, Run.init_state, sample_long):
        assert getattr(fn, "__wrapped__", None) is not None, fn


def test_the_command_keeps_printed_and_logged_lines_in_order_on_one_stream():
    """stdout is block-buffered into a pipe (unless PYTHONUNBUFFERED): the handler flushes it before
    each record."""
    code = (
        "import logging\nfrom jaxdrive.cli import stderr_logging\n"
        "with stderr_logging():\n"
        "    print('printed first')\n"
        "    logging.getLogger('jaxdrive.test_logs').info('logged second')\n"
        "    logging.getLogger('jaxdrive.test_logs').debug('not shown')\n"
        "    print('printed third')\n"
        "with stderr_logging(quiet=True):\n"
        "    logging.getLogger('jaxdrive.test_logs').info('not shown with --quiet')\n"
        "    logging.getLogger('jaxdrive.test_logs').warning('warned with --quiet')\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    out = subprocess.run(
        [sys.executable, "-c", code],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        check=True,
        cwd=ROOT,
        env=env,
        timeout=120,
    ).stdout
    assert out.splitlines() == [
        "printed first",
        "INFO jaxdrive.test_logs: logged second",
        "printed third",
        "WARNING jaxdrive.test_logs: warned with --quiet",
    ]
