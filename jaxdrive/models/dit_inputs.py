"""Deprecated: this module moved to :mod:`jaxdrive.models.dit.inputs`. It re-exports that module
(private names too) and warns on import; it goes in the next release."""

import warnings

from jaxdrive.models.dit import inputs as _new
from jaxdrive.models.dit.inputs import *  # noqa: F403

warnings.warn(
    "jaxdrive.models.dit_inputs moved to jaxdrive.models.dit.inputs (the old path goes in the next release)",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name: str):
    return getattr(_new, name)
