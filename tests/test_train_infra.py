"""Training infrastructure: config overrides, the optimizer's schedule and masks, non-finite step
skipping, and checkpoints (fallback past a damaged one, restore onto another mesh)."""

import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive.config import DataConfig, OptimConfig, load_config, override
from jaxdrive.parallel import make_mesh
from jaxdrive.train.checkpoint import Checkpoints
from jaxdrive.train.optim import global_norm, learning_rate, make_optimizer, square_sums, trainable_labels
from jaxdrive.train.state import apply_gradients, apply_gradients_and_norm, create_state


@dataclasses.dataclass(frozen=True)
class _Cfg:
    data: DataConfig = DataConfig()
    optim: OptimConfig = OptimConfig()
    name: str | None = None


def test_override_parses_by_type_and_names_bad_keys():
    c = _Cfg()
    c = override(c, "data.frames=17")
    c = override(c, "optim.lr=3e-4")
    c = override(c, "optim.trainable=blocks_27/.*,final.*")
    c = override(c, "name=none")
    assert (c.data.frames, c.optim.lr, c.optim.trainable, c.name) == (17, 3e-4, ("blocks_27/.*", "final.*"), None)
    assert _Cfg().data.frames == 9  # frozen: the original is untouched
    with pytest.raises(ValueError, match=r"unknown key 'frame' in data; expected one of \[.*'frames'"):
        override(c, "data.frame=3")
    with pytest.raises(ValueError, match=r"data.frames: expected int, got '2.5'"):
        override(c, "data.frames=2.5")
    with pytest.raises(ValueError, match=r"^override: expected key=value"):
        override(c, "data.frames")
    with pytest.raises(ValueError, match=r"data.frames.x: .*not a section|data.frames is not a section"):
        override(c, "data.frames.x=1")


def test_load_config_runs_the_file(tmp_path):
    path = tmp_path / "c.py"
    path.write_text("from jaxdrive.config import DataConfig\ndef get_config():\n    return DataConfig(frames=5)\n")
    assert load_config(path, ["height=64"]) == DataConfig(frames=5, height=64)
    with pytest.raises(ValueError, match="config: expected a python config file"):
        load_config(tmp_path / "missing.py")


def test_learning_rate_schedule_worked_numbers():
    sched = learning_rate(OptimConfig(lr=1.0, warmup_steps=10, schedule="cosine", min_lr_ratio=0.1), 110)
    assert float(sched(0)) == 0.0 and float(sched(5)) == pytest.approx(0.5)
    assert float(sched(10)) == pytest.approx(1.0)
    assert float(sched(60)) == pytest.approx(0.1 + 0.9 * 0.5, rel=1e-5)  # half way down the cosine
    assert float(sched(110)) == pytest.approx(0.1, rel=1e-5)
    lin = learning_rate(OptimConfig(lr=2.0, warmup_steps=0, schedule="linear", min_lr_ratio=0.0), 4)
    assert [float(lin(i)) for i in range(5)] == pytest.approx([2.0, 1.5, 1.0, 0.5, 0.0])


def test_partial_training_updates_only_the_matched_parameters():
    params = {
        "blocks_0": {"kernel": jnp.ones((2, 2))},
        "blocks_1": {"kernel": jnp.ones((2, 2))},
        "final": {"bias": jnp.ones(2)},
    }
    labels = trainable_labels(params, ("blocks_1/.*", "^final"))
    assert labels == {"blocks_0": {"kernel": "freeze"}, "blocks_1": {"kernel": "train"}, "final": {"bias": "train"}}
    cfg = OptimConfig(lr=0.1, warmup_steps=0, schedule="constant", trainable=("blocks_1/.*", "^final"))
    opt = make_optimizer(cfg, 10, params)
    state = create_state(params, opt, 0)
    grads = jax.tree_util.tree_map(jnp.ones_like, params)
    state = apply_gradients(state, grads, jnp.float32(1.0), opt, 0.0, state.rng)
    assert float(state.params["blocks_0"]["kernel"][0, 0]) == 1.0
    assert float(state.params["blocks_1"]["kernel"][0, 0]) < 1.0 and float(state.params["final"]["bias"][0]) < 1.0
    with pytest.raises(ValueError, match=r"optim.trainable: expected patterns that match .*'htft'"):
        trainable_labels(params, ("htft",))


