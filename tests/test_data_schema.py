import numpy as np
import pytest

from jaxdrive.data import schema


def make_clip(V=2, F=3, H=4, W=6, N=5, Hm=8, Wm=8):
    return {
        "video": np.zeros((V, F, H, W, 3), np.uint8),
        "instance_ids": np.full((V, F, H, W), -1, np.int32),
        "intrinsics": np.tile(np.eye(3, dtype=np.float32), (V, 1, 1)),
        "cam_to_ego": np.tile(np.eye(4, dtype=np.float32), (V, 1, 1)),
        "ego_to_world": np.tile(np.eye(4), (F, 1, 1)),
        "boxes": np.zeros((F, N, 7), np.float32),
        "box_classes": np.zeros((F, N), np.int32),
        "box_ids": np.zeros((F, N), np.int32),
        "box_valid": np.zeros((F, N), bool),
        "bev_map": np.zeros((F, Hm, Wm, 8), np.uint8),
        "waypoints": np.zeros((F, 2), np.float32),
        "fps": 12.0,
        "caption": schema.caption(sensor="CAM_FRONT", location="boston-seaport", season="summer", daytime="day"),
    }


def test_good_clip_binds_sizes():
    sizes = schema.check_clip(make_clip())
    assert sizes == {"V": 2, "F": 3, "H": 4, "W": 6, "N": 5, "Hm": 8, "Wm": 8}
    clip = make_clip()
    del clip["instance_ids"]  # optional
    schema.check_clip(clip)


def test_caption_template():
    assert schema.caption(sensor="CAM_FRONT", location="singapore-onenorth", season="winter", daytime="night") == (
        "This is a driving scene video captured by camera in CAM_FRONT "
        "of a car at singapore-onenorth during winter night."
    )


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda c: c.pop("boxes"), r"scene-1: field 'boxes' is missing \(expected float32 \['F', 'N', 7\]\)"),
        (lambda c: c.update(video=c["video"].astype(np.float32)), "field 'video': expected dtype uint8, got float32"),
        (
            lambda c: c.update(waypoints=np.zeros((4, 2), np.float32)),
            r"field 'waypoints': expected shape \['F', 2\] with F = 3",
        ),
        (lambda c: c.update(bev_map=np.zeros((3, 8, 8, 6), np.uint8)), "field 'bev_map': expected shape"),
        (lambda c: c.update(fps=0.0), "field 'fps': expected a positive float"),
    ],
)
def test_bad_clips_name_the_field(mutate, match):
    clip = make_clip()
    mutate(clip)
    with pytest.raises(ValueError, match=match):
        schema.check_clip(clip, source="scene-1")
