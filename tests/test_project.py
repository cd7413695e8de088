"""The project's own promises: the CLI, the README's commands, the benchmarks (the examples of the
README and the docs run in tests/test_docs.py)."""

import json
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_cli_help_lists_the_commands_that_exist():
    out = subprocess.run(
        [sys.executable, "-m", "jaxdrive.cli", "--help"], capture_output=True, text=True, check=True
    ).stdout
    assert "usage: jaxdrive" in out and "bench" in out


def test_importing_the_library_loads_neither_matplotlib_nor_transformers():
    """matplotlib draws only the demo's loss plot and transformers serves only the T5 text path:
    both are imported inside the functions that use them."""
    code = (
        "import importlib, pkgutil, sys\n"
        "import jaxdrive, jaxdrive.train, jaxdrive.generate, jaxdrive.cli, jaxdrive.media\n"
        "for pkg in (jaxdrive.train, jaxdrive.generate, jaxdrive.cli):\n"
        "    for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + '.'):\n"
        "        if not m.name.endswith('__main__'):\n"
        "            importlib.import_module(m.name)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('matplotlib', 'transformers')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_t5_path_names_its_extra(monkeypatch, tmp_path):
    from jaxdrive.data.text import precompute_t5

    assert re.search(r'^t5 = \[.*"transformers>=', (ROOT / "pyproject.toml").read_text(), flags=re.M)
    monkeypatch.setitem(sys.modules, "transformers", None)  # as if it were not installed
    with pytest.raises(ImportError, match=re.escape('pip install "jaxdrive[t5]"')):
        precompute_t5(["a caption"], tmp_path)


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    readme_cmd = re.search(r"```bash\n(?:.*\n)*?(pip install -e .*pytest.*)\n```", README).group(1)
    assert readme_cmd in ci.splitlines()


def test_the_suite_installs_the_tpu_compiler():
    # tests/test_tpu_compile.py compiles for TPU topologies through libtpu (the tpu extra)
    readme_cmd = re.search(r"```bash\n(?:.*\n)*?(pip install -e .*pytest.*)\n```", README).group(1)
    assert re.match(r'pip install -e "\.\[[^]]*\btpu\b[^]]*\]"', readme_cmd), readme_cmd
    assert re.search(r'^tpu = \["jax\[tpu\]', (ROOT / "pyproject.toml").read_text(), flags=re.M)


def test_readme_starts_with_the_demo_then_the_tests():
    blocks = re.findall(r"```bash\n(.*?)```", README, flags=re.S)
    assert blocks[0].strip().endswith("pip install -e . && jaxdrive demo")
    assert "python -m pytest" in blocks[1]


def test_sampler_benchmark_prints_json_figures(capsys):
    from jaxdrive.cli import main

    main(["bench", "sampler", "--steps", "2", "--shape", "1", "2", "1", "2", "2", "2", "--hidden", "4"])
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    figures = {r["figure"] for r in rows}
    assert {"compile_time", "scan_time_per_step", "python_loop_time_per_step", "temp_memory"} <= figures
    assert all(r["bench"] == "sampler" and r["steps"] == 2 for r in rows)


def test_sampler_benchmark_compares_the_full_model_with_diffusers(capsys):
    pytest.importorskip("diffusers")
    from jaxdrive.cli import main

    main(
        [
            "bench",
            "sampler",
            "--model",
            "tiny-full",
            "--steps",
            "2",
            "--frames",
            "2",
            "--height",
            "4",
            "--width",
            "4",
            "--repeats",
            "1",
        ]
    )
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    row = next(r for r in rows if r["figure"] == "ratio_to_torch")
    assert row["model"] == "tiny-full/diffusers" and row["steps"] == 2 and row["params"] > 0
    assert row["forward_ms"] > 0 and row["torch_forward_ms"] > 0 and row["loop_ms_per_step"] > 0
    assert row["value"] == pytest.approx(row["torch_forward_ms"] / row["forward_ms"], rel=5e-2)
    assert row["loop_overhead"] == pytest.approx(row["loop_ms_per_step"] / row["forward_ms"] - 1, abs=5e-2)
    assert main(["bench", "sampler", "--model", "tiny", "--steps", "2"]) == 2
    assert "--model: expected full-layout presets" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["bench", "sampler", "--model", "tiny-full", "--steps", "2", "3"])


def test_unknown_benchmark_is_named():
    from jaxdrive.cli import main

    with pytest.raises(SystemExit, match=r"name: expected one of \[.*'sampler'.*\], got 'nope'"):
        main(["bench", "nope"])


def test_ci_runs_the_demo_on_the_base_install():
    """A missing base dependency hides behind the test extra: CI also runs the main job in a
    second virtual environment that has the project alone (``pip install -e .``, no extras)."""
    ci = (ROOT / ".ci" / "run").read_text()
    assert "python3 -m venv .venv-base" in ci
    assert re.search(r"pip install -q (--no-compile )?-e \. \\\n\s+&& jaxdrive demo ", ci)


# Third-party modules that jaxdrive imports only on an optional path, each with the extra that
# installs it: none is reached by demo, train, sample or eval on their default paths.
OPTIONAL_IMPORTS = {"torch": "ref / t5", "diffusers": "ref", "transformers": "t5"}


def test_every_module_jaxdrive_imports_is_a_base_dependency():
    """Every third-party module under ``jaxdrive/`` (imports inside functions included) comes with
    the base install, except :data:`OPTIONAL_IMPORTS`: OpenCV once sat in an extra while the
    demo's last step imported it."""
    import ast
    import importlib.metadata as md
    import tomllib

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    base = {re.split(r"[<>=!~\[; ]", d, maxsplit=1)[0].lower().replace("_", "-") for d in deps}
    owners = md.packages_distributions()
    stdlib = set(sys.stdlib_module_names)
    missing = {}
    for path in sorted((ROOT / "jaxdrive").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top in stdlib or top == "jaxdrive" or top in OPTIONAL_IMPORTS:
                    continue
                dists = {d.lower().replace("_", "-") for d in owners.get(top, [])}
                # a module whose distribution is a dependency of a base dependency counts too
                # (jaxlib comes with jax, etils with orbax): it is on the base install's path
                if not dists & base and not any(_required_by_base(d, base) for d in dists):
                    missing.setdefault(top, str(path.relative_to(ROOT)))
    assert missing == {}


def _required_by_base(dist: str, base: set) -> bool:
    import importlib.metadata as md

    for b in base:
        try:
            requires = md.requires(b) or []
        except md.PackageNotFoundError:
            continue
        names = {
            re.split(r"[<>=!~\[; (]", r, maxsplit=1)[0].lower().replace("_", "-")
            for r in requires
            if "extra ==" not in r
        }
        if dist in names:
            return True
    return False
