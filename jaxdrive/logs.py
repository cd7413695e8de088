"""jaxdrive's messages go through :mod:`logging`, never ``print``.

Each library module logs to ``logging.getLogger(__name__)``, so every message sits under the
``jaxdrive`` logger: progress (a resumed checkpoint, the first step's time, a written sample) at
INFO, what went wrong but let the work go on (a damaged checkpoint skipped, a save that failed)
at WARNING. The library configures no handler; the program does. The ``jaxdrive`` command puts
one on stderr while a command runs (INFO, WARNING with ``--quiet``); a program that calls the
library turns the messages on with ``logging.basicConfig(level=logging.INFO)``, or
``logging.getLogger("jaxdrive").setLevel(logging.INFO)`` beside a handler of its own.

:func:`deprecated_log` keeps, for one release, the ``log=`` callable that the documented entry
points (``train.run.train``, ``train.run.restore_params``, ``Run.init_state``,
``generate.long_video.sample_long``) took before.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import warnings

ROOT = "jaxdrive"


class _Forward(logging.Handler):
    """Each record's message, as one string, to a ``log`` callable."""

    def __init__(self, log):
        super().__init__(logging.INFO)
        self.log = log

    def emit(self, record: logging.LogRecord) -> None:
        self.log(record.getMessage())


def deprecated_log(fn):
    """Decorates an entry point that took a ``log=`` callable, for one release: ``fn(..., log=f)``
    still works, with a ``DeprecationWarning`` that points at the caller; while ``fn`` runs, ``f``
    gets the message of every record of the ``jaxdrive`` loggers at INFO and above, as it got them
    before, and the ``jaxdrive`` logger is at INFO at least (its level is put back afterwards).
    Without ``log`` (or with None) ``fn`` runs as it is."""
    name = f"{fn.__module__}.{fn.__qualname__}"

    @functools.wraps(fn)
    def wrapper(*args, log=None, **kwargs):
        if log is None:
            return fn(*args, **kwargs)
        warnings.warn(
            f"{name}(log=...) is deprecated and goes in the next release: jaxdrive logs its messages to "
            f"the {ROOT!r} logger (logging.getLogger({ROOT!r}); jaxdrive.logs says how to see them)",
            DeprecationWarning,
            stacklevel=2,
        )
        with _forwarding(log):
            return fn(*args, **kwargs)

    return wrapper


@contextlib.contextmanager
def _forwarding(log):
    logger, handler = logging.getLogger(ROOT), _Forward(log)
    level = logger.level
    logger.addHandler(handler)
    if not logger.isEnabledFor(logging.INFO):
        logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
