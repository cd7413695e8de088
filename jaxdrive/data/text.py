"""Text for the DiT, on the data side: the built-in caption tokenizer (whose ids feed
:class:`jaxdrive.models.dit.controls.CaptionEncoder`) and T5 embeddings precomputed from a local
encoder.

**Built-in.** Captions follow MiLA's template (``jaxdrive.data.schema.CAPTION_TEMPLATE``): its
fields ``sensor``, ``location``, ``season`` and ``daytime`` carry all the information, the rest is
constant. :func:`tokenize_captions` parses a caption against the template and turns each word of
each field into a token id ``1 + field * P + crc32(word) mod P`` (a stable hash, so no vocabulary
file is needed; P = ``(vocab - 1) // 5`` buckets per field; id 0 is padding). A caption that does
not match the template is tokenised word by word under a fifth "free text" field. The DiT learns
the embedding of these ids with its own small transformer, so the synthetic default needs no
external model.

**T5.** :func:`precompute_t5` runs a T5 encoder (e.g. T5-v1.1-XXL as Open-Sora, MagicDrive-V2 and
CogVideoX use) from a local folder with ``transformers`` and ``torch``, which jaxdrive does not
depend on (the ``t5`` extra installs them: ``pip install "jaxdrive[t5]"``): they are imported when
called, and their absence is a clear error. Only safetensors
weights are loaded. ``jaxdrive data text-embed`` applies it to the captions of a dataset.
"""

from __future__ import annotations

import re
import zlib
from collections.abc import Sequence

import numpy as np

from jaxdrive.data.schema import CAPTION_TEMPLATE
from jaxdrive.validate import check_positive_int

FIELDS = ("sensor", "location", "season", "daytime")


def _template_regex() -> re.Pattern:
    parts = re.split(r"\{(\w+)\}", CAPTION_TEMPLATE)
    pattern = "".join(re.escape(p) if i % 2 == 0 else f"(?P<{p}>.+?)" for i, p in enumerate(parts))
    return re.compile(pattern, flags=re.IGNORECASE)


_TEMPLATE = _template_regex()


def caption_fields(caption: str) -> list[tuple[int, str]]:
    """``[(field index, word), ...]`` of a caption: its template fields' words, or every word under
    field ``len(FIELDS)`` when the caption does not follow the template."""
    words = lambda s: re.findall(r"[a-z0-9]+", s.lower())
    m = _TEMPLATE.fullmatch(caption.strip())
    if m is None:
        return [(len(FIELDS), w) for w in words(caption)]
    return [(i, w) for i, f in enumerate(FIELDS) for w in words(m.group(f))]


def tokenize_captions(captions: Sequence[str], *, vocab: int = 4096, max_len: int = 32):
    """Captions -> ``(ids [N, max_len] int32, mask [N, max_len] bool)`` for the caption encoder
    (``vocab`` must equal ``Controls.caption_vocab``, ``max_len`` at most ``DiTConfig.text_len``).
    Longer captions are truncated."""
    check_positive_int("vocab", vocab, minimum=len(FIELDS) + 2)
    check_positive_int("max_len", max_len)
    if isinstance(captions, str):
        raise ValueError("captions: expected a sequence of strings, got one string")
    buckets = (vocab - 1) // (len(FIELDS) + 1)
    ids = np.zeros((len(captions), max_len), np.int32)
    for n, cap in enumerate(captions):
        if not isinstance(cap, str):
            raise ValueError(f"captions[{n}]: expected a string, got {type(cap).__name__}")
        toks = [1 + f * buckets + zlib.crc32(w.encode()) % buckets for f, w in caption_fields(cap)]
        ids[n, : min(len(toks), max_len)] = toks[:max_len]
    return ids, ids > 0


def precompute_t5(captions: Sequence[str], encoder_dir, *, max_length: int = 300, batch_size: int = 8):
    """T5 encoder embeddings of ``captions``: ``(embeddings [N, max_length, D] float32,
    mask [N, max_length] bool)``, padded to ``max_length`` tokens (the DiT's ``text_len``).

    ``encoder_dir`` holds a Hugging Face T5 encoder and its tokenizer (e.g. a CogVideoX
    checkpoint's ``text_encoder`` with its ``tokenizer`` folder beside it, or one folder with
    both). Needs ``transformers`` and ``torch`` (the ``t5`` extra) and safetensors
    weights; runs on the CPU unless torch sees a GPU."""
    import pathlib

    check_positive_int("max_length", max_length)
    check_positive_int("batch_size", batch_size)
    try:
        import torch
        from transformers import AutoTokenizer, T5EncoderModel
    except ImportError as e:
        raise ImportError(
            f"precompute_t5 needs the packages 'transformers' and 'torch', which jaxdrive does "
            f'not depend on: pip install "jaxdrive[t5]" ({e})'
        ) from None
    folder = pathlib.Path(encoder_dir)
    if not folder.is_dir():
        raise ValueError(f"encoder_dir: expected a folder with a T5 encoder, got {str(folder)!r}")
    tok_dir = folder.parent / "tokenizer" if (folder.parent / "tokenizer").is_dir() else folder
    try:
        tokenizer = AutoTokenizer.from_pretrained(str(tok_dir), local_files_only=True)
        model = T5EncoderModel.from_pretrained(str(folder), local_files_only=True, use_safetensors=True).eval()
    except (OSError, ValueError) as e:
        raise ValueError(
            f"{folder}: expected a T5 encoder (safetensors) and its tokenizer, could not load: {e}"
        ) from None
    device = "cuda" if torch.cuda.is_available() else "cpu"
    model = model.to(device)
    embs, masks = [], []
    for i in range(0, len(captions), batch_size):
        batch = tokenizer(
            list(captions[i : i + batch_size]),
            padding="max_length",
            max_length=max_length,
            truncation=True,
            add_special_tokens=True,
            return_tensors="pt",
        )
        with torch.no_grad():
            out = model(batch.input_ids.to(device), attention_mask=batch.attention_mask.to(device))[0]
        embs.append(out.float().cpu().numpy())
        masks.append(batch.attention_mask.bool().numpy())
    if not embs:
        return np.zeros((0, max_length, model.config.d_model), np.float32), np.zeros((0, max_length), bool)
    return np.concatenate(embs), np.concatenate(masks)
