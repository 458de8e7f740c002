"""The systemd notify protocol against a fake service manager: a real AF_UNIX datagram socket
(a path in tmp_path, or an abstract name) standing where systemd's would, and the exact
datagrams it receives; and the daemon's watchdog predicate (every bus thread alive and turning
its loop) on a real bus runner."""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import threading
import time
from types import SimpleNamespace

import pytest

from busgate.codecs import inspire_la as la
from busgate.errors import BusUnavailableError
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.scheduler.devices import BusDevices
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.service.daemon import every_bus_on_schedule
from busgate.gateway.service.sdnotify import Notifier, Watchdog
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.config import SerialBus


class FakeManager:
    """The receiving end of NOTIFY_SOCKET."""

    def __init__(self, address: str | bytes) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(address)
        self.sock.setblocking(False)

    def received(self) -> list[bytes]:
        datagrams = []
        while True:
            try:
                datagrams.append(self.sock.recv(4096))
            except BlockingIOError:
                return datagrams


@pytest.fixture
def manager(tmp_path):
    fake = FakeManager(str(tmp_path / "notify"))
    yield fake
    fake.sock.close()


def environ_for(manager: FakeManager, **extra: str) -> dict[str, str]:
    name = manager.sock.getsockname()
    value = "@" + name[1:].decode() if isinstance(name, bytes) else name
    return {"NOTIFY_SOCKET": value, **extra}


def test_each_notification_is_one_datagram_of_exact_fields(manager) -> None:
    notifier = Notifier(environ_for(manager))
    assert notifier.enabled
    assert notifier.ready("serving 2 buses")
    assert notifier.status("bus uart0 up,\n bus can0 down")
    assert notifier.watchdog()
    assert notifier.stopping()
    assert manager.received() == [
        b"READY=1\nSTATUS=serving 2 buses",
        b"STATUS=bus uart0 up, bus can0 down",
        b"WATCHDOG=1",
        b"STOPPING=1",
    ]


def test_an_abstract_socket_name_is_reached() -> None:
    fake = FakeManager(f"\0busgate-test-{os.getpid()}".encode())
    try:
        notifier = Notifier(environ_for(fake))
        assert notifier.address == f"\0busgate-test-{os.getpid()}".encode()
        assert notifier.ready()
        assert fake.received() == [b"READY=1"]
    finally:
        fake.sock.close()


@pytest.mark.parametrize("environ", [{}, {"NOTIFY_SOCKET": ""}, {"NOTIFY_SOCKET": "relative"}])
def test_without_a_socket_every_call_is_a_no_op(environ) -> None:
    notifier = Notifier(environ)
    assert not notifier.enabled
    assert not notifier.ready("x")
    assert not notifier.status("x")
    assert not notifier.watchdog()
    assert not notifier.stopping()


def test_a_socket_that_is_gone_is_logged_not_raised(tmp_path, caplog) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone")})
    assert not notifier.ready()
    assert "not sent" in caplog.text


