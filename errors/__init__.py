"""The one exception tree of busgate, at the package's top: ``busgate.errors``.

Every layer imports it (it imports nothing of busgate), so every layer raises and catches the
same classes; the codecs' own errors (``busgate.codecs.errors``) and the SDK's
(``busgate.client.errors``) join it. Rules of this file:

1. Every class carries a stable ``code``: the zenoh API puts it verbatim into error replies
   (``busgate.schemas.replies`` maps every exception there, whichever thread raised it),
   so renaming a code is a breaking change. A class is here because something raises it, and
   each class is defined once, in the room of what raises it when only that room does.
2. Exceptions carry structured attributes (device, register, …) besides their message, and
   are raised ``from`` the exception that caused them.
3. Where a class has a natural builtin twin it inherits from it too (``CommandError`` is a
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


class FamilyError(BusgateError):
    """A registered device family lacks a part, or a part is not what the registry needs
    (``busgate.gateway.drivers.families``): a fault of the installation, found at start."""

    code = "family_error"


class CommandError(BusgateError, ValueError):
    """A client's command is malformed or not allowed."""

    code = "bad_command"


class RefusedError(BusgateError):
    """The gateway will not send what was asked; ``code`` says why (``claimed``,
    ``estopped``, ``unknown_device``, ``busy`` …) and the message how to go on."""

    code = "refused"

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class BusyError(BusgateError):
    """The bus's command queue is full, or a command found no room before its deadline;
    nothing was sent: try again."""

    code = "busy"


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


class DeviceRefusedError(DeviceError):
    """The device answered that it did not do it (a ZLAC706's ``FF``: no such register)."""

    code = "device_refused"
