"""Clip datasets on disk: TFDS in ArrayRecord format, written and read without TensorFlow.

    write_dataset("/data/clips", {"train": train_clips, "validation": val_clips})
    source = open_source("/data/clips", "train")      # random access: len(source), source[i]
    dataset_info("/data/clips")                        # splits, counts, feature shapes, metadata

Layout: ``out_dir`` is one TFDS dataset directory (``dataset_info.json``, ``features.json``,
``metadata.json`` and ``<name>-<split>.array_record-NNNNN-of-NNNNN`` shards), readable by
``tfds.builder_from_directory(out_dir)`` and grain. Every record is checked against the field table
of its kind (:data:`jaxdrive.data.schema.RECORD_FIELDS`) before it is written: ``"clips"`` (source
video) or ``"windows"`` (latent windows of ``jaxdrive data encode``); the kind is kept in the
metadata (:attr:`ClipSource.kind`). Features: one ``tfds.features.Tensor`` per schema array, every
symbolic size (V, F, H, W, N, Hm, Wm) left as ``None`` so clips of different lengths, view counts
and resolutions share one dataset; ``caption`` is ``Text``, ``fps`` a float64 ``Scalar``; extra
string fields of the clips (e.g. ``scene``, ``source``) become ``Text`` features, extra arrays
``Tensor`` features of the same rank.

Choices:
- Arrays are stored raw (``encoding="bytes"``) by default: decoding is a copy, so the input
  pipeline is not bound by zlib; ``compression="zlib"`` compresses the pixel-sized fields
  (``video``, ``bev_map``, ``instance_ids``) for smaller files at some decode cost.
- Written by a streaming writer (TFDS serialisation, ``array_record`` files, TFDS metadata via
  ``tfds.folder_dataset.write_metadata``), not ``DatasetBuilder.download_and_prepare``: TFDS's
  builder buffers a whole split in memory and spills through ``tf.io.gfile`` beyond 1 GB, which
  needs TensorFlow. Clips are written in order (no shuffling; the pipeline shuffles): example i
  of a split is the i-th clip written, so the per-clip frame counts stored in the metadata
  (``frame_counts``, used by the pipeline to plan without decoding video) line up with indices.
  Shards roll over every ``shard_bytes``.
- Atomic: the dataset is built in a hidden temporary directory beside ``out_dir`` and renamed into
  place, so a crash never leaves a partial dataset under the final name.
"""

from __future__ import annotations

import itertools
import logging
import os
import shutil
import uuid
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import tensorflow_datasets as tfds
from array_record.python.array_record_module import ArrayRecordWriter

from jaxdrive.atomic import move_into_place
from jaxdrive.data import schema
from jaxdrive.data.faults import BadRecordError

log = logging.getLogger(__name__)

VERSION = "1.0.0"
_COMPRESSIBLE = ("video", "latents", "bev_map", "instance_ids")
_RESERVED_METADATA = "jaxdrive"  # metadata key holding the record kind and per-split frame counts


def _features(first: Mapping, compression: str, kind: str) -> tuple[tfds.features.FeaturesDict, list[str]]:
    """The FeaturesDict for records of ``kind`` shaped like ``first``; also the names of its Text features."""
    feats, texts = {}, []
    for name, (dtype, spec) in schema.RECORD_FIELDS[kind].items():
        if name not in first:
            continue
        shape = tuple(s if isinstance(s, int) else None for s in spec)
        enc = compression if name in _COMPRESSIBLE else "bytes"
        feats[name] = tfds.features.Tensor(shape=shape, dtype=np.dtype(dtype), encoding=enc)
    feats["caption"] = tfds.features.Text()
    feats["fps"] = tfds.features.Scalar(dtype=np.float64)
    texts.append("caption")
    for name, value in first.items():
        if name in feats:
            continue
        if isinstance(value, str):
            feats[name] = tfds.features.Text()
            texts.append(name)
        elif np.ndim(value) == 0 and isinstance(value, (bool, int, float, np.generic)):
            feats[name] = tfds.features.Scalar(dtype=np.asarray(value).dtype)
        elif isinstance(value, np.ndarray):
            feats[name] = tfds.features.Tensor(shape=(None,) * value.ndim, dtype=value.dtype,
                                               encoding="bytes")
        else:
            raise ValueError(f"clip field {name!r}: expected a string, a number or a NumPy array, "
                             f"got {type(value).__name__}")
    return tfds.features.FeaturesDict(feats), texts


