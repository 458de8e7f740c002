"""The dashboard's pieces below HTTP: where it may listen and the names it answers to
(``Listen``), and the hub's push to browsers on a real asyncio loop (a snapshot and every
change after it, once each; a browser that falls behind let go, not waited for); and
``busgate dashboard``'s refusals (and ``busgate demo``'s of a name for its dashboard), each one
line with exit status 2 before anything listens."""

from __future__ import annotations

import asyncio
import json
import socket

import pytest

from busgate.dashboard.feed import Feed
from busgate.dashboard.fleet import MAX_GATEWAYS, Fleet
from busgate.dashboard.hub import BACKLOG, Hub
from busgate.dashboard.server import Listen
from busgate.errors import CommandError
from tests.gateway_process import run_busgate


@pytest.mark.parametrize(("text", "host", "port"), [
    ("127.0.0.1:8080", "127.0.0.1", 8080),
    ("0.0.0.0:0", "0.0.0.0", 0),
    ("[::1]:65535", "::1", 65535),
])
def test_an_address_and_a_port_are_taken(text, host, port) -> None:
    assert Listen.parse(text) == Listen(host, port)


@pytest.mark.parametrize("text", [
    "", ":", "8080", "127.0.0.1", "127.0.0.1:", "localhost:8080", "example.com:80",
    "127.0.0.1:65536", "127.0.0.1:-1", "127.0.0.1:+80", "127.0.0.1: 80", "127.0.0.1:8_0",
    "127.0.0.1:٨٠", "::1:8080", "[::1]", "127.0.0.1:80:80", "1.2.3:99", "x" * 10_000,
])
def test_anything_else_is_refused(text) -> None:
    with pytest.raises(CommandError, match="HOST:PORT"):
        Listen.parse(text)


@pytest.mark.parametrize("port", ["65536", "70000", "-5", "80x"])
def test_a_bad_port_is_named_as_the_port(port) -> None:
    """The host was blamed for it (an audit: ``127.0.0.1:70000``)."""
    with pytest.raises(CommandError) as refused:
        Listen.parse(f"127.0.0.1:{port}")
    assert str(refused.value) == (
        f"listen on HOST:PORT: port '{port}' is no port: from 0 to 65535 (0: any free one)")


def test_the_hosts_a_browser_may_name_follow_the_address_and_allow_host() -> None:
    assert Listen("127.0.0.1", 1).names() == {"127.0.0.1", "localhost"}
    assert Listen("0:0::1", 1).names() == {"::1", "localhost"}
    assert Listen("192.0.2.7", 1).names() == {"192.0.2.7"}
    machine = {"localhost", "127.0.0.1", "::1", socket.gethostname().lower()}
    for everywhere in ("0.0.0.0", "::"):
        assert Listen(everywhere, 1).names() == machine  # nothing resolved, never "*"
    also = Listen.parse("192.0.2.7:80", ["Robot.Example", "[0:0::1]", "fe80::1", "10.0.0.9"])
    assert also.names() == {"192.0.2.7", "robot.example", "::1", "fe80::1", "10.0.0.9"}
    assert Listen("0.0.0.0", 1).url(8080) == "http://127.0.0.1:8080/"
    assert Listen("::1", 1).url(8080) == "http://[::1]:8080/"


@pytest.mark.parametrize("name", [
    "", "*", "*.example", "robot.example:8080", "[::1]:80", "http://robot.example", "a b",
    "user@robot.example", "robot.example/", "[zz::1]", "x" * 10_000,
])
def test_a_name_to_answer_to_is_a_name_or_an_address_alone(name) -> None:
    with pytest.raises(CommandError, match="a DNS name or an IP address, without a port"):
        Listen.parse("127.0.0.1:0", [name])


def test_a_port_in_use_is_refused_naming_it() -> None:
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        port = taken.getsockname()[1]
        with pytest.raises(CommandError, match=f"cannot listen on 127.0.0.1:{port}: "):
            Listen("127.0.0.1", port).bind()
    finally:
        taken.close()