def test_last_in_a_pattern_names_the_highest_layer_the_parameters_have():
    """``{last}`` resolves against the parameters, not the config: a depth set after the config was
    built (``--set model.depth=1``) moves it. Scanned stacks (``layers_0_40``) are not layers."""
    leaf = {"kernel": jnp.ones((2, 2))}
    two = {"layers_0": leaf, "layers_1": leaf, "final": leaf}
    assert trainable_labels(two, ("layers_{last}/",)) == {
        "layers_0": {"kernel": "freeze"},
        "layers_1": {"kernel": "train"},
        "final": {"kernel": "freeze"},
    }
    one = {"layers_0": leaf, "final": leaf}
    assert trainable_labels(one, ("layers_{last}/",))["layers_0"] == {"kernel": "train"}
    scanned = {"layers_0_40": leaf, "layers_41": leaf, "layers_10x": leaf}
    labels = trainable_labels(scanned, ("layers_{last}/",))
    assert labels["layers_41"] == {"kernel": "train"} and labels["layers_0_40"] == {"kernel": "freeze"}
    message = r"optim.trainable: '\{last\}' names the last DiT layer .*got 'layers_\{last\}/'"
    with pytest.raises(ValueError, match=message):
        trainable_labels({"layers_0_1": leaf}, ("layers_{last}/",))


def test_non_finite_steps_are_skipped_and_counted():
    params = {"w": jnp.ones((2, 2))}
    opt = make_optimizer(OptimConfig(lr=0.1, warmup_steps=0, schedule="constant"), 10, params)
    state = create_state(params, opt, 0)
    good = {"w": jnp.ones((2, 2))}
    bad = {"w": jnp.full((2, 2), jnp.nan)}
    s1 = apply_gradients(state, bad, jnp.float32(1.0), opt, 0.9, state.rng)
    s2 = apply_gradients(s1, good, jnp.float32(jnp.inf), opt, 0.9, state.rng)
    assert (int(s2.step), int(s2.bad_steps), int(s2.skipped)) == (2, 2, 2)
    for a, b in zip(
        jax.tree_util.tree_leaves((s2.params, s2.opt_state, s2.ema)),
        jax.tree_util.tree_leaves((state.params, state.opt_state, state.ema)),
    ):
        np.testing.assert_array_equal(a, b)
    s3 = apply_gradients(s2, good, jnp.float32(1.0), opt, 0.9, state.rng)
    assert (int(s3.bad_steps), int(s3.skipped)) == (0, 2)
    assert float(s3.params["w"][0, 0]) < 1.0
    # EMA moves by (1 - decay) towards the new parameters
    np.testing.assert_allclose(s3.ema["w"], 0.9 * 1.0 + 0.1 * s3.params["w"], rtol=1e-6)


def _grad_tree(seed=0, scale=1.0):
    rng = np.random.default_rng(seed)
    shapes = {"blocks_0": {"kernel": (3, 5), "bias": (5,)}, "blocks_1": {"kernel": (5, 5)}, "final": {"bias": (7,)}}
    return jax.tree_util.tree_map(
        lambda s: jnp.asarray(rng.normal(size=s) * scale, jnp.float32), shapes, is_leaf=lambda s: isinstance(s, tuple)
    )


@pytest.mark.parametrize("trainable", [(), ("blocks_1/.*", "^final")])
def test_one_gradient_norm_serves_the_check_the_clipping_and_the_metric(trainable):
    """square_sums / global_norm give optax.tree.norm bit for bit, and the optimizer clipping with
    the sums it is handed (masked to the trained parameters inside the partition) updates bit for
    bit as optax's own clip_by_global_norm, which computes them again."""
    params, grads = _grad_tree(0), _grad_tree(1, scale=3.0)
    sums = square_sums(grads)
    assert np.asarray(global_norm(sums)).tobytes() == np.asarray(optax.tree.norm(grads)).tobytes()
    cfg = OptimConfig(lr=0.1, warmup_steps=0, schedule="constant", clip_norm=0.5, trainable=trainable)
    opt = make_optimizer(cfg, 10, params)
    inner = optax.chain(
        optax.clip_by_global_norm(0.5),
        optax.adamw(
            0.1,
            weight_decay=cfg.weight_decay,
            b1=cfg.b1,
            b2=cfg.b2,
            eps=cfg.eps,
            mask=jax.tree_util.tree_map(lambda p: p.ndim >= 2, params),
        ),
    )
    reference = (
        optax.multi_transform({"train": inner, "freeze": optax.set_to_zero()}, trainable_labels(params, trainable))
        if trainable
        else inner
    )
    want, _ = jax.jit(reference.update)(grads, reference.init(params), params)
    got, _ = jax.jit(lambda g, s, p, q: opt.update(g, s, p, square_sums=q))(grads, opt.init(params), params, sums)
    again, _ = jax.jit(opt.update)(grads, opt.init(params), params)  # no sums given: computed inside
    for w, g, a in zip(*(jax.tree_util.tree_leaves(t) for t in (want, got, again)), strict=True):
        np.testing.assert_array_equal(g, w)
        np.testing.assert_array_equal(a, w)
    # the trained parameters' norm clips them, not the frozen ones' too
    if trainable:
        trained = {"blocks_1": grads["blocks_1"], "final": grads["final"]}
        assert float(optax.tree.norm(trained)) < float(global_norm(sums))


