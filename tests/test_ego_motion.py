"""The ego's motion read from a clip's pixels (jaxdrive.eval.ego_motion), scored on renders of the
synthetic world whose poses are known."""

import numpy as np
import pytest

from jaxdrive.data.synthetic import generate_clip
from jaxdrive.eval.ego_motion import (
    estimate_ego_motion,
    manoeuvre,
    motion_from_poses,
    path,
    route_following,
)

KW = dict(views=6, frames=33, height=32, width=56)  # the world recipe's generated size
START = 8


@pytest.fixture(scope="module")
def turns():
    """Seed 10 turns right (-1.5 rad over the clip), seed 22 left (+1.1 rad)."""
    return {side: generate_clip(seed, **KW) for side, seed in [("right", 10), ("left", 22)]}


def test_a_render_gives_back_its_known_motion_and_tells_left_from_right(turns):
    for side, clip in turns.items():
        est = estimate_ego_motion(clip["video"], clip["intrinsics"], clip["cam_to_ego"])
        true = motion_from_poses(clip["ego_to_world"])
        assert est.shape == true.shape == (32, 3)
        err = np.abs(est - true).mean(0)
        # the bounds the estimator meets on these renders (0.03-0.05 m, 0.02-0.03 m, 0.004 rad a frame)
        assert err[0] < 0.1 and err[1] < 0.05 and err[2] < 0.01, (side, err)
        score = route_following(est, true, START, clip["fps"])
        assert score["commanded"] == score["manoeuvre"] == f"turn-{side}", (side, score)
        assert score["ade"] < 1.5, (side, score)


def test_manoeuvres_of_known_paths():
    fps = 10.0
    steady = np.tile([1.0, 0.0, 0.0], (20, 1))  # 10 m/s straight on
    assert manoeuvre(steady, 5, fps) == "keep"
    brake = steady.copy()
    brake[5:12, 0], brake[12:, 0] = np.linspace(1.0, 0.0, 7), 0.0
    assert manoeuvre(brake, 5, fps) == "stop"
    assert manoeuvre(steady * [[0.6, 1, 1]], 5, fps) == "keep"  # slow throughout is no change
    slow = steady.copy()
    slow[5:, 0] = 0.6
    fast = steady.copy()
    fast[5:, 0] = 1.5
    assert manoeuvre(slow, 5, fps) == "slower" and manoeuvre(fast, 5, fps) == "faster"
    left = steady.copy()
    left[5:, 2] = 0.1  # 1.5 rad to the left
    assert manoeuvre(left, 5, fps) == "turn-left" and manoeuvre(left * [[1, 1, -1]], 5, fps) == "turn-right"
    change = steady.copy()
    change[5:15, 1] = 0.35  # 3.5 m to the left, heading kept
    assert manoeuvre(change, 5, fps) == "lane-left" and manoeuvre(change * [[1, -1, 1]], 5, fps) == "lane-right"
    xy, yaw = path(left)
    assert xy.shape == (21, 2) and np.isclose(yaw[-1], 1.5) and xy[-1, 1] > 0


def test_route_following_scores_the_path_distance():
    fps = 10.0
    cmd = np.tile([1.0, 0.0, 0.0], (20, 1))
    est = cmd.copy()
    est[:, 1] = 0.1  # drifting 0.1 m a frame to the left
    score = route_following(est, cmd, 5, fps)
    assert np.isclose(score["fde"], 2.0) and np.isclose(score["ade"], np.mean(np.arange(5, 21) * 0.1))
    assert score["recognised"] is False and score["manoeuvre"] == "lane-left" and score["commanded"] == "keep"


def test_bad_inputs_name_the_argument():
    clip = np.zeros((2, 5, 8, 8, 3), np.uint8)
    k, e = np.tile(np.eye(3), (2, 1, 1)), np.tile(np.eye(4), (2, 1, 1))
    with pytest.raises(ValueError, match=r"video: expected shape \[V, F, H, W, 3\]"):
        estimate_ego_motion(clip[..., 0], k, e)
    with pytest.raises(ValueError, match="video: expected at least 2 frames"):
        estimate_ego_motion(clip[:, :1], k, e)
    with pytest.raises(ValueError, match=r"intrinsics: expected shape \[2, 3, 3\]"):
        estimate_ego_motion(clip, k[:1], e)
    with pytest.raises(ValueError, match="cam_to_ego: expected cameras that see the ground"):
        estimate_ego_motion(clip, k, e)  # cameras at the ego's origin looking along ego z: no ground
    with pytest.raises(ValueError, match=r"start: expected a frame in \[1, 19\]"):
        manoeuvre(np.zeros((20, 3)), 20, 10.0)
    with pytest.raises(ValueError, match="estimated: expected the commanded motions' shape"):
        route_following(np.zeros((19, 3)), np.zeros((20, 3)), 5, 10.0)
