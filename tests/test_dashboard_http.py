"""The dashboard over real HTTP, served by ``busgate demo`` (a child process) beside its
gateway: the page and its files, the event stream, and every refusal of what a browser, a
page on another site, or a tired operator might send, each checked to have moved nothing; the
e-stop, its reset and the enable reaching the gateway; and ``busgate dashboard --allow-host``
answering to the name it was given."""

from __future__ import annotations

import hashlib
import http.client
import json
import re
import subprocess
from pathlib import Path
from urllib.parse import urlsplit

import pytest

import busgate.client as bc
from busgate.dashboard.app import MAX_BODY
from tests.conftest import silent_listener, status_once_signalled
from tests.gateway_process import BUSGATE, ServingProcess
from tests.sdk_helpers import patiently

VENDOR = Path(__file__).resolve().parent.parent / "dashboard" / "static" / "vendor"
DEVICES = {"la1", "la2", "la3", "servo1", "servo2", "wheel", "wheel_l", "wheel_r", "drive"}


@pytest.fixture(scope="module")
def dashboard(module_demo):
    assert module_demo.dashboard is not None, module_demo.hints
    return urlsplit(module_demo.dashboard)


@pytest.fixture(scope="module")
def client(module_demo):
    with bc.connect(module_demo.endpoint, client_id="dashboard-http-test") as c:
        yield c


def request(where, method: str, path: str, body: bytes | None = None,
            headers: dict | None = None) -> tuple[int, bytes, dict]:
    connection = http.client.HTTPConnection(where.hostname, where.port, timeout=10)
    try:
        connection.request(method, path, body=body, headers=headers or {})
        response = connection.getresponse()
        return response.status, response.read(), dict(response.getheaders())
    finally:
        connection.close()


def post(where, path: str, body: object, **headers: str) -> tuple[int, dict]:
    raw = body if isinstance(body, bytes) else json.dumps(body).encode()
    status, reply, _ = request(where, "POST", path, raw,
                               {"Content-Type": "application/json", **headers})
    return status, json.loads(reply)


def events(where, count: int) -> list[tuple[str, dict]]:
    """The first ``count`` events of one browser's stream."""
    connection = http.client.HTTPConnection(where.hostname, where.port, timeout=10)
    connection.request("GET", "/events")
    response = connection.getresponse()
    assert response.status == 200
    assert response.getheader("content-type").startswith("text/event-stream")
    found, name = [], None
    try:
        while len(found) < count:
            line = response.fp.readline().decode().rstrip("\n")
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: "):
                found.append((name, json.loads(line[6:])))
    finally:
        connection.close()
    return found


def power(client, field: str = "estopped") -> dict[str, bool]:
    """Each demo device's ``estopped`` (or another ``field`` of its state), from a fresh info."""
    [info] = client.gateways(timeout=2.0).values()
    return {d.name: getattr(d.state, field) for bus in info.buses for d in bus.devices}


def test_the_page_its_script_and_the_vendored_library_are_served(dashboard) -> None:
    status, page, headers = request(dashboard, "GET", "/")
    assert status == 200 and b"<title>busgate fleet</title>" in page
    assert headers["content-type"].startswith("text/html")
    for name in re.findall(rb'(?:src|href)="(/static/[^"]+)"', page):
        assert request(dashboard, "GET", name.decode())[0] == 200, name
    table = (VENDOR / "README.md").read_text()
    for file, digest in re.findall(r"\| (\S+) \| ([0-9a-f]{64}) \|", table):
        assert hashlib.sha256((VENDOR / file).read_bytes()).hexdigest() == digest, file
    assert "MIT License" in (VENDOR / "LICENSE.uPlot").read_text()
    assert request(dashboard, "GET", "/static/../app.py")[0] == 404


def test_a_browser_gets_a_snapshot_of_every_device_then_what_changes(dashboard) -> None:
    (first, snapshot), *rest = events(dashboard, 6)
    assert first == "snapshot"
    assert [g["name"] for g in snapshot["gateways"]] == ["demo"]
    assert {d["device"] for d in snapshot["devices"]} == DEVICES
    assert {b["name"] for b in snapshot["gateways"][0]["buses"]} == {"uart0", "uart1", "can0",
                                                                       "rs232"}
    assert all(name == "delta" for name, _ in rest)
    stamps = [body["now"] for _, body in rest]
    assert stamps == sorted(stamps) and stamps[0] >= snapshot["now"]
    assert any(body["devices"] or body["gateways"] for _, body in rest)


