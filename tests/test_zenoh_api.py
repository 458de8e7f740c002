"""The zenoh API end to end: the real daemon (``serve``) with a real zenoh session on
127.0.0.1, multicast scouting off, a client session beside it, and the Inspire LA simulator on
a pty behind it."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future

import pytest
import zenoh

from busgate.codecs import inspire_la as la
from busgate.gateway.api.bridge import ZenohBridge
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.scheduler.outcomes import settled
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.service.daemon import serve
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.config import parse_config
from busgate.schemas.payload import MAX_PAYLOAD
from busgate.schemas.zenoh_session import MAX_RECEIVED, session_config


def config_for(port: str, endpoint: str) -> dict:
    return {
        "gateway": {"name": "gw1"},
        "zenoh": {"mode": "peer", "listen": [endpoint]},
        # A reply margin with room for the simulator, which shares the daemon's process and a
        # loaded machine's cores: a late reply must not pass for a device gone offline.
        "buses": [{"name": "uart0", "transport": "serial", "port": port, "baudrate": 921600,
                   "reply_margin_ms": 50,
                   "devices": [{"name": "la1", "kind": "inspire_la", "id": 1, "poll_hz": 20},
                               {"name": "la2", "kind": "inspire_la", "id": 2, "poll_hz": 20}]}],
    }


class Daemon:
    """``serve`` on a thread of its own, as ``busgate run`` would run it."""

    def __init__(self, config: dict) -> None:
        self.ready = threading.Event()
        self.loop = asyncio.new_event_loop()
        self.stop = asyncio.Event()
        self.thread = threading.Thread(target=self._run, args=(parse_config(config),))
        self.thread.start()
        assert self.ready.wait(10), "the daemon did not come up"

    def _run(self, config) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_until_complete(serve(config, ready=self.ready, stop=self.stop))

    def shutdown(self) -> None:
        self.loop.call_soon_threadsafe(self.stop.set)
        self.thread.join(5)


def connected(client: zenoh.Session, timeout: float = 20.0) -> zenoh.Session:
    """``client`` once the gateway answers it: a peer connects in the background, and a get
    made before its transport is up finds no one to ask."""
    deadline = time.monotonic() + timeout
    while not get(client, "busgate/gw1/info", "", timeout=2):
        assert time.monotonic() < deadline, "the gateway does not answer"
        time.sleep(0.05)
    return client


@contextlib.contextmanager
def served(endpoint: str) -> Iterator[tuple[zenoh.Session, SerialSimulator]]:
    """The daemon on ``endpoint`` over two simulated LA actuators, and a client session
    that reaches it."""
    simulator = SerialSimulator(la, [InspireLaDevice(1), InspireLaDevice(2)], baudrate=921_600)
    simulator.start()
    daemon = Daemon(config_for(simulator.port, endpoint))
    client = zenoh.open(session_config(mode="peer", connect=[endpoint]))
    try:
        connected(client)
        yield client, simulator
    finally:
        client.close()
        daemon.shutdown()
        simulator.stop()


@pytest.fixture
def setup(free_port):
    with served(f"tcp/127.0.0.1:{free_port()}") as both:
        yield both


@contextlib.contextmanager
def idle_bridge(free_port) -> Iterator[tuple[ZenohBridge, zenoh.Session]]:
    """A bridge over one LA bus that is never started (no port opened: what is tested is the
    zenoh side), its loop running on a thread of its own (the replies'), and a client's
    session connected to it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = parse_config(config_for("/dev/null", endpoint))
    runners = {bus.name: build_bus(bus) for bus in config.buses}
    bridge = ZenohBridge(config, GatewayApi("gw1", runners), runners, deque(), deque())
    loop = asyncio.new_event_loop()
    bridge.open(loop)
    replies = threading.Thread(target=loop.run_forever, daemon=True)
    replies.start()
    client = zenoh.open(session_config(mode="peer", connect=[endpoint]))
    try:
        yield bridge, client
    finally:
        client.close()
        loop.call_soon_threadsafe(loop.stop)
        replies.join(5)
        bridge.close()
        loop.close()


#: An e-stop's put, as the SDK puts it.
URGENT = {"priority": zenoh.Priority.REAL_TIME, "express": True,
          "congestion_control": zenoh.CongestionControl.BLOCK}


def get(client: zenoh.Session, key: str, payload: bytes | str, timeout: float = 5.0) -> list:
    replies = client.get(key, payload=payload, timeout=timeout)
    return [json.loads(reply.ok.payload.to_bytes()) for reply in replies if reply.ok]


def test_a_get_is_answered_and_its_frame_goes_out(setup) -> None:
    client, simulator = setup
    [reply] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"move","position":1234}')
    assert reply["ok"] and reply["state"]["target"] == 1234
    wire = la.encode(la.MoveCommand(1, 1234, True)).hex()
    assert wire in [r.wire for r in simulator.recorder.received()]


