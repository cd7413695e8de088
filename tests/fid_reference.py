"""pytorch-fid's FID Inception, importable beside the CPU torch wheel, for the parity tests.

pytorch-fid builds its network from torchvision's Inception modules, and torchvision's compiled
extension does not load beside the CPU torch wheel (``operator torchvision::nms does not exist``
on ``import torchvision``). The modules themselves are pure Python: this loads
``torchvision/models/inception.py`` from the installed wheel by its path, under a stand-in
``torchvision`` package that provides the few names it imports (weight enums and logging the
reference never uses), and then imports ``pytorch_fid.inception`` against it. Nothing of
jaxdrive is involved.
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


def load_pytorch_fid():
    """``pytorch_fid.inception`` (its ``InceptionV3``), with torchvision's Inception modules."""
    if "pytorch_fid.inception" in sys.modules:
        return sys.modules["pytorch_fid.inception"]
    spec = importlib.util.find_spec("torchvision")         # locates the package without importing it
    root = Path(spec.submodule_search_locations[0])
    from importlib.metadata import version
    tv = _stub("torchvision", __version__=version("torchvision"), __path__=[str(root)])
    models = _stub("torchvision.models", __path__=[str(root / "models")])
    tv.models = models
    _stub("torchvision.transforms", __path__=[])
    _stub("torchvision.transforms._presets", ImageClassification=object)
    _stub("torchvision.utils", _log_api_usage_once=lambda *a, **k: None)
    _stub("torchvision.models._api", register_model=_decorator_factory, Weights=_Weights, WeightsEnum=_WeightsEnum)
    _stub("torchvision.models._meta", _IMAGENET_CATEGORIES=[])
    _stub("torchvision.models._utils", _ovewrite_named_param=lambda kw, k, v: kw.setdefault(k, v),
          handle_legacy_interface=_decorator_factory)
    file = root / "models" / "inception.py"
    mod_spec = importlib.util.spec_from_file_location("torchvision.models.inception", file)
    inception = importlib.util.module_from_spec(mod_spec)
    sys.modules["torchvision.models.inception"] = inception
    mod_spec.loader.exec_module(inception)
    models.inception = inception
    models.inception_v3 = inception.inception_v3
    import pytorch_fid.inception as fid_inception
    return fid_inception


# pytorch-fid's InceptionV3 wrapper ("blocks.i.j") -> the weights file's names (torchvision's)
WRAPPER_NAMES = {"blocks.0.0": "Conv2d_1a_3x3", "blocks.0.1": "Conv2d_2a_3x3", "blocks.0.2": "Conv2d_2b_3x3",
                 "blocks.1.0": "Conv2d_3b_1x1", "blocks.1.1": "Conv2d_4a_3x3",
                 **{f"blocks.2.{i}": n for i, n in enumerate(["Mixed_5b", "Mixed_5c", "Mixed_5d", "Mixed_6a",
                                                               "Mixed_6b", "Mixed_6c", "Mixed_6d", "Mixed_6e"])},
                 **{f"blocks.3.{i}": n for i, n in enumerate(["Mixed_7a", "Mixed_7b", "Mixed_7c"])}}


def random_fid_inception(seed: int = 0):
    """pytorch-fid's ``InceptionV3()`` (pool3 features) with random weights and batch-norm
    statistics instead of the downloaded ones, in eval mode; returns ``(model, state_dict)`` with
    the weights file's tensor names (plus its 1008-class ``fc``)."""
    import torch
    fid = load_pytorch_fid()
    real_load = torch.nn.Module.load_state_dict
    real_url = fid.load_state_dict_from_url
    fid.load_state_dict_from_url = lambda *a, **k: None           # nothing is downloaded
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
            else:                                                  # bn.bias, running_mean
                t.copy_(torch.randn(t.shape, generator=gen) * 0.1)
    model.eval()
    state = {}
    for name, t in model.state_dict().items():
        prefix = ".".join(name.split(".")[:3])
        state[WRAPPER_NAMES[prefix] + name[len(prefix):]] = t.clone()
    state["fc.weight"] = torch.randn(1008, 2048, generator=gen) * 0.01
    state["fc.bias"] = torch.zeros(1008)
    return model, state
