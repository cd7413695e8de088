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
- Several processes can write one dataset (``write_dataset(..., processes=...)``): each writes
  its records as its own shards, process 0 numbers them in process order and writes the metadata,
  so the dataset reads as the concatenation of the processes' records.
"""

from __future__ import annotations

import json
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
            feats[name] = tfds.features.Tensor(shape=(None,) * value.ndim, dtype=value.dtype, encoding="bytes")
        else:
            raise ValueError(
                f"clip field {name!r}: expected a string, a number or a NumPy array, got {type(value).__name__}"
            )
    return tfds.features.FeaturesDict(feats), texts


class _Features:
    """The FeaturesDict of a dataset, decided by the first record written (whichever split holds it)."""

    def __init__(self, compression: str, kind: str):
        self.compression, self.kind, self.dict, self.keys = compression, kind, None, None

    def of(self, clip: Mapping):
        if self.dict is None:
            self.dict, _ = _features(clip, self.compression, self.kind)
            self.keys = set(self.dict.keys())
        return self.dict


def _write_split(
    tmp: Path, prefix: str, split: str, clips: Iterable[dict], features: _Features, shard_bytes: int
) -> dict:
    """Stream one split into ArrayRecord parts ``<split>.<prefix>.partN`` (TFDS serialisation,
    written in order); returns the parts' record counts, the records' frame counts and bytes."""
    lengths, frames, total = [], [], 0
    writer, size = None, 0
    try:
        for i, clip in enumerate(clips):
            where = f"split {split!r} clip {i}"
            sizes = schema.check_clip(clip, source=where, kind=features.kind)
            feats = features.of(clip)
            if set(clip.keys()) != features.keys:
                raise ValueError(
                    f"{where}: expected the fields of the first clip {sorted(features.keys)}, got {sorted(clip.keys())}"
                )
            data = feats.serialize_example({k: (float(v) if k == "fps" else v) for k, v in clip.items()})
            if writer is None or size >= shard_bytes:
                if writer is not None:
                    writer.close()
                writer, size = (
                    ArrayRecordWriter(os.fspath(tmp / f"{split}.{prefix}.part{len(lengths)}"), "group_size:1"),
                    0,
                )
                lengths.append(0)
            writer.write(data)
            size += len(data)
            total += len(data)
            lengths[-1] += 1
            frames.append(int(sizes["F"]))
    finally:
        if writer is not None:
            writer.close()
    return {"lengths": lengths, "frames": frames, "num_bytes": total}


def _write_part(
    tmp: Path, index: int, splits: Mapping[str, Iterable[dict]], features: _Features, shard_bytes: int
) -> None:
    """Process ``index``'s records of every split, in split order, and ``p<index>.json``: what
    :func:`_assemble` needs of them (the features its first record gave, per split its parts)."""
    prefix = f"p{index:05d}"
    written = {split: _write_split(tmp, prefix, split, clips, features, shard_bytes) for split, clips in splits.items()}
    summary = {"features": None if features.dict is None else features.dict.to_json(), "splits": written}
    (tmp / f"{prefix}.json").write_text(json.dumps(summary))


def _assemble(
    tmp: Path, out_dir: Path, count: int, splits: list[str], *, name: str, description: str, metadata: dict, kind: str
) -> dict:
    """The parts of processes ``0..count-1`` (:func:`_write_part`), in process order, as the
    TFDS dataset in ``tmp``: shards renamed ``<name>-<split>.array_record-NNNNN-of-NNNNN``, TFDS
    metadata written; returns the per-split frame counts."""
    summaries = [json.loads((tmp / f"p{i:05d}.json").read_text()) for i in range(count)]
    given = [s["features"] for s in summaries if s["features"] is not None]
    if not given:
        raise ValueError(f"splits: expected at least one clip for {out_dir}, got none")
    for i, f in enumerate(s["features"] for s in summaries):
        if f is not None and f != given[0]:
            raise ValueError(
                f"splits: expected the fields of the first clip in every process, got others in process {i}"
            )
    features = tfds.features.FeatureConnector.from_json(given[0])
    template = tfds.core.ShardedFileTemplate(
        data_dir=tmp,
        template="{DATASET}-{SPLIT}.{FILEFORMAT}-{SHARD_X_OF_Y}",
        dataset_name=name,
        filetype_suffix="array_record",
    )
    infos, counts = [], {}
    for split in splits:
        rows = [s["splits"][split] for s in summaries]
        parts = [(i, k) for i, r in enumerate(rows) for k in range(len(r["lengths"]))]
        if not parts:
            raise ValueError(f"splits[{split!r}]: expected at least one clip for {out_dir}, got none")
        named = template.replace(split=split)
        for shard, (i, k) in enumerate(parts):
            os.rename(
                tmp / f"{split}.p{i:05d}.part{k}", named.sharded_filepath(shard_index=shard, num_shards=len(parts))
            )
        counts[split] = [n for r in rows for n in r["frames"]]
        infos.append(
            tfds.core.SplitInfo(
                name=split,
                shard_lengths=[n for r in rows for n in r["lengths"]],
                num_bytes=sum(r["num_bytes"] for r in rows),
                filename_template=named,
            )
        )
    for i in range(count):
        (tmp / f"p{i:05d}.json").unlink()
    metadata[_RESERVED_METADATA] = {"kind": kind, "frame_counts": counts, "schema_fields": sorted(features.keys())}
    tfds.folder_dataset.write_metadata(
        data_dir=tmp,
        features=features,
        split_infos=infos,
        version=VERSION,
        filename_template=template,
        check_data=False,
        description=description,
        metadata=tfds.core.MetadataDict(metadata),
        disable_shuffling=True,
    )
    return counts


def write_dataset(
    out_dir,
    splits: Mapping[str, Iterable[dict]],
    *,
    name: str = "jaxdrive_clips",
    description: str = "jaxdrive driving clips (see jaxdrive.data.schema).",
    metadata: Mapping | None = None,
    compression: str = "bytes",
    overwrite: bool = False,
    shard_bytes: int = 1 << 30,
    kind: str = "clips",
    processes=None,
) -> Path:
    """Write clip iterables as one TFDS ArrayRecord dataset at ``out_dir``; return its path.

    ``splits`` maps split names (e.g. ``"train"``, ``"validation"``) to iterables of clip dicts
    (consumed once, split after split, streamed: the clips never all sit in memory). All clips must
    carry the same fields; the first clip decides the features. ``kind``: ``"clips"``
    (:data:`schema.CLIP_FIELDS`) or ``"windows"`` (:data:`schema.WINDOW_FIELDS`). ``metadata`` is a
    JSON-serialisable dict saved in ``metadata.json``. ``out_dir`` must not exist unless
    ``overwrite`` is set (the old dataset is replaced only after the new one is complete).

    ``processes``: written by several processes together (each passes its own records, the same
    splits in the same order, and the same other arguments), an object with ``index``, ``count``
    and ``gather(int) -> list[int]`` (an all-gather of one integer per process, which is also a
    barrier; :class:`jaxdrive.parallel.Processes`). Every process writes its records as its own
    shards into one temporary directory beside ``out_dir`` (a filesystem all of them see); then
    process 0 numbers the shards in process order, writes the metadata and moves the dataset into
    place. The dataset reads as the records of process 0, then 1, ...; a process may hold none. A
    process that fails while writing raises at once (the others stop at their next collective):
    the hidden temporary directory stays, and the error names it and the command that removes it
    (the failing process cannot: the others may still be writing there); nothing ever appears
    under ``out_dir``.
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
    index, count = (0, 1) if processes is None else (processes.index, processes.count)
    gather = (lambda v: [v]) if processes is None else processes.gather
    token = gather(uuid.uuid4().int % (1 << 31))[0]  # process 0's: one temporary directory for all
    tmp = out_dir.parent / f".{out_dir.name}.tmp-{token:08x}"
    error = None
    try:
        tmp.mkdir(parents=True, exist_ok=True)
        _write_part(tmp, index, splits, _Features(compression, kind), shard_bytes)
    except Exception as e:
        if count > 1:  # stop now: the others may be inside a collective of their records' making
            _reraise(
                e,
                out_dir,
                f"the others stop at their next collective; the partial dataset stays in {tmp}: "
                f"remove it with rm -rf '{tmp}'",
            )
        error = e
    gather(1)  # every part is written here
    if index == 0:
        try:
            if error is None:
                counts = _assemble(
                    tmp, out_dir, count, list(splits), name=name, description=description, metadata=metadata, kind=kind
                )
                move_into_place(tmp, out_dir)
                log.info("wrote dataset %s: %s", out_dir, {s: len(c) for s, c in counts.items()})
        except Exception as e:
            error = e
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    if not gather(int(error is None))[0] and error is None:  # process 0 has finished (or failed)
        error = ValueError("process 0 could not finish it (its error says why)")
    if error is not None:
        _reraise(error, out_dir, "nothing was left under that name")
    return out_dir


