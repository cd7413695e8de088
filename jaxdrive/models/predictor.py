"""The future-controls predictor: what plays MILE's role in STAGE (sec. D), closed-loop future
conditions for generating past the end of a clip's recorded controls.

A small transformer reads the past ``history`` steps of the ego pose and of every agent's box
(with its class and track) and the BEV map around the ego, and predicts the next step's ego pose
and agent poses; rolled forward (:func:`rollout`, a ``lax.scan`` under jit) with the map re-cut
at each predicted pose (:func:`jaxdrive.data.scene_map.cut`), it gives the controls of any number
of frames. Sizes, classes and track ids are carried unchanged.

Tokens, all in the current ego frame (so the network never sees world coordinates): one for the
ego (its past poses), one per agent slot (its past poses where seen, size, class, which past steps
saw it) and one per ``map_patch`` x ``map_patch`` cells of the BEV map; self-attention over them
with absent agents masked. Each output is a correction, in metres and radians, to the
constant-velocity step (the velocity of the last step held, the heading kept): freshly initialised
(zero heads) the predictor is the constant-velocity baseline it is measured against, and training
only has to learn where that baseline goes wrong (stopping, following, turning, lanes).
"""

from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp

from jaxdrive.classes import BEV_CLASSES, OBJECT_CLASSES
from jaxdrive.geometry import wrap

POSITION_SCALE = 10.0  # metres of one unit of a position feature
STEP_SCALE = 0.5  # metres of one unit of a predicted position correction
YAW_SCALE = 0.1  # radians of one unit of a predicted heading correction


@dataclasses.dataclass(frozen=True)
class PredictorConfig:
    """The future-controls predictor (:class:`Predictor`): a transformer over the past ``history``
    steps of the ego pose and the agents' boxes and the BEV map around the ego, one step every
    ``stride`` source frames of the dataset; trained by rolling it ``horizon`` steps forward
    (:class:`jaxdrive.config.PredictorRunConfig`, which re-exports this class)."""

    history: int = 8
    horizon: int = 8
    stride: int = 2
    width: int = 64
    depth: int = 2
    heads: int = 4
    map_patch: int = 8  # BEV cells per side of one map token
    max_agents: int = 20  # agent slots (a clip's box slots, padded or cut)


@flax.struct.dataclass
class Traffic:
    """The last ``T`` steps of traffic, world frame: ``ego [B, T, 3]`` and ``agents [B, T, N, 3]``
    poses (x, y, yaw), ``seen [B, T, N]``; per agent ``size [B, N, 3]``, ``z [B, N]`` (box centre
    height), ``classes [B, N]``, ``ids [B, N]``; an agent is present when seen at the last step."""

    ego: jax.Array
    agents: jax.Array
    seen: jax.Array
    size: jax.Array
    z: jax.Array
    classes: jax.Array
    ids: jax.Array

    def advance(self, ego_next, agents_next) -> Traffic:
        """The history one step on: ``ego_next [B, 3]``, ``agents_next [B, N, 3]`` appended."""
        # flax.struct.dataclass adds .replace at runtime; its stub does not declare it
        return self.replace(  # type: ignore[attr-defined]
            ego=jnp.concatenate([self.ego[:, 1:], ego_next[:, None]], 1),
            agents=jnp.concatenate([self.agents[:, 1:], agents_next[:, None]], 1),
            seen=jnp.concatenate([self.seen[:, 1:], self.seen[:, -1:]], 1),
        )


