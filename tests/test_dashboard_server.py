"""The dashboard's own server (``serve_dashboard``) in this process, over real sockets on
127.0.0.1, on a client that reaches no zenoh and records what it is asked to do: the names
it answers to whatever it listens on (a page that rebinds its DNS name to the machine gets
nothing), the origins it takes an action from, and what it holds of a client that sends half
a request or opens too many connections."""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import json
import logging
import queue
import select
import socket
import threading
import time
from collections.abc import Iterator
from types import SimpleNamespace
from urllib.parse import SplitResult, urlsplit

import pytest

import busgate.client as bc
from busgate.dashboard import app as app_module
from busgate.dashboard import server
from busgate.dashboard.server import Listen, serve_dashboard
from tests.test_dashboard_http import request

ATTACKER = "rebind.attacker.example:8080"
#: The request deadline while these tests run (the dashboard's own is ``REQUEST_TIMEOUT_S``).
SHORT_S = 0.5


class RecordingClient:
    """What ``serve_dashboard`` asks of a ``busgate.client.aio`` client, without zenoh: it
    hears of no gateway and records each e-stop, reset and enable (``asked``)."""

    def __init__(self) -> None:
        self.asked: list[tuple[str, str | None]] = []

    def subscribe(self, key: str, callback: object) -> object:
        return lambda: None

    def on_gateways(self, callback: object) -> object:
        return lambda: None

    async def estop(self, gateway: str | None) -> None:
        self.asked.append(("estop", gateway))

    async def reset_estop(self, gateway: str) -> None:
        self.asked.append(("reset_estop", gateway))

    async def device(self, name: str) -> SimpleNamespace:
        async def enable() -> dict:
            self.asked.append(("enable", name))
            return {"ok": True}

        return SimpleNamespace(enable=enable)


@contextlib.contextmanager
def served(listen: Listen) -> Iterator[tuple[SplitResult, RecordingClient]]:
    """``serve_dashboard`` on ``listen``, on a loop in a thread of its own, until the block
    ends: where to reach it (127.0.0.1 and its port) and its client."""
    client, urls = RecordingClient(), queue.Queue()
    loop, stop = asyncio.new_event_loop(), asyncio.Event()
    serving = serve_dashboard(client, listen, stop, on_ready=urls.put)
    thread = threading.Thread(target=loop.run_until_complete, args=(serving,))
    thread.start()
    try:
        yield urlsplit(urls.get(timeout=10)), client
    finally:
        loop.call_soon_threadsafe(stop.set)
        thread.join(timeout=10)
        loop.close()


#: Each action a browser may send, as it sends it, and what the client is then asked.
ACTIONS = {
    "enable": ("/api/enable", b'{"device": "demo/la1"}', ("enable", "demo/la1")),
    "reset_estop": ("/api/reset_estop", b'{"gateway": "demo"}', ("reset_estop", "demo")),
}


def act(where: SplitResult, host: str, origin: str | None = None,
        action: str = "enable") -> tuple[int, dict]:
    """An action (``ACTIONS``) as a browser sends it, naming ``host`` (and ``origin``)."""
    headers = {"Host": host, "Content-Type": "application/json"}
    if origin is not None:
        headers["Origin"] = origin
    path, body, _ = ACTIONS[action]
    status, reply, _ = request(where, "POST", path, body, headers)
    return status, json.loads(reply)


@pytest.mark.parametrize("action", ACTIONS)
@pytest.mark.parametrize(("address", "names"), [
    ("0.0.0.0", ["localhost", "127.0.0.1", "[::1]", socket.gethostname()]),
    ("127.0.0.1", ["localhost", "127.0.0.1"]),
])
def test_a_page_that_rebinds_its_name_to_the_dashboard_gets_nothing_whatever_it_listens_on(
        address, names, action) -> None:
    with served(Listen(address, 0)) as (where, client):
        for name in names:  # what a browser on this machine names it by
            assert request(where, "GET", "/", headers={"Host": f"{name}:{where.port}"})[0] == 200
        for path in ("/", "/static/app.js"):
            status, reply, _ = request(where, "GET", path, headers={"Host": ATTACKER})
            assert status == 400 and json.loads(reply)["error"]["code"] == "unknown_host"
        status, reply = act(where, ATTACKER, f"http://{ATTACKER}", action)
        assert status == 400, reply
        assert reply["error"] == {"code": "unknown_host", "message": f"{ATTACKER!r} is not a "
                                  "name this dashboard answers to"}
        assert client.asked == []
        assert act(where, where.netloc, f"http://{where.netloc}", action)[0] == 200
        assert client.asked == [ACTIONS[action][2]]


