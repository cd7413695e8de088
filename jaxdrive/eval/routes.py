"""Scoring control with counterfactual ground truth: ``jaxdrive eval --routes recorded,stop,...``.

A dataset written with ``jaxdrive data synth --counterfactuals`` holds, beside each validation
clip, the same scene rendered along other ego routes (:mod:`jaxdrive.data.synth_routes`); their
frames before the route's ``start`` are the recorded clip's. Every strategy starts from the same
given frames and is conditioned on each route's controls in turn (its waypoints, trajectory, warp
poses, and the boxes and map re-rendered along it), then scored against that route's render.
Two baselines per route: ``repeat`` (the last given frame held) and ``warp`` (the last given frame
warped along the route's ego poses with LongDWM's depth-free warp and inpainted: the classical
baseline, :func:`jaxdrive.warp.warp_views`). And one figure per route and strategy:

    route effect = score(generation under the route, against the route's render)
                 - score(generation under the recorded route, against the same render)

per horizon bucket and metric (PSNR, SSIM, mIoU): 0 means the model ignored the route, and a
model that follows its controls scores above 0 on every route that changes the future.
"""

from __future__ import annotations

import numpy as np

from jaxdrive.eval.compare import EFFECT_METRICS, effect_table, score  # noqa: F401  (effect_table: its old home)

RECORDED = "recorded"
SEP = " @ "  # result names: "rollout @ stop", "repeat frame 1 @ stop", "warp @ stop"
WARP = "warp"


def parse_routes(text: str) -> list[str]:
    """``--routes "recorded,stop"`` -> at least one route name (:func:`jaxdrive.data.synth_routes.parse_routes`)."""
    from jaxdrive.data.synth_routes import parse_routes as parse

    names = parse(text, "routes")
    if not names:
        raise ValueError(f"routes: expected at least one route, got {text!r}")
    return names


