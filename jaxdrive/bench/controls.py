"""Does each control pathway of the DiT carry its control? One toy per pathway in which that
control alone decides what changes between the given frame and the next, a fixed number of
training steps, then the flow loss with the true control against the control shuffled between
clips.

    jaxdrive bench controls [--pathways boxes layout map waypoints trajectory warp camera]
                            [--steps 60] [--batch 8] [--seed 0] [--lr 0.01] [--clips 16]

**Model.** For each pathway a one-layer ``tiny`` DiT (2 heads of 16) with only that control on
(no text, no fps), clean condition frames (``cond_frames="replace"``) and the given frame as a
residual base (``reference_frame="residual"``, ``prediction="data"``): the untrained model
repeats the given frame exactly, and training has to learn the change. Clips are one view of two
latent frames of 8 x 8 x 4 (a 64 x 64 image at the VAE's 8x compression); frame 0 is given (level
0, a random N(0, 1) "scene" ``x0``), frame 1 is generated, and its target is ``x1 = x0 + change``
where the change is decided by the control alone:

- ``boxes`` (cross-attention, ``controls.boxes``) and ``layout`` (the projected canvas,
  ``controls.layout``): one box 6-12 m ahead of a front camera, up to 3 m to either side; the
  change is +2 on the fraction of each latent cell the box covers (``layout_canvas``: the box
  appears). The same toy for both box pathways, so their rows compare them.
- ``map`` (the BEV map ControlNet, ``controls.map``): a 32 x 32 BEV map whose road channel is a
  random 4 x 4 pattern of 8 x 8-cell blocks; the change is +2 on the road mask resampled (mean) to
  the 4 x 4 token grid.
- ``waypoints`` (``controls.waypoints``, MiLA [2503.15875v1] eq. 1-2) and ``trajectory`` (MagicDrive-V2's ego
  trajectory encoder, ``controls.trajectory``): the ego moves 2-6 m forward and -2..2 m sideways
  between the frames; frame 1 is frame 0 multiplied by the sign of the lateral motion (``x1 = s
  x0``, change ``(s - 1) x0``). A shift left or right would be the physical picture; the sign
  was chosen because it is a local gate of the given frame (each cell needs its own given value
  and the control), where a shift needs each token to fetch its neighbour's content through
  attention, more than a few dozen steps of a one-layer model are likely to learn (not tried).
- ``warp`` (LongDWM's warped frames, ``controls.warp``): the control's frames are the given frame
  and the given frame rolled by -2..2 latent cells in each direction (the toy's warp along the
  ego motion); the target is that warped frame.
- ``camera`` (intrinsics and extrinsics, ``controls.camera``): one camera of random yaw (-90..90
  degrees) and focal length (0.6-1.5 x that of a 70-degree field of view); the change is +2 over
  the whole frame when the direction straight ahead of the ego lies in the camera's horizontal
  field of view (a landmark far ahead comes into view), 0 otherwise: yaw and intrinsics together
  decide it. (A landmark drawn where it projects would ask the per-view embedding for a spatial
  answer, which a one-layer model does not learn in a few dozen steps: its loss ratio stayed at
  0.995 after 60.)

**Training.** ``steps`` Adam steps at ``lr`` on ``batch`` fresh clips each, levels uniform in
[0.2, 1] for frame 1, the flow loss (MiLA [2503.15875v1] eq. 15, velocity from the data prediction,
:func:`jaxdrive.flow.velocity_from_output`) over frame 1.

**Figures** on ``clips`` held-out clips (drawn with the training clips, never trained on), with
one draw of noise and levels (frame 1's evenly 0.3 .. 0.9) shared by every figure:

- ``loss_true``, ``loss_shuffled``: the flow loss with the clips' own controls and with the
  controls rolled by one clip along the batch (every control field of the pathway moves
  together; the given frame and the target stay); ``ratio`` = loss_true / loss_shuffled (1: the
  pathway carries nothing). ``loss_repeat``: the untrained model's loss, which repeats the given
  frame.
- ``moved`` = ||x^(true) - x^(shuffled)|| / ||x1 - x0||: how far shuffling moves the generated
  frame's prediction ``x^`` (the model's clean-data output), as a fraction of the target's change
  from the given frame (norms over all held-out clips). The issue's "shuffling moves the output by
  11% of its change from the last frame" is this figure.
- ``follow`` = ||x^(true) - x^(shuffled)|| / ||x1(true) - x1(shuffled)||: the same movement as a
  fraction of how far the shuffle moves the target itself (the target under the shuffled control,
  with the clip's own given frame). A model that follows the control perfectly at these levels
  would be near 1 (less at low levels, where the noisy frame itself shows the target); 0 is a
  model that ignores the control.

Each pathway prints one JSON line (``figure`` ``control_ratio``, its value the ratio, with every
other figure as a field) and all of them one table.
"""

