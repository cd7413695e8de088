"""Options that several commands share, worded once."""

from __future__ import annotations


def add_config(parser, what: str, *, required: bool = True) -> None:
    """``--config FILE.py[:ARG]``: ``what`` the file is for, then the argument convention."""
    parser.add_argument("--config", required=required, metavar="FILE.py[:ARG]",
                        help=f"{what}; FILE.py:key=value,... passes the text after the colon to its "
                             f"get_config (big_vision's convention)")
