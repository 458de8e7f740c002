"""What a client of busgate can meet, as exceptions: one class per error code of the API,
and the failures that happen on the client's side.

Rules of this file:

1. The root is busgate's one ``BusgateError`` (``busgate.errors``): a program catches
   every failure of the SDK, the gateway's refusals included, with one ``except``.
2. Every stable code of ``{"ok": false, "error": {"code": …}}`` (``schemas.api.ERROR_CODES``)
   has its own subclass of ``GatewayError``, made from that list, so a code added to the API
   has its class without an edit here; ``error_for(code)`` finds it. Each carries ``.code``
   and ``.message`` (cut to the longest a gateway sends, ``MAX_MESSAGE``: a peer's may be
   megabytes); ``ClaimedError`` also the ``.holder`` its message names. A code this version
   does not know is told as it came, cut to ``MAX_CODE``.
3. What fails before a gateway could answer has its own classes: ``ConnectError`` (no zenoh
   session), ``NoAnswerError`` (nobody answered in time), ``AmbiguousError`` (a bare name that
   several gateways have). ``ClaimLostError`` is both: the SDK raises it when it knows a claim
   is lost, and it is the class of the gateway's ``not_claimed``. ``UnknownGatewayError``
   (``unknown_gateway``) is the SDK's own finding, in the family of ``unknown_device``: no
   gateway of the name given is up; ``error_for`` finds it too. No ``zenoh.ZError`` reaches
   a user: the modules that call zenoh turn it into one of these. An argument the SDK
   refuses before anything is sent (a name that would address others, a timeout that is no
   number) is busgate's ``CommandError``, as the gateway's own refusal of a bad argument is.
"""

from __future__ import annotations

import re
from typing import Any

from busgate.errors import BusgateError, CommandError
from busgate.schemas.api import ERROR_CODES, MAX_MESSAGE
from busgate.schemas.validation import cut


class GatewayError(BusgateError):
    """A gateway refused a command or failed to carry it out: ``code`` says why (stable),
    ``message`` says it for people (it may change between versions)."""

    code = "internal"

    def __init__(self, message: str, *, gateway: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.gateway = gateway


class ClaimedError(GatewayError):
    """The device is claimed by another client, ``holder`` (``None`` if the message does not
    name it)."""

    code = "claimed"

    def __init__(self, message: str, *, gateway: str | None = None) -> None:
        super().__init__(message, gateway=gateway)
        holder = re.search(r"claimed by '([A-Za-z0-9_-]+)'", message)
        self.holder = holder.group(1) if holder else None


class ClaimLostError(GatewayError):
    """A claim this client took is gone (its gateway went away or restarted, a renewal was
    refused, or it lapsed): what the client meant to do under it is refused, by the SDK when
    it knows, else by the gateway (``not_claimed``), until the client claims again. Reads and
    stops still go through."""

    code = "not_claimed"


class UnknownGatewayError(GatewayError):
    """No gateway of the name given is up (none answers under it): a misspelt name, or a
    gateway that is down. ``gateway`` is the name; ``gateways`` those that do answer."""

    code = "unknown_gateway"

    def __init__(
        self, message: str, *, gateway: str | None = None, gateways: list[str] | None = None
    ) -> None:
        super().__init__(message, gateway=gateway)
        self.gateways = gateways or []


def _class_name(code: str) -> str:
    """``out_of_range`` → ``OutOfRangeError``."""
    return "".join(part.capitalize() for part in code.split("_")) + "Error"


def _error_classes() -> dict[str, type[GatewayError]]:
    classes: dict[str, type[GatewayError]] = {
        "claimed": ClaimedError,
        "not_claimed": ClaimLostError,
        "unknown_gateway": UnknownGatewayError,
    }
    for code in ERROR_CODES:
        if code not in classes:
            doc = f"The gateway answered ``{code}``."
            classes[code] = type(_class_name(code), (GatewayError,), {"code": code, "__doc__": doc})
    return classes


#: Each error code of the API and its class (and the SDK's own ``unknown_gateway``).
ERROR_CLASSES: dict[str, type[GatewayError]] = _error_classes()
globals().update({cls.__name__: cls for cls in ERROR_CLASSES.values()})


def error_for(code: str) -> type[GatewayError]:
    """The class of error ``code`` (``GatewayError`` itself for a code this version does not
    know: a newer gateway's)."""
    return ERROR_CLASSES.get(code, GatewayError)


#: The longest unknown code told as it came (every code of the API is under 20 characters).
MAX_CODE = 64


def raise_for(error: Any, *, gateway: str | None = None) -> None:
    """Raise the error an ``{"ok": false}`` reply's ``error`` object describes."""
    if not isinstance(error, dict):
        raise GatewayError("the gateway's reply is not ok and carries no error", gateway=gateway)
    code, message = str(error.get("code", "internal")), str(error.get("message", ""))
    cls = error_for(code)
    exc = cls(cut(message, MAX_MESSAGE - 1), gateway=gateway)
    if cls is GatewayError:
        exc.code = cut(code, MAX_CODE - 1)  # an unknown code is still told as it came
    raise exc


class ConnectError(BusgateError, ConnectionError):
    """A zenoh session could not be opened: nothing listens at the endpoints, a bad endpoint
    or config file, refused credentials (a client's) or a listen address in use (a gateway's)."""

    code = "cannot_connect"

    def __init__(self, message: str, *, unreached: bool = False) -> None:
        super().__init__(message)
        #: zenoh found nobody at the endpoints, and nothing else is known to be wrong (no
        #: account or CA was involved): the usual case is a gateway not started yet.
        self.unreached = unreached


class NoAnswerError(BusgateError, TimeoutError):
    """Nobody answered in time: no gateway has the key, or it is down or cut off."""

    code = "no_answer"


class AmbiguousError(BusgateError, LookupError):
    """A bare device or bus name that several gateways have: name the gateway
    (``"gw1/la1"``). ``gateways`` lists them."""

    code = "ambiguous"

    def __init__(self, message: str, *, gateways: list[str]) -> None:
        super().__init__(message)
        self.gateways = gateways


__all__ = [
    "ERROR_CLASSES",
    "AmbiguousError",
    "BusgateError",
    "ClaimLostError",
    "ClaimedError",
    "CommandError",
    "ConnectError",
    "GatewayError",
    "NoAnswerError",
    "error_for",
    "raise_for",
    *(cls.__name__ for cls in ERROR_CLASSES.values() if cls not in (ClaimedError, ClaimLostError)),
]
