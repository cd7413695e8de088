"""Condition patterns: where the given frames and the JDC anchors of a clip sit (prefix, ends,
anchors), the per-clip draw of the train step, and the config keys that choose them."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive import flow
from jaxdrive.config import Config, FlowConfig, override
from jaxdrive.config_checks import check_sections
from jaxdrive.train import flow_step

T, F_ = True, False


def bools(rows):
    return np.asarray(rows, bool)


# ------------------------------------------------------------------------- pattern_masks
@pytest.mark.parametrize(
    "pattern, frames, n_cond, every, cond, anchors",
    [
        ("prefix", 5, 2, 0, [T, T, F_, F_, F_], [F_, F_, F_, F_, T]),
        ("prefix", 5, 0, 0, [F_, F_, F_, F_, F_], [F_, F_, F_, F_, T]),
        ("prefix", 2, 1, 0, [T, F_], [F_, T]),
        ("ends", 5, 1, 0, [T, F_, F_, F_, T], [F_] * 5),  # LongDWM's interpolation
        ("ends", 5, 0, 0, [F_, F_, F_, F_, T], [F_] * 5),
        ("ends", 5, 3, 0, [T, T, T, F_, T], [F_] * 5),
        # MiLA's (Re)fine window: 4 given + 12 generated, one anchor every 12 frames: the tail
        ("anchors", 16, 4, 12, [T] * 4 + [F_] * 12, [F_] * 15 + [T]),
        ("anchors", 8, 2, 3, [T, T, F_, F_, F_, F_, F_, F_], [F_, F_, F_, F_, T, F_, F_, T]),
        ("anchors", 6, 0, 2, [F_] * 6, [F_, T, F_, T, F_, T]),  # counted from a virtual frame -1
        ("anchors", 4, 1, 1, [T, F_, F_, F_], [F_, T, T, T]),
    ],
)
def test_worked_masks(pattern, frames, n_cond, every, cond, anchors):
    c, a = flow.pattern_masks(pattern, frames, n_cond, anchor_every=every)
    assert c.shape == a.shape == (frames,)
    np.testing.assert_array_equal(c, bools(cond))
    np.testing.assert_array_equal(a, bools(anchors))


def test_batched_n_cond_gives_one_row_per_clip():
    n = jnp.array([0, 2, 3])
    c, a = flow.pattern_masks("anchors", 8, n, anchor_every=3)
    assert c.shape == a.shape == (3, 8)
    for i, k in enumerate([0, 2, 3]):
        ci, ai = flow.pattern_masks("anchors", 8, k, anchor_every=3)
        np.testing.assert_array_equal(c[i], ci)
        np.testing.assert_array_equal(a[i], ai)
    c, a = flow.pattern_masks("ends", 4, jnp.array([0, 2]))
    np.testing.assert_array_equal(c, bools([[F_, F_, F_, T], [T, T, F_, T]]))
    assert not bool(jnp.any(a))
    # jit: a traced n_cond is a contract, the masks are the same
    c_jit = jax.jit(lambda n: flow.pattern_masks("prefix", 4, n)[0])(jnp.array([1, 3]))
    np.testing.assert_array_equal(c_jit, bools([[T, F_, F_, F_], [T, T, T, F_]]))


@pytest.mark.parametrize(
    "call, match",
    [
        (
            lambda: flow.pattern_masks("middle", 4, 1),
            r"pattern: expected one of \['prefix', 'ends', 'anchors'\], got 'middle'",
        ),
        (lambda: flow.pattern_masks("anchors", 4, 1), r"anchor_every: expected an integer >= 1, got 0"),
        (lambda: flow.pattern_masks("anchors", 4, 1, anchor_every=-2), "anchor_every: expected an integer >= 1"),
        (lambda: flow.pattern_masks("prefix", 4, 4), r"n_cond: expected values in \[0, 3\] for pattern 'prefix'"),
        (lambda: flow.pattern_masks("ends", 4, 3), r"n_cond: expected values in \[0, 2\] for pattern 'ends'"),
        (
            lambda: flow.pattern_masks("prefix", 4, jnp.array([1, -1])),
            r"n_cond: expected values in \[0, 3\].*\[1, -1\]",
        ),
        (lambda: flow.pattern_masks("prefix", 4, jnp.array([1.0])), "n_cond: expected an int or an int array"),
        (lambda: flow.pattern_masks("prefix", 4, jnp.ones((2, 2), int)), "n_cond: expected an int or an int array"),
        (lambda: flow.pattern_masks("ends", 1, 0), "frames: expected >= 2 for pattern 'ends'"),
        (lambda: flow.pattern_masks("prefix", 0, 0), "frames: expected an integer >= 1, got 0"),
    ],
)
def test_bad_pattern_inputs(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# ------------------------------------------------------------------------- draw_condition_masks
def old_draw(key, batch, frames, cond_frames, cond_random, rate):
    """The train step's draw before patterns: a prefix of 0..cond_frames frames, the tail an anchor
    in a fraction ``rate`` of clips."""
    k_cond, k_anchor = jax.random.split(key)
    most = min(cond_frames, frames - 1)
    n = jax.random.randint(k_cond, (batch,), 0, most + 1) if cond_random and most > 0 else jnp.full((batch,), most)
    frame = jnp.arange(frames)[None]
    return frame < n[:, None], (frame == frames - 1) & (jax.random.uniform(k_anchor, (batch, 1)) < rate)


def law(cond, anchors):
    """Frequencies of each (number given, tail anchored) outcome."""
    n, a = np.asarray(cond).sum(1), np.asarray(anchors)[:, -1]
    return {(k, t): float(np.mean((n == k) & (a == t))) for k in range(cond.shape[1] + 1) for t in (False, True)}


@pytest.mark.slow(seconds=3)
@pytest.mark.parametrize("cond_frames, cond_random", [(2, True), (9, True), (2, False)])
def test_prefix_only_reproduces_the_old_draw(cond_frames, cond_random):
    n = 4000
    cond, anchors = flow.draw_condition_masks(
        jax.random.key(0), n, 5, cond_frames=cond_frames, cond_frames_random=cond_random, anchor_rate=0.3
    )
    ref = law(*old_draw(jax.random.key(1), n, 5, cond_frames, cond_random, 0.3))
    got = law(cond, anchors)
    for outcome in ref:
        assert got[outcome] == pytest.approx(ref[outcome], abs=0.03), outcome
    assert not bool(jnp.any(anchors[:, :-1]))  # only the tail is ever an anchor
    assert not bool(jnp.any(cond[:, -1]))  # and it is always generated
    if not cond_random:
        np.testing.assert_array_equal(cond.sum(1), cond_frames)


@pytest.mark.slow(seconds=5)
def test_pattern_and_anchor_rates_are_respected():
    n, frames = 4000, 6
    cond, anchors = flow.draw_condition_masks(
        jax.random.key(3),
        n,
        frames,
        patterns=("prefix", "ends", "anchors"),
        pattern_rates=(0.2, 0.5, 0.3),
        cond_frames=2,
        anchor_every=2,
        anchor_rate=0.75,
    )
    cond, anchors = np.asarray(cond), np.asarray(anchors)
    ends = cond[:, -1]
    assert ends.mean() == pytest.approx(0.5, abs=0.03)
    assert not anchors[ends].any()  # interpolation has no anchors
    # prefix and anchors clips: an anchored clip has the tail (prefix) or every 2nd frame from the
    # last given one (anchors); the two agree on the tail only when that count lands there
    rest = ~ends
    anchored = anchors[rest].any(1)
    assert anchored.mean() == pytest.approx(0.75, abs=0.03)
    n_given = cond.sum(1)
    assert set(n_given[rest].tolist()) == {0, 1, 2} and set(n_given[ends].tolist()) == {1, 2, 3}
    spaced = rest & (anchors.sum(1) > 1)  # only the anchors pattern has several
    assert spaced.mean() > 0.1
    for row_c, row_a in zip(cond[spaced], anchors[spaced]):
        k = int(row_c.sum())
        np.testing.assert_array_equal(row_a, np.asarray(flow.pattern_masks("anchors", frames, k, anchor_every=2)[1]))
    # equal rates when none are given
    c2, _ = flow.draw_condition_masks(jax.random.key(4), n, frames, patterns=("prefix", "ends"), cond_frames=1)
    assert float(jnp.mean(c2[:, -1])) == pytest.approx(0.5, abs=0.03)
    # a zero rate never draws its pattern
    c3, _ = flow.draw_condition_masks(
        jax.random.key(5), 512, frames, patterns=("prefix", "ends"), pattern_rates=(1.0, 0.0)
    )
    assert not bool(jnp.any(c3[:, -1]))


def test_draw_levels_puts_the_patterns_anchors_at_g():
    x = jnp.zeros((256, 1, 6, 2, 2, 4))
    cfg = FlowConfig(
        patterns=("anchors",),
        anchor_every=2,
        cond_frames=1,
        cond_frames_random=False,
        jdc_anchor_rate=1.0,
        jdc_slope=0.5,
    )
    sigma, cond, levels, anchor = flow_step.draw_levels(jax.random.key(1), x, cfg, height=16, width=16)
    np.testing.assert_array_equal(cond[0], bools([T, F_, F_, F_, F_, F_]))
    np.testing.assert_array_equal(anchor[0], bools([F_, F_, T, F_, T, F_]))
    want = jnp.where(anchor, 0.5 * sigma[:, None], jnp.where(cond, 0.0, sigma[:, None]))
    np.testing.assert_allclose(levels, want, atol=1e-7)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(patterns=()), "patterns: expected distinct names"),
        (dict(patterns=("prefix", "prefix")), "patterns: expected distinct names"),
        (dict(patterns=("prefix", "tail")), r"patterns: expected one of .*got 'tail'"),
        (dict(patterns=("prefix", "ends"), pattern_rates=(1.0,)), "pattern_rates: expected 2 rates"),
        (
            dict(patterns=("prefix", "ends"), pattern_rates=(0.7, 0.7)),
            "pattern_rates: expected non-negative rates summing to 1",
        ),
        (dict(patterns=("prefix", "ends"), pattern_rates=(1.5, -0.5)), "pattern_rates: expected non-negative"),
        (dict(patterns=("anchors",)), "anchor_every: expected an integer >= 1, got 0"),
        (dict(anchor_rate=1.5), r"anchor_rate: expected a value in \[0, 1\]"),
        (dict(cond_frames=-1), "cond_frames: expected an integer >= 0"),
    ],
)
def test_bad_draw_inputs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        flow.draw_condition_masks(jax.random.key(0), 4, 5, **kwargs)


def test_ends_needs_two_frames():
    with pytest.raises(ValueError, match="frames: expected >= 2 for pattern 'ends'"):
        flow.draw_condition_masks(jax.random.key(0), 4, 1, patterns=("prefix", "ends"))


# ------------------------------------------------------------------------- FlowConfig keys
def with_flow(**kw):
    return dataclasses.replace(Config(), flow=FlowConfig(**kw))


def test_defaults_and_command_line_keys():
    check_sections(Config())  # existing configs keep working
    assert Config().flow.patterns == ("prefix",) and Config().flow.pattern_rates == ()
    c = override(override(Config(), "flow.patterns=prefix,ends"), "flow.pattern_rates=0.25,0.75")
    assert c.flow.patterns == ("prefix", "ends") and c.flow.pattern_rates == (0.25, 0.75)
    check_sections(c)
    c = override(override(c, "flow.patterns=prefix,ends,anchors"), "flow.anchor_every=12")
    check_sections(dataclasses.replace(c, flow=dataclasses.replace(c.flow, pattern_rates=())))


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(patterns=("prefix", "middle")), "flow.patterns: expected one of"),
        (dict(patterns=()), "flow.patterns: expected distinct names"),
        (dict(patterns=("prefix", "ends"), pattern_rates=(0.5,)), "flow.pattern_rates: expected 2 rates"),
        (
            dict(patterns=("prefix", "ends"), pattern_rates=(0.5, 0.6)),
            "flow.pattern_rates: expected non-negative rates summing to 1",
        ),
        (dict(patterns=("prefix", "anchors")), "flow.anchor_every: expected an integer >= 1, got 0"),
        (dict(anchor_every=-1), "flow.anchor_every: expected an integer >= 0"),
        (dict(jdc_alpha1=1.0), r"flow.jdc_alpha1: expected values in \[0.0, 1.0\)"),
    ],
)
def test_bad_flow_config(kw, match):
    with pytest.raises(ValueError, match=match):
        check_sections(with_flow(**kw))
