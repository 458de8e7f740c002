"""The benchmarks' command lines: ``--help`` tells what a script measures and what it takes,
and a bad argument is refused in one line, before anything runs (a new user's ``--help``
ran a minute of benchmark, or ended in a traceback of ``int('--help')``)."""

from __future__ import annotations

import argparse


def arguments(doc: str | None, *positionals: tuple[str, type, object, str]) -> argparse.Namespace:
    """The script's arguments: each of ``positionals`` (name, type, default, what it is)
    optional, in order; ``doc`` (the script's docstring) is its ``--help``."""
    parser = argparse.ArgumentParser(
        description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    for name, kind, default, what in positionals:
        parser.add_argument(
            name, type=kind, nargs="?", default=default, help=f"{what} (default {default})"
        )
    return parser.parse_args()
