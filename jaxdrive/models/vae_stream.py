"""Deprecated: this module moved to :mod:`jaxdrive.models.vae.stream`. It re-exports that module
(private names too) and warns on import; it goes in the next release."""

import warnings

from jaxdrive.models.vae import stream as _new
from jaxdrive.models.vae.stream import *  # noqa: F403

warnings.warn(
    "jaxdrive.models.vae_stream moved to jaxdrive.models.vae.stream (the old path goes in the next release)",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name: str):
    return getattr(_new, name)
