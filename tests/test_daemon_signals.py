"""``busgate run`` stopped by a signal, as a real process: SIGHUP (a terminal or an ssh session
that closes, a habitual ``kill -HUP``) stops it in order as SIGTERM does, each device put in
its safe state, and says which signal it was; it ended the daemon at once before (exit status
129, no log line, a ZLAC706 left enabled). A stop ends in time with a ``connect`` endpoint
that never answers: zenoh's close waited for it 10 s, systemd's whole ``TimeoutStopSec``."""

from __future__ import annotations

import asyncio
import signal
import socket
import threading
import time

from busgate.codecs import inspire_la as la
from busgate.gateway.api.bridge import ZenohBridge
from busgate.gateway.service.daemon import serve
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.config import parse_config
from tests.conftest import silent_listener, status_once_signalled, unused_loopback_port
from tests.gateway_process import TIMEOUT_S, GatewayProcess, serial_bus, write_config
from tests.wire_frames import received


def test_sighup_stops_the_daemon_in_order_as_sigterm_does(tmp_path) -> None:
    simulator = SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600).start()
    endpoint = f"tcp/127.0.0.1:{unused_loopback_port()}"
    config = write_config(
        tmp_path / "gw.toml", endpoint, serial_bus("uart0", simulator.port, "la1"), workers=1
    )
    gateway = GatewayProcess(config)
    try:
        gateway.wait_for("serving 1 bus, 1 up")
        mark = len(simulator.recorder.received())
        gateway.process.send_signal(signal.SIGHUP)
        assert gateway.process.wait(timeout=TIMEOUT_S) == 0
        gateway.wait_for("SIGHUP: stopping")
        gateway.wait_for("gateway gw1 stopped")
        stops = [
            frame
            for _, frame in received(simulator, mark, la)
            if isinstance(frame, la.ControlCommand) and frame.code is la.ControlCode.ESTOP
        ]
        assert stops, "the device was not put in its safe state"
    finally:
        gateway.stop()
        simulator.stop()


def test_a_connect_endpoint_that_never_answers_holds_the_stop_one_second_at_most(
        tmp_path) -> None:
    with silent_listener() as (mute, endpoint):  # takes the connection, never speaks zenoh
        config = write_config(tmp_path / "gw.toml", f"tcp/127.0.0.1:{unused_loopback_port()}",
                              serial_bus("uart0", str(tmp_path / "unplugged"), "la1"), workers=1)
        config.write_text(config.read_text().replace(
            "[zenoh]\n", f'[zenoh]\nconnect = ["{endpoint}"]\n'))
        gateway = GatewayProcess(config)
        try:
            gateway.wait_for("serving 1 bus")
            assert status_once_signalled(gateway.process, mute) == 0  # zenoh's connect under way
            gateway.wait_for("did not close within 1 s")
            gateway.wait_for("gateway gw1 stopped")
        finally:
            gateway.stop()


def test_a_stop_while_zenoh_waits_for_a_router_that_never_answers_is_heard_at_once(
        tmp_path) -> None:
    """zenoh's opening waits 10 s for a router that took the connection and never answers:
    the stop signal was heard only after it, systemd's whole ``TimeoutStopSec``."""
    with silent_listener() as (mute, endpoint):
        config = tmp_path / "gw.toml"
        config.write_text(f'[gateway]\nname = "gw1"\n[zenoh]\nmode = "client"\n'
                          f'connect = ["{endpoint}"]\n'
                          + serial_bus("uart0", str(tmp_path / "unplugged"), "la1"))
        gateway = GatewayProcess(config)
        try:
            assert status_once_signalled(gateway.process, mute) == 0  # zenoh's opening under way
            gateway.wait_for("gateway gw1 stopped before its session opened")
        finally:
            gateway.stop()


def test_a_stop_while_the_session_opens_leaves_nothing_of_it_open(monkeypatch, tmp_path) -> None:
    """``serve`` in a process that goes on (a test, a benchmark): an opening the stop came
    in the middle of ended, after ``serve`` returned, with its session open for nobody, its
    listen port held and its threads running; in ``busgate run`` the process aborted
    ("FATAL: exception not rethrown") when zenoh handed the thread back as it ended."""
    opened_late = threading.Event()
    opening = ZenohBridge.open

    def slow_open(bridge: ZenohBridge, loop: asyncio.AbstractEventLoop) -> None:
        time.sleep(0.5)  # a router that answers slowly
        opening(bridge, loop)
        opened_late.set()

    monkeypatch.setattr(ZenohBridge, "open", slow_open)
    port = unused_loopback_port()
    config = parse_config({
        "gateway": {"name": "ghost", "workers": 1},
        "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]},
        "buses": [{"name": "uart0", "transport": "serial", "port": str(tmp_path / "unplugged"),
                   "baudrate": 921600,
                   "devices": [{"name": "la1", "kind": "inspire_la", "id": 1}]}],
    })

    async def stopped_while_opening() -> None:
        stop = asyncio.Event()
        serving = asyncio.create_task(serve(config, stop=stop))
        await asyncio.sleep(0.2)
        stop.set()
        await serving

    asyncio.run(stopped_while_opening())
    assert opened_late.is_set()  # waited for: the thread came back before serve returned
    assert "zenoh-open" not in [thread.name for thread in threading.enumerate()]
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", port))  # its listener closed with the session
