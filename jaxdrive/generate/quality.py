"""Frame fidelity of a generated clip against the recorded clip it continues: PSNR and SSIM per
frame, beside the trivial baselines a generator has to beat.

    q = clip_quality(generated, recorded, cond_frames=2, window=9)
    q["first_window"]["psnr"], q["first_window"]["repeat_psnr"]    # model vs repeating the last given frame

Videos are ``[V, F, H, W, 3]`` (or ``[F, H, W, 3]``) in [-1, 1]. PSNR and SSIM are DeepMind PIX's
(``dm_pix``: SSIM of Wang et al. 2004 with an 11-tap Gaussian of sigma 1.5, k1 = 0.01, k2 = 0.03),
on images mapped to [0, 1], per (view, frame) and averaged over views.

The baselines, each scored against the same recorded frames:

- ``repeat``: every generated frame replaced by the last condition frame (a world model that
  learned nothing about motion; for short horizons a strong baseline on PSNR);
- ``noise``: uniform noise frames with the recorded frames' per-channel mean and standard
  deviation (seeded, so reproducible): a generator that only matches the clip's colours scores
  this; saturated colour noise scores lower.

Generation scores its own output here (``quality.json`` of every sample,
:func:`jaxdrive.generate.samples.write_samples`; a long video's report,
:mod:`jaxdrive.generate.long_video`), so the metrics live in the generate layer; ``jaxdrive eval``
reads the same ones (:mod:`jaxdrive.eval.frames` re-exports them).
"""

from __future__ import annotations

import dm_pix
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.validate import check_ndim, check_positive_int


def _unit(video):
    return (jnp.asarray(video, jnp.float32) + 1.0) / 2.0


def _images(metric, a, b):
    """``metric`` (PIX takes ``[N, H, W, C]``) over images ``[..., H, W, C]`` -> ``[...]``."""
    a, b = _unit(a), _unit(b)
    lead = a.shape[:-3]
    return metric(a.reshape((-1,) + a.shape[-3:]), b.reshape((-1,) + b.shape[-3:])).reshape(lead)


@jax.jit
def psnr(a, b):
    """PSNR in dB of images ``[..., H, W, 3]`` in [-1, 1] (peak 1 after mapping to [0, 1]);
    identical images give ``inf``."""
    return _images(dm_pix.psnr, a, b)


@jax.jit
def ssim(a, b):
    """SSIM of images ``[..., H, W, 3]`` in [-1, 1] (``dm_pix.ssim`` on [0, 1], its defaults)."""
    return _images(dm_pix.ssim, a, b)


def _per_frame(a, b) -> tuple[np.ndarray, np.ndarray]:
    """PSNR and SSIM ``[F]`` of videos ``[V, F, H, W, 3]``, each the mean over views."""
    p = np.asarray(psnr(a, b), np.float64)
    s = np.asarray(ssim(a, b), np.float64)
    return np.minimum(p, 100.0).mean(axis=0), s.mean(axis=0)  # identical frames: 100 dB, not inf


def noise_like(recorded, seed: int = 0) -> np.ndarray:
    """Uniform noise with the per-channel mean and standard deviation of ``recorded``, clipped to
    [-1, 1]: the ``noise`` baseline."""
    r = np.asarray(recorded, np.float32)
    mean = r.mean(axis=tuple(range(r.ndim - 1)))
    std = r.std(axis=tuple(range(r.ndim - 1)))
    u = np.random.default_rng(seed).uniform(-np.sqrt(3.0), np.sqrt(3.0), r.shape).astype(np.float32)
    return np.clip(mean + std * u, -1.0, 1.0)


def _summary(rows: list[dict], frames: list[int]) -> dict:
    keys = ("psnr", "ssim", "repeat_psnr", "repeat_ssim", "noise_psnr", "noise_ssim")
    pick = [rows[f] for f in frames]
    return {"frames": [int(f) for f in frames], **{k: float(np.mean([r[k] for r in pick])) for k in keys}}


