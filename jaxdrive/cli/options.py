"""What several commands share: options worded once, the config they give, and starting JAX."""

from __future__ import annotations

import os
import re

# Library errors name the library's argument ("fine_workdir: ..."); these are the ones whose
# command-line option is not the argument's own name with dashes (see ``as_flags``).
LIBRARY_NAMES = {
    "models.main": "--workdir",
    "models.fine": "--fine-workdir",
    "override": "--set",
}
_LEADING_NAME = re.compile(r"[A-Za-z_][\w.]*(?=:| [^ :]+:)")  # "name: ..." or "name key: ..."


def add_config(parser, what: str, *, required: bool = True) -> None:
    """``--config FILE.py[:ARG]``: ``what`` the file is for, then the argument convention."""
    parser.add_argument(
        "--config",
        required=required,
        metavar="FILE.py[:ARG]",
        help=f"{what}; FILE.py:key=value,... passes the text after the colon to its "
        f"get_config (big_vision's convention)",
    )


def add_progress(parser, what: str) -> None:
    """``--no-progress``: no tqdm bar over ``what`` (on stderr; ``--quiet`` leaves the bar on)."""
    parser.add_argument("--no-progress", action="store_true", help=f"no progress bar over {what}")


def add_sampling(parser, *, sweep: bool = False) -> None:
    """What sampling a run's checkpoint takes: ``--steps``, ``--cfg`` (default: the run's
    ``sample.cfg``; with ``sweep`` a comma-separated list of scales), ``--cfg-boxes``,
    ``--cfg-route``, ``--seed``, ``--mesh``, ``--no-ema``, ``--set``."""
    parser.add_argument("--steps", type=int, help="sampling steps (default: the run's train.sample_steps)")
    if sweep:
        parser.add_argument(
            "--cfg",
            help="classifier-free guidance scales, comma-separated, e.g. 1,2,4: every "
            "strategy is scored at each (rows STRATEGY@cfgS); default: the run's "
            "sample.cfg",
        )
    else:
        parser.add_argument(
            "--cfg",
            type=float,
            help="classifier-free guidance scale (1: none, 0: unconditional; default: the run's sample.cfg)",
        )
    parser.add_argument(
        "--cfg-boxes",
        type=float,
        help="the 3D boxes' own guidance scale (compositional guidance: "
        "one more forward per step; needs a model trained with boxes)",
    )
    parser.add_argument(
        "--cfg-route",
        type=float,
        help="the ego route's own guidance scale (waypoints, trajectory and warp, which training drops together)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mesh", help="mesh axis sizes for sampling")
    parser.add_argument("--no-ema", action="store_true", help="sample with the raw parameters, not the EMA")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE")


def parse_scales(text) -> list:
    """``--cfg`` of ``jaxdrive eval``: ``"1,2,4"`` -> ``[1.0, 2.0, 4.0]`` (each a guidance scale
    >= 0, no repeats); None -> ``[None]`` (the run's ``sample.cfg``)."""
    from jaxdrive.generate.guidance import check_scale

    if text is None:
        return [None]
    out = []
    for part in str(text).split(","):
        try:
            value = float(part)
        except ValueError:
            raise ValueError(f"--cfg: expected guidance scales like 1,2,4, got {text!r}") from None
        out.append(check_scale("--cfg", value))
    if len(set(out)) != len(out):
        raise ValueError(f"--cfg: expected distinct scales, got {text!r}")
    return out


def guidance_options(args, specs) -> dict:
    """The per-control scales of ``--cfg-boxes`` / ``--cfg-route`` checked against every run's
    :class:`jaxdrive.generate.samples.Sampling` in ``specs`` (and ``--cfg`` when it is one
    number): ``ValueError`` naming the option before anything compiles. Returns control -> scale."""
    from jaxdrive.generate.guidance import check_controls, check_scale

    if isinstance(args.cfg, (int, float)):
        check_scale("--cfg", args.cfg)
    controls = {"boxes": args.cfg_boxes, "route": args.cfg_route}
    for spec in specs:
        if spec is not None:
            check_controls(spec.model, spec.data.drop_prob, controls, option=lambda c: f"--cfg-{c}")
    return {k: v for k, v in controls.items() if v is not None}


def config_with_mesh(config, mesh: str):
    """``config`` with its mesh replaced by the ``--mesh`` spec ``mesh`` (e.g. ``data=2,seq=4``;
    axes it leaves out are 1)."""
    from jaxdrive.config import override
    from jaxdrive.parallel import parse_mesh_spec

    sizes = parse_mesh_spec(mesh)
    for k in ("data", "fsdp", "seq", "tensor"):
        config = override(config, f"mesh.{k}={sizes.get(k, 1)}")
    return config


def start_jax() -> str:
    """Before JAX starts: honour ``JAXDRIVE_CPU_DEVICES`` (fake CPU devices with gloo collectives,
    set by ``launch/local.py --cpu-devices``), then start the multi-process runtime from the
    environment (:func:`jaxdrive.parallel.initialize_distributed`: explicit ``JAXDRIVE_*``
    variables, SLURM or a TPU VM pod)."""
    import jax

    n = os.environ.get("JAXDRIVE_CPU_DEVICES")
    if n:
        if not n.isdigit() or int(n) < 1:
            raise ValueError(f"JAXDRIVE_CPU_DEVICES: expected a positive integer, got {n!r}")
        jax.config.update("jax_platforms", "cpu")
        jax.config.update("jax_num_cpu_devices", int(n))
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    from jaxdrive import compile_cache

    compile_cache.enable("default")  # before anything compiles; a run's train.compile_cache re-points it
    from jaxdrive.parallel import initialize_distributed

    return initialize_distributed()


def load_config(path, mesh: str | None, sets, extra=()):
    """The config of ``--config path`` with the ``--set`` assignments ``sets`` (after ``extra``)
    and the ``--mesh`` spec ``mesh``, when given."""
    from jaxdrive.config import load_config as load

    config = load(path, list(extra) + list(sets or []))
    return config_with_mesh(config, mesh) if mesh else config


def _option_names(parser) -> dict:
    """dest -> its first long option (``--fine-workdir``) over ``parser`` and its subcommands.
    argparse keeps its actions in ``_actions``: there is no public accessor."""
    names = {}
    for action in parser._actions:
        if isinstance(action.choices, dict):  # a sub-command group: its parsers' options too
            for sub in action.choices.values():
                names.update(_option_names(sub))
        longs = [o for o in action.option_strings if o.startswith("--")]
        if longs and action.dest not in names:
            names[action.dest] = longs[0]
    return names


def as_flags(message: str, parser) -> str:
    """A library error as the command line's: the leading library argument of ``message``
    (``segment_batch: ...``, ``models.fine: ...``, ``override a.b: ...``) becomes the option of
    ``parser`` (the invoked command) that sets it (``--segment-batch``), so a user reads the flag
    they typed. Names the command has no option for (config keys such as ``flow.jdc_slope``) stay."""
    match = _LEADING_NAME.match(message)
    if not match:
        return message
    name = match.group()
    flag = LIBRARY_NAMES.get(name) or _option_names(parser).get(name)
    return flag + message[match.end() :] if flag else message
