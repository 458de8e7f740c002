"""Over-long and malformed key expressions against the real gateway (``serve``, a zenoh session
on 127.0.0.1, the Inspire LA simulator on a pty), each carrying a valid move. Whatever the key,
the gateway answers with an error or zenoh delivers nothing, the gateway serves on, and no move
reaches the wire (that a move to ``la1`` does reach it is ``test_zenoh_api``'s first test).

What zenoh itself does with such keys, in eclipse-zenoh 1.10: a key with many chunks matches
no queryable of the gateway (``*`` stands for one chunk), so the get ends at once with no
reply; keys that are not canonical or use ``#`` or a bare partial wildcard are refused by the
client with ``ZError`` before anything is sent.
"""

from __future__ import annotations

import json
import logging

import pytest
import zenoh

from busgate.codecs import inspire_la as la
from tests import test_zenoh_api

# The daemon, a client session and the simulator, as test_zenoh_api runs them.
setup = test_zenoh_api.setup
get = test_zenoh_api.get

MOVE = '{"op":"move","position":1000}'

# Keys the gateway's queryables match, naming nothing it has: an error reply within 1 s.
ANSWERED = {
    "5000-char device": ("busgate/gw1/dev/" + "x" * 5000 + "/cmd", "unknown_device"),
    "60000-char device, just under one zenoh batch": (
        "busgate/gw1/dev/" + "x" * 60_000 + "/cmd", "unknown_device"),
    "device of spaces and accents": ("busgate/gw1/dev/" + "é " * 2000 + "/cmd", "unknown_device"),
    "5000-char bus": ("busgate/gw1/bus/" + "b" * 5000 + "/cmd", "unknown_bus"),
    "5000-char base": ("busgate/gw1/base/" + "b" * 5000 + "/cmd", "unknown_device"),
}
# Keys no queryable of the gateway matches: the get ends with no reply.
UNMATCHED = {
    "2000 device chunks": "busgate/gw1/dev/" + "a/" * 2000 + "cmd",
    "2000 bus chunks": "busgate/gw1/bus/" + "a/" * 2000 + "cmd",
    "2000 base chunks": "busgate/gw1/base/" + "a/" * 2000 + "cmd",
    "2000 wildcard chunks": "busgate/gw1/dev/" + "*/" * 2000 + "cmd",
    "2000 chunks between **": "busgate/" + "**/a/" * 2000 + "cmd",
}
# Keys zenoh refuses on the client: nothing is sent.
REFUSED = {
    "2000 partial wildcards": "busgate/gw1/dev/" + "a*/" * 2000 + "cmd",
    "an empty chunk": "busgate/gw1/dev//cmd",
    "** twice": "busgate/gw1/dev/**/**/cmd",
    "a # in the name": "busgate/gw1/dev/la#1/cmd",
}


def assert_serves_on_and_nothing_moved(client: zenoh.Session, simulator, before: int) -> None:
    [status] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"status"}')
    assert status["ok"], "the gateway serves on"
    moves = [r for r in simulator.recorder.received()[before:] if r.frame == "MoveCommand"]
    assert moves == [], "nothing reached the wire"


@pytest.mark.parametrize(("key", "code"), ANSWERED.values(), ids=ANSWERED)
def test_a_key_naming_nothing_gets_its_error_code(setup, key, code) -> None:
    client, simulator = setup
    before = len(simulator.recorder.received())
    [reply] = get(client, key, MOVE, timeout=1.0)
    assert reply["error"]["code"] == code
    assert len(reply["error"]["message"]) < 200, "the name is cut, not echoed whole"
    assert_serves_on_and_nothing_moved(client, simulator, before)


@pytest.mark.parametrize("key", UNMATCHED.values(), ids=UNMATCHED)
def test_a_key_of_many_chunks_gets_no_reply(setup, key) -> None:
    client, simulator = setup
    before = len(simulator.recorder.received())
    assert list(client.get(key, payload=MOVE, timeout=1.0)) == []
    assert_serves_on_and_nothing_moved(client, simulator, before)


