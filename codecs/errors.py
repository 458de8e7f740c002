"""The one exception tree of busgate.

It lives in the lowest layer (codecs) so that every layer above can raise and catch the
same classes. Rules of this file:

1. Every class carries a stable ``code``: the zenoh API puts it verbatim into error replies
   (``busgate.gateway.api.errors`` maps every exception there, whichever thread raised it),
   so renaming a code is a breaking change. A class is here because something raises it.
2. Exceptions carry structured attributes (device, register, …) besides their message, and
   are raised ``from`` the exception that caused them.
3. Where a class has a natural builtin twin it inherits from it too (``EncodeError`` is a
   ``ValueError``), so generic callers can catch what they already know.
"""

from __future__ import annotations


class BusgateError(Exception):
    """Root of every error busgate raises on purpose."""

    code = "internal"


class ConfigError(BusgateError, ValueError):
    """The configuration is invalid; ``path`` names the key (``buses[0].baudrate``)."""

    code = "config_invalid"

    def __init__(self, message: str, *, path: str = "") -> None:
        super().__init__(message)
        self.path = path


class CodecError(BusgateError):
    """A wire-protocol problem."""

    code = "codec_error"


class CommandError(BusgateError, ValueError):
    """A client's command is malformed or not allowed."""

    code = "bad_command"


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


class BusUnavailableError(BusgateError, ConnectionError):
    """The bus is down: the adapter is gone or cannot be opened."""

    code = "bus_unavailable"


class BusIOError(BusgateError, OSError):
    """Reading or writing the bus failed."""

    code = "bus_io"


class DeviceError(BusgateError):
    """A device did not do what was asked (the base of what a device's silence raises)."""

    code = "device_error"

    def __init__(self, message: str, *, device: str = "", device_id: int | None = None) -> None:
        super().__init__(message)
        self.device = device
        self.device_id = device_id


class DeviceTimeoutError(DeviceError, TimeoutError):
    """The device did not answer in time."""

    code = "device_timeout"


class RefusedError(BusgateError):
    """The gateway will not send what was asked; ``code`` says why (``claimed``,
    ``estopped``, ``unknown_device``, ``busy`` …) and the message how to go on."""

    code = "refused"

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