def _write_split(tmp: Path, template, split: str, clips: Iterable[dict], features, keys: set,
                 shard_bytes: int, kind: str) -> tuple[tfds.core.SplitInfo, list[int]]:
    """Stream one split into ArrayRecord shards (TFDS serialisation, written in order)."""
    lengths, frames, parts, total = [], [], [], 0
    writer, size = None, 0
    try:
        for i, clip in enumerate(clips):
            where = f"split {split!r} clip {i}"
            sizes = schema.check_clip(clip, source=where, kind=kind)
            if set(clip.keys()) != keys:
                raise ValueError(f"{where}: expected the fields of the first clip {sorted(keys)}, "
                                 f"got {sorted(clip.keys())}")
            data = features.serialize_example({k: (float(v) if k == "fps" else v) for k, v in clip.items()})
            if writer is None or size >= shard_bytes:
                if writer is not None:
                    writer.close()
                parts.append(tmp / f"{split}.part{len(parts)}")
                writer, size = ArrayRecordWriter(os.fspath(parts[-1]), "group_size:1"), 0
                lengths.append(0)
            writer.write(data)
            size += len(data)
            total += len(data)
            lengths[-1] += 1
            frames.append(int(sizes["F"]))
    finally:
        if writer is not None:
            writer.close()
    named = template.replace(split=split)
    for i, part in enumerate(parts):
        os.rename(part, named.sharded_filepath(shard_index=i, num_shards=len(parts)))
    return tfds.core.SplitInfo(name=split, shard_lengths=lengths, num_bytes=total,
                               filename_template=named), frames


def write_dataset(out_dir, splits: Mapping[str, Iterable[dict]], *, name: str = "jaxdrive_clips",
                  description: str = "jaxdrive driving clips (see jaxdrive.data.schema).",
                  metadata: Mapping | None = None, compression: str = "bytes",
                  overwrite: bool = False, shard_bytes: int = 1 << 30, kind: str = "clips") -> Path:
    """Write clip iterables as one TFDS ArrayRecord dataset at ``out_dir``; return its path.

    ``splits`` maps split names (e.g. ``"train"``, ``"validation"``) to iterables of clip dicts
    (consumed once, streamed: the clips never all sit in memory). All clips must carry the same
    fields; the first clip decides the features. ``kind``: ``"clips"`` (:data:`schema.CLIP_FIELDS`)
    or ``"windows"`` (:data:`schema.WINDOW_FIELDS`). ``metadata`` is a JSON-serialisable dict saved in
    ``metadata.json``. ``out_dir`` must not exist unless ``overwrite`` is set (the old dataset is
    replaced only after the new one is complete).
    """
    out_dir = Path(out_dir)
    if compression not in ("bytes", "zlib"):
        raise ValueError(f"compression: expected 'bytes' or 'zlib', got {compression!r}")
    if kind not in schema.RECORD_FIELDS:
        raise ValueError(f"kind: expected one of {sorted(schema.RECORD_FIELDS)}, got {kind!r}")
    if not splits:
        raise ValueError(f"splits: expected at least one split for {out_dir}, got none")
    if out_dir.exists() and not overwrite:
        raise ValueError(f"out_dir: {out_dir} already exists (pass overwrite=True to replace it)")
    metadata = dict(metadata or {})
    if _RESERVED_METADATA in metadata:
        raise ValueError(f"metadata: the key {_RESERVED_METADATA!r} is reserved, got it in {sorted(metadata)}")
    iters, first = {}, None
    for split, clips in splits.items():
        it = iter(clips)
        head = next(it, None)
        if head is None:
            raise ValueError(f"splits[{split!r}]: expected at least one clip for {out_dir}, got none")
        first = head if first is None else first
        iters[split] = itertools.chain([head], it)
    features, _ = _features(first, compression, kind)
    metadata[_RESERVED_METADATA] = {"kind": kind, "frame_counts": {}, "schema_fields": sorted(features.keys())}

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.parent / f".{out_dir.name}.tmp-{uuid.uuid4().hex[:8]}"
    counts = metadata[_RESERVED_METADATA]["frame_counts"]
    try:
        tmp.mkdir()
        template = tfds.core.ShardedFileTemplate(
            data_dir=tmp, template="{DATASET}-{SPLIT}.{FILEFORMAT}-{SHARD_X_OF_Y}", dataset_name=name,
            filetype_suffix="array_record")
        infos = []
        for split, clips in iters.items():
            info, counts[split] = _write_split(tmp, template, split, clips, features, set(features.keys()),
                                               shard_bytes, kind)
            infos.append(info)
        tfds.folder_dataset.write_metadata(
            data_dir=tmp, features=features, split_infos=infos, version=VERSION,
            filename_template=template, check_data=False, description=description,
            metadata=tfds.core.MetadataDict(metadata), disable_shuffling=True)
        move_into_place(tmp, out_dir)
    except ValueError as e:
        raise ValueError(f"writing dataset {out_dir}: {e}") from e
    except Exception as e:
        e.add_note(f"while writing dataset {out_dir} (nothing was left under that name)")
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log.info("wrote dataset %s: %s", out_dir,
             {s: len(c) for s, c in metadata[_RESERVED_METADATA]["frame_counts"].items()})
    return out_dir