def test_an_enable_whose_reply_timed_out_is_not_sent_again() -> None:
    """An audit: the dashboard sent a device's enable again (three times in all) while its
    reply timed out, and one sent after an e-stop put meanwhile took the device out of it.
    Sent once, the timeout is the operator's answer."""

    async def timed_out(timeout: float | None = None) -> dict:
        asked.append("enable")
        raise bc.error_for("device_timeout")("no reply from la1")

    async def device(name: str) -> SimpleNamespace:
        return SimpleNamespace(enable=timed_out)

    asked: list[str] = []
    actions = server.ClientActions(SimpleNamespace(device=device))  # type: ignore[arg-type]
    with pytest.raises(bc.error_for("device_timeout")):
        asyncio.run(actions.enable("demo/la1"))
    assert asked == ["enable"]


def test_a_name_given_with_allow_host_is_answered_and_acted_for() -> None:
    with served(Listen.parse("127.0.0.1:0", ["Robot.Example"])) as (where, client):
        host = f"robot.example:{where.port}"
        assert request(where, "GET", "/", headers={"Host": host})[0] == 200
        assert act(where, host, f"http://{host}")[0] == 200
        assert act(where, f"robot.example.evil:{where.port}")[0] == 400
        assert client.asked == [("enable", "demo/la1")]


@pytest.mark.parametrize("action", ACTIONS)
def test_an_action_is_taken_from_the_dashboards_own_origins_alone(action) -> None:
    with served(Listen("127.0.0.1", 0)) as (where, client):
        port = where.port
        for origin, status in [
            (f"http://127.0.0.1:{port}", 200),
            (f"https://127.0.0.1:{port}", 200),  # a proxy in front that speaks TLS
            (f"http://localhost:{port}", 200),
            (f"http://{ATTACKER}", 403),
            (f"http://rebind.attacker.example:{port}", 403),
            ("http://127.0.0.1:1", 403),  # another port of the machine: another site
            ("http://127.0.0.1", 403),
            (f"ftp://127.0.0.1:{port}", 403),
            (f"http://user@127.0.0.1:{port}", 403),
            ("null", 403),  # a sandboxed frame, a file
        ]:
            before = len(client.asked)
            got, reply = act(where, f"127.0.0.1:{port}", origin, action)
            assert got == status, (origin, reply)
            assert len(client.asked) == before + (status == 200), origin
        assert set(client.asked) == {ACTIONS[action][2]}


def closed_at(connection: socket.socket) -> float:
    """When the server closed ``connection`` (``time.monotonic``), having sent nothing on it."""
    connection.settimeout(10 * SHORT_S)
    assert connection.recv(1024) == b""
    return time.monotonic()


def readable_now(connection: socket.socket) -> bytes:
    """What ``connection`` has for reading now; fails when the server closed it."""
    connection.settimeout(0.1)
    seen = b""
    while True:
        try:
            chunk = connection.recv(65536)
        except TimeoutError:
            return seen
        assert chunk, f"closed by the server after {seen[:200]!r}"
        seen += chunk


def test_a_half_sent_request_is_closed_within_the_deadline_and_an_event_stream_is_not(
        monkeypatch, caplog) -> None:
    monkeypatch.setattr(server, "REQUEST_TIMEOUT_S", SHORT_S)
    with served(Listen("127.0.0.1", 0)) as (where, client):
        address = ("127.0.0.1", where.port)
        head = f"Host: {where.netloc}\r\nContent-Type: application/json\r\n"
        halves = [
            b"GET / HT",  # half a request line
            f"POST /api/estop HTTP/1.1\r\n{head}Content-Length: 100\r\n\r\n{{".encode(),
            f"POST /api/estop HTTP/1.1\r\n{head}".encode(),  # headers, not their end
        ]
        stream = socket.create_connection(address)
        stream.sendall(f"GET /events HTTP/1.1\r\nHost: {where.netloc}\r\n\r\n".encode())
        opened = time.monotonic()  # the deadline starts later, with the server's accept
        clients = [socket.create_connection(address) for _ in halves]
        for connection, half in zip(clients, halves, strict=True):
            connection.sendall(half)
        took = [closed_at(connection) - opened for connection in clients]
        assert all(0.9 * SHORT_S < seconds < 4 * SHORT_S for seconds in took), took

        kept = socket.create_connection(address)  # a whole request, then half of the next
        asked = time.monotonic()  # the deadline starts later, with the reply
        kept.sendall(f"GET /nothing HTTP/1.1\r\nHost: {where.netloc}\r\n\r\n".encode())
        time.sleep(0.1)
        assert readable_now(kept).startswith(b"HTTP/1.1 404 ")
        kept.sendall(b"GET /nothing HTTP/1.1\r\nHo")
        assert 0.9 * SHORT_S < closed_at(kept) - asked < 4 * SHORT_S

        assert b"event: snapshot" in readable_now(stream)  # well past the deadline, still open
        for connection in [stream, kept, *clients]:
            connection.close()
    assert client.asked == []
    assert [r.getMessage() for r in caplog.records if r.levelname == "ERROR"] == []