def test_a_step_reduces_each_gradient_once():
    """The finiteness check, the clipping and grad_norm share one sum of squares per gradient (a
    small model's train step had three reductions per parameter array, a quarter of its program)."""
    params = _grad_tree(0)
    opt = make_optimizer(OptimConfig(lr=0.1, warmup_steps=0, schedule="constant", clip_norm=1.0), 10, params)
    state = create_state(params, opt, 0)
    text = jax.jit(lambda s, g: apply_gradients(s, g, jnp.float32(1.0), opt, 0.9, s.rng)).lower(state, params).as_text()
    assert text.count("stablehlo.reduce") == len(jax.tree_util.tree_leaves(params))


def test_the_update_under_explicit_axes_is_not_annotated_op_by_op_and_gives_the_same_numbers():
    """Under an Explicit mesh JAX gives every operation a sharding annotation, and the norm, the
    finiteness check and the update are ~30 reductions and elementwise operations per parameter
    array (a third of a small model's train step, compiled): :func:`apply_gradients_and_norm` runs
    them with the mesh's axes Auto. The state keeps its shardings, and the state and the norm are
    the ones without a mesh, bit for bit (the clipping runs: the norm is past 1)."""
    rng = np.random.default_rng(2)
    params = {**_grad_tree(0), "w": jnp.asarray(rng.normal(size=(3, 8)), jnp.float32)}
    grads = {**_grad_tree(1, scale=3.0), "w": jnp.asarray(rng.normal(size=(3, 8)), jnp.float32)}
    opt = make_optimizer(OptimConfig(lr=0.1, warmup_steps=0, schedule="constant", clip_norm=1.0), 10, params)
    step = jax.jit(lambda s, g: apply_gradients_and_norm(s, g, jnp.float32(1.0), opt, 0.9, s.rng))
    want, want_norm = step(create_state(params, opt, 0), grads)
    assert float(want_norm) > 1.0
    mesh = make_mesh(data=2, fsdp=4)
    spec = lambda x: P(None, "fsdp") if x.shape[-1:] == (8,) else P()  # "w" over fsdp, the rest replicated
    with jax.set_mesh(mesh):
        place = lambda t: jax.tree_util.tree_map(lambda x: jax.device_put(x, NamedSharding(mesh, spec(x))), t)
        state = create_state(place(params), opt, 0)
        text = step.lower(state, place(grads)).as_text()
        got, norm = step(state, place(grads))
    # op by op: 245 annotations for these 26 state arrays; 26 now, each array's reshard back to its
    # sharding (the norm, the check and the conditional's results are not annotated either)
    leaves = len(jax.tree_util.tree_leaves(state))
    assert text.count("sdy.sharding_constraint") <= leaves + 2, (text.count("sdy.sharding_constraint"), leaves)
    assert got.params["w"].sharding.spec == got.ema["w"].sharding.spec == P(None, "fsdp")
    assert norm.sharding.spec == P()
    np.testing.assert_array_equal(norm, want_norm)
    flat = dict(jax.tree_util.tree_leaves_with_path(got))
    for path, w in jax.tree_util.tree_leaves_with_path(want):
        np.testing.assert_array_equal(flat[path], w, err_msg=jax.tree_util.keystr(path))


def test_a_gradient_norm_past_float32_range_skips_the_step():
    """Every gradient finite, but their squares overflow float32: the norm is infinite, and the step
    is skipped as a non-finite one (clipping by an infinite norm would zero the gradients)."""
    params = {"w": jnp.ones((2, 2))}
    opt = make_optimizer(OptimConfig(lr=0.1, warmup_steps=0, schedule="constant"), 10, params)
    state = create_state(params, opt, 0)
    huge = {"w": jnp.full((2, 2), 1e20, jnp.float32)}
    assert np.isfinite(np.asarray(huge["w"])).all() and not np.isfinite(float(global_norm(square_sums(huge))))
    after = apply_gradients(state, huge, jnp.float32(1.0), opt, 0.9, state.rng)
    assert (int(after.bad_steps), int(after.skipped)) == (1, 1)
    np.testing.assert_array_equal(after.params["w"], state.params["w"])


