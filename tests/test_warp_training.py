"""LongDWM's warp-guided control in training: the pipeline warps each clip's first frame along the
clip's own poses (host, inpainted), the step encodes the warped clip into the DiT's ``warp``
input, and what rules it out is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from jaxdrive.config import load_config
from jaxdrive.train.run import Run

from train_fixtures import write_synthetic

ROOT = Path(__file__).resolve().parents[1]
WARP = ["model.controls.warp=true", "data.views=2", "data.batch_size=2", "data.frames=5", "mesh.data=2",
        "mesh.seq=4", "optim.warmup_steps=1", "train.log_every=1", "train.checkpoint_every=2"]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("warp") / "data", train=2, frames=9)


def config(data, *sets):
    return load_config(str(ROOT / "configs" / "tiny.py"), [f"data.path={data}", *WARP, *sets])


def test_the_pipeline_warps_each_clip_from_its_first_frame_along_its_own_poses(data):
    from jaxdrive.data.pipeline import clip_warp
    from jaxdrive.warp import warp_views
    run = Run(config(data, "data.warp_depth=15"))
    batch = next(iter(run.dataset()))
    video, warp = batch["video"], batch["warp_video"]
    assert warp.shape == video.shape and warp.dtype == np.float32
    np.testing.assert_allclose(warp[:, :, 0], video[:, :, 0], atol=1e-5)      # frame 0: the first frame itself
    # the clip's own poses relative to its first frame, at data.warp_depth
    i = 1
    e2w = batch["ego_to_world"][i].astype(np.float64)
    poses = (np.linalg.inv(e2w[0]) @ e2w).astype(np.float32)
    want = warp_views(video[i, :, 0], batch["intrinsics"][i], batch["cam_to_ego"][i], poses, 15.0)
    np.testing.assert_allclose(warp[i], want, atol=1e-5)
    sample = {k: batch[k][i] for k in ("video", "ego_to_world", "intrinsics", "cam_to_ego")}
    np.testing.assert_allclose(clip_warp(sample, 15.0), want, atol=1e-5)
    assert np.abs(warp[:, :, -1] - video[:, :, 0]).max() > 0.05       # the ego moved: later frames are warped
    inputs = run.global_batch([batch])
    assert inputs["warp_video"].shape == (1,) + video.shape
    # classifier-free guidance drops the warp with the trajectory, the control it carries
    from jaxdrive.data.batches import conditions
    cond = conditions(dict(batch, drop=dict(batch["drop"], trajectory=np.asarray([True, False]))), run.training.model)
    np.testing.assert_array_equal(cond.drop["warp"], [True, False])


def test_the_step_encodes_the_warped_clip_into_the_dit_and_learns_its_embedding(data):
    """The loss of a batch from the run's own pipeline depends on its warped clip, and the
    gradient reaches the warp embedding (the step: loss, gradients, optimizer)."""
    import jax

    from jaxdrive.train import flow_step
    run = Run(config(data))
    state, _, _ = run.init_state(log=lambda *a: None)
    params = jax.tree_util.tree_map(lambda p: p + 0.01, state.params)       # every layer off its zero init
    inputs = jax.tree_util.tree_map(lambda a: a[0], run.global_batch([next(iter(run.dataset()))]))
    key = jax.random.key(0)
    with jax.set_mesh(run.mesh):
        grad = jax.jit(jax.value_and_grad(lambda p, i: flow_step.flow_loss_fn(run.training, p, None, i, key)[0]))
        (same, g), (other, _) = grad(params, inputs), grad(params, dict(inputs, warp_video=-inputs["warp_video"]))
    assert np.isfinite(float(same)) and abs(float(same) - float(other)) > 1e-6
    warp_grads = {jax.tree_util.keystr(k): float(np.abs(np.asarray(v)).max())
                  for k, v in jax.tree_util.tree_leaves_with_path(g) if "warp" in jax.tree_util.keystr(k)}
    assert warp_grads and max(warp_grads.values()) > 0, warp_grads


@pytest.mark.parametrize("sets, match", [
    (["data.warp_depth=0"], "data.warp_depth: expected a positive depth"),
    (["stream.enabled=true", "stream.taps=()"], "stream.enabled: expected False with model.controls.warp"),
])
def test_what_rules_the_warp_out_is_refused(data, sets, match):
    with pytest.raises(ValueError, match=match):
        Run(config(data, *sets))