def test_every_malformed_command_gets_its_code_and_nothing_reaches_the_wire(setup) -> None:
    client, simulator = setup
    before = len(simulator.recorder.received())
    cases = {b"\xff": "not_utf8", b"{": "not_json", b'{"op":"move","position":9999}':
             "out_of_range", b'{"op":"nope"}': "bad_command"}
    for payload, expected in cases.items():
        [reply] = get(client, "busgate/gw1/dev/la1/cmd", payload)
        assert reply["error"]["code"] == expected
    [reply] = get(client, "busgate/gw1/dev/ghost/cmd", '{"op":"status"}')
    assert reply["error"]["code"] == "unknown_device"
    [again] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"status"}')
    assert again["ok"], "the gateway serves on"
    # Checked after a later command was carried out: one let through would have gone first.
    moves = [r for r in simulator.recorder.received()[before:] if r.frame == "MoveCommand"]
    assert moves == []


def test_telemetry_info_and_liveliness(wait_for, setup) -> None:
    client, _ = setup
    states: list[dict] = []
    subscriber = client.declare_subscriber(
        "busgate/gw1/dev/*/state", lambda s: states.append(json.loads(s.payload.to_bytes())))
    wait_for(lambda: {s["device"] for s in states} == {"la1", "la2"})
    assert all(s["kind"] == "inspire_la" and "position" in s for s in states)
    [info] = get(client, "busgate/gw1/info", "")
    assert [d["name"] for d in info["buses"][0]["devices"]] == ["la1", "la2"]
    alive = [str(r.ok.key_expr) for r in client.liveliness().get("busgate/gw1/**", timeout=2)]
    assert "busgate/gw1/alive" in alive and "busgate/gw1/dev/la1/alive" in alive
    subscriber.undeclare()


def test_estop_from_any_client_stops_every_device(wait_for, setup) -> None:
    client, simulator = setup
    client.put("busgate/*/estop", b"")  # the fleet-wide form
    stops = {la.encode(la.ControlCommand(i, la.ControlCode.ESTOP)).hex() for i in (1, 2)}
    wait_for(lambda: stops <= {r.wire for r in simulator.recorder.received()})


def test_follow_puts_stream_at_the_period_and_a_bad_one_is_an_event(wait_for, setup) -> None:
    client, simulator = setup
    events: list[dict] = []
    subscriber = client.declare_subscriber(
        "busgate/gw1/events", lambda s: events.append(json.loads(s.payload.to_bytes())))

    def streamed() -> bool:  # a client streaming its target until six ticks reached la1
        client.put("busgate/gw1/dev/la1/follow", '{"position": 800}')
        return sum(r.frame == "FollowCommand" for r in simulator.recorder.received()) > 5

    wait_for(streamed, timeout=10)
    client.put("busgate/gw1/dev/la1/follow", '{"position": 99999}')
    wait_for(lambda: any(e["type"] == "command_refused" for e in events))
    wait_for(lambda: any(e["type"] == "stream_stale" for e in events))
    subscriber.undeclare()


