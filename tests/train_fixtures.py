"""Shared helpers of the training tests: small synthetic clip datasets on disk."""

from __future__ import annotations


def write_synthetic(out, *, first: int = 0, train: int = 3, frames: int = 9):
    """``train`` synthetic scenes from seed ``first`` (6 views of 32 x 56) and one validation
    scene, written as a TFDS dataset at ``out``; returns ``out``."""
    from jaxdrive.data.synthetic import generate_clip
    from jaxdrive.data.tfds_io import write_dataset
    clips = lambda seed, n: (generate_clip(seed + i, views=6, frames=frames, height=32, width=56) for i in range(n))
    write_dataset(out, {"train": clips(first, train), "validation": clips(100, 1)}, name="jaxdrive_synthetic")
    return out
