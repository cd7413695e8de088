"""Long-video strategies scored side by side on the same clips: ``jaxdrive eval``.

Each strategy runs (:func:`jaxdrive.generate.strategies.run_strategy`) from the same given frames
and controls; its latents are decoded part by part and scored against the recorded clip per
horizon bucket (frame ranges of the output clip): PSNR and SSIM always; FID (per view and over all
views) and FVD (16-frame windows) where feature functions are given (the FID Inception, the I3D:
:mod:`jaxdrive.eval.inception`, :mod:`jaxdrive.eval.i3d`). Writes ``eval.json``, ``eval.md`` (a
table of strategies x metrics) and ``quality_vs_horizon.png``.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from jaxdrive.eval.fid import FeatureStats
from jaxdrive.generate.quality import psnr, ssim

logger = logging.getLogger(__name__)

FVD_FRAMES = 16
EFFECT_METRICS = ("psnr", "ssim", "miou")  # the route effects (:mod:`jaxdrive.eval.routes`) of each row


def parse_buckets(text: str | None, given: int, frames: int) -> list[tuple[int, int]]:
    """``--buckets "2-12,13-24"`` (inclusive output frame ranges, after the ``given`` frames) ->
    ``[(2, 13), (13, 25), (2, 25)]`` (half-open; the last, when there are several, the whole span
    they cover: the overall scores); None: the generated frames in thirds."""
    if text is None:
        edges = np.linspace(given, frames, 4).round().astype(int)
        out = [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    else:
        out = []
        for part in text.split(","):
            try:
                a, b = (int(v) for v in part.split("-"))
            except ValueError:
                raise ValueError(f"buckets: expected ranges like 2-12,13-24, got {text!r}") from None
            out.append((a, b + 1))
    for a, b in out:
        if not given <= a < b <= frames:
            raise ValueError(
                f"buckets: expected ranges within the generated frames {given}-{frames - 1}, got "
                f"{a}-{b - 1} (clips shorter than the horizon buckets)"
            )
    whole = (min(a for a, _ in out), max(b for _, b in out))
    return out + [whole] if len(out) > 1 and whole not in out else out


def _horizon_rows(rows: list) -> list:
    """The per-bucket rows of a result, without the overall one (:func:`parse_buckets`)."""
    if len(rows) > 2 and rows[-1]["frames"] == [
        min(r["frames"][0] for r in rows[:-1]),
        max(r["frames"][1] for r in rows[:-1]),
    ]:
        return rows[:-1]
    return rows


def _to_255(video):
    return np.clip((np.asarray(video, np.float32) + 1.0) * 127.5, 0.0, 255.0)


def controllability(segment, video, masks, buckets) -> dict:
    """Per bucket, the segmenter's scores (:func:`jaxdrive.models.segmenter.summary`: ``miou``,
    ``per_class``, ``pixel_accuracy``) of ``video [B, V, F, H, W, 3]`` against the class ids
    ``masks [B, V, F, H, W]`` (and the bucket's ``frames``); ``segment(frames) -> class ids``."""
    from jaxdrive.models.segmenter import confusion, summary

    lo, hi = min(a for a, _ in buckets), max(b for _, b in buckets)
    pred = segment(video[:, :, lo:hi])  # once: the buckets overlap (the whole span is one)
    return {
        f"{a}-{b - 1}": {"frames": [a, b - 1], **summary(confusion(pred[:, :, a - lo : b - lo], masks[:, :, a:b]))}
        for a, b in buckets
    }


def score(video, recorded, buckets, *, fid_features=None, fvd_features=None, segment=None, masks=None) -> dict:
    """Scores of ``video`` against ``recorded`` (both ``[B, V, F, H, W, 3]`` in [-1, 1]) per bucket:
    ``psnr``, ``ssim``; ``fid`` (over all views) and ``fid_per_view`` with ``fid_features(images
    [N, H, W, 3] in [0, 255]) -> [N, D]``; ``fvd`` with ``fvd_features(videos [N, 16, H, W, 3])``
    over the bucket's 16-frame windows (None where the bucket is shorter); ``miou`` and
    ``miou_per_class`` with ``segment`` and the class ``masks`` of the boxes the video was
    conditioned on (:func:`controllability`)."""
    out = {}
    control = controllability(segment, video, masks, buckets) if segment is not None else {}
    lo, hi = min(a for a, _ in buckets), max(b for _, b in buckets)
    if fid_features is not None:  # every frame's features once: the buckets overlap

        def frame_features(x):
            x = x[:, :, lo:hi]
            return np.asarray(fid_features(_to_255(x.reshape(-1, *x.shape[3:])))).reshape(*x.shape[:3], -1)

        frame_feats = [frame_features(x) for x in (video, recorded)]  # [B, V, F, D] each
    for a, b in buckets:
        g, r = video[:, :, a:b], recorded[:, :, a:b]
        row = {
            "frames": [a, b - 1],
            "psnr": float(np.minimum(np.asarray(psnr(g, r)), 100.0).mean()),
            "ssim": float(np.asarray(ssim(g, r)).mean()),
        }
        if control:
            c = control[f"{a}-{b - 1}"]
            row["miou"] = c["miou"]
            row["miou_per_class"] = {k: v for k, v in c["per_class"].items() if k != "background" and v is not None}
        if fid_features is not None:
            fg, fr = (f[:, :, a - lo : b - lo] for f in frame_feats)
            stats = lambda f: FeatureStats(f.shape[-1]).add(f.reshape(-1, f.shape[-1]))
            row["fid_per_view"] = [round(stats(fg[:, v]).fid(stats(fr[:, v])), 4) for v in range(fg.shape[1])]
            row["fid"] = stats(fg).fid(stats(fr))
        if fvd_features is not None:
            starts = range(a, b - FVD_FRAMES + 1, FVD_FRAMES)
            if len(starts) * video.shape[0] * video.shape[1] >= 2:

                def windows(x):
                    w = np.stack([x[:, :, s : s + FVD_FRAMES] for s in starts], 2)  # [B, V, W, 16, H, W, 3]
                    return _to_255(w.reshape(-1, *w.shape[3:]))

                f = [np.asarray(fvd_features(windows(x))) for x in (video, recorded)]
                row["fvd"] = FeatureStats(f[0].shape[1]).add(f[0]).fid(FeatureStats(f[1].shape[1]).add(f[1]))
            else:
                row["fvd"] = None
        out[f"{a}-{b - 1}"] = row
    return out


REPEAT = "repeat frame "  # the baseline rows: "repeat frame 1" holds frame 1 (2 given frames)


def repeat_name(given: int) -> str:
    return f"{REPEAT}{given - 1}"


def repeat_video(recorded, given: int) -> np.ndarray:
    """``recorded [B, V, F, H, W, 3]`` with its last given frame (``given - 1``) held for every later frame."""
    video = np.array(recorded, copy=True)
    video[:, :, given:] = video[:, :, given - 1 : given]
    return video


def baseline_row(video, recorded, buckets, **features) -> dict:
    """A baseline's ``video`` scored as a strategy (:func:`score`) against ``recorded``, with no time."""
    return {"seconds": None, "peak_device_bytes": None, "buckets": score(video, recorded, buckets, **features)}


def repeat_baseline(recorded, given: int, buckets, **features) -> dict:
    """The baseline row :func:`repeat_name`: the recorded clip's last given frame held for every
    later frame (:func:`repeat_video`), scored as a strategy; what a model that learned no motion gets."""
    return baseline_row(repeat_video(recorded, given), recorded, buckets, **features)


def run_strategies(
    strategies,
    models,
    codec,
    controls,
    first,
    length,
    recorded,
    buckets,
    *,
    key,
    mesh=None,
    fid_features=None,
    fvd_features=None,
    segment=None,
    masks=None,
    targets=None,
    keep=False,
) -> dict:
    """Every strategy of ``strategies`` (name -> its options) on the same inputs, decoded and
    scored (:func:`score`); returns ``{name: {"seconds", "sequential_sampler_calls",
    "peak_device_bytes", "buckets": {...}}}``. ``targets`` (label -> ``(video, masks)``): each
    generation is also scored against these other videos (the counterfactual renders of
    ``jaxdrive eval --routes``), under the result's ``"against": {label: buckets}``. ``keep``:
    the clips' decoded videos ``[B, V, F, H, W, 3]`` stay under ``"video"`` (pop them before
    writing the results as JSON). Each strategy's time is logged at INFO."""
    from jaxdrive.generate.strategies import run_strategy
    from jaxdrive.generate.windows import Tracker

    results = {}
    for name, opts in strategies.items():
        tracker = Tracker()
        start = time.perf_counter()
        decoder = codec.stream_decoder(length)
        parts = []
        for part in run_strategy(
            name, models, controls, first, length, key=key, tracker=tracker, mesh=mesh, **(opts or {})
        ):
            video = decoder.push(part)
            if video is not None and video.shape[2]:
                parts.append(np.asarray(video))
            tracker.observe()
        tail = decoder.flush()
        if tail is not None and tail.shape[2]:
            parts.append(np.asarray(tail))
        seconds = time.perf_counter() - start
        video = np.concatenate(parts, axis=2)
        results[name] = {
            "seconds": round(seconds, 3),
            "sequential_sampler_calls": tracker.calls,
            "peak_device_bytes": int(tracker.peak_bytes),
            "buckets": score(
                video,
                recorded,
                buckets,
                fid_features=fid_features,
                fvd_features=fvd_features,
                segment=segment,
                masks=masks,
            ),
        }
        if keep:
            results[name]["video"] = video
        if targets:
            results[name]["against"] = {
                label: score(video, target, buckets, segment=segment, masks=target_masks)
                for label, (target, target_masks) in targets.items()
            }
        logger.info(
            "%s: %d frames x %d views x %d clips in %.1f s",
            name,
            video.shape[2],
            video.shape[1],
            video.shape[0],
            seconds,
        )
    return results


def table(results: dict, ceiling: dict | None = None) -> str:
    """A markdown table: one row per strategy and bucket; ``ceiling`` (:func:`controllability` of
    the recorded frames) adds the segmenter's mIoU on them as rows ``recorded frames``."""
    metrics = [
        m
        for m in ("psnr", "ssim", "fid", "fvd", "miou")
        if any(m in row for r in results.values() for row in r["buckets"].values())
    ]
    head = ["strategy", "frames", *[m.upper() if m != "miou" else "mIoU" for m in metrics], "seconds", "peak MiB"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in results.items():
        for span, row in r["buckets"].items():
            cells = [f"{row[m]:.3f}" if row.get(m) is not None else "-" for m in metrics]
            seconds = "-" if r.get("seconds") is None else f"{r['seconds']:.1f}"
            peak = "-" if r.get("peak_device_bytes") is None else f"{r['peak_device_bytes'] / 2**20:.1f}"
            lines.append(f"| {name} | {span} | " + " | ".join(cells) + f" | {seconds} | {peak} |")
    for span, row in (ceiling or {}).items():
        cells = [f"{row['miou']:.3f}" if m == "miou" and row["miou"] is not None else "-" for m in metrics]
        lines.append(f"| recorded frames | {span} | " + " | ".join(cells) + " | - | - |")
    return "\n".join(lines)


def write_outputs(
    results: dict,
    out,
    *,
    meta: dict,
    ceiling: dict | None = None,
    effects: dict | None = None,
    following: dict | None = None,
) -> dict:
    """``eval.json``, ``eval.md`` and ``quality_vs_horizon.png`` under ``out``; returns the paths.
    ``ceiling``: the segmenter's scores on the recorded frames (``eval.json``'s
    ``recorded_controllability`` and the table's ``recorded frames`` rows). ``effects``: the
    route effects of ``--routes`` (:func:`jaxdrive.eval.routes.route_effect`), ``eval.json``'s
    ``route_effect``, a second table in ``eval.md`` and a panel of the plot. ``following``: the
    ego-motion estimator's scores on each route's render (``--ego-motion``, ``eval.json``'s
    ``route_following_ceiling``), which with the results' own ``following`` make a third table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    extra = {} if ceiling is None else {"recorded_controllability": ceiling}
    if effects:
        extra["route_effect"] = effects
    if following is not None:
        extra["route_following_ceiling"] = following
    (out / "eval.json").write_text(json.dumps({**meta, **extra, "strategies": results}, indent=1))
    md = table(results, ceiling)
    if effects:
        md += (
            "\n\nRoute effect (the generation under the route minus the recorded-route generation, both "
            "against the route's render; 0: the route was ignored):\n\n" + effect_table(effects)
        )
    if following is not None or any("following" in r for r in results.values()):
        md += (
            "\n\nRoute following (the ego's path read from the frames, jaxdrive.eval.ego_motion, against "
            "the route's; render: the estimator on the route's own render, its error):\n\n"
            + following_table(results, following or {})
        )
    (out / "eval.md").write_text(md + "\n")
    panels = [("psnr", "PSNR dB against the recorded clip", "PSNR vs horizon")]
    if any(row.get("miou") is not None for r in results.values() for row in r["buckets"].values()):
        panels.append(("miou", "segmenter mIoU against the boxes", "controllability vs horizon"))
    count = len(panels) + bool(effects)
    fig, axes = plt.subplots(1, count, figsize=(6 * count, 3.5), dpi=120, squeeze=False)
    for ax, (metric, label, title) in zip(axes[0], panels):
        for name, r in results.items():
            rows = _horizon_rows(list(r["buckets"].values()))
            ax.plot([np.mean(row["frames"]) for row in rows], [row.get(metric) for row in rows], marker="o", label=name)
        if metric == "miou" and ceiling:
            rows = _horizon_rows(list(ceiling.values()))
            ax.plot(
                [np.mean(row["frames"]) for row in rows], [row["miou"] for row in rows], "k--", label="recorded frames"
            )
        ax.set(xlabel="frame (bucket centre)", ylabel=label, title=title)
        ax.grid(alpha=0.3)
        ax.legend()
    if effects:
        _effect_panel(axes[0][-1], effects)
    fig.tight_layout()
    fig.savefig(out / "quality_vs_horizon.png")
    plt.close(fig)
    return {"json": out / "eval.json", "md": out / "eval.md", "plot": out / "quality_vs_horizon.png", "table": md}


def following_table(results: dict, ceiling: dict) -> str:
    """A markdown table of route following: one row per route's render (``ceiling``) and per
    result with ``following``: ADE, FDE, the share of clips whose manoeuvre is recognised."""
    lines = ["| route | strategy | ADE m | FDE m | manoeuvre recognised | clips |", "|---|---|---|---|---|---|"]
    row = lambda route, name, f: (
        f"| {route} | {name} | {f['ade']:.2f} | {f['fde']:.2f} | {f['recognised']:.0%} | {f['clips']} |"
    )
    for route, f in ceiling.items():
        lines.append(row(route, "render", f))
    for name, r in results.items():
        if "following" in r:
            lines.append(row(r.get("route", "recorded"), name, r["following"]))
    return "\n".join(lines)


def effect_table(effects: dict) -> str:
    """A markdown table of :func:`jaxdrive.eval.routes.route_effect`: one row per route, strategy and bucket."""
    metrics = [
        m for m in EFFECT_METRICS if any(m in row for r in effects.values() for s in r.values() for row in s.values())
    ]
    head = ["route", "strategy", "frames", *[f"{m.upper() if m != 'miou' else 'mIoU'} effect" for m in metrics]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for route, by_strategy in effects.items():
        for name, spans in by_strategy.items():
            for span, row in spans.items():
                cells = [f"{row[m]:+.3f}" if m in row else "-" for m in metrics]
                lines.append(f"| {route} | {name} | {span} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _effect_panel(ax, effects):
    """The PSNR route effect per horizon on ``ax``, a line per route and strategy."""
    for route, by_strategy in effects.items():
        for name, spans in by_strategy.items():
            rows = _horizon_rows([{"frames": [int(v) for v in k.split("-")], **row} for k, row in spans.items()])
            ax.plot(
                [np.mean(r["frames"]) for r in rows],
                [r.get("psnr") for r in rows],
                marker="o",
                label=f"{name} @ {route}",
            )
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set(xlabel="frame (bucket centre)", ylabel="PSNR dB, route minus recorded route", title="route effect")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)


def merge(dirs) -> tuple[dict, dict, dict | None, dict]:
    """``(results, meta, ceiling, effects)`` of several ``eval.json`` (the meta holds the first
    one's ``route_following_ceiling``, the data's, when it has one) (strategies of different
    models on the same clips: MiLA's, LongDWM's, STAGE's): each strategy named ``"name (run)"``
    after the run it sampled, in the results and in the route effects of ``--routes``. They must
    agree on the clips, frames, buckets, segmenter, shuffling and routes, or the rows would not
    compare: a ``ValueError`` names what differs. The baselines (repeat, warp) are the recorded
    data's, kept once."""
    results, baselines, first, ceiling, effects = {}, {}, None, None, {}
    same = ("clips", "frames", "segmenter", "shuffle_boxes", "split", "routes")
    for d in dirs:
        path = Path(d) / "eval.json"
        try:
            report = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise ValueError(f"merge: expected eval.json of jaxdrive eval under {str(d)!r}, got {e}") from None
        spans = [list(r["buckets"]) for r in report["strategies"].values()]
        if first is None:
            first, ceiling, want = report, report.get("recorded_controllability"), spans[0]
        for key in same:
            if report.get(key) != first.get(key):
                raise ValueError(
                    f"merge: expected the same {key} in every eval.json, got {first.get(key)!r} in "
                    f"{dirs[0]} and {report.get(key)!r} in {d}"
                )
        if any(s != want for s in spans):
            raise ValueError(
                f"merge: expected the same horizon buckets in every eval.json (evaluate with the same "
                f"buckets), got {want} in {dirs[0]} and {spans[0]} in {d}"
            )
        run = Path(report.get("workdir") or report.get("videos") or str(d)).name
        for name, r in report["strategies"].items():
            if name.startswith(REPEAT) or name.startswith("warp @ "):  # the data's, not a model's: once, last
                baselines.setdefault(name, r)
            else:
                results[f"{name} ({run})"] = r
        for route, by_strategy in report.get("route_effect", {}).items():
            for name, spans in by_strategy.items():
                effects.setdefault(route, {})[f"{name} ({run})"] = spans
    results.update(baselines)
    meta = {k: first.get(k) for k in ("clips", "frames", "views", "segmenter", "shuffle_boxes", "split", "routes")}
    if first.get("route_following_ceiling") is not None:
        meta["route_following_ceiling"] = first["route_following_ceiling"]
    return results, {**meta, "merged": [str(d) for d in dirs]}, ceiling, effects
