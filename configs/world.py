"""World: the CPU recipe that shows control (issue 33, part 5), an hour on 2 cores.

``configs/tiny.py`` (its model, latents and training aids: clean given frames, the residual to the
newest given frame, predicted data) with the controls that ``jaxdrive bench controls`` found
learnable in a few dozen steps, and none that it did not:

- the projected layout (``controls.layout``): every box of the clip ray cast into each camera and
  the BEV map's road classes on the visible ground, on the latent grid; in the bench the true layout
  gave 0.05x the flow loss of a shuffled one, where box cross-attention gave 0.93x, so the boxes
  come in through the layout alone (``controls.boxes`` off) and a box dropped for guidance is
  dropped from the canvas;
- the ego's waypoints (MiLA [2503.15875v1] eq. 1-2, added to the tokens, 0.14x): the route;
- the cameras, the frame rate and the caption, as in tiny.py.

Noise levels: SD3's resolution-dependent timestep shift (Esser et al. 2024, arXiv 2403.03206:
``t' = s t / (1 + (s - 1) t)``, :func:`jaxdrive.flow.shift_sigmas`) at ``flow.shift=3``, in
training and sampling. A data-predicting model trained with the velocity
loss (JiT's v-loss) weighs level ``t`` by ``1 / t^2``, so at tiny.py's shift 1 the levels near
pure noise, where a sample's layout and motion are decided, get almost none of the gradient: after
4000 steps its prediction from pure noise scored 19.39 dB (latent PSNR, 2 validation clips,
frames 2-8) against 20.23 for repeating the last given frame, and its samples fell below repeat
already in the first window (19.29). 1200 more steps at shift 3 gave 21.15 and 20.64, and the
rollout above ``repeat`` in PSNR in every bucket of every route (docs/results/demo.md).

Left out: the ego trajectory token (the bench's loss ratio was 0.98, a token no layer learned to
read in its steps) and the BEV-map ControlNet (the layout already paints the map's road classes
where the cameras see the ground; the ControlNet would double the step time).

Data: the clips of ``jaxdrive data synth`` at 2x the latent resolution (64 x 112, 6 views, 33
frames, the validation clips also along the counterfactual routes; docs/guides/demo.md,
the world recipe), 9-frame windows at random offsets, 2 given frames. Train and score::

    jaxdrive data synth --out data/world --scenes 200 --val-fraction 0.04 --frames 33 \\
        --counterfactuals stop,slower,faster,lane-left --counterfactual-splits validation --skip-undrivable
    jaxdrive train --config configs/world.py --workdir runs/world --set data.path=data/world
    jaxdrive eval --workdir runs/world --frames 33 --routes recorded,stop,slower,faster,lane-left

``steps`` (default 4000: about 55 minutes on 2 cores) sets the training length: ``configs/world.py:steps=2000``.

``control=warp`` (issue 58; not yet trained to its goals) adds what a model needs to follow a route
it is told rather than the motion its history shows:

- counterfactual futures (``data.routes``, :mod:`jaxdrive.data.route_mix`): each training scene read
  along the recorded drive (weight 2) or a stop, a slower, a faster drive, a lane change to the
  left or the other branch at the next intersection (weight 1 each): half of the futures leave the
  recorded motion, and the turns (``branch``) are the routes the recorded clips hold fewest of;
  the dataset needs them: ``jaxdrive data synth ... --counterfactuals stop,slower,faster,lane-left,branch``;
- LongDWM's warp as the route's pixels (``controls.warp``, sec. 3.4) from the last given frame
  (``data.warp_frame=1``), the output a correction to it (``controls.reference_frame="warp"``):
  an untrained model already gives the ``warp`` baseline;
- GameNGen's noise on the given frames (``flow.given_noise_max=0.7`` in training, 0.1 at sampling).

Part 2's comparison changes only the controls, on the same futures and noise: ``control=warp_only``
drops the waypoint tokens (the warp and its correction alone), ``control=waypoints_cf`` drops the
warp (the tokens alone, the output the residual to the newest given frame as in the recipe).
"""

import dataclasses
from pathlib import Path

from jaxdrive.config import check_arg, load_config, parse_arg

# the route controls (issue 58, part 2): the waypoint tokens alone, as first trained; then, on the
# counterfactual futures with noise on the given frames, the warp with the tokens, the warp alone,
# the tokens alone
CONTROLS = ("waypoints", "warp", "warp_only", "waypoints_cf")


def get_config(arg: str | None = None):
    a = parse_arg(arg, steps=4000, control="waypoints")
    base = load_config(Path(__file__).with_name("tiny.py"))
    m = base.model
    controls = dataclasses.replace(m.controls, layout=True, boxes=False, map=False, trajectory=False, waypoints=True)
    train = dataclasses.replace(base.train, steps=a.steps, log_every=50, checkpoint_every=500, keep_checkpoints=2)
    optim = dataclasses.replace(base.optim, warmup_steps=100)
    data = dataclasses.replace(base.data, path="data/world")
    flow = dataclasses.replace(base.flow, shift=3.0)
    check_arg("control", a.control, CONTROLS)
    if a.control != "waypoints":  # every route-following variant trains on the same counterfactual futures
        routes = ("recorded:2", "stop", "slower", "faster", "lane-left", "branch")
        data = dataclasses.replace(data, routes=routes)
        flow = dataclasses.replace(flow, given_noise_max=0.7, given_noise_sample=0.1)
    if a.control in ("warp", "warp_only"):
        controls = dataclasses.replace(controls, warp=True, reference_frame="warp", waypoints=a.control == "warp")
        data = dataclasses.replace(data, warp_frame=base.flow.cond_frames - 1)
    return dataclasses.replace(base, model=m.replace(controls=controls), train=train, optim=optim, data=data, flow=flow)