def route_clips(dataset, routes, clips: int, given_frames: int, stride: int = 1) -> dict:
    """Which clips every route is scored on: ``{"indices": [validation clip of each sample],
    "rows": {route: [row of its split for each sample]}, "splits": {route: split}}``, the first
    ``clips`` validation clips that have every route. ``ValueError`` naming ``routes`` when the
    dataset has no counterfactuals, lacks a route, has too few clips with all of them, or when
    its routes change before the given frames end (``given_frames`` pixel frames at ``stride``)."""
    from jaxdrive.data.synthetic import read_counterfactuals

    meta = read_counterfactuals(dataset)
    others = [r for r in routes if r != RECORDED]
    if others and not meta:
        raise ValueError(
            f"routes: expected a dataset with counterfactual routes (jaxdrive data synth "
            f"--counterfactuals ...), got {dataset} without any"
        )
    stored = meta.get("routes", {})
    missing = [r for r in others if r not in stored]
    if missing:
        raise ValueError(
            f"routes: expected routes stored in {dataset} ({', '.join(stored) or 'none'}), got {', '.join(missing)}"
        )
    if others and (given_frames - 1) * stride >= meta["start"]:
        raise ValueError(
            f"routes: expected the given frames to end before the routes change (source frame "
            f"{meta['start']}), got {given_frames} given frames at stride {stride}"
        )
    have = [set(stored[r]["clips"]) for r in others]
    common = sorted(set.intersection(*have)) if have else None
    indices = list(range(clips)) if common is None else common[:clips]
    if len(indices) < clips:
        raise ValueError(
            f"clips: expected at most {len(indices)} (the validation clips that have every route of "
            f"routes {','.join(routes)}), got {clips}"
        )
    rows = {r: list(range(clips)) if r == RECORDED else [stored[r]["clips"].index(i) for i in indices] for r in routes}
    splits = {r: None if r == RECORDED else stored[r]["split"] for r in routes}
    start = -(-int(meta["start"]) // stride) if others else None  # the first generated frame a route changes
    return {"indices": indices, "rows": rows, "splits": splits, "start": start}


def following_scores(video, ego_to_world, intrinsics, cam_to_ego, start: int, fps) -> dict:
    """Route following read from the pixels (:mod:`jaxdrive.eval.ego_motion`) of ``video [B, V, F,
    H, W, 3]`` (in [-1, 1]) against the commanded poses ``ego_to_world [B, F, 4, 4]``: the mean
    ``ade`` and ``fde`` (metres, from frame ``start`` on), the fraction of clips whose manoeuvre
    is ``recognised``, and each clip's ``manoeuvres`` and ``commanded`` ones. ``fps``: the clips'
    frame rate (``[B]`` or one number)."""
    from jaxdrive.eval.ego_motion import estimate_ego_motion, motion_from_poses, route_following

    video = np.asarray(video, np.float32)
    rates = np.broadcast_to(np.asarray(fps, np.float64), (video.shape[0],))
    per = [
        route_following(
            estimate_ego_motion(video[b], intrinsics[b], cam_to_ego[b]),
            motion_from_poses(ego_to_world[b]),
            start,
            float(rates[b]),
        )
        for b in range(video.shape[0])
    ]
    return {
        "ade": float(np.mean([p["ade"] for p in per])),
        "fde": float(np.mean([p["fde"] for p in per])),
        "recognised": float(np.mean([p["recognised"] for p in per])),
        "clips": len(per),
        "manoeuvres": [p["manoeuvre"] for p in per],
        "commanded": [p["commanded"] for p in per],
    }


def warp_video(render, poses, given: int, depth: float) -> np.ndarray:
    """The ``warp`` baseline's frames: ``render [B, V, F, H, W, 3]`` up to frame ``given - 1``,
    that frame warped along the route's ego poses after it."""
    from jaxdrive.warp import warp_views

    video = np.array(render, copy=True)
    for b in range(video.shape[0]):
        e2w = np.asarray(poses["ego_to_world"][b], np.float64)
        rel = (np.linalg.inv(e2w[given - 1]) @ e2w[given - 1 :]).astype(np.float32)
        video[b, :, given:] = warp_views(
            video[b, :, given - 1], poses["intrinsics"][b], poses["cam_to_ego"][b], rel, depth
        )[:, 1:]
    return video


def route_effect(results: dict, against: dict, routes) -> dict:
    """``{route: {strategy: {bucket: {metric: difference}}}}``: each strategy's score under the
    route minus the recorded-route generation's score against the same render (``against``:
    strategy -> route -> buckets, from :func:`jaxdrive.eval.compare.run_strategies`'s
    ``targets``)."""
    out = {}
    for route in routes:
        if route == RECORDED:
            continue
        for name, by_route in against.items():
            mine = results[f"{name}{SEP}{route}"]["buckets"]
            base = by_route[route]
            out.setdefault(route, {})[name] = {
                span: {
                    m: round(mine[span][m] - base[span][m], 4)
                    for m in EFFECT_METRICS
                    if mine[span].get(m) is not None and base[span].get(m) is not None
                }
                for span in mine
            }
    return out


def evaluate_routes(
    routes,
    plan,
    *,
    load_inputs,
    first_latents,
    strategies,
    models,
    codec,
    length,
    buckets,
    key,
    given: int,
    depth: float,
    warp_frame: int = 0,
    mesh=None,
    segment=None,
    without_boxes: bool = False,
    ego_motion: bool = False,
    fps: float = 12.0,
    **features,
) -> tuple[dict, dict, list, dict | None]:
    """Every strategy under every route of ``routes`` (:func:`route_clips`'s ``plan``), scored
    against each route's render, with the ``repeat`` and ``warp`` rows per route; returns
    ``(results, effects, rows, ceiling)``: the results and route effects for
    :func:`jaxdrive.eval.compare.write_outputs`, and for the first clip and strategy the
    ``(label, render, generated)`` videos of each route (:func:`jaxdrive.media.write_route_grid`).

    ``load_inputs(split, indices)`` gives :func:`jaxdrive.generate.samples.dataset_inputs` of those
    clips (with ``poses``, and ``class_masks`` with a ``segment`` function);
    ``first_latents(inputs)`` the given latents every strategy starts from; ``depth`` and
    ``warp_frame``: a warp-guided model's ``data.warp_depth`` and ``data.warp_frame``. With
    ``ego_motion``, every result also has ``following`` (:func:`following_scores`: the ego's path
    read from its frames against the route's, from the route's start on; the clips' frame rate
    ``fps``) and ``ceiling`` is the same read from each route's render, ``{route: scores}`` (the
    estimator's own error; None without ``ego_motion``). Every route's
    generation draws the same noise (``key``), so what differs between routes is the controls.
    ``without_boxes``: one more row, the first strategy under the recorded route with the boxes
    (and the layout drawn from them) dropped to their learned nulls, named ``"NAME (no boxes)"``:
    what the boxes change."""
    from jaxdrive.eval.compare import baseline_row, repeat_name, repeat_video, run_strategies
    from jaxdrive.generate.warps import warp_options

    base = load_inputs(None, plan["indices"])
    inputs = {r: base if r == RECORDED else load_inputs(plan["splits"][r], plan["rows"][r]) for r in routes}
    first = first_latents(base)
    masks = lambda inp: inp.get("class_masks") if segment is not None else None
    targets = {r: (np.asarray(inp["video"]), masks(inp)) for r, inp in inputs.items() if r != RECORDED}

    def run(inp, names=strategies, cond=None, **kw):
        opts = warp_options(models, inp, codec, depth=depth, frame=warp_frame)  # along this route's poses
        return run_strategies(
            {n: opts for n in names},
            models,
            codec,
            inp["cond"] if cond is None else cond,
            first,
            length,
            np.asarray(inp["video"]),
            buckets,
            key=key,
            mesh=mesh,
            segment=segment,
            masks=masks(inp),
            keep=True,
            **features,
            **kw,
        )

    ceiling = {} if ego_motion else None
    recorded = run(base, targets=targets)
    against = {name: r.pop("against") for name, r in recorded.items()}
    results, rows = {}, []
    for route in routes:
        inp = inputs[route]
        video = np.asarray(inp["video"])
        runs = recorded if route == RECORDED else run(inp)
        rows.append((f"{strategies[0]} @ {route}", video[0], runs[strategies[0]]["video"][0]))
        p = inp["poses"]
        start = plan.get("start") or given
        follow = lambda v: following_scores(v, p["ego_to_world"], p["intrinsics"], p["cam_to_ego"], start, fps)
        if ego_motion:
            ceiling[route] = follow(video)
        for name, r in runs.items():
            extra = {"following": follow(r["video"])} if ego_motion else {}
            r = {k: v for k, v in r.items() if k != "video"}
            results[name if route == RECORDED else f"{name}{SEP}{route}"] = {**r, **extra, "route": route}
        label = "" if route == RECORDED else f"{SEP}{route}"
        # the baselines: the last given frame held, and warped along the route (each made once)
        for name, base_video in (
            (repeat_name(given) + label, repeat_video(video, given)),
            (f"{WARP}{SEP}{route}", warp_video(video, p, given, depth)),
        ):
            row = baseline_row(base_video, video, buckets, segment=segment, masks=masks(inp), **features)
            results[name] = {**row, **({"following": follow(base_video)} if ego_motion else {}), "route": route}
    if without_boxes:
        # the box inputs left out, which the DiT reads as dropped (the learned null of box
        # cross-attention, nothing from the layout); the same sample as a boxes drop of True
        cond = base["cond"].replace(boxes=None, box_classes=None, box_valid=None)
        name = strategies[0]
        r = run(base, names=[name], cond=cond)[name]
        rows.append((f"{name} @ recorded, no boxes", np.asarray(base["video"])[0], r.pop("video")[0]))
        results[f"{name} (no boxes)"] = {**r, "route": RECORDED}
    return results, route_effect(results, against, routes), rows, ceiling
