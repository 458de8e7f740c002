"""A payload off the network as a JSON object, refused in one line when it is not one: the
parse every key of the API shares (device and bus commands, follow targets, e-stops, the
trajectory key), whichever room takes the payload.

Rules of this file:

1. Refused with a stable code and nothing else done: over its key's ``limit`` (``too_large``),
   not UTF-8 (``not_utf8``), not JSON, or a number JSON cannot carry: NaN, infinities, past a
   double (``not_json``), a key given twice, nested too deeply, or not an object
   (``bad_command``).
2. The payload is parsed once, here; what it means is the schemas' (``validation``).
"""

from __future__ import annotations

import json
import math
from typing import Any

from busgate.errors import RefusedError

#: The largest payload a key takes, in bytes (the trajectory key takes more:
#: ``schemas.trajectory.MAX_TRAJECTORY_PAYLOAD``).
MAX_PAYLOAD = 64 * 1024


def ok_reply(**fields: Any) -> dict[str, Any]:
    """A reply that says the command was carried out, with what it found."""
    return {"ok": True, **fields}


class _DuplicateKey(ValueError):
    pass


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number JSON allows")


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:  # past the interpreter's 4300 digits: its message names sys's knobs
        raise ValueError(
            f"an integer of {len(text.lstrip('-'))} digits is past any number a command takes"
        ) from None


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


def decode_object(payload: bytes, *, limit: int = MAX_PAYLOAD) -> dict[str, Any]:
    """Bytes off the network to a JSON object, or ``RefusedError`` saying what is wrong
    (``limit``: the most bytes this key takes)."""
    if len(payload) > limit:
        raise RefusedError("too_large", f"payload of {len(payload)} bytes; at most {limit}")
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
