"""The config argument: ``--config FILE.py:key=value,...`` reaches ``get_config(arg)``, which
reads it with ``parse_arg`` (typed by the defaults; unknown keys and wrong types name the key)."""

from pathlib import Path

import pytest

from jaxdrive.config import DataConfig, load_config, parse_arg, split_config_path

TINY = Path(__file__).resolve().parents[1] / "configs" / "tiny.py"

WITH_ARG = """
from jaxdrive.config import DataConfig, parse_arg

def get_config(arg=None):
    a = parse_arg(arg, size="small", stage=1, lr=1e-4, flip=False)
    frames = {"tiny": 5, "small": 9}[a.size]
    return DataConfig(frames=frames, batch_size=a.stage, drop_prob=a.lr, path=f"{a.size}-{a.stage}-{a.flip}")
"""


@pytest.fixture
def config_file(tmp_path):
    path = tmp_path / "sized.py"
    path.write_text(WITH_ARG)
    return path


def test_the_text_after_the_colon_reaches_get_config(config_file):
    c = load_config(f"{config_file}:size=tiny,stage=2")
    assert (c.frames, c.batch_size, c.path) == (5, 2, "tiny-2-False")
    assert load_config(config_file) == DataConfig(frames=9, batch_size=1, drop_prob=1e-4, path="small-1-False")
    # overrides apply after the argument
    c = load_config(f"{config_file}:stage=3,flip", ["frames=17"])
    assert (c.frames, c.batch_size, c.path) == (17, 3, "small-3-True")


def test_a_wrong_key_names_the_key_and_the_allowed_ones(config_file):
    with pytest.raises(
        ValueError,
        match=r"config argument: unknown key 'sise'; "
        r"expected one of \['flip', 'lr', 'size', 'stage'\]",
    ):
        load_config(f"{config_file}:sise=tiny,stage=2")


def test_a_wrong_type_names_the_key_the_type_and_the_value(config_file):
    with pytest.raises(ValueError, match=r"config argument stage: expected int, got 'two'"):
        load_config(f"{config_file}:size=tiny,stage=two")
    with pytest.raises(ValueError, match=r"config argument flip: expected a bool \(true/false\), got 'maybe'"):
        load_config(f"{config_file}:flip=maybe")


def test_parse_arg_converts_to_the_defaults_types():
    a = parse_arg(
        "stage=2,lr=1,name=x,flag,off=false,opt=gs://b/c", stage=1, lr=0.5, name="", flag=False, off=True, opt=None
    )
    assert vars(a) == {"stage": 2, "lr": 1.0, "name": "x", "flag": True, "off": False, "opt": "gs://b/c"}
    assert type(a.lr) is float
    assert vars(parse_arg(None, stage=1)) == vars(parse_arg("", stage=1)) == {"stage": 1}
    with pytest.raises(ValueError, match=r"config argument stage: expected stage=value, got 'stage'"):
        parse_arg("stage", stage=1)
    with pytest.raises(ValueError, match=r"key 'stage' given twice"):
        parse_arg("stage=1,stage=2", stage=1)
    with pytest.raises(ValueError, match=r"default of 'sizes': expected a bool, int, float, str or None, got tuple"):
        parse_arg("", sizes=(1, 2))


def test_split_config_path_keeps_colons_in_values():
    assert split_config_path("configs/x.py:data=gs://b/c,n=1") == (Path("configs/x.py"), "data=gs://b/c,n=1")
    assert split_config_path(Path("configs/x.py")) == (Path("configs/x.py"), None)
    assert split_config_path("configs/x.py:") == (Path("configs/x.py"), "")
    with pytest.raises(ValueError, match=r"config: expected a path FILE.py\[:key=value,...\], got int"):
        split_config_path(3)


def test_an_argument_to_a_config_without_one_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"get_config\(\) takes no argument\), got the argument 'size=tiny'"):
        load_config(f"{TINY}:size=tiny")
    needs = tmp_path / "needs.py"
    needs.write_text("def get_config(arg):\n    return arg\n")
    with pytest.raises(ValueError, match=r"its get_config takes an argument"):
        load_config(needs)
    assert load_config(f"{needs}:a=1") == "a=1"


def test_the_cli_reports_a_bad_config_argument(config_file, tmp_path, capsys):
    from jaxdrive.cli import main

    assert main(["train", "--config", f"{config_file}:size=tiny,sise=2", "--workdir", str(tmp_path)]) == 2
    assert "jaxdrive train: error: --config argument: unknown key 'sise'" in capsys.readouterr().err


def test_mixed_frame_rate_keys_parse_and_are_checked():
    from jaxdrive.config_checks import check_sections

    c = load_config(TINY, ["data.rate_head=4", "data.rate_strides=1,6,12", "model.controls.frame_time=true"])
    assert (c.data.rate_head, c.data.rate_strides, c.model.controls.frame_time) == (4, (1, 6, 12), True)
    check_sections(c)
    for sets, match in [
        (["data.rate_head=-1"], r"data.rate_head: expected an integer >= 0, got -1"),
        ([f"data.rate_head={c.data.frames + 1}"], rf"data.rate_head: expected at most data.frames = {c.data.frames}"),
        (["data.rate_strides=2,0"], r"data.rate_strides: expected positive integers, got \(2, 0\)"),
        (
            ["data.rate_strides=2,4", "latents.precomputed=true"],
            r"data.rate_strides: expected \(\) with latents.precomputed",
        ),
        (
            ["data.rate_strides=2", "flow.distill_teacher=runs/fine", "flow.distill_segment_len=3"],
            r"data.rate_strides: expected \(\) with flow.distill_teacher",
        ),
    ]:
        with pytest.raises(ValueError, match=match):
            check_sections(load_config(TINY, sets))
