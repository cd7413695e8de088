"""Resize and crop of frames, labels and intrinsics for training samples.

Scale to cover (H, W) keeping the aspect ratio, then crop (centre or random); an antialiased
triangle filter in the pixel-centre convention (pixel c covers [c, c + 1), centre c + 0.5), so
``fx' = fx * sx``, ``cx' = cx * sx - crop_x`` exactly match the resampled image. Labels take the
input pixel under each output pixel's centre (never averaged).
"""

from __future__ import annotations

import numpy as np


def _resize_weights(n_in: int, n_resized: int, offset: int, n_out: int) -> np.ndarray:
    """[n_out, n_in] antialiased triangle-filter weights for output pixels offset..offset+n_out-1
    of an n_in -> n_resized resize (pixel centres at c + 0.5 on both grids)."""
    scale = n_resized / n_in
    support = max(1.0, 1.0 / scale)
    x = (np.arange(offset, offset + n_out) + 0.5) / scale - 0.5  # input pixel-index coordinate
    d = np.abs(np.arange(n_in)[None, :] - x[:, None]) / support
    w = np.maximum(0.0, 1.0 - d)
    return (w / w.sum(axis=1, keepdims=True)).astype(np.float32)


def resize_plan(
    in_hw: tuple[int, int], out_hw: tuple[int, int], *, crop: str = "center", rng: np.random.Generator | None = None
) -> dict:
    """Cover-resize then crop: the scale factors (sy, sx), resized size and crop offset (oy, ox)."""
    (h, w), (H, W) = in_hw, out_hw
    s = max(H / h, W / w)
    hr, wr = max(H, round(h * s)), max(W, round(w * s))
    if crop == "center":
        oy, ox = (hr - H) // 2, (wr - W) // 2
    elif crop == "random":
        rng = rng if rng is not None else np.random.default_rng(0)
        oy, ox = int(rng.integers(0, hr - H + 1)), int(rng.integers(0, wr - W + 1))
    else:
        raise ValueError(f"crop: expected 'center' or 'random', got {crop!r}")
    return {"sy": hr / h, "sx": wr / w, "resized": (hr, wr), "offset": (oy, ox), "out": (H, W)}


def adjust_intrinsics(K: np.ndarray, plan: dict) -> np.ndarray:
    """Intrinsics [..., 3, 3] for the resized and cropped image of :func:`resize_plan`."""
    K = np.array(K, np.float32, copy=True)
    (oy, ox), sy, sx = plan["offset"], plan["sy"], plan["sx"]
    K[..., 0, :] *= sx
    K[..., 1, :] *= sy
    K[..., 0, 2] -= ox
    K[..., 1, 2] -= oy
    return K


def resize_crop_video(video: np.ndarray, plan: dict) -> np.ndarray:
    """uint8 [..., h, w, 3] -> float32 [..., H, W, 3] in [-1, 1] (resized, cropped, normalised)."""
    *lead, h, w, c = video.shape
    (hr, wr), (oy, ox), (H, W) = plan["resized"], plan["offset"], plan["out"]
    ry = _resize_weights(h, hr, oy, H) * np.float32(2.0 / 255.0)
    rx = _resize_weights(w, wr, ox, W)
    # Width first as one large matmul ([n*h*c, w] @ [w, W]), then rows ([H, h] @ [n, h, c*W]).
    x = video.reshape(-1, h, w, c).transpose(0, 1, 3, 2).astype(np.float32)
    y = (x.reshape(-1, w) @ rx.T).reshape(-1, h, c * W)
    z = np.matmul(ry, y).reshape(-1, H, c, W).transpose(0, 1, 3, 2) - np.float32(1.0)
    return np.clip(z, -1.0, 1.0).reshape(*lead, H, W, c)


def resize_crop_labels(labels: np.ndarray, plan: dict) -> np.ndarray:
    """Integer labels ``[..., h, w]`` (instance or class ids) resized and cropped as
    :func:`resize_crop_video` resizes the frames, each output pixel taking the label of the input
    pixel under its centre: labels are not averaged."""
    labels = np.asarray(labels)
    h, w = labels.shape[-2:]
    (oy, ox), (H, W) = plan["offset"], plan["out"]
    ys = np.minimum(((np.arange(oy, oy + H) + 0.5) / plan["sy"]).astype(np.int64), h - 1)
    xs = np.minimum(((np.arange(ox, ox + W) + 0.5) / plan["sx"]).astype(np.int64), w - 1)
    return labels[..., ys[:, None], xs[None, :]]