def test_a_flood_of_refused_puts_is_told_a_few_times_and_counted_whole(wait_for, setup) -> None:
    """300 refused follow puts as fast as a client sends them: a handful of events (one a
    device every 0.1 s), whose ``suppressed`` counts make up the rest: none lost."""
    client, _ = setup
    events: list[dict] = []
    subscriber = client.declare_subscriber(
        "busgate/gw1/dev/la2/event", lambda s: events.append(json.loads(s.payload.to_bytes())))
    started = time.monotonic()
    for _ in range(300):
        client.put("busgate/gw1/dev/la2/follow", '{"position": 99999}',
                   congestion_control=zenoh.CongestionControl.BLOCK)

    def accounted() -> int:
        refused = [e for e in events if e["type"] == "command_refused"]
        return len(refused) + sum(e.get("suppressed", 0) for e in refused)

    wait_for(lambda: accounted() == 300)
    told = [e for e in events if e["type"] == "command_refused"]
    assert 2 <= len(told) <= (time.monotonic() - started) / 0.1 + 2
    assert {e["code"] for e in told} == {"out_of_range"}
    subscriber.undeclare()


def test_end_follow_stops_a_stream_without_it_going_stale(wait_for, setup) -> None:
    """alice streams to la1, which she claimed: bob's end_follow is refused ``claimed`` and
    the stream goes on; hers ends it with ``stream_stopped`` and its reason, and a second
    past the stale timeout (100 ms) no ``stream_stale`` came."""
    client, simulator = setup
    events: list[dict] = []
    subscriber = client.declare_subscriber(
        "busgate/gw1/events", lambda s: events.append(json.loads(s.payload.to_bytes())))
    [claimed] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"claim","client":"alice"}')
    assert claimed["ok"]
    streaming = threading.Event()
    target = '{"position": 900, "client": "alice"}'

    def stream() -> None:
        while not streaming.is_set():
            client.put("busgate/gw1/dev/la1/follow", target)
            time.sleep(0.02)

    def ticks() -> int:
        return sum(r.frame == "FollowCommand" for r in simulator.recorder.received())

    streamer = threading.Thread(target=stream)
    streamer.start()
    try:
        wait_for(lambda: ticks() > 5, timeout=10)
        [refused] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"end_follow","client":"bob"}')
        assert refused["error"]["code"] == "claimed"
        going_on = ticks()
        wait_for(lambda: ticks() > going_on + 5, timeout=10)
    finally:
        streaming.set()
        streamer.join()
    # What the end is judged by starts here: a stream_stale before it would be this test's
    # own streaming thread stalled past the stale timeout on a loaded host, not the end's.
    mark = len(events)
    client.put("busgate/gw1/dev/la1/follow", target)  # the last target, then at once the end
    [ended] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"end_follow","client":"alice"}')
    assert ended == {"ok": True, "ended": True}
    wait_for(lambda: any(e["type"] == "stream_stopped" for e in events[mark:]))
    time.sleep(1.1)
    subscriber.undeclare()
    stream_events = [(e["device"], e["type"], e.get("reason")) for e in events[mark:]
                     if e["type"].startswith("stream_")]
    assert stream_events == [("la1", "stream_stopped", "ended by alice")]


@pytest.mark.parametrize("payload", [
    b"[" * 1001 + b"]" * 1001,  # deeper than the JSON parser goes
    b'{"position": 800, "client": ["x"]}',
    b'{"position": 800, "position": 100}',
])
def test_a_follow_put_of_any_payload_is_taken_or_refused_as_an_event(wait_for, setup, payload):
    client, simulator = setup
    events: list[dict] = []
    subscriber = client.declare_subscriber(
        "busgate/gw1/dev/la1/event", lambda s: events.append(json.loads(s.payload.to_bytes())))
    client.put("busgate/gw1/dev/la1/follow", payload)
    wait_for(lambda: any(e["type"] == "command_refused" for e in events))
    assert [e["code"] for e in events if e["type"] == "command_refused"] == ["bad_command"]
    # A stream let through would have started before a later command, and its first tick,
    # due at once, goes ahead of polls: two frames after that command's answer prove it.
    [status] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"status"}')
    assert status["ok"]
    mark = len(simulator.recorder.received())
    wait_for(lambda: len(simulator.recorder.received()) >= mark + 2)
    assert not any(r.frame == "FollowCommand" for r in simulator.recorder.received())
    subscriber.undeclare()


