"""What crosses a client's session, apart from the session itself (``core.py``): each reply as
an ``Answer`` and a query's as ``Answers``, the body of the first ok one or the error it is,
a future of what follows from another's result (``then``), the checks of a client's numbers
of seconds, and the JSON every message is sent as.

The models of what gateways publish are ``busgate.schemas``' (closed: every field the gateway
publishes is named and typed there, and ``tests/test_schema_export.py`` holds the gateway to
them), named here for the SDK: a device's joint in its state (``JointState``) and in ``info``
(``JointInfo``), a gateway's joints message (``JointsMessage`` of ``JointReading``s) and a
base's odometry (``Odometry``). A message that does not validate (a field this SDK does not
know, a joint's NaN) or is larger than any a gateway publishes (never parsed)
is left out with a warning naming its gateway, as ``gateways()`` leaves out an ``info``
(``published``); so is one naming another gateway, device or base than the key it came on
(``published_naming``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass
from typing import Any, TypeVar

from pydantic import BaseModel

from busgate.client.errors import NoAnswerError, error_for, raise_for
from busgate.errors import CommandError
from busgate.schemas.api import JointInfo as JointInfo
from busgate.schemas.api import JointReading as JointReading
from busgate.schemas.api import JointsMessage as JointsMessage
from busgate.schemas.bases import Odometry as Odometry
from busgate.schemas.joints import JointState as JointState
from busgate.schemas.payload import MAX_PAYLOAD, MAX_WHOLE_GATEWAY

log = logging.getLogger(__name__)
M = TypeVar("M", bound=BaseModel)


@dataclass(frozen=True, slots=True)
class Answer:
    """One reply to a query: the key it came on, its JSON (text when it is not JSON, or when
    it was too large to read: what it was), and whether it is an ok reply."""

    key: str
    body: Any
    ok: bool

    @property
    def error(self) -> dict[str, Any]:
        """The error object of a reply that is not ok (one made up when it carries none)."""
        error = self.body.get("error") if isinstance(self.body, dict) else None
        if isinstance(error, dict):
            return error
        text = self.body if isinstance(self.body, str) else json.dumps(self.body)[:200]
        return {"code": "internal", "message": f"a reply that is not an ok reply: {text}"}


#: What ``json.loads`` raises on a payload that is not JSON, or is nested past its depth (a
#: hostile peer's answer or sample, never to escape into zenoh's callback thread).
UNPARSED = (ValueError, RecursionError)


#: What was told to be left out, once each: (what, gateway) (states, joints messages, a
#: base's odometry).
_told: set[tuple[str, str]] = set()


def joints_message(payload: bytes, gateway: str) -> JointsMessage | None:
    """A joints message of ``gateway`` as the model; ``None`` when it is not one, or names
    another gateway (``published_naming``). It is about every joint of the gateway: as large
    as ``MAX_WHOLE_GATEWAY``."""
    return published_naming(
        JointsMessage, payload, "joints messages", gateway, "gateway", gateway, MAX_WHOLE_GATEWAY
    )


def published_naming(
    model: type[M],
    payload: bytes,
    what: str,
    gateway: str,
    field: str,
    name: str,
    most: int = MAX_PAYLOAD,
) -> M | None:
    """``published``, and ``None`` when the message's ``field`` names another than ``name``,
    the gateway, device or base whose key it came on (a peer's, which would pass its message
    off as theirs; a warning names the gateway, the first time)."""
    message = published(model, payload, what, gateway, most)
    if message is None or getattr(message, field) == name:
        return message
    _left_out(what, gateway, f"it names {field} {getattr(message, field)!r}, not {name!r}")
    return None


def published(
    model: type[M], payload: bytes, what: str, gateway: str, most: int = MAX_PAYLOAD
) -> M | None:
    """A message of ``gateway`` (``what`` it is, for people) as ``model``; ``None`` when it is
    not one, or is larger than any such message a gateway publishes (``most``: a state's, an
    odometry's, ``MAX_PAYLOAD``), unparsed (a peer's 100 MB on a state key; a warning names
    what and the gateway, the first time)."""
    if len(payload) > most:
        _left_out(what, gateway, f"{len(payload)} bytes, more than any gateway publishes")
        return None
    try:
        return model.model_validate_json(payload)
    except UNPARSED as exc:
        article = "an" if model.__name__[0] in "AEIOU" else "a"
        why = str(exc).replace("\n", " ")[:200]
        _left_out(what, gateway, f"not {article} {model.__name__} ({why})")
        return None


def _left_out(what: str, gateway: str, why: str) -> None:
    """Warn that ``what`` of ``gateway`` is left out, and ``why``: the first time only."""
    if (what, gateway) not in _told and len(_told) < 256:
        _told.add((what, gateway))
        log.warning("%s of gateway %.64r left out: %s", what, gateway, why)


class Answers(list[Answer]):
    """Every answer to one query; ``timed_out``: zenoh ended it at its timeout (a queryable
    had not answered), not because every one had."""

    timed_out = False


#: Why a query ended before its timeout with no answer: zenoh knew nobody who would take it,
#: or the one that took it went (its link dropped) before it answered.
NOTHING_THERE = (
    "nothing there took the query (no such gateway or device, or the access rules keep this "
    "account from it), or its gateway went before it answered (then it may have been carried "
    "out: see the device's state)"
)


def first_ok(answers: Sequence[Answer], key: str, timeout_s: float, gateway: str | None) -> Any:
    """The body of the first ok answer; the error of the first other one; ``NoAnswerError``
    when there is none."""
    for answer in answers:
        if answer.ok:
            return answer.body
    if answers:
        raise_for(answers[0].error, gateway=gateway)
    if getattr(answers, "timed_out", True):
        raise NoAnswerError(f"nobody answered on {key} within {timeout_s:g} s")
    raise NoAnswerError(f"nobody answered on {key}: {NOTHING_THERE}")


def then(future: Future, make: Callable[[Any], Any]) -> Future:
    """A future of ``make(result)`` (or of the exception ``future`` or ``make`` raised)."""
    chained: Future = Future()

    def settle(done: Future) -> None:
        try:
            result = make(done.result())
        except BaseException as exc:  # handed to whoever waits, never raised on zenoh's thread
            with contextlib.suppress(InvalidStateError):
                chained.set_exception(exc)
            return
        with contextlib.suppress(InvalidStateError):
            chained.set_result(result)

    future.add_done_callback(settle)
    return chained


#: The bounds of a client's settings: a lease shorter than zenoh's keep-alive round would drop
#: a healthy client; waits and leases past an hour are a mistake, not a choice.
MIN_LEASE_S, MAX_LEASE_S = 0.1, 3600.0
MIN_WAIT_S, MAX_WAIT_S = 0.001, 3600.0
#: The longest feed (``feed_deadline``): for ever, as a thread can wait (``threading.TIMEOUT_MAX``).
MAX_FEED_S = 1e9


def seconds(what: str, value: float, least: float, most: float) -> float:
    """``value`` when it is a number of seconds from ``least`` to ``most``; else
    ``CommandError`` (NaN, a string, a bool …).

    >>> seconds("timeout", 2, 0.001, 10)
    2
    """
    if isinstance(value, bool) or not isinstance(value, int | float) or not least <= value <= most:
        raise CommandError(f"{what} must be a number of seconds from {least:g} to {most:g}")
    return value


def feed_deadline(timeout: float) -> float:
    """When a feed of ``timeout`` seconds ends, on ``time.monotonic``'s clock; ``CommandError``
    for a timeout that is no number of seconds (NaN, a negative …: a feed that would end
    before its first item, without a word)."""
    return time.monotonic() + seconds("timeout", timeout, 0, MAX_FEED_S)


_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)


def dumps(body: Any) -> bytes:
    """``body`` as compact JSON (one encoder for every message: building one costs more than
    encoding a small command); ``NotJsonError`` for what JSON cannot carry (NaN, a set …),
    the code the gateway would answer."""
    try:
        return _ENCODER.encode(body).encode()
    except (TypeError, ValueError) as exc:
        raise error_for("not_json")(f"the command cannot be sent as JSON: {exc}") from None
