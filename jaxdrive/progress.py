"""Progress that reads well on a terminal and in a log file: a tqdm bar on a terminal, one plain
line per update otherwise.

Written to a file, tqdm's bar is its carriage-return frames one after the other (``  8%|▊ |
50/600 [01:00<11:09, 1.22s/step, loss=0.05217``, ...), which a file viewer shows as one long
screen line per update. :class:`Progress` draws the bar only when the stream it would draw on
(``sys.stderr`` by default) is a terminal (``stream.isatty()``); otherwise each update (at least
``every`` items on from the last line) is one message of the ``jaxdrive.progress`` logger at INFO,
e.g. ``step 50/600  loss 0.05217  0.823 step/s  ETA 11:09``: the count, the caller's fields, the
rate since the last line and the time left at that rate. The library never prints
(:mod:`jaxdrive.logs`): the ``jaxdrive`` command shows these lines on stderr (INFO; ``--quiet``
hides them, the bar on a terminal stays), a program that calls the library turns them on as it
turns on the others, and ``logging.getLogger("jaxdrive.progress").setLevel(logging.WARNING)``
turns them off alone. ``enabled=False`` (``progress=False``, ``--no-progress``) shows nothing.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

logger = logging.getLogger(__name__)


def is_terminal(stream) -> bool:
    """Whether ``stream`` is a terminal (its ``isatty()``; a stream without one, or a closed one,
    is not)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def format_interval(seconds: float) -> str:
    """``mm:ss``, or ``h:mm:ss`` from an hour on (tqdm's form of its ETA)."""
    minutes, secs = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours:d}:{minutes:02d}:{secs:02d}" if hours else f"{minutes:02d}:{secs:02d}"


def _value(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


class Progress:
    """Progress over ``total`` items (None: unknown) of ``unit``, counted from ``initial``: a tqdm
    bar on ``stream`` (default ``sys.stderr``, read when the object is made) when that is a
    terminal, one plain log line per update otherwise (module docstring); nothing when not
    ``enabled``. ``desc`` heads the bar and the lines; ``every``: a plain line once the count is
    at least that many items on from the last one (a last line at :meth:`close` shows the rest).
    ``tqdm_kwargs`` go to tqdm alone (``dynamic_ncols``, ...). Use it as a context manager, or
    call :meth:`close`."""

    def __init__(
        self,
        total: int | None = None,
        *,
        initial: int = 0,
        unit: str = "it",
        desc: str | None = None,
        enabled: bool = True,
        stream=None,
        every: int = 1,
        **tqdm_kwargs: Any,
    ):
        if total is not None and (isinstance(total, bool) or not isinstance(total, int) or total < 0):
            raise ValueError(f"total: expected None or an int >= 0, got {total!r}")
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ValueError(f"every: expected an int >= 1, got {every!r}")
        stream = sys.stderr if stream is None else stream
        self.total, self.unit, self.desc, self.every = total, unit, desc, every
        self.enabled = bool(enabled)
        self.terminal = self.enabled and is_terminal(stream)  # tqdm draws; else plain lines
        self.n = initial
        self._shown = (time.perf_counter(), initial)  # (time, count) of the last plain line
        self._postfix: Mapping[str, Any] = {}
        self._bar = None
        if self.terminal:
            from tqdm import tqdm

            self._bar = tqdm(total=total, initial=initial, unit=unit, desc=desc, file=stream, **tqdm_kwargs)

    def update(self, n: int = 1, postfix: Mapping[str, Any] | None = None) -> None:
        """``n`` more items done; ``postfix``: fields shown after the count (tqdm's postfix on a
        terminal, ``name value`` in a plain line; floats with 4 significant digits)."""
        self.update_to(self.n + n, postfix)

    def update_to(self, n: int, postfix: Mapping[str, Any] | None = None) -> None:
        """The count is ``n`` now (e.g. a run's step); ``postfix`` as :meth:`update` takes it."""
        if not self.enabled:
            return
        if postfix is not None:
            self._postfix = dict(postfix)
        if self._bar is not None:
            self._bar.update(n - self._bar.n)
            if postfix is not None:
                self._bar.set_postfix({k: _value(v) for k, v in self._postfix.items()})
            self.n = n
            return
        self.n = n
        if n - self._shown[1] >= self.every:
            self._line()

    def iterate(self, iterable: Iterable) -> Iterator:
        """The items of ``iterable``, counting one as each is taken."""
        for item in iterable:
            yield item
            self.update(1)

    def close(self) -> None:
        """Closes the bar, or logs the last line when the count moved on since the last one."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif self.enabled and not self.terminal and self.n != self._shown[1]:
            self._line()
        self.enabled = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def line(self, now: float | None = None) -> str:
        """The plain line for the count now: ``[desc ]unit n/total  name value ...  rate unit/s
        ETA mm:ss`` (the rate since the last line; no ETA without a total or a rate)."""
        now = time.perf_counter() if now is None else now
        then, last = self._shown
        count = f"{self.unit} {self.n}" + ("" if self.total is None else f"/{self.total}")
        parts = [count if self.desc is None else f"{self.desc} {count}"]
        parts += [f"{k} {_value(v)}" for k, v in self._postfix.items()]
        elapsed, done = now - then, self.n - last
        if elapsed > 0 and done > 0:
            rate = done / elapsed
            parts.append(f"{rate:.3g} {self.unit}/s")
            if self.total is not None:
                parts.append(f"ETA {format_interval(max(self.total - self.n, 0) / rate)}")
        return "  ".join(parts)

    def _line(self) -> None:
        now = time.perf_counter()
        if logger.isEnabledFor(logging.INFO):
            logger.info("%s", self.line(now))
        self._shown = (now, self.n)
