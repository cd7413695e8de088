"""The FID Inception network (pool3, 2048 features) in JAX, from the standard weights file.

FID's features (Heusel et al. 2017) come from TensorFlow's 2015 InceptionV3 graph; pytorch-fid
ported it (``pt_inception-2015-12-05-6726825d.pth``, from its GitHub releases, a state dict) as
torchvision's InceptionV3 layout with the TF graph's differences: 1008 classes, average pools
that do not count the padding, and a max pool in the last block. This module is that network as
pure JAX functions over a dict of the file's tensors (each convolution's batch norm folded into a
scale and shift), jitted, NHWC:

    model, params = load_fid_inception("pt_inception-2015-12-05-6726825d.pth")   # or .safetensors
    feats = model.features(params, images)      # [N, H, W, 3] in [0, 255] -> [N, 2048]

Images are resized to 299 x 299 bilinearly without antialiasing (``F.interpolate(...,
align_corners=False)``, as pytorch-fid does) and scaled to [-1, 1]. ``jaxdrive convert inception``
rewrites the ``.pth`` as safetensors, so that evaluation needs no torch.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.eval.weights import conv_batch_norm, read_state_dict

BN_EPS = 1e-3  # torchvision's BasicConv2d
FEATURES = 2048
SIZE = 299

# name -> (in, out, (kh, kw), stride, (ph, pw)); branches keep torchvision's names
_A = lambda c, pool: {
    "branch1x1": (c, 64, 1),
    "branch5x5_1": (c, 48, 1),
    "branch5x5_2": (48, 64, 5),
    "branch3x3dbl_1": (c, 64, 1),
    "branch3x3dbl_2": (64, 96, 3),
    "branch3x3dbl_3": (96, 96, 3),
    "branch_pool": (c, pool, 1),
}
_B = lambda c: {
    "branch3x3": (c, 384, 3, 2),
    "branch3x3dbl_1": (c, 64, 1),
    "branch3x3dbl_2": (64, 96, 3),
    "branch3x3dbl_3": (96, 96, 3, 2),
}
_C = lambda c, c7: {
    "branch1x1": (c, 192, 1),
    "branch7x7_1": (c, c7, 1),
    "branch7x7_2": (c7, c7, (1, 7)),
    "branch7x7_3": (c7, 192, (7, 1)),
    "branch7x7dbl_1": (c, c7, 1),
    "branch7x7dbl_2": (c7, c7, (7, 1)),
    "branch7x7dbl_3": (c7, c7, (1, 7)),
    "branch7x7dbl_4": (c7, c7, (7, 1)),
    "branch7x7dbl_5": (c7, 192, (1, 7)),
    "branch_pool": (c, 192, 1),
}
_D = lambda c: {
    "branch3x3_1": (c, 192, 1),
    "branch3x3_2": (192, 320, 3, 2),
    "branch7x7x3_1": (c, 192, 1),
    "branch7x7x3_2": (192, 192, (1, 7)),
    "branch7x7x3_3": (192, 192, (7, 1)),
    "branch7x7x3_4": (192, 192, 3, 2),
}
_E = lambda c: {
    "branch1x1": (c, 320, 1),
    "branch3x3_1": (c, 384, 1),
    "branch3x3_2a": (384, 384, (1, 3)),
    "branch3x3_2b": (384, 384, (3, 1)),
    "branch3x3dbl_1": (c, 448, 1),
    "branch3x3dbl_2": (448, 384, 3),
    "branch3x3dbl_3a": (384, 384, (1, 3)),
    "branch3x3dbl_3b": (384, 384, (3, 1)),
    "branch_pool": (c, 192, 1),
}
STEM = {
    "Conv2d_1a_3x3": (3, 32, 3, 2, 0),
    "Conv2d_2a_3x3": (32, 32, 3, 1, 0),
    "Conv2d_2b_3x3": (32, 64, 3),
    "Conv2d_3b_1x1": (64, 80, 1),
    "Conv2d_4a_3x3": (80, 192, 3, 1, 0),
}
MIXED = (
    ("Mixed_5b", "A", _A(192, 32)),
    ("Mixed_5c", "A", _A(256, 64)),
    ("Mixed_5d", "A", _A(288, 64)),
    ("Mixed_6a", "B", _B(288)),
    ("Mixed_6b", "C", _C(768, 128)),
    ("Mixed_6c", "C", _C(768, 160)),
    ("Mixed_6d", "C", _C(768, 160)),
    ("Mixed_6e", "C", _C(768, 192)),
    ("Mixed_7a", "D", _D(768)),
    ("Mixed_7b", "E", _E(1280)),
    ("Mixed_7c", "E2", _E(2048)),
)


def _spec(entry):
    """``(in, out, k[, stride[, pad]])`` -> ``(in, out, (kh, kw), stride, (ph, pw))``; a stride-1
    convolution pads to keep its size, a strided one does not."""
    cin, cout, k = entry[:3]
    k = (k, k) if isinstance(k, int) else k
    stride = entry[3] if len(entry) > 3 else 1
    pad = entry[4] if len(entry) > 4 else (0 if stride > 1 else None)
    pad = ((k[0] - 1) // 2, (k[1] - 1) // 2) if pad is None else (pad, pad)
    return cin, cout, k, stride, pad


LAYERS = {name: _spec(e) for name, e in STEM.items()}
LAYERS.update({f"{block}.{name}": _spec(e) for block, _, layers in MIXED for name, e in layers.items()})


def _conv(params, name, x):
    _, _, _, stride, pad = LAYERS[name]
    p = params[name]
    y = jax.lax.conv_general_dilated(
        x,
        p["kernel"],
        (stride, stride),
        [(pad[0], pad[0]), (pad[1], pad[1])],
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
        precision=jax.lax.Precision.HIGHEST,
    )
    return jax.nn.relu(y * p["scale"] + p["shift"])


def _max_pool(x, stride=2, pad=0):
    return jax.lax.reduce_window(
        x, -jnp.inf, jax.lax.max, (1, 3, 3, 1), (1, stride, stride, 1), [(0, 0), (pad, pad), (pad, pad), (0, 0)]
    )


def _avg_pool_valid_only(x):
    """3 x 3, stride 1, padding 1, the padding not counted (TensorFlow's, pytorch-fid's patch)."""
    pads = [(0, 0), (1, 1), (1, 1), (0, 0)]
    total = jax.lax.reduce_window(x, 0.0, jax.lax.add, (1, 3, 3, 1), (1, 1, 1, 1), pads)
    count = jax.lax.reduce_window(
        jnp.ones(x.shape[1:3])[None, ..., None], 0.0, jax.lax.add, (1, 3, 3, 1), (1, 1, 1, 1), pads
    )
    return total / count


def _mixed(params, block, kind, x):
    c = lambda name, y: _conv(params, f"{block}.{name}", y)
    if kind == "A":
        return jnp.concatenate(
            [
                c("branch1x1", x),
                c("branch5x5_2", c("branch5x5_1", x)),
                c("branch3x3dbl_3", c("branch3x3dbl_2", c("branch3x3dbl_1", x))),
                c("branch_pool", _avg_pool_valid_only(x)),
            ],
            -1,
        )
    if kind == "B":
        return jnp.concatenate(
            [c("branch3x3", x), c("branch3x3dbl_3", c("branch3x3dbl_2", c("branch3x3dbl_1", x))), _max_pool(x)], -1
        )
    if kind == "C":
        b7 = c("branch7x7_3", c("branch7x7_2", c("branch7x7_1", x)))
        d = x
        for i in range(1, 6):
            d = c(f"branch7x7dbl_{i}", d)
        return jnp.concatenate([c("branch1x1", x), b7, d, c("branch_pool", _avg_pool_valid_only(x))], -1)
    if kind == "D":
        b3 = c("branch3x3_2", c("branch3x3_1", x))
        b7 = x
        for i in range(1, 5):
            b7 = c(f"branch7x7x3_{i}", b7)
        return jnp.concatenate([b3, b7, _max_pool(x)], -1)
    b3 = c("branch3x3_1", x)
    d = c("branch3x3dbl_2", c("branch3x3dbl_1", x))
    pool = _avg_pool_valid_only(x) if kind == "E" else _max_pool(x, stride=1, pad=1)  # the last block: max
    return jnp.concatenate(
        [
            c("branch1x1", x),
            c("branch3x3_2a", b3),
            c("branch3x3_2b", b3),
            c("branch3x3dbl_3a", d),
            c("branch3x3dbl_3b", d),
            c("branch_pool", pool),
        ],
        -1,
    )


@jax.jit
def _features(params, images):
    x = jnp.asarray(images, jnp.float32) / 255.0
    x = jax.image.resize(x, (x.shape[0], SIZE, SIZE, 3), "bilinear", antialias=False)
    x = 2.0 * x - 1.0
    for name in ("Conv2d_1a_3x3", "Conv2d_2a_3x3", "Conv2d_2b_3x3"):
        x = _conv(params, name, x)
    x = _max_pool(x)
    x = _max_pool(_conv(params, "Conv2d_4a_3x3", _conv(params, "Conv2d_3b_1x1", x)))
    for block, kind, _ in MIXED:
        x = _mixed(params, block, kind, x)
    return x.mean((1, 2))


@dataclasses.dataclass(frozen=True)
class FIDInception:
    """The network's functions; its parameters are the dict :func:`load_fid_inception` returns."""

    def features(self, params, images) -> jax.Array:
        """Pool3 features ``[N, 2048]`` of ``images [N, H, W, 3]`` with values in [0, 255]."""
        shape = np.shape(images)
        if len(shape) != 4 or shape[-1] != 3:
            raise ValueError(f"images: expected [N, H, W, 3] with values in [0, 255], got shape {list(shape)}")
        return _features(params, images)


def params_from_state_dict(state: dict, *, source: str = "weights") -> dict:
    """The network's parameters from pytorch-fid's state dict (NumPy arrays by their torch names):
    HWIO kernels and each batch norm folded to ``scale``/``shift``. A missing or misshapen tensor
    (another network, a truncated file) is a ``ValueError`` naming it."""
    what = "the FID Inception's tensor {key!r} (pytorch-fid's pt_inception-2015-12-05 weights)"
    return {
        name: conv_batch_norm(
            state, f"{name}.conv", f"{name}.bn", (cout, cin, kh, kw), BN_EPS, source=source, what=what
        )
        for name, (cin, cout, (kh, kw), _, _) in LAYERS.items()
    }


def load_fid_inception(path, *, option: str = "path"):
    """``(model, params)`` from pytorch-fid's ``.pth`` or its safetensors copy."""
    return FIDInception(), params_from_state_dict(read_state_dict(path, option=option), source=f"{option} {path}")