def test_a_client_that_vanishes_loses_its_claim(wait_for, setup) -> None:
    client, _ = setup
    token = client.liveliness().declare_token("busgate/clients/alice")
    [claimed] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"claim","client":"alice"}')
    assert claimed["ok"]
    [refused] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"move","position":5,"client":"bob"}')
    assert refused["error"]["code"] == "claimed"
    token.undeclare()

    def bob_moves() -> bool:
        [reply] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"status","client":"bob"}')
        [move] = get(client, "busgate/gw1/dev/la1/cmd",
                     '{"op":"move","position":5,"client":"bob"}')
        return reply["ok"] and move["ok"]

    wait_for(bob_moves)


def test_busgate_run_stops_in_order_on_sigterm_during_traffic(free_port, wait_for, tmp_path):
    """SIGTERM while a client streams follow targets to la1 and sends moves to la2: the
    daemon exits 0 within a few seconds, each actuator is e-stopped with no motion frame after
    it, and no frame is left half-written."""
    simulator = SerialSimulator(la, [InspireLaDevice(1), InspireLaDevice(2)], baudrate=921_600)
    simulator.start()
    config = tmp_path / "gw.toml"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config.write_text(
        f'[gateway]\nname = "gw1"\n[zenoh]\nlisten = ["{endpoint}"]\n'
        f'[[buses]]\nname = "uart0"\ntransport = "serial"\nport = "{simulator.port}"\n'
        'baudrate = 921600\n'
        + "".join(f'[[buses.devices]]\nname = "la{i}"\nkind = "inspire_la"\nid = {i}\n'
                  'follow_period_ms = 10\n' for i in (1, 2))
    )
    process = subprocess.Popen([sys.executable, "-m", "busgate.gateway.cli", "run", "--config",
                                str(config)], stderr=subprocess.PIPE, text=True)
    client = zenoh.open(session_config(mode="peer", connect=[endpoint]))
    traffic = threading.Event()

    def client_traffic() -> None:
        position = 0
        while not traffic.is_set():
            position = (position + 7) % 2000
            client.put("busgate/gw1/dev/la1/follow", json.dumps({"position": position}))
            client.put("busgate/gw1/dev/la2/cmd", json.dumps({"op": "move", "position": position}))
            time.sleep(0.003)

    streaming = threading.Thread(target=client_traffic)
    try:
        streaming.start()
        wait_for(lambda: {"FollowCommand", "MoveCommand"}
                 <= {r.frame for r in simulator.recorder.received()}, timeout=15)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=20) == 0  # a generous deadline, not a duration measured
    finally:
        traffic.set()
        streaming.join()
        client.close()
        if process.poll() is None:
            process.kill()
        simulator.stop()
    motion = ("FollowCommand", "MoveCommand", "GroupFollowCommand", "GroupMoveCommand")
    for device_id in (1, 2):
        frames = [r for r in simulator.recorder.received() if r.device_id in (device_id, 255)]
        estop = la.encode(la.ControlCommand(device_id, la.ControlCode.ESTOP)).hex()
        last_estop = max(i for i, r in enumerate(frames) if r.wire == estop)
        after = [r.frame for r in frames[last_estop:] if r.frame in motion]
        assert after == [], f"la{device_id} moved after its e-stop"
    assert simulator.partial_frame == b"", "a frame left half-written"


def test_a_fleet_wide_get_is_answered_only_by_the_gateway_that_has_the_device(setup) -> None:
    client, _ = setup
    replies = get(client, "busgate/*/dev/la1/cmd", '{"op":"status"}')
    assert len(replies) == 1 and replies[0]["ok"]
    assert get(client, "busgate/*/dev/ghost/cmd", '{"op":"status"}', timeout=10) == []
    [refused] = get(client, "busgate/gw1/dev/ghost/cmd", '{"op":"status"}')
    assert refused["error"]["code"] == "unknown_device"


