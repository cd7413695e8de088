"""Deprecated: this module moved to :mod:`jaxdrive.models.dit.controls`. It re-exports that module
(private names too) and warns on import; it goes in the next release."""

import warnings

from jaxdrive.models.dit import controls as _new
from jaxdrive.models.dit.controls import *  # noqa: F403

warnings.warn(
    "jaxdrive.models.dit_controls moved to jaxdrive.models.dit.controls (the old path goes in the next release)",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name: str):
    return getattr(_new, name)
