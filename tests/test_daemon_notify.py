"""``busgate run`` under a systemd-like supervisor: READY once every bus has had its first
attempt to open (one down does not hold it back: STATUS says which and why, and follows it),
watchdog pings while the buses keep their schedule, STOPPING on SIGTERM — read off a real
NOTIFY_SOCKET."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from busgate.codecs import inspire_la as la
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from tests.gateway_process import TIMEOUT_S


def _run_under_systemd(config: Path, notify_path: Path, watchdog_usec: str,
                       timeout_s: float) -> tuple[socket.socket, subprocess.Popen]:
    """``busgate run --config config`` with a stand-in for systemd's notify socket at
    ``notify_path`` (its receives time out after ``timeout_s``), and the process."""
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.settimeout(timeout_s)
    env = {**os.environ, "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": watchdog_usec}
    process = subprocess.Popen([sys.executable, "-m", "busgate.gateway.cli", "run", "--config",
                                str(config)], env=env, stderr=subprocess.DEVNULL)
    return notify, process


def test_ready_watchdog_and_stopping(free_port, tmp_path) -> None:
    simulator = SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600).start()
    config = tmp_path / "gw.toml"
    config.write_text(
        f'[gateway]\nname = "gw1"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{free_port()}"]\n'
        f'[[buses]]\nname = "uart0"\ntransport = "serial"\nport = "{simulator.port}"\n'
        'baudrate = 921600\n[[buses.devices]]\nname = "la1"\nkind = "inspire_la"\nid = 1\n'
    )
    notify, process = _run_under_systemd(config, tmp_path / "notify", "400000", 15)
    try:
        messages = []
        while not any("READY=1" in m for m in messages):
            messages.append(notify.recv(4096).decode())
        ready = next(m for m in messages if "READY=1" in m)
        assert "STATUS=gateway gw1: 1 bus(es) open" in ready
        while "WATCHDOG=1" not in messages:
            messages.append(notify.recv(4096).decode())
        process.send_signal(signal.SIGTERM)
        while not any("STOPPING=1" in m for m in messages):
            messages.append(notify.recv(4096).decode())
        assert process.wait(timeout=10) == 0
    finally:
        if process.poll() is None:
            process.kill()
        notify.close()
        simulator.stop()


def _notifications(notify: socket.socket, messages: list[str], field: str) -> str:
    """The first notification holding ``field``, received into ``messages`` as they come
    (watchdog pings go on meanwhile: a deadline, a hang guard, ends the wait)."""
    deadline = time.monotonic() + TIMEOUT_S
    while not (found := [m for m in messages if field in m]):
        assert time.monotonic() < deadline, f"no {field!r} in {messages}"
        messages.append(notify.recv(4096).decode())
    return found[0]


@pytest.mark.parametrize("workers", [1, 2])
def test_a_bus_whose_adapter_is_unplugged_does_not_hold_ready_back(
    free_port, tmp_path, workers
) -> None:
    """Held back until every bus was open, READY never came with an adapter unplugged, and
    systemd killed the whole gateway at TimeoutStartSec, again and again. Now READY says which
    bus is down and why, and STATUS says so once it is up (with workers: from their beats)."""
    simulators = [SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600).start()
                  for _ in range(2)]
    unplugged = tmp_path / "ttyUSB9"
    buses = [("uart0", simulators[0].port), ("uart1", str(unplugged))]
    config = tmp_path / "gw.toml"
    config.write_text(
        f'[gateway]\nname = "gw1"\nworkers = {workers}\n[zenoh]\n'
        f'listen = ["tcp/127.0.0.1:{free_port()}"]\n'
        + "".join(
            f'[[buses]]\nname = "{bus}"\ntransport = "serial"\nport = "{port}"\n'
            f'baudrate = 921600\n[[buses.devices]]\nname = "la{n}"\nkind = "inspire_la"\n'
            "id = 1\n"
            for n, (bus, port) in enumerate(buses)
        )
    )
    notify, process = _run_under_systemd(config, tmp_path / "notify", "2000000", 30)
    try:
        messages: list[str] = []
        ready = _notifications(notify, messages, "READY=1")
        assert "STATUS=gateway gw1: 1 of 2 bus(es) open, 2 device(s), zenoh up; " in ready
        assert f"bus uart1 down: {unplugged}" in ready
        Path(unplugged).symlink_to(simulators[1].port)  # plugged in
        _notifications(notify, messages, "STATUS=gateway gw1: 2 bus(es) open, 2 device(s)")
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
    finally:
        if process.poll() is None:
            process.kill()
        notify.close()
        for simulator in simulators:
            simulator.stop()