def _state_after(steps):
    params = {"w": jnp.arange(16.0).reshape(4, 4), "b": jnp.ones(4)}
    opt = optax.adamw(1e-2)
    state = create_state(params, opt, 0)
    for _ in range(steps):
        state = apply_gradients(
            state, jax.tree_util.tree_map(jnp.ones_like, state.params), jnp.float32(1.0), opt, 0.9, state.rng
        )
    return state


def warnings_of(caplog, name="jaxdrive.train.checkpoint") -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == name and r.levelno == logging.WARNING]


def test_checkpoints_fall_back_past_a_damaged_one_and_reshard(tmp_path, caplog):
    ck = Checkpoints(tmp_path, keep=2)
    for step in (1, 2, 3):
        ck.save(step, _state_after(step), {"next_index": step}, {"step": step})
    ck.wait()
    assert ck.steps() == [2, 3]  # keep-N
    abstract = jax.eval_shape(lambda: _state_after(0))
    step, state, data, meta = ck.restore_latest(abstract)
    assert (step, data, meta["step"], int(state.step)) == (3, {"next_index": 3}, 3, 3)
    np.testing.assert_array_equal(state.params["w"], _state_after(3).params["w"])
    for f in (tmp_path / "checkpoints" / "3" / "state").rglob("*"):  # damage the newest
        if f.is_file() and f.name != "commit_success.txt":
            f.write_bytes(b"garbage")
    with caplog.at_level(logging.WARNING, logger="jaxdrive.train.checkpoint"):
        step, state, data, _ = ck.restore_latest(abstract)
    assert (step, data) == (2, {"next_index": 2})
    messages = warnings_of(caplog)
    assert len(messages) == 1 and "checkpoints/3 is incomplete or damaged" in messages[0]
    assert ck.skipped == messages
    mesh = make_mesh(data=2, fsdp=4)
    sharded = jax.tree_util.tree_map(
        lambda a: jax.ShapeDtypeStruct(
            a.shape, a.dtype, sharding=NamedSharding(mesh, P("fsdp") if a.ndim == 2 else P())
        ),
        abstract,
    )
    state, _, _ = ck.restore(2, sharded)
    assert state.params["w"].sharding.spec == P("fsdp")
    np.testing.assert_array_equal(state.params["w"], _state_after(2).params["w"])
    ck.close()


def test_a_replicated_state_saves_without_compiling_and_either_format_restores(tmp_path):
    """On CPU a replicated array is written from one replica: orbax's replica-parallel save would
    compile one slice program per parameter shape. A checkpoint that orbax's standard save wrote
    (replica-parallel, as on TPU) restores through Checkpoints bit-equal, and so does its own."""
    import orbax.checkpoint as ocp

    mesh = make_mesh(data=8)
    replicated = NamedSharding(mesh, P())
    # shapes no other test uses (so no slice program of them is in this process's jit cache), each
    # with an axis that 8 replicas divide (orbax slices only those)
    arrays = {"w": np.arange(24 * 40, dtype=np.float32).reshape(24, 40), "b": np.arange(56, dtype=np.int32)}
    state = jax.device_put(arrays, replicated)
    abstract = jax.tree_util.tree_map(
        lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=replicated), jax.eval_shape(lambda: state)
    )
    lowered = []  # every new program is lowered, whether or not the compilation cache holds it

    def listener(event, duration, **_):
        if event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            lowered.append(event)

    ck = Checkpoints(tmp_path / "ours", keep=3, asynchronous=False)
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        ck.save(2, state, {}, {"step": 2})
        ck.wait()
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert lowered == []
    theirs = ocp.CheckpointManager(tmp_path / "theirs" / "checkpoints", item_names=("state", "data", "meta"))
    theirs.save(
        2,
        args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), data=ocp.args.JsonSave({}), meta=ocp.args.JsonSave({"step": 2})
        ),
    )
    theirs.wait_until_finished()
    theirs.close()
    for folder in ("ours", "theirs"):
        reader = Checkpoints(tmp_path / folder, asynchronous=False)
        got, _, meta = reader.restore(2, abstract)
        reader.close()
        assert meta == {"step": 2}
        for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(state)):
            assert a.sharding == replicated
            np.testing.assert_array_equal(a, b)
    ck.close()


