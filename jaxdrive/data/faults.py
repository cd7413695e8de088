"""Records that cannot be read: one error type that names the file, and a log that names each bad
file once.

A corrupt or truncated ArrayRecord shard (:class:`jaxdrive.data.tfds_io.ClipSource`) and an
unreadable or missing camera image (:mod:`jaxdrive.data.nuscenes`) raise :class:`BadRecordError`,
a ``ValueError`` whose message starts with the file's path. Readers that may skip bad records
(``data.skip_bad_records``, ``jaxdrive data nuscenes --skip-bad-records``) catch this type only, so
any other error (a wrong shape, a bad argument) still stops them. :class:`OncePerFile` warns the
first time a file is met, not once per record: a truncated shard of a million records is one line.
"""

from __future__ import annotations

import logging
import threading


class BadRecordError(ValueError):
    """A record that cannot be read from ``path`` (the shard or image file, also the message's start)."""

    def __init__(self, path, message: str):
        self.path, self.detail = str(path), message
        super().__init__(f"{path}: {message}")

    def __reduce__(self):  # picklable across grain worker processes
        return type(self), (self.path, self.detail)


class OncePerFile:
    """``note(error)`` logs a warning naming ``error.path`` the first time that file is met (thread-safe:
    grain's read threads share it); returns whether it was new."""

    def __init__(self, logger: logging.Logger, what: str):
        self.logger, self.what = logger, what
        self._seen: set[str] = set()
        self._lock = threading.Lock()

    def note(self, error: BadRecordError) -> bool:
        with self._lock:
            if error.path in self._seen:
                return False
            self._seen.add(error.path)
        self.logger.warning(
            "%s: unreadable, %s (further bad records of this file are not logged): %s",
            error.path,
            self.what,
            error.detail,
        )
        return True

    def __getstate__(self):
        return {"logger": self.logger, "what": self.what, "_seen": set(self._seen)}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()