def to_traffic(w: dict, history: int) -> Traffic:
    """The history part of stacked NumPy windows (leading batch axis;
    :func:`jaxdrive.data.traffic.window_traffic`) as a device :class:`Traffic`."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    return Traffic(
        ego=f32(w["ego"][:, :history]),
        agents=f32(w["agents"][:, :history]),
        seen=jnp.asarray(w["seen"][:, :history]),
        size=f32(w["size"]),
        z=f32(w["z"]),
        classes=jnp.asarray(w["classes"], jnp.int32),
        ids=jnp.asarray(w["ids"], jnp.int32),
    )


def to_frame(poses, frame):
    """World poses ``[..., 3]`` -> in the frame of ``frame [..., 3]`` (broadcast)."""
    c, s = jnp.cos(frame[..., 2]), jnp.sin(frame[..., 2])
    dx, dy = poses[..., 0] - frame[..., 0], poses[..., 1] - frame[..., 1]
    return jnp.stack([c * dx + s * dy, -s * dx + c * dy, wrap(poses[..., 2] - frame[..., 2])], -1)


def _features(rel, axis: int):
    """Relative poses ``[..., T, ..., 3]`` (time along ``axis``) -> ``(x, y) / POSITION_SCALE``, cos
    and sin of the heading, and each step's motion, ``(dx, dy) / STEP_SCALE`` and ``dyaw /
    YAW_SCALE`` (zero at the first step): positions are metres apart, steps centimetres, and the
    network reads speed and acceleration from the latter."""
    step = jnp.diff(rel, axis=axis, prepend=jnp.take(rel, jnp.array([0]), axis=axis))
    step = jnp.concatenate([step[..., :2] / STEP_SCALE, wrap(step[..., 2:]) / YAW_SCALE], -1)
    return jnp.concatenate([rel[..., :2] / POSITION_SCALE, jnp.cos(rel[..., 2:]), jnp.sin(rel[..., 2:]), step], -1)


class _Block(nn.Module):
    width: int
    heads: int

    @nn.compact
    def __call__(self, x, mask):
        h = nn.LayerNorm()(x)
        x = x + nn.MultiHeadDotProductAttention(num_heads=self.heads, qkv_features=self.width)(h, h, mask=mask)
        h = nn.LayerNorm()(x)
        return x + nn.Dense(self.width)(nn.gelu(nn.Dense(4 * self.width)(h)))


class Predictor(nn.Module):
    """Corrections ``(ego [B, 3], agents [B, N, 3])`` to the constant-velocity step (module
    docstring) from ``traffic`` and ``bev [B, Hm, Wm, 8]`` in [0, 1] around the current ego."""

    config: PredictorConfig

    @nn.compact
    def __call__(self, traffic: Traffic, bev):
        cfg = self.config
        b, t, n = traffic.seen.shape
        now = traffic.ego[:, -1]
        ego = _features(to_frame(traffic.ego, now[:, None]), 1).reshape(b, -1)
        agents = _features(to_frame(traffic.agents, now[:, None, None]), 1)  # [B, T, N, 7]
        seen = traffic.seen.astype(jnp.float32)
        both = seen * jnp.concatenate([seen[:, :1], seen[:, :-1]], 1)  # a step needs both ends
        agents = jnp.concatenate([agents[..., :4] * seen[..., None], agents[..., 4:] * both[..., None]], -1)
        agents = agents.transpose(0, 2, 1, 3).reshape(b, n, -1)
        agents = jnp.concatenate(
            [agents, seen.transpose(0, 2, 1), traffic.size / 5.0, jax.nn.one_hot(traffic.classes, len(OBJECT_CLASSES))],
            -1,
        )
        embed = lambda x, name: nn.Dense(cfg.width, name=f"{name}_out")(
            nn.gelu(nn.Dense(cfg.width, name=f"{name}_in")(x))
        )
        p = cfg.map_patch
        hm, wm = bev.shape[1] // p, bev.shape[2] // p
        cells = bev[:, : hm * p, : wm * p].reshape(b, hm, p, wm, p, len(BEV_CLASSES))
        cells = cells.transpose(0, 1, 3, 2, 4, 5).reshape(b, hm * wm, -1)
        map_tokens = nn.Dense(cfg.width, name="map_in")(cells)
        map_tokens = map_tokens + self.param("map_position", nn.initializers.normal(0.02), (hm * wm, cfg.width))
        kinds = self.param("kind", nn.initializers.normal(0.02), (3, cfg.width))
        x = jnp.concatenate(
            [embed(ego, "ego")[:, None] + kinds[0], embed(agents, "agent") + kinds[1], map_tokens + kinds[2]], 1
        )
        present = traffic.seen[:, -1]
        keys = jnp.concatenate([jnp.ones((b, 1), bool), present, jnp.ones((b, hm * wm), bool)], 1)
        mask = jnp.broadcast_to(keys[:, None, None, :], (b, 1, x.shape[1], x.shape[1]))
        for i in range(cfg.depth):
            x = _Block(cfg.width, cfg.heads, name=f"block_{i}")(x, mask)
        x = nn.LayerNorm()(x)
        head = nn.Dense(3, kernel_init=nn.initializers.zeros, name="head")
        return head(x[:, 0]), head(x[:, 1 : 1 + n]) * present[..., None]


def constant_velocity(traffic: Traffic):
    """The constant-velocity step: each pose moved by its last step's displacement, heading kept
    (an agent not seen at both of the last two steps stands). ``(ego [B, 3], agents [B, N, 3])``."""
    e, a = traffic.ego, traffic.agents
    ego = e[:, -1].at[:, :2].add(e[:, -1, :2] - e[:, -2, :2])
    moving = (traffic.seen[:, -1] & traffic.seen[:, -2])[..., None]
    agents = a[:, -1].at[..., :2].add(jnp.where(moving, a[:, -1, :, :2] - a[:, -2, :, :2], 0.0))
    return ego, agents


def predict_step(model: Predictor, params, traffic: Traffic, bev):
    """The next step's world poses ``(ego [B, 3], agents [B, N, 3])``: the constant-velocity step
    plus the model's corrections, which are in the current ego frame."""
    d_ego, d_agents = model.apply({"params": params}, traffic, bev)
    cv_ego, cv_agents = constant_velocity(traffic)
    now = traffic.ego[:, -1]
    c, s = jnp.cos(now[:, 2]), jnp.sin(now[:, 2])

    def moved(pose, d):  # d in the ego frame, broadcast over agents
        cc, ss = (c, s) if d.ndim == 2 else (c[:, None], s[:, None])
        dx, dy = STEP_SCALE * d[..., 0], STEP_SCALE * d[..., 1]
        return jnp.stack(
            [
                pose[..., 0] + cc * dx - ss * dy,
                pose[..., 1] + ss * dx + cc * dy,
                wrap(pose[..., 2] + YAW_SCALE * d[..., 2]),
            ],
            -1,
        )

    agents = jnp.where(traffic.seen[:, -1, :, None], moved(cv_agents, d_agents), traffic.agents[:, -1])
    return moved(cv_ego, d_ego), agents


