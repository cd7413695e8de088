"""The reference code of FID and FVD (pytorch-fid's FID Inception and Fréchet distance, cd-fvd's
I3D), importable beside the CPU torch wheel, for the parity tests.

torchvision's compiled extension does not load beside the CPU torch wheel (``operator
torchvision::nms does not exist`` on ``import torchvision``), and with torchvision installed
diffusers imports it (and fails). So the README's test command installs the reference packages
into ``.reference/`` with ``pip install --no-deps --target .reference``, off the import path, and
this module loads them by path: torchvision's pure-Python ``models/inception.py`` under a
stand-in ``torchvision`` package that provides the few names it imports (weight enums and logging
the reference never uses), pytorch-fid on top of it, and cd-fvd's pure-torch ``pytorch_i3d.py``.
The stand-in leaves ``sys.modules`` once pytorch-fid holds what it needs. Nothing of jaxdrive is
involved.
"""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path


def _stub(name: str, **attrs) -> types.ModuleType:
    module = types.ModuleType(name)
    module.__dict__.update(attrs)
    sys.modules[name] = module
    return module


class _Weights:
    def __init__(self, **kwargs):
        self.__dict__.update(kwargs)


class _WeightsEnum:
    @classmethod
    def verify(cls, value):
        return value


def _decorator_factory(*args, **kwargs):
    return lambda fn: fn


REFERENCE = Path(__file__).resolve().parents[1] / ".reference"
INSTALL = "pip install --no-deps --target .reference torchvision==0.28.0 pytorch-fid==0.3.0 cd-fvd==0.1.1"


def _require(relative: str) -> Path:
    import pytest

    path = REFERENCE / relative
    if not path.is_file():
        pytest.skip(
            f"the reference code is not installed ({path} missing): run '{INSTALL}' (the README's test command does)"
        )
    return path


def load_pytorch_fid():
    """``pytorch_fid.inception`` (its ``InceptionV3``) and ``pytorch_fid.fid_score``, with
    torchvision's Inception modules."""
    if "pytorch_fid.fid_score" in sys.modules:
        return sys.modules["pytorch_fid.inception"]
    root = _require("torchvision/models/inception.py").parents[1]
    before = set(sys.modules)
    sys.path.insert(0, str(REFERENCE))
    try:
        tv = _stub("torchvision", __version__="0.28.0", __path__=[str(root)])
        models = _stub("torchvision.models", __path__=[str(root / "models")])
        tv.models = models
        tv.transforms = _stub("torchvision.transforms", __path__=[])
        _stub("torchvision.transforms._presets", ImageClassification=object)
        _stub("torchvision.utils", _log_api_usage_once=lambda *a, **k: None)
        _stub("torchvision.models._api", register_model=_decorator_factory, Weights=_Weights, WeightsEnum=_WeightsEnum)
        _stub("torchvision.models._meta", _IMAGENET_CATEGORIES=[])
        _stub(
            "torchvision.models._utils",
            _ovewrite_named_param=lambda kw, k, v: kw.setdefault(k, v),
            handle_legacy_interface=_decorator_factory,
        )
        spec = importlib.util.spec_from_file_location("torchvision.models.inception", root / "models" / "inception.py")
        inception = importlib.util.module_from_spec(spec)
        sys.modules["torchvision.models.inception"] = inception
        spec.loader.exec_module(inception)
        models.inception = inception
        models.inception_v3 = inception.inception_v3
        import pytorch_fid.fid_score  # noqa: F401  (its Fréchet distance; it imports the network too)
        import pytorch_fid.inception as fid_inception
    finally:
        sys.path.remove(str(REFERENCE))
        for name in set(sys.modules) - before:  # the stand-in goes; pytorch-fid keeps its references
            if name == "torchvision" or name.startswith("torchvision."):
                del sys.modules[name]
    return fid_inception


def load_cd_fvd_i3d():
    """cd-fvd's ``pytorch_i3d`` module (pure torch), loaded by its path."""
    path = _require("cdfvd/third_party/i3d/pytorch_i3d.py")
    spec = importlib.util.spec_from_file_location("cdfvd_pytorch_i3d", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# pytorch-fid's InceptionV3 wrapper ("blocks.i.j") -> the weights file's names (torchvision's)
WRAPPER_NAMES = {
    "blocks.0.0": "Conv2d_1a_3x3",
    "blocks.0.1": "Conv2d_2a_3x3",
    "blocks.0.2": "Conv2d_2b_3x3",
    "blocks.1.0": "Conv2d_3b_1x1",
    "blocks.1.1": "Conv2d_4a_3x3",
    **{
        f"blocks.2.{i}": n
        for i, n in enumerate(
            ["Mixed_5b", "Mixed_5c", "Mixed_5d", "Mixed_6a", "Mixed_6b", "Mixed_6c", "Mixed_6d", "Mixed_6e"]
        )
    },
    **{f"blocks.3.{i}": n for i, n in enumerate(["Mixed_7a", "Mixed_7b", "Mixed_7c"])},
}


def random_fid_inception(seed: int = 0):
    """pytorch-fid's ``InceptionV3()`` (pool3 features) with random weights and batch-norm
    statistics instead of the downloaded ones, in eval mode; returns ``(model, state_dict)`` with
    the weights file's tensor names (plus its 1008-class ``fc``)."""
    import torch

    fid = load_pytorch_fid()
    real_load = torch.nn.Module.load_state_dict
    real_url = fid.load_state_dict_from_url
    fid.load_state_dict_from_url = lambda *a, **k: None  # nothing is downloaded
    torch.nn.Module.load_state_dict = lambda self, *a, **k: None
    try:
        model = fid.InceptionV3()
    finally:
        torch.nn.Module.load_state_dict = real_load
        fid.load_state_dict_from_url = real_url
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, t in model.state_dict().items():
            if name.endswith("num_batches_tracked"):
                continue
            if name.endswith("conv.weight"):
                fan_in = t[0].numel()
                t.copy_(torch.randn(t.shape, generator=gen) * (2.0 / fan_in) ** 0.5)
            elif name.endswith("running_var"):
                t.copy_(torch.rand(t.shape, generator=gen) + 0.5)
            elif name.endswith("bn.weight"):
                t.copy_(torch.rand(t.shape, generator=gen) * 0.5 + 0.75)
            else:  # bn.bias, running_mean
                t.copy_(torch.randn(t.shape, generator=gen) * 0.1)
    model.eval()
    state = {}
    for name, t in model.state_dict().items():
        prefix = ".".join(name.split(".")[:3])
        state[WRAPPER_NAMES[prefix] + name[len(prefix) :]] = t.clone()
    state["fc.weight"] = torch.randn(1008, 2048, generator=gen) * 0.01
    state["fc.bias"] = torch.zeros(1008)
    return model, state
