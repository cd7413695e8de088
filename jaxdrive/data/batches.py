"""Pipeline batches -> the DiT's inputs, on the host: the one place a batch becomes model inputs.

    inputs = model_inputs(batch, dit_config, text_embeddings)
    # {"video" or "latents": [B, V, F, H, W, 3] / [B, V, F', h, w, C], "cond": Conditions, ...}

The train step (:mod:`jaxdrive.train.flow_step`) and the samplers (:mod:`jaxdrive.generate`) both
take what :func:`model_inputs` makes; neither prepares a batch itself. Captions become token ids of
the built-in caption encoder or looked-up precomputed T5 embeddings (:class:`TextEmbeddings`);
everything else is read by :meth:`jaxdrive.models.dit.conditions.Conditions.from_batch`.
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.models.dit.config import DiTConfig

LOSS_FIELDS = ("boxes", "box_valid", "intrinsics", "cam_to_ego")  # what STAGE's W_aux reads
POSES = "poses"  # a distillation teacher's inputs carry the clip's ego_to_world under this key


class TextEmbeddings:
    """Precomputed T5 embeddings by caption (the ``.npz`` of ``jaxdrive data text-embed``)."""

    def __init__(self, path):
        path = Path(path)
        if not path.is_file():
            raise ValueError(
                f"data.text_embeddings: expected the .npz of 'jaxdrive data text-embed', got {str(path)!r} (not found)"
            )
        with np.load(path) as f:
            self.index = {str(c): i for i, c in enumerate(f["captions"])}
            self.embeddings, self.mask = f["embeddings"], f["mask"]

    def __call__(self, captions):
        missing = [c for c in captions if c not in self.index]
        if missing:
            raise ValueError(
                f"data.text_embeddings: no embedding for captions {missing[:3]}; run "
                f"'jaxdrive data text-embed' on this dataset"
            )
        idx = [self.index[c] for c in captions]
        return self.embeddings[idx], self.mask[idx]


def text_inputs(captions, model: DiTConfig, text_embeddings: TextEmbeddings | None = None):
    """``(text, text_mask)`` of ``captions`` for ``model``'s text control: token ids of the
    built-in caption encoder, looked-up T5 embeddings, or ``(None, None)`` without text."""
    c = model.controls
    if c.text == "caption":
        from jaxdrive.data.text import tokenize_captions

        return tokenize_captions(captions, vocab=c.caption_vocab, max_len=model.text_len)
    if c.text == "embeddings":
        if text_embeddings is None:
            raise ValueError(
                "data.text_embeddings: expected the .npz of 'jaxdrive data text-embed' for a model "
                "with text='embeddings', got none (or set model.controls.text=caption)"
            )
        return text_embeddings(list(captions))
    return None, None


def conditions(batch: dict, model: DiTConfig, text_embeddings: TextEmbeddings | None = None) -> Conditions:
    """The :class:`~jaxdrive.models.dit.conditions.Conditions` of ``model`` from a pipeline batch."""
    text, mask = text_inputs(batch["caption"], model, text_embeddings) if "caption" in batch else (None, None)
    return Conditions.from_batch(batch, model, text=text, text_mask=mask)


def model_inputs(
    batch: dict,
    model: DiTConfig,
    text_embeddings: TextEmbeddings | None = None,
    *,
    foreground: bool = False,
    teacher: DiTConfig | None = None,
    poses: bool = False,
) -> dict:
    """What a step or a sampler needs from a pipeline batch (:mod:`jaxdrive.data.pipeline`):
    ``video`` (or the precomputed ``latents`` of a batch of latent windows) and ``cond``, the
    model's conditions (the batch's drops renamed to the DiT's conditions). With ``foreground``
    (STAGE's W_aux), ``loss`` holds the boxes and cameras it reads; with a distillation
    ``teacher``, ``teacher`` holds the fine model's ``cond`` and the ego poses (:data:`POSES`).
    ``poses``: a warp-guided model's ``warp`` (the poses and cameras) also beside the pipeline's
    ``warp_video``, for a step that warps frames of its own (:mod:`jaxdrive.train.self_rollout`)."""
    x = "latents" if "latents" in batch else "video"  # precomputed latent windows or pixels
    out = {x: np.asarray(batch[x], np.float32), "cond": conditions(batch, model, text_embeddings)}
    if model.controls.warp:  # LongDWM's warped frames: made by the pipeline (training) or the sampler
        if "warp_video" in batch:
            out["warp_video"] = np.asarray(batch["warp_video"], np.float32)  # encoded by the step, like video
        if "warp_video" not in batch or poses:
            out["warp"] = {
                k: np.asarray(batch[b], np.float32)
                for k, b in (("poses", "ego_to_world"), ("intrinsics", "intrinsics"), ("cam_to_ego", "cam_to_ego"))
            }
    if foreground:
        out["loss"] = {k: np.asarray(batch[k]) for k in LOSS_FIELDS}
    if teacher is not None:
        out["teacher"] = {
            "cond": conditions(batch, teacher, text_embeddings),
            POSES: np.asarray(batch["ego_to_world"], np.float32),
        }
    return out


def stack_micro_batches(inputs: list[dict]) -> dict:
    """``grad_accum`` micro-batches -> one tree with a leading ``[A]`` axis."""
    return jax.tree_util.tree_map(lambda *xs: np.stack(xs), *inputs)