from __future__ import annotations

import argparse
import functools

import numpy as np

from jaxdrive.bench.report import emit, table

NAME = "controls"
PATHWAYS = ("boxes", "layout", "map", "waypoints", "trajectory", "warp", "camera")
DEFAULTS = dict(steps=60, batch=8, seed=0, lr=1e-2, clips=16)
H = W = 8  # latent grid; the image is 8x larger (vae_spatial)
CHANNELS = 4
MAP_HW = 32
# XLA's backend optimisations off: compiling a one-layer DiT's train step then takes less than
# half the CPU time (8 against 20 s measured), and the toys' steps are milliseconds either way
_FAST_COMPILE = {"xla_backend_optimization_level": 0}
# the control fields of each pathway (rolled together by the shuffle)
FIELDS = {
    "boxes": ("boxes", "box_classes", "box_valid"),
    "layout": ("boxes", "box_classes", "box_valid"),
    "map": ("bev_map",),
    "waypoints": ("waypoints",),
    "trajectory": ("ego_to_world",),
    "warp": ("warp",),
    "camera": ("intrinsics", "cam_to_ego"),
}
_CONTROLS = {
    "boxes": dict(boxes=True),
    "layout": dict(layout=True, layout_hidden=16),
    "map": dict(map=True, map_blocks=1, map_hidden=16),
    "waypoints": dict(waypoints=True),
    "trajectory": dict(trajectory=True),
    "warp": dict(warp=True),
    "camera": dict(camera=True),
}


def check_pathways(pathways) -> tuple[str, ...]:
    """``pathways`` as a tuple; ``ValueError`` naming ``--pathways`` for an unknown or empty one."""
    pathways = tuple(pathways)
    bad = [p for p in pathways if p not in PATHWAYS]
    if not pathways or bad:
        raise ValueError(f"--pathways: expected names from {list(PATHWAYS)}, got {list(pathways)}")
    return pathways


