"""Deprecated: this module moved to :mod:`jaxdrive.models.dit.presets`. It re-exports that module
(private names too) and warns on import; it goes in the next release."""

import warnings

from jaxdrive.models.dit import presets as _new
from jaxdrive.models.dit.presets import *  # noqa: F403

warnings.warn(
    "jaxdrive.models.dit_presets moved to jaxdrive.models.dit.presets (the old path goes in the next release)",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name: str):
    return getattr(_new, name)


if __name__ == "__main__":  # python -m jaxdrive.models.dit_presets
    from jaxdrive.models.dit.presets import main

    main()