def test_the_daemon_serves_prometheus_metrics_when_configured(free_port, wait_for) -> None:
    import urllib.request

    simulator = SerialSimulator(la, [InspireLaDevice(1), InspireLaDevice(2)], baudrate=921_600)
    simulator.start()
    endpoint, metrics_port = f"tcp/127.0.0.1:{free_port()}", free_port()
    config = config_for(simulator.port, endpoint)
    config["metrics"] = {"listen": f"127.0.0.1:{metrics_port}"}
    daemon = Daemon(config)
    client = zenoh.open(session_config(mode="peer", connect=[endpoint]))
    url = f"http://127.0.0.1:{metrics_port}/metrics"

    def answered() -> float:
        """How many queries the latency histogram holds (each is observed once its reply
        went out, so a moment after the client has it)."""
        text = urllib.request.urlopen(url, timeout=5).read().decode()
        [count] = [line for line in text.splitlines()
                   if line.startswith("busgate_command_latency_seconds_count")]
        return float(count.split()[-1])

    try:
        connected(client)  # an info query answered
        wait_for(lambda: answered() >= 1)
        before = answered()
        [reply] = get(client, "busgate/gw1/dev/la1/cmd", '{"op":"status"}')
        assert reply["ok"]
        wait_for(lambda: answered() == before + 1)
        text = urllib.request.urlopen(url, timeout=5).read().decode()
        assert 'busgate_device_online{bus="uart0",device="la1",kind="inspire_la"} 1.0' in text
        frames = [line for line in text.splitlines()
                  if line.startswith('busgate_bus_frames_total{bus="uart0",direction="out"}')]
        assert frames and float(frames[0].split()[-1]) > 0
        clients = [line for line in text.splitlines() if line.startswith("busgate_zenoh_clients")]
        assert clients and float(clients[0].split()[-1]) >= 1
    finally:
        client.close()
        daemon.shutdown()
        simulator.stop()


def test_every_state_a_bus_made_is_published_in_order(free_port, wait_for) -> None:
    """A publishing round sends every state made since the last one, several of one device
    included: telemetry at the device's rate is never thinned by the round's period."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = parse_config(config_for("/dev/null", endpoint))
    runners = {bus.name: build_bus(bus) for bus in config.buses}  # not started: no port opened
    states: deque = deque()
    bridge = ZenohBridge(config, GatewayApi("gw1", runners), runners,
                         deque(), states)
    loop = asyncio.new_event_loop()
    bridge.open(loop)
    client = zenoh.open(session_config(mode="peer", connect=[endpoint]))
    received: list[dict] = []
    subscriber = client.declare_subscriber(
        "busgate/gw1/dev/*/state", lambda s: received.append(json.loads(s.payload.to_bytes())))
    try:
        def subscribed() -> bool:  # a probe published until one arrives
            states.append(("la2", {"device": "la2", "probe": True}))
            bridge.publish_states()
            return bool(received)

        wait_for(subscribed, timeout=20)
        marker = {"device": "la2", "marker": True}  # published after every probe: once it
        states.append(("la2", marker))  # arrived, no probe is still on its way
        bridge.publish_states()
        wait_for(lambda: marker in received)
        received.clear()
        sent = [{"device": "la1", "online": True, "position": p} for p in (10, 20, 30)]
        sent.append({"device": "la2", "online": False, "position": None})
        states.extend((state["device"], state) for state in sent)
        bridge.publish_states()
        wait_for(lambda: len(received) == len(sent))
        assert received == sent and not states
    finally:
        subscriber.undeclare()
        client.close()
        bridge.close()
        loop.close()


def test_estops_and_resets_put_one_after_the_other_reach_the_buses_in_that_order(
    free_port, wait_for
) -> None:
    """Zenoh keeps the order of one session's puts of one priority, and the SDK sends a reset
    as it sends an e-stop so that an e-stop put after a reset never overtakes it: the gateway
    hands them to its buses in the order they were put. A put on ``**`` is an e-stop only; a
    put on a wildcard reset key, or under the e-stop's key, is neither."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = parse_config(config_for("/dev/null", endpoint))
    runners = {bus.name: build_bus(bus) for bus in config.buses}  # not started: no port opened
    bridge = ZenohBridge(config, GatewayApi("gw1", runners), runners, deque(), deque())
    handed: list[str] = []
    bridge.api.stop_every_bus = lambda: handed.append("estop") or []
    bridge.api.reset_every_bus = lambda sender: handed.append("reset") or ([], [])
    loop = asyncio.new_event_loop()
    bridge.open(loop)
    client = zenoh.open(session_config(mode="peer", connect=[endpoint]))
    urgent = {"priority": zenoh.Priority.REAL_TIME, "express": True,  # as the SDK puts them
              "congestion_control": zenoh.CongestionControl.BLOCK}
    try:
        wait_for(lambda: client.put("busgate/gw1/estop", b"{}", **urgent) or handed, timeout=20)
        client.put("busgate/gw1/estop/reset", b"{}", **urgent)
        wait_for(lambda: handed[-1:] == ["reset"])
        handed.clear()
        for key in ["busgate/gw1/estop/reset", "busgate/gw1/estop"] * 100:
            client.put(key, b'{"client": "panel"}', **urgent)
        for key in ["busgate/*/estop/reset", "busgate/gw1/estop/other", "**"]:
            client.put(key, b"{}", **urgent)
        wait_for(lambda: len(handed) == 201)
        assert handed == ["reset", "estop"] * 100 + ["estop"]
    finally:
        client.close()
        bridge.close()
        loop.close()


