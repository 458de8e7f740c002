"""A payload off the network as a JSON object, refused in one line when it is not one: the
parse every key of the API shares (device and bus commands, follow targets, e-stops, the
trajectory key), whichever room takes the payload.

Rules of this file:

1. Refused with a stable code and nothing else done: over its key's ``limit`` (``too_large``),
   not UTF-8 (``not_utf8``), not JSON, or a number JSON cannot carry: NaN, infinities, past a
   double, integers too (``not_json``), a key given twice, nested too deeply, or not an object
   (``bad_command``).
2. The payload is parsed once, here; what it means is the schemas' (``validation``).
"""

from __future__ import annotations

import json
import math
import sys
from typing import Any

from busgate.errors import RefusedError

#: The largest payload a key takes, in bytes (the trajectory key takes more:
#: ``schemas.trajectory.MAX_TRAJECTORY_PAYLOAD``); and far more than any message a gateway
#: publishes about one thing (a device's state or event, a bus's statistics, a base's odometry).
MAX_PAYLOAD = 64 * 1024
#: The largest message a gateway sends about all its devices at once: its ``info`` reply, which
#: says the most of each device (its fullest state, its joint): 28.0 MiB, measured for the
#: most devices its config's 1 MiB can name (30,293 ZLAC706 on 278 CAN buses, every fault set),
#: as the gateway encodes it. The joints message and a trajectory's feedback (some 170 bytes a
#: device) are bounded by it too: past 64 KiB from some 390 devices on.
MAX_WHOLE_GATEWAY = 32 * 1024 * 1024
#: The most digits of a double's integers (its largest, 1.8e308, has 309).
DOUBLE_DIGITS = len(str(int(sys.float_info.max)))
#: The last chunk of the keys a gateway publishes its whole-gateway messages on.
WHOLE_GATEWAY_LEAVES = frozenset({"joints", "feedback"})


def largest_published(key: str) -> int:
    """The largest message a gateway publishes on ``key``: what a subscriber reads at most
    (past it, a peer's: a 2 MB event kept by the dashboard took it past a gigabyte).

    >>> largest_published("busgate/gw1/dev/la1/state"), largest_published("busgate/gw1/joints")
    (65536, 33554432)
    """
    whole = key.rpartition("/")[2] in WHOLE_GATEWAY_LEAVES
    return MAX_WHOLE_GATEWAY if whole else MAX_PAYLOAD


def ok_reply(**fields: Any) -> dict[str, Any]:
    """A reply that says the command was carried out, with what it found."""
    return {"ok": True, **fields}


class _DuplicateKey(ValueError):
    pass


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number JSON allows")


def _integer(text: str) -> int:
    """An integer within a double's range, as ``_finite`` takes a float: every number a
    command takes is one (``10**400`` was left for each field to refuse in its own words, or
    the interpreter's past 4300 digits, which name sys's knobs)."""
    digits = len(text.lstrip("-"))
    if digits > DOUBLE_DIGITS or abs(value := int(text)) > sys.float_info.max:
        raise ValueError(f"an integer of {digits} digits is too large for a double")
    return value


def _finite(text: str) -> float:
    value = float(text)
    if math.isinf(value):
        raise ValueError(f"{text} is too large for a double")
    return value


def _object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    value = dict(pairs)
    if len(value) < len(pairs):
        keys = [key for key, _ in pairs]
        twice = next(key for key in keys if keys.count(key) > 1)
        raise _DuplicateKey(f"key {twice!r} appears twice: a command is never guessed")
    return value


def too_large(size: int, limit: int) -> RefusedError:
    """The refusal of a payload of ``size`` bytes where its key takes ``limit`` at most."""
    return RefusedError("too_large", f"payload of {size} bytes; at most {limit}")


def decode_object(payload: bytes, *, limit: int = MAX_PAYLOAD) -> dict[str, Any]:
    """Bytes off the network to a JSON object, or ``RefusedError`` saying what is wrong
    (``limit``: the most bytes this key takes)."""
    if len(payload) > limit:
        raise too_large(len(payload), limit)
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RefusedError("not_utf8", f"payload is not UTF-8: {exc.reason}") from exc
    try:
        value = json.loads(
            text,
            parse_constant=_reject_constant,
            parse_float=_finite,
            parse_int=_integer,
            object_pairs_hook=_object,
        )
    except _DuplicateKey as exc:
        raise RefusedError("bad_command", str(exc)) from exc
    except RecursionError as exc:
        raise RefusedError("bad_command", "payload is nested too deeply") from exc
    except ValueError as exc:
        raise RefusedError("not_json", f"payload is not JSON: {exc}") from exc
    if not isinstance(value, dict):
        raise RefusedError("bad_command", "a command is a JSON object")
    return value