def _dataset_dir(path) -> Path:
    """The directory holding ``dataset_info.json``: ``path`` itself or one TFDS layout below it."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"path: expected a TFDS dataset directory, got {path} (it does not exist)")
    if (path / "dataset_info.json").is_file():
        return path
    found = sorted(p.parent for pat in ("*/dataset_info.json", "*/*/dataset_info.json")
                   for p in path.glob(pat))
    if len(found) != 1:
        raise ValueError(f"path: expected a directory with dataset_info.json (or exactly one dataset "
                         f"below it), got {path} with {len(found)} datasets below it")
    return found[0]


def _builder(path):
    d = _dataset_dir(path)
    try:
        return d, tfds.builder_from_directory(os.fspath(d))
    except Exception as e:  # corrupt or partial dataset: name the directory
        raise ValueError(f"path: could not read the TFDS dataset at {d}: {e}") from e


class ClipSource:
    """Random access to the clips of one split: ``len(src)``, ``src[i]`` -> a clip dict.

    Clips come back as NumPy arrays of the schema dtypes, ``caption`` and other text fields as
    ``str``, ``fps`` as ``float``. ``frame_counts[i]`` is clip i's frame count, read from the
    metadata without decoding the clip; ``kind`` is the record kind (``"clips"`` or ``"windows"``).
    Picklable (reopens lazily), so grain workers can use it.

    A record that cannot be read or decoded (a corrupt or truncated shard file: array_record
    raises ``RuntimeError`` for a hash mismatch or a file shorter than its index says, and a
    truncated file may give no record at all) raises
    :class:`jaxdrive.data.faults.BadRecordError` naming the shard file, the record's position in
    it and the clip index; :meth:`shard_of` says where clip i lives.
    """

    def __init__(self, path, split: str):
        self.path, builder = _builder(path)
        self.split = split
        splits = list(builder.info.splits.keys())
        if split not in splits:
            raise ValueError(f"split: expected one of {splits} for {self.path}, got {split!r}")
        self._texts = [k for k, f in builder.info.features.items() if isinstance(f, tfds.features.Text)]
        ours = (builder.info.metadata or {}).get(_RESERVED_METADATA, {})
        self.kind = ours.get("kind", "clips")     # datasets written before kinds existed hold clips
        counts = ours.get("frame_counts", {}).get(split)
        self.frame_counts = None if counts is None else np.asarray(counts, np.int64)
        self._len = int(builder.info.splits[split].num_examples)
        files = builder.info.splits[split].file_instructions
        self._shards = [(str(f.filename), int(f.skip)) for f in files]
        self._starts = np.cumsum([0] + [int(f.take) for f in files])
        self._builder = builder
        self._source = None

    def _open(self):
        if self._source is None:
            if self._builder is None:
                _, self._builder = _builder(self.path)
            try:
                self._source = self._builder.as_data_source(split=self.split)
            except Exception as e:
                raise ValueError(f"path: could not open split {self.split!r} of {self.path}: {e}") from e
        return self._source

    def __len__(self) -> int:
        return self._len

    def __getitem__(self, index: int) -> dict:
        if not -self._len <= index < self._len:
            raise IndexError(f"index: expected in [0, {self._len}) for {self.path} {self.split!r}, got {index}")
        index = int(index) % self._len
        source = self._open()
        try:
            return self._decode(source[index])
        except Exception as e:       # array_record / TFDS raise RuntimeError, TypeError, ... for damage
            shard, position = self.shard_of(index)
            raise BadRecordError(shard, f"record {position} (clip {index} of split {self.split!r} of {self.path}) "
                                        f"could not be read: the shard file is corrupt or truncated "
                                        f"({type(e).__name__}: {str(e)[:300]})") from e

    def shard_of(self, index: int) -> tuple[str, int]:
        """``(shard file, record position in it)`` of clip ``index``."""
        i = int(np.searchsorted(self._starts, index, side="right")) - 1
        path, skip = self._shards[i]
        return path, skip + int(index - self._starts[i])

    def _decode(self, raw) -> dict:
        clip = {}
        for k, v in raw.items():
            if k in self._texts:
                clip[k] = v.decode("utf-8") if isinstance(v, bytes) else str(v)
            elif k == "fps":
                clip[k] = float(v)
            else:
                clip[k] = v
        return clip

    def __getstate__(self):
        return {"path": self.path, "split": self.split, "kind": self.kind, "_texts": self._texts,
                "frame_counts": self.frame_counts, "_len": self._len, "_shards": self._shards,
                "_starts": self._starts, "_builder": None, "_source": None}

    def __repr__(self):
        return f"ClipSource({str(self.path)!r}, {self.split!r}, len={self._len})"


def open_source(data_dir_or_path, split: str = "train") -> ClipSource:
    """A random-access source of decoded clip dicts for ``split`` of the dataset at the path."""
    return ClipSource(data_dir_or_path, split)


def dataset_info(path) -> dict:
    """Splits, example counts, feature shapes/dtypes, frame-count ranges, the record kind and the
    metadata of a dataset."""
    d, builder = _builder(path)
    info = builder.info
    meta = dict(info.metadata or {})
    ours = meta.pop(_RESERVED_METADATA, {})
    features = {}
    for k, f in info.features.items():
        if isinstance(f, tfds.features.Text):
            features[k] = {"kind": "text"}
        else:
            features[k] = {"kind": "tensor", "shape": [None if s is None else int(s) for s in f.shape],
                           "dtype": np.dtype(f.np_dtype).name}
    splits = {}
    for s, split in info.splits.items():
        row = {"num_examples": int(split.num_examples), "num_bytes": int(split.num_bytes)}
        counts = ours.get("frame_counts", {}).get(s)
        if counts:
            row.update(min_frames=int(min(counts)), max_frames=int(max(counts)),
                       total_frames=int(sum(counts)))
        splits[s] = row
    return {"path": str(d), "name": info.name, "version": str(info.version),
            "description": info.description, "file_format": "array_record", "kind": ours.get("kind", "clips"),
            "splits": splits, "features": features, "metadata": meta}