def rollout(model: Predictor, params, traffic: Traffic, steps: int, *, bev=None, scene=None, ego_path=None):
    """Roll ``steps`` steps forward -> ``(ego [B, S, 3], agents [B, S, N, 3], traffic)`` (the
    final history). The map of each step: ``bev [B, S, Hm, Wm, 8]`` given per step (training), or
    ``bev [B, Hm, Wm, 8]`` (the newest seen) re-cut from ``scene`` (a
    :class:`jaxdrive.data.scene_map.SceneMap`, one clip: B = 1; its ``cut(pose, fallback)``) at
    each pose, or held as it is. ``ego_path [B, S, 3]``: the ego drives it (a user's route) and
    only the agents are predicted."""

    def step(state, k):
        traffic = state
        if bev is None or bev.ndim == 4:
            now = bev
            if scene is not None:
                now = jax.vmap(scene.cut)(traffic.ego[:, -1], bev)
        else:
            now = bev[:, k]
        ego, agents = predict_step(model, params, traffic, now)
        if ego_path is not None:
            ego = ego_path[:, k]
        return traffic.advance(ego, agents), (ego, agents)

    traffic, (ego, agents) = jax.lax.scan(step, traffic, jnp.arange(steps))
    return ego.swapaxes(0, 1), agents.swapaxes(0, 1), traffic


def constant_velocity_rollout(traffic: Traffic, steps: int):
    """The constant-velocity baseline rolled ``steps`` steps -> ``(ego [B, S, 3], agents [B, S, N, 3])``."""

    def step(tr, _):
        ego, agents = constant_velocity(tr)
        return tr.advance(ego, agents), (ego, agents)

    _, (ego, agents) = jax.lax.scan(step, traffic, None, length=steps)
    return ego.swapaxes(0, 1), agents.swapaxes(0, 1)


@functools.lru_cache(maxsize=8)
def rollout_program(config: PredictorConfig):
    """:func:`rollout` jitted for ``config`` (``steps`` static), compiled once per config and
    shapes: ``program(params, traffic, steps, bev, scene, ego_path) -> (ego, agents)``."""
    model = Predictor(config)

    @functools.partial(jax.jit, static_argnums=(2,))
    def run(params, traffic, steps, bev, scene, ego_path):
        return rollout(model, params, traffic, steps, bev=bev, scene=scene, ego_path=ego_path)[:2]

    return run


def init_params(config: PredictorConfig, key, *, bev_size=(64, 64)):
    """Fresh parameters for ``bev_size`` maps (the dataset's BEV grid), initialised in one jitted
    program (run eagerly, each layer's initialiser and forward op would compile on its own),
    compiled once per config and size."""
    return _init_params(config, key, tuple(bev_size))


@functools.partial(jax.jit, static_argnums=(0, 2))
def _init_params(config: PredictorConfig, key, bev_size: tuple[int, ...]):
    t, n = config.history, config.max_agents
    traffic = Traffic(
        ego=jnp.zeros((1, t, 3)),
        agents=jnp.zeros((1, t, n, 3)),
        seen=jnp.ones((1, t, n), bool),
        size=jnp.ones((1, n, 3)),
        z=jnp.zeros((1, n)),
        classes=jnp.zeros((1, n), jnp.int32),
        ids=jnp.zeros((1, n), jnp.int32),
    )
    return Predictor(config).init(key, traffic, jnp.zeros((1, *bev_size, len(BEV_CLASSES))))["params"]