def _reraise(error: Exception, out_dir: Path, note: str):
    """``error`` naming the dataset and ``note``: a ``ValueError`` with both in its message,
    others with a note."""
    if isinstance(error, ValueError):
        raise ValueError(f"writing dataset {out_dir}: {error} ({note})") from error
    error.add_note(f"while writing dataset {out_dir} ({note})")
    raise error


def _dataset_dir(path) -> Path:
    """The directory holding ``dataset_info.json``: ``path`` itself or one TFDS layout below it."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"path: expected a TFDS dataset directory, got {path} (it does not exist)")
    if (path / "dataset_info.json").is_file():
        return path
    found = sorted(p.parent for pat in ("*/dataset_info.json", "*/*/dataset_info.json") for p in path.glob(pat))
    if len(found) != 1:
        raise ValueError(
            f"path: expected a directory with dataset_info.json (or exactly one dataset "
            f"below it), got {path} with {len(found)} datasets below it"
        )
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
        self.kind = ours.get("kind", "clips")  # datasets written before kinds existed hold clips
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
        except Exception as e:  # array_record / TFDS raise RuntimeError, TypeError, ... for damage
            shard, position = self.shard_of(index)
            raise BadRecordError(
                shard,
                f"record {position} (clip {index} of split {self.split!r} of {self.path}) "
                f"could not be read: the shard file is corrupt or truncated "
                f"({type(e).__name__}: {str(e)[:300]})",
            ) from e

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
        return {
            "path": self.path,
            "split": self.split,
            "kind": self.kind,
            "_texts": self._texts,
            "frame_counts": self.frame_counts,
            "_len": self._len,
            "_shards": self._shards,
            "_starts": self._starts,
            "_builder": None,
            "_source": None,
        }

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
            features[k] = {
                "kind": "tensor",
                "shape": [None if s is None else int(s) for s in f.shape],
                "dtype": np.dtype(f.np_dtype).name,
            }
    splits = {}
    for s, split in info.splits.items():
        row = {"num_examples": int(split.num_examples), "num_bytes": int(split.num_bytes)}
        counts = ours.get("frame_counts", {}).get(s)
        if counts:
            row.update(min_frames=int(min(counts)), max_frames=int(max(counts)), total_frames=int(sum(counts)))
        splits[s] = row
    return {
        "path": str(d),
        "name": info.name,
        "version": str(info.version),
        "description": info.description,
        "file_format": "array_record",
        "kind": ours.get("kind", "clips"),
        "splits": splits,
        "features": features,
        "metadata": meta,
    }
