"""The I3D network of FVD (Carreira & Zisserman 2017; Unterthiner et al. 2018) in JAX, as cd-fvd
uses it: ``InceptionI3d(400)`` with its ``i3d_pretrained_400.pt`` state dict, whose 400 Kinetics
logits are the features FVD compares.

    model, params = load_i3d("i3d_pretrained_400.pt")        # or a safetensors copy
    logits = model.logits(params, videos)          # [N, T, H, W, 3] in [0, 255] -> [N, 400]

Videos are resized to 224 x 224 bilinearly without antialiasing and scaled to [-1, 1], as cd-fvd's
``preprocess_i3d``. Every convolution and max pool pads TensorFlow's "same" way (computed from the
input size; max pools pad with zeros, as the reference does), the logits are averaged over the
remaining time steps. Pure JAX functions over a dict of the file's tensors, NDHWC, jitted.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.eval.weights import conv_batch_norm, read_state_dict

BN_EPS = 1e-5
CLASSES = 400
SIZE = 224

# name -> (in, out, kernel (t, h, w), stride (t, h, w)); modules: (in, [b0, b1a, b1b, b2a, b2b, b3b])
STEM = (
    ("Conv3d_1a_7x7", 3, 64, (7, 7, 7), (2, 2, 2)),
    ("MaxPool3d_2a_3x3", (1, 3, 3), (1, 2, 2)),
    ("Conv3d_2b_1x1", 64, 64, (1, 1, 1), (1, 1, 1)),
    ("Conv3d_2c_3x3", 64, 192, (3, 3, 3), (1, 1, 1)),
    ("MaxPool3d_3a_3x3", (1, 3, 3), (1, 2, 2)),
)
MODULES = (
    ("Mixed_3b", 192, (64, 96, 128, 16, 32, 32)),
    ("Mixed_3c", 256, (128, 128, 192, 32, 96, 64)),
    ("MaxPool3d_4a_3x3", (3, 3, 3), (2, 2, 2)),
    ("Mixed_4b", 480, (192, 96, 208, 16, 48, 64)),
    ("Mixed_4c", 512, (160, 112, 224, 24, 64, 64)),
    ("Mixed_4d", 512, (128, 128, 256, 24, 64, 64)),
    ("Mixed_4e", 512, (112, 144, 288, 32, 64, 64)),
    ("Mixed_4f", 528, (256, 160, 320, 32, 128, 128)),
    ("MaxPool3d_5a_2x2", (2, 2, 2), (2, 2, 2)),
    ("Mixed_5b", 832, (256, 160, 320, 32, 128, 128)),
    ("Mixed_5c", 832, (384, 192, 384, 48, 128, 128)),
)
FEATURES = 384 + 384 + 128 + 128


def _layers():
    """Every convolution: name -> (in, out, kernel, stride)."""
    out = {}
    for entry in STEM + MODULES:
        if entry[0].startswith("Conv3d"):
            out[entry[0]] = entry[1:]
        elif entry[0].startswith("Mixed"):
            name, cin, (c0, c1a, c1b, c2a, c2b, c3b) = entry
            one, three = (1, 1, 1), (3, 3, 3)
            out.update(
                {
                    f"{name}.b0": (cin, c0, one, one),
                    f"{name}.b1a": (cin, c1a, one, one),
                    f"{name}.b1b": (c1a, c1b, three, one),
                    f"{name}.b2a": (cin, c2a, one, one),
                    f"{name}.b2b": (c2a, c2b, three, one),
                    f"{name}.b3b": (cin, c3b, one, one),
                }
            )
    return out


LAYERS = _layers()


def _same(size: int, k: int, s: int) -> tuple[int, int]:
    """TensorFlow's "same" padding of one axis, the reference's ``compute_pad`` (front, back)."""
    pad = max(k - s, 0) if size % s == 0 else max(k - size % s, 0)
    return pad // 2, pad - pad // 2


def _pads(shape, kernel, stride):
    return [_same(n, k, s) for n, k, s in zip(shape[1:4], kernel, stride)]


def _unit(params, name, x, relu=True):
    _, _, kernel, stride = LAYERS[name] if name in LAYERS else (None, None, (1, 1, 1), (1, 1, 1))
    p = params[name]
    y = jax.lax.conv_general_dilated(
        x,
        p["kernel"],
        stride,
        _pads(x.shape, kernel, stride),
        dimension_numbers=("NDHWC", "DHWIO", "NDHWC"),
        precision=jax.lax.Precision.HIGHEST,
    )
    y = y * p["scale"] + p["shift"]
    return jax.nn.relu(y) if relu else y


def _max_pool(x, kernel, stride):
    x = jnp.pad(x, [(0, 0), *_pads(x.shape, kernel, stride), (0, 0)])  # zeros, as F.pad
    return jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, *kernel, 1), (1, *stride, 1), "VALID")


def _module(params, name, x):
    u = lambda b, y: _unit(params, f"{name}.{b}", y)
    return jnp.concatenate(
        [u("b0", x), u("b1b", u("b1a", x)), u("b2b", u("b2a", x)), u("b3b", _max_pool(x, (3, 3, 3), (1, 1, 1)))], -1
    )


@jax.jit
def _logits(params, videos):
    n, t = videos.shape[:2]
    x = jnp.asarray(videos, jnp.float32).reshape(n * t, *videos.shape[2:])
    x = jax.image.resize(x, (n * t, SIZE, SIZE, 3), "bilinear", antialias=False)
    x = (2.0 * x / 255.0 - 1.0).reshape(n, t, SIZE, SIZE, 3)
    for entry in STEM + MODULES:
        if entry[0].startswith("Conv3d"):
            x = _unit(params, entry[0], x)
        elif entry[0].startswith("MaxPool"):
            x = _max_pool(x, *entry[1:])
        else:
            x = _module(params, entry[0], x)
    # AvgPool3d([2, 7, 7], stride 1), the 1x1x1 logits layer, the mean over the steps left
    x = jax.lax.reduce_window(x, 0.0, jax.lax.add, (1, 2, 7, 7, 1), (1, 1, 1, 1, 1), "VALID") / (2 * 7 * 7)
    x = _unit(params, "logits", x, relu=False)
    return x.mean((1, 2, 3))


@dataclasses.dataclass(frozen=True)
class I3D:
    """The network's functions; its parameters are the dict :func:`load_i3d` returns."""

    def logits(self, params, videos) -> jax.Array:
        """The 400 Kinetics logits ``[N, 400]`` of ``videos [N, T, H, W, 3]`` in [0, 255]
        (T >= 9: the network's strides leave at least 2 steps for its last average pool)."""
        shape = np.shape(videos)
        if len(shape) != 5 or shape[-1] != 3:
            raise ValueError(f"videos: expected [N, T, H, W, 3] with values in [0, 255], got shape {list(shape)}")
        if shape[1] < 9:
            raise ValueError(f"videos: expected at least 9 frames (FVD uses 16), got {shape[1]}")
        return _logits(params, videos)


def params_from_state_dict(state: dict, *, source: str = "weights") -> dict:
    """The network's parameters from cd-fvd's ``InceptionI3d(400)`` state dict (NumPy arrays by
    their torch names); a missing or misshapen tensor is a ``ValueError`` naming it."""
    what = "the I3D tensor {key!r} (cd-fvd's i3d_pretrained_400.pt)"
    params = {
        name: conv_batch_norm(
            state, f"{name}.conv3d", f"{name}.bn", (cout, cin, *kernel), BN_EPS, source=source, what=what
        )
        for name, (cin, cout, kernel, _) in LAYERS.items()
    }
    params["logits"] = conv_batch_norm(
        state, "logits.conv3d", None, (CLASSES, FEATURES, 1, 1, 1), BN_EPS, source=source, what=what, bias=True
    )
    return params


def load_i3d(path, *, option: str = "path"):
    """``(model, params)`` from cd-fvd's ``i3d_pretrained_400.pt`` or its safetensors copy."""
    return I3D(), params_from_state_dict(read_state_dict(path, option=option), source=f"{option} {path}")
