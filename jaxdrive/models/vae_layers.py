"""Deprecated: this module moved to :mod:`jaxdrive.models.vae.layers`. It re-exports that module
(private names too) and warns on import; it goes in the next release."""

import warnings

from jaxdrive.models.vae import layers as _new
from jaxdrive.models.vae.layers import *  # noqa: F403

warnings.warn(
    "jaxdrive.models.vae_layers moved to jaxdrive.models.vae.layers (the old path goes in the next release)",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name: str):
    return getattr(_new, name)
