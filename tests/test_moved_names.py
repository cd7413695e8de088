"""The module paths that the DiT and VAE packages replaced still import, for one release: each
warns (a DeprecationWarning naming the new home, at the importing line) and gives the new home's
objects. The packages give what the modules ``jaxdrive.models.dit`` and ``.vae`` gave, and
nothing in the project imports an old path any more."""

import ast
import importlib
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MOVED = {
    "jaxdrive.models.dit_blocks": "jaxdrive.models.dit.blocks",
    "jaxdrive.models.dit_config": "jaxdrive.models.dit.config",
    "jaxdrive.models.dit_controls": "jaxdrive.models.dit.controls",
    "jaxdrive.models.dit_inputs": "jaxdrive.models.dit.inputs",
    "jaxdrive.models.dit_presets": "jaxdrive.models.dit.presets",
    "jaxdrive.models.layout": "jaxdrive.models.dit.layout",
    "jaxdrive.models.vae_layers": "jaxdrive.models.vae.layers",
    "jaxdrive.models.vae_stream": "jaxdrive.models.vae.stream",
}


@pytest.mark.parametrize("old, new", sorted(MOVED.items()))
def test_an_old_path_warns_and_gives_the_new_homes_objects(old, new, monkeypatch):
    home = importlib.import_module(new)
    monkeypatch.delitem(sys.modules, old, raising=False)  # imported afresh: it warns at import
    with pytest.warns(DeprecationWarning, match=re.escape(f"{old} moved to {new}")) as caught:
        __import__(old)
    assert [w.filename for w in caught if w.category is DeprecationWarning] == [__file__]  # the importer's line
    shim = sys.modules[old]
    names = [n for n in vars(home) if not n.startswith("__")]
    assert all(getattr(shim, n) is getattr(home, n) for n in names)  # private names too
    public = {n for n in names if not n.startswith("_")}
    namespace = {}
    exec(f"from {old} import *", namespace)
    assert public <= namespace.keys()


def test_the_public_conditions_path_stays_without_a_warning():
    """``jaxdrive.models.conditions`` is the path the design fixes: an alias, not deprecated."""
    import warnings

    home = importlib.import_module("jaxdrive.models.dit.conditions")
    sys.modules.pop("jaxdrive.models.conditions", None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        alias = importlib.import_module("jaxdrive.models.conditions")
    assert alias.Conditions is home.Conditions and alias.PER_FRAME is home.PER_FRAME


@pytest.mark.parametrize(
    "package, home, names",
    [
        (
            "jaxdrive.models.dit",
            "jaxdrive.models.dit.model",
            [
                "DiT",
                "DiTConfig",
                "POLICIES",
                "example_inputs",
                "param_count",
                "patchify",
                "reference_input",
                "unpatchify",
            ],
        ),
        (
            "jaxdrive.models.vae",
            "jaxdrive.models.vae.model",
            ["MODES", "CausalVAE", "Decoder3D", "Encoder3D", "VAEConfig", "chunk_plan", "fold_views", "tiled_apply"],
        ),
    ],
)
def test_the_packages_give_what_the_modules_gave(package, home, names):
    package, home = importlib.import_module(package), importlib.import_module(home)
    assert all(getattr(package, n) is getattr(home, n) for n in names)


@pytest.mark.slow(seconds=4)
def test_nothing_in_the_project_imports_an_old_path():
    """Imports in the package, the configs and the tests (the shims and this file aside), and the
    Python examples of the docs."""
    shims = {ROOT / (old.replace(".", "/") + ".py") for old in MOVED}
    found = []
    for path in sorted(
        {*ROOT.glob("jaxdrive/**/*.py"), *ROOT.glob("configs/*.py"), *ROOT.glob("tests/*.py")}
        - shims
        - {Path(__file__)}
    ):
        for node in ast.walk(ast.parse(path.read_text())):
            modules = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""] + [f"{node.module}.{a.name}" for a in node.names]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            found += [f"{path.relative_to(ROOT)}:{node.lineno} {m}" for m in modules if m in MOVED]
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        for block in re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S):
            found += [f"{page.relative_to(ROOT)}: {old}" for old in MOVED if re.search(rf"\b{re.escape(old)}\b", block)]
    assert found == []
