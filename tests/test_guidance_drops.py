"""Each clip's own guidance drops (``Conditions.drop``'s values) through the samplers: a clip whose
value is True is sampled without that condition in every branch, one whose value is False is
guided against its null, whatever the other clips of the batch hold; a bad value is refused."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

from jaxdrive.generate.guidance import sampler_guidance
from jaxdrive.generate.streaming import stream_frame
from jaxdrive.generate.windows import WindowModel, sample_window
from jaxdrive.models.dit import DiT
from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.models.dit.inputs import example_inputs
from jaxdrive.models.dit.presets import preset

from dit_fixtures import max_rel, params_for

BOXES = preset("tiny", depth=1, controls=dict(boxes=True))
SHAPES = (("batch", 2), ("frames", 3))  # one streaming window: anchor, previous frame, new frame


def test_the_guidance_variants_keep_each_clips_drops():
    rows = {"text": np.array([False, False]), "boxes": np.array([True, False]), "waypoints": np.array([False, True])}
    out = sampler_guidance(Conditions(), rows, 2, 2.0, (("boxes", 3.0), ("route", 0.5)))
    values = lambda c: {n: np.asarray(v).tolist() for n, v in c.drop.items()}
    assert values(out["cond"]) == {n: v.tolist() for n, v in rows.items()}
    assert values(out["null_cond"]) == {n: [True, True] for n in rows}
    assert values(out["control_guidance"]["boxes"][1]) == {**values(out["cond"]), "boxes": [True, True]}
    assert values(out["control_guidance"]["route"][1]) == {**values(out["cond"]), "waypoints": [True, True]}
    alone = sampler_guidance(Conditions(), rows, 2, 1.0)  # no guidance: the clips' drops still apply
    assert set(alone) == {"cond"} and values(alone["cond"]) == values(out["cond"])


@functools.cache
def _setup():
    params = params_for(BOXES, SHAPES, skip=())  # every pathway live, the box cross-attention too
    model = WindowModel(
        DiT(BOXES), params, window=3, cond_frames=1, steps=2, guidance=2.0, control_guidance=(("boxes", 3.0),)
    )
    ex = example_inputs(BOXES, batch=2, frames=3, pixel_frames=False)
    mask = np.zeros((2, 3), bool)
    mask[:, :2] = True
    return model, ex["latents"], mask, ex["cond"]


@functools.cache
def _sampler(name: str):
    model, lat, mask, _ = _setup()
    if name == "window":
        fn = jax.jit(lambda p, c: sample_window(model, p, lat, mask, c, jax.random.key(0)))
    else:
        fn = jax.jit(lambda p, c: stream_frame(model, (), p, lat[:, :, :1], lat[:, :, 1:2], c, jax.random.key(0))[0])
    return lambda c: fn(model.params, c)


def _controls(boxes_drop):
    cond = _setup()[3]
    return cond.replace(drop={"text": np.zeros(2, bool), "boxes": np.asarray(boxes_drop)})


@pytest.mark.parametrize("sampler", [pytest.param("window", marks=pytest.mark.slow(seconds=4)), "stream"])
def test_each_clip_is_sampled_with_its_own_drop(sampler):
    """Clip 0 drops its boxes, clip 1 keeps them: clip 0 is the clip of an all-dropped batch and
    clip 1 that of a batch that drops nothing (guided against the boxes' null). Before the values
    were read, all three batches sampled the same."""
    run = lambda d: np.asarray(_sampler(sampler)(_controls(d)))
    mixed, kept, dropped = run([True, False]), run([False, False]), run([True, True])
    assert max_rel(dropped[0], kept[0]) > 1e-3  # the drop reaches the model
    np.testing.assert_allclose(mixed[0], dropped[0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(mixed[1], kept[1], rtol=0, atol=1e-6)


@pytest.mark.parametrize("sampler", ["window", "stream"])
@pytest.mark.parametrize(
    "value, match",
    [
        (np.ones(3, bool), r"drop\['boxes'\]: expected shape \[2\], got \[3\]"),
        (np.ones((2, 1), bool), r"drop\['boxes'\]: expected shape \[2\], got \[2, 1\]"),
        (np.ones(2, np.float32), r"drop\['boxes'\]: expected dtype bool, got float32"),
        (np.ones(2, np.int32), r"drop\['boxes'\]: expected dtype bool, got int32"),
    ],
)
def test_a_drop_of_the_wrong_shape_or_dtype_is_refused(sampler, value, match):
    """Refused while tracing, before anything compiles (it was dropped unread before)."""
    with pytest.raises(ValueError, match=match):
        _sampler(sampler)(_controls(value))
