"""The diffusion transformer: the model, its layers, its config and presets, its controls.

- ``model.py``: :class:`~jaxdrive.models.dit.model.DiT`, patchify, the parameter count;
- ``blocks.py``: the layers (STDiT-3 / STDiT-2 factorized, CogVideoX full) and their attentions;
- ``config.py``: :class:`~jaxdrive.models.dit.config.DiTConfig` and its controls, checked;
- ``controls.py``: the encoders of the driving controls (cameras, boxes, map, trajectory, text, ...);
- ``conditions.py``: :class:`~jaxdrive.models.dit.conditions.Conditions`, all the controls' inputs
  as one typed pytree, checked against a config;
- ``layout.py``: the projected layout control (boxes and the map ray cast into every camera);
- ``inputs.py``: example inputs of any config, for shapes, tests and benchmarks;
- ``presets.py``: the papers' sizes (``preset(name, **overrides)``).

This package re-exports what the module ``jaxdrive.models.dit`` held before it became one
(``from jaxdrive.models.dit import DiT``); jaxdrive itself imports from the modules.
"""

from jaxdrive.models.dit.config import DiTConfig
from jaxdrive.models.dit.inputs import example_inputs
from jaxdrive.models.dit.model import POLICIES as POLICIES  # public, outside the old __all__: still re-exported
from jaxdrive.models.dit.model import DiT, param_count, patchify, unpatchify
from jaxdrive.models.dit.model import reference_input as reference_input  # likewise

__all__ = ["DiT", "DiTConfig", "example_inputs", "param_count", "patchify", "unpatchify"]