def check_options(*, steps: int, batch: int, clips: int, lr: float, seed: int = 0) -> None:
    """``ValueError`` naming the option for a non-positive count or learning rate."""
    for name, value in (("steps", steps), ("batch", batch), ("clips", clips), ("seed", seed)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < (name != "seed"):
            raise ValueError(f"--{name}: expected an integer >= {int(name != 'seed')}, got {value!r}")
    if clips < 2:
        raise ValueError(f"--clips: expected at least 2 clips to shuffle between, got {clips}")
    if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not 0 < lr < float("inf"):
        raise ValueError(f"--lr: expected a positive learning rate, got {lr!r}")


def config(pathway: str):
    """The one-layer DiT with only ``pathway``'s control (module docstring)."""
    from jaxdrive.models.dit.presets import preset

    check_pathways([pathway])
    return preset(
        "tiny",
        depth=1,
        heads=2,
        head_dim=16,
        in_channels=CHANNELS,
        prediction="data",
        controls=dict(text=None, fps=False, cond_frames="replace", reference_frame="residual", **_CONTROLS[pathway]),
    )


def _cameras(batch: int, yaw=None, focal_scale=None):
    """One camera at (1, 0, 1.5) m per clip, 70-degree field of view (times ``1 / focal_scale``),
    turned by ``yaw`` (radians, left positive) about the ego's z axis."""
    from jaxdrive.models.dit.inputs import example_cameras

    cams = example_cameras(batch, 1, 8 * H, 8 * W)
    if yaw is not None:
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.zeros((batch, 3, 3), np.float32)
        rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1
        cams["cam_to_ego"][:, 0, :3, :3] = rot @ cams["cam_to_ego"][:, 0, :3, :3]
    if focal_scale is not None:
        cams["intrinsics"][:, 0, 0, 0] *= focal_scale
        cams["intrinsics"][:, 0, 1, 1] *= focal_scale
    return cams


def _box_cover(boxes, cams):
    """The fraction of each latent cell that ``boxes [B, 1, N, 7]`` cover in the clip's camera,
    ``[B, 1 (view), h, w, 1]`` (:func:`jaxdrive.models.dit.layout.layout_canvas`, 2 x 2 rays a cell)."""
    return np.asarray(_cover(boxes, cams["intrinsics"], cams["cam_to_ego"]))


@functools.cache
def _cover_fn():
    import jax

    from jaxdrive.models.dit.layout import layout_canvas

    def cover(boxes, intrinsics, cam_to_ego):
        b, _, n = boxes.shape[:3]
        canvas = layout_canvas(
            boxes,
            np.zeros((b, 1, n), np.int32),
            np.ones((b, 1, n), bool),
            intrinsics,
            cam_to_ego,
            (8 * H, 8 * W),
            (H, W),
            num_classes=1,
            samples=2,
        )
        return canvas[:, 0, ..., :1]

    return jax.jit(cover, compiler_options=_FAST_COMPILE)


def _cover(*args):
    return _cover_fn()(*args)


def _ahead_in_view(intrinsics, cam_to_ego):
    """``[B]``: 1 where the direction straight ahead of the ego lies inside the horizontal field of
    view of the clip's camera (``intrinsics [B, 1, 3, 3]``, ``cam_to_ego [B, 1, 4, 4]``), else 0."""
    d = np.einsum("bji,j->bi", np.asarray(cam_to_ego)[:, 0, :3, :3], np.array([1.0, 0.0, 0.0]))  # in the camera
    k = np.asarray(intrinsics)[:, 0]
    u = k[:, 0, 0] * d[:, 0] / np.maximum(d[:, 2], 1e-9) + k[:, 0, 2]
    return ((d[:, 2] > 0) & (u >= 0) & (u <= 8 * W)).astype(np.float32)


def toy_clips(pathway: str, rng: np.random.Generator, batch: int):
    """``batch`` clips of ``pathway``'s toy (module docstring): ``(x [B, 1, 2, h, w, C], cond)``,
    ``cond`` a :class:`~jaxdrive.models.dit.conditions.Conditions` with the control and frame 0 as the
    given frame."""
    from jaxdrive.models.dit.conditions import Conditions

    check_pathways([pathway])
    x0 = rng.standard_normal((batch, 1, H, W, CHANNELS)).astype(np.float32)  # [B, V, h, w, C]
    kw = {}
    if pathway in ("boxes", "layout"):
        boxes = np.zeros((batch, 2, 1, 7), np.float32)
        boxes[..., 0], boxes[..., 1] = rng.uniform(6, 12, (batch, 1, 1)), rng.uniform(-3, 3, (batch, 1, 1))
        boxes[..., 2:6] = (1.0, 3.0, 2.5, 2.0)
        cams = _cameras(batch)
        x1 = x0 + 2 * _box_cover(boxes[:, :1], cams)
        kw = dict(
            boxes=boxes, box_classes=np.zeros((batch, 2, 1), np.int32), box_valid=np.ones((batch, 2, 1), bool), **cams
        )
    elif pathway == "map":
        road = (rng.uniform(size=(batch, 4, 4)) < 0.5).astype(np.float32)
        bev = np.zeros((batch, 2, MAP_HW, MAP_HW, 8), np.float32)
        bev[..., 0] = np.repeat(np.repeat(road, MAP_HW // 4, 1), MAP_HW // 4, 2)[:, None]
        tokens = bev[:, 0, ..., 0].reshape(batch, 4, MAP_HW // 4, 4, MAP_HW // 4).mean((2, 4))  # token grid
        cells = np.repeat(np.repeat(tokens, H // 4, 1), W // 4, 2)
        x1 = x0 + 2 * cells[:, None, :, :, None]
        kw = dict(bev_map=bev)
    elif pathway in ("waypoints", "trajectory"):
        forward, lateral = rng.uniform(2, 6, batch), rng.uniform(-2, 2, batch)
        x1 = np.sign(lateral)[:, None, None, None, None].astype(np.float32) * x0
        if pathway == "waypoints":
            wp = np.zeros((batch, 2, 2), np.float32)
            wp[:, 1, 0], wp[:, 1, 1] = forward, lateral
            kw = dict(waypoints=wp)
        else:
            yaw0 = rng.uniform(-np.pi, np.pi, batch)
            poses = np.tile(np.eye(4, dtype=np.float32), (batch, 2, 1, 1))
            c, s = np.cos(yaw0), np.sin(yaw0)
            for f in range(2):
                poses[:, f, 0, 0], poses[:, f, 0, 1], poses[:, f, 1, 0], poses[:, f, 1, 1] = c, -s, s, c
            poses[:, 0, :2, 3] = rng.uniform(-50, 50, (batch, 2))
            poses[:, 1, :2, 3] = poses[:, 0, :2, 3] + np.stack(
                [c * forward - s * lateral, s * forward + c * lateral], -1
            )
            kw = dict(ego_to_world=poses)
    elif pathway == "warp":
        shift = rng.integers(-2, 3, (batch, 2))
        x1 = np.stack([np.roll(x0[i], tuple(shift[i]), axis=(1, 2)) for i in range(batch)])
        kw = dict(warp=np.stack([x0, x1], axis=2))
    else:  # camera
        yaw, focal = rng.uniform(-np.pi / 2, np.pi / 2, batch), rng.uniform(0.6, 1.5, batch)
        kw = _cameras(batch, yaw, focal)
        x1 = x0 + 2 * _ahead_in_view(kw["intrinsics"], kw["cam_to_ego"])[:, None, None, None, None]
    x = np.stack([x0, x1], axis=2)  # [B, V, 2, h, w, C]
    mask = np.zeros((batch, 2), bool)
    mask[:, 0] = True
    return x, Conditions(cond_latents=x, cond_mask=mask, **kw)


def shuffled(pathway: str, cond):
    """``cond`` with ``pathway``'s control fields rolled by one clip along the batch."""
    return cond.replace(**{k: np.roll(np.asarray(getattr(cond, k)), 1, axis=0) for k in FIELDS[pathway]})


@functools.cache
def _functions(cfg, lr: float):
    """The jitted train step and data prediction of ``DiT(cfg)`` (compiled once per pathway and
    learning rate in a process)."""
    import jax
    import jax.numpy as jnp
    import optax

    from jaxdrive import flow
    from jaxdrive.models.dit.model import DiT

    dit, opt = DiT(cfg), optax.adam(lr)

    def loss(params, x, cond, noise, sigma):
        x_t = flow.add_noise(x, noise, sigma)
        v = flow.velocity_from_output(
            dit.forward(params, x_t, sigma, cond), x_t, sigma, cfg.prediction, cfg.prediction_min_sigma
        )
        return flow.flow_loss(v, x, noise, cond_mask=cond.cond_mask)

    @functools.partial(jax.jit, compiler_options=_FAST_COMPILE)
    def step(params, state, x, cond, key):
        k1, k2 = jax.random.split(key)
        sigma = jnp.stack([jnp.zeros(x.shape[0]), jax.random.uniform(k2, (x.shape[0],), minval=0.2)], 1)
        value, grads = jax.value_and_grad(loss)(params, x, cond, jax.random.normal(k1, x.shape), sigma)
        updates, state = opt.update(grads, state, params)
        return optax.apply_updates(params, updates), state, value

    predict = jax.jit(
        lambda params, x_t, sigma, cond: dit.forward(params, x_t, sigma, cond), compiler_options=_FAST_COMPILE
    )
    return dit, opt, step, predict


def measure(
    pathway: str,
    *,
    steps: int = DEFAULTS["steps"],
    batch: int = DEFAULTS["batch"],
    seed: int = DEFAULTS["seed"],
    lr: float = DEFAULTS["lr"],
    clips: int = DEFAULTS["clips"],
) -> dict:
    """Train ``pathway``'s toy model and measure it (module docstring): a dict with ``pathway``,
    ``steps``, ``loss_repeat``, ``loss_true``, ``loss_shuffled``, ``ratio``, ``moved``,
    ``follow`` and ``train_loss`` (the mean over the last ``min(10, steps)`` steps)."""
    import jax
    import jax.numpy as jnp

    from jaxdrive import flow

    check_pathways([pathway])
    check_options(steps=steps, batch=batch, clips=clips, lr=lr)
    cfg = config(pathway)
    dit, opt, step, predict = _functions(cfg, lr)
    params = jax.tree_util.tree_map(
        jnp.asarray, dit.init_params(seed, batch=batch, views=1, frames=2, height=H, width=W)
    )
    init = params
    state, rng, key = opt.init(params), np.random.default_rng(seed), jax.random.PRNGKey(seed)
    # every clip drawn at once (the box toys' canvas runs op by op: one shape, compiled once);
    # the last ``clips`` are held out
    data, conds = toy_clips(pathway, rng, steps * batch + clips)
    take = lambda a, lo, hi: jax.tree_util.tree_map(lambda v: v[lo:hi], a)
    losses = []
    for i in range(steps):
        lo, hi = i * batch, (i + 1) * batch
        params, state, value = step(params, state, data[lo:hi], take(conds, lo, hi), jax.random.fold_in(key, i))
        losses.append(value)

    # held-out clips, one draw of noise and levels for every figure
    x, cond = data[-clips:], take(conds, steps * batch, None)
    other = shuffled(pathway, cond)
    noise = jax.random.normal(jax.random.PRNGKey(seed + 1), x.shape)
    sigma = np.stack([np.zeros(clips), np.linspace(0.3, 0.9, clips)], 1).astype(np.float32)
    x_t = flow.add_noise(x, noise, sigma)

    def frame1(params, cond):  # the data prediction of frame 1 and the flow loss over it
        out = predict(params, x_t, sigma, cond)
        v = flow.velocity_from_output(out, x_t, sigma, cfg.prediction, cfg.prediction_min_sigma)
        return np.asarray(out)[:, :, 1], float(flow.flow_loss(v, x, noise, cond_mask=cond.cond_mask))

    (true, loss_true), (shuf, loss_shuffled) = frame1(params, cond), frame1(params, other)
    norm = lambda a: float(np.sqrt(np.sum(np.square(a))))
    moved = norm(true - shuf)
    return dict(
        pathway=pathway,
        steps=steps,
        loss_repeat=round(frame1(init, cond)[1], 4),
        loss_true=round(loss_true, 4),
        loss_shuffled=round(loss_shuffled, 4),
        ratio=round(loss_true / loss_shuffled, 4),
        moved=round(moved / norm(x[:, :, 1] - x[:, :, 0]), 4),
        follow=round(moved / max(norm(x[:, :, 1] - shuffled_target(pathway, x)), 1e-12), 4),
        train_loss=round(float(np.mean(np.asarray(losses[-min(10, steps) :]))), 4),
    )


def shuffled_target(pathway: str, x):
    """Frame 1's target of each clip of ``x [B, V, 2, h, w, C]`` (its given frame kept) under the
    control of :func:`shuffled` (the previous clip's): ``x0`` plus the change that control decides.
    The change of ``boxes``, ``layout``, ``map`` and ``camera`` is added to ``x0`` and depends on
    the control alone; ``warp``'s target is the control's frame; the ego motion's sign multiplies
    ``x0``."""
    x0, x1 = x[:, :, 0], x[:, :, 1]
    roll = lambda a: np.roll(a, 1, axis=0)
    if pathway == "warp":
        return roll(x1)
    if pathway in ("waypoints", "trajectory"):
        sign = np.sign(np.sum(x0 * x1, axis=(1, 2, 3, 4)))
        return roll(sign)[:, None, None, None, None] * x0
    check_pathways([pathway])
    return x0 + roll(x1 - x0)


def run(pathways=PATHWAYS, **options) -> list[dict]:
    """Measure each of ``pathways`` (module docstring); print one JSON line each and the table."""
    import jax

    pathways = check_pathways(pathways)
    check_options(**{k: options.get(k, v) for k, v in DEFAULTS.items()})
    rows = []
    for pathway in pathways:
        row = measure(pathway, **options)
        rows.append(row)
        ctx = {k: v for k, v in row.items() if k != "ratio"}
        emit(
            NAME,
            "control_ratio",
            row["ratio"],
            "loss_true / loss_shuffled",
            backend=jax.default_backend(),
            **{k: v for k, v in options.items() if k != "steps"},
            **ctx,
        )
    print(table(rows, ["pathway", "steps", "loss_repeat", "loss_true", "loss_shuffled", "ratio", "moved", "follow"]))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench controls", description=__doc__.split("\n\n")[0])
    parser.add_argument("--pathways", nargs="+", default=list(PATHWAYS), help=f"any of {', '.join(PATHWAYS)}")
    parser.add_argument("--steps", type=int, default=DEFAULTS["steps"], help="Adam steps per pathway")
    parser.add_argument("--batch", type=int, default=DEFAULTS["batch"], help="clips per training step")
    parser.add_argument("--seed", type=int, default=DEFAULTS["seed"])
    parser.add_argument("--lr", type=float, default=DEFAULTS["lr"], help="Adam learning rate")
    parser.add_argument("--clips", type=int, default=DEFAULTS["clips"], help="held-out clips")
    args = parser.parse_args(argv)
    pathways = check_pathways(args.pathways)
    check_options(steps=args.steps, batch=args.batch, clips=args.clips, lr=args.lr, seed=args.seed)
    return run(pathways, steps=args.steps, batch=args.batch, seed=args.seed, lr=args.lr, clips=args.clips)


if __name__ == "__main__":
    main()
