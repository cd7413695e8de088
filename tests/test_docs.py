"""The documentation: its Python examples run, the site builds without a warning, every module has
an API page, and the README's links lead somewhere."""

import importlib.util
import pathlib
import re
import subprocess
import sys

import pytest

from conftest import shared

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
EXAMPLES = [
    (page.relative_to(ROOT).as_posix(), i, block)
    for page in PAGES
    for i, block in enumerate(re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S))
]


def test_the_docs_hold_python_examples():
    assert EXAMPLES, "no ```python block under README.md or docs/: the examples test would run nothing"


@pytest.mark.slow(seconds=35)
@pytest.mark.parametrize("page, index, block", EXAMPLES, ids=[f"{p}:{i}" for p, i, _ in EXAMPLES])
def test_python_examples_run(page, index, block, tmp_path, tmp_path_factory, monkeypatch):
    monkeypatch.chdir(tmp_path)
    if "data/synth" in block:  # the examples read the dataset the docs' command writes: once a run (30 s)
        from jaxdrive.cli import main

        def build(folder):
            assert main(["data", "synth", "--out", str(folder / "synth"), "--scenes", "16", "--frames", "33"]) == 0

        (tmp_path / "data").mkdir()
        (tmp_path / "data" / "synth").symlink_to(shared(tmp_path_factory, "docs_synth", build) / "synth")
    if "configs/" in block:  # examples run from a checkout, where configs/ is at hand
        (tmp_path / "configs").symlink_to(ROOT / "configs")
    if "CogVideoX-2b/vae" in block:  # the import example reads a diffusers VAE: a tiny random one
        diffusers = pytest.importorskip("diffusers")
        diffusers.AutoencoderKLCogVideoX(
            block_out_channels=(8, 8, 16),
            latent_channels=4,
            layers_per_block=1,
            norm_num_groups=4,
            down_block_types=("CogVideoXDownBlock3D",) * 3,
            up_block_types=("CogVideoXUpBlock3D",) * 3,
        ).save_pretrained("CogVideoX-2b/vae")
    exec(compile(block, f"{page} python block {index}", "exec"), {})


@pytest.mark.slow(seconds=4)
def test_the_site_builds_without_a_warning(tmp_path):
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip('mkdocs is not installed: pip install -e ".[docs]" (the test extra includes it)')
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "mkdocs",
            "build",
            "--strict",
            "--config-file",
            str(ROOT / "mkdocs.yml"),
            "--site-dir",
            str(tmp_path / "site"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr[-4000:]
    assert (tmp_path / "site" / "api" / "flow" / "index.html").is_file()


def test_every_module_has_an_api_page():
    """The API pages list the modules one by one (``::: jaxdrive.x.y``): a new module needs its line."""
    documented = set(
        re.findall(
            r"^::: (jaxdrive[\w.]*)", "\n".join(p.read_text() for p in (ROOT / "docs" / "api").glob("*.md")), flags=re.M
        )
    )
    modules = {
        ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        for p in (ROOT / "jaxdrive").rglob("*.py")
        if p.name != "__main__.py"
    }
    assert sorted(modules - documented) == []
    assert sorted(documented - modules) == []


def test_the_readmes_links_lead_to_files():
    """Relative links, which GitHub shows as they are (the site's own links are checked by the build)."""
    for readme in (ROOT / "README.md", ROOT / "configs" / "README.md", ROOT / "launch" / "README.md"):
        for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", readme.read_text()):
            if not re.match(r"[a-z]+:", target):
                assert (readme.parent / target).exists(), f"{readme.relative_to(ROOT)}: {target}"


def test_the_references_page_cites_every_paper_at_its_version():
    from jaxdrive import references

    page = (ROOT / "docs" / "references.md").read_text()
    for paper in references.PAPERS.values():
        assert paper.arxiv in page and paper.title in page and paper.authors in page, paper.name