@pytest.mark.parametrize(("environ", "interval"), [
    ({"WATCHDOG_USEC": "10000000"}, 10.0),
    ({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": str(os.getpid())}, 0.5),
    ({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "1"}, None),  # another process's watchdog
    ({"WATCHDOG_USEC": "0"}, None),
    ({"WATCHDOG_USEC": "soon"}, None),
    ({}, None),
])
def test_the_watchdog_interval_comes_from_the_environment(environ, interval) -> None:
    assert Notifier(environ).watchdog_interval_s == interval


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_the_watchdog_pings_at_half_the_interval_while_healthy(manager) -> None:
    clock = FakeClock()
    health = {"ok": True}
    watchdog = Watchdog(Notifier(environ_for(manager, WATCHDOG_USEC="4000000")),
                        lambda: health["ok"], clock=clock)
    assert watchdog.check()           # the first check pings
    clock.t += 1.9
    assert not watchdog.check()       # not yet half the 4 s interval
    clock.t += 0.1
    assert watchdog.check()
    health["ok"] = False
    clock.t += 2.0
    assert not watchdog.check()       # due, but unhealthy: no ping
    clock.t += 1.0
    assert not watchdog.check()
    health["ok"] = True
    assert watchdog.check()           # healthy again: pings at once
    assert manager.received() == [b"WATCHDOG=1"] * 3


def test_no_watchdog_no_pings_and_no_health_checks(manager) -> None:
    def never_asked() -> bool:
        raise AssertionError("the predicate is not consulted without a watchdog")

    watchdog = Watchdog(Notifier(environ_for(manager)), never_asked)
    assert not watchdog.check()
    asyncio.run(watchdog.run(asyncio.Event()))  # returns at once
    assert manager.received() == []


def test_run_pings_until_stopped_and_only_while_healthy(manager) -> None:
    checks = []

    def healthy() -> bool:
        checks.append(len(checks))
        return len(checks) <= 2

    async def scenario() -> None:
        stop = asyncio.Event()
        watchdog = Watchdog(Notifier(environ_for(manager, WATCHDOG_USEC="40000")), healthy)
        task = asyncio.create_task(watchdog.run(stop))
        while len(checks) < 5:
            await asyncio.sleep(0.005)
        stop.set()
        await task

    asyncio.run(scenario())
    assert manager.received() == [b"WATCHDOG=1"] * 2


class StuckOwner:
    """A bus owner whose ``open`` hangs until released: a bus thread that stopped turning."""

    port = "stuck"
    is_open = False

    def __init__(self) -> None:
        self.counters = BusCounters(now())
        self.entered = threading.Event()
        self.release = threading.Event()

    def open(self) -> None:
        self.entered.set()
        self.release.wait()
        raise BusUnavailableError("released")

    def close(self) -> None:
        pass


def test_a_stuck_bus_thread_stops_the_pings(manager) -> None:
    owner = StuckOwner()
    runner = BusRunner("stuck", owner, link_timing("inspire_la", 921_600, margin_s=0.002),
                       BusDevices([]), poll_hz={}).start()
    watchdog = Watchdog(Notifier(environ_for(manager, WATCHDOG_USEC="1000000")),
                        lambda: runner.keeping_schedule(stall_s=0.05))
    try:
        assert owner.entered.wait(10)
        time.sleep(0.1)  # more than stall_s without a turn of the loop
        assert runner.alive and not runner.keeping_schedule(stall_s=0.05)
        assert not watchdog.check()
    finally:
        owner.release.set()
        runner.stop()
    assert not runner.alive and not runner.keeping_schedule()
    assert manager.received() == []


def test_a_bus_thread_that_does_not_stop_is_told_of(caplog) -> None:
    """A stop whose bus thread hung read as a clean one: ``gateway … stopped``, exit 0, and
    nothing said of the safe state that may not have gone out (an audit)."""
    owner = StuckOwner()
    runner = BusRunner("stuck", owner, link_timing("inspire_la", 921_600, margin_s=0.002),
                       BusDevices([]), poll_hz={}).start()
    try:
        assert owner.entered.wait(10)
        with caplog.at_level(logging.WARNING, logger="busgate.gateway.scheduler.runner"):
            runner.stop(timeout=0.05)
        assert [r.getMessage() for r in caplog.records] == [
            "bus stuck: its thread did not stop within 0.05 s: its devices' safe state may not "
            "have been sent"]
    finally:
        owner.release.set()
        runner.stop()


def test_a_working_bus_keeps_its_schedule(tmp_path) -> None:
    bus = SerialBus(name="uart0", transport="serial", port=str(tmp_path / "usb-la"),
                    baudrate=921_600,
                    devices=[{"name": "la1", "kind": "inspire_la", "id": 1, "poll_hz": 50}])
    link = PtyLink(str(tmp_path / "usb-la"))
    with SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600, link=link):
        runner = build_bus(bus).start()
        try:
            deadline = time.monotonic() + 10
            while not runner.states.get("la1", {}).get("online"):
                assert time.monotonic() < deadline, "the device did not come online"
                time.sleep(0.01)
            assert runner.keeping_schedule()
        finally:
            runner.stop()
    assert not runner.keeping_schedule()


def test_a_held_back_ping_names_the_buses_off_their_schedule(caplog) -> None:
    """The journal showed only systemd's watchdog timeout, naming no bus (an audit)."""
    runners = {"uart0": SimpleNamespace(keeping_schedule=lambda: True),
               "can0": SimpleNamespace(keeping_schedule=lambda: False)}
    with caplog.at_level(logging.WARNING, logger="busgate.gateway.service.daemon"):
        assert not every_bus_on_schedule(runners)  # type: ignore[arg-type]
        assert every_bus_on_schedule({"uart0": runners["uart0"]})  # type: ignore[arg-type]
    assert [r.getMessage() for r in caplog.records] == [
        "watchdog: not pinged, bus can0 not keeping its schedule (systemd restarts the service "
        "if it goes on)"]