def events_of(chunks: list[bytes]) -> list[tuple[str, dict]]:
    found = []
    for chunk in chunks:
        name, data = chunk.decode().rstrip("\n").split("\n")
        found.append((name.removeprefix("event: "), json.loads(data.removeprefix("data: "))))
    return found


def fleet_with_a_device() -> Fleet:
    fleet = Fleet(clock=lambda: 5.0)
    fleet.gateway_up("gw1")
    fleet.info("gw1", {"version": "1", "buses": [{"name": "uart0", "protocol": "inspire_la",
                       "devices": [{"name": "la1", "kind": "inspire_la"}]}]})
    return fleet


class SubscribedClient:
    """What ``Feed`` subscribes with, without zenoh: each key's callback, to call by hand."""

    def __init__(self) -> None:
        self.callbacks: dict[str, object] = {}

    def subscribe(self, key: str, callback: object) -> object:
        self.callbacks[key] = callback
        return lambda: None

    def on_gateways(self, callback: object) -> object:
        return lambda: None

    async def query(self, key: str, timeout: float) -> list:
        return []  # no gateway answers its info here


def test_a_sample_on_a_wildcard_key_is_dropped_and_a_named_one_taken() -> None:
    """A put on ``busgate/**/state`` reaches every subscriber of states: the feed drops it
    (it raised on each before, logged with a traceback), and takes what names a device."""
    async def run() -> dict:
        fleet, client = fleet_with_a_device(), SubscribedClient()
        Feed(client, fleet, "busgate").close()  # its subscriptions, called by hand below
        on = client.callbacks
        for key in ("busgate/**/state", "busgate/*/dev/*/state", "busgate/gw1/dev/**",
                    "busgate/gw1/dev/la1/**", "busgate/**"):
            on["busgate/*/dev/*/state"](key, {"ts": 1, "position": 666})
        on["busgate/*/bus/*/stats"]("busgate/**/stats", {"uptime_s": 1})
        on["busgate/*/base/*/odom"]("busgate/demo/**/odom", {"base": "b"})
        fleet.gateway_up("**")  # as a token on a wildcard key would make one, were it kept
        for key in ("busgate/**/events", "busgate/*/events", "busgate/gw1/x/events"):
            on["busgate/*/events"](key, {"type": "estop", "n": 1})
        assert "position" not in str(fleet.snapshot()) and "estop" not in str(fleet.snapshot())
        on["busgate/*/dev/*/state"]("busgate/gw1/dev/la1/state", {"ts": 2, "position": 777})
        on["busgate/*/events"]("busgate/gw1/events", {"type": "estop", "n": 2})
        return fleet.snapshot()

    snapshot = str(asyncio.run(run()))
    assert "777" in snapshot and "'n': 2" in snapshot and "'n': 1" not in snapshot


def test_a_gateway_that_found_the_dashboard_full_is_shown_once_one_goes(caplog) -> None:
    """256 gateways shown (peers' tokens, say): the next one's token is not announced again,
    so it was never shown, even once they had gone."""
    async def run() -> tuple[bool, bool, bool]:
        fleet, client = Fleet(), SubscribedClient()
        feed = Feed(client, fleet, "busgate")
        try:
            for n in range(MAX_GATEWAYS):
                feed._on_gateway(f"fake{n}", True)
            feed._on_gateway("late", True)
            feed._on_gateway("later", True)
            shown_while_full = fleet.has("late")
            feed._on_gateway("fake7", False)
            await asyncio.sleep(0)
            return shown_while_full, fleet.has("late"), fleet.has("later")
        finally:
            feed.close()

    assert asyncio.run(run()) == (False, True, False)
    assert "256 gateways shown already: late, and any more, wait for one to go" in caplog.text


