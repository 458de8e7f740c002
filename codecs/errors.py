"""The codecs' own errors, in busgate's one exception tree (``busgate.errors``).

Rules of this file: only what a codec raises is here; each class joins the tree, and carries
its stable ``code`` (``busgate.errors`` rule 1).
"""

from __future__ import annotations

from busgate.errors import BusgateError, CommandError


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