class FrameScores:
    """:func:`clip_quality` a part at a time, for videos too long to hold decoded: ``add`` the
    generated frames in order as they are decoded (``[V, n, H, W, 3]``), then ``result()``.
    ``recorded`` is the whole recorded clip ``[V, F, H, W, 3]`` (the baselines need its last
    given frame and its colour statistics); the scores equal :func:`clip_quality` of the whole
    clip, part boundaries aside."""

    def __init__(self, recorded, *, cond_frames: int, seed: int = 0):
        r = np.asarray(recorded, np.float32)
        check_ndim("recorded", r, (5,))
        if r.shape[-1] != 3:
            raise ValueError(f"recorded: expected RGB frames [..., H, W, 3], got shape {list(r.shape)}")
        check_positive_int("cond_frames", cond_frames)
        if cond_frames >= r.shape[1]:
            raise ValueError(f"cond_frames: expected fewer than the clip's {r.shape[1]} frames, got {cond_frames}")
        self.recorded, self.cond_frames, self.seed = r, cond_frames, seed
        self._noise = None
        self.rows: list[dict] = []

    def add(self, generated) -> FrameScores:
        """Score the next frames ``[V, n, H, W, 3]`` of the generated clip."""
        g = np.asarray(generated, np.float32)
        lo, r = len(self.rows), self.recorded
        hi = lo + (g.shape[1] if g.ndim == 5 else 0)
        if g.ndim != 5 or g.shape[0] != r.shape[0] or g.shape[2:] != r.shape[2:] or hi > r.shape[1]:
            raise ValueError(
                f"generated: expected the next frames [V, n, H, W, 3] of a clip shaped "
                f"{list(r.shape)} (frames {lo}..{r.shape[1] - 1} left), got shape {list(g.shape)}"
            )
        if self._noise is None:
            self._noise = noise_like(r, self.seed)
        truth = r[:, lo:hi]
        held = np.minimum(np.arange(lo, hi), self.cond_frames - 1)  # the last given frame, held
        scores = {
            "": _per_frame(g, truth),
            "repeat_": _per_frame(r[:, held], truth),
            "noise_": _per_frame(self._noise[:, lo:hi], truth),
        }
        for i, f in enumerate(range(lo, hi)):
            row = {"frame": f, "kind": "condition" if f < self.cond_frames else "generated"}
            for prefix, (p, s) in scores.items():
                row[f"{prefix}psnr"], row[f"{prefix}ssim"] = float(p[i]), float(s[i])
            self.rows.append(row)
        return self

    def result(self, window: int | None = None, every: int | None = None) -> dict:
        """The JSON-ready report of :func:`clip_quality` over the frames added so far; with
        ``every``, also ``horizon``: the summary of each run of ``every`` generated frames (a
        quality-versus-horizon curve, e.g. one point per second of video)."""
        nf, k = len(self.rows), self.cond_frames
        if nf <= k:
            raise ValueError(f"generated: expected frames beyond the {k} given ones, got {nf} frames")
        window = nf if window is None else min(check_positive_int("window", window), nf)
        if window <= k:
            raise ValueError(f"window: expected more than cond_frames = {k} frames, got {window}")
        out = {
            "views": int(self.recorded.shape[0]),
            "cond_frames": int(k),
            "window": int(window),
            "per_frame": self.rows,
            "first_window": _summary(self.rows, list(range(k, window))),
            "all_generated": _summary(self.rows, list(range(k, nf))),
        }
        if every is not None:
            every = check_positive_int("every", every)
            out["horizon"] = [_summary(self.rows, list(range(a, min(a + every, nf)))) for a in range(k, nf, every)]
        return out


def clip_quality(generated, recorded, *, cond_frames: int, window: int | None = None, seed: int = 0) -> dict:
    """PSNR / SSIM of each frame of ``generated`` against ``recorded`` (same shape), and of the
    ``repeat`` and ``noise`` baselines (module docstring).

    ``cond_frames``: the leading frames that were given, not generated (their rows are marked
    ``"condition"`` and left out of the summaries); ``window``: frames of the first sampler window
    (default all), summarised as ``first_window``; ``all_generated`` summarises every generated
    frame. Returns a JSON-ready dict: ``per_frame`` (one row per frame), ``first_window``,
    ``all_generated``."""
    g = np.asarray(generated, np.float32)
    r = np.asarray(recorded, np.float32)
    check_ndim("generated", g, (4, 5))
    if g.shape != r.shape:
        raise ValueError(f"recorded: expected the shape of generated {list(g.shape)}, got {list(r.shape)}")
    if g.ndim == 4:
        g, r = g[None], r[None]
    if g.shape[-1] != 3:
        raise ValueError(f"generated: expected RGB frames [..., H, W, 3], got shape {list(g.shape)}")
    return FrameScores(r, cond_frames=cond_frames, seed=seed).add(g).result(window)
