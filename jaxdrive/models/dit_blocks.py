"""Deprecated: this module moved to :mod:`jaxdrive.models.dit.blocks`. It re-exports that module
(private names too) and warns on import; it goes in the next release."""

import warnings

from jaxdrive.models.dit import blocks as _new
from jaxdrive.models.dit.blocks import *  # noqa: F403

warnings.warn(
    "jaxdrive.models.dit_blocks moved to jaxdrive.models.dit.blocks (the old path goes in the next release)",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name: str):
    return getattr(_new, name)
