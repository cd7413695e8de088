"""Weights, checkpoints and run configs are data: a pickle bomb where weights are expected is
refused with a ValueError and never runs, and a run's config.json is parsed, never executed."""

import pickle
from pathlib import Path

import pytest

from jaxdrive.convert.safetensors_io import read_tensors, read_weights
from jaxdrive.eval.weights import read_state_dict
from jaxdrive.train.run import load_run_config


class _Bomb:
    """Unpickling this calls ``Path(marker).touch()``: any loader that unpickles it leaves the file."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


def _bomb(path: Path, marker: Path) -> Path:
    path.write_bytes(pickle.dumps({"weight": _Bomb(marker)}))
    return path


def test_a_pickle_bomb_state_dict_is_refused_and_never_runs(tmp_path):
    torch = pytest.importorskip("torch")
    marker, path = tmp_path / "ran", tmp_path / "evil.pth"
    torch.save({"weight": _Bomb(marker)}, path)  # a real torch checkpoint file
    with pytest.raises(ValueError, match=r"^path: could not read .*evil.pth as a state dict"):
        read_state_dict(path)
    assert not marker.exists()
    torch.load(path, weights_only=False)  # the control: unpickling runs it
    assert marker.exists()


def test_a_pickle_bomb_named_safetensors_is_refused_and_never_runs(tmp_path):
    marker = tmp_path / "ran"
    with pytest.raises(ValueError, match="evil.safetensors"):
        read_tensors(_bomb(tmp_path / "evil.safetensors", marker))
    with pytest.raises(ValueError, match="evil.safetensors"):
        read_state_dict(tmp_path / "evil.safetensors", option="--i3d")
    assert not marker.exists()


def test_a_model_folder_with_only_pickled_weights_is_refused(tmp_path):
    marker = tmp_path / "ran"
    _bomb(tmp_path / "diffusion_pytorch_model.bin", marker)
    with pytest.raises(ValueError, match=r"pickled weights are never loaded"):
        read_weights(tmp_path)
    assert not marker.exists()


def test_a_run_config_is_parsed_never_executed(tmp_path):
    marker = tmp_path / "ran"
    (tmp_path / "config.json").write_text(f"__import__('pathlib').Path({str(marker)!r}).touch()")
    with pytest.raises(ValueError, match=r"workdir: expected JSON in .*config.json"):
        load_run_config(tmp_path)
    (tmp_path / "config.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"workdir: expected a JSON object in .*config.json, got list"):
        load_run_config(tmp_path)
    assert not marker.exists()