@pytest.mark.parametrize("key", REFUSED.values(), ids=REFUSED)
def test_a_malformed_key_is_refused_by_the_client(setup, key) -> None:
    client, simulator = setup
    before = len(simulator.recorder.received())
    with pytest.raises(zenoh.ZError, match="Invalid Key Expr"):
        client.get(key, payload=MOVE, timeout=1.0)
    assert_serves_on_and_nothing_moved(client, simulator, before)


def test_a_put_on_every_key_logs_no_traceback_and_no_reset_rides_along(
        setup, caplog, capfd, wait_for) -> None:
    """A put on ``**`` reaches every subscriber of the gateway: the device command and follow
    ones find no device in it (dropped, no traceback: any peer could flood the log), the
    e-stop takes it (a stop is never refused), and the reset, whose key it matches too,
    ignores it: a reset names its gateway's key exactly."""
    client, simulator = setup
    caplog.set_level(logging.DEBUG, logger="busgate")
    before = len(simulator.recorder.received())
    for key in ("**", "busgate/gw1/estop/**"):
        client.put(key, MOVE)

    def estopped() -> bool:  # a status queued as the e-stop came is cancelled by it: ask again
        [state] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"status"}')
        return state["ok"] and state["state"]["estopped"]

    wait_for(estopped)  # the e-stop took the puts
    assert_serves_on_and_nothing_moved(client, simulator, before)
    enable = la.encode(la.ControlCommand(1, la.ControlCode.ENABLE)).hex()
    assert enable not in [r.wire for r in simulator.recorder.received()[before:]]
    problems = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert problems == [] and "Traceback" not in capfd.readouterr().err


PLAY = ('{"op":"play","id":"wild","devices":["la1"],'
        '"points":[{"t_s":0,"positions":[300]},{"t_s":0.5,"positions":[800]}]}')


@pytest.mark.parametrize(("way", "key", "payload"), [
    ("get", "**", PLAY),  # reaches the trajectory key, and info: no play
    ("get", "busgate/*/trajectory", PLAY),  # names no gateway: every one would play
    ("put", "busgate/gw1/dev/la1/**", MOVE),  # reaches cmd and follow alike
    ("put", "busgate/gw1/dev/la1/*", '{"position":1000}'),
    ("get", "busgate/gw1/dev/la1/*", MOVE),
], ids=["get **", "get */trajectory", "put la1/**", "put la1/* follow", "get la1/*"])
def test_a_wildcard_leaf_or_gateway_carries_no_command(setup, way, key, payload) -> None:
    """A command acts only on a key that names its leaf (``cmd``, ``follow``), and a
    trajectory only on its gateway's own key: nothing moves, no traceback."""
    client, simulator = setup
    before = len(simulator.recorder.received())
    if way == "get":
        replies = get(client, key, payload, timeout=1.0)
        assert not [r for r in replies if "trajectory" in r or "state" in r], replies
    else:
        client.put(key, payload)
    [status] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"status"}')
    assert status["ok"], "the gateway serves on"
    frames = {r.frame for r in simulator.recorder.received()[before:]}
    assert frames <= {"ControlCommand", "ReadCommand"}, "only the status and the polls"


def test_a_refused_put_on_a_long_name_tells_the_name_cut(setup, wait_for) -> None:
    """A put on a 30,000-character device is refused as an event on ``events``: the event's
    ``device`` is cut as a refusal's message cuts it, not echoed whole to every subscriber."""
    client, _ = setup
    heard: list[dict] = []
    events = client.declare_subscriber(
        "busgate/gw1/events", lambda sample: heard.append(json.loads(sample.payload.to_bytes())))
    try:
        client.put("busgate/gw1/dev/" + "x" * 30_000 + "/cmd", MOVE)
        wait_for(lambda: any(e.get("type") == "command_refused" for e in heard))
    finally:
        events.undeclare()
    [refused] = [e for e in heard if e.get("type") == "command_refused"]
    assert refused["code"] == "unknown_device"
    assert len(refused["device"]) <= 65 and len(refused["message"]) < 200
