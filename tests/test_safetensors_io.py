"""Reading safetensors weights without PyTorch: a truncated or garbled file is refused by the
safetensors package itself, and the error names the file."""

import numpy as np
import pytest
from safetensors.numpy import save_file

from jaxdrive.convert.safetensors_io import WEIGHTS, read_weights


def _weights(tmp_path):
    tensors = {"a.weight": np.arange(600, dtype=np.float32).reshape(20, 30), "b.bias": np.ones(7, np.float32)}
    save_file(tensors, tmp_path / WEIGHTS)
    return tensors, (tmp_path / WEIGHTS).read_bytes()


def test_a_complete_file_reads_back(tmp_path):
    tensors, _ = _weights(tmp_path)
    got = read_weights(tmp_path)
    assert sorted(got) == sorted(tensors)
    for name, value in tensors.items():
        np.testing.assert_array_equal(got[name], value)


@pytest.mark.parametrize("keep", [0, 5, 8, 20, "half", "all but one"])
def test_a_truncated_file_is_refused_naming_the_file(tmp_path, keep):
    _, data = _weights(tmp_path)
    keep = {"half": len(data) // 2, "all but one": len(data) - 1}.get(keep, keep)
    (tmp_path / WEIGHTS).write_bytes(data[:keep])
    with pytest.raises(ValueError, match=rf"{WEIGHTS}: not a complete safetensors file \({keep} bytes"):
        read_weights(tmp_path)


def test_a_garbled_header_is_refused_naming_the_file(tmp_path):
    _, data = _weights(tmp_path)
    (tmp_path / WEIGHTS).write_bytes(data[:8] + b"{x" + data[10:])
    with pytest.raises(ValueError, match=rf"{WEIGHTS}: corrupt safetensors file"):
        read_weights(tmp_path)