def _damage(step_dir, how):
    state = step_dir / "state"
    if how == "truncated array file":
        for data in (f for f in state.rglob("*") if f.is_file() and f.parent.name == "d"):  # OCDBT data files
            data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    elif how == "missing metadata file":
        (state / "_METADATA").unlink()
    elif how == "empty step folder":
        import shutil

        shutil.rmtree(step_dir)
        step_dir.mkdir()


@pytest.mark.parametrize("how", ["truncated array file", "missing metadata file", "empty step folder"])
def test_each_kind_of_damaged_checkpoint_is_named_and_the_newest_intact_one_used(tmp_path, how, caplog):
    ck = Checkpoints(tmp_path, keep=3)
    for step in (1, 2):
        ck.save(step, _state_after(step), {"next_index": step}, {"step": step})
    ck.wait()
    _damage(tmp_path / "checkpoints" / "2", how)
    ck.close()
    ck = Checkpoints(tmp_path, keep=3)
    with caplog.at_level(logging.WARNING, logger="jaxdrive.train.checkpoint"):
        step, state, data, _ = ck.restore_latest(jax.eval_shape(lambda: _state_after(0)))
    assert (step, data) == (1, {"next_index": 1})
    np.testing.assert_array_equal(state.params["w"], _state_after(1).params["w"])
    messages = warnings_of(caplog)
    assert len(messages) == 1 and "checkpoints/2 is incomplete or damaged" in messages[0]
    ck.close()


def test_a_checkpoint_of_another_model_is_a_value_error_saying_what_differs(tmp_path):
    ck = Checkpoints(tmp_path, keep=3)
    ck.save(1, _state_after(1), {}, {"step": 1})
    ck.wait()
    other = jax.eval_shape(lambda: _state_after(0).replace(params={"w": jnp.zeros((8, 4)), "c": jnp.zeros(2)}))
    with pytest.raises(
        ValueError,
        match=r"^workdir: expected checkpoints of this config's model .* got step 1 with "
        r"other parameters \(3 differ: w: expected shape \[8, 4\], got \[4, 4\]; "
        r"c: expected in the checkpoint, missing; b: in the checkpoint, "
        r"not in this model\)",
    ):
        ck.restore_latest(other)
    ck.close()
    # reached through another option (train.init_from, --segmenter, --fine-workdir): that option is named
    ck = Checkpoints(tmp_path, keep=3, option="train.init_from")
    with pytest.raises(
        ValueError,
        match=r"^train.init_from: expected checkpoints of this config's model .*; use a "
        r"new train.init_from or the config it was trained with",
    ):
        ck.restore_latest(other)
    ck.close()


def test_a_sampler_reads_the_weights_alone(tmp_path, caplog):
    """``restore_latest_weights``: the EMA (or the parameters) of the newest readable checkpoint,
    equal to the full restore's, without reading the optimizer's state: an abstract state whose
    optimizer state the checkpoint does not hold still gives the weights, where the full restore
    finds no checkpoint it can read."""
    ck = Checkpoints(tmp_path, keep=3)
    for step in (1, 2):
        ck.save(step, _state_after(step), {}, {"step": step})
    ck.wait()
    abstract = jax.eval_shape(lambda: _state_after(0))
    _, full, _, _ = ck.restore_latest(abstract)
    for ema, want in ((True, full.ema), (False, full.params)):
        step, weights = ck.restore_latest_weights(abstract, ema=ema)
        assert step == 2 and jax.tree_util.tree_structure(weights) == jax.tree_util.tree_structure(want)
        for a, b in zip(jax.tree_util.tree_leaves(weights), jax.tree_util.tree_leaves(want)):
            np.testing.assert_array_equal(a, b)
    assert not np.array_equal(full.ema["w"], full.params["w"])  # the two choices differ
    step, weights = ck.restore_latest_weights(abstract.replace(ema=None))  # a run without EMA: its parameters
    np.testing.assert_array_equal(weights["w"], full.params["w"])
    other_optimizer = abstract.replace(opt_state={"other": jax.ShapeDtypeStruct((3,), jnp.float32)})
    with caplog.at_level(logging.WARNING, logger="jaxdrive.train.checkpoint"):
        assert ck.restore_latest(other_optimizer) is None  # read, it is not in either checkpoint
        assert len(ck.skipped) == 2
        step, weights = ck.restore_latest_weights(other_optimizer)
    assert step == 2 and ck.skipped == []
    np.testing.assert_array_equal(weights["w"], full.ema["w"])
    ck.close()