def test_a_command_sent_on_a_wildcard_reaches_only_info_and_is_told_so(free_port) -> None:
    """No command key takes a wildcard; info does, so a command sent to ``busgate/gw1/**``
    (a tired operator's ``busgate send``) is answered by info alone: with a refusal saying
    why, not with an info that reads as the command's success. A get with no payload still
    has its info."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = parse_config(config_for("/dev/null", endpoint))
    runners = {bus.name: build_bus(bus) for bus in config.buses}  # not started: no port opened
    bridge = ZenohBridge(config, GatewayApi("gw1", runners), runners, deque(), deque())
    loop = asyncio.new_event_loop()
    bridge.open(loop)
    threading.Thread(target=loop.run_forever, daemon=True).start()  # the replies' thread
    client = zenoh.open(session_config(mode="peer", connect=[endpoint]))
    try:
        deadline = time.monotonic() + 20
        while not (info := get(client, "busgate/gw1/**", None, 1.0)):
            assert time.monotonic() < deadline, "the gateway's info never came"
        assert [reply.get("gateway") for reply in info] == ["gw1"]
        [refused] = get(client, "busgate/gw1/**", '{"op":"estop"}')
        assert refused["ok"] is False and refused["error"]["code"] == "bad_command"
        assert "takes no payload" in refused["error"]["message"]
        # A wildcard where a command names one device, or one bus: one refusal, not silence
        # (the client waited out its timeout); a fleet's command for a device not here: none.
        for key, noun in [("busgate/gw1/dev/*/cmd", "device"), ("busgate/*/dev/la2/*", "device"),
                          ("busgate/gw1/bus/*/cmd", "bus")]:
            [refused] = get(client, key, '{"op":"status"}')
            assert refused["error"]["code"] == "bad_command"
            assert refused["error"]["message"].startswith(
                f"{key} has a wildcard where a command names one {noun} and its cmd key")
        assert get(client, "busgate/*/dev/la9/cmd", '{"op":"status"}', 1.0) == []
        # The trajectory key takes no wildcard at all, the gateway's name included.
        for key in ("busgate/*/trajectory", "busgate/gw1/traj$*", "busgate/gw1/trajectory/**"):
            [refused] = get(client, key, '{"op":"status"}')
            assert refused["error"]["code"] == "bad_command"
            assert refused["error"]["message"] == (
                f"{key} has a wildcard: a trajectory is sent to one gateway's own key (such "
                "as busgate/gw1/trajectory). Nothing was played")
    finally:
        client.close()
        loop.call_soon_threadsafe(loop.stop)
        bridge.close()


@pytest.mark.parametrize("in_file", [False, True])
def test_the_session_up_line_names_the_endpoints_listened_on_a_config_files_too(
    in_file, free_port, tmp_path, caplog
) -> None:
    """With its endpoints in ``[zenoh] config_file`` the line named the file, not where
    the gateway listens; with them in ``listen`` it printed a Python list."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = config_for("/dev/null", endpoint)
    if in_file:
        zenoh_file = tmp_path / "zenoh.json5"
        zenoh_file.write_text(json.dumps({"listen": {"endpoints": [endpoint]}}))
        config["zenoh"] = {"mode": "peer", "config_file": str(zenoh_file)}
    parsed = parse_config(config)
    runners = {bus.name: build_bus(bus) for bus in parsed.buses}  # not started
    bridge = ZenohBridge(parsed, GatewayApi("gw1", runners), runners, deque(), deque())
    loop = asyncio.new_event_loop()
    caplog.set_level(logging.INFO, logger="busgate.gateway.api.bridge")
    try:
        bridge.open(loop)
    finally:
        bridge.close()
        loop.close()
    assert f"zenoh session up: gateway busgate/gw1, listening on {endpoint}\n" in caplog.text


