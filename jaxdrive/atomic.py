"""Putting a finished directory in place without ever exposing a half-written one."""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path


def move_into_place(staging: Path, target: Path) -> None:
    """Rename the finished directory ``staging`` to ``target`` (a sibling), replacing an existing
    ``target`` by moving it aside first: at every moment ``target`` is either the old complete
    directory or the new one."""
    staging, target = Path(staging), Path(target)
    if target.exists():
        old = target.parent / f".{target.name}.old-{uuid.uuid4().hex[:8]}"
        os.replace(target, old)
        os.replace(staging, target)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(staging, target)