def test_a_browser_gets_a_snapshot_then_each_change_once() -> None:
    async def run() -> list[bytes]:
        fleet = fleet_with_a_device()
        hub = Hub(fleet)
        stream = hub.stream(10)
        first = await anext(stream)  # the snapshot, taken with the browser joining
        fleet.state("gw1", "la1", {"ts": 1.0, "position": 7})
        hub.push()
        hub.push()  # nothing new: nothing sent
        fleet.event("gw1", {"ts": 2.0, "device": "la1", "type": "claimed"})
        hub.push()
        chunks = [first, await anext(stream), await anext(stream)]
        hub.let_go()
        with pytest.raises(StopAsyncIteration):
            await anext(stream)
        assert hub.browsers == 0
        return chunks

    (snapshot_name, snapshot), (_, state), (_, claimed) = events_of(asyncio.run(run()))
    assert snapshot_name == "snapshot" and snapshot["gateways"][0]["name"] == "gw1"
    assert [d["state"] for d in state["devices"]] == [{"ts": 1.0, "position": 7}]
    assert claimed["events"] == [{"gateway": "gw1", "event": {"ts": 2.0, "device": "la1",
                                                              "type": "claimed"}}]
    assert claimed["devices"] == []


def test_a_browser_that_falls_behind_is_let_go_and_the_others_are_not() -> None:
    async def run() -> tuple[list[bytes], list[bytes], int]:
        fleet = fleet_with_a_device()
        hub = Hub(fleet)
        slow, quick = hub.stream(10), hub.stream(10)
        slow_seen = [await anext(slow)]
        quick_seen = [await anext(quick)]
        for n in range(BACKLOG + 1):  # one more than the slow browser's queue holds
            fleet.state("gw1", "la1", {"ts": float(n), "position": n})
            hub.push()
            quick_seen.append(await anext(quick))
        browsers = hub.browsers
        slow_seen += [chunk async for chunk in slow]  # what is left: nothing, it ends
        return slow_seen, quick_seen, browsers

    slow_seen, quick_seen, browsers = asyncio.run(run())
    assert browsers == 1  # the quick one
    assert len(slow_seen) == 1  # its snapshot; its backlog was dropped with it
    assert len(quick_seen) == BACKLOG + 2
    positions = [e[1]["devices"][0]["state"]["position"] for e in events_of(quick_seen[1:])]
    assert positions == list(range(BACKLOG + 1))


@pytest.mark.parametrize(("command", "args", "message"), [
    ("dashboard", ["--listen", "localhost:8080"], "error: listen on HOST:PORT"),
    ("dashboard", ["--listen", "127.0.0.1:99999"], "error: listen on HOST:PORT"),
    ("dashboard", ["--connect", "nonsense"], "error: cannot open a zenoh session to nonsense"),
    ("dashboard", ["--allow-host", "robot.example:8080"], "error: a name to answer to is a"),
    ("demo", ["--dashboard-allow-host", "*"], "error: a name to answer to is a"),
    ("dashboard", ["--prefix", "*"], "error: not a key prefix: '*'"),
])
def test_busgate_dashboard_and_demo_refuse_in_one_line(command, args, message) -> None:
    done = run_busgate(command, *args)
    assert done.returncode == 2 and message in done.stderr, done
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr


def test_busgate_dashboard_refuses_a_port_in_use(module_demo) -> None:
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        port = taken.getsockname()[1]
        done = run_busgate("dashboard", "--connect", module_demo.endpoint,
                           "--listen", f"127.0.0.1:{port}")
    finally:
        taken.close()
    assert done.returncode == 2, done
    assert done.stderr.strip() == (f"busgate dashboard: error: the dashboard cannot listen on "
                                   f"127.0.0.1:{port}: Address already in use")


def test_streams_past_the_most_end_at_once_however_many_were_admitted_together() -> None:
    """A burst of requests each passed the count made before any of their streams began, and
    100 views held every connection the server had (an audit's): a stream is counted as it
    begins, and one past the most ends at once, sending nothing."""
    async def run() -> tuple[list[int], int]:
        hub = Hub(fleet_with_a_device())
        admitted = [hub.stream(2) for _ in range(4)]  # all asked before any began
        for stream in admitted[:2]:
            await anext(stream)  # its snapshot: it has begun
        async def drained(stream) -> list[bytes]:
            return [chunk async for chunk in stream]

        sent = [len(await asyncio.wait_for(drained(stream), 2.0)) for stream in admitted[2:]]
        return sent, hub.browsers

    sent, browsers = asyncio.run(run())
    assert sent == [0, 0] and browsers == 2
