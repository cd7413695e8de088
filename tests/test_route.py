"""User-given routes (``--route``): files, named manoeuvres, and the poses they drive."""

import json

import numpy as np
import pytest

from jaxdrive.generate.route import BRAKING, TURN_RADIUS, load_route


def test_a_json_route_with_times_gives_poses_through_its_points(tmp_path):
    path = tmp_path / "r.json"
    path.write_text(json.dumps({"points": [[0, 0], [5, 0], [10, 1]], "times": [0, 0.5, 1.0]}))
    route = load_route(str(path), duration=2.0)
    poses = route.poses(frames=13, fps=12.0)                     # the last point at frame 12
    np.testing.assert_allclose(poses[[0, 6, 12], :2, 3], [[0, 0], [5, 0], [10, 1]], atol=1e-4)
    # objects and bare rows read the same
    path.write_text(json.dumps([{"x": 0, "y": 0, "t": 0}, {"x": 5, "y": 0, "t": 0.5}, {"x": 10, "y": 1, "t": 1}]))
    np.testing.assert_allclose(load_route(str(path), duration=2.0).poses(13, 12.0), poses, atol=1e-6)
    path.write_text(json.dumps([[0, 0], [5, 0], [10, 1]]))          # no times: spread over the clip
    np.testing.assert_allclose(load_route(str(path), duration=2.0).poses(13, 12.0)[[0, 6, 12], :2, 3],
                               [[0, 0], [5, 0], [10, 1]], atol=1e-4)


def test_a_csv_route(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("x,y,t\n0,0,0\n4,0,0.5\n8,0.5,1\n")
    route = load_route(str(path), duration=1.0)
    np.testing.assert_allclose(route.points, [[0, 0], [4, 0], [8, 0.5]])
    np.testing.assert_allclose(route.times, [0, 0.5, 1])


def test_named_manoeuvres():
    straight = load_route("straight 5 m/s", duration=2.0).poses(frames=25, fps=12.0)
    np.testing.assert_allclose(straight[:, 0, 3], np.arange(25) * 5 / 12, atol=1e-4)
    np.testing.assert_allclose(straight[:, 1, 3], 0, atol=1e-6)
    # a left turn: a quarter circle of the turn radius, heading +90 degrees at its end, then on along +y
    left = load_route("left turn", duration=6.0)
    end_of_arc = np.argmin(np.abs(left.times - np.pi / 2 * TURN_RADIUS / 8.0))
    np.testing.assert_allclose(left.points[end_of_arc], [TURN_RADIUS, TURN_RADIUS], atol=0.5)
    poses = left.poses(frames=73, fps=12.0)
    yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    assert abs(yaw[0]) < 1e-6 and abs(yaw[-1] - np.pi / 2) < 0.01 and poses[-1, 1, 3] > TURN_RADIUS
    right = load_route("Right turn 8 m/s", duration=6.0)
    np.testing.assert_allclose(right.points * [1, -1], left.points, atol=1e-5)
    # a stop: braking distance v^2 / 2a, then standing with the heading kept
    stop = load_route("stop", duration=6.0).poses(frames=73, fps=12.0)
    np.testing.assert_allclose(stop[-1, 0, 3], 10.0 ** 2 / (2 * BRAKING), atol=1e-3)
    np.testing.assert_allclose(stop[-20:, :2, 3], np.broadcast_to(stop[-1, :2, 3], (20, 2)), atol=1e-3)
    np.testing.assert_allclose(stop[-1, :3, :3], np.eye(3), atol=1e-6)


@pytest.mark.parametrize("name, text, match", [
    ("one.json", json.dumps([[0, 0]]), "expected at least 2 points, got 1"),
    ("nan.json", json.dumps([[0, 0], [1, float("nan")]]).replace("NaN", "NaN"), "row 2: expected finite values"),
    ("cols.json", json.dumps([[0, 0], [1, 2, 3, 4]]), "row 2: expected 2 values"),
    ("four.json", json.dumps([[0, 0, 0, 0], [1, 2, 3, 4]]), "row 1: expected 2 or 3 values"),
    ("keys.json", json.dumps([{"x": 0, "y": 0}, {"x": 1, "z": 0}]), "row 2: expected keys x, y"),
    ("start.json", json.dumps([[3, 0], [5, 0]]), r"row 1: expected the ego's start"),
    ("times.json", json.dumps({"points": [[0, 0], [1, 0], [2, 0]], "times": [0, 1, 1]}),
     "row 3: expected times increasing"),
    ("cols.csv", "x,z\n0,0\n1,1\n", "row 1: expected the header 'x,y' or 'x,y,t'"),
    ("inf.csv", "x,y\n0,0\n1,inf\n", "row 3: expected finite values"),
    ("text.csv", "x,y\n0,0\n1,abc\n", "row 3: expected numbers"),
    ("bad.json", "{not json", "expected JSON or a .csv file"),
])
def test_bad_route_files_are_named_with_their_row(tmp_path, name, text, match):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as e:
        load_route(str(path), duration=1.0)
    assert str(path) in str(e.value)


def test_an_unknown_route_names_the_choices():
    with pytest.raises(ValueError, match=r"route: expected a JSON or CSV file or a manoeuvre \(straight, left turn"):
        load_route("u-turn", duration=1.0)