def test_follow_targets_are_taken_by_their_own_thread_which_a_bug_does_not_end(
    free_port, wait_for, caplog
) -> None:
    """Follow targets wait in zenoh's ring for the ``follow-targets`` thread (bridge rule 6):
    each is handed to the API in order, a target whose handling raises is logged and the
    next is taken all the same, and closing the bridge ends the thread."""
    taken: list[bytes] = []

    def follow(device: str, payload: bytes) -> None:
        taken.append(payload)
        if payload == b"bug":
            raise RuntimeError("a bug")

    with idle_bridge(free_port) as (bridge, client):
        bridge.api.follow = follow
        wait_for(lambda: client.put("busgate/gw1/dev/la1/follow", b"probe") or taken, timeout=20)
        for payload in (b"1", b"bug", b"2"):  # after every probe: one session's puts in order
            client.put("busgate/gw1/dev/la1/follow", payload)
        wait_for(lambda: taken[-1:] == [b"2"])
        assert taken[-3:] == [b"1", b"bug", b"2"]
        assert "follow-targets: what came on busgate/gw1/dev/la1/follow" in caplog.text
    assert all(intake.join() for intake in bridge._intakes)


def test_follow_targets_still_waiting_when_an_e_stop_comes_are_dropped(
    free_port, wait_for
) -> None:
    """Targets put before an e-stop, still waiting for the ``follow-targets`` thread when it
    comes, never reach the API: a reset right after the e-stop would let them start a
    stream. Targets put after it do."""
    taken: list[bytes] = []
    busy, stopped = threading.Event(), threading.Event()

    def follow(device: str, payload: bytes) -> None:
        taken.append(payload)
        if payload == b"slow":  # the thread held up while the others wait in the ring
            busy.set()
            stopped.wait(10)

    with idle_bridge(free_port) as (bridge, client):
        bridge.api.follow = follow
        bridge.api.stop_every_bus = lambda: []
        bridge.put_reports.estop = lambda key, sender: stopped.set()  # told after the drop
        try:
            wait_for(lambda: client.put("busgate/gw1/dev/la1/follow", b"probe") or taken, 20)
            client.put("busgate/gw1/dev/la1/follow", b"slow")
            busy.wait(10)
            for payload in (b"1", b"2", b"3"):
                client.put("busgate/gw1/dev/la1/follow", payload)
            time.sleep(0.2)  # they are in the ring by now
            client.put("busgate/gw1/estop", b"{}")
            client.put("busgate/gw1/dev/la1/follow", b"after")
            wait_for(lambda: taken[-1:] == [b"after"])
            assert not {b"1", b"2", b"3"} & set(taken)
        finally:
            stopped.set()


