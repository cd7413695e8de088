"""Writing what a run produces: multi-view mp4 videos, frame-grid PNGs and loss plots.

Videos are ``[V, F, H, W, 3]`` (or ``[F, H, W, 3]``) floats in [-1, 1] or uint8. Six views are
laid out as a driver sees them, in nuScenes order (front, front-right, back-right, back,
back-left, front-left): front-left, front, front-right on top; back-left, back, back-right below.
Other view counts go in one row.
"""

from __future__ import annotations

from pathlib import Path

import einops
import numpy as np

from jaxdrive import validate

SIX_VIEW_LAYOUT = ((5, 0, 1), (4, 3, 2))


def to_uint8(video) -> np.ndarray:
    video = np.asarray(video)
    if video.dtype == np.uint8:
        return video
    return np.clip(np.round((video.astype(np.float32) + 1.0) * 127.5), 0, 255).astype(np.uint8)


def _with_views(video) -> np.ndarray:
    video = to_uint8(video)
    validate.check_ndim("video", video, (4, 5))
    if video.shape[-1] != 3:
        raise ValueError(f"video: expected 3 channels in the last axis, got shape {list(video.shape)}")
    return video[None] if video.ndim == 4 else video


def view_mosaic(video) -> np.ndarray:
    """``[V, F, H, W, 3] -> [F, rows * H, cols * W, 3]`` uint8 (the layout in the module docstring)."""
    video = _with_views(video)
    layout = SIX_VIEW_LAYOUT if video.shape[0] == 6 else (tuple(range(video.shape[0])),)
    tiles = video[[v for row in layout for v in row]]  # views in reading order
    return einops.rearrange(tiles, "(rows cols) f h w c -> f (rows h) (cols w) c", rows=len(layout))


def split_mosaic(frames, views: int) -> np.ndarray:
    """Inverse of :func:`view_mosaic`: ``[F, rows * H (+ 1), cols * W (+ 1), 3] -> [V, F, H, W, 3]``
    (an odd size's padding row or column, as :class:`Mp4Writer` adds it, dropped)."""
    frames = np.asarray(frames)
    validate.check_ndim("frames", frames, 4)
    layout = SIX_VIEW_LAYOUT if views == 6 else (tuple(range(views)),)
    rows, cols = len(layout), len(layout[0])
    h, w = frames.shape[1] // rows, frames.shape[2] // cols
    if views < 1 or not h or not w:
        raise ValueError(
            f"views: expected a positive view count whose layout ({rows} x {cols}) fits frames of "
            f"{frames.shape[1]} x {frames.shape[2]}, got {views}"
        )
    tiles = einops.rearrange(
        frames[:, : rows * h, : cols * w], "f (rows h) (cols w) c -> (rows cols) f h w c", rows=rows, cols=cols
    )
    order = np.argsort([v for row in layout for v in row])  # reading order -> view order
    return tiles[order]


def read_mp4(path, views: int) -> np.ndarray:
    """The frames of an mp4 as uint8 ``[V, F, H, W, 3]`` (a mosaic of ``views`` views, as
    :class:`Mp4Writer` writes them; ``views=1``: the whole frame)."""
    import av

    try:
        with av.open(str(path)) as container:
            frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    except (av.error.FFmpegError, OSError) as e:
        raise ValueError(f"videos: expected a readable mp4 video, got {str(path)!r} ({e})") from None
    if not frames:
        raise ValueError(f"videos: expected an mp4 with frames, got {str(path)!r} (none decoded)")
    return split_mosaic(np.stack(frames), views)


