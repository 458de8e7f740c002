"""Whatever a client sends, every get on every queryable key gets exactly one reply, carrying a
code the manual lists (docs/api.md): a property over arbitrary JSON values and byte strings,
against the real daemon (``serve``) on a real zenoh session, with the LA simulator behind it.

The default run is a bounded profile; ``-m slow`` runs many more examples."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.conftest import unused_loopback_port
from tests.test_zenoh_api import served

KEYS = ["busgate/gw1/dev/la1/cmd", "busgate/gw1/dev/la2/cmd", "busgate/gw1/bus/uart0/cmd",
        "busgate/gw1/info"]
API_PAGE = (Path(__file__).parents[1] / "docs" / "api.md").read_text()
#: The error codes of the API page's table (its first column), after "Error codes are stable".
_CODE_TABLE = API_PAGE[API_PAGE.index("Error codes are stable"):].split("\n\n")[1]
DOCUMENTED_CODES = {code
                    for cell in re.findall(r"^\| (`[^|]+`) \|", _CODE_TABLE, re.MULTILINE)
                    for code in re.findall(r"`([a-z0-9_]+)`", cell)}

#: Ops the devices and the bus know, with fields drawn from what they take: so that examples
#: reach validation, claims and planning, not only the JSON parser. Nothing here rewrites an
#: actuator's id, baud rate or flash.
OPS = ["move", "follow", "status", "read", "enable", "estop", "pause", "clear_fault", "claim",
       "release", "group_move", "group_follow", "scan", "set_overcurrent", "set_overtemp"]
FIELDS = ["position", "index", "length", "client", "ttl_s", "targets", "ids", "id", "device",
          "current_ma", "temp_c", "reply", "data"]

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner,
                                                                max_size=5),
    max_leaves=20,
)
commands = st.fixed_dictionaries(
    {"op": st.sampled_from(OPS)},
    optional={name: json_values | st.integers(-5, 3000) | st.sampled_from(["A", "B", "la2"])
              for name in FIELDS},
)
payloads = st.one_of(
    st.binary(max_size=200),
    json_values.map(lambda value: json.dumps(value).encode()),
    commands.map(lambda value: json.dumps(value).encode()),
)

BOUNDED = settings(max_examples=40, deadline=None,
                   suppress_health_check=[HealthCheck.function_scoped_fixture])
LONG = settings(max_examples=600, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def gateway():
    with served(f"tcp/127.0.0.1:{unused_loopback_port()}") as (client, _):
        yield client


def replies_to(client: zenoh.Session, key: str, payload: bytes) -> list[dict]:
    answers = []
    for reply in client.get(key, payload=payload, timeout=15):
        assert reply.ok is not None, f"an error reply on {key}: {reply.err}"
        answers.append(json.loads(reply.ok.payload.to_bytes()))
    return answers


def check_one_reply(client: zenoh.Session, key: str, payload: bytes) -> None:
    answers = replies_to(client, key, payload)
    assert len(answers) == 1, f"{len(answers)} replies on {key} to {payload[:80]!r}"
    [answer] = answers
    if not answer["ok"]:
        assert answer["error"]["code"] in DOCUMENTED_CODES, answer


def test_the_api_page_lists_the_codes_this_test_accepts():
    assert {"bad_command", "estopped", "busy", "internal", "claimed"} <= DOCUMENTED_CODES


@BOUNDED
@given(key=st.sampled_from(KEYS), payload=payloads)
def test_every_query_gets_exactly_one_reply(gateway, key, payload):
    check_one_reply(gateway, key, payload)


@pytest.mark.slow
@LONG
@given(key=st.sampled_from(KEYS), payload=payloads)
def test_every_query_gets_exactly_one_reply_long(gateway, key, payload):
    check_one_reply(gateway, key, payload)


@pytest.mark.parametrize("key", KEYS)
def test_json_nested_past_the_parsers_depth_gets_one_reply(gateway, key):
    for depth in (1_001, 30_000):
        check_one_reply(gateway, key, b"[" * depth + b"]" * depth)
        check_one_reply(gateway, key, b'{"op":' + b"[" * depth + b"]" * depth + b"}")
