"""What the gateway publishes is written as JSON whatever the value holds."""

from __future__ import annotations

import json
import math

from busgate.schemas.encoding import message_json


def test_a_state_is_compact_json_that_reads_back_equal() -> None:
    state = {"ts": 1764680000.123456, "online": True, "rpm": -12.5, "faults": [], "id": 3}
    data = message_json(state)
    assert b" " not in data
    assert json.loads(data) == state


def test_what_json_has_no_word_for_is_written_anyway() -> None:
    assert json.loads(message_json({"nan": math.nan, "inf": -math.inf})) == {
        "nan": None, "inf": None}  # valid JSON, where the standard library writes NaN
    assert json.loads(message_json({1: "a", "set": {2}})) == {"1": "a", "set": "{2}"}


def test_an_integer_past_64_bits_from_a_peers_payload_is_written_exactly() -> None:
    quoted = {"command": {"position": 10**30}}
    assert json.loads(message_json(quoted)) == quoted
