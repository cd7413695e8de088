"""Options that several commands share, worded once."""

from __future__ import annotations


def add_config(parser, what: str, *, required: bool = True) -> None:
    """``--config FILE.py[:ARG]``: ``what`` the file is for, then the argument convention."""
    parser.add_argument("--config", required=required, metavar="FILE.py[:ARG]",
                        help=f"{what}; FILE.py:key=value,... passes the text after the colon to its "
                             f"get_config (big_vision's convention)")


def add_progress(parser, what: str) -> None:
    """``--no-progress``: no tqdm bar over ``what`` (on stderr; ``--quiet`` leaves the bar on)."""
    parser.add_argument("--no-progress", action="store_true", help=f"no progress bar over {what}")


def add_sampling(parser, *, cfg: float) -> None:
    """What sampling a run's checkpoint takes: ``--steps``, ``--cfg`` (default ``cfg``), ``--seed``,
    ``--mesh``, ``--no-ema``, ``--set``."""
    parser.add_argument("--steps", type=int, help="sampling steps (default: the run's train.sample_steps)")
    parser.add_argument("--cfg", type=float, default=cfg, help="classifier-free guidance scale (1: none)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mesh", help="mesh axis sizes for sampling")
    parser.add_argument("--no-ema", action="store_true", help="sample with the raw parameters, not the EMA")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE")
