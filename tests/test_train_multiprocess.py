"""``jaxdrive train`` as 2 processes x 4 fake CPU devices (gloo), launched by ``launch/local.py``,
logs the same losses as 1 process x 8 devices.

The dataset holds copies of one clip with exactly the training length and no condition drops,
so every process feeds the same samples whichever clips the data sharding gives it; what is
compared is the engine: global batches from host-local rows, the sharded step, the collectives.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxdrive.config import load_config
from jaxdrive.train.metrics import read_metrics
from jaxdrive.train.run import train

from train_fixtures import write_same_clips

ROOT = Path(__file__).resolve().parents[1]
SETS = ["data.views=2", "data.frames=5", "data.batch_size=2", "data.drop_prob=0.0", "model.depth=1",
        "train.steps=2", "train.log_every=1", "train.checkpoint_every=100", "optim.warmup_steps=1",
        "mesh.data=2", "mesh.seq=4"]


@pytest.fixture(scope="module")
def same_clips(tmp_path_factory):
    return write_same_clips(tmp_path_factory.mktemp("same") / "data", seed=7, frames=5, copies=4)


def test_two_processes_match_one(same_clips, tmp_path):
    sets = [f"data.path={same_clips}", *SETS]
    cmd = [sys.executable, str(ROOT / "launch" / "local.py"), "--processes", "2", "--cpu-devices", "4", "--",
           sys.executable, "-m", "jaxdrive.cli", "train", "--config", str(ROOT / "configs" / "tiny.py"),
           "--workdir", str(tmp_path / "two"), "--no-progress"]
    for s in sets:
        cmd += ["--set", s]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    two = read_metrics(tmp_path / "two")
    one = train(load_config(ROOT / "configs" / "tiny.py", sets), tmp_path / "one", progress=False)
    assert one["status"] == "done"
    ref = read_metrics(tmp_path / "one")
    assert [r["step"] for r in two] == [r["step"] for r in ref] == [1, 2]
    np.testing.assert_allclose([r["loss"] for r in two], [r["loss"] for r in ref], rtol=1e-5)
    np.testing.assert_allclose([r["grad_norm"] for r in two], [r["grad_norm"] for r in ref], rtol=1e-4)
