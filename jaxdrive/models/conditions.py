"""The public path of :class:`Conditions` and its helpers (the one the design fixes and the
data pipeline builds): everything of :mod:`jaxdrive.models.dit.conditions`, where the code lives
because the DiT and the conditions import each other. Not deprecated."""

from jaxdrive.models.dit import conditions as _home
from jaxdrive.models.dit.conditions import *  # noqa: F403


def __getattr__(name: str):
    return getattr(_home, name)