def test_a_browser_is_told_the_demos_base_by_its_odometry(dashboard) -> None:
    """``info`` lists no base: the dashboard finds the demo's by its odometry (every 100 ms)."""
    told = [base for _, body in events(dashboard, 5) for base in body["bases"]]
    assert told and {(b["gateway"], b["base"]) for b in told} == {("demo", "base")}
    odometry = told[-1]["odometry"]
    assert set(odometry) == {"base", "ts", "x", "y", "theta", "linear", "angular", "commanded"}
    assert set(odometry["commanded"]) == set(told[-1]["measured"]) == {"linear", "angular"}
    assert all(len(point) == 3 for base in told for point in base["track"])  # [ts, x, y]


def test_a_page_on_another_site_that_rebinds_its_name_gets_nothing(dashboard) -> None:
    for path in ("/", "/events"):
        assert request(dashboard, "GET", path, headers={"Host": "evil.example"})[0] == 400
    status, _, _ = request(dashboard, "POST", "/api/estop", b"{}",
                           {"Host": "evil.example:80", "Content-Type": "application/json"})
    assert status == 400


def test_busgate_dashboard_answers_to_a_name_given_with_allow_host(module_demo) -> None:
    served = ServingProcess("dashboard", "--connect", module_demo.endpoint, "--listen",
                            "127.0.0.1:0", "--allow-host", "Robot.Example",
                            ready="busgate dashboard")
    try:
        where = urlsplit(served.printed.split()[-1])
        for host, status in [(f"robot.example:{where.port}", 200), (where.netloc, 200),
                             (f"other.example:{where.port}", 400)]:
            assert request(where, "GET", "/", headers={"Host": host})[0] == status, host
    finally:
        assert served.terminate() == 0


@pytest.mark.parametrize("listen", ["127.0.0.1:0", "0.0.0.0:0"])
def test_a_stop_while_its_session_opens_is_heard_at_once(listen) -> None:
    """zenoh waits 10 s for an endpoint that took the connection and never answers; the
    dashboard's stop signal was heard only after it (and then its exit waited as long again
    for the thread that opened). Listening beyond this host is warned of first, before the
    session, as a gateway's zenoh listener is."""
    with silent_listener() as (mute, endpoint):
        dashboard = subprocess.Popen([*BUSGATE, "dashboard", "--connect", endpoint, "--listen",
                                      listen], stderr=subprocess.PIPE, text=True)
        try:
            assert status_once_signalled(dashboard, mute) == 0
        finally:
            dashboard.kill()
            _, err = dashboard.communicate()
    warned = [] if listen.startswith("127.") else [
        "busgate dashboard: warning: 0.0.0.0:0 can be reached from other hosts: whoever reaches "
        "it may e-stop any gateway, reset its e-stop and enable any device (docs/fleet.md)"]
    assert err.splitlines() == [*warned, "busgate dashboard: stopped before a session opened"]


@pytest.mark.parametrize(("body", "headers", "status"), [
    (b"{}", {"Content-Type": "text/plain"}, 415),  # what a form on another site can send
    (b"{}", {"Content-Type": "application/x-www-form-urlencoded"}, 415),
    (b"{}", {"Content-Type": "application/json", "Origin": "http://evil.example"}, 403),
    (b"{" + b" " * MAX_BODY + b"}", {"Content-Type": "application/json"}, 413),
    (b"{not json", {"Content-Type": "application/json"}, 400),
    (b"[" * 100_000, {"Content-Type": "application/json"}, 413),
    (b"[1]", {"Content-Type": "application/json"}, 400),
    (b'{"gateway": "*"}', {"Content-Type": "application/json"}, 400),
    (b'{"gateway": "demo/x"}', {"Content-Type": "application/json"}, 400),
    (b'{"gateway": 7}', {"Content-Type": "application/json"}, 400),
    (b"\xff\xfe", {"Content-Type": "application/json"}, 400),
    (b'{"gateway": "nowhere", "gateway": "demo"}', {"Content-Type": "application/json"}, 400),
    (b'{"gateway": "demo", "x": NaN}', {"Content-Type": "application/json"}, 400),
])
@pytest.mark.parametrize("path", ["/api/estop", "/api/reset_estop"])
def test_an_estop_or_a_reset_asked_wrongly_is_refused_and_stops_nothing(
        dashboard, client, path, body, headers, status) -> None:
    got, reply, _ = request(dashboard, "POST", path, body, headers)
    assert got == status, reply
    assert json.loads(reply)["ok"] is False
    assert not any(power(client).values())


