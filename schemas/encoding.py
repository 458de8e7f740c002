"""How the gateway writes what it publishes as JSON: compact, one encoder for every message.

orjson, since encoding was a quarter of the publishing thread's profile (cProfile on thread
time, 2000 ZLAC706 states a second): a 13-field state takes 3.8 µs with the standard
library's encoder and 0.46 µs with orjson here (``timeit``, docs/performance.md). What orjson
cannot write (an integer past 64 bits, which only a peer's payload quoted back can hold) goes
through the standard library's encoder, so every message is written. orjson writes NaN and
infinities as ``null``, which a JSON parser reads (the standard library writes ``NaN``, which
none does; the fallback still would).
"""

from __future__ import annotations

import json
from typing import Any

import orjson

_FALLBACK = json.JSONEncoder(separators=(",", ":"), default=str)


def message_json(value: Any) -> bytes:
    """``value`` (dicts, lists, strings, numbers; anything else as its ``str``) as JSON."""
    try:
        return orjson.dumps(value, default=str, option=orjson.OPT_NON_STR_KEYS)
    except TypeError:
        return _FALLBACK.encode(value).encode()