def test_puts_held_up_by_their_handler_never_hold_up_an_e_stop(free_port, wait_for) -> None:
    """Zenoh's receiving thread waited for a key's handler once 256 of its puts were waiting
    (zenoh-python's channel to a callback's thread): an e-stop put behind a flood of commands
    waited for the whole flood (0.2-2 s under two flooding clients). Now puts wait in their
    intake's ring: with the handler of ``cmd`` puts held up, 1,000 more of them and then an
    e-stop, the e-stop reaches the buses while the handler is still held."""
    held, release, stopped = threading.Event(), threading.Event(), threading.Event()
    handled: list[bytes] = []

    def command(device: str, payload: bytes) -> Future:
        handled.append(payload)
        held.set()
        release.wait(10)
        return settled({"ok": True})

    with idle_bridge(free_port) as (bridge, client):
        bridge.api.command = command
        bridge.api.stop_every_bus = lambda: stopped.set() or []
        try:
            wait_for(lambda: client.put("busgate/gw1/dev/la1/cmd", b"probe") or held.is_set(), 20)
            for n in range(1000):
                client.put("busgate/gw1/dev/la1/cmd", b"%d" % n)
            client.put("busgate/gw1/estop", b"{}", **URGENT)
            assert stopped.wait(10), "the e-stop waited behind the puts"
            assert len(handled) == 1  # the handler still held up by the first
        finally:
            release.set()


def test_a_message_larger_than_any_key_takes_is_dropped_before_the_gateway_holds_it(
    free_port, wait_for
) -> None:
    """Zenoh took messages up to 1 GiB, held whole in a key's ring before its thread could
    refuse them: a gateway's session takes none over ``MAX_RECEIVED`` (2 MiB), and a get of
    more is never answered; one under it, past its key's 64 KiB, is refused by its size."""
    key = "busgate/gw1/dev/la1/cmd"
    with idle_bridge(free_port) as (_, client):
        wait_for(lambda: get(client, "busgate/gw1/info", b"", timeout=1), timeout=20)
        assert get(client, key, bytes(MAX_RECEIVED + 1024), timeout=2) == []
        [half] = get(client, key, bytes(MAX_RECEIVED // 2))
        assert half["error"] == {"code": "too_large", "message": (
            f"payload of {MAX_RECEIVED // 2} bytes; at most {MAX_PAYLOAD}")}


def test_commands_still_waiting_when_an_e_stop_comes_are_answered_estopped(
    free_port, wait_for
) -> None:
    """Commands got before an e-stop and still waiting for their thread when it comes are
    never carried out (a reset right after it would let them move a device): each is
    answered ``estopped``. The command being handled when it came, and those got after it,
    are carried out; what else was sent before it is forgotten (``at_estop``)."""
    held, release = threading.Event(), threading.Event()
    carried_out: list[bytes] = []

    def command(device: str, payload: bytes) -> Future:
        carried_out.append(payload)
        if payload == b"slow":
            held.set()
            release.wait(10)
        return settled({"ok": True, "payload": payload.decode()})

    key = "busgate/gw1/dev/la1/cmd"
    with idle_bridge(free_port) as (bridge, client):
        bridge.api.command = command
        bridge.api.stop_every_bus = lambda: []
        forgotten: list[bool] = []
        bridge.at_estop.append(lambda: forgotten.append(True))
        try:
            wait_for(lambda: get(client, key, b"probe", 1.0), timeout=20)
            slow = client.get(key, payload=b"slow", timeout=20)
            assert held.wait(10)
            waiting = [client.get(key, payload=b"%d" % n, timeout=20) for n in range(3)]
            time.sleep(0.2)  # in the ring by now
            client.put("busgate/gw1/estop", b"{}", **URGENT)
            for replies in waiting:
                [reply] = [json.loads(r.ok.payload.to_bytes()) for r in replies]
                assert reply["error"]["code"] == "estopped"
            assert forgotten == [True]
        finally:
            release.set()
        assert [json.loads(r.ok.payload.to_bytes())["ok"] for r in slow] == [True]
        assert get(client, key, b"after") == [{"ok": True, "payload": "after"}]
        assert carried_out[-2:] == [b"slow", b"after"]