def test_a_request_that_finds_too_many_connections_open_gets_a_503(monkeypatch) -> None:
    monkeypatch.setattr(server, "MAX_CONNECTIONS", 3)
    with served(Listen("127.0.0.1", 0)) as (where, _):
        idle = [socket.create_connection(("127.0.0.1", where.port)) for _ in range(2)]
        assert request(where, "GET", "/")[0] == 503  # its own is the third
        for connection in idle:
            connection.close()
        time.sleep(0.1)  # the server sees them go
        assert request(where, "GET", "/")[0] == 200


def from_address(where: SplitResult, source: str, method: str, path: str,
                 body: bytes | None = None) -> tuple[int, bytes]:
    """A request from ``source`` (another loopback address: another client host)."""
    connection = http.client.HTTPConnection(where.hostname, where.port, timeout=10,
                                            source_address=(source, 0))
    try:
        connection.request(method, path, body=body,
                           headers={"Content-Type": "application/json"} if body else {})
        response = connection.getresponse()
        return response.status, response.read()
    finally:
        connection.close()


def test_one_host_holding_connections_leaves_the_others_their_page_and_e_stop() -> None:
    """A host that holds 99 connections open (idle, or each a live view it never reads)
    kept every other client out, the e-stop included, with a 503: it now holds at most
    ``MAX_PER_CLIENT``, each past them closed as it opens, and the others are served."""
    with served(Listen("127.0.0.1", 0)) as (where, client), contextlib.ExitStack() as held:
        sockets = [held.enter_context(socket.create_connection((where.hostname, where.port)))
                   for _ in range(server.MAX_PER_CLIENT + 10)]
        closed: list[socket.socket] = []
        deadline = time.monotonic() + 4.0  # within the request deadline (5 s): only the cap
        while len(closed) < 10 and time.monotonic() < deadline:  # closes any before it
            readable, _, _ = select.select([s for s in sockets if s not in closed], [], [], 0.1)
            closed += [s for s in readable if s.recv(1) == b""]
        time.sleep(0.2)  # none more
        assert len(closed) == 10 and not select.select(
            [s for s in sockets if s not in closed], [], [], 0)[0]
        assert from_address(where, "127.0.0.2", "GET", "/")[0] == 200
        status, reply = from_address(where, "127.0.0.2", "POST", "/api/estop",
                                     b'{"gateway": "demo"}')
        assert (status, json.loads(reply)) == (200, {"ok": True, "estop": "demo"})
        assert client.asked == [("estop", "demo")]


def test_live_views_past_the_most_get_a_503_and_actions_still_go(monkeypatch) -> None:
    monkeypatch.setattr(app_module, "MAX_STREAMS", 2)
    with served(Listen("127.0.0.1", 0)) as (where, client), contextlib.ExitStack() as held:
        for _ in range(2):
            stream = http.client.HTTPConnection(where.hostname, where.port, timeout=10)
            held.callback(stream.close)
            stream.request("GET", "/events")
            assert stream.getresponse().status == 200
        status, reply = from_address(where, "127.0.0.3", "GET", "/events")
        assert (status, json.loads(reply)["error"]["code"]) == (503, "busy")
        status, _ = from_address(where, "127.0.0.3", "POST", "/api/estop", b'{"gateway": "gw"}')
        assert status == 200 and client.asked == [("estop", "gw")]


def test_the_warning_of_a_request_at_the_limit_is_logged_once_a_minute() -> None:
    now_and_then = server._NowAndThen()

    def record(message: str, created: float) -> logging.LogRecord:
        made = logging.LogRecord("uvicorn.error", logging.WARNING, "", 0, message, None, None)
        made.created = created
        return made

    told = [now_and_then.filter(record("Exceeded concurrency limit.", t)) for t in (0, 1, 59, 61)]
    assert told == [True, False, False, True]
    assert now_and_then.filter(record("something else", 62))


def test_malformed_requests_are_each_refused_and_warned_of_once(caplog) -> None:
    """uvicorn logged a warning for each one: 2,000 lines a second for whoever sends them."""
    with served(Listen("127.0.0.1", 0)) as (where, _):
        for _ in range(5):
            with socket.create_connection((where.hostname, where.port), timeout=10) as raw:
                raw.sendall(b"NOT HTTP AT ALL\r\n\r\n")
                assert raw.recv(64).startswith(b"HTTP/1.1 400")
    warned = [r.getMessage() for r in caplog.records if r.name == "uvicorn.error"]
    assert warned == ["Invalid HTTP request received."]


def test_a_websocket_upgrade_is_a_plain_request_warned_of_once(caplog) -> None:
    """uvicorn warned twice of each upgrade it does not serve (install a websocket
    library): now once a minute, whatever a client sends."""
    with served(Listen("127.0.0.1", 0)) as (where, _):
        for _ in range(5):
            status, _, _ = request(where, "GET", "/", headers={
                "Host": f"127.0.0.1:{where.port}", "Connection": "Upgrade",
                "Upgrade": "websocket", "Sec-WebSocket-Version": "13",
                "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ=="})
            assert status == 200
    warned = [r.getMessage()[:30] for r in caplog.records if r.name == "uvicorn.error"]
    assert warned == ["Unsupported upgrade request.", "No supported WebSocket library"]
