"""The codecs' own errors, in busgate's one exception tree (``busgate.errors``).

Rules of this file: only what a codec raises is here; each class joins the tree, and carries
its stable ``code`` (``busgate.errors`` rule 1). The classes this module held before the tree
moved up are still found here by their old names, with a ``DeprecationWarning``
(``__getattr__``), so that code written against them runs on.
"""

from __future__ import annotations

import warnings

import busgate.errors
from busgate.errors import BusgateError, CommandError

#: What moved from here to ``busgate.errors`` (``BusgateError`` and ``CommandError`` are still
#: imported above, for the codecs' own classes).
_MOVED = frozenset(
    {
        "ConfigError",
        "BusUnavailableError",
        "BusIOError",
        "DeviceError",
        "DeviceTimeoutError",
        "RefusedError",
    }
)


def __getattr__(name: str) -> object:
    if name in _MOVED:
        warnings.warn(
            f"busgate.codecs.errors.{name} is busgate.errors.{name}: import it from there",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(busgate.errors, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class CodecError(BusgateError):
    """A wire-protocol problem."""

    code = "codec_error"


class EncodeError(CodecError, CommandError):
    """A value cannot be put on the wire: outside the manual's range or of the wrong shape.

    It is a refused command too (whoever catches ``CommandError`` catches this), with a code
    of its own. ``field`` names what was wrong, ``value`` is what was given.
    """

    code = "out_of_range"

    def __init__(self, message: str, *, field: str = "", value: object = None) -> None:
        super().__init__(message)
        self.field = field
        self.value = value


class CdrError(CodecError):
    """Bytes that are not a valid CDR payload of the type being read (a ROS 2 message:
    ``busgate.codecs.ros2``); it never leaves ``messages.decode``, which answers ``None``."""

    code = "malformed_cdr"
