"""Deprecated: this module moved to :mod:`jaxdrive.models.dit.config`. It re-exports that module
(private names too) and warns on import; it goes in the next release."""

import warnings

from jaxdrive.models.dit import config as _new
from jaxdrive.models.dit.config import *  # noqa: F403

warnings.warn(
    "jaxdrive.models.dit_config moved to jaxdrive.models.dit.config (the old path goes in the next release)",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name: str):
    return getattr(_new, name)
