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
