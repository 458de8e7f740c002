"""Argument types the command line's commands share (``argparse`` ``type=``), in a module that
imports nothing heavy: ``busgate bench`` must not load zenoh to parse ``--seconds``."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from busgate.schemas.files import EMPTY_PATH

#: The longest wait a command takes (a year): past it a timer cannot be set, and no
#: measurement or watch runs longer.
MAX_SECONDS = 365 * 86400


def named_path(text: str) -> str:
    """A file's or a folder's path, as given; an empty one is refused, where ``Path("")``
    would be the working directory, which nobody means by it."""
    if not text:
        raise argparse.ArgumentTypeError(EMPTY_PATH)
    return text


def seconds(text: str) -> float:
    """A number of seconds above 0 and at most ``MAX_SECONDS`` (NaN and infinity refused)."""
    value = float(text)
    if not 0 < value <= MAX_SECONDS:
        raise argparse.ArgumentTypeError(
            f"must be a number of seconds above 0 and at most {MAX_SECONDS}, not {text}"
        )
    return value


def seconds_from(least: float, most: float) -> Callable[[str], float]:
    """A type of a number of seconds from ``least`` to ``most`` (what the command then hands
    it to takes: ``--timeout`` the SDK's wait), refused by argparse naming the flag."""

    def within(text: str) -> float:
        value = float(text)
        if not least <= value <= most:
            raise argparse.ArgumentTypeError(
                f"must be a number of seconds from {least:g} to {most:g}, not {text}"
            )
        return value

    within.__name__ = "seconds"  # argparse names a value it cannot read by it
    return within
