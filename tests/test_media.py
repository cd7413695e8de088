"""Run outputs: the multi-view mosaic, mp4 (decoded back), frame grid, loss plot, metrics files."""

import json

import av
import numpy as np
import pytest
from PIL import Image

from jaxdrive.media import plot_losses, to_uint8, view_mosaic, write_frame_grid, write_mp4
from jaxdrive.train.metrics import MetricsWriter, read_metrics


def _views(v=6, f=5, h=8, w=10):
    # view i is filled with the value 40 * i, so each tile of the mosaic says which view it shows
    return np.broadcast_to((40 * np.arange(v, dtype=np.uint8))[:, None, None, None, None], (v, f, h, w, 3)).copy()


def test_six_views_are_laid_out_as_a_driver_sees_them():
    m = view_mosaic(_views())
    assert m.shape == (5, 16, 30, 3)
    # top: front-left (5), front (0), front-right (1); bottom: back-left (4), back (3), back-right (2)
    assert [m[0, 0, 10 * c, 0] // 40 for c in range(3)] == [5, 0, 1]
    assert [m[0, 8, 10 * c, 0] // 40 for c in range(3)] == [4, 3, 2]
    assert view_mosaic(_views(v=1)).shape == (5, 8, 10, 3)
    assert to_uint8(np.array([-1.0, 0.0, 1.0])).tolist() == [0, 128, 255]
    with pytest.raises(ValueError, match="video: expected 3 channels"):
        view_mosaic(np.zeros((2, 3, 4, 4, 1)))


def test_mp4_decodes_back_to_the_frames(tmp_path):
    video = np.zeros((1, 6, 16, 24, 3), np.float32)
    video[0, :, :, :, 0] = np.linspace(-1, 1, 6)[:, None, None]  # red ramps over time
    path = write_mp4(tmp_path / "v.mp4", video, fps=6)
    with av.open(str(path)) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(frames) == 6 and frames[0].shape == (16, 24, 3)
    reds = [float(f[..., 0].mean()) for f in frames]
    assert reds[0] < 20 and reds[-1] > 235 and all(np.diff(reds) > 0)


def test_grid_and_plot_are_pngs(tmp_path):
    grid = Image.open(write_frame_grid(tmp_path / "g.png", _views(), num_frames=3, min_width=1))
    assert grid.size == (30, 3 * 16 + 2 * 2)
    # beside a reference: [reference | 4 white columns | video], enlarged 8x to reach 480 pixels
    ref = _views() // 2
    grid = np.asarray(
        Image.open(write_frame_grid(tmp_path / "r.png", _views(), num_frames=3, reference=ref, min_width=480))
    )
    assert grid.shape == (3 * 16 * 8 + 2 * 2, (30 + 4 + 30) * 8, 3)
    np.testing.assert_array_equal(grid[: 16 * 8, : 30 * 8], view_mosaic(ref)[0].repeat(8, 0).repeat(8, 1))
    np.testing.assert_array_equal(grid[: 16 * 8, 34 * 8 :], view_mosaic(_views())[0].repeat(8, 0).repeat(8, 1))
    with pytest.raises(ValueError, match=r"reference: expected the shape of video \[6, 5, 8, 10, 3\], got"):
        write_frame_grid(tmp_path / "x.png", _views(), reference=ref[:, :2])
    plot = Image.open(plot_losses(tmp_path / "l.png", [1, 2, 3], [1.0, 0.5, 0.01]))
    assert plot.size[0] > 100


def test_metrics_jsonl_and_tensorboard(tmp_path):
    w = MetricsWriter(tmp_path, total_steps=10, tokens_per_step=100, progress=False)
    w.write(1, {"loss": np.float32(0.5)})
    w.write(3, {"loss": 0.25, "lr": 1e-3})
    w.close()
    rows = read_metrics(tmp_path)
    assert [r["step"] for r in rows] == [1, 3] and rows[1]["loss"] == 0.25
    assert rows[1]["tokens_per_s"] == pytest.approx(rows[1]["steps_per_s"] * 100)
    assert json.loads((tmp_path / "metrics.jsonl").read_text().splitlines()[0])["loss"] == 0.5
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))


@pytest.mark.slow(seconds=3)
def test_the_metrics_writer_does_not_import_torch(tmp_path):
    """tensorboardX imports torch whenever it is installed (the test extra installs it): a run's
    writer keeps it out, still writes its scalars, and leaves torch importable afterwards."""
    import subprocess
    import sys

    script = f"""
import importlib.util, sys
from jaxdrive.train.metrics import MetricsWriter
w = MetricsWriter({str(tmp_path)!r}, total_steps=2, progress=False)
w.write(1, {{"loss": 0.5}})
w.close()
print("torch imported:", "torch" in sys.modules)
if importlib.util.find_spec("torch") is not None:
    import torch
    print("torch after:", torch.__name__)
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "torch imported: False" in done.stdout
    import importlib.util

    if importlib.util.find_spec("torch") is not None:
        assert "torch after: torch" in done.stdout
    events = b"".join(p.read_bytes() for p in (tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    assert b"loss" in events