class Mp4Writer:
    """An H.264 mp4 written part by part (views tiled by :func:`view_mosaic`; sizes padded to
    even), so a long video never has to be in memory whole::

        with Mp4Writer(path, fps=12) as out:
            out.write(part)          # [V, n, H, W, 3] or [n, H, W, 3] in [-1, 1] or uint8
    """

    def __init__(self, path, fps: float = 12.0):
        self.path = Path(path)
        self.fps = fps
        self._container = self._stream = None
        self.frames = 0

    def write(self, video) -> None:
        import av

        frames = view_mosaic(video)
        if not len(frames):
            return
        f, h, w, _ = frames.shape
        frames = np.pad(frames, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)))
        if self._container is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._container = av.open(str(self.path), "w")
            self._stream = self._container.add_stream("libx264", rate=round(self.fps))
            self._stream.width, self._stream.height, self._stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
            self._stream.options = {"crf": "18"}
        elif (frames.shape[1], frames.shape[2]) != (self._stream.height, self._stream.width):
            raise ValueError(
                f"video: expected frames of {self._stream.height} x {self._stream.width} (the first "
                f"part's mosaic), got {frames.shape[1]} x {frames.shape[2]}"
            )
        for frame in frames:
            self._container.mux(self._stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        self.frames += len(frames)

    def close(self) -> Path:
        if self._container is not None:
            self._container.mux(self._stream.encode())
            self._container.close()
            self._container = None
        return self.path

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def write_mp4(path, video, fps: float = 12.0) -> Path:
    """Write ``video`` (views tiled by :func:`view_mosaic`) as H.264 mp4; sizes are padded to even."""
    with Mp4Writer(path, fps) as out:
        out.write(video)
    return Path(path)


# BEV panel colours (jaxdrive.classes.BEV_CLASSES order)
BEV_COLOURS = (
    (70, 70, 78),
    (150, 150, 160),
    (110, 100, 90),
    (230, 230, 230),
    (60, 90, 60),
    (240, 200, 40),
    (220, 220, 220),
    (80, 80, 90),
)
PAINT_ORDER = (0, 4, 2, 7, 1, 3, 5, 6)  # areas first, then crossings, stop lines and dividers on top
PATH_COLOUR, FUTURE_COLOUR, AGENT_COLOUR = (40, 140, 255), (255, 60, 60), (255, 150, 40)


def bev_image(bev_map, *, cell, path=None, split: int | None = None, boxes=None, valid=None) -> np.ndarray:
    """The BEV map ``[Hm, Wm, 8]`` (0 / 1 classes; ego at the centre, x up) as RGB uint8, with the
    ego's ``path [P, 2]`` (metres in this frame's ego frame) drawn blue up to point ``split`` and
    red after it (the route or predicted part), and the agents' ``boxes [N, 7]`` where ``valid``
    as orange dots; ``cell``: metres (x, y) of one BEV cell."""
    bev = np.asarray(bev_map)
    hm, wm = bev.shape[:2]
    img = np.zeros((hm, wm, 3), np.uint8)
    for ch in PAINT_ORDER:
        if ch < bev.shape[-1]:
            img[bev[..., ch] > 0] = BEV_COLOURS[ch]

    def plot(xy, colour, radius=0):
        r = np.floor(hm / 2 - np.asarray(xy)[:, 0] / cell[0]).astype(int)
        c = np.floor(wm / 2 - np.asarray(xy)[:, 1] / cell[1]).astype(int)
        for dr in range(-radius, radius + 1):
            for dc in range(-radius, radius + 1):
                ok = (r + dr >= 0) & (r + dr < hm) & (c + dc >= 0) & (c + dc < wm)
                img[r[ok] + dr, c[ok] + dc] = colour

    if boxes is not None:
        plot(np.asarray(boxes)[np.asarray(valid, bool)][:, :2], AGENT_COLOUR, radius=1)
    if path is not None and len(path) > 1:
        path = np.asarray(path, np.float64)
        dense = np.concatenate(
            [p + np.linspace(0, 1, 8, endpoint=False)[:, None] * (q - p) for p, q in zip(path[:-1], path[1:])]
            + [path[-1:]]
        )
        cut = len(dense) if split is None else 8 * max(split - 1, 0)
        plot(dense[:cut], PATH_COLOUR)
        plot(dense[cut:], FUTURE_COLOUR)
    plot(np.zeros((1, 2)), (255, 255, 255), radius=1)  # the ego
    return img


def write_frame_grid(path, video, num_frames: int = 4, *, reference=None, min_width: int = 480, side=None) -> Path:
    """A PNG with ``num_frames`` evenly spaced frames of ``video``, one mosaic per row. With
    ``reference`` (a video of the same shape, e.g. the recorded clip) each row shows the
    reference's mosaic on the left and ``video``'s on the right. Small frames are enlarged by an
    integer factor (nearest neighbour) until a row is at least ``min_width`` pixels wide.
    ``side``: one image per row (uint8 ``[n, h, w, 3]``, e.g. :func:`bev_image`), put first in
    the row, scaled to the row's height."""
    from PIL import Image

    frames = view_mosaic(video)
    if reference is not None:
        if np.shape(reference) != np.shape(video):
            raise ValueError(
                f"reference: expected the shape of video {list(np.shape(video))}, got {list(np.shape(reference))}"
            )
        sep = np.full(frames.shape[:2] + (4, 3), 255, np.uint8)
        frames = np.concatenate([view_mosaic(reference), sep, frames], axis=2)
    picks = np.unique(np.linspace(0, frames.shape[0] - 1, min(num_frames, frames.shape[0])).round().astype(int))
    up = max(1, -(-min_width // frames.shape[2]))
    frames = einops.repeat(frames[picks], "n h w c -> n (h sy) (w sx) c", sy=up, sx=up)  # nearest neighbour
    if side is not None:
        side = np.asarray(side, np.uint8)[picks]
        h = frames.shape[1]
        rows = np.minimum((np.arange(h) * side.shape[1]) // h, side.shape[1] - 1)
        width = max(1, round(side.shape[2] * h / side.shape[1]))
        cols = np.minimum((np.arange(width) * side.shape[2]) // width, side.shape[2] - 1)
        sep = np.full(frames.shape[:2] + (4, 3), 255, np.uint8)
        frames = np.concatenate([side[:, rows][:, :, cols], sep, frames], axis=2)
    frames = np.pad(frames, ((0, 0), (0, 2), (0, 0), (0, 0)), constant_values=255)  # a white gap below each
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(einops.rearrange(frames, "n h w c -> (n h) w c")[:-2]).save(path)
    return path


def write_route_grid(path, rows, num_frames: int = 5, *, view: int = 0, min_width: int = 960) -> Path:
    """A PNG comparing generations under different controls: one row per ``(label, render,
    generated)`` (videos ``[V, F, H, W, 3]`` of the same shape), each showing ``view`` (default the
    front camera) at ``num_frames`` evenly spaced frames, the render on the left and the generation
    on the right, with the label above. Enlarged by an integer factor (nearest neighbour) until a
    row is at least ``min_width`` pixels wide."""
    from PIL import Image, ImageDraw

    if not rows:
        raise ValueError("rows: expected at least one (label, render, generated), got none")
    strips = []
    for label, render, generated in rows:
        render, generated = _with_views(render), _with_views(generated)
        if render.shape != generated.shape:
            raise ValueError(
                f"rows[{label!r}]: expected render and generated of one shape, got "
                f"{list(render.shape)} and {list(generated.shape)}"
            )
        picks = np.unique(np.linspace(0, render.shape[1] - 1, min(num_frames, render.shape[1])).round().astype(int))
        side = lambda v: np.concatenate(
            [np.pad(f, ((0, 0), (0, 2), (0, 0)), constant_values=255) for f in v[view, picks]], axis=1
        )
        a, b = side(render), side(generated)
        strip = np.concatenate([a, np.full((a.shape[0], 6, 3), 255, np.uint8), b], axis=1)
        up = max(1, -(-min_width // strip.shape[1]))
        strip = einops.repeat(strip, "h w c -> (h sy) (w sx) c", sy=up, sx=up)
        head = Image.new("RGB", (strip.shape[1], 14), "white")
        ImageDraw.Draw(head).text(
            (2, 1), f"{label}: render | generated (frames {', '.join(map(str, picks))})", fill=(0, 0, 0)
        )
        strips += [np.asarray(head), strip]
    width = max(x.shape[1] for x in strips)
    strips = [np.pad(x, ((0, 0), (0, width - x.shape[1]), (0, 0)), constant_values=255) for x in strips]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(strips, axis=0)).save(path)
    return path


def plot_losses(path, steps, losses, *, title: str = "training loss") -> Path:
    """A PNG of ``losses`` against ``steps`` (log scale when they span a decade)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps, losses = np.asarray(steps), np.asarray(losses, np.float64)
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=120)
    ax.plot(steps, losses, lw=1.2)
    finite = losses[np.isfinite(losses) & (losses > 0)]
    if finite.size and finite.max() > 10 * finite.min():
        ax.set_yscale("log")
    ax.set(xlabel="step", ylabel="loss", title=title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