@pytest.mark.parametrize(("body", "status", "code"), [
    ({"device": "la1"}, 400, "bad_request"),  # a bare name: which gateway's?
    ({"device": "demo/la*"}, 400, "bad_request"),
    ({"device": ["demo/la1"]}, 400, "bad_request"),
    ({}, 400, "bad_request"),
    ({"device": "demo/nothing"}, 502, "unknown_device"),
    (b'{"device": "demo/la1", "device": "demo/la2"}', 400, "bad_request"),  # was la2's
])
def test_an_enable_asked_wrongly_is_refused(dashboard, body, status, code) -> None:
    got, reply = post(dashboard, "/api/enable", body)
    assert (got, reply["ok"], reply["error"]["code"]) == (status, False, code), reply


def test_no_response_may_be_shown_in_another_pages_frame(dashboard) -> None:
    """No response said so: any site could frame the dashboard and trick a click on its
    e-stop, reset or enable (the framed page's requests carry its own host and origin)."""
    for method, path, host in (("GET", "/", None), ("GET", "/static/dashboard.js", None),
                               ("POST", "/api/estop", None), ("GET", "/", "evil.example")):
        headers = {"Host": host} if host else {}
        _, _, got = request(dashboard, method, path, headers=headers)
        assert got.get("x-frame-options") == "DENY", (path, got)
        assert got.get("content-security-policy") == "frame-ancestors 'none'", (path, got)


@pytest.mark.parametrize(("path", "body", "status", "code"), [
    ("/api/estop", {"gateway": "nowhere"}, 404, "unknown_gateway"),  # put all the same
    ("/api/reset_estop", {"gateway": "nowhere"}, 404, "unknown_gateway"),
    ("/api/enable", {"device": "nowhere/la1"}, 404, "unknown_gateway"),  # was 502 no_answer
    ("/api/reset_estop", {}, 400, "bad_request"),  # a reset is never the fleet's
    ("/api/reset_estop", {"gateway": None}, 400, "bad_request"),
])
def test_a_gateway_that_is_not_up_is_a_404_and_a_reset_names_one(
        dashboard, client, path, body, status, code) -> None:
    got, reply = post(dashboard, path, body)
    assert (got, reply["ok"], reply["error"]["code"]) == (status, False, code), reply
    if code == "unknown_gateway":
        assert reply["error"]["message"].startswith("no gateway 'nowhere' is up"), reply
        assert "demo" in reply["error"]["message"]  # the gateways that answer
    assert not any(power(client).values())


def test_only_posts_act(dashboard) -> None:
    for path in ("/api/estop", "/api/reset_estop", "/api/enable"):
        assert request(dashboard, "GET", path)[0] == 405


def test_a_head_opens_no_view(dashboard) -> None:
    """A HEAD of the events held a view for ever, its body dropped, so that it never fell
    behind; 48 of them left every browser its 503 (an audit's)."""
    assert request(dashboard, "HEAD", "/events")[0] == 405


def test_the_gateway_estop_stops_every_device_and_each_enable_brings_one_back(
        dashboard, client, wait_for) -> None:
    origin = f"http://{dashboard.netloc}"
    assert post(dashboard, "/api/estop", {"gateway": "demo"}, Origin=origin) == (
        200, {"ok": True, "estop": "demo"})
    wait_for(lambda: all(power(client).values()))
    for device in sorted(DEVICES):
        for _ in range(3):  # sent once: a reply that timed out (a loaded host) is ours to retry
            status, reply = post(dashboard, "/api/enable", {"device": f"demo/{device}"})
            if reply["ok"] or reply["error"]["code"] != "device_timeout":
                break
        assert status == 200 and reply["ok"] and reply["device"] == f"demo/{device}", reply
    wait_for(lambda: not any(power(client).values()))
    patiently(client.device("wheel").send, {"op": "disable"})  # as the demo starts it
    patiently(client.device("drive").send, {"op": "disable"})


def test_the_gateway_reset_puts_every_device_back_as_it_was_before_the_estop(
        dashboard, client, wait_for) -> None:
    before = power(client, "enabled")
    assert not all(before.values()) and any(before.values())  # the demo's wheel and drive: off
    assert post(dashboard, "/api/estop", {"gateway": "demo"})[0] == 200
    wait_for(lambda: all(power(client).values()))
    origin = f"http://{dashboard.netloc}"
    assert post(dashboard, "/api/reset_estop", {"gateway": "demo"}, Origin=origin) == (
        200, {"ok": True, "reset_estop": "demo"})
    wait_for(lambda: not any(power(client).values()))
    wait_for(lambda: power(client, "enabled") == before)
