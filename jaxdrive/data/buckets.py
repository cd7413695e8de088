"""Buckets of a mixed resolution and length training (Open-Sora / MagicDrive-V2 [2411.13807v3]
appendix B): each bucket is a clip shape ``(H, W, F)`` with its batch, its share of the clips and
its repeat, parsed from a mapping (:func:`parse_buckets`) or from config text ``HxWxF:batch[:prob[:repeat]]``
(:func:`parse_bucket_specs`); and the source frames a clip of a bucket spans (:func:`frame_offsets`).
The pipeline that fills them is :mod:`jaxdrive.data.pipeline`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from jaxdrive.validate import check_positive_int


def frames_for(k: int, *, compression: int = 4) -> int:
    """Clip length ``1 + compression * k`` (the 3D VAE maps it to ``1 + k`` latent frames)."""
    return 1 + compression * check_positive_int("k", k, minimum=0)


@dataclasses.dataclass(frozen=True)
class Bucket:
    height: int
    width: int
    frames: int
    batch_size: int
    prob: float
    repeat: int | None = None  # rounds of clips an epoch (the pipeline's batch plan); None: automatic

    @property
    def key(self) -> tuple[int, int, int]:
        return (self.height, self.width, self.frames)

    def needed(self, stride: int, head: int = 0, tail_stride: int | None = None) -> int:
        """Source frames one clip of this bucket spans (:func:`frame_offsets`)."""
        return int(frame_offsets(self.frames, stride, head, tail_stride)[-1]) + 1


def frame_offsets(frames: int, stride: int, head: int = 0, tail_stride: int | None = None) -> np.ndarray:
    """Source-frame offsets ``[frames]`` of a clip from its first frame: the first ``head`` frames
    every ``stride``, then every ``tail_stride`` after the last of them (``head = 0``: every
    ``tail_stride`` throughout; ``tail_stride=None``: ``stride``). Spans
    ``1 + (head - 1) stride + (frames - head) tail_stride`` source frames when ``0 < head < frames``."""
    tail = stride if tail_stride is None else tail_stride
    h = min(head, frames)
    if h == 0:
        return tail * np.arange(frames)
    return np.concatenate([stride * np.arange(h), stride * (h - 1) + tail * np.arange(1, frames - h + 1)])


def parse_buckets(buckets, *, compression: int = 4) -> tuple[Bucket, ...]:
    """``{(H, W, F): batch_size}``, ``{(H, W, F): (batch_size, prob)}`` or ``{(H, W, F):
    (batch_size, prob, repeat)}`` -> buckets (probabilities default to uniform and are normalised;
    ``repeat`` None, the default, is automatic: :mod:`jaxdrive.data.pipeline`'s batch plan)."""
    if not isinstance(buckets, Mapping) or not buckets:
        raise ValueError(f"buckets: expected a non-empty {{(H, W, F): batch_size}} mapping, got {buckets!r}")
    out = []
    for key, value in buckets.items():
        if not (isinstance(key, tuple) and len(key) == 3):
            raise ValueError(f"buckets: expected keys (H, W, F), got {key!r}")
        h, w, f = (check_positive_int(f"buckets key {key} {n}", v) for n, v in zip("HWF", key))
        if (f - 1) % compression:
            raise ValueError(f"buckets: bucket {key}: expected F = 1 + {compression}k frames, got {f}")
        if isinstance(value, tuple) and len(value) not in (2, 3):
            raise ValueError(
                f"buckets[{key}]: expected batch_size, (batch_size, prob) or (batch_size, prob, repeat), got {value!r}"
            )
        bs, p, repeat = (*value, None)[:3] if isinstance(value, tuple) else (value, 1.0, None)
        bs = check_positive_int(f"buckets[{key}] batch size", bs)
        if not (isinstance(p, (int, float)) and p >= 0):
            raise ValueError(f"buckets[{key}]: expected a probability >= 0, got {p!r}")
        if repeat is not None:
            repeat = check_positive_int(f"buckets[{key}] repeat (None: automatic)", repeat)
        out.append(Bucket(h, w, f, bs, float(p), repeat))
    total = sum(b.prob for b in out)
    if total <= 0:
        raise ValueError(f"buckets: expected a positive probability somewhere, got {buckets!r}")
    return tuple(dataclasses.replace(b, prob=b.prob / total) for b in out)


SPEC_FORMAT = "'HxWxF:batch[:prob[:repeat]]'"


def parse_bucket_specs(specs: Sequence[str], *, name: str = "data.buckets") -> dict:
    """Config text ``("HxWxF:B", "HxWxF:B:P", "HxWxF:B:P:R", ...)`` -> ``{(H, W, F): (B, P, R)}``
    (``P`` defaults to 1, :func:`parse_buckets` normalises; ``R``, an integer >= 1 or ``auto``, the
    default, is None for automatic). ``B`` is the bucket's global batch; MagicDrive-V2 (appendix B)
    picks each so that every bucket's step takes about the same time, and repeats the scarce clips
    within an epoch (``R``)."""
    if isinstance(specs, str) or not isinstance(specs, Sequence):
        raise ValueError(f"{name}: expected a sequence of {SPEC_FORMAT} strings, got {specs!r}")
    out = {}
    for spec in specs:
        parts = str(spec).split(":")
        dims = parts[0].lower().split("x")
        try:
            if len(parts) not in (2, 3, 4) or len(dims) != 3:
                raise ValueError
            key = tuple(int(v) for v in dims)
            batch, prob = int(parts[1]), float(parts[2]) if len(parts) > 2 else 1.0
            repeat = _parse_repeat(parts[3] if len(parts) == 4 else "auto")
        except ValueError:
            raise ValueError(
                f"{name}: expected {SPEC_FORMAT} (e.g. '32x56x9:2' or '32x56x1:4:1:3'; repeat an "
                f"integer or 'auto'), got {spec!r}"
            ) from None
        if min(key) < 1 or batch < 1 or not prob >= 0 or (repeat is not None and repeat < 1):
            raise ValueError(
                f"{name}: expected positive H, W, F and batch, a probability >= 0 and a repeat "
                f">= 1 or 'auto', got {spec!r}"
            )
        if key in out:
            raise ValueError(f"{name}: expected each (H, W, F) once, got {key} twice")
        out[key] = (batch, prob, repeat)
    if not out or sum(p for _, p, _ in out.values()) <= 0:
        raise ValueError(f"{name}: expected at least one bucket with a positive probability, got {list(specs)!r}")
    return out


def _parse_repeat(text: str) -> int | None:
    """A spec's repeat field: ``auto`` -> None, else an integer (ValueError otherwise)."""
    return None if text.strip().lower() == "auto" else int(text)
